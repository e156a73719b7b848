"""Corrections of F/T readings: a stack of physics and learned layers, its checkpoint, its use.

On contact-free frames the residual ``r = ft - ft_nominal`` of a sensor (``ft_nominal``: the
reading :meth:`ContactEstimator.predict_ft <torchcontact.ContactEstimator.predict_ft>` predicts
with no contact) holds what the rigid-body model does not know: offset and thermal drift, payload
and CAD errors, cables. A *correction* ``c(q, qd, qdd, extra)`` estimates it, and the estimator
uses ``ft - c`` (Del Prete et al. 2012, Sec. 2: the reading enters ``b``). A correction is a
stack of layers whose outputs add up:

- ``offset``: a constant wrench ``o`` ``(6,)``;
- ``inertial``: ``Y(q, qd, qdd) delta``, re-identified inertial parameters of the bodies the
  sensor carries (a payload, wrong CAD masses). The reading is linear in each body's ten
  parameters ``(m, m c, I_origin)`` (the regressor form of Newton-Euler, Atkeson, An and
  Hollerbach 1986), so a change ``delta`` of the parameters changes the reading by ``Y delta``;
  :func:`sensor_regressor` computes ``Y``;
- ``mlp`` or ``gru``: a small network trained on what the physics layers leave, from features
  (:class:`FeatureSpec`): by default sin/cos of the angles and the velocities of the joints that
  can move the sensor or its load (:func:`sensor_joints`), the nominal wrench ``ft_nominal`` and
  extra logged columns such as ``temperature``.

The stack evaluates as one torch function (:class:`CorrectionGraph`, ``torchcontact estimate
--residual``); its structure is a frozen :class:`CorrectionSpec`, which the ONNX graph of
:func:`torchcontact.export.export_residual_checkpoint` and the single-frame estimator graph read
as well. Physics layers compute in the model's
dtype; the networks train and run in float32 and cast at their boundary.

Checkpoint directory (``python -m training`` writes it, :meth:`ResidualCorrection.load` reads
it, never unpickling):

- ``weights.safetensors``: every tensor of the stack: ``offset.wrench`` ``(6,)`` and
  ``inertial.delta`` ``(P,)`` float64; ``learned.*``, the network's ``state_dict`` with its
  feature and target normalisation, float32.
- ``checkpoint.json``: ``format`` (:data:`CHECKPOINT_FORMAT`), ``sensor``, ``layers``,
  ``inertial`` (bodies, rank, singular values), ``learned`` (arch, features), ``extra_columns``,
  ``joint_names``, ``robot_sha256``, ``data_sha256``, ``weights_sha256`` (of the weights file),
  ``config``, ``report``.

This module needs torch and safetensors only; the fitting lives in ``training/``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchcontact.errors import CheckpointError, ModelMismatchError
from torchcontact.model import RobotModel
from torchcontact.spatial import (
    cross,
    inertia_about,
    matvec,
    skew,
    transform_wrench,
    twist_in_frame,
)

__all__ = [
    "CHECKPOINT_FORMAT",
    "LAYERS",
    "PARAM_NAMES",
    "RANGE_MARGIN",
    "CheckpointError",
    "CorrectionGraph",
    "CorrectionSpec",
    "FeatureSpec",
    "ResidualCorrection",
    "ResidualGRU",
    "ResidualMLP",
    "body_regressor",
    "inertial_params",
    "sensor_joints",
    "sensor_regressor",
    "subtree_bodies",
]

#: Value of ``checkpoint.json["format"]``; a different value is a foreign checkpoint.
CHECKPOINT_FORMAT = "torchcontact.residual/2"
WEIGHTS_FILE = "weights.safetensors"
META_FILE = "checkpoint.json"
#: Layer kinds, in the order they are stacked (at most one of ``mlp`` and ``gru``).
LAYERS = ("offset", "inertial", "mlp", "gru")
#: The ten inertial parameters of a body, about its origin in its axes (pinocchio's order).
PARAM_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")
_WRENCH_AXES = ("fx", "fy", "fz", "mx", "my", "mz")
#: A frame is outside a learned layer's training range when a feature lies beyond
#: ``[min - m span, max + m span]`` of the training frames, ``m`` this margin (span: max - min).
RANGE_MARGIN = 0.05


# ---------------------------------------------------------------------- the robot side
def subtree_bodies(model: RobotModel, sensor: str) -> list[int]:
    """Bodies whose motion the sensor measures: its child body's subtree, ascending.

    Raises:
        ModelMismatchError: ``sensor`` is not a sensor of ``model``.
    """
    _check_sensor(model, sensor)
    return model.subtree(model.ft_sensors[sensor].child_body)


def _check_sensor(model: RobotModel, sensor: str) -> None:
    if sensor not in model.ft_sensors:
        raise ModelMismatchError(
            f"{model.name} has no F/T sensor {sensor!r}; it has {list(model.ft_sensors)}"
        )


def sensor_joints(model: RobotModel, sensor: str) -> list[str]:
    """Joints that can change a sensor's contact-free reading, in ``model.joint_names`` order.

    The joints of the sensor's subtree (they move its load) and of its ancestors (they move the
    sensor in gravity and accelerate it); the other joints of a fixed-base robot do not enter the
    reading.

    Example:
        >>> import torchcontact as tc
        >>> sensor_joints(tc.RobotModel.from_urdf(tc.robots.tcarm_path()), "base_ft")[:2]
        ['shoulder_yaw', 'shoulder_pitch']
    """
    bodies = set(subtree_bodies(model, sensor))
    b = model.ft_sensors[sensor].parent_body
    while b >= 0:
        bodies.add(b)
        b = model.body_parent[b]
    drives = model.q_to_body.detach().cpu().numpy() != 0  # (nv, nb)
    return [j for i, j in enumerate(model.joint_names) if drives[i, sorted(bodies)].any()]


def inertial_params(model: RobotModel, bodies: Sequence[int]) -> np.ndarray:
    """``(10 len(bodies),)`` parameters of the bodies, :data:`PARAM_NAMES` each, float64.

    ``(m, m c, I_origin)``: mass (kg), first moments (kg m) and rotational inertia about the body
    origin in body axes (kg m^2), the form in which the reading is linear.
    """
    out = []
    for b in bodies:
        m = float(model.mass[b])
        c = model.com[b].detach().cpu().double().numpy()
        ic = model.inertia_com[b].detach().cpu().double().numpy()
        io = inertia_about(m, c, ic, np.zeros(3))  # about the body origin
        out.append([m, *(m * c), io[0, 0], io[0, 1], io[1, 1], io[0, 2], io[1, 2], io[2, 2]])
    return np.asarray(out, float).reshape(-1)


def body_regressor(v: Tensor, a: Tensor) -> Tensor:
    """Regressor of a body's Newton-Euler wrench: ``I a + v x* I v = Y(v, a) theta``.

    Args:
        v: ``(*B, 6)`` twist of the body ``[linear; angular]`` in its frame about its origin
            (m/s, rad/s).
        a: ``(*B, 6)`` spatial acceleration likewise, gravity included as an upward acceleration
            of the root (m/s^2, rad/s^2).

    Returns:
        ``(*B, 6, 10)``: columns in :data:`PARAM_NAMES` order, rows ``[force; moment about the
        origin]`` in the body frame (pinocchio's ``bodyRegressor``).
    """
    vl, w = v[..., :3], v[..., 3:]
    al, dw = a[..., :3], a[..., 3:]
    zero3 = torch.zeros_like(vl)
    # mass: f = m (a_lin + w x v_lin), no moment about the origin
    col_m = torch.cat((al + cross(w, vl), zero3), -1).unsqueeze(-1)
    # first moments h = m c: f = (dw x + w x w x) h, n = (-a_lin x - w x v_lin x + v_lin x w x) h
    Sw, Sv = skew(w), skew(vl)
    h_f = skew(dw) + Sw @ Sw
    h_n = -skew(al) - Sw @ Sv + Sv @ Sw

    # rotational inertia about the origin: n = I dw + w x (I w), I x = L(x) (Ixx..Izz)
    def L(x: Tensor) -> Tensor:  # noqa: N802 - the operator's name
        x0, x1, x2 = x.unbind(-1)
        z = torch.zeros_like(x0)
        rows = ((x0, x1, z, x2, z, z), (z, x0, x1, z, x2, z), (z, z, z, x0, x1, x2))
        return torch.stack([torch.stack(r, -1) for r in rows], -2)

    i_n = L(dw) + Sw @ L(w)
    top = torch.cat((col_m[..., :3, :], h_f, torch.zeros_like(i_n)), -1)
    bottom = torch.cat((col_m[..., 3:, :], h_n, i_n), -1)
    return torch.cat((top, bottom), -2)


def sensor_regressor(
    model: RobotModel, sensor: str, q: Tensor, qd: Tensor, qdd: Tensor, bodies=None
) -> Tensor:
    """Regressor ``Y`` of a sensor's contact-free reading: ``predict_ft = Y @ inertial_params``.

    The reading is the wrench the parent side exerts on the sensor's subtree, i.e. the sum of the
    subtree's Newton-Euler body wrenches (RNEA forward pass, Featherstone 2008 Sec. 5.3), moved to
    the sensor frame with the sign of its measure direction. Each body's wrench is linear in its
    ten parameters (:func:`body_regressor`).

    Args:
        model: the robot (its dtype and device are the computation's).
        sensor: the F/T sensor.
        q: ``(*B, nv)`` joint positions, rad or m; ``qd``, ``qdd`` likewise (finite).
        qd: ``(*B, nv)`` rad/s or m/s.
        qdd: ``(*B, nv)`` rad/s^2 or m/s^2.
        bodies: the bodies whose columns to return (default :func:`subtree_bodies`; bodies
            outside the subtree give zero columns).

    Returns:
        ``(*B, 6, 10 len(bodies))``, body-major columns, rows ``[force (N); moment (N m)]`` in the
        sensor's frame and measure direction.

    Raises:
        InputError: wrong shapes or non-finite joint values (from :func:`forward_pass`).

    Example:
        >>> import torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> q = torch.rand(4, m.nv, dtype=torch.float64)
        >>> Y = sensor_regressor(m, "base_ft", q, q, q)
        >>> theta = torch.as_tensor(inertial_params(m, subtree_bodies(m, "base_ft")))
        >>> nominal = tc.ContactEstimator(m, ["base_ft"]).predict_ft(
        ...     q, q, q, tc.Contacts((), (), q.new_zeros(4, 0, 3)))["base_ft"]
        >>> Y.shape, torch.allclose(Y @ theta, nominal)
        (torch.Size([4, 6, 80]), True)
    """
    from torchcontact.dynamics import forward_pass

    _check_sensor(model, sensor)
    s = model.ft_sensors[sensor]
    in_subtree = set(subtree_bodies(model, sensor))
    bodies = subtree_bodies(model, sensor) if bodies is None else list(bodies)
    fp = forward_pass(model, q, qd, qdd)
    idx = torch.tensor(bodies, device=q.device, dtype=torch.long)
    R, p = fp.R.index_select(-3, idx), fp.p.index_select(-2, idx)  # T_root_body
    # forward pass: twists and accelerations of each body in its frame about its origin
    v_b = twist_in_frame(R, p, fp.v.index_select(-2, idx))
    a_b = twist_in_frame(R, p, fp.a.index_select(-2, idx))
    Yb = body_regressor(v_b, a_b)  # (*B, nbs, 6, 10)
    # sensor pose T_root_sensor = T_root_child T_child_sensor; bodies in the sensor frame
    R_c, p_c = fp.R[..., s.child_body, :, :], fp.p[..., s.child_body, :]
    R_cs = torch.as_tensor(s.R_child_sensor, dtype=q.dtype, device=q.device)
    p_cs = torch.as_tensor(s.p_child_sensor, dtype=q.dtype, device=q.device)
    R_s = R_c @ R_cs
    p_s = p_c + matvec(R_c, p_cs)
    R_sb = R_s.transpose(-1, -2).unsqueeze(-3) @ R  # (*B, nbs, 3, 3)
    p_sb = matvec(R_s.transpose(-1, -2).unsqueeze(-3), p - p_s.unsqueeze(-2))
    # each column is a wrench in the body frame: expressed in the sensor frame
    cols = transform_wrench(R_sb.unsqueeze(-3), p_sb.unsqueeze(-2), Yb.transpose(-1, -2))
    sign = 1.0 if s.measure_direction == "parent_to_child" else -1.0
    mask = q.new_tensor([sign if b in in_subtree else 0.0 for b in bodies])
    cols = cols.transpose(-1, -2) * mask[:, None, None]  # (*B, nbs, 6, 10)
    return cols.movedim(-3, -2).flatten(-2)


# ---------------------------------------------------------------------- features
@dataclass(frozen=True)
class FeatureSpec:
    """Inputs of a learned layer, computed from the joint state inside the correction.

    Attributes:
        joints: joint names whose state enters (default in :meth:`default`: :func:`sensor_joints`).
        angles: ``"sincos"``: ``sin.<joint>``, ``cos.<joint>`` of revolute angles (a prismatic
            joint gives ``q.<joint>``), or ``"raw"``: ``q.<joint>``.
        velocities: add ``qd.<joint>``.
        accelerations: add ``qdd.<joint>`` (off by default: noisy on real robots, and their
            effect on the reading is in the nominal wrench).
        nominal: add the nominal contact-free wrench ``nominal.fx`` ... ``nominal.mz``.
        extra: logged columns, e.g. ``("temperature",)``.
    """

    joints: tuple[str, ...]
    angles: str = "sincos"
    velocities: bool = True
    accelerations: bool = False
    nominal: bool = True
    extra: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", tuple(self.joints))
        object.__setattr__(self, "extra", tuple(self.extra))
        if self.angles not in ("sincos", "raw"):
            raise ValueError(f"features.angles must be 'sincos' or 'raw', got {self.angles!r}")

    @classmethod
    def default(cls, model: RobotModel, sensor: str, **kwargs: Any) -> FeatureSpec:
        """The default inputs: :func:`sensor_joints`, sin/cos, velocities, nominal wrench."""
        return cls(tuple(sensor_joints(model, sensor)), **kwargs)

    def names(self, model: RobotModel) -> list[str]:
        """Feature names in column order.

        Example:
            >>> import torchcontact as tc
            >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
            >>> FeatureSpec(("shoulder_yaw",), extra=("temperature",)).names(m)[:4]
            ['sin.shoulder_yaw', 'cos.shoulder_yaw', 'qd.shoulder_yaw', 'nominal.fx']
        """
        types = dict(zip(model.joint_names, model.joint_types, strict=True))
        out: list[str] = []
        for j in self.joints:
            if self.angles == "sincos" and types[j] != "prismatic":
                out += [f"sin.{j}", f"cos.{j}"]
            else:
                out.append(f"q.{j}")
        out += [f"qd.{j}" for j in self.joints if self.velocities]
        out += [f"qdd.{j}" for j in self.joints if self.accelerations]
        out += [f"nominal.{a}" for a in _WRENCH_AXES if self.nominal]
        return out + list(self.extra)

    def check(self, model: RobotModel) -> None:
        """Raise :class:`ModelMismatchError` naming joints ``model`` does not have."""
        unknown = [j for j in self.joints if j not in model.joint_names]
        if unknown:
            raise ModelMismatchError(
                f"features name joints {unknown} that {model.name} does not have"
            )

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dictionary (lists for tuples)."""
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


@dataclass(frozen=True)
class CorrectionSpec:
    """The structure of a correction stack, built once from a checkpoint (a frozen value).

    What every consumer of a stack reads: :class:`CorrectionGraph` (the torch function), the
    single-frame estimator graph (which rebuilds the physics layers natively) and the exported
    metadata (``stack``, as :meth:`to_json`).

    Attributes:
        sensor: the corrected sensor.
        offset: 6 values ``[N; N m]`` or None.
        inertial: per body of the inertial layer ``(link name, 10 parameters)``
            (:data:`PARAM_NAMES`, link frame, about the body origin).
        features: the learned layer's inputs, or None.
        learned: the learned layer's kind (``"mlp"``, ``"gru"``) or None.
    """

    sensor: str
    offset: tuple[float, ...] | None = None
    inertial: tuple[tuple[str, tuple[float, ...]], ...] = ()
    features: FeatureSpec | None = None
    learned: str | None = None

    @property
    def nominal(self) -> bool:
        """The learned layer reads the nominal wrench."""
        return self.features is not None and self.features.nominal

    def offset_array(self) -> np.ndarray | None:
        """``(6,)`` float64 offset, or None."""
        return None if self.offset is None else np.asarray(self.offset, float)

    def to_json(self) -> dict[str, Any]:
        """The ``stack`` metadata of an exported correction graph."""
        return {
            "sensor": self.sensor,
            "offset": None if self.offset is None else list(self.offset),
            "inertial_bodies": [name for name, _ in self.inertial],
            "delta": [v for _, p in self.inertial for v in p] if self.inertial else None,
            "features": None if self.features is None else self.features.to_json(),
            "learned": self.learned,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any], sensor: str = "") -> CorrectionSpec:
        """Inverse of :meth:`to_json` (also reads the ``stack`` of graphs without ``sensor``)."""
        names = list(d.get("inertial_bodies") or [])
        delta = np.asarray(d.get("delta") or [], float).reshape(-1, 10)
        feats = d.get("features")
        return cls(
            sensor=str(d.get("sensor", sensor)),
            offset=None if d.get("offset") is None else tuple(float(v) for v in d["offset"]),
            inertial=tuple(
                (n, tuple(float(v) for v in p)) for n, p in zip(names, delta, strict=True)
            ),
            features=None if feats is None else FeatureSpec(**feats),
            learned=d.get("learned"),
        )

    def columns(self, model: RobotModel) -> tuple[list, int, np.ndarray] | None:
        """The learned layer's raw input columns and their map to its feature order.

        Returns:
            ``(columns, n_angles, perm)``: per column ``("q" | "qd" | "qdd", joint)`` or
            ``("extra", name)``, the first ``n_angles`` of them entering as ``sin, cos`` pairs;
            ``perm`` ``(V, F)`` maps ``[sin (n_angles), cos (n_angles), other columns, extra,
            nominal (6)]`` to the feature order of :meth:`FeatureSpec.names`. None when a
            sin/cos set mixes prismatic joints in (their features interleave).
        """
        spec = self.features
        if spec is None:
            return None
        types = dict(zip(model.joint_names, model.joint_types, strict=True))
        prismatic = [types[j] == "prismatic" for j in spec.joints]
        sincos = spec.angles == "sincos"
        if sincos and any(prismatic) and not all(prismatic):
            return None
        sincos = sincos and not any(prismatic)
        angle_cols = [("q", j) for j in spec.joints]
        other = [] if sincos else list(angle_cols)
        other += [("qd", j) for j in spec.joints if spec.velocities]
        other += [("qdd", j) for j in spec.joints if spec.accelerations]
        extra_cols = [("extra", c) for c in spec.extra]
        n_angles = len(spec.joints) if sincos else 0
        columns = (angle_cols if sincos else []) + other + extra_cols
        n_in = 2 * n_angles + len(other) + len(extra_cols) + (6 if spec.nominal else 0)
        order = [i for k in range(n_angles) for i in (k, n_angles + k)]
        base = 2 * n_angles
        order += [base + k for k in range(len(other))]
        if spec.nominal:
            order += [base + len(other) + len(extra_cols) + k for k in range(6)]
        order += [base + len(other) + k for k in range(len(extra_cols))]
        perm = np.zeros((n_in, len(order)))
        perm[order, np.arange(len(order))] = 1.0
        return columns, n_angles, perm


# ---------------------------------------------------------------------- learned layers
class _Normalised(nn.Module):
    """Feature/target standardisation held as buffers (saved with the weights)."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        self.register_buffer("feature_mean", torch.zeros(in_features))
        self.register_buffer("feature_std", torch.ones(in_features))
        self.register_buffer("target_mean", torch.zeros(out_features))
        self.register_buffer("target_std", torch.ones(out_features))

    def set_normalisation(self, x: Tensor, y: Tensor) -> None:
        """Set the statistics from training features ``(N, F)`` and targets ``(N, out)``."""
        x, y = x.detach().float(), y.detach().float()
        self.feature_mean.copy_(x.mean(0))
        self.feature_std.copy_(x.std(0).clamp_min(1e-6))
        self.target_mean.copy_(y.mean(0))
        self.target_std.copy_(y.std(0).clamp_min(1e-6))

    def _in(self, x: Tensor) -> Tensor:
        if x.shape[-1] != self.in_features:
            raise ValueError(f"features: expected (..., {self.in_features}), got {tuple(x.shape)}")
        return (x.float() - self.feature_mean) / self.feature_std

    def _out(self, z: Tensor) -> Tensor:
        return z * self.target_std + self.target_mean


class ResidualMLP(_Normalised):
    """MLP ``r_hat = f(features)``.

    Args:
        in_features: number of features F.
        hidden: width of the hidden layers.
        layers: number of hidden layers.
        out_features: 6 (one wrench ``[force; moment]``).

    Example:
        >>> m = ResidualMLP(4, hidden=8, layers=1)
        >>> m(torch.zeros(2, 3, 4, dtype=torch.float64)).shape, m(torch.zeros(4)).dtype
        (torch.Size([2, 3, 6]), torch.float32)
    """

    kind = "mlp"

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 2, out_features: int = 6):
        super().__init__(in_features, out_features)
        self.arch = {"kind": self.kind, "in_features": in_features, "hidden": hidden}
        self.arch.update(layers=layers, out_features=out_features)
        mods: list[nn.Module] = []
        width = in_features
        for _ in range(layers):
            mods += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        mods.append(nn.Linear(width, out_features))
        self.net = nn.Sequential(*mods)

    def forward(self, features: Tensor) -> Tensor:
        """Residual ``(*B, 6)`` [N; N m] from features ``(*B, F)``, float32."""
        return self._out(self.net(self._in(features)))


class ResidualGRU(_Normalised):
    """GRU residual model with explicit state, for drift and hysteresis.

    ``forward(features, h) -> (r_hat, h_next)`` runs one frame, so the robot can call it at its
    control rate; :meth:`forward_sequence` runs a whole sequence (training) and gives the same
    numbers as stepping frame by frame.

    Args:
        in_features: number of features F.
        hidden: GRU state size H.
        layers: stacked GRU layers L.
        out_features: 6.

    Example:
        >>> m = ResidualGRU(4, hidden=8, layers=1)
        >>> r, h = m(torch.zeros(3, 4), None)
        >>> r.shape, h.shape
        (torch.Size([3, 6]), torch.Size([3, 1, 8]))
    """

    kind = "gru"

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 1, out_features: int = 6):
        super().__init__(in_features, out_features)
        self.arch = {"kind": self.kind, "in_features": in_features, "hidden": hidden}
        self.arch.update(layers=layers, out_features=out_features)
        self.hidden, self.layers = hidden, layers
        self.gru = nn.GRU(in_features, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden + in_features, out_features)

    def initial_state(self, *batch: int, device: torch.device | str | None = None) -> Tensor:
        """Zero state ``(*batch, L, H)`` float32."""
        return torch.zeros(*batch, self.layers, self.hidden, device=device)

    def forward_sequence(self, features: Tensor, h: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Run a sequence.

        Args:
            features: ``(B, T, F)``.
            h: ``(B, L, H)`` state before the first frame, or None for zeros.

        Returns:
            ``r_hat (B, T, 6)`` float32, ``h (B, L, H)`` float32 after the last frame.
        """
        x = self._in(features)
        h0 = None if h is None else h.float().transpose(0, 1).contiguous()
        y, hn = self.gru(x, h0)
        return self._out(self.head(torch.cat((y, x), -1))), hn.transpose(0, 1)

    def forward(self, features: Tensor, h: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """One frame: ``features (*B, F)``, ``h (*B, L, H)`` -> ``(r_hat (*B, 6), h_next)``."""
        batch = features.shape[:-1]
        x = features.reshape(-1, 1, features.shape[-1])
        hh = None if h is None else h.reshape(-1, self.layers, self.hidden)
        r, hn = self.forward_sequence(x, hh)
        return r.reshape(*batch, -1), hn.reshape(*batch, self.layers, self.hidden)


_LEARNED: dict[str, type[_Normalised]] = {"mlp": ResidualMLP, "gru": ResidualGRU}


def _build_learned(arch: Mapping[str, Any]) -> ResidualMLP | ResidualGRU:
    arch = dict(arch)
    kind = arch.pop("kind", None)
    if kind not in _LEARNED:
        raise CheckpointError(
            f"unknown learned layer kind {kind!r}; expected one of {list(_LEARNED)}"
        )
    try:
        return _LEARNED[kind](**arch)  # type: ignore[return-value]
    except TypeError as e:
        raise CheckpointError(f"bad arch for {kind!r}: {e}") from None


# ---------------------------------------------------------------------- the stack as a function
class CorrectionGraph(nn.Module):
    """A correction stack as one tensor function (what ``estimate`` runs and ONNX exports).

    ``forward(q, qd, qdd, extra, h_in) -> (correction, h_out)``: the offset, plus ``Y delta``
    of the inertial layer, plus the learned layer on its features (one frame per batch element
    for a GRU, whose state is explicit). Physics in the model's dtype; the robot model's tensors
    become constants of a traced graph.

    Args:
        model: the robot (dtype and device of the computation).
        sensor: the corrected sensor.
        offset: ``(6,)`` or None.
        bodies: body indices of the inertial layer (None: no inertial layer).
        delta: ``(10 len(bodies),)`` parameter change, :data:`PARAM_NAMES` per body.
        learned: a :class:`ResidualMLP` or :class:`ResidualGRU`, or None.
        features: its inputs.
    """

    def __init__(
        self,
        model: RobotModel,
        sensor: str,
        offset: Tensor | None = None,
        bodies: Sequence[int] | None = None,
        delta: Tensor | None = None,
        learned: ResidualMLP | ResidualGRU | None = None,
        features: FeatureSpec | None = None,
    ) -> None:
        super().__init__()
        _check_sensor(model, sensor)
        self.model, self.sensor = model, sensor
        dt, dev = model.dtype, model.device

        def t(x: Any) -> Tensor:
            return torch.as_tensor(np.asarray(x), dtype=dt, device=dev)

        self.offset = None if offset is None else t(offset.detach().cpu()).reshape(6)
        nominal = features is not None and features.nominal
        if (bodies is None) != (delta is None):
            raise ValueError("the inertial layer needs both bodies and delta")
        # regressor columns: every body the sensor carries; the inertial layer's change is zero
        # outside its own bodies
        self.bodies = subtree_bodies(model, sensor)
        self.delta = None
        if delta is not None:
            assert bodies is not None
            d = t(delta.detach().cpu()).reshape(-1)
            outside = [model.body_names[b] for b in bodies if b not in self.bodies]
            if outside or d.numel() != 10 * len(bodies):
                raise ValueError(
                    f"inertial layer: {d.numel()} values for bodies {list(bodies)}; bodies"
                    f" {outside} are not carried by sensor {sensor!r}"
                )
            full = torch.zeros(10 * len(self.bodies), dtype=dt, device=dev)
            for i, b in enumerate(bodies):
                j = self.bodies.index(b)
                full[10 * j : 10 * j + 10] = d[10 * i : 10 * i + 10]
            self.delta = full
        self.theta0 = t(inertial_params(model, self.bodies)) if nominal else None
        self.needs_regressor = self.delta is not None or nominal
        self.learned = learned
        self.features = features
        if features is not None:
            features.check(model)
        if learned is not None and features is None:
            raise ValueError("a learned layer needs its FeatureSpec")
        if learned is not None and len(features.names(model)) != learned.in_features:
            raise CheckpointError(
                f"{len(features.names(model))} features for a network with"
                f" {learned.in_features} inputs"
            )
        if features is not None:
            jidx = [model.joint_names.index(j) for j in features.joints]
            self._jidx = torch.tensor(jidx, dtype=torch.long, device=dev)
            types = [model.joint_types[i] for i in jidx]
            self._revolute = torch.tensor(
                [ty != "prismatic" for ty in types], dtype=torch.bool, device=dev
            )
            self._all_revolute = bool(self._revolute.all()) and len(jidx) > 0
            self._none_revolute = not bool(self._revolute.any())

    @classmethod
    def from_spec(
        cls, model: RobotModel, spec: CorrectionSpec, learned: ResidualMLP | ResidualGRU | None
    ) -> CorrectionGraph:
        """The stack of a :class:`CorrectionSpec` (its network given: the spec holds no weights).

        Raises:
            ModelMismatchError: a sensor or body ``model`` lacks.
            ValueError: inconsistent layers.
        """
        unknown = [b for b, _ in spec.inertial if b not in model.body_names]
        if unknown:
            raise ModelMismatchError(f"inertial layer bodies {unknown} not in {model.name}")
        offset = None if spec.offset is None else torch.tensor(spec.offset, dtype=torch.float64)
        bodies = [model.body_names.index(b) for b, _ in spec.inertial] or None
        delta = (
            torch.tensor([v for _, p in spec.inertial for v in p], dtype=torch.float64)
            if spec.inertial
            else None
        )
        return cls(model, spec.sensor, offset, bodies, delta, learned, spec.features)

    @property
    def extra_columns(self) -> tuple[str, ...]:
        """Logged columns the stack reads besides the joint state, in ``extra`` order."""
        return () if self.features is None or self.learned is None else self.features.extra

    @property
    def recurrent(self) -> bool:
        """True when the learned layer is a GRU."""
        return isinstance(self.learned, ResidualGRU)

    def physics(self, q: Tensor, qd: Tensor, qdd: Tensor) -> tuple[Tensor, Tensor | None]:
        """Physics layers ``(N, 6)`` and the nominal wrench ``(N, 6)`` (None unless a feature)."""
        out = q.new_zeros(q.shape[0], 6)
        if self.offset is not None:
            out = out + self.offset
        nominal = None
        if self.needs_regressor:
            Y = sensor_regressor(self.model, self.sensor, q, qd, qdd, self.bodies)
            if self.delta is not None:
                out = out + Y @ self.delta
            if self.theta0 is not None:
                nominal = Y @ self.theta0
        return out, nominal

    def feature_matrix(
        self, q: Tensor, qd: Tensor, qdd: Tensor, extra: Tensor | None, nominal: Tensor | None
    ) -> Tensor:
        """Features ``(N, F)`` of the learned layer in :meth:`FeatureSpec.names` order."""
        spec = self.features
        assert spec is not None
        qs = q.index_select(-1, self._jidx)
        if spec.angles == "sincos" and self._all_revolute:
            angles = torch.stack((qs.sin(), qs.cos()), -1).flatten(-2)
        elif spec.angles == "sincos" and not self._none_revolute:
            parts = []
            for i in range(qs.shape[-1]):
                x = qs[..., i : i + 1]
                parts += [x.sin(), x.cos()] if bool(self._revolute[i]) else [x]
            angles = torch.cat(parts, -1)
        else:
            angles = qs
        cols = [angles]
        if spec.velocities:
            cols.append(qd.index_select(-1, self._jidx))
        if spec.accelerations:
            cols.append(qdd.index_select(-1, self._jidx))
        if spec.nominal:
            assert nominal is not None
            cols.append(nominal)
        if spec.extra:
            if extra is None:
                raise ValueError(f"the correction needs extra columns {list(spec.extra)}")
            cols.append(extra.to(q.dtype))
        return torch.cat(cols, -1)

    def forward(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        extra: Tensor | None = None,
        h_in: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None]:
        """Correction of ``N`` frames (a GRU: one step of ``N`` independent sequences).

        Args:
            q: ``(N, nv)`` in ``model.joint_names`` order, rad or m; ``qd``, ``qdd`` likewise.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            extra: ``(N, E)`` the :attr:`extra_columns`, or None when there are none.
            h_in: ``(N, L, H)`` GRU state (None: zeros).

        Returns:
            ``correction (N, 6)`` [N; N m] in the model's dtype, to subtract from the reading,
            and the next GRU state ``(N, L, H)`` float32 (None without a GRU).
        """
        out, nominal = self.physics(q, qd, qdd)
        if self.learned is None:
            return out, None
        x = self.feature_matrix(q, qd, qdd, extra, nominal)
        if isinstance(self.learned, ResidualGRU):
            r, h = self.learned(x, h_in)
            return out + r.to(out.dtype), h
        return out + self.learned(x).to(out.dtype), None


# ---------------------------------------------------------------------- checkpoint and use
def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@dataclass(eq=False)
class ResidualCorrection:
    """A correction stack bound to a robot: ``ft_corrected = ft - c(q, qd, qdd, extra)``.

    A plain value (not an ``nn.Module``) holding the layers; build it with :meth:`load` or from
    fitted layers (``python -m training``). For a GRU the frames of one :meth:`correct` call are
    one time-ordered sequence and the state carries over between calls (:meth:`reset` starts
    afresh).

    Attributes:
        model: the robot (physics in its dtype).
        sensor: the corrected sensor.
        offset: ``(6,)`` [N; N m] or None.
        inertial_bodies: body names of the inertial layer (empty: none).
        delta: ``(10 len(inertial_bodies),)`` parameter change or None.
        learned: the network or None.
        features: the network's inputs.
        meta: everything else of ``checkpoint.json`` (report, config, ...).
        source: where it was loaded from ("" when built in memory).

    Example:
        >>> import torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> c = ResidualCorrection(m, "base_ft", offset=torch.tensor([1.0, 0, 0, 0, 0, 0]))
        >>> q = torch.zeros(5, m.nv, dtype=torch.float64)
        >>> c.correct(torch.ones(5, 6, dtype=torch.float64), q, q, q)[0].tolist()
        [0.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    """

    model: RobotModel
    sensor: str
    offset: Tensor | None = None
    inertial_bodies: tuple[str, ...] = ()
    delta: Tensor | None = None
    learned: ResidualMLP | ResidualGRU | None = None
    features: FeatureSpec | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        self.inertial_bodies = tuple(self.inertial_bodies)
        unknown = [b for b in self.inertial_bodies if b not in self.model.body_names]
        if unknown:
            raise ModelMismatchError(f"inertial layer bodies {unknown} not in {self.model.name}")
        if self.learned is not None:
            self.learned = self.learned.eval()
        if self.delta is not None and self.delta.numel() != 10 * len(self.inertial_bodies):
            raise ValueError(
                f"inertial layer: {self.delta.numel()} values for bodies {self.inertial_bodies}"
            )
        delta = () if self.delta is None else self.delta.detach().cpu().double().reshape(-1, 10)
        self._spec = CorrectionSpec(
            sensor=self.sensor,
            offset=None if self.offset is None else tuple(self.offset.double().reshape(6).tolist()),
            inertial=tuple(
                (b, tuple(d.tolist())) for b, d in zip(self.inertial_bodies, delta, strict=True)
            ),
            features=self.features,
            learned=None if self.learned is None else self.learned.kind,
        )
        self.graph = CorrectionGraph.from_spec(self.model, self._spec, self.learned)
        self._h: Tensor | None = None

    # ------------------------------------------------------------------ description
    @property
    def spec(self) -> CorrectionSpec:
        """The stack's :class:`CorrectionSpec` (built once)."""
        return self._spec

    @property
    def layers(self) -> list[str]:
        """Layer kinds of the stack, e.g. ``["offset", "inertial", "mlp"]``."""
        out = ["offset"] if self.offset is not None else []
        out += ["inertial"] if self.delta is not None else []
        return out + ([self.learned.kind] if self.learned is not None else [])

    @property
    def recurrent(self) -> bool:
        """True for a GRU: frames must arrive in time order, the state carries over."""
        return self.graph.recurrent

    @property
    def extra_columns(self) -> list[str]:
        """Logged columns the correction reads besides ``q``, ``qd``, ``qdd``."""
        return list(self.graph.extra_columns)

    # ------------------------------------------------------------------ use
    def reset(self) -> None:
        """Forget the recurrent state."""
        self._h = None

    def _extra(self, extra: Mapping[str, Any] | None, n: int, like: Tensor) -> Tensor | None:
        names = self.extra_columns
        if not names:
            return None
        extra = extra or {}
        missing = [c for c in names if c not in extra]
        if missing:
            raise KeyError(f"the residual correction needs columns {missing}")
        cols = [torch.tensor(np.asarray(extra[c], np.float64)).to(like) for c in names]
        for c, x in zip(names, cols, strict=True):
            if x.shape != (n,):
                raise ValueError(f"column {c!r}: expected ({n},), got {tuple(x.shape)}")
        return torch.stack(cols, -1)

    @torch.no_grad()
    def correction(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        extra: Mapping[str, Any] | None = None,
        chunk: int = 8192,
    ) -> Tensor:
        """The correction ``(*B, 6)`` [N; N m] of frames in time order (a GRU keeps its state).

        Frames with a non-finite joint value or extra column get NaN (their reading cannot be
        corrected); a GRU skips them.

        Args:
            q: ``(*B, nv)`` in ``model.joint_names`` order; ``qd``, ``qdd`` likewise.
            qd: ``(*B, nv)``.
            qdd: ``(*B, nv)``.
            extra: column name -> ``(*B,)`` values for every :attr:`extra_columns`.
            chunk: frames evaluated at once (bounds memory).

        Raises:
            KeyError: an extra column is missing.
        """
        m = self.model
        batch = q.shape[:-1]
        n = int(np.prod(batch)) if len(batch) else 1
        qs = [
            torch.as_tensor(x).to(device=m.device, dtype=m.dtype).reshape(n, m.nv)
            for x in (q, qd, qdd)
        ]
        ex = self._extra(
            None if extra is None else {k: np.asarray(v).reshape(-1) for k, v in extra.items()},
            n,
            qs[0],
        )
        ok = torch.stack([torch.isfinite(x).all(-1) for x in qs], -1).all(-1)
        if ex is not None:
            ok &= torch.isfinite(ex).all(-1)
        out = qs[0].new_full((n, 6), float("nan"))
        rows = ok.nonzero().squeeze(-1)
        g = self.graph
        for s in range(0, len(rows), chunk):  # in time order: a GRU's state carries over
            sel = rows[s : s + chunk]
            args = [x[sel] for x in qs] + [None if ex is None else ex[sel]]
            if g.recurrent:
                phys, nominal = g.physics(*args[:3])
                x = g.feature_matrix(*args, nominal)
                r, self._h = g.learned.forward_sequence(x[None], self._h)  # type: ignore[union-attr]
                out[sel] = phys + r[0].to(phys.dtype)
            else:
                out[sel] = g(*args)[0]
        return out.reshape(*batch, 6)

    @torch.no_grad()
    def feature_values(
        self,
        q: Any,
        qd: Any,
        qdd: Any,
        extra: Mapping[str, Any] | None = None,
        chunk: int = 8192,
    ) -> np.ndarray | None:
        """The learned layer's features ``(N, F)`` (:meth:`FeatureSpec.names` order), float64.

        Args:
            q: ``(N, nv)`` in ``model.joint_names`` order; ``qd``, ``qdd`` likewise.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            extra: column name -> ``(N,)`` for every :attr:`extra_columns`.
            chunk: frames evaluated at once.

        Returns:
            The features (NaN rows where an input is not finite), or None without a learned
            layer.
        """
        if self.learned is None or self.features is None:
            return None
        m, g = self.model, self.graph
        qs = [torch.as_tensor(np.asarray(x, np.float64)).to(m.dtype).reshape(-1, m.nv)
              for x in (q, qd, qdd)]  # fmt: skip
        n = qs[0].shape[0]
        ex = self._extra(
            None if extra is None else {k: np.asarray(v).reshape(-1) for k, v in extra.items()},
            n,
            qs[0],
        )
        out = np.full((n, len(self.features.names(m))), np.nan)
        for a in range(0, n, chunk):
            args = [x[a : a + chunk] for x in qs]
            e = None if ex is None else ex[a : a + chunk]
            _, nominal = g.physics(*args)
            out[a : a + chunk] = g.feature_matrix(*args, e, nominal).double().cpu().numpy()
        return out

    def record_ranges(
        self, q: Any, qd: Any, qdd: Any, extra: Mapping[str, Any] | None = None
    ) -> dict[str, Any] | None:
        """Record the training range of each feature of the learned layer in :attr:`meta`.

        Saved with the checkpoint (``feature_ranges`` in ``checkpoint.json``: ``names``,
        ``min``, ``max``, ``frames``, ``margin``); :meth:`outside_range` then flags frames a
        network would extrapolate on (``estimate --residual``: status bit
        :attr:`~torchcontact.status.Status.OUTSIDE_TRAINING`).

        Args:
            q: ``(N, nv)`` the training frames' joint positions (model order).
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            extra: their extra columns.

        Returns:
            The recorded entry, or None (no learned layer, or no finite frame).
        """
        f = self.feature_values(q, qd, qdd, extra)
        if f is None:
            return None
        f = f[np.isfinite(f).all(1)]
        if not len(f):
            return None
        entry = {
            "names": self.features.names(self.model),  # type: ignore[union-attr]
            "min": f.min(0).tolist(),
            "max": f.max(0).tolist(),
            "frames": len(f),
            "margin": RANGE_MARGIN,
        }
        self.meta["feature_ranges"] = entry
        return entry

    @property
    def feature_ranges(self) -> tuple[list[str], np.ndarray, np.ndarray] | None:
        """``(names, lo, hi)``: each feature's allowed interval (training range and margin).

        None without a learned layer, or for a checkpoint written before ranges were recorded.
        """
        r = self.meta.get("feature_ranges")
        if not isinstance(r, Mapping) or self.features is None:
            return None
        names = list(r.get("names", []))
        if names != self.features.names(self.model):
            return None
        lo, hi = np.asarray(r["min"], np.float64), np.asarray(r["max"], np.float64)
        pad = float(r.get("margin", RANGE_MARGIN)) * (hi - lo)
        return names, lo - pad, hi + pad

    def outside_range(
        self, q: Any, qd: Any, qdd: Any, extra: Mapping[str, Any] | None = None
    ) -> np.ndarray | None:
        """``(N, F)`` bool: features outside the training range (:attr:`feature_ranges`).

        Returns:
            None without recorded ranges (old checkpoints: nothing is flagged). Frames with a
            non-finite input are not flagged here (their status says so).
        """
        rng = self.feature_ranges
        if rng is None:
            return None
        f = self.feature_values(q, qd, qdd, extra)
        assert f is not None
        with np.errstate(invalid="ignore"):
            return (f < rng[1]) | (f > rng[2])

    def correct(
        self, ft: Tensor, q: Tensor, qd: Tensor, qdd: Tensor, extra: Mapping[str, Any] | None = None
    ) -> Tensor:
        """``ft (*B, 6) - correction`` in ``ft``'s dtype and device (see :meth:`correction`)."""
        c = self.correction(q, qd, qdd, extra)
        return ft - c.to(device=ft.device, dtype=ft.dtype)

    # ------------------------------------------------------------------ checkpoint
    def tensors(self) -> dict[str, Tensor]:
        """Every tensor of the stack by checkpoint name (physics float64, network float32)."""
        out: dict[str, Tensor] = {}
        if self.offset is not None:
            out["offset.wrench"] = self.offset.detach().cpu().double().reshape(6).contiguous()
        if self.delta is not None:
            out["inertial.delta"] = self.delta.detach().cpu().double().reshape(-1).contiguous()
        if self.learned is not None:
            for k, v in self.learned.state_dict().items():
                out[f"learned.{k}"] = v.detach().cpu().float().contiguous()
        return out

    def describe(self) -> dict[str, Any]:
        """The structure written to ``checkpoint.json`` (what :meth:`load` rebuilds)."""
        d: dict[str, Any] = {
            "format": CHECKPOINT_FORMAT,
            "sensor": self.sensor,
            "layers": self.layers,
            "joint_names": list(self.model.joint_names),
            "robot": self.model.name,
            "robot_sha256": self.model.urdf_sha256,
            "robot_identity_sha256": self.model.identity.sha256,
            "robot_identity": self.model.identity.to_json(),
            "extra_columns": self.extra_columns,
        }
        if self.delta is not None:
            d["inertial"] = {
                **dict(self.meta.get("inertial", {})),
                "bodies": list(self.inertial_bodies),
                "params": list(PARAM_NAMES),
            }
        if self.learned is not None and self.features is not None:
            d["learned"] = {
                "arch": self.learned.arch,
                "features": self.features.to_json(),
                "feature_names": self.features.names(self.model),
            }
        return d

    def save(self, directory: str | Path) -> Path:
        """Write ``weights.safetensors`` and ``checkpoint.json`` (with the weights' sha256).

        ``meta`` keys other than the structure (``data_sha256``, ``config``, ``report``, ...)
        are written too.

        Returns:
            The directory (created if absent).
        """
        from safetensors.torch import save_file

        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        tensors = self.tensors()
        save_file(tensors, str(d / WEIGHTS_FILE), metadata={"format": CHECKPOINT_FORMAT})
        full = {k: v for k, v in self.meta.items() if k not in ("inertial",)}
        full.update(self.describe())
        full["tensors"] = {
            k: [list(v.shape), str(v.dtype).removeprefix("torch.")] for k, v in tensors.items()
        }
        full["weights_sha256"] = self.meta["weights_sha256"] = _sha256(d / WEIGHTS_FILE)
        (d / META_FILE).write_text(json.dumps(_json_clean(full), indent=2, sort_keys=True) + "\n")
        self.source = str(d.resolve())
        return d

    @classmethod
    def load(
        cls, directory: str | Path, model: RobotModel, *, check_robot: bool = True
    ) -> ResidualCorrection:
        """Load and verify a checkpoint directory for ``model``; never unpickles.

        Checks: ``checkpoint.json`` is this format; the sha256 of ``weights.safetensors`` equals
        the recorded one; the tensor names, shapes and dtypes are exactly those the recorded
        layers need; the robot's URDF hash is the recorded one (``check_robot``); the sensor,
        bodies and joints exist in ``model``.

        Args:
            directory: the checkpoint directory.
            model: the robot it will correct (its dtype is the physics dtype).
            check_robot: refuse a checkpoint trained for another URDF.

        Returns:
            The correction, ``source`` the resolved directory.

        Raises:
            CheckpointError: missing file, hash mismatch, foreign format, inconsistent structure,
                another robot, or a sensor, body or joint ``model`` lacks (the message says which).
        """
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        d = Path(directory)
        meta_path, weights_path = d / META_FILE, d / WEIGHTS_FILE
        for p in (meta_path, weights_path):
            if not p.is_file():
                raise CheckpointError(f"{d}: not a residual checkpoint ({p.name} missing)")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise CheckpointError(f"{meta_path}: not valid JSON ({e})") from None
        if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
            got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
            hint = (
                " (a checkpoint of an earlier torchcontact: retrain it with python -m training)"
                if got == "torchcontact.residual/1"
                else ""
            )
            raise CheckpointError(
                f"{meta_path}: foreign checkpoint (format {got!r}, expected"
                f" {CHECKPOINT_FORMAT!r}){hint}"
            )
        digest = _sha256(weights_path)
        if digest != meta.get("weights_sha256"):
            raise CheckpointError(
                f"{weights_path}: sha256 {digest} does not match checkpoint.json's weights_sha256"
                f" {meta.get('weights_sha256')}: the weights were modified or belong to another"
                " checkpoint"
            )
        if check_robot:
            _check_robot(d, meta, model)
        sensor = meta.get("sensor")
        if sensor not in model.ft_sensors:
            raise CheckpointError(
                f"{d}: corrects sensor {sensor!r}, which {model.name} does not have"
                f" ({list(model.ft_sensors)})"
            )
        layers = meta.get("layers")
        if (
            not isinstance(layers, list)
            or not layers
            or any(k not in LAYERS for k in layers)
            or len(set(layers)) != len(layers)
            or ("mlp" in layers and "gru" in layers)
        ):
            raise CheckpointError(f"{d}: bad layer list {layers!r} (from {list(LAYERS)})")
        learned = None
        features = None
        expected: dict[str, tuple[tuple[int, ...], torch.dtype]] = {}
        if "offset" in layers:
            expected["offset.wrench"] = ((6,), torch.float64)
        bodies: list[str] = []
        if "inertial" in layers:
            bodies = list(meta.get("inertial", {}).get("bodies", []))
            carried = [model.body_names[b] for b in subtree_bodies(model, sensor)]
            missing = [b for b in bodies if b not in carried]
            if not bodies or missing:
                raise CheckpointError(
                    f"{d}: inertial layer bodies {missing or bodies} are not bodies that"
                    f" {model.name}'s sensor {sensor!r} carries"
                )
            expected["inertial.delta"] = ((10 * len(bodies),), torch.float64)
        if "mlp" in layers or "gru" in layers:
            spec = meta.get("learned", {})
            learned = _build_learned(spec.get("arch", {}))
            try:
                features = FeatureSpec(**spec.get("features", {}))
                features.check(model)
            except (TypeError, ValueError) as e:
                raise CheckpointError(f"{d}: bad feature spec: {e}") from None
            names = features.names(model)
            if names != spec.get("feature_names") or len(names) != learned.in_features:
                raise CheckpointError(
                    f"{d}: the feature spec gives {len(names)} features for"
                    f" {learned.in_features} network inputs"
                )
            for k, v in learned.state_dict().items():
                expected[f"learned.{k}"] = (tuple(v.shape), torch.float32)
        try:
            state = load_file(str(weights_path))
        except (SafetensorError, OSError) as e:
            raise CheckpointError(f"{weights_path}: unreadable safetensors ({e})") from None
        got = {k: (tuple(v.shape), v.dtype) for k, v in state.items()}
        if got != expected:
            diff = sorted(
                str(x) for x in set(expected.items()) ^ set(got.items())
            )  # names, shapes or dtypes that differ
            raise CheckpointError(f"{d}: weights do not fit the recorded layers: {diff[:6]}")
        if learned is not None:
            sd = {
                k.removeprefix("learned."): v for k, v in state.items() if k.startswith("learned.")
            }
            learned.load_state_dict(sd, strict=True)
            learned = learned.to(model.device)
        rest = {k: v for k, v in meta.items() if k not in ("tensors",)}
        return cls(
            model,
            sensor,
            offset=state.get("offset.wrench"),
            inertial_bodies=tuple(bodies),
            delta=state.get("inertial.delta"),
            learned=learned,
            features=features,
            meta=rest,
            source=str(d.resolve()),
        )


def _check_robot(d: Path, meta: Mapping[str, Any], model: RobotModel) -> None:
    """Refuse a checkpoint trained for another robot, naming the first thing that differs.

    A checkpoint records its robot's identity (:attr:`RobotModel.identity`, the parsed model);
    one of an earlier version only the URDF text's hash, which must then match.
    """
    from torchcontact.identity import RobotIdentity

    recorded = meta.get("robot_identity")
    if recorded:
        try:
            why = RobotIdentity.from_json(recorded).difference(model.identity)
        except ValueError as e:
            raise CheckpointError(f"{d}: malformed robot_identity ({e})") from None
        if why is not None:
            raise CheckpointError(
                f"{d}: trained for robot {meta.get('robot')!r}, not this robot ({model.name}):"
                f" {why}"
            )
    elif meta.get("robot_sha256") != model.urdf_sha256:
        raise CheckpointError(
            f"{d}: trained for robot {meta.get('robot_sha256')} ({meta.get('robot')}), not"
            f" this robot ({model.urdf_sha256}, {model.name})"
        )


def _json_clean(x: Any) -> Any:
    """JSON-ready copy: numpy scalars and arrays to Python, NaN and inf to None."""
    if isinstance(x, dict):
        return {str(k): _json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _json_clean(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x
