"""Batched recursive Newton-Euler algorithm (RNEA): forward kinematics pass and inverse dynamics.

Formulation (Featherstone, *Rigid Body Dynamics Algorithms*, 2008, Sec. 5.3, in the "spatial
vectors at the base origin" form). Every twist, acceleration and wrench is expressed in the root
(base) frame, about the root's origin. Then the motion of a body is its parent's plus its own
joint's term, and the wrench a joint carries is the plain sum of the body wrenches of its subtree.
Only the poses need a product along the tree. The passes run one tree depth at a time (bodies are
numbered breadth-first, see :mod:`torchcontact.model`), batched over frames and over the bodies of
that depth:

1. joint transforms ``T_parent_body(q)`` for all bodies at once (Rodrigues' formula folded into
   constant matrices);
2. poses ``T_root_body`` by depth;
3. joint motion subspaces ``S`` in the root frame; twists ``v_i = v_parent + S_i qd_i`` and
   accelerations ``a_i = a_parent + S_i qdd_i + v_i x (S_i qd_i)`` by depth (Featherstone
   eq. 5.7-5.8);
4. body wrenches ``f_i = I_i a_i + v_i x* I_i v_i - f_ext_i`` (eq. 5.9) for all bodies at once;
5. subtree sums of ``f`` by depth, leaves first, and ``tau_i = S_i^T F_i`` (eq. 5.10-5.11).

Gravity enters as a fictitious upward acceleration of the root (``a_0 = -g``), so the
accelerations here are pinocchio's ``a_gf``. A moving base measured by an IMU enters the same way:
``v_0 = [0; omega]`` and ``a_0 = [proper acceleration; domega]`` (a Galilean shift of the base's
linear velocity changes no force, so the IMU's missing linear velocity is not needed).

All code is elementwise torch with constant indexing: differentiable, exportable with
``torch.onnx.export``, no Python branching on tensor values.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchcontact._internal import check_input, flatten_batch, in_tracing
from torchcontact.model import RobotModel

__all__ = [
    "BaseMotion",
    "ForwardPass",
    "body_wrenches",
    "compiled_inverse_dynamics",
    "forward_pass",
    "inverse_dynamics",
    "subtree_sum",
]


class BaseMotion(NamedTuple):
    """Motion of a moving base as an IMU on the root body measures it, all in the root frame.

    Attributes:
        omega: ``(*B, 3)`` angular velocity, rad/s.
        domega: ``(*B, 3)`` angular acceleration, rad/s^2.
        proper_acc: ``(*B, 3)`` proper linear acceleration of the root origin (what an
            accelerometer there reads: acceleration minus gravity), m/s^2. At rest on a table
            with z up it is ``(0, 0, +9.81)``.
    """

    omega: Tensor
    domega: Tensor
    proper_acc: Tensor


class ForwardPass(NamedTuple):
    """Kinematic quantities of every body, batched, in the root frame about the root origin.

    Attributes:
        R: ``(*B, nb, 3, 3)`` rotation ``R_root_body``.
        p: ``(*B, nb, 3)`` body origin in the root frame, m.
        v: ``(*B, nb, 6)`` spatial velocity ``[linear; angular]`` at the root origin, m/s, rad/s.
        a: ``(*B, nb, 6)`` spatial acceleration including the fictitious upward gravity
            (pinocchio's ``a_gf``), at the root origin, m/s^2, rad/s^2.
        S: ``(*B, nb, 6)`` joint motion subspace of each body's joint in the root frame (0 for the
            root and fixed joints).
    """

    R: Tensor
    p: Tensor
    v: Tensor
    a: Tensor
    S: Tensor


# Internally every per-frame quantity is stored batch-last, ``(bodies, features..., N)``, so that
# each elementwise op runs over long contiguous vectors of frames (SIMD-friendly, and what
# ``torch.compile`` turns into one vectorised loop). ``_bl`` marks these tensors.


def _cross_bl(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over dim -2 of batch-last vectors ``(..., 3, N)``."""
    a0, a1, a2 = a.unbind(-2)
    b0, b1, b2 = b.unbind(-2)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), dim=-2)


def _mv_bl(m: Tensor, v: Tensor) -> Tensor:
    """``m @ v``: batch-last ``m (..., r, c, N)`` or constant ``(..., r, c, 1)``, ``v (..., c, N)``.

    Written as a broadcast multiply-sum: for 3x3 blocks this beats batched GEMM on CPU and fuses
    under compilation.
    """
    return (m * v.unsqueeze(-3)).sum(-2)


def _levels_forward(model: RobotModel, first: Tensor, local: Tensor, step) -> Tensor:
    """Propagate a per-body quantity from the root down, one depth at a time.

    ``first`` is the root's value ``(1, ..., N)``; ``step(parent_value, local_slice)`` gives the
    bodies of one depth from their parents' values. Returns ``(nb, ..., N)``.
    """
    out = [first]
    prev = first
    for (s, e), parent in zip(model.levels[1:], model.level_parent, strict=True):
        prev = step(prev.index_select(0, parent), local[s:e])
        out.append(prev)
    return torch.cat(out, dim=0)


def _cumulate_down(model: RobotModel, root_value: Tensor, increments: Tensor) -> Tensor:
    """``x_i = x_parent + increment_i`` from the root down; ``root_value`` is ``(1, k, N)``."""
    return _levels_forward(model, root_value + increments[:1], increments, lambda p, inc: p + inc)


def subtree_sum(model: RobotModel, x: Tensor) -> Tensor:
    """Sum a per-body quantity over each body's subtree (itself included).

    Args:
        model: the robot.
        x: ``(nb, ...)`` per-body values, bodies first (any trailing shape).

    Returns:
        ``(nb, ...)`` with ``out[i] = sum of x[j]`` for ``j`` in the subtree of ``i``.
    """
    # Leaves first: each depth adds its accumulated values into the previous depth's parents.
    acc = x[model.levels[-1][0] : model.levels[-1][1]]
    parts = [acc]
    for d in range(len(model.levels) - 1, 0, -1):
        s, e = model.levels[d - 1]
        acc = x[s:e].index_add(0, model.level_parent[d - 1], acc)
        parts.append(acc)
    return torch.cat(parts[::-1], dim=0)


def _c(t: Tensor) -> Tensor:
    """A model constant ``(nb, ...)`` broadcast against batch-last tensors ``(nb, ..., N)``."""
    return t.unsqueeze(-1)


def forward_pass(
    model: RobotModel,
    q: Tensor,
    qd: Tensor,
    qdd: Tensor,
    gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -9.81),
    base: BaseMotion | None = None,
) -> ForwardPass:
    """Forward pass of the RNEA: poses, twists and accelerations of every body.

    Args:
        model: the robot.
        q: ``(*B, nv)`` joint positions in ``model.joint_names`` order, rad or m.
        qd: ``(*B, nv)`` joint velocities, rad/s or m/s.
        qdd: ``(*B, nv)`` joint accelerations, rad/s^2 or m/s^2.
        gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame, m/s^2 (fixed base only).
        base: IMU measurement of a moving base; when given, ``gravity`` is ignored (the proper
            acceleration already contains it).

    Returns:
        :class:`ForwardPass` with ``(*B, nb, ...)`` fields.

    Raises:
        ValueError: a wrong shape, dtype or device, or a NaN/inf input; the message names it.

    Example:
        >>> import io, torchcontact
        >>> urdf = io.StringIO(torchcontact.robots.pendulum_urdf())
        >>> model = torchcontact.RobotModel.from_urdf(urdf)
        >>> fp = forward_pass(model, *torch.zeros(3, 5, 1, dtype=torch.float64))  # B = (5,)
        >>> fp.R.shape, fp.v.shape
        (torch.Size([5, 2, 3, 3]), torch.Size([5, 2, 6]))
    """
    batch, (q, qd, qdd), base_bl = _prepare(model, q, qd, qdd, gravity, base)
    fp = _forward_bl(model, q, qd, qdd, *base_bl)
    # batch-last (nb, ..., N) -> (*B, nb, ...)
    return ForwardPass(*(t.movedim(-1, 0).reshape(*batch, *t.shape[:-1]) for t in fp))


def _prepare(model, q, qd, qdd, gravity, base):
    """Validate inputs; return batch shape, batch-last ``(nv, N)`` joint vectors, base terms."""
    nv = model.nv
    for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
        check_input(name, x, (nv,), model, f"(*B, {nv})")
    batch = q.shape[:-1]
    if qd.shape[:-1] != batch or qdd.shape[:-1] != batch:
        raise ValueError(
            f"q, qd, qdd must share their batch shape; got {tuple(q.shape)}, {tuple(qd.shape)},"
            f" {tuple(qdd.shape)}"
        )
    joints = [flatten_batch(x, batch, 1).T for x in (q, qd, qdd)]
    if base is None:
        base_bl = _gravity_base(model, gravity, batch, q)
    else:
        parts = []
        for name in ("omega", "domega", "proper_acc"):
            x = getattr(base, name)
            check_input(f"base.{name}", x, (3,), model, "(*B, 3)")
            if x.shape[:-1] != batch:
                raise ValueError(
                    f"base.{name} must be (*B, 3) with B={tuple(batch)}, got {tuple(x.shape)}"
                )
            parts.append(flatten_batch(x, batch, 1).T)
        base_bl = tuple(parts)
    return batch, joints, base_bl


def _gravity_base(model: RobotModel, gravity, batch: torch.Size, like: Tensor) -> tuple:
    """Fixed-base root motion, batch-last: ``(omega, domega, a_0) = (0, 0, -g)`` each ``(3, N)``."""
    n = math.prod(batch)
    g = gravity if isinstance(gravity, Tensor) else like.new_tensor(gravity)
    check_input("gravity", g, (3,), model, "(3,) or (*B, 3)")
    if g.dim() > 1 and g.shape[:-1] != batch:
        raise ValueError(
            f"gravity must be (3,) or (*B, 3) with B={tuple(batch)}, got {tuple(g.shape)}"
        )
    g = g.reshape(-1, 3).T.expand(3, n)
    zero = g.new_zeros(3, n)
    return zero, zero, -g


def _forward_bl(model: RobotModel, q, qd, qdd, omega0, domega0, acc0) -> ForwardPass:
    """Forward pass on batch-last inputs ``(nv, N)`` and ``(3, N)``; fields ``(nb, ..., N)``."""
    n = q.shape[-1]
    # 1. joint transforms T_parent_body(q) for every body at once
    qb = (model.q_to_body.T @ q + _c(model.q_offset)).unsqueeze(1)  # (nb, 1, N)
    s, c1 = qb.sin().unsqueeze(1), (1 - qb.cos()).unsqueeze(1)
    R_loc = _c(model.C0) + s * _c(model.C1) + c1 * _c(model.C2)  # (nb, 3, 3, N)
    p_loc = _c(model.p0) + qb * _c(model.prismatic_dir)  # (nb, 3, N)

    # 2. poses T_root_body, depth by depth, as [R | p] blocks (nb, 3, 4, N)
    pose_loc = torch.cat((R_loc, p_loc.unsqueeze(2)), dim=2)
    pose0 = torch.eye(3, 4, dtype=q.dtype, device=q.device).unsqueeze(-1).expand(1, 3, 4, n)

    def compose(parent: Tensor, loc: Tensor) -> Tensor:
        # [R_p | p_p] [R_l | p_l] = [R_p R_l | R_p p_l + p_p]
        prod = (parent[:, :, :3].unsqueeze(3) * loc.unsqueeze(1)).sum(2)
        return prod + torch.nn.functional.pad(parent[:, :, 3:], (0, 0, 3, 0))

    pose = _levels_forward(model, pose0, pose_loc, compose)
    R, p = pose[:, :, :3], pose[:, :, 3]
    # 3. motion subspaces in the root frame: revolute [p x a; a], prismatic [a; 0]
    a_w = _mv_bl(R, _c(model.axis))
    rev, pri = _c(model.is_revolute).unsqueeze(1), _c(model.is_prismatic).unsqueeze(1)
    S = torch.cat((rev * _cross_bl(p, a_w) + pri * a_w, rev * a_w), dim=1)  # (nb, 6, N)
    Sqd = S * (model.q_to_body.T @ qd).unsqueeze(1)
    Sqdd = S * (model.q_to_body.T @ qdd).unsqueeze(1)
    v0 = torch.cat((omega0.new_zeros(3, n), omega0), dim=0).unsqueeze(0)
    v = _cumulate_down(model, v0, Sqd)
    # Featherstone 5.8: a_i = a_parent + S qdd + v_i x S qd (spatial motion cross product)
    a0 = torch.cat((acc0, domega0), dim=0).unsqueeze(0)
    a = _cumulate_down(model, a0, Sqdd + _motion_cross_bl(v, Sqd))
    return ForwardPass(R, p, v, a, S)


def _motion_cross_bl(v: Tensor, m: Tensor) -> Tensor:
    """Spatial motion cross product ``v x m``, batch-last ``[linear; angular]`` ``(..., 6, N)``."""
    vl, w = v[..., :3, :], v[..., 3:, :]
    ml, mw = m[..., :3, :], m[..., 3:, :]
    return torch.cat((_cross_bl(w, ml) + _cross_bl(vl, mw), _cross_bl(w, mw)), dim=-2)


def _body_wrenches_bl(model: RobotModel, fp: ForwardPass) -> Tensor:
    """``I a + v x* I v`` per body, batch-last ``(nb, 6, N)``, root frame at the root origin."""
    R, p, v, a = fp.R, fp.p, fp.v, fp.a
    m = _c(model.mass).unsqueeze(1)
    c = p + _mv_bl(R, _c(model.com))  # centre of mass in the root frame
    # rotational inertia about the centre of mass in root axes: R I R^T
    RI = (R.unsqueeze(3) * _c(model.inertia_com).unsqueeze(1)).sum(2)
    Iw = (RI.unsqueeze(2) * R.unsqueeze(1)).sum(3)

    def apply_inertia(x: Tensor) -> tuple[Tensor, Tensor]:
        # spatial inertia at the root origin: h_lin = m (x_lin + w x c), h_ang = I_c w + c x h_lin
        lin, w = x[:, :3], x[:, 3:]
        h_lin = m * (lin + _cross_bl(w, c))
        return h_lin, _mv_bl(Iw, w) + _cross_bl(c, h_lin)

    f_lin, f_ang = apply_inertia(a)
    h_lin, h_ang = apply_inertia(v)
    vl, w = v[:, :3], v[:, 3:]
    # force cross product v x* h = [w x h_lin; w x h_ang + vl x h_lin]
    f_lin = f_lin + _cross_bl(w, h_lin)
    f_ang = f_ang + _cross_bl(w, h_ang) + _cross_bl(vl, h_lin)
    return torch.cat((f_lin, f_ang), dim=1)


def body_wrenches(model: RobotModel, fp: ForwardPass) -> Tensor:
    """Wrench each body needs for its motion, ``I a + v x* I v``, in the root frame at its origin.

    Args:
        model: the robot.
        fp: a :class:`ForwardPass` from :func:`forward_pass`, fields ``(*B, nb, ...)``.

    Returns:
        ``(*B, nb, 6)`` ``[force (N); moment about the root origin (N m)]``, gravity included
        (``fp.a`` contains the fictitious upward acceleration).
    """
    batch = fp.p.shape[:-2]
    bl = ForwardPass(*(flatten_batch(t, batch, t.dim() - len(batch)).movedim(0, -1) for t in fp))
    f = _body_wrenches_bl(model, bl)
    return f.movedim(-1, 0).reshape(*batch, model.nb, 6)


def _wrench_to_root_bl(fp: ForwardPass, f_body: Tensor) -> Tensor:
    """Body-frame wrenches ``(nb, 6, N)`` (moment about the body origin) to the root frame."""
    f = _mv_bl(fp.R, f_body[:, :3])
    return torch.cat((f, _mv_bl(fp.R, f_body[:, 3:]) + _cross_bl(fp.p, f)), dim=1)


def inverse_dynamics(
    model: RobotModel,
    q: Tensor,
    qd: Tensor,
    qdd: Tensor,
    gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -9.81),
    base: BaseMotion | None = None,
    f_ext: Tensor | None = None,
    chunk_size: int | None = 16384,
) -> Tensor:
    """Joint torques of the RNEA, ``tau = M(q) qdd + C(q, qd) qd + g(q) - J^T f_ext``.

    Args:
        model: the robot (fixed base, or moving base through ``base``).
        q: ``(*B, nv)`` joint positions in ``model.joint_names`` order, rad or m.
        qd: ``(*B, nv)`` joint velocities, rad/s or m/s.
        qdd: ``(*B, nv)`` joint accelerations, rad/s^2 or m/s^2.
        gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame, m/s^2 (fixed base).
        base: IMU measurement of a moving base (:class:`BaseMotion`); ``gravity`` is then unused.
        f_ext: ``(*B, nb, 6)`` external wrenches acting on each body (``model.body_names``
            order), ``[force (N); moment about the body origin (N m)]`` in the body frame, like
            pinocchio's ``rnea(..., fext)``.
        chunk_size: frames processed at once (keeps the working set in cache); None for one go.

    Returns:
        ``(*B, nv)`` joint torques (N m) or forces (N) in ``model.joint_names`` order.

    Raises:
        ValueError: a wrong shape, dtype or device, or a NaN/inf input; the message names it.

    Example:
        >>> import io, torchcontact
        >>> urdf = io.StringIO(torchcontact.robots.pendulum_urdf())
        >>> model = torchcontact.RobotModel.from_urdf(urdf)
        >>> q = torch.zeros(4, 1, dtype=torch.float64)  # (B, nv)
        >>> inverse_dynamics(model, q, q, q)  # a horizontal 1 kg rod of 1 m: tau = m g l / 2
        tensor([[4.9050],
                [4.9050],
                [4.9050],
                [4.9050]], dtype=torch.float64)
    """
    batch, (q, qd, qdd), base_bl = _prepare(model, q, qd, qdd, gravity, base)
    if f_ext is not None:
        check_input("f_ext", f_ext, (model.nb, 6), model, f"(*B, {model.nb}, 6)")
        if f_ext.shape[:-2] != batch:
            raise ValueError(
                f"f_ext must be (*B, {model.nb}, 6) with B={tuple(batch)}, got {tuple(f_ext.shape)}"
            )
        f_ext = flatten_batch(f_ext, batch, 2).permute(1, 2, 0)  # (nb, 6, N)
    n = q.shape[-1]
    if chunk_size is None or n <= chunk_size or in_tracing():
        tau = _inverse_dynamics_bl(model, q, qd, qdd, base_bl, f_ext)
    else:
        outs = []
        for s in range(0, n, chunk_size):
            sl = slice(s, s + chunk_size)
            outs.append(
                _inverse_dynamics_bl(
                    model, q[:, sl], qd[:, sl], qdd[:, sl], tuple(t[:, sl] for t in base_bl),
                    None if f_ext is None else f_ext[..., sl],
                )
            )  # fmt: skip
        tau = torch.cat(outs, dim=-1)
    return tau.T.reshape(*batch, model.nv)


def _inverse_dynamics_bl(model, q, qd, qdd, base_bl, f_ext) -> Tensor:
    """RNEA on batch-last inputs; returns ``(nv, N)``."""
    fp = _forward_bl(model, q, qd, qdd, *base_bl)
    f = _body_wrenches_bl(model, fp)
    if f_ext is not None:
        f = f - _wrench_to_root_bl(fp, f_ext)
    F = subtree_sum(model, f)
    tau_body = (fp.S * F).sum(1)  # (nb, N): S_i . F_i
    return model.q_to_body @ tau_body


def compiled_inverse_dynamics(model: RobotModel, chunk_size: int = 4096):
    """Inverse dynamics compiled with ``torch.compile`` for throughput on large batches.

    The core runs on fixed-size chunks of ``chunk_size`` frames (the last chunk is padded), so it
    compiles exactly once per model, dtype and device. Compilation happens on the first call and
    takes roughly 15-30 s on a 2-core CPU the first time; inductor caches the kernels on disk and
    later processes start in about 3 s. Results equal :func:`inverse_dynamics` to rounding.

    Args:
        model: the robot (fixed base; moving base through the ``base`` argument).
        chunk_size: frames per compiled call.

    Returns:
        A function ``(q, qd, qdd, gravity=..., base=None) -> tau`` with the signature and shapes
        of :func:`inverse_dynamics` (no ``f_ext``).
    """

    def core(q, qd, qdd, omega0, domega0, acc0):
        return _inverse_dynamics_bl(model, q, qd, qdd, (omega0, domega0, acc0), None)

    compiled = torch.compile(core, dynamic=False)

    def run(q, qd, qdd, gravity=(0.0, 0.0, -9.81), base=None):
        batch, joints, base_bl = _prepare(model, q, qd, qdd, gravity, base)
        n = joints[0].shape[-1]
        out = joints[0].new_empty(n, model.nv)
        for s in range(0, n, chunk_size):
            # one cache-sized chunk at a time, made contiguous batch-last; the last one padded
            e = min(n, s + chunk_size)
            ins = [x[:, s:e] for x in (*joints, *base_bl)]
            if e - s < chunk_size:
                ins = [torch.nn.functional.pad(x, (0, chunk_size - (e - s))) for x in ins]
            out[s:e] = compiled(*(x.contiguous() for x in ins))[:, : e - s].T
        return out.reshape(*batch, model.nv)

    return run
