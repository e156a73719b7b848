"""Residual learning pipeline for torchcontact (GitHub issue 5): ``python -m training``.

Learns the contact-free residual ``ft_measured - ft_predicted`` of an F/T sensor, compares it with
classical corrections, and writes checkpoints that :mod:`torchcontact.residual` loads without
this package.
"""

from .baselines import InertialLeastSquares, inertial_params, inertial_regressor
from .data import ResidualDataset, Split, load_parquet, split_blocks
from .fit import TrainConfig, fit_residual, predict_residual
from .pipeline import DataConfig, load_checkpoint, run_experiment, save_checkpoint

__all__ = [
    "DataConfig",
    "InertialLeastSquares",
    "ResidualDataset",
    "Split",
    "TrainConfig",
    "fit_residual",
    "inertial_params",
    "inertial_regressor",
    "load_checkpoint",
    "load_parquet",
    "predict_residual",
    "run_experiment",
    "save_checkpoint",
    "split_blocks",
]
