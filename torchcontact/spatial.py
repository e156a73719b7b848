"""Spatial algebra: the one module for rotations, poses, twists, wrenches and inertias.

Conventions (stated once, used everywhere in torchcontact):

* a **twist** (spatial motion vector) is ``[linear; angular]``, shape ``(..., 6)``;
* a **wrench** (spatial force vector) is ``[force; moment]``, shape ``(..., 6)``;
* a pose ``T_a_b`` is a rotation ``R_a_b`` ``(..., 3, 3)`` and a translation ``p_a_b`` ``(..., 3)``
  such that a point ``x_b`` in frame ``b`` is ``x_a = R_a_b @ x_b + p_a_b`` in frame ``a``;
* quaternions appear only at input/output boundaries and are named ``quat_wxyz``.

The module has three layers, each operation written once:

1. **Scalar layer** (the physics program, :mod:`torchcontact._scalar`): 3-vectors ``V3`` are
   tuples of 3 scalars, rotations ``M3`` tuples of 3 rows, twists and wrenches pairs of ``V3``.
   A scalar is a constant, a ``(N,)`` tensor or a traced symbol, so the same code runs eagerly in
   torch and is compiled into kernels (Featherstone, *Rigid Body Dynamics Algorithms*, 2008,
   Ch. 2: motion and force transforms, cross products, spatial inertia).
2. **Tensor layer**: the same operations on batched tensors with trailing ``(3,)``, ``(6,)``,
   ``(3, 3)`` dimensions (any leading batch), for user code, tests and tools.
3. **Inertia constants** (numpy, float64): the parallel-axis theorem and the combination of rigid
   bodies, for building and editing robot models.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from torchcontact._scalar import Scalar, add, lincomb, mul, neg, sub, sum_

__all__ = [
    "combine_inertias",
    "cross",
    "inertia_about",
    "matvec",
    "rpy_to_matrix",
    "skew",
    "transform_wrench",
    "transform_wrench_inverse",
    "twist_in_frame",
]

V3 = tuple  # (x, y, z) scalars
M3 = tuple  # three rows of three scalars
Motion = tuple  # (linear V3, angular V3)
Force = tuple  # (force V3, moment V3)
Pose = tuple  # (R M3, p V3): T_a_b

ZERO3: V3 = (0.0, 0.0, 0.0)
EYE3: M3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

# ----------------------------------------------------------------------------------- scalar layer


def v_add(a: V3, b: V3) -> V3:
    """``a + b``."""
    return (add(a[0], b[0]), add(a[1], b[1]), add(a[2], b[2]))


def v_sub(a: V3, b: V3) -> V3:
    """``a - b``."""
    return (sub(a[0], b[0]), sub(a[1], b[1]), sub(a[2], b[2]))


def v_neg(a: V3) -> V3:
    """``-a``."""
    return (neg(a[0]), neg(a[1]), neg(a[2]))


def v_scale(s: Scalar, a: V3) -> V3:
    """``s a``."""
    return (mul(s, a[0]), mul(s, a[1]), mul(s, a[2]))


def v_dot(a: V3, b: V3) -> Scalar:
    """``a . b``."""
    return sum_([mul(a[0], b[0]), mul(a[1], b[1]), mul(a[2], b[2])])


def v_cross(a: V3, b: V3) -> V3:
    """``a x b``."""
    return (
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    )


def v_sum(vs: Sequence[V3]) -> V3:
    """Sum of 3-vectors."""
    return tuple(sum_([v[i] for v in vs]) for i in range(3))


def m_vec(R: M3, v: V3) -> V3:
    """``R v``."""
    return tuple(sum_([mul(R[i][j], v[j]) for j in range(3)]) for i in range(3))


def mT_vec(R: M3, v: V3) -> V3:  # noqa: N802 - R^T
    """``R^T v``."""
    return tuple(sum_([mul(R[j][i], v[j]) for j in range(3)]) for i in range(3))


def m_mul(A: M3, B: M3) -> M3:
    """``A B``."""
    return tuple(
        tuple(sum_([mul(A[i][k], B[k][j]) for k in range(3)]) for j in range(3)) for i in range(3)
    )


def mT_mul(A: M3, B: M3) -> M3:  # noqa: N802 - A^T B
    """``A^T B``."""
    return tuple(
        tuple(sum_([mul(A[k][i], B[k][j]) for k in range(3)]) for j in range(3)) for i in range(3)
    )


def m_T(A: M3) -> M3:  # noqa: N802
    """``A^T``."""
    return tuple(tuple(A[j][i] for j in range(3)) for i in range(3))


def const_vec(x: np.ndarray, tol: float = 1e-14) -> V3:
    """A constant 3-vector, with entries within ``tol`` of 0 or +-1 snapped to them exactly.

    Snapping turns the rounding noise of URDF angles such as ``pi/2`` (``cos = 6e-17``) into the
    structural zeros the physics program folds away; it changes the model by < 1e-14.
    """
    return tuple(_snap(float(v), tol) for v in np.asarray(x, float).reshape(3))


def const_mat(x: np.ndarray, tol: float = 1e-14) -> M3:
    """A constant 3x3 matrix, snapped like :func:`const_vec`."""
    x = np.asarray(x, float).reshape(3, 3)
    return tuple(tuple(_snap(float(v), tol) for v in row) for row in x)


def _snap(v: float, tol: float) -> float:
    if abs(v) < tol:
        return 0.0
    if abs(abs(v) - 1.0) < tol:
        return 1.0 if v > 0 else -1.0
    return v


def cmat_vec(C: np.ndarray, v: Sequence[Scalar]) -> list[Scalar]:
    """``C v`` for a constant matrix ``C (r, c)`` (numpy) and ``c`` scalars: zeros skipped."""
    return [lincomb(row, v) for row in np.asarray(C, float)]


def rot_z(c: Scalar, s: Scalar) -> M3:
    """Rotation about z by the angle with cosine ``c`` and sine ``s``."""
    return ((c, neg(s), 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))


def pose_compose(T_a_b: Pose, T_b_c: Pose) -> Pose:
    """``T_a_c = T_a_b T_b_c``."""
    R_ab, p_ab = T_a_b
    R_bc, p_bc = T_b_c
    return m_mul(R_ab, R_bc), v_add(m_vec(R_ab, p_bc), p_ab)


def pose_inverse(T_a_b: Pose) -> Pose:
    """``T_b_a``."""
    R, p = T_a_b
    return m_T(R), v_neg(mT_vec(R, p))


def pose_apply(T_a_b: Pose, x_b: V3) -> V3:
    """A point given in ``b`` expressed in ``a``."""
    return v_add(m_vec(T_a_b[0], x_b), T_a_b[1])


def motion_to_child(T_parent_child: Pose, v: Motion) -> Motion:
    """A twist in the parent frame (at its origin) expressed in the child frame (at its origin)."""
    R, p = T_parent_child
    lin, ang = v
    return mT_vec(R, v_add(lin, v_cross(ang, p))), mT_vec(R, ang)


def motion_to_parent(T_parent_child: Pose, v: Motion) -> Motion:
    """A twist in the child frame expressed in the parent frame (inverse of the above)."""
    R, p = T_parent_child
    ang = m_vec(R, v[1])
    return v_add(m_vec(R, v[0]), v_cross(p, ang)), ang


def force_to_parent(T_parent_child: Pose, f: Force) -> Force:
    """A wrench in the child frame (moment about its origin) expressed in the parent frame."""
    R, p = T_parent_child
    force = m_vec(R, f[0])
    return force, v_add(m_vec(R, f[1]), v_cross(p, force))


def force_to_child(T_parent_child: Pose, f: Force) -> Force:
    """A wrench in the parent frame expressed in the child frame (inverse of the above)."""
    R, p = T_parent_child
    force, moment = f
    return mT_vec(R, force), mT_vec(R, v_sub(moment, v_cross(p, force)))


def motion_cross_motion(v: Motion, m: Motion) -> Motion:
    """Spatial cross product ``v x m`` of twists (Featherstone eq. 2.31)."""
    vl, w = v
    ml, mw = m
    return v_add(v_cross(w, ml), v_cross(vl, mw)), v_cross(w, mw)


def motion_cross_force(v: Motion, f: Force) -> Force:
    """Spatial cross product ``v x* f`` of a twist and a wrench (Featherstone eq. 2.32)."""
    vl, w = v
    fl, fn = f
    return v_cross(w, fl), v_add(v_cross(w, fn), v_cross(vl, fl))


def inertia_apply(mass: float, com: V3, inertia_com: M3, v: Motion) -> Force:
    """Spatial inertia times a twist, about the frame's origin: ``[m (v + w x c); I_c w + c x h]``.

    Args:
        mass: kg.
        com: centre of mass in the frame, m.
        inertia_com: rotational inertia about the centre of mass, frame axes, kg m^2.
        v: twist (or acceleration) at the frame's origin.
    """
    lin, w = v
    h = v_scale(mass, v_add(lin, v_cross(w, com)))
    return h, v_add(m_vec(inertia_com, w), v_cross(com, h))


def inertia_apply_origin(mass: Scalar, h: V3, inertia_origin: M3, v: Motion) -> Force:
    """Spatial inertia about the frame's origin times a twist: ``[m v - h x w; I_o w + h x v]``.

    The form in which the wrench is linear in the ten inertial parameters (Atkeson, An and
    Hollerbach 1986), so the parameters may be traced inputs and need not be physical (a
    parameter *change*, whose mass may be zero or negative, has no centre of mass).

    Args:
        mass: kg.
        h: first moment of mass ``m c`` in the frame, kg m.
        inertia_origin: rotational inertia about the frame's origin, frame axes, kg m^2.
        v: twist (or acceleration) at the frame's origin.
    """
    lin, w = v
    return (
        v_sub(v_scale(mass, lin), v_cross(h, w)),
        v_add(m_vec(inertia_origin, w), v_cross(h, lin)),
    )


def body_wrench_params(mass: Scalar, h: V3, inertia_origin: M3, v: Motion, a: Motion) -> Force:
    """``I a + v x* I v`` (Featherstone eq. 5.9) with ``I`` in parameter form (see above)."""
    Ia = inertia_apply_origin(mass, h, inertia_origin, a)
    vxIv = motion_cross_force(v, inertia_apply_origin(mass, h, inertia_origin, v))
    return v_add(Ia[0], vxIv[0]), v_add(Ia[1], vxIv[1])


#: ``(row, column)`` of the rotational inertia's six parameters ``I_xx, I_xy, I_yy, I_xz, I_yz,
#: I_zz`` (the order of :data:`torchcontact.online.payload.PARAM_NAMES` after ``m, m c``).
INERTIA_PARAM_ENTRIES = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2))


def body_wrench_link_params(Q: np.ndarray, theta: Sequence[Scalar], v: Motion, a: Motion) -> Force:
    """:func:`body_wrench_params` of ten parameters given in another frame of the body.

    The parameters ``theta = [m, m c (3), I_xx, I_xy, I_yy, I_xz, I_yz, I_zz]`` (about the
    body origin) are in the link frame, the motion and the wrench in the body's internal frame,
    which is the link frame turned by ``Q = R_link_internal``: ``h = Q^T (m c)``,
    ``I = Q^T I_link Q``. Linear in ``theta`` (the sensor regressor's columns are its unit
    vectors).

    Args:
        Q: ``(3, 3)`` constant rotation ``R_link_internal``.
        theta: ten scalars (constants or traced symbols).
        v: twist of the body, internal frame.
        a: its acceleration.
    """
    Q = np.asarray(Q, dtype=float)
    h = tuple(cmat_vec(Q.T, theta[1:4]))
    rows = []
    for r in range(3):
        row = []
        for c in range(3):
            # (Q^T I Q)[r, c] = sum_ij Q[i, r] Q[j, c] I[i, j], I symmetric from 6 parameters
            coeffs = [Q[i, r] * Q[j, c] + (Q[j, r] * Q[i, c] if i != j else 0.0)
                      for i, j in INERTIA_PARAM_ENTRIES]  # fmt: skip
            row.append(lincomb(coeffs, theta[4:10]))
        rows.append(tuple(row))
    return body_wrench_params(theta[0], h, tuple(rows), v, a)


def add_forces(fs: Sequence[Force]) -> Force:
    """Sum of wrenches."""
    return v_sum([f[0] for f in fs]), v_sum([f[1] for f in fs])


# ----------------------------------------------------------------------------------- tensor layer


def _unbind3(x: Tensor) -> V3:
    return tuple(x.unbind(-1))


def _unbind33(x: Tensor) -> M3:
    return tuple(tuple(r.unbind(-1)) for r in x.unbind(-2))


def _stack3(v: V3, like: Tensor) -> Tensor:
    return torch.stack([c if isinstance(c, Tensor) else like.new_full((), c).expand_as(like)
                        for c in v], -1)  # fmt: skip


def cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over the last dimension, broadcasting the leading ones.

    Args:
        a: ``(..., 3)``.
        b: ``(..., 3)``.

    Returns:
        ``a x b``, ``(..., 3)``.

    Example:
        >>> cross(torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]))
        tensor([0., 0., 1.])
    """
    a, b = torch.broadcast_tensors(a, b)
    return _stack3(v_cross(_unbind3(a), _unbind3(b)), a[..., 0])


def matvec(m: Tensor, v: Tensor) -> Tensor:
    """Batched matrix-vector product ``m @ v`` written as a broadcast multiply-sum.

    Args:
        m: ``(..., r, c)``.
        v: ``(..., c)``.

    Returns:
        ``(..., r)``.

    Example:
        >>> matvec(torch.eye(3) * 2, torch.tensor([1.0, 2, 3]))
        tensor([2., 4., 6.])
    """
    return (m * v.unsqueeze(-2)).sum(-1)


def skew(v: Tensor) -> Tensor:
    """Skew-symmetric matrix ``[v]x`` with ``skew(v) @ w == cross(v, w)``.

    Args:
        v: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)``.

    Example:
        >>> skew(torch.tensor([0.0, 0, 1]))
        tensor([[ 0., -1.,  0.],
                [ 1.,  0., -0.],
                [-0.,  0.,  0.]])
    """
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        (
            torch.stack((zero, -z, y), -1),
            torch.stack((z, zero, -x), -1),
            torch.stack((-y, x, zero), -1),
        ),
        dim=-2,
    )


def rpy_to_matrix(rpy: Tensor) -> Tensor:
    """Rotation matrix of URDF roll-pitch-yaw angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Args:
        rpy: ``(..., 3)`` roll, pitch, yaw in rad (fixed axes x, y, z, as in URDF ``<origin>``).

    Returns:
        ``(..., 3, 3)`` rotation matrix.

    Example:
        >>> R = rpy_to_matrix(torch.tensor([0.0, 0.0, torch.pi / 2]))  # yaw 90 deg: x -> y
        >>> torch.allclose(R @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]), atol=1e-7)
        True
    """
    r, p, y = rpy.unbind(-1)
    cr, sr, cp, sp, cy, sy = r.cos(), r.sin(), p.cos(), p.sin(), y.cos(), y.sin()
    return torch.stack(
        (
            torch.stack((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr), -1),
            torch.stack((sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr), -1),
            torch.stack((-sp, cp * sr, cp * cr), -1),
        ),
        dim=-2,
    )


def _pose_args(R: Tensor, p: Tensor, x: Tensor) -> tuple[Pose, Motion, Tensor]:
    batch = torch.broadcast_shapes(R.shape[:-2], p.shape[:-1], x.shape[:-1])
    R = R.expand(*batch, 3, 3)
    p = p.expand(*batch, 3)
    x = x.expand(*batch, 6)
    T = (_unbind33(R), _unbind3(p))
    return T, (_unbind3(x[..., :3]), _unbind3(x[..., 3:])), x[..., 0]


def _stack6(v: Motion, like: Tensor) -> Tensor:
    return torch.cat((_stack3(v[0], like), _stack3(v[1], like)), -1)


def twist_in_frame(R_a_b: Tensor, p_a_b: Tensor, twist_a: Tensor) -> Tensor:
    """Express a twist given in frame ``a`` (about a's origin) in frame ``b`` (about b's origin).

    Args:
        R_a_b: ``(..., 3, 3)`` rotation of ``b`` in ``a``.
        p_a_b: ``(..., 3)`` origin of ``b`` in ``a``, m.
        twist_a: ``(..., 6)`` ``[linear (m/s); angular (rad/s)]`` in frame ``a``.

    Returns:
        ``(..., 6)`` the same twist in frame ``b``.
    """
    T, v, like = _pose_args(R_a_b, p_a_b, twist_a)
    return _stack6(motion_to_child(T, v), like)


def transform_wrench(R_a_b: Tensor, p_a_b: Tensor, wrench_b: Tensor) -> Tensor:
    """Express a wrench given in frame ``b`` (moment about b's origin) in frame ``a``.

    Args:
        R_a_b: ``(..., 3, 3)`` rotation of ``b`` in ``a``.
        p_a_b: ``(..., 3)`` origin of ``b`` in ``a``, m.
        wrench_b: ``(..., 6)`` ``[force (N); moment (N m)]`` in frame ``b``.

    Returns:
        ``(..., 6)`` the same wrench in frame ``a``, moment about a's origin.

    Example:
        >>> R, p = torch.eye(3), torch.tensor([0.0, 0.0, 1.0])
        >>> transform_wrench(R, p, torch.tensor([1.0, 0, 0, 0, 0, 0]))
        tensor([1., 0., 0., 0., 1., 0.])
    """
    T, f, like = _pose_args(R_a_b, p_a_b, wrench_b)
    return _stack6(force_to_parent(T, f), like)


def transform_wrench_inverse(R_a_b: Tensor, p_a_b: Tensor, wrench_a: Tensor) -> Tensor:
    """Express a wrench given in frame ``a`` in frame ``b`` (inverse of :func:`transform_wrench`).

    Args:
        R_a_b: ``(..., 3, 3)`` rotation of ``b`` in ``a``.
        p_a_b: ``(..., 3)`` origin of ``b`` in ``a``, m.
        wrench_a: ``(..., 6)`` ``[force (N); moment (N m)]`` in frame ``a``, about a's origin.

    Returns:
        ``(..., 6)`` the same wrench in frame ``b``, moment about b's origin.
    """
    T, f, like = _pose_args(R_a_b, p_a_b, wrench_a)
    return _stack6(force_to_child(T, f), like)


# ----------------------------------------------------------------------------- inertia constants


def inertia_about(mass: float, com: np.ndarray, inertia_com: np.ndarray, point) -> np.ndarray:
    """Rotational inertia about ``point`` (parallel-axis theorem), same axes, float64.

    Args:
        mass: kg.
        com: ``(3,)`` centre of mass, m.
        inertia_com: ``(3, 3)`` rotational inertia about the centre of mass, kg m^2.
        point: ``(3,)`` the new reference point, m (same frame as ``com``).

    Returns:
        ``(3, 3)`` ``I_com + m (|d|^2 1 - d d^T)`` with ``d = com - point``.

    Example:
        >>> float(inertia_about(2.0, np.array([1.0, 0, 0]), np.zeros((3, 3)), np.zeros(3))[2, 2])
        2.0
    """
    d = np.asarray(com, float) - np.asarray(point, float)
    return np.asarray(inertia_com, float) + mass * (d @ d * np.eye(3) - np.outer(d, d))


def combine_inertias(
    parts: Sequence[tuple[float, np.ndarray, np.ndarray]],
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and inertia about it of rigidly joined parts given in one frame.

    Args:
        parts: ``(mass, com (3,), inertia_com (3, 3))`` per part, kg, m, kg m^2.

    Returns:
        ``(mass, com, inertia_com)`` of the union (zeros for a massless union).
    """
    m = float(sum(p[0] for p in parts))
    if m <= 0.0:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    c = sum(p[0] * np.asarray(p[1], float) for p in parts) / m
    inertia = sum((inertia_about(mi, ci, Ii, c) for mi, ci, Ii in parts), np.zeros((3, 3)))
    return m, c, inertia
