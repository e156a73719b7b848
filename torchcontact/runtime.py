"""Run an exported estimator with onnxruntime and numpy only: :mod:`torchcontact.onnx.runtime`.

This module re-exports the public names where users import them (``from torchcontact.runtime
import EstimatorRuntime``); the implementation lives in :mod:`torchcontact.onnx.runtime`. It
imports no torch.
"""

from torchcontact.onnx.runtime import (
    FORMAT,
    RESIDUAL_FORMATS,
    EstimatorRuntime,
    Inputs,
    ModelMismatchError,
    ResidualGraph,
    identity_of,
    robot_identity,
    session_options,
)

__all__ = [
    "FORMAT",
    "RESIDUAL_FORMATS",
    "EstimatorRuntime",
    "Inputs",
    "ModelMismatchError",
    "ResidualGraph",
    "identity_of",
    "robot_identity",
    "session_options",
]
