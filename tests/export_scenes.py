"""Scenes for the export tests: F/T readings simulated from known contacts, then perturbed.

Readings come from ``ContactEstimator.predict_ft`` (float64) for random joint states, base
motions and contact wrenches on the bundled ``tcarm`` (also with a second sensor on its tool
flange), on the Franka ``panda`` of example-robot-data (prismatic fingers with a mimic joint, a
wrist sensor) and on iCubGenova04 (icub-models), so the true contacts are known. Noise is added
to the readings so that ``b`` leaves the range of ``A`` and the least-squares part of the solve is
exercised. Slot activity patterns make some frames identifiable and some rank-deficient (two pure
forces in one region: the force along the line joining them is unobservable).

Measured joint torques (torque rows) are the torques of the true contact state plus noise; the
reading covariances are random symmetric positive definite matrices.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from robots import ROBOTS

import torchcontact as tc

# name -> robot, sensors, slot links, kinds, activity patterns (cycled over frames), flags
# (moving_base, torque_rows, covariance), joints whose torques are output
LAYOUTS = {
    "tcarm": dict(
        robot="tcarm",
        sensors=None,
        links=("forearm_skin", "hand_skin"),
        kinds=("force", "force"),
        patterns=((1, 0), (0, 1), (1, 1), (0, 0)),
        flags=(False, False, False),
        joints=None,
    ),
    "tcarm2": dict(
        robot="tcarm2",
        sensors=None,
        links=("forearm_skin", "hand_skin", "tool", "hand_skin"),
        kinds=("force", "force_dir", "wrench", "known"),
        patterns=((1, 0, 1, 1), (0, 1, 1, 0), (1, 1, 0, 1), (1, 1, 1, 1)),
        flags=(True, False, True),
        joints=None,
    ),
    "panda": dict(
        robot="panda",
        sensors=None,
        links=("panda_leftfinger", "panda_rightfinger", "panda_hand"),
        kinds=("force", "force", "force_dir"),
        patterns=((1, 0, 0), (1, 1, 0), (1, 1, 1), (0, 0, 1)),
        flags=(True, True, True),
        joints=None,
    ),
    "icub": dict(
        robot="icub",
        sensors=("l_arm_ft",),
        links=("l_hand", "l_hand", "l_forearm", "l_forearm"),
        kinds=("force", "force", "force", "wrench"),
        patterns=((1, 0, 0, 0), (1, 1, 0, 0), (1, 0, 1, 1), (0, 1, 1, 0)),
        flags=(False, False, False),
        joints="sensed",
    ),
}


@functools.cache
def robot_model(name: str) -> tc.RobotModel:
    """The robots of :data:`LAYOUTS` (float64)."""
    if name == "tcarm":
        return tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    if name == "tcarm2":  # a second sensor between the hand and its tool flange
        m = tc.RobotModel.from_urdf(tc.robots.tcarm_path(), keep_fixed=["tool_joint"])
        return m.with_ft_sensor("tool_ft", "tool_joint")
    if name == "panda":
        m = tc.RobotModel.from_urdf(ROBOTS["panda"](), keep_fixed=["panda_hand_joint"])
        return m.with_ft_sensor("wrist_ft", "panda_hand_joint")
    return tc.RobotModel.from_urdf(ROBOTS[name]())


def reference_estimator(name: str, dtype=np.float64, compute=np.float64) -> tc.ContactEstimator:
    """The torch estimator of a layout, computing in ``compute``, with ``dtype``'s rank rule."""
    lay = LAYOUTS[name]
    tdt = torch.float32 if compute == np.float32 else torch.float64
    rtol = tc.solve.RANK_RTOL[torch.float32 if dtype == np.float32 else torch.float64]
    return tc.ContactEstimator(
        robot_model(lay["robot"]).to(dtype=tdt), lay["sensors"], rank_rtol=rtol
    )


def scene(
    name: str, n: int, seed: int = 0, noise: float = 0.05, patterns=None
) -> dict[str, np.ndarray]:
    """``n`` frames of the runtime's inputs (float64 numpy), plus ``truth`` (the true wrenches).

    ``patterns`` overrides the layout's slot activity patterns.

    Keys: ``q, qd, qdd, ft, ft_residual, positions, directions, wrenches, active`` and, as the
    layout's flags ask, ``omega, domega, proper_acc``, ``tau_measured, tau_mask``, ``ft_cov``.
    """
    lay = LAYOUTS[name]
    model = robot_model(lay["robot"])
    est = tc.ContactEstimator(model, lay["sensors"])
    links, kinds = lay["links"], lay["kinds"]
    moving, torque, cov = lay["flags"]
    K, S, nv = len(links), len(est.sensor_names), model.nv
    g = torch.Generator().manual_seed(seed)

    def r(*shape, scale=1.0):
        return (2 * torch.rand(*shape, generator=g, dtype=torch.float64) - 1) * scale

    q, qd, qdd = r(n, nv, scale=1.2), r(n, nv), r(n, nv, scale=2.0)
    pos = r(n, K, 3, scale=0.05)
    dirs = r(n, K, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    wr = r(n, K, 6, scale=15.0)
    for k, kind in enumerate(kinds):
        if kind == "force":
            wr[:, k, 3:] = 0
        elif kind == "force_dir":  # a magnitude along the given direction
            wr[:, k, :3] = dirs[:, k] * r(n, 1, scale=15.0)
            wr[:, k, 3:] = 0
        else:
            wr[:, k, 3:] *= 0.05
    patterns = lay["patterns"] if patterns is None else patterns
    active = torch.tensor([patterns[i % len(patterns)] for i in range(n)], dtype=torch.float64)
    base = None
    x: dict[str, torch.Tensor] = {}
    if moving:
        x.update(omega=r(n, 3), domega=r(n, 3), proper_acc=r(n, 3, scale=2.0))
        x["proper_acc"][:, 2] += 9.81
        base = tc.BaseMotion(x["omega"], x["domega"], x["proper_acc"])
    truth = tc.Contacts(links, ("known",) * K, pos, wrenches=wr, active=active > 0)
    ft = est.predict_ft(q, qd, qdd, truth, base=base)
    ft = torch.stack([ft[s] for s in est.sensor_names], 1)  # (N, S, 6)
    ft = ft + r(n, S, 6, scale=noise)
    residual = r(n, S, 6, scale=0.2)
    x.update(
        q=q,
        qd=qd,
        qdd=qdd,
        ft=ft + residual,
        ft_residual=residual,
        positions=pos,
        directions=dirs,
        wrenches=wr * (torch.tensor([k == "known" for k in kinds], dtype=torch.float64)[:, None]),
        active=active,
    )
    if torque:
        given = tc.Contacts(links, ("known",) * K, pos, wrenches=wr, active=active > 0)
        tau = est.estimate(
            q, qd, qdd, {s: ft[:, i] for i, s in enumerate(est.sensor_names)}, given, base=base
        ).joint_torques
        x["tau_measured"] = tau + r(n, nv, scale=0.05)
        x["tau_mask"] = (torch.rand(n, nv, generator=g) > 0.3).double()
    if cov:
        A = r(n, S, 6, 6, scale=0.3)
        x["ft_cov"] = A @ A.transpose(-1, -2) + 0.01 * torch.eye(6, dtype=torch.float64)
    out = {k: v.numpy() for k, v in x.items()}
    out["truth"] = wr.numpy()
    return out


def reference(
    name: str, x: dict[str, np.ndarray], dtype=np.float64, compute=np.float64, estimator=None
) -> tc.ContactEstimate:
    """The torch estimator's estimate of the frames ``x`` (float64 outputs).

    Args:
        name: the layout.
        x: the frames (:func:`scene`).
        dtype: the graph dtype whose rank rule applies.
        compute: the dtype the torch estimator computes in (float32: the float32 baseline).
        estimator: the estimator to use (e.g. with status limits); default
            :func:`reference_estimator`.
    """
    lay = LAYOUTS[name]
    est = estimator or reference_estimator(name, dtype, compute)
    tdt = torch.float32 if compute == np.float32 else torch.float64
    t = {k: torch.as_tensor(v, dtype=tdt) for k, v in x.items() if k != "truth"}
    ft = {s: t["ft"][:, i] - t["ft_residual"][:, i] for i, s in enumerate(est.sensor_names)}
    c = tc.Contacts(
        lay["links"],
        lay["kinds"],
        t["positions"],
        t["directions"],
        t["wrenches"],
        t["active"] > 0.5,
    )
    kw = {}
    if "omega" in t:
        kw["base"] = tc.BaseMotion(t["omega"], t["domega"], t["proper_acc"])
    if "tau_measured" in t:
        kw.update(tau_measured=t["tau_measured"], tau_mask=t["tau_mask"] > 0.5)
    if "ft_cov" in t:  # the exported graphs propagate the noise, unweighted (the paper's pinv)
        kw["ft_covariance"] = {s: t["ft_cov"][:, i] for i, s in enumerate(est.sensor_names)}
        kw["weighted"] = False
    out = est.estimate(t["q"], t["qd"], t["qdd"], ft, c, backend="eager", **kw)
    return type(out)(
        *[
            {k: v.double() if v.is_floating_point() else v for k, v in f.items()}
            if isinstance(f, dict)
            else (f.double() if f is not None and f.is_floating_point() else f)
            for f in out
        ]
    )


#: Parity of the exported graphs with the torch estimator (float64, the graph dtype's rank rule),
#: per output kind, relative to ``max(1, max |reference|)``: float64 to 1e-9, float32 to 1e-4
#: (the residual ``|b - A x|``, a difference of terms as large as the forces, relative to them).
#: On an ill-conditioned frame (contacts close together) float32 rounding alone exceeds 1e-4;
#: there a float32 graph may be off by twice what the torch estimator computing in float32 is.
PARITY = {np.float64: 1e-9, np.float32: 1e-4}


def assert_parity(out: dict, ref, sensors, dtype, frames=slice(None), ref32=None) -> None:
    """Every output of a runtime call equals the torch estimate (``PARITY``, NaN where NaN).

    Args:
        out: the runtime's outputs, ``(N, ...)``.
        ref: the float64 torch estimate (the graph dtype's rank rule).
        sensors: sensor order of the outputs.
        dtype: the graph's dtype.
        frames: the frames of ``ref`` that ``out`` holds.
        ref32: for a float32 graph, the torch estimator's float32 estimate (the baseline).
    """
    tol = PARITY[np.dtype(dtype).type]

    def per_sensor(est, name):
        return np.stack([getattr(est, name)[s].numpy() for s in sensors], -1)[frames]

    fields = ["force", "moment", "joint_torques", "residual"]
    if ref.covariance is not None:
        fields.append("covariance")
    force = ref.force.numpy()[frames]
    force_scale = float(np.nanmax(np.abs(force))) if np.isfinite(force).any() else 1.0
    for name in fields:
        want = per_sensor(ref, name) if name == "residual" else getattr(ref, name).numpy()[frames]
        got = np.asarray(out[name], dtype=np.float64).reshape(want.shape)
        assert np.array_equal(np.isnan(got), np.isnan(want)), f"{name}: NaN pattern differs"
        if not np.isfinite(want).any():
            continue
        scale = max(1.0, float(np.nanmax(np.abs(want))))
        if name == "residual":  # |b - A x|: a difference of terms as large as the forces
            scale = max(scale, force_scale)
        n = len(want)
        err = np.nan_to_num(np.abs(got - want)).reshape(n, -1).max(-1)
        allowed = np.full(n, tol * scale)
        if ref32 is not None:  # what float32 rounding costs the torch estimator on each frame
            base = (
                per_sensor(ref32, name)
                if name == "residual"
                else getattr(ref32, name).numpy()[frames]
            )
            base = np.nan_to_num(np.abs(base.reshape(want.shape) - want)).reshape(n, -1).max(-1)
            allowed = np.maximum(allowed, 2.0 * base)
        bad = np.flatnonzero(err > allowed)
        assert not len(bad), f"{name}: frames {bad.tolist()} error {err[bad]} > {allowed[bad]}"
    for name in ("rank", "unknowns"):
        want = per_sensor(ref, name)
        np.testing.assert_array_equal(np.asarray(out[name]).reshape(want.shape), want, name)
    np.testing.assert_array_equal(
        np.asarray(out["status"]).reshape(-1), ref.status.numpy()[frames].reshape(-1)
    )


def correction_checkpoint(
    directory, model: tc.RobotModel, sensor: str, kind: str, seed: int = 3, constant=None
):
    """A correction-stack checkpoint (``torchcontact.residual``) saved as training saves it.

    Layers: a random offset and a learned ``kind`` ("mlp" or "gru") on the default features of
    ``sensor`` with one extra column ``temperature`` (random weights, non-identity
    normalisation), or, with ``constant`` (6,), only a learned MLP whose weights are zero, so that
    the correction is ``constant`` whatever the inputs (it still reads ``temperature``).

    Returns:
        The checkpoint directory.
    """
    from torchcontact.residual import FeatureSpec, ResidualCorrection, ResidualGRU, ResidualMLP

    spec = FeatureSpec.default(model, sensor, extra=("temperature",))
    F = len(spec.names(model))
    torch.manual_seed(seed)
    kw: dict = {}
    if constant is not None:
        net = ResidualMLP(F, 8, 1)
        with torch.no_grad():
            for p in net.parameters():
                p.zero_()
        net.set_normalisation(torch.randn(4, F), torch.tensor([list(constant)] * 4))
    else:
        g = torch.Generator().manual_seed(seed)
        kw["offset"] = torch.randn(6, generator=g, dtype=torch.float64)
        net = ResidualMLP(F, 16, 2) if kind == "mlp" else ResidualGRU(F, 8, layers=1)
        net.set_normalisation(torch.randn(64, F) * 2, torch.randn(64, 6) * 3)
    corr = ResidualCorrection(model, sensor, learned=net, features=spec, **kw)
    return corr.save(directory)
