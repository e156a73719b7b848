"""Fixtures of the export tests; the scenes themselves are in ``tests/export_scenes.py``."""

from __future__ import annotations

import pytest
import torch
from export_scenes import LAYOUTS, robot_model


@pytest.fixture(scope="session")
def exported(tmp_path_factory):
    """Exported float32 graphs of both layouts, built once per session: name -> path."""
    from torchcontact.export import export_estimator

    d = tmp_path_factory.mktemp("onnx")
    out = {}
    for name in LAYOUTS:
        model = robot_model(name)
        sensors, links, kinds, _ = LAYOUTS[name]
        path = d / f"{name}.onnx"
        export_estimator(model, sensors, links, kinds, path, dtype=torch.float32)
        out[name] = path
    return out
