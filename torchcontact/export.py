"""Export the contact estimator and F/T corrections to ONNX: :mod:`torchcontact.onnx.export`.

This module re-exports the public names where users import them (``from torchcontact.export
import export_estimator``); the implementation lives in :mod:`torchcontact.onnx`.
"""

from torchcontact.onnx.export import (
    CONE_INPUTS,
    CONE_OUTPUTS,
    DEFAULT_OPSET,
    ESTIMATOR_INPUTS,
    ESTIMATOR_OUTPUTS,
    FORMAT,
    RESIDUAL_GRAPH_FORMAT,
    check_parity,
    export_estimator,
    export_residual,
    export_residual_checkpoint,
    step_graph_path,
)

__all__ = [
    "CONE_INPUTS",
    "CONE_OUTPUTS",
    "DEFAULT_OPSET",
    "ESTIMATOR_INPUTS",
    "ESTIMATOR_OUTPUTS",
    "FORMAT",
    "RESIDUAL_GRAPH_FORMAT",
    "check_parity",
    "export_estimator",
    "export_residual",
    "export_residual_checkpoint",
    "step_graph_path",
]
