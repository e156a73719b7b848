"""Spatial algebra on batched tensors.

Conventions (stated once, used everywhere in torchcontact):

* a **twist** (spatial motion vector) is ``[linear; angular]``, shape ``(..., 6)``;
* a **wrench** (spatial force vector) is ``[force; moment]``, shape ``(..., 6)``;
* a pose ``T_a_b`` is a rotation ``R_a_b`` ``(..., 3, 3)`` and a translation ``p_a_b`` ``(..., 3)``
  such that a point ``x_b`` in frame ``b`` is ``x_a = R_a_b @ x_b + p_a_b`` in frame ``a``;
* quaternions appear only at input/output boundaries and are named ``quat_wxyz``.

All functions accept any number of leading batch dimensions and follow the dtype and device of
their inputs. They are written in elementwise torch ops only, so that they trace into ONNX and
fuse under ``torch.compile``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "cross",
    "matvec",
    "rpy_to_matrix",
    "skew",
    "transform_wrench",
    "transform_wrench_inverse",
    "twist_in_frame",
]


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
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), dim=-1)


def matvec(m: Tensor, v: Tensor) -> Tensor:
    """Batched matrix-vector product ``m @ v`` written as a broadcast multiply-sum.

    For 3x3 matrices this is faster than a batched GEMM on CPU and fuses under compilation.

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


def twist_in_frame(R_a_b: Tensor, p_a_b: Tensor, twist_a: Tensor) -> Tensor:
    """Express a twist given in frame ``a`` (about a's origin) in frame ``b`` (about b's origin).

    Args:
        R_a_b: ``(..., 3, 3)`` rotation of ``b`` in ``a``.
        p_a_b: ``(..., 3)`` origin of ``b`` in ``a``, m.
        twist_a: ``(..., 6)`` ``[linear (m/s); angular (rad/s)]`` in frame ``a``.

    Returns:
        ``(..., 6)`` the same twist in frame ``b``.
    """
    lin, ang = twist_a[..., :3], twist_a[..., 3:]
    lin_at_b = lin + cross(ang, p_a_b)
    Rt = R_a_b.transpose(-1, -2)
    return torch.cat((matvec(Rt, lin_at_b), matvec(Rt, ang)), dim=-1)


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
    f = matvec(R_a_b, wrench_b[..., :3])
    n = matvec(R_a_b, wrench_b[..., 3:]) + cross(p_a_b, f)
    return torch.cat((f, n), dim=-1)


def transform_wrench_inverse(R_a_b: Tensor, p_a_b: Tensor, wrench_a: Tensor) -> Tensor:
    """Express a wrench given in frame ``a`` in frame ``b`` (inverse of :func:`transform_wrench`).

    Args:
        R_a_b: ``(..., 3, 3)`` rotation of ``b`` in ``a``.
        p_a_b: ``(..., 3)`` origin of ``b`` in ``a``, m.
        wrench_a: ``(..., 6)`` ``[force (N); moment (N m)]`` in frame ``a``, about a's origin.

    Returns:
        ``(..., 6)`` the same wrench in frame ``b``, moment about b's origin.
    """
    f_a, n_a = wrench_a[..., :3], wrench_a[..., 3:]
    Rt = R_a_b.transpose(-1, -2)
    return torch.cat((matvec(Rt, f_a), matvec(Rt, n_a - cross(p_a_b, f_a))), dim=-1)
