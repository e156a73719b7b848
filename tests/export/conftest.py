"""Fixtures of the export tests: graphs exported once per session, and the tolerance table.

The scenes are in ``tests/export_scenes.py``. Exports take well under a second each; the batched
graphs' onnxruntime sessions (thousands of nodes) are created once per layout and dtype.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from export_scenes import LAYOUTS, robot_model


class Exports:
    """Lazily exported graphs and their runtimes, keyed by (layout, dtype[, variant])."""

    def __init__(self, root) -> None:
        self.root = root
        self.paths: dict = {}
        self.runtimes: dict = {}

    def path(self, name: str, dtype=np.float64, **kw):
        key = (name, np.dtype(dtype).name, tuple(sorted(kw.items())))
        if key not in self.paths:
            from torchcontact.export import export_estimator

            lay = LAYOUTS[name]
            moving, torque, cov = lay["flags"]
            path = self.root / f"{name}-{np.dtype(dtype).name}-{len(self.paths)}.onnx"
            export_estimator(
                robot_model(lay["robot"]),
                lay["sensors"],
                lay["links"],
                lay["kinds"],
                path,
                dtype=torch.float32 if dtype == np.float32 else torch.float64,
                moving_base=moving,
                torque_rows=torque,
                covariance=cov,
                joints=lay["joints"],
                **kw,
            )
            self.paths[key] = path
        return self.paths[key]

    def runtime(self, name: str, dtype=np.float64, **kw):
        key = (name, np.dtype(dtype).name, tuple(sorted(kw.items())))
        if key not in self.runtimes:
            from torchcontact.runtime import EstimatorRuntime

            self.runtimes[key] = EstimatorRuntime(self.path(name, dtype, **kw))
        return self.runtimes[key]


@pytest.fixture(scope="session")
def exports(tmp_path_factory):
    return Exports(tmp_path_factory.mktemp("onnx"))
