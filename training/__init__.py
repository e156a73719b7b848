"""Fitting corrections of F/T readings for torchcontact: ``python -m training``.

Fits a correction stack (constant offset, offset plus re-identified inertial parameters, a
learned layer on what the physics leaves) on the contact-free frames of logs in the documented
format, chooses its layers on validation blocks, reports cross-validated errors, and writes one
checkpoint that :class:`torchcontact.residual.ResidualCorrection` loads without this package.
"""

from .baselines import InertialFit, RegressorBlocks, fit_inertial, fit_offset, predict_free
from .data import ResidualDataset, Split, fold_splits, load_parquet, read_log_columns, split_blocks
from .fit import TrainConfig, fit_residual, predict_residual
from .pipeline import Config, DataConfig, FeatureConfig, StackConfig, load_config, train

__all__ = [
    "Config",
    "DataConfig",
    "FeatureConfig",
    "InertialFit",
    "RegressorBlocks",
    "ResidualDataset",
    "Split",
    "StackConfig",
    "TrainConfig",
    "fit_inertial",
    "fit_offset",
    "fit_residual",
    "fold_splits",
    "load_config",
    "load_parquet",
    "predict_free",
    "predict_residual",
    "read_log_columns",
    "split_blocks",
    "train",
]
