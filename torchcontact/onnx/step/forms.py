"""Row forms of the single-frame graph: pose feature rows and bilinear adjoint maps.

A pose ``T = (R, p)`` travels through the graph as its homogeneous 4 x 4 matrix, row-major
(16 entries, the last one 1: :func:`torchcontact.onnx.step.kinematics.poses`) and, extended, as
``[R, p, pR = [p]x R, -R^T p, 1]`` (:data:`TP_ONE`), so that
the adjoint maps of :mod:`torchcontact.spatial` become bilinear in (pose row, vector):
``R^T (w x p) = (pR)^T w`` and ``R^T (p x f) = -(pR)^T f``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from torchcontact import spatial as sp
from torchcontact._scalar import neg

__all__ = [
    "TP_ONE",
    "const_force_map",
    "flat",
    "force_to_child",
    "force_to_parent",
    "motion_to_child",
    "rows",
    "signed",
    "skew",
    "split",
    "tp",
]

#: Index of the 1 column of a pose feature row ``[R, p, pR, -R^T p, 1]`` (25 columns).
TP_ONE = 24


def rows(v: Sequence) -> sp.M3:
    """A 3 x 3 matrix from 9 row-major scalars."""
    return (tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9]))


def flat(R: sp.M3) -> list:
    """The 9 row-major scalars of a 3 x 3 matrix."""
    return [x for row in R for x in row]


def split(v: Sequence) -> tuple[sp.V3, sp.V3]:
    """A spatial 6-vector ``(first 3, last 3)`` from 6 scalars."""
    return tuple(v[0:3]), tuple(v[3:6])


def skew(v: sp.V3) -> sp.M3:
    """``[v]x``."""
    return ((0.0, neg(v[2]), v[1]), (v[2], 0.0, neg(v[0])), (neg(v[1]), v[0], 0.0))


def signed(sign: float, f: Sequence) -> sp.Force:
    """``sign f`` of a wrench given as six scalars or a (force, moment) pair."""
    if len(f) == 2:
        f = (*f[0], *f[1])
    lin, ang = split(f)
    if sign == 1.0:
        return lin, ang
    return sp.v_neg(lin), sp.v_neg(ang)


def tp(t: Sequence) -> tuple[sp.M3, sp.V3, sp.M3, sp.V3]:
    """``R``, ``p``, ``pR = [p]x R`` and ``-R^T p`` of a pose feature row."""
    return rows(t[0:9]), tuple(t[9:12]), rows(t[12:21]), tuple(t[21:24])


def motion_to_child(R: sp.M3, pR: sp.M3, v: sp.Motion) -> sp.Motion:
    """:func:`torchcontact.spatial.motion_to_child` written with ``pR``."""
    lin, ang = v
    return sp.v_add(sp.mT_vec(R, lin), sp.mT_vec(pR, ang)), sp.mT_vec(R, ang)


def force_to_parent(R: sp.M3, pR: sp.M3, f: sp.Force) -> sp.Force:
    """:func:`torchcontact.spatial.force_to_parent` written with ``pR``."""
    return sp.m_vec(R, f[0]), sp.v_add(sp.m_vec(R, f[1]), sp.m_vec(pR, f[0]))


def force_to_child(R: sp.M3, pR: sp.M3, f: sp.Force) -> sp.Force:
    """:func:`torchcontact.spatial.force_to_child` written with ``pR``."""
    return sp.mT_vec(R, f[0]), sp.v_add(sp.mT_vec(R, f[1]), sp.mT_vec(pR, f[0]))


def const_force_map(fn, n: int = 6) -> np.ndarray:
    """The matrix of a linear map on 6-vectors given as a function on scalars (constants)."""
    cols = []
    for j in range(n):
        e = [1.0 if i == j else 0.0 for i in range(n)]
        out = fn(split(e))
        cols.append([float(x) for x in (*out[0], *out[1])])
    return np.array(cols).T
