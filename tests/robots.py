"""Shared fixtures: real robot descriptions from installed PyPI packages, and pinocchio helpers.

Robots come from ``example-robot-data`` (panda, ur5, xarm7) and ``icub-models`` (iCubGenova04),
located through the installed packages; nothing is copied into this repository.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import numpy as np
import pytest
import torch

import torchcontact as tc

# One tolerance table per dtype (see ../shared/STYLE.md): float64 against pinocchio/iDynTree to
# 1e-9 absolute; float32 to 1e-3 relative to the magnitude of the reference.
TOL = {torch.float64: dict(atol=1e-9, rtol=0.0), torch.float32: dict(rel=1e-3)}


def erd_path(relative: str) -> Path:
    """Path of a file shipped by example-robot-data (installed under cmeel.prefix)."""
    for f in importlib.metadata.files("example-robot-data"):
        if str(f).endswith(relative):
            return Path(f.locate()).resolve()
    raise FileNotFoundError(relative)


def icub_path() -> Path:
    import icub_models

    return Path(icub_models.get_model_file("iCubGenova04"))


ROBOTS = {
    "panda": lambda: erd_path("panda_description/urdf/panda.urdf"),
    "ur5": lambda: erd_path("ur_description/urdf/ur5_robot.urdf"),
    "xarm7": lambda: erd_path("xarm_description/urdf/xarm7.urdf"),
    "icub": icub_path,
}


@pytest.fixture(scope="session")
def robot_paths():
    return {k: v() for k, v in ROBOTS.items()}


_MODELS: dict = {}


def load_model(name: str, dtype=torch.float64) -> tc.RobotModel:
    key = (name, dtype)
    if key not in _MODELS:
        _MODELS[key] = tc.RobotModel.from_urdf(ROBOTS[name](), dtype=dtype)
    return _MODELS[key]


class PinRobot:
    """pinocchio model of the same URDF, with maps between its joint vectors and torchcontact's.

    pinocchio ignores <mimic> and gives continuous joints two coordinates (cos, sin), so vectors are
    converted: torchcontact joint coordinates -> one value per pinocchio joint via the model's
    ``q_to_body`` map, and pinocchio torques folded back onto the leaders.
    """

    def __init__(self, path, model: tc.RobotModel, free_flyer: bool = False):
        import pinocchio as pin

        self.pin = pin
        if free_flyer:
            self.m = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
        else:
            self.m = pin.buildModelFromUrdf(str(path))
        self.d = self.m.createData()
        self.model = model
        self.joints = []  # (pin joint id, torchcontact body index)
        for jid in range(1, self.m.njoints):
            name = self.m.names[jid]
            if name in model.body_joint:
                self.joints.append((jid, model.body_joint.index(name)))
        self.Q = model.q_to_body.double().numpy()
        self.off = model.q_offset.double().numpy()

    def q(self, q, base=None):
        out = (
            np.zeros(self.m.nq) if base is None else np.concatenate([base, np.zeros(self.m.nq - 7)])
        )
        qb = q @ self.Q + self.off
        for jid, b in self.joints:
            j = self.m.joints[jid]
            if j.nq == 2:  # continuous joint: (cos, sin)
                out[j.idx_q : j.idx_q + 2] = np.cos(qb[b]), np.sin(qb[b])
            else:
                out[j.idx_q] = qb[b]
        return out

    def v(self, v, base=None):
        out = (
            np.zeros(self.m.nv) if base is None else np.concatenate([base, np.zeros(self.m.nv - 6)])
        )
        vb = v @ self.Q
        for jid, b in self.joints:
            out[self.m.joints[jid].idx_v] = vb[b]
        return out

    def fold_tau(self, tau_pin):
        per_body = np.zeros(self.model.nb)
        for jid, b in self.joints:
            per_body[b] = tau_pin[self.m.joints[jid].idx_v]
        return self.Q @ per_body

    def rnea(self, q, qd, qdd, fext=None):
        pin = self.pin
        args = [self.m, self.d, self.q(q), self.v(qd), self.v(qdd)]
        if fext is not None:
            args.append(fext)
        return self.fold_tau(pin.rnea(*args))


def random_state(model, n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return tuple(
        (torch.rand(n, model.nv, generator=g, dtype=torch.float64) * 2 - 1).to(dtype) * s
        for s in (1.5, 2.0, 3.0)
    )
