"""The deployment wing: ONNX graphs of the estimator and of F/T corrections, and their runtime.

* :mod:`~torchcontact.onnx.format`: the contract between writer and reader (names, metadata
  keys, layouts; torch-free);
* :mod:`~torchcontact.onnx.builder`: the one graph builder;
* :mod:`~torchcontact.onnx.batched`: the batched and constrained graphs, the chained-correction
  wiring;
* :mod:`~torchcontact.onnx.step`: the single-frame graph in named stages;
* :mod:`~torchcontact.onnx.export`: the public export functions (torch);
* :mod:`~torchcontact.onnx.runtime`: onnxruntime and numpy only (torch-free).

Nothing below this package imports it; ``torchcontact.export`` and ``torchcontact.runtime``
re-export its public names. Public names are imported lazily, so that importing the runtime
does not import torch.
"""

from __future__ import annotations

import importlib

__all__ = [
    "EstimatorRuntime",
    "Inputs",
    "ResidualGraph",
    "check_parity",
    "export_estimator",
    "export_residual",
    "export_residual_checkpoint",
    "step_graph_path",
]

_LAZY = {
    "EstimatorRuntime": "runtime",
    "Inputs": "runtime",
    "ResidualGraph": "runtime",
    "check_parity": "export",
    "export_estimator": "export",
    "export_residual": "export",
    "export_residual_checkpoint": "export",
    "step_graph_path": "export",
}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'torchcontact.onnx' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"torchcontact.onnx.{_LAZY[name]}"), name)
    globals()[name] = value
    return value
