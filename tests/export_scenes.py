"""Scenes for the export tests: simulated F/T readings from known contacts (the round trip).

Readings come from ``ContactEstimator.predict_ft`` (float64) for random joint states and contact
forces on the bundled ``tcarm`` and on iCubGenova04 (``icub-models``), so the true contacts are
known. Slot activity patterns make some frames identifiable (one pure force per region) and some
rank-deficient (two pure forces in one region: the force along the line joining them is
unobservable, rank 5 of 6 unknowns).
"""

from __future__ import annotations

import icub_models
import torch

import torchcontact as tc

# (robot, sensors, slot links, slot kinds, activity patterns cycled over frames)
LAYOUTS = {
    "tcarm": (
        None,
        ("forearm_skin", "hand_skin"),
        ("force", "force"),
        ((1, 0), (0, 1), (1, 1), (0, 0)),
    ),
    "icub": (
        None,
        ("l_hand", "l_forearm", "r_hand", "r_foot", "l_lower_leg"),
        ("force", "force", "wrench", "force", "force"),
        ((1, 0, 1, 1, 1), (0, 1, 1, 0, 1), (1, 1, 0, 1, 0), (0, 0, 0, 0, 0)),
    ),
}


def robot_model(name: str) -> tc.RobotModel:
    if name == "tcarm":
        return tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    return tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))


_MODELS: dict[str, tc.RobotModel] = {}


def scene(name: str, n: int, seed: int = 0):
    """Model, estimator (float64, eigh), links, kinds and float64 inputs of ``n`` frames."""
    if name not in _MODELS:
        _MODELS[name] = robot_model(name)
    model = _MODELS[name]
    sensors, links, kinds, patterns = LAYOUTS[name]
    est = tc.ContactEstimator(model, sensors)
    K = len(links)
    g = torch.Generator().manual_seed(seed)

    def r(*shape, scale=1.0):
        return (2 * torch.rand(*shape, generator=g, dtype=torch.float64) - 1) * scale

    q, qd, qdd = r(n, model.nv, scale=1.5), r(n, model.nv), r(n, model.nv, scale=2.0)
    pos = r(n, K, 3, scale=0.05)
    wr = r(n, K, 6, scale=20.0)
    for k, kind in enumerate(kinds):
        if kind == "force":
            wr[:, k, 3:] = 0
        else:
            wr[:, k, 3:] *= 0.05
    active = torch.tensor([patterns[i % len(patterns)] for i in range(n)], dtype=torch.float64)
    dirs = torch.zeros(n, K, 3, dtype=torch.float64)
    contacts = tc.Contacts(links, kinds, pos, dirs, wr, active > 0)
    ft = est.predict_ft(q, qd, qdd, contacts)
    ft = torch.stack([ft[s] for s in est.sensor_names], 1)  # (N, S, 6)
    inputs = dict(
        q=q, qd=qd, qdd=qdd, ft=ft, positions=pos, directions=dirs,
        wrenches=torch.zeros_like(wr), active=active, ft_residual=torch.zeros_like(ft),
    )  # fmt: skip
    return model, est, links, kinds, inputs, wr
