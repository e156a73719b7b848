"""Batched recursive Newton-Euler algorithm (RNEA): the physics program and its public API.

Formulation (Featherstone, *Rigid Body Dynamics Algorithms*, 2008, Sec. 5.3; body-frame form, as
in pinocchio). Every twist, acceleration and wrench of body ``i`` is expressed in the body's own
frame about its origin. The tree is unrolled at trace time into straight-line code on scalars
(:mod:`torchcontact._scalar`), so the same source runs eagerly in torch and as a generated kernel
(:mod:`torchcontact.kernels`):

1. **joint placements** ``T_parent_i(q)``: each body frame is turned (by a constant rotation
   ``Q_i``, :class:`BodyConstants`) so that its joint axis is +z; then the joint rotation is a
   constant times ``Rz(q)`` and the motion subspace is ``S = e_6`` (revolute) or ``e_3``
   (prismatic), and the exact zeros and ones of the model fold away;
2. **forward pass**, kinematics (eq. 5.7-5.8) ``v_i = X_i v_parent + S qd_i``,
   ``a_i = X_i a_parent + S qdd_i + v_i x S qd_i``, and
3. body wrenches (eq. 5.9) ``f_i = I_i a_i + v_i x* I_i v_i`` (minus external wrenches), body by
   body in depth-first order;
4. **backward pass** (eq. 5.10-5.11): ``F_parent += X_i^* F_i``, ``tau_i = S^T F_i``, with mimic
   torques folded onto their leaders.

Gravity lives on the model (``model.gravity``) and enters as a fictitious upward acceleration of
the root, ``a_0 = -g``, so the accelerations are pinocchio's ``a_gf``. A moving base measured by an
IMU enters the same way: ``v_0 = [0; omega]`` and ``a_0 = [proper acceleration; domega]`` (a
Galilean shift of the base's linear velocity changes no force, so the IMU's missing linear
velocity is not needed).
"""

from __future__ import annotations

import hashlib
import weakref
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchcontact import kernels
from torchcontact import spatial as sp
from torchcontact._internal import check_input, flatten_batch
from torchcontact._scalar import Scalar, add, cos, mul, sin
from torchcontact.errors import InputError
from torchcontact.kernels.runner import run_program
from torchcontact.model import RobotModel

__all__ = [
    "BaseMotion",
    "BodyConstants",
    "ForwardPass",
    "Tree",
    "backward_pass",
    "body_wrenches",
    "compiled_inverse_dynamics",
    "forward_pass",
    "inverse_dynamics",
    "joint_placements",
    "body_wrench",
    "forward_step",
    "rnea_forward",
    "tree_of",
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


# ------------------------------------------------------------------------ constants of the program


@dataclass(frozen=True)
class BodyConstants:
    """Constants of one body in its *internal* frame (the link frame turned so the axis is +z).

    Attributes:
        parent: parent body index (-1 for the root).
        kind: ``"root"``, ``"revolute"``, ``"prismatic"`` or ``"fixed"``.
        coord: index of the joint coordinate driving the body (the leader for a mimic joint), -1.
        mult: mimic multiplier (1 otherwise): the body's joint angle is ``mult * q[coord] +
            offset``.
        offset: mimic offset, rad or m.
        C: rotation of the internal frame in the parent's internal frame at ``q = 0``.
        p: origin of the body in the parent's internal frame at ``q = 0``, m.
        Q: ``(3, 3)`` numpy rotation ``R_link_internal`` (its third column is the joint axis).
        mass: kg.
        com: centre of mass, internal frame, m.
        inertia: rotational inertia about the centre of mass, internal axes, kg m^2.
    """

    parent: int
    kind: str
    coord: int
    mult: float
    offset: float
    C: sp.M3
    p: sp.V3
    Q: np.ndarray
    mass: float
    com: sp.V3
    inertia: sp.M3


@dataclass(frozen=True, eq=False)
class Tree:
    """The robot as constants of the physics program (float64), derived once from a model.

    Attributes:
        bodies: per body, :class:`BodyConstants` (breadth-first order of the model: parents
            first).
        nv: number of joint coordinates.
        gravity: gravity in the root frame, m/s^2.
        order: body indices in depth-first preorder (parents first, one branch at a time): the
            order the passes visit bodies in, which keeps the generated code's live values few.
        key: hash of every constant (identifies generated kernels).
    """

    bodies: tuple[BodyConstants, ...]
    nv: int
    gravity: sp.V3
    order: tuple[int, ...]
    key: str


def _axis_frame(axis: np.ndarray) -> np.ndarray:
    """A rotation ``Q`` with ``Q e_z = axis``, as sparse as possible (signed permutations)."""
    a = axis / np.linalg.norm(axis)
    k = int(np.argmin(np.abs(a)))  # the coordinate axis least aligned with ``a``
    e = np.zeros(3)
    e[k] = 1.0
    x = e - (e @ a) * a
    x /= np.linalg.norm(x)
    y = np.cross(a, x)
    Q = np.stack([x, y, a], axis=1)
    return np.where(np.abs(Q) < 1e-15, 0.0, Q)


_TREES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def tree_of(model: RobotModel) -> Tree:
    """The :class:`Tree` of ``model`` (cached per model object).

    Built from the model's tensors, so a model edited with ``dataclasses.replace`` (new inertias,
    another gravity) gets its own constants and its own kernels.
    """
    tree = _TREES.get(model)
    if tree is None:
        tree = _build_tree(model)
        _TREES[model] = tree
    return tree


def _np(t: Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


def _build_tree(model: RobotModel) -> Tree:
    C0, p0, axis = _np(model.C0), _np(model.p0), _np(model.axis)
    mass, com, inertia = _np(model.mass), _np(model.com), _np(model.inertia_com)
    is_rev, is_pri = _np(model.is_revolute), _np(model.is_prismatic)
    q_to_body, q_offset = _np(model.q_to_body), _np(model.q_offset)
    bodies: list[BodyConstants] = []
    Qs: list[np.ndarray] = []
    for b in range(model.nb):
        parent = model.body_parent[b]
        if b == 0:
            kind = "root"
        elif is_rev[b]:
            kind = "revolute"
        elif is_pri[b]:
            kind = "prismatic"
        else:
            kind = "fixed"
        Q = _axis_frame(axis[b]) if kind in ("revolute", "prismatic") else np.eye(3)
        Qs.append(Q)
        coord, mult = -1, 1.0
        if kind in ("revolute", "prismatic"):
            nz = np.flatnonzero(q_to_body[:, b])
            coord, mult = int(nz[0]), float(q_to_body[nz[0], b])
        Qp = Qs[parent] if parent >= 0 else np.eye(3)
        C = Qp.T @ C0[b] @ Q if b else np.eye(3)
        p = Qp.T @ p0[b] if b else np.zeros(3)
        bodies.append(
            BodyConstants(
                parent=parent,
                kind=kind,
                coord=coord,
                mult=mult,
                offset=float(q_offset[b]),
                C=sp.const_mat(C),
                p=sp.const_vec(p),
                Q=Q,
                mass=float(mass[b]),
                com=sp.const_vec(Q.T @ com[b]),
                inertia=sp.const_mat(Q.T @ inertia[b] @ Q),
            )
        )
    gravity = sp.const_vec(_np(model.gravity))
    children: list[list[int]] = [[] for _ in bodies]
    for b, body in enumerate(bodies[1:], start=1):
        children[body.parent].append(b)
    order: list[int] = []
    stack = [0]
    while stack:
        b = stack.pop()
        order.append(b)
        stack.extend(reversed(children[b]))
    h = hashlib.sha256(repr((model.urdf_sha256, model.nv, bodies, gravity)).encode())
    return Tree(
        bodies=tuple(bodies),
        nv=model.nv,
        gravity=gravity,
        order=tuple(order),
        key=h.hexdigest()[:24],
    )


def internal_frame(tree: Tree, body: int, R_body_frame: np.ndarray, p_body_frame: np.ndarray):
    """A frame fixed on ``body`` (given in the body's link frame) in the body's internal frame."""
    Q = tree.bodies[body].Q
    return Q.T @ np.asarray(R_body_frame, float), Q.T @ np.asarray(p_body_frame, float)


# ------------------------------------------------------------------------------- physics program


def joint_placements(tree: Tree, q: list[Scalar]) -> list[sp.Pose | None]:
    """Stage 1: ``T_parent_i(q)`` of every body in internal frames (None for the root).

    Args:
        tree: the robot's constants.
        q: ``nv`` joint coordinates, rad or m.
    """
    X: list[sp.Pose | None] = [None]
    for body in tree.bodies[1:]:
        d = add(mul(body.mult, q[body.coord]), body.offset) if body.coord >= 0 else 0.0
        if body.kind == "revolute":
            X.append((sp.m_mul(body.C, sp.rot_z(cos(d), sin(d))), body.p))
        elif body.kind == "prismatic":
            axis = tuple(row[2] for row in body.C)
            X.append((body.C, sp.v_add(body.p, sp.v_scale(d, axis))))
        else:
            X.append((body.C, body.p))
    return X


def _joint_motion(body: BodyConstants, rate: Scalar) -> sp.Motion:
    """``S x`` for a joint rate or acceleration ``x`` (already multiplied for mimic joints)."""
    if body.kind == "revolute":
        return (sp.ZERO3, (0.0, 0.0, rate))
    if body.kind == "prismatic":
        return ((0.0, 0.0, rate), sp.ZERO3)
    return (sp.ZERO3, sp.ZERO3)


def root_motion(tree: Tree, base: dict[str, list[Scalar]] | None) -> tuple[sp.Motion, sp.Motion]:
    """Twist and acceleration of the root: ``(0, -g)`` on a fixed base, the IMU's otherwise."""
    if base is None:
        return (sp.ZERO3, sp.ZERO3), (sp.v_neg(tree.gravity), sp.ZERO3)
    return (sp.ZERO3, tuple(base["omega"])), (tuple(base["proper_acc"]), tuple(base["domega"]))


def forward_step(
    tree: Tree,
    i: int,
    X_i: sp.Pose,
    v_parent: sp.Motion,
    a_parent: sp.Motion,
    qd: list[Scalar],
    qdd: list[Scalar],
) -> tuple[sp.Motion, sp.Motion]:
    """Twist and acceleration of body ``i`` from its parent's (Featherstone eq. 5.7-5.8)."""
    body = tree.bodies[i]
    vJ = _joint_motion(body, mul(body.mult, qd[body.coord]) if body.coord >= 0 else 0.0)
    aJ = _joint_motion(body, mul(body.mult, qdd[body.coord]) if body.coord >= 0 else 0.0)
    vp = sp.motion_to_child(X_i, v_parent)
    ap = sp.motion_to_child(X_i, a_parent)
    vi = (sp.v_add(vp[0], vJ[0]), sp.v_add(vp[1], vJ[1]))
    vxs = sp.motion_cross_motion(vi, vJ)
    return vi, tuple(sp.v_add(sp.v_add(ap[k], aJ[k]), vxs[k]) for k in range(2))


def body_wrench(tree: Tree, i: int, v: sp.Motion, a: sp.Motion) -> sp.Force:
    """``I_i a_i + v_i x* I_i v_i`` (eq. 5.9), internal frame of body ``i``, about its origin."""
    b = tree.bodies[i]
    if b.mass == 0.0 and all(x == 0.0 for row in b.inertia for x in row):
        return (sp.ZERO3, sp.ZERO3)
    Ia = sp.inertia_apply(b.mass, b.com, b.inertia, a)
    Iv = sp.inertia_apply(b.mass, b.com, b.inertia, v)
    vxIv = sp.motion_cross_force(v, Iv)
    return sp.v_add(Ia[0], vxIv[0]), sp.v_add(Ia[1], vxIv[1])


def rnea_forward(
    tree: Tree,
    X: list[sp.Pose | None],
    qd: list[Scalar],
    qdd: list[Scalar],
    root: tuple[sp.Motion, sp.Motion],
    wrenches: bool = True,
) -> tuple[list[sp.Motion], list[sp.Motion], list[sp.Force | None]]:
    """Stages 2-3, the forward pass: twists, accelerations and body wrenches of every body.

    Bodies are visited depth-first; each body's wrench is formed as soon as its motion is known,
    which keeps few values alive in generated code.

    Args:
        tree: the robot's constants.
        X: joint placements from :func:`joint_placements`.
        qd: ``nv`` joint velocities.
        qdd: ``nv`` joint accelerations.
        root: the root's twist and acceleration (:func:`root_motion`).
        wrenches: also compute the body wrenches (else ``f`` is all None).

    Returns:
        ``v, a, f`` per body (model order), internal frames about the body origins; ``a``
        includes gravity.
    """
    nb = len(tree.bodies)
    v: list = [None] * nb
    a: list = [None] * nb
    f: list = [None] * nb
    v[0], a[0] = root
    for i in tree.order:
        if i:
            p = tree.bodies[i].parent
            v[i], a[i] = forward_step(tree, i, X[i], v[p], a[p], qd, qdd)
        if wrenches:
            f[i] = body_wrench(tree, i, v[i], a[i])
    return v, a, f


def backward_pass(
    tree: Tree,
    X: list[sp.Pose | None],
    f: list[sp.Force | None],
    transmitted: dict[int, sp.Force] | None = None,
) -> tuple[list[sp.Force], list[Scalar]]:
    """Stage 4: wrench each joint transmits, ``F_i = f_i + sum_children X^* F_c``, and torques.

    Args:
        tree: the robot's constants.
        X: joint placements from :func:`joint_placements`.
        f: per body, the net wrench it needs (body wrench minus external wrenches).
        transmitted: body -> the wrench its parent joint transmits, when known (an F/T sensor's
            reading in the body's internal frame): it replaces the computed sum for the
            parent side, so joints nearer the root see the measurement (Del Prete et al. 2012,
            Sec. 2.3).

    Returns:
        ``F``: per body, the wrench its parent side exerts on its subtree (internal frame, body
        origin); ``tau``: ``nv`` joint torques (N m or N), mimic torques folded onto leaders.
    """
    nb = len(tree.bodies)
    F: list[sp.Force] = [f[i] if f[i] is not None else (sp.ZERO3, sp.ZERO3) for i in range(nb)]
    children: list[list[sp.Force]] = [[] for _ in range(nb)]
    for i in reversed(tree.order[1:]):  # children before parents
        Fi = sp.add_forces([F[i], *children[i]]) if children[i] else F[i]
        F[i] = Fi
        up = transmitted[i] if transmitted and i in transmitted else Fi
        children[tree.bodies[i].parent].append(sp.force_to_parent(X[i], up))
    if children[0]:
        F[0] = sp.add_forces([F[0], *children[0]])
    tau: list[Scalar] = [0.0] * tree.nv
    for i, body in enumerate(tree.bodies):
        if body.kind == "revolute":
            t = F[i][1][2]
        elif body.kind == "prismatic":
            t = F[i][0][2]
        else:
            continue
        tau[body.coord] = add(tau[body.coord], mul(body.mult, t))
    return F, tau


def poses(tree: Tree, X: list[sp.Pose | None]) -> list[sp.Pose]:
    """``T_root_i`` of every body, internal frames, composed along the tree."""
    T: list[sp.Pose] = [(sp.EYE3, sp.ZERO3)]
    for i, body in enumerate(tree.bodies[1:], start=1):
        T.append(sp.pose_compose(T[body.parent], X[i]))
    return T


# ---------------------------------------------------------------------------------- programs


def _sub_force(f: sp.Force, g: sp.Force) -> sp.Force:
    return sp.v_sub(f[0], g[0]), sp.v_sub(f[1], g[1])


def _id_program(model: RobotModel, moving_base: bool, with_fext: bool) -> kernels.Program:
    tree = tree_of(model)
    inputs = {"q": tree.nv, "qd": tree.nv, "qdd": tree.nv}
    if moving_base:
        inputs.update(omega=3, domega=3, proper_acc=3)
    if with_fext:
        inputs["f_ext"] = 6 * len(tree.bodies)

    def fn(x: dict[str, list]) -> dict[str, list]:
        X = joint_placements(tree, x["q"])
        base = {k: x[k] for k in ("omega", "domega", "proper_acc")} if moving_base else None
        v, a, f = rnea_forward(tree, X, x["qd"], x["qdd"], root_motion(tree, base))
        if with_fext:
            fe = x["f_ext"]
            for i, body in enumerate(tree.bodies):  # link frame -> internal frame (same origin)
                w = [fe[6 * i + k] for k in range(6)]
                ext = (tuple(sp.cmat_vec(body.Q.T, w[:3])), tuple(sp.cmat_vec(body.Q.T, w[3:])))
                f[i] = _sub_force(f[i], ext)
        _, tau = backward_pass(tree, X, f)
        return {"tau": tau}

    key = f"id|{tree.key}|{moving_base}|{with_fext}"
    return kernels.Program("rnea", fn, inputs, {"tau": tree.nv}, key)


def _fp_program(model: RobotModel, moving_base: bool) -> kernels.Program:
    tree = tree_of(model)
    nb = len(tree.bodies)
    inputs = {"q": tree.nv, "qd": tree.nv, "qdd": tree.nv}
    if moving_base:
        inputs.update(omega=3, domega=3, proper_acc=3)

    def fn(x: dict[str, list]) -> dict[str, list]:
        X = joint_placements(tree, x["q"])
        base = {k: x[k] for k in ("omega", "domega", "proper_acc")} if moving_base else None
        v, a, _ = rnea_forward(tree, X, x["qd"], x["qdd"], root_motion(tree, base), False)
        T = poses(tree, X)
        out: dict[str, list] = {"R": [], "p": [], "v": [], "a": [], "S": []}
        for i, body in enumerate(tree.bodies):
            R, p = T[i]
            # internal frame -> link frame: R_root_link = R_root_internal Q^T
            out["R"] += [x for row in R for x in sp.cmat_vec(body.Q, row)]
            out["p"] += list(p)
            for name, m in (("v", v[i]), ("a", a[i]), ("S", _joint_motion(body, 1.0))):
                lin, ang = sp.motion_to_parent(T[i], m)
                out[name] += [*lin, *ang]
        return out

    key = f"fp|{tree.key}|{moving_base}"
    outs = {"R": 9 * nb, "p": 3 * nb, "v": 6 * nb, "a": 6 * nb, "S": 6 * nb}
    return kernels.Program("fpass", fn, inputs, outs, key)


_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def program(model: RobotModel, name: str, *flags) -> kernels.Program:
    """The cached program ``name`` (``"id"``, ``"fp"``) of a model."""
    cache = _PROGRAMS.setdefault(model, {})
    key = (name, *flags)
    if key not in cache:
        cache[key] = {"id": _id_program, "fp": _fp_program}[name](model, *flags)
    return cache[key]


# ------------------------------------------------------------------------------------ public API


def _prepare(model: RobotModel, q: Tensor, qd: Tensor, qdd: Tensor, base: BaseMotion | None):
    """Validate; return the batch shape and ``(N, k)`` input tensors of the programs."""
    nv = model.nv
    for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
        check_input(name, x, (nv,), model, f"(*B, {nv})")
    batch = q.shape[:-1]
    if qd.shape[:-1] != batch or qdd.shape[:-1] != batch:
        raise InputError(
            f"q, qd, qdd must share their batch shape; got {tuple(q.shape)}, {tuple(qd.shape)},"
            f" {tuple(qdd.shape)}"
        )
    tensors = {k: flatten_batch(x, batch, 1) for k, x in (("q", q), ("qd", qd), ("qdd", qdd))}
    if base is not None:
        for name in ("omega", "domega", "proper_acc"):
            x = getattr(base, name)
            check_input(f"base.{name}", x, (3,), model, "(*B, 3)")
            if x.shape[:-1] != batch:
                raise InputError(
                    f"base.{name} must be (*B, 3) with B={tuple(batch)}, got {tuple(x.shape)}"
                )
            tensors[name] = flatten_batch(x, batch, 1)
    return batch, tensors


def forward_pass(
    model: RobotModel,
    q: Tensor,
    qd: Tensor,
    qdd: Tensor,
    base: BaseMotion | None = None,
    backend: str = "eager",
) -> ForwardPass:
    """Forward pass of the RNEA: poses, twists and accelerations of every body, root frame.

    Args:
        model: the robot.
        q: ``(*B, nv)`` joint positions in ``model.joint_names`` order, rad or m.
        qd: ``(*B, nv)`` joint velocities, rad/s or m/s.
        qdd: ``(*B, nv)`` joint accelerations, rad/s^2 or m/s^2.
        base: IMU measurement of a moving base; when given, ``model.gravity`` is not used (the
            proper acceleration already contains it).
        backend: ``"eager"`` (default), ``"auto"``, ``"cpu"`` or ``"cuda"``
            (:mod:`torchcontact.kernels`).

    Returns:
        :class:`ForwardPass` with ``(*B, nb, ...)`` fields.

    Raises:
        InputError: a wrong shape, dtype or device, or a NaN/inf input; the message names it.

    Example:
        >>> import io, torchcontact
        >>> urdf = io.StringIO(torchcontact.robots.pendulum_urdf())
        >>> model = torchcontact.RobotModel.from_urdf(urdf)
        >>> fp = forward_pass(model, *torch.zeros(3, 5, 1, dtype=torch.float64))  # B = (5,)
        >>> fp.R.shape, fp.v.shape
        (torch.Size([5, 2, 3, 3]), torch.Size([5, 2, 6]))
    """
    batch, tensors = _prepare(model, q, qd, qdd, base)
    tree_of(model)
    out = run_program(program(model, "fp", base is not None), tensors, backend, 16384)
    nb = model.nb
    return ForwardPass(
        out["R"].reshape(*batch, nb, 3, 3),
        out["p"].reshape(*batch, nb, 3),
        out["v"].reshape(*batch, nb, 6),
        out["a"].reshape(*batch, nb, 6),
        out["S"].reshape(*batch, nb, 6),
    )


def body_wrenches(model: RobotModel, fp: ForwardPass) -> Tensor:
    """Wrench each body needs for its motion, ``I a + v x* I v``, in the root frame at its origin.

    Args:
        model: the robot.
        fp: a :class:`ForwardPass` from :func:`forward_pass`, fields ``(*B, nb, ...)``.

    Returns:
        ``(*B, nb, 6)`` ``[force (N); moment about the root origin (N m)]``, gravity included
        (``fp.a`` contains the fictitious upward acceleration).
    """
    R, p = fp.R, fp.p
    nb = model.nb
    mass, com, inertia = model.mass, model.com, model.inertia_com
    out = []
    for i in range(nb):
        T = (sp._unbind33(R[..., i, :, :]), sp._unbind3(p[..., i, :]))
        v = sp.motion_to_child(T, (sp._unbind3(fp.v[..., i, :3]), sp._unbind3(fp.v[..., i, 3:])))
        a = sp.motion_to_child(T, (sp._unbind3(fp.a[..., i, :3]), sp._unbind3(fp.a[..., i, 3:])))
        c, Ic = sp._unbind3(com[i]), sp._unbind33(inertia[i])
        Ia = sp.inertia_apply(mass[i], c, Ic, a)
        Iv = sp.inertia_apply(mass[i], c, Ic, v)
        vxIv = sp.motion_cross_force(v, Iv)
        f = (sp.v_add(Ia[0], vxIv[0]), sp.v_add(Ia[1], vxIv[1]))
        out.append(sp._stack6(sp.force_to_parent(T, f), p[..., i, 0]))
    return torch.stack(out, -2)


def inverse_dynamics(
    model: RobotModel,
    q: Tensor,
    qd: Tensor,
    qdd: Tensor,
    base: BaseMotion | None = None,
    f_ext: Tensor | None = None,
    backend: str = "auto",
    chunk_size: int | None = 16384,
) -> Tensor:
    """Joint torques of the RNEA, ``tau = M(q) qdd + C(q, qd) qd + g(q) - J^T f_ext``.

    Args:
        model: the robot (fixed base with ``model.gravity``, or moving base through ``base``).
        q: ``(*B, nv)`` joint positions in ``model.joint_names`` order, rad or m.
        qd: ``(*B, nv)`` joint velocities, rad/s or m/s.
        qdd: ``(*B, nv)`` joint accelerations, rad/s^2 or m/s^2.
        base: IMU measurement of a moving base (:class:`BaseMotion`); gravity is then unused.
        f_ext: ``(*B, nb, 6)`` external wrenches acting on each body (``model.body_names``
            order), ``[force (N); moment about the body origin (N m)]`` in the body frame, like
            pinocchio's ``rnea(..., fext)``.
        backend: ``"auto"`` (a generated kernel when built, else eager torch while it builds in
            the background), ``"eager"`` (differentiable), ``"cpu"`` or ``"cuda"`` (build the
            kernel now), see :mod:`torchcontact.kernels`. Inputs that require grad always run
            eagerly under ``"auto"``.
        chunk_size: frames per eager call (keeps the working set in cache); None for one go.

    Returns:
        ``(*B, nv)`` joint torques (N m) or forces (N) in ``model.joint_names`` order.

    Raises:
        InputError: a wrong shape, dtype or device, or a NaN/inf input; the message names it.

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
    batch, tensors = _prepare(model, q, qd, qdd, base)
    if f_ext is not None:
        check_input("f_ext", f_ext, (model.nb, 6), model, f"(*B, {model.nb}, 6)")
        if f_ext.shape[:-2] != batch:
            raise InputError(
                f"f_ext must be (*B, {model.nb}, 6) with B={tuple(batch)}, got {tuple(f_ext.shape)}"
            )
        tensors["f_ext"] = flatten_batch(f_ext, batch, 2).reshape(-1, 6 * model.nb)
    prog = program(model, "id", base is not None, f_ext is not None)
    out = run_program(prog, tensors, backend, chunk_size)
    return out["tau"].reshape(*batch, model.nv)


def compiled_inverse_dynamics(model: RobotModel, chunk_size: int | None = None):
    """Inverse dynamics through the generated CPU (or CUDA) kernel, built now.

    Kept for code written against earlier versions; ``inverse_dynamics(..., backend="cpu")`` is
    the same. The kernel is built once per model and dtype (a few seconds; cached on disk).

    Args:
        model: the robot.
        chunk_size: ignored (the kernel streams any batch).

    Returns:
        A function ``(q, qd, qdd, base=None) -> tau`` with the shapes of
        :func:`inverse_dynamics`.
    """
    del chunk_size
    backend = "cuda" if model.device.type == "cuda" else "cpu"

    def run(q: Tensor, qd: Tensor, qdd: Tensor, base: BaseMotion | None = None) -> Tensor:
        return inverse_dynamics(model, q, qd, qdd, base=base, backend=backend)

    return run
