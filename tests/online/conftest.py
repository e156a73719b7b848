"""Fixtures of the online tests: the bundled arm and its C step library, built once per session.

The library (3 force slots on the arm's skin frames, the layout of the simulated streams in
``tests/online_scenes.py``) is exported with :func:`torchcontact.online.cstep.export_c_step`; its
build is cached under ``$TORCHCONTACT_CACHE/clib`` like the kernels, so only a first run compiles
it (about 10 s).
"""

from __future__ import annotations

import pytest
import torch
from online_scenes import KINDS, LINKS

import torchcontact as tc

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def arm():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


@pytest.fixture(scope="session")
def arm_lib(arm, tmp_path_factory):
    """``(path, metadata)`` of the arm's C step (float64, every joint torque)."""
    from torchcontact.online.cstep import export_c_step

    path = tmp_path_factory.mktemp("clib") / "tc_estimator.so"
    meta = export_c_step(arm, None, LINKS, KINDS, path)
    return path, meta


@pytest.fixture(scope="session")
def arm_onnx(arm, tmp_path_factory):
    """The arm's ONNX graphs exported with ``online`` (float64, the layout of ``arm_lib``)."""
    from torchcontact.export import export_estimator

    path = tmp_path_factory.mktemp("onnx_online") / "arm.onnx"
    export_estimator(arm, None, LINKS, KINDS, path, dtype=torch.float64, online=True)
    return path
