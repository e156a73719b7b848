"""Contacts without skin: localize a single contact from an F/T wrench and the collision meshes.

Intrinsic contact sensing (Salisbury, *Interpretation of contact geometries from force
measurements*, 1984; Bicchi, Salisbury, Brock, IJRR 1993): a pure force ``f`` at a point ``r``
causes the wrench ``[f; m] = [f; r x f]`` about the sensor, so ``r`` lies on the force's line of
action::

    r(s) = (f x m) / |f|^2 + s f / |f|

and the contact is where that line meets a candidate link's surface with the force pushing into
it (``f . n < 0``, ``n`` the outward normal). The wrench is the paper's ``b`` of the sensor's region
(Del Prete et al. 2012, Sec. 2.1): the reading after the region's own dynamics, computed by the
estimator's stages (:func:`torchcontact.estimation.stages.region_rhs`), so that gravity, motion
and nested sensors are accounted for exactly as in the estimate.

**Stages**, all batched over frames (no Python loop over frames), CPU or CUDA, float32 or float64:

1. the line program (a :class:`torchcontact.kernels.Program`, eager or a generated kernel): ``b``
   of every region and the pose of every candidate link in its region's sensor frame;
2. the line in each candidate link's frame (torch);
3. ray casting: every intersection of the (infinite) line with the candidate meshes, by a
   breadth-first traversal of a bounding-volume hierarchy over the (ray, node) pairs, one tensor
   step per tree level (``ray="torch"``), by testing every triangle (``"brute"``), or by Embree
   directly (``"embree"``, CPU, when ``embreex`` is installed);
4. selection: hits sorted along the line; a hit entering the union of the candidate meshes
   (``f . n < 0`` and no mesh around it, counted by the entries and exits before it) is a
   candidate contact; the first one along the force is reported, several distinct ones (farther
   apart than ``merge_distance``) make the frame *ambiguous*;
5. the first-order propagation of the F/T noise to the contact point.

The status of each frame is a bit field of :data:`torchcontact.status.LOCALIZE_STATUS`.

A contact lasts: :meth:`Localizer.localize` takes a ``prior`` (where each frame's contact is
expected) that resolves ambiguous frames, and :meth:`Localizer.localize_sequence` finds the
priors of consecutive frames itself (:func:`temporal_prior`, :func:`stationary_choice`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchcontact import kernels
from torchcontact import spatial as sp
from torchcontact._internal import check_input, counts, flatten_batch
from torchcontact._scalar import isfinite, logical_and, logical_not, select
from torchcontact.dynamics import BaseMotion
from torchcontact.errors import InputError, MissingExtraError
from torchcontact.estimation import stages
from torchcontact.estimation.layout import EstimationModel
from torchcontact.kernels.runner import run_program
from torchcontact.meshes import LinkMesh, RobotMeshes
from torchcontact.model import RobotModel
from torchcontact.status import LOCALIZE_STATUS, LocalizeStatus

__all__ = [
    "LOCALIZE_STATUS",
    "RAY_BACKENDS",
    "LocalizedChunk",
    "Localization",
    "Localizer",
    "TriangleSet",
    "localize_chunk",
    "localized_frames",
    "stationary_choice",
    "temporal_prior",
]

#: Ray-casting backends of :class:`Localizer`.
RAY_BACKENDS = ("auto", "torch", "brute", "embree")

# status bits (torchcontact.status.LocalizeStatus)
_NONFINITE, _NO_CONTACT = int(LocalizeStatus.NONFINITE), int(LocalizeStatus.NO_CONTACT)
_MISS, _PULLING = int(LocalizeStatus.NO_INTERSECTION), int(LocalizeStatus.PULLING)
_AMBIGUOUS, _OUTSIDE_CONE = int(LocalizeStatus.AMBIGUOUS), int(LocalizeStatus.OUTSIDE_CONE)
_SNAPPED, _PRIOR = int(LocalizeStatus.NEAR_MISS), int(LocalizeStatus.PRIOR)
#: bits that come with a contact point (a caveat, not a failure)
SOFT_BITS = _AMBIGUOUS | _OUTSIDE_CONE | _SNAPPED | _PRIOR


class Localization(NamedTuple):
    """The contact localized for one sensor; ``*B`` is the input batch shape.

    Frames whose status has a bit other than 16 (ambiguous), 64 (outside the friction cone) and
    128 (snapped) set have ``link`` -1 and NaN outputs.

    Attributes:
        link: ``(*B,)`` int64 index into :attr:`Localizer.links` of the contact's link, -1 none.
        position: ``(*B, 3)`` contact point in the link frame, m.
        normal: ``(*B, 3)`` unit outward surface normal at the point (the hit triangle's), link
            frame.
        force: ``(*B, 3)`` the pure-force estimate, the measured force ``b[:3]``, link frame, N.
        moment_residual: ``(*B,)`` ``|f . m| / |f|``, N m: the moment along the force that no
            point force explains (0 for an exact single pure-force contact).
        candidates: ``(*B,)`` int64 number of distinct points where the line enters the link
            surfaces (1: unique; more: ambiguous, the first along the force is reported).
        status: ``(*B,)`` int64 bits of :data:`torchcontact.status.LOCALIZE_STATUS` (0 ok).
        wrench: ``(*B, 6)`` the sensor region's ``b`` ``[force; moment about the sensor]``,
            sensor frame (NaN for non-finite input).
        covariance: ``(*B, 3, 3)`` first-order covariance of the contact point from the F/T
            noise covariance (link frame, m^2), or None when none was given.
        position_std: ``(*B,)`` ``sqrt(trace(covariance))``, m, or None.
    """

    link: Tensor
    position: Tensor
    normal: Tensor
    force: Tensor
    moment_residual: Tensor
    candidates: Tensor
    status: Tensor
    wrench: Tensor
    covariance: Tensor | None = None
    position_std: Tensor | None = None


# ------------------------------------------------------------------------------ triangle sets
@dataclass(frozen=True, eq=False)
class TriangleSet:
    """The triangles of several links' meshes with a bounding-volume hierarchy, as tensors.

    Triangles are in their own link's frame; each link has its own tree. Build it with
    :meth:`build`; :meth:`to` returns a copy on another device or dtype.

    Attributes:
        links: the link names, in order.
        link_of_tri: ``(F,)`` int64 index into ``links`` of each triangle.
        v0: ``(F, 3)`` first vertex of each triangle, link frame, m.
        e1: ``(F, 3)`` ``v1 - v0``.
        e2: ``(F, 3)`` ``v2 - v0``.
        normal: ``(F, 3)`` unit outward normal (``e1 x e2`` normalised; 0 when degenerate).
        lo: ``(M, 3)`` lower corner of each node's box (slightly inflated), link frame.
        hi: ``(M, 3)`` upper corner.
        left: ``(M,)`` int64 first child, -1 for a leaf.
        right: ``(M,)`` int64 second child, -1 for a leaf.
        leaf_tris: ``(M, T)`` int64 the triangles of each leaf, -1 padded (inner nodes: -1).
        root: ``(L,)`` int64 root node of each link's tree.
        depth: the deepest leaf's level + 1 (traversal steps).
    """

    links: tuple[str, ...]
    link_of_tri: Tensor
    v0: Tensor
    e1: Tensor
    e2: Tensor
    normal: Tensor
    lo: Tensor
    hi: Tensor
    left: Tensor
    right: Tensor
    leaf_tris: Tensor
    root: Tensor
    depth: int

    @property
    def n_triangles(self) -> int:
        """Number of triangles ``F``."""
        return int(self.v0.shape[0])

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> TriangleSet:
        """A copy with the tensors on ``device``, floating ones cast to ``dtype``."""
        floats = {k: getattr(self, k).to(device=device, dtype=dtype)
                  for k in ("v0", "e1", "e2", "normal", "lo", "hi")}  # fmt: skip
        ints = {k: getattr(self, k).to(device=device)
                for k in ("link_of_tri", "left", "right", "leaf_tris", "root")}  # fmt: skip
        return replace(self, **floats, **ints)

    @classmethod
    def build(
        cls,
        meshes: Sequence[LinkMesh],
        leaf_size: int = 4,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> TriangleSet:
        """Triangles and one median-split tree per link mesh.

        Args:
            meshes: the links' meshes (vertices in the link frame).
            leaf_size: most triangles per leaf.
            dtype: floating dtype of the tensors.
            device: device of the tensors.

        Returns:
            The :class:`TriangleSet`.
        """
        v0s, e1s, e2s, link_of, roots = [], [], [], [], []
        lo_all, hi_all, left_all, right_all, leaves_all = [], [], [], [], []
        n_tri = n_node = depth = 0
        for li, m in enumerate(meshes):
            tri = np.asarray(m.vertices, np.float64)[np.asarray(m.faces, np.int64)]  # (F, 3, 3)
            lo, hi, left, right, leaves, d = _median_bvh(tri, leaf_size)
            v0s.append(tri[:, 0])
            e1s.append(tri[:, 1] - tri[:, 0])
            e2s.append(tri[:, 2] - tri[:, 0])
            link_of.append(np.full(len(tri), li, np.int64))
            roots.append(n_node)
            lo_all.append(lo)
            hi_all.append(hi)
            left_all.append(np.where(left >= 0, left + n_node, -1))
            right_all.append(np.where(right >= 0, right + n_node, -1))
            leaves_all.append(np.where(leaves >= 0, leaves + n_tri, -1))
            n_tri += len(tri)
            n_node += len(lo)
            depth = max(depth, d)
        e1, e2 = np.concatenate(e1s), np.concatenate(e2s)
        nrm = np.cross(e1, e2)
        norm = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.divide(nrm, norm, out=np.zeros_like(nrm), where=norm > 0)

        def f(x: np.ndarray) -> Tensor:
            return torch.as_tensor(x, dtype=dtype, device=device)

        def i(x: np.ndarray) -> Tensor:
            return torch.as_tensor(x, dtype=torch.int64, device=device)

        return cls(
            links=tuple(m.link for m in meshes),
            link_of_tri=i(np.concatenate(link_of)),
            v0=f(np.concatenate(v0s)),
            e1=f(e1),
            e2=f(e2),
            normal=f(nrm),
            lo=f(np.concatenate(lo_all)),
            hi=f(np.concatenate(hi_all)),
            left=i(np.concatenate(left_all)),
            right=i(np.concatenate(right_all)),
            leaf_tris=i(np.concatenate(leaves_all)),
            root=i(np.array(roots, np.int64)),
            depth=depth,
        )


def _median_bvh(tri: np.ndarray, leaf_size: int):
    """A binary tree over triangles ``(F, 3, 3)``: split at the median centroid, longest axis.

    Returns ``(lo, hi, left, right, leaf_tris, depth)``; node 0 is the root; boxes are inflated
    by 1e-9 of their scale so that rounding never misses a triangle on a box face.
    """
    cen = tri.mean(1)
    tlo, thi = tri.min(1), tri.max(1)
    los, his, lefts, rights, leaves = [], [], [], [], []
    depth = 0
    stack = [(np.arange(len(tri)), -1, 0, 0)]  # (triangles, parent, side, level)
    while stack:
        idx, parent, side, level = stack.pop()
        node = len(los)
        if parent >= 0:
            (lefts if side == 0 else rights)[parent] = node
        lo, hi = tlo[idx].min(0), thi[idx].max(0)
        pad = 1e-9 * max(float(np.abs(np.r_[lo, hi]).max()), 1e-3)
        los.append(lo - pad)
        his.append(hi + pad)
        lefts.append(-1)
        rights.append(-1)
        depth = max(depth, level + 1)
        if len(idx) <= leaf_size:
            leaves.append((node, idx))
            continue
        c = cen[idx]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = idx[np.argsort(c[:, axis], kind="stable")]
        half = len(order) // 2
        stack.append((order[half:], node, 1, level + 1))
        stack.append((order[:half], node, 0, level + 1))
    M = len(los)
    leaf_tris = -np.ones((M, leaf_size), np.int64)
    for node, idx in leaves:
        leaf_tris[node, : len(idx)] = idx
    return (np.array(los), np.array(his), np.array(lefts, np.int64), np.array(rights, np.int64),
            leaf_tris, depth)  # fmt: skip


# ------------------------------------------------------------------------------ ray casting
class Hits(NamedTuple):
    """Intersections of rays with triangles (unordered), one row per hit.

    Attributes:
        ray: ``(H,)`` int64 ray index.
        tri: ``(H,)`` int64 triangle index into the :class:`TriangleSet`.
        t: ``(H,)`` line parameter of the hit, ``point = origin + t * direction``.
        entering: ``(H,)`` bool, the ray enters the solid there (``direction . normal < 0``).
    """

    ray: Tensor
    tri: Tensor
    t: Tensor
    entering: Tensor


def _moller_trumbore(ts: TriangleSet, orig: Tensor, dirs: Tensor, ray: Tensor, tri: Tensor) -> Hits:
    """Intersections of the infinite lines ``orig[ray] + t dirs[ray]`` with triangles ``tri``.

    Moller and Trumbore, *Fast, minimum storage ray-triangle intersection*, 1997, without the
    ``t >= 0`` test (the line of action extends both ways). Edges count for both triangles that
    share them (the selection merges the duplicates).
    """
    o, d = orig[ray], dirs[ray]
    e1, e2 = ts.e1[tri], ts.e2[tri]
    pvec = torch.linalg.cross(d, e2)
    det = (e1 * pvec).sum(-1)
    scale = (e1 * e1).sum(-1) * (e2 * e2).sum(-1)
    ok = det * det > scale * (torch.finfo(det.dtype).eps ** 2)  # not parallel to the plane
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    tvec = o - ts.v0[tri]
    u = (tvec * pvec).sum(-1) * inv
    qvec = torch.linalg.cross(tvec, e1)
    v = (d * qvec).sum(-1) * inv
    t = (e2 * qvec).sum(-1) * inv
    eps = 8 * torch.finfo(det.dtype).eps
    hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)
    return Hits(ray[hit], tri[hit], t[hit], det[hit] > 0)


def _on_edge(ts: TriangleSet, orig: Tensor, dirs: Tensor, hits: Hits, tol: float) -> Tensor:
    """``(H,)`` bool: the hit point's smallest barycentric coordinate is below ``tol``."""
    p = orig[hits.ray] + hits.t.unsqueeze(-1) * dirs[hits.ray] - ts.v0[hits.tri]
    e1, e2 = ts.e1[hits.tri], ts.e2[hits.tri]
    d11, d12, d22 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    p1, p2 = (p * e1).sum(-1), (p * e2).sum(-1)
    den = (d11 * d22 - d12 * d12).clamp_min(torch.finfo(p.dtype).tiny)
    u = (d22 * p1 - d12 * p2) / den
    v = (d11 * p2 - d12 * p1) / den
    return torch.minimum(torch.minimum(u, v), 1 - u - v) < tol


def _nearest_facing_edge(
    ts: TriangleSet, orig: Tensor, dirs: Tensor, rays: Tensor, ray_link: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per ray, the nearest point to the line on the edges of triangles it would enter.

    ``(distance (R,), point (R, 3), triangle (R,))``, only triangles with ``d . n < 0``; inf
    where none faces the line. Brute force over the link's triangles (for the few lines that
    meet no triangle).
    """
    R = len(rays)
    dist = orig.new_full((R,), math.inf)
    point = orig.new_zeros(R, 3)
    tri_out = torch.zeros(R, dtype=torch.int64, device=orig.device)
    for li in range(len(ts.links)):
        sel = torch.nonzero(ray_link == li).reshape(-1)
        tris = torch.nonzero(ts.link_of_tri == li).reshape(-1)
        if not len(sel) or not len(tris):
            continue
        step = max(1, (1 << 21) // (3 * len(tris)))
        for s0 in range(0, len(sel), step):
            r = sel[s0 : s0 + step]
            o, d = orig[rays[r]][:, None, None], dirs[rays[r]][:, None, None]  # (r, 1, 1, 3)
            v0, e1, e2 = ts.v0[tris], ts.e1[tris], ts.e2[tris]
            A = torch.stack([v0, v0 + e1, v0 + e2], 1)[None]  # (1, F, 3, 3): edge starts
            E = torch.stack([e1, e2 - e1, -e2], 1)[None]  # edge vectors
            w = A - o
            w = w - (w * d).sum(-1, keepdim=True) * d  # parts across the line
            ep = E - (E * d).sum(-1, keepdim=True) * d
            den = (ep * ep).sum(-1).clamp_min(torch.finfo(o.dtype).tiny)
            uu = (-(w * ep).sum(-1) / den).clamp(0, 1)
            gap = (w + uu.unsqueeze(-1) * ep).norm(dim=-1)  # (r, F, 3)
            facing = (d[:, :, 0] * ts.normal[tris][None]).sum(-1) < 0  # (r, F)
            gap = torch.where(facing.unsqueeze(-1), gap, math.inf).reshape(len(r), -1)
            best = gap.argmin(1)
            fi, ei = best // 3, best % 3
            ar = torch.arange(len(r), device=orig.device)
            dist[r] = gap[ar, best]
            point[r] = A[0, fi, ei] + uu[ar, fi, ei].unsqueeze(-1) * E[0, fi, ei]
            tri_out[r] = tris[fi]
    return dist, point, tri_out


def cast_brute(ts: TriangleSet, orig: Tensor, dirs: Tensor, ray_link: Tensor, chunk: int = 1 << 22):
    """Every hit of the lines ``(R, 3)`` (each in its link's frame) with its link's triangles.

    Tests every (ray, triangle of its link) pair, ``chunk`` pairs at a time: the reference the
    tree traversal is checked against.
    """
    F = ts.n_triangles
    dev = orig.device
    parts = []
    per_link = [torch.nonzero(ts.link_of_tri == li).reshape(-1) for li in range(len(ts.links))]
    for li, tris in enumerate(per_link):
        rays = torch.nonzero(ray_link == li).reshape(-1)
        if not len(rays) or not len(tris):
            continue
        step = max(1, chunk // max(len(tris), 1))
        for s in range(0, len(rays), step):
            r = rays[s : s + step]
            rr = r.repeat_interleave(len(tris))
            tt = tris.repeat(len(r))
            parts.append(_moller_trumbore(ts, orig, dirs, rr, tt))
    if not parts:
        z = torch.zeros(0, dtype=torch.int64, device=dev)
        return Hits(z, z, orig.new_zeros(0), torch.zeros(0, dtype=torch.bool, device=dev))
    del F
    return Hits(*(torch.cat([getattr(p, k) for p in parts]) for k in Hits._fields))


def cast_bvh(ts: TriangleSet, orig: Tensor, dirs: Tensor, ray_link: Tensor) -> Hits:
    """Every hit of the lines ``(R, 3)`` with their links' triangles, through the trees.

    Breadth-first: a frontier of (ray, node) pairs goes down one tree level per step (a slab
    test of the infinite line against each node's box keeps the pairs that meet it; inner nodes
    are replaced by their two children, leaves collected), then the leaves' triangles are tested.
    One tensor step per level, no loop over rays.
    """
    tiny = torch.finfo(dirs.dtype).tiny ** 0.5
    dsafe = torch.where(
        dirs.abs() < tiny, torch.full_like(dirs, tiny) * torch.where(dirs < 0, -1.0, 1.0), dirs
    )
    rd = torch.cat([orig, 1.0 / dsafe], -1)  # (R, 6): one gather per pair and level

    def meets(r6: Tensor, box: Tensor) -> Tensor:  # slab test, r6 (P, 1, 6), box (P, k, 6)
        t1 = (box[..., :3] - r6[..., :3]) * r6[..., 3:]
        t2 = (box[..., 3:] - r6[..., :3]) * r6[..., 3:]
        return torch.minimum(t1, t2).amax(-1) <= torch.maximum(t1, t2).amin(-1)

    box = torch.cat([ts.lo, ts.hi], -1)  # (M, 6)
    kids = torch.stack([ts.left, ts.right], -1)  # (M, 2)
    kid_box = box[kids.clamp_min(0)]  # (M, 2, 6); leaves' rows unused
    ray = torch.arange(orig.shape[0], device=orig.device)
    node = ts.root[ray_link]
    keep = meets(rd.unsqueeze(1), box[node].unsqueeze(1))[:, 0]
    ray, node = ray[keep], node[keep]
    leaf_ray, leaf_node = [ray[:0]], [node[:0]]
    for _ in range(ts.depth):
        if ray.numel() == 0:
            break
        leaf = ts.left[node] < 0
        leaf_ray.append(ray[leaf])
        leaf_node.append(node[leaf])
        ray, node = ray[~leaf], node[~leaf]
        # both children of every inner pair at once
        hit = meets(rd[ray].unsqueeze(1), kid_box[node])  # (P, 2)
        p, c = torch.nonzero(hit, as_tuple=True)
        ray, node = ray[p], kids[node[p], c]
    lr, ln = torch.cat(leaf_ray), torch.cat(leaf_node)
    tris = ts.leaf_tris[ln]  # (Q, T)
    valid = tris >= 0
    rr = lr.unsqueeze(1).expand_as(tris)[valid]
    return _moller_trumbore(ts, orig, dirs, rr, tris[valid])


def cast_embree(meshes: Sequence[LinkMesh], ts: TriangleSet, orig: Tensor, dirs: Tensor,
                ray_link: Tensor) -> Hits:  # fmt: skip
    """Every hit of the lines with their links' meshes, by Embree (``embreex``).

    Each line becomes a ray starting outside its link's bounding sphere; Embree casts it again
    past each hit (:func:`_embree_all_hits`). Embree computes in float32 (on the mesh centred at
    its box's middle); the hit parameter is recomputed in float64 on the hit triangle's plane.

    Raises:
        MissingExtraError: embreex is not installed.
    """
    if not embree_available():
        raise MissingExtraError("embreex", "meshes")
    dev, dtype = orig.device, orig.dtype
    On = orig.detach().cpu().double().numpy()
    Dn = dirs.detach().cpu().double().numpy()
    rl = ray_link.cpu().numpy()
    out_r, out_f, out_t = [], [], []
    offset = 0
    for li, m in enumerate(meshes):
        nf = len(m.faces)
        rays = np.flatnonzero(rl == li)
        if len(rays):
            scene, center, base = _embree_scene(m)
            c = 0.5 * (m.vertices.min(0) + m.vertices.max(0))
            radius = float(np.linalg.norm(m.vertices - c, axis=1).max()) + 1e-3
            o, d = On[rays], Dn[rays]
            s0 = ((c - o) * d).sum(1) - radius  # start before the sphere along the line
            start = o + s0[:, None] * d
            index_ray, index_tri = _embree_all_hits(scene, m, start - center, d, base, center)
            if len(index_ray):
                r = rays[index_ray]
                tri = index_tri + offset
                v0 = np.asarray(m.vertices)[np.asarray(m.faces)[index_tri, 0]]
                nrm = ts.normal[torch.as_tensor(tri, device=dev)].cpu().double().numpy()
                # the exact parameter on the triangle's plane (Embree's is float32)
                den = (Dn[r] * nrm).sum(1)
                t = ((v0 - On[r]) * nrm).sum(1) / np.where(den == 0, 1.0, den)
                out_r.append(r)
                out_f.append(tri)
                out_t.append(t)
        offset += nf
    if not out_r:
        z = torch.zeros(0, dtype=torch.int64, device=dev)
        return Hits(z, z, orig.new_zeros(0), torch.zeros(0, dtype=torch.bool, device=dev))
    r = torch.as_tensor(np.concatenate(out_r), device=dev)
    f = torch.as_tensor(np.concatenate(out_f), device=dev)
    t = torch.as_tensor(np.concatenate(out_t), dtype=dtype, device=dev)
    entering = (dirs[r] * ts.normal[f]).sum(-1) < 0
    return Hits(r, f, t, entering)


_EMBREE: dict[tuple, tuple] = {}


def _embree_scene(m: LinkMesh) -> tuple[object, np.ndarray, float]:
    """An Embree scene of a link mesh (built once per mesh), its centre and the step past a hit.

    The vertices are centred at the middle of their box before the float32 conversion.
    """
    v = np.asarray(m.vertices, np.float64)
    f = np.asarray(m.faces, np.int64)
    key = (v.tobytes(), f.tobytes())
    if key not in _EMBREE:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        center = 0.5 * (v.min(0) + v.max(0))
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=scene, vertices=(v - center).astype(np.float32),
                     indices=f.astype(np.int32))  # fmt: skip
        base = max(1e-8, float(np.linalg.norm(v.max(0) - v.min(0))) * 1e-6)
        _EMBREE[key] = (scene, center, base)
    return _EMBREE[key]


def _embree_all_hits(
    scene, m: LinkMesh, orig: np.ndarray, d: np.ndarray, base: float, center: np.ndarray
):
    """Every triangle the rays ``orig + t d`` (``t > 0``; centred frame, float64) pass through.

    Cast, step past each hit on the hit triangle's plane (float64) and cast again until every
    ray leaves the mesh; a ray that meets the same triangle again (float32 rounding) steps twice
    as far. Returns ``(ray, triangle)`` index arrays, one row per hit.
    """
    tri = np.asarray(m.vertices, np.float64)[np.asarray(m.faces, np.int64)]
    tri = tri - center
    v0 = tri[:, 0]
    nrm = np.cross(tri[:, 1] - v0, tri[:, 2] - v0)
    o = np.array(orig, np.float64)
    step = np.full(len(o), base)
    last = np.full(len(o), -1, np.int64)
    live = np.arange(len(o))
    out_r, out_f = [], []
    for _ in range(100):
        if not len(live):
            break
        q = scene.run(o[live].astype(np.float32), d[live].astype(np.float32))
        hit = q >= 0
        r, f = live[hit], q[hit].astype(np.int64)
        dupe = last[r] == f
        last[r] = f
        ok_r, ok_f = r[~dupe], f[~dupe]
        den = (d[ok_r] * nrm[ok_f]).sum(1)
        fine = den != 0
        ok_r, ok_f = ok_r[fine], ok_f[fine]
        out_r.append(ok_r)
        out_f.append(ok_f)
        t = ((v0[ok_f] - o[ok_r]) * nrm[ok_f]).sum(1) / den[fine]
        o[ok_r] += (t + base)[:, None] * d[ok_r]
        step[ok_r] = base
        stuck = r[dupe]
        step[stuck] *= 2.0
        o[stuck] += step[stuck, None] * d[stuck]
        live = np.concatenate([ok_r, stuck])
    if not out_r:
        z = np.zeros(0, np.int64)
        return z, z
    return np.concatenate(out_r), np.concatenate(out_f)


def embree_available() -> bool:
    """True when Embree can be used (the ``embreex`` package is installed)."""
    try:
        from embreex import rtcore_scene  # noqa: F401
        from embreex.mesh_construction import TriangleMesh  # noqa: F401
    except ImportError:
        return False
    return True


# ------------------------------------------------------------------------------ selection
class Selected(NamedTuple):
    """Per frame (or ray group), the first point where the line enters the surfaces."""

    found: Tensor  # (G,) bool: a valid entry exists
    any_hit: Tensor  # (G,) bool: the line meets a surface at all
    ray: Tensor  # (G,) int64 ray of the reported hit (0 where not found)
    tri: Tensor  # (G,) int64 triangle of the reported hit
    t: Tensor  # (G,) line parameter of the reported hit
    candidates: Tensor  # (G,) int64 distinct valid entries
    normal: Tensor | None  # (G, 3) unit outward normal there (mean over an edge or vertex)
    outside_cone: Tensor  # (G,) bool: no valid entry lies in the friction cone (any is taken)


def select_entries(
    hits: Hits,
    group: Tensor,
    G: int,
    merge: float,
    dedup: float,
    normals: Tensor | None = None,
    dirs: Tensor | None = None,
    cos_min: float | None = None,
    edge: Tensor | None = None,
    target: Tensor | None = None,
) -> Selected:
    """The first valid entry of each group of rays (the rays of one frame share one line).

    A hit is a valid entry when the line enters a surface there while outside every mesh: the
    entries minus the exits before it along the line (duplicates within ``dedup`` of the same
    kind merged: an edge or vertex shared by several triangles; the count clamped at zero, so
    that an exit without its entry, through a hole of an open mesh, is forgiven) are zero, and,
    with ``cos_min``, the line lies within ``acos(cos_min)`` of the inward normal there (the
    friction cone; at an edge or vertex, of the mean of its faces' normals; a line with no such
    entry keeps its other entries, flagged ``outside_cone``). Valid entries farther apart than
    ``merge`` along the line are distinct candidates.

    Args:
        hits: every hit.
        group: ``(R,)`` int64 group of each ray (its frame).
        G: number of groups.
        merge: distance along the line below which two valid entries are one candidate, m.
        dedup: distance below which two hits of the same kind are one (shared edges), m.
        normals: ``(H,)`` per hit, the unit outward normal of its triangle (ray's frame); gives
            ``normal`` of the result.
        dirs: ``(H, 3)`` per hit, its ray's unit direction (with ``cos_min``).
        cos_min: the friction cone's cosine, or None (any entering direction).
        edge: ``(H,)`` bool, the hit lies on a triangle's edge or vertex, where the normal is
            a cone the sum of the hit triangles' normals may not represent: such entries pass
            the friction-cone test.
        target: ``(G,)`` per group, a line parameter (NaN: none): the valid entry nearest it is
            reported instead of the first (a prior on where the contact is).
    """
    dev = hits.t.device
    g = group[hits.ray]
    # order the hits by (group, t)
    o1 = torch.argsort(hits.t, stable=True)
    o2 = torch.argsort(g[o1], stable=True)
    order = o1[o2]
    g, t = g[order], hits.t[order]
    ent = hits.entering[order]
    H = len(t)
    same_prev = torch.zeros(H, dtype=torch.bool, device=dev)
    if H > 1:
        same_prev[1:] = (g[1:] == g[:-1]) & (ent[1:] == ent[:-1]) & ((t[1:] - t[:-1]) < dedup)
    keep = ~same_prev
    n_sum = on_edge = None
    cluster = torch.cumsum(keep.to(torch.int64), 0) - 1
    if normals is not None:  # per merged hit, the sum of its triangles' normals
        n_sum = normals.new_zeros(int(keep.sum()), 3)
        n_sum.index_add_(0, cluster, normals[order])
    if edge is not None:
        on_edge = torch.zeros(int(keep.sum()), dtype=torch.int64, device=dev)
        on_edge.index_add_(0, cluster, edge[order].to(torch.int64))
    order, g, t, ent = order[keep], g[keep], t[keep], ent[keep]
    # entries minus exits before each hit, within its group, never below zero (a mesh with a
    # hole may lack an entry): the walk clamped at 0 is W - min(0, running min of W)
    sign = ent.to(torch.int64) * 2 - 1
    before = torch.cumsum(sign, 0) - sign
    first = torch.searchsorted(g, g)  # index of the group's first hit (g is sorted)
    walk = before - before[first]  # starts at 0 in every group
    big = 2 * walk.numel() + 2  # later groups lie lower: a global running min stays per group
    low = torch.cummin(walk - g * big, 0).values + g * big
    depth = walk - low.clamp_max(0)
    valid = ent & (depth <= 0)
    outside_cone = torch.zeros(G, dtype=torch.bool, device=dev)
    if cos_min is not None and n_sum is not None and dirs is not None:
        # entries inside the friction cone if the group has any, else every entry (flagged)
        inward = -(dirs[order] * n_sum).sum(-1)
        cone = inward >= cos_min * n_sum.norm(dim=-1)
        if on_edge is not None:
            cone |= on_edge > 0
        has_cone = torch.zeros(G, dtype=torch.bool, device=dev)
        has_cone[g[valid & cone]] = True
        outside_cone[g[valid]] = True
        outside_cone &= ~has_cone
        valid &= cone | ~has_cone[g]
    any_hit = torch.zeros(G, dtype=torch.bool, device=dev)
    any_hit[g] = True
    vi = torch.nonzero(valid).reshape(-1)
    vg, vt = g[vi], t[vi]
    new = torch.ones(len(vi), dtype=torch.bool, device=dev)
    if len(vi) > 1:
        new[1:] = (vg[1:] != vg[:-1]) | ((vt[1:] - vt[:-1]) > merge)
    candidates = torch.zeros(G, dtype=torch.int64, device=dev)
    candidates.index_add_(0, vg, new.to(torch.int64))
    pick = torch.ones(len(vi), dtype=torch.bool, device=dev)
    if target is not None and len(vi):
        # the entry nearest the target parameter (ties and groups without one: the first)
        tg = target[vg]
        key = torch.where(torch.isnan(tg), torch.zeros_like(vt), (vt - tg).abs())
        best = torch.full((G,), math.inf, dtype=key.dtype, device=dev)
        best = best.scatter_reduce(0, vg, key, "amin")
        pick = key <= best[vg]
    vi_p, vg_p = vi[pick], vg[pick]
    firsts = vi_p[(torch.searchsorted(vg_p, vg_p) == torch.arange(len(vi_p), device=dev))]
    found = torch.zeros(G, dtype=torch.bool, device=dev)
    ray = torch.zeros(G, dtype=torch.int64, device=dev)
    tri = torch.zeros(G, dtype=torch.int64, device=dev)
    tsel = hits.t.new_zeros(G)
    fg = g[firsts]
    found[fg] = True
    ray[fg] = hits.ray[order[firsts]]
    tri[fg] = hits.tri[order[firsts]]
    tsel[fg] = t[firsts]
    normal = None
    if n_sum is not None:
        normal = n_sum.new_zeros(G, 3)
        ns = n_sum[firsts]
        normal[fg] = ns / ns.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(ns.dtype).tiny)
    return Selected(found, any_hit, ray, tri, tsel, candidates, normal, outside_cone)


# ------------------------------------------------------------------------------ the line program
def line_program(em: EstimationModel, candidates: Sequence[int], moving_base: bool):
    """Stage 1 as a program: every region's ``b`` and the candidate links' poses.

    Inputs: ``q, qd, qdd`` (nv), ``ft0 .. ft{S-1}`` (6 each), base motion (moving base). Outputs:
    ``b`` (6 S: per region, the contact wrench in its sensor frame about its origin), ``pose``
    (12 per candidate slot: ``R_sensor_link`` row-major, then ``p_sensor_link``) and ``status``
    (1: bit 1 for a non-finite input; such frames compute on zeros).

    Args:
        em: the estimation model whose slots are the candidate links (kind ``force``).
        candidates: slot indices to output poses of.
        moving_base: with IMU inputs.
    """
    S, nv = len(em.sensors), em.tree.nv
    inputs = {"q": nv, "qd": nv, "qdd": nv, **{f"ft{i}": 6 for i in range(S)}}
    if moving_base:
        inputs.update(omega=3, domega=3, proper_acc=3)
    base_keys = ("omega", "domega", "proper_acc") if moving_base else ()

    def fn(x: dict[str, list]) -> dict[str, list]:
        every = [v for k in inputs for v in x[k]]
        ok: object = True
        for v in every:
            ok = logical_and(ok, isfinite(v))

        def clean(v):
            return select(ok, v, 0.0)

        q, qd, qdd = ([clean(v) for v in x[k]] for k in ("q", "qd", "qdd"))
        readings = [[clean(v) for v in x[f"ft{i}"]] for i in range(S)]
        base = {k: [clean(v) for v in x[k]] for k in base_keys} if moving_base else None
        X, _, _, f = stages.forward(em, q, qd, qdd, base)
        _, _, b = stages.region_rhs(em, X, f, readings, {}, None, None)
        pose, posers = [], {}
        for k in candidates:
            slot = em.slots[k]
            if slot.region not in posers:
                posers[slot.region] = stages.body_in_sensor(em, X, slot.region)
            T = posers[slot.region](slot.body)
            R, p = sp.pose_compose(T, (slot.R, slot.p))
            pose += [v for row in R for v in row] + list(p)
        return {
            "b": [v for r in b for v in r[:6]],
            "pose": pose,
            "status": [select(logical_not(ok), float(_NONFINITE), 0.0)],
        }

    outputs = {"b": 6 * S, "pose": 12 * len(candidates), "status": 1}
    key = f"loc|{em.key}|{tuple(candidates)}|{moving_base}"
    return kernels.Program("localize", fn, inputs, outputs, key)


# ------------------------------------------------------------------------------ façade
class Localizer:
    """Localize one pure-force contact per F/T sensor region from its wrench and the meshes.

    Args:
        model: the robot; its dtype and device are those of the computation.
        meshes: the collision meshes (:func:`torchcontact.meshes.load_meshes`), a
            :class:`~torchcontact.meshes.RobotMeshes` or a mapping link -> :class:`LinkMesh`.
        links: the candidate links, or ``"subtree"``: every link with a mesh inside the regions
            of ``sensors``.
        sensors: the F/T sensors that cut the tree, as for :class:`~torchcontact.ContactEstimator`
            (default all of the model's); each region holding candidates gets one contact.
        force_threshold: below this force (N) a frame has no contact (status bit 2).
        merge_distance: valid entries closer than this along the line are one candidate, m.
        friction: friction coefficient ``mu``: a point is a candidate only where the force lies
            inside its friction cone, within ``atan(mu)`` of the inward normal (default 1, 45
            degrees); None accepts any inward force. Lines whose entries all lie outside the
            cone keep them (status bit 64).
        snap_distance: a line that meets no candidate (noise near a silhouette) takes the
            nearest edge point of a triangle facing the force if it passes within this
            distance, m (status bit 128); 0 disables it.
        ray: ray casting backend, one of :data:`RAY_BACKENDS`: ``"torch"`` (tree traversal in
            torch, any device), ``"brute"`` (every triangle), ``"embree"`` (embreex,
            computed on the CPU); ``"auto"``: Embree for a CPU model when ``embreex`` is
            installed (about 10x the torch traversal there), else torch.
        backend: backend of the line program (:mod:`torchcontact.kernels`).
        leaf_size: most triangles per tree leaf.

    Raises:
        InputError: an unknown link, a link outside every sensor's region, a link without
            collision geometry, an unknown sensor or ray backend.

    Example:
        >>> import torch, trimesh, torchcontact as tc
        >>> from torchcontact.meshes import LinkMesh
        >>> model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
        >>> fr = model.frame("hand")
        >>> mesh = LinkMesh("hand", fr.body, box.vertices, box.faces, fr.R_body_frame,
        ...                 fr.p_body_frame, None, ("box",))
        >>> loc = Localizer(model, {"hand": mesh}, links=["hand"])
        >>> q = torch.zeros(1, model.nv, dtype=torch.float64)
        >>> push = torch.tensor([[0, 0, -5.0, 0, 0, 0]], dtype=torch.float64)  # on the top face
        >>> pos = torch.tensor([[[0.01, 0.02, 0.05]]], dtype=torch.float64)
        >>> est = tc.ContactEstimator(model)
        >>> ft = est.predict_ft(q, q, q, tc.Contacts(["hand"], ["known"], pos,
        ...                     wrenches=push[:, None]))
        >>> r = loc.localize(q, q, q, ft)["base_ft"]
        >>> r.status.tolist(), r.position.round(decimals=6).tolist()
        ([0], [[0.01, 0.02, 0.05]])
    """

    def __init__(
        self,
        model: RobotModel,
        meshes: RobotMeshes | Mapping[str, LinkMesh],
        links: Sequence[str] | str = "subtree",
        sensors: Sequence[str] | None = None,
        *,
        force_threshold: float = 1.0,
        merge_distance: float = 1e-3,
        friction: float | None = 1.0,
        snap_distance: float = 2e-3,
        ray: str = "auto",
        backend: str = "auto",
        leaf_size: int = 4,
    ) -> None:
        if ray not in RAY_BACKENDS:
            raise InputError(f"unknown ray backend {ray!r}; expected one of {RAY_BACKENDS}")
        if backend not in kernels.BACKENDS:
            raise InputError(f"unknown backend {backend!r}; expected one of {kernels.BACKENDS}")
        if not force_threshold >= 0:
            raise InputError(f"force_threshold must be >= 0 N, got {force_threshold!r}")
        if not merge_distance >= 0:
            raise InputError(f"merge_distance must be >= 0 m, got {merge_distance!r}")
        if friction is not None and not (0 < friction < math.inf):
            raise InputError(f"friction must be a finite number > 0 or None, got {friction!r}")
        missing: dict[str, str] = {}
        if isinstance(meshes, RobotMeshes):
            if meshes.kind != "collision":
                raise InputError(f"localization needs collision meshes, got {meshes.kind} ones")
            for link, fname, why in meshes.missing:
                missing.setdefault(link, f"{fname}: {why}")
            meshes = meshes.links
        names = list(model.ft_sensors) if sensors is None else list(sensors)
        em0 = EstimationModel.build(model, names, (), ())  # validates the sensors
        region = em0.region_of_body
        if isinstance(links, str):
            if links != "subtree":
                raise InputError(f"links must be a list of link names or 'subtree', got {links!r}")
            links = [n for n, m in meshes.items() if region[model.frame(n).body] >= 0]
            if not links:
                raise InputError(
                    f"no link with collision geometry lies in the regions of sensors {names}"
                )
        links = list(dict.fromkeys(links))
        if not links:
            raise InputError("links: name at least one candidate link")
        unknown = [n for n in links if n not in model.frames]
        if unknown:
            raise InputError(f"links {unknown} are not links of {model.name}")
        outside = [n for n in links if region[model.frame(n).body] < 0]
        if outside:
            raise InputError(
                f"links {outside} lie outside the subtree of every F/T sensor {names}: no sensor"
                " measures a contact there"
            )
        bare = [n for n in links if n not in meshes]
        if bare:
            why = "; ".join(f"{n}: {missing[n]}" for n in bare if n in missing)
            raise InputError(
                f"links {bare} have no collision geometry" + (f" ({why})" if why else "")
            )
        self.model = model
        self.links: tuple[str, ...] = tuple(links)
        self.meshes = tuple(meshes[n] for n in links)
        self.force_threshold = float(force_threshold)
        self.merge_distance = float(merge_distance)
        self.friction = None if friction is None else float(friction)
        if not snap_distance >= 0:
            raise InputError(f"snap_distance must be >= 0 m, got {snap_distance!r}")
        self.snap_distance = float(snap_distance)
        if ray == "auto":  # Embree is the faster on CPU (benchmarks/localize.py)
            ray = "embree" if model.device.type == "cpu" and embree_available() else "torch"
        self.ray = ray
        if self.ray == "embree" and not embree_available():
            raise MissingExtraError("embreex", "meshes")
        self.backend = backend
        self.em = EstimationModel.build(model, names, self.links, ("force",) * len(self.links))
        self.estimator_sensors = tuple(names)
        regs = sorted({s.region for s in self.em.slots})
        #: the sensors that localize a contact (those whose region holds candidates)
        self.sensor_names: tuple[str, ...] = tuple(names[r] for r in regs)
        self._slots_of = {names[r]: [k for k, s in enumerate(self.em.slots) if s.region == r]
                          for r in regs}  # fmt: skip
        self.triangles = TriangleSet.build(
            self.meshes, leaf_size, dtype=model.dtype, device=model.device
        )

    def region_links(self, sensor: str) -> tuple[str, ...]:
        """The candidate links of one sensor's region."""
        return tuple(self.links[k] for k in self._slots_of[sensor])

    def localize(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        ft: Mapping[str, Tensor],
        *,
        base: BaseMotion | None = None,
        ft_covariance: Mapping[str, Tensor] | None = None,
        chunk_size: int | None = 65536,
        prior: Mapping[str, tuple[Tensor, ...]] | None = None,
        hold_distance: float = 0.0,
    ) -> dict[str, Localization]:
        """Localize the contact of every frame in each sensor's region.

        Args:
            q: ``(*B, nv)`` joint positions, ``model.joint_names`` order.
            qd: ``(*B, nv)`` joint velocities.
            qdd: ``(*B, nv)`` joint accelerations.
            ft: sensor name -> ``(*B, 6)`` reading ``[N; N m]`` (every sensor of
                ``estimator_sensors``), sensor frame and declared direction.
            base: IMU measurement of a moving base (else ``model.gravity`` on a fixed base).
            ft_covariance: sensor name -> ``(6, 6)`` or ``(*B, 6, 6)`` covariance of its reading
                noise: fills ``covariance`` and ``position_std``.
            chunk_size: frames per eager call of the line program (kernels take any batch).
            prior: sensor name -> ``(link (*B,), position (*B, 3))``, where each frame's contact
                is expected: an index into :attr:`links` (-1: no prior) and a point in that
                link's frame, m (e.g. the previous frame's ``link`` and ``position``). A frame
                whose line enters the links at several points reports the one nearest the prior
                point (status bit 256, ``PRIOR``, instead of 16, ``AMBIGUOUS``); other frames
                are unchanged. For a sequence of frames, :meth:`localize_sequence` finds the
                priors itself. An optional third tensor ``(*B, 3)``: the outward normal there.
            hold_distance: with ``prior``: a frame whose line passes within this distance of
                its prior point (m) but that reports another link or no point reports the prior
                point (bit 256); 0 (default): never.

        Returns:
            localizing sensor name -> :class:`Localization` with ``(*B, ...)`` fields.

        Raises:
            InputError: wrong shapes, dtype or device; a missing or unknown sensor reading.
                Non-finite values do not raise: the frame gets status bit 1.
        """
        model, nv = self.model, self.model.nv
        for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
            check_input(name, x, (nv,), model, f"(*B, {nv})", finite=False)
        batch = q.shape[:-1]
        if qd.shape[:-1] != batch or qdd.shape[:-1] != batch:
            raise InputError("q, qd, qdd must share their batch shape")
        n = math.prod(batch)
        names = self.estimator_sensors
        missing = [s for s in names if s not in ft]
        if missing:
            raise InputError(f"ft is missing readings of sensors {missing} (keys: {list(ft)})")
        extra = [s for s in ft if s not in names]
        if extra:
            raise InputError(f"ft has readings of unknown or unused sensors {extra}")
        unknown_prior = [s for s in (prior or {}) if s not in self.sensor_names]
        if unknown_prior:
            raise InputError(f"prior names sensors {unknown_prior} that localize no contact"
                             f" (localizing: {list(self.sensor_names)})")  # fmt: skip

        def per_frame(name: str, x: Tensor, trailing: tuple[int, ...]) -> Tensor:
            shape = f"(*B, {', '.join(map(str, trailing))})"
            check_input(name, x, trailing, model, shape, finite=False)
            if x.shape[: x.dim() - len(trailing)] != batch:
                raise InputError(f"{name} must be {shape} with B={tuple(batch)}, got"
                                 f" {tuple(x.shape)}")  # fmt: skip
            return flatten_batch(x, batch, len(trailing)).reshape(n, math.prod(trailing))

        tensors = {k: per_frame(k, x, (nv,)) for k, x in (("q", q), ("qd", qd), ("qdd", qdd))}
        for i, s in enumerate(names):
            tensors[f"ft{i}"] = per_frame(f"ft[{s!r}]", ft[s], (6,))
        if base is not None:
            for k in BaseMotion._fields:
                tensors[k] = per_frame(f"base.{k}", getattr(base, k), (3,))
        cands = list(range(len(self.links)))
        prog = self.em._programs.get(("localize", base is not None))
        if prog is None:
            prog = line_program(self.em, cands, base is not None)
            self.em._programs[("localize", base is not None)] = prog
        out = run_program(prog, tensors, self.backend, chunk_size)
        status0 = counts(out["status"][:, 0])
        pose = out["pose"].reshape(n, len(cands), 12)
        R_all = pose[..., :9].reshape(n, len(cands), 3, 3)
        p_all = pose[..., 9:]
        result = {}
        for s in self.sensor_names:
            r = names.index(s)
            slots = self._slots_of[s]
            b = out["b"][:, 6 * r : 6 * r + 6]
            cov = None
            if ft_covariance is not None and s in ft_covariance:
                c = ft_covariance[s]
                check_input(f"ft_covariance[{s!r}]", c, (6, 6), model, "(6, 6) or (*B, 6, 6)")
                cov = c.expand(*batch, 6, 6).reshape(n, 6, 6)
            pr = None
            if prior is not None and s in prior:
                pl, *rest = prior[s]
                shapes = [tuple(x.shape) for x in rest]
                if tuple(pl.shape) != tuple(batch) or shapes not in (
                    [(*batch, 3)],
                    [(*batch, 3)] * 2,
                ):
                    raise InputError(
                        f"prior[{s!r}] must be (link (*B,), position (*B, 3)[, normal (*B, 3)])"
                        f" with B={tuple(batch)}, got {[tuple(pl.shape), *shapes]}"
                    )
                pr = (pl.reshape(n), *(x.reshape(n, 3) for x in rest))
            loc = self.localize_wrench(
                b, R_all[:, slots], p_all[:, slots], s, status=status0, covariance=cov, prior=pr,
                hold_distance=hold_distance,
            )  # fmt: skip
            result[s] = Localization(*(None if v is None else v.reshape((*batch, *v.shape[1:]))
                                       for v in loc))  # fmt: skip
        return result

    def localize_sequence(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        ft: Mapping[str, Tensor],
        *,
        starts: Tensor | None = None,
        skip: Mapping[str, Tensor] | None = None,
        base: BaseMotion | None = None,
        ft_covariance: Mapping[str, Tensor] | None = None,
        chunk_size: int | None = 65536,
        hold_distance: float = 0.0,
    ) -> dict[str, Localization]:
        """Localize consecutive frames, resolving ambiguous ones by their neighbours' contacts.

        A contact persists over consecutive frames: an ambiguous frame (the line enters the
        links at several points) takes the candidate nearest the contact of the nearest
        unambiguous frame (status 0) of the same run of contact, before or after it
        (:func:`temporal_prior`); such frames get status bit 256 (``PRIOR``) instead of 16. A
        run is a stretch of consecutive frames above the force threshold within one time
        segment. Two passes, both batched: every frame, then the ambiguous frames with their
        priors (:meth:`localize` with ``prior``).

        Args:
            q: ``(N, nv)`` joint positions of consecutive frames; ``qd``, ``qdd`` likewise.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            ft: sensor name -> ``(N, 6)`` reading.
            starts: ``(N,)`` bool, True where a time segment starts (a gap in the stamps; see
                :func:`torchcontact.logs.derive.time_segments`); None: one segment.
            skip: sensor name -> ``(N,)`` bool, frames whose result is not used (e.g. with skin
                contacts in the region): they end runs and are no prior.
            base: as :meth:`localize`.
            ft_covariance: as :meth:`localize`.
            chunk_size: as :meth:`localize`.
            hold_distance: also hold the contact through the run's other frames: a frame of a
                run with a prior whose line passes within this distance (m) of the prior point
                but that reports another link, or none (noise moved the line off the link),
                reports the prior point (bit 256); 0 (default): only ambiguous frames change.

        Returns:
            localizing sensor name -> :class:`Localization` with ``(N, ...)`` fields.

        Raises:
            InputError: as :meth:`localize`; a batch that is not ``(N, nv)``; ``starts`` or
                ``skip`` not ``(N,)``.
        """
        if q.dim() != 2:
            raise InputError(f"q must be (N, {self.model.nv}) for a sequence, got {tuple(q.shape)}")
        n = q.shape[0]
        checks = [("starts", starts), *((f"skip[{k!r}]", v) for k, v in (skip or {}).items())]
        for name, x in checks:
            if x is not None and tuple(x.shape) != (n,):
                raise InputError(f"{name} must be ({n},) bool, got {tuple(x.shape)}")
        res = self.localize(q, qd, qdd, ft, base=base, ft_covariance=ft_covariance,
                            chunk_size=chunk_size)  # fmt: skip
        codes, priors, lone = {}, {}, {}
        for s, r in res.items():
            code = r.status
            if skip is not None and s in skip:
                code = torch.where(skip[s].to(code.device), code | int(LocalizeStatus.SKIN_CONTACT),
                                   code)  # fmt: skip
            codes[s] = code
            priors[s] = temporal_prior(code, r.link, r.position, starts, r.normal,
                                       every=hold_distance > 0)  # fmt: skip
            # ambiguous frames of runs without an unambiguous frame: their last entry too
            in_run = _runs(code, starts)[0]
            amb = in_run & ((code & _AMBIGUOUS) != 0) & (priors[s][0] < 0) & (r.link >= 0)
            f = r.force / r.force.norm(dim=-1, keepdim=True).clamp_min(1e-30)
            lone[s] = (torch.where(amb, r.link, -1),
                       torch.where(amb[:, None], r.position + 1e3 * f, math.nan))  # fmt: skip
        last = self._localize_with(q, qd, qdd, ft, lone, res, base, ft_covariance, chunk_size)
        for s, r in res.items():  # runs whose other hypothesis is the one that stays put
            lk, pp, pn = priors[s]
            amb = torch.nonzero(lone[s][0] >= 0).reshape(-1)
            if not len(amb):
                continue
            run = _runs(codes[s], starts)[1][amb]
            la = last[s]
            take_a, take_b = stationary_choice(run, r.link[amb], r.position[amb], la.link[amb],
                                               la.position[amb],
                                               floor=self.merge_distance)  # fmt: skip
            pick = torch.where(take_b[:, None], la.position[amb], r.position[amb])
            lk, pp = lk.clone(), pp.clone()
            lk[amb] = torch.where(take_a | take_b, torch.where(take_b, la.link[amb],
                                                               r.link[amb]), -1)  # fmt: skip
            pp[amb] = torch.where((take_a | take_b)[:, None], pick, math.nan)
            pn = pn.clone()
            pn[amb] = torch.where(take_b[:, None], la.normal[amb], r.normal[amb])
            priors[s] = (lk, pp, pn)
        return self._localize_with(q, qd, qdd, ft, priors, res, base, ft_covariance, chunk_size,
                                   hold_distance)  # fmt: skip

    def _localize_with(self, q, qd, qdd, ft, priors, res, base, ft_covariance, chunk_size,
                       hold_distance=0.0):  # fmt: skip
        """``res`` with the frames that have a prior (link >= 0) localized again with it."""
        n = q.shape[0]
        need = torch.zeros(n, dtype=torch.bool, device=q.device)
        for pl, *_ in priors.values():
            need |= (pl >= 0).to(need.device)
        idx = torch.nonzero(need).reshape(-1)
        if not len(idx):
            return res
        sub_base = None if base is None else BaseMotion(*(x[idx] for x in base))
        sub_cov = None
        if ft_covariance is not None:
            sub_cov = {k: c if c.dim() == 2 else c[idx] for k, c in ft_covariance.items()}
        sub = self.localize(
            q[idx], qd[idx], qdd[idx], {k: v[idx] for k, v in ft.items()}, base=sub_base,
            ft_covariance=sub_cov, chunk_size=chunk_size,
            prior={s: tuple(x[idx] for x in pr) for s, pr in priors.items()},
            hold_distance=hold_distance,
        )  # fmt: skip
        out = {}
        for s, r in res.items():
            used = torch.nonzero(priors[s][0][idx] >= 0).reshape(-1)
            where = idx[used]
            fields = []
            for full, part in zip(r, sub[s], strict=True):
                if full is None:
                    fields.append(None)
                    continue
                full = full.clone()
                full[where] = part[used]
                fields.append(full)
            out[s] = Localization(*fields)
        return out

    def localize_wrench(
        self,
        wrench: Tensor,
        R_sensor_link: Tensor,
        p_sensor_link: Tensor,
        sensor: str,
        *,
        status: Tensor | None = None,
        covariance: Tensor | None = None,
        prior: tuple[Tensor, ...] | None = None,
        hold_distance: float = 0.0,
    ) -> Localization:
        """Stages 2-5 for one sensor: localize from its region's ``b`` and the links' poses.

        Args:
            wrench: ``(N, 6)`` the region's ``b``: the contact wrench ``[force; moment about the
                sensor origin]`` in the sensor frame, N and N m.
            R_sensor_link: ``(N, L, 3, 3)`` rotation of each candidate link of the region
                (:meth:`region_links` order) in the sensor frame.
            p_sensor_link: ``(N, L, 3)`` origin of each candidate link in the sensor frame, m.
            sensor: the sensor's name.
            status: ``(N,)`` int64 status bits already set (frames with bit 1 are not cast).
            covariance: ``(N, 6, 6)`` covariance of the wrench (sensor frame), or None.
            prior: ``(link (N,), position (N, 3))``: per frame, where the contact is expected
                (an index into :attr:`links`, -1 for none, and a point in that link's frame, m):
                an ambiguous frame reports the entry nearest it (status bit 256 instead of 16).
                A third tensor ``(N, 3)``, the outward normal there (link frame), is optional.
            hold_distance: with a prior, a frame whose line passes within this distance of the
                prior point (m) but reports another link, or no point, reports the prior point
                itself (the contact held; bit 256, the bits 4, 8, 16, 64, 128 cleared); 0: never.

        Returns:
            :class:`Localization` with ``(N, ...)`` fields; ``link`` indexes :attr:`links`.
        """
        slots = self._slots_of[sensor]
        n, L = wrench.shape[0], len(slots)
        dtype, dev = wrench.dtype, wrench.device
        eps = torch.finfo(dtype).eps
        status = torch.zeros(n, dtype=torch.int64, device=dev) if status is None else status
        bad_in = ~torch.isfinite(wrench).all(-1) | ((status & _NONFINITE) != 0)
        f, m = wrench[:, :3], wrench[:, 3:]
        fn2 = (f * f).sum(-1)
        fn = fn2.sqrt()
        weak = ~bad_in & ~(fn >= max(self.force_threshold, 1e-30))
        live = ~bad_in & ~weak
        safe = torch.where(live, fn2, torch.ones_like(fn2))
        u = f / safe.sqrt().unsqueeze(-1)
        a = torch.linalg.cross(f, m) / safe.unsqueeze(-1)  # the line's point nearest the origin
        # ---- stage 2: the line in each candidate link's frame
        frames = torch.nonzero(live).reshape(-1)
        Rl, pl = R_sensor_link[frames], p_sensor_link[frames]  # (n', L, 3, 3), (n', L, 3)
        orig = torch.einsum("nlji,nlj->nli", Rl, a[frames].unsqueeze(1) - pl).reshape(-1, 3)
        dirs = torch.einsum("nlji,nj->nli", Rl, u[frames]).reshape(-1, 3)
        slot_t = torch.as_tensor(slots, device=dev)
        ray_link = slot_t.repeat(len(frames))  # index into self.links / triangle-set links
        group = torch.arange(len(frames), device=dev).repeat_interleave(L)
        # ---- stage 3: ray casting
        ts = self.triangles
        if ts.v0.dtype != dtype or ts.v0.device != dev:
            ts = ts.to(dev, dtype)
        if self.ray == "brute":
            hits = cast_brute(ts, orig, dirs, ray_link)
        elif self.ray == "embree":
            hits = cast_embree(self.meshes, ts, orig, dirs, ray_link)
        else:
            hits = cast_bvh(ts, orig, dirs, ray_link)
        # ---- stage 4: the first valid entry along the force
        scale = 1.0 + float(a.abs().max()) if len(frames) else 1.0
        dedup = max(1e-9, 1e3 * eps) * scale
        cos_min = None if self.friction is None else 1.0 / math.sqrt(1.0 + self.friction**2)
        # edges and vertices pass the friction-cone test; only entries are tested there
        edge = torch.zeros_like(hits.entering)
        e_in = torch.nonzero(hits.entering).reshape(-1)
        sub = Hits(*(x[e_in] for x in hits))
        edge[e_in] = _on_edge(ts, orig, dirs, sub, max(1e-9, 1e3 * eps))
        target = None
        if prior is not None:
            target, p_local, p_ok, p_s = self._prior_parameter(prior, frames, slots, Rl, pl, a, u)
        sel = select_entries(hits, group, len(frames), self.merge_distance, dedup,
                             ts.normal[hits.tri], dirs[hits.ray], cos_min, edge,
                             target)  # fmt: skip
        nan = float("nan")
        link = torch.full((n,), -1, dtype=torch.int64, device=dev)
        position = wrench.new_full((n, 3), nan)
        normal = wrench.new_full((n, 3), nan)
        force = wrench.new_full((n, 3), nan)
        candidates = torch.zeros(n, dtype=torch.int64, device=dev)
        code = status.clone()
        code |= torch.where(bad_in, _NONFINITE, 0)
        code |= torch.where(weak, _NO_CONTACT, 0)
        pull = frames[sel.any_hit & ~sel.found]
        code[pull] |= _PULLING
        candidates[frames] = sel.candidates
        if target is None:
            code[frames[sel.candidates > 1]] |= _AMBIGUOUS
        else:  # the prior chose among the candidates
            resolved = ~torch.isnan(target)
            code[frames[(sel.candidates > 1) & ~resolved]] |= _AMBIGUOUS
            code[frames[(sel.candidates > 1) & resolved]] |= _PRIOR
        code[frames[sel.outside_cone]] |= _OUTSIDE_CONE
        found, ray_sel = sel.found.clone(), sel.ray.clone()
        pt_sel = orig[ray_sel] + sel.t.unsqueeze(-1) * dirs[ray_sel]
        nrm_sel = sel.normal
        # a line that meets nothing: the nearest edge point facing the force, if close enough
        gone = torch.nonzero(~sel.any_hit).reshape(-1)
        if len(gone) and self.snap_distance > 0:
            rr = (gone.unsqueeze(1) * L + torch.arange(L, device=dev)).reshape(-1)
            dist, pnt, tri = _nearest_facing_edge(ts, orig, dirs, rr, ray_link[rr])
            dist, pnt, tri = dist.reshape(-1, L), pnt.reshape(-1, L, 3), tri.reshape(-1, L)
            best = dist.argmin(1)
            ar = torch.arange(len(gone), device=dev)
            close = dist[ar, best] <= self.snap_distance
            g2 = gone[close]
            found[g2] = True
            ray_sel[g2] = rr.reshape(-1, L)[ar, best][close]
            pt_sel[g2] = pnt[ar, best][close]
            nrm_sel[g2] = ts.normal[tri[ar, best][close]]
            code[frames[g2]] |= _SNAPPED
            code[frames[gone[~close]]] |= _MISS
        else:
            code[frames[gone]] |= _MISS
        if prior is not None and hold_distance > 0 and len(frames):
            # the contact held: the line passes the prior point within the distance, but the
            # frame reports another link or nothing
            off = p_s - a[frames]
            off = off - (off * u[frames]).sum(-1, keepdim=True) * u[frames]
            ray_p = torch.arange(len(frames), device=dev) * L + p_local
            hold = p_ok & (off.norm(dim=-1) <= hold_distance)
            hold &= ~found | (ray_link[ray_sel] != ray_link[ray_p])
            h = torch.nonzero(hold).reshape(-1)
            found[h] = True
            ray_sel[h] = ray_p[h]
            pt_sel[h] = prior[1].to(device=dev, dtype=dtype)[frames[h]]
            if nrm_sel is not None:
                nrm_sel[h] = (prior[2].to(device=dev, dtype=dtype)[frames[h]] if len(prior) > 2
                              else nan)  # fmt: skip
            held = frames[h]
            code[held] = (code[held] & ~(_MISS | _PULLING | _AMBIGUOUS | _OUTSIDE_CONE | _SNAPPED)
                          ) | _PRIOR  # fmt: skip
        fr_found = frames[found]
        rays = ray_sel[found]
        li = ray_link[rays]
        link[fr_found] = li
        pt = pt_sel[found]
        position[fr_found] = pt
        normal[fr_found] = nrm_sel[found]
        # the pure-force estimate in the link frame
        local = rays % L
        R_hit = R_sensor_link[fr_found, local]  # (h, 3, 3)
        force[fr_found] = torch.einsum("hji,hj->hi", R_hit, f[fr_found])
        moment_residual = torch.where(
            live, (u * m).sum(-1).abs(), torch.where(weak, (m * m).sum(-1).sqrt(), nan)
        )
        wrench_out = torch.where(bad_in.unsqueeze(-1), nan, wrench)
        cov = std = None
        if covariance is not None:
            cov = wrench.new_full((n, 3, 3), nan)
            if len(fr_found):
                s_hit = ((pt - orig[rays]) * dirs[rays]).sum(-1)
                n_s = torch.einsum("hij,hj->hi", R_hit, normal[fr_found])
                C = _point_covariance(f[fr_found], m[fr_found], s_hit, n_s,
                                      covariance[fr_found])  # fmt: skip
                cov[fr_found] = R_hit.transpose(-1, -2) @ C @ R_hit
            std = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1).clamp_min(0).sqrt()
        return Localization(link, position, normal, force, moment_residual, candidates, code,
                            wrench_out, cov, std)  # fmt: skip

    def _prior_parameter(
        self,
        prior: tuple[Tensor, Tensor],
        frames: Tensor,
        slots: Sequence[int],
        R: Tensor,
        p: Tensor,
        a: Tensor,
        u: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(n',)`` the line parameter nearest each live frame's prior point (NaN: no prior).

        Also returns the prior link's index among ``slots``, whether the frame has a prior, and
        the prior point in the sensor frame ``(n', 3)``.

        The prior point, in its link's frame, is posed in the sensor frame by the frame's own
        pose of that link (``R``, ``p``: ``(n', L, ...)`` of the live ``frames``); the line
        parameter is the same in every link's frame (``point = a + t u``, sensor frame), so the
        candidate nearest the prior point is the one whose parameter is nearest this.
        """
        link, pos = prior[0], prior[1]
        n = a.shape[0]
        if link.shape != (n,) or pos.shape != (n, 3):
            raise InputError(f"prior must be (link (N,), position (N, 3)) with N={n}, got"
                             f" {tuple(link.shape)} and {tuple(pos.shape)}")  # fmt: skip
        dev = a.device
        local_of = torch.full((len(self.links) + 1,), -1, dtype=torch.int64, device=dev)
        local_of[torch.as_tensor(slots, device=dev)] = torch.arange(len(slots), device=dev)
        lk = link.to(device=dev, dtype=torch.int64)[frames]
        ok = (lk >= 0) & (lk < len(self.links))
        local = local_of[torch.where(ok, lk, len(self.links))]
        ok &= local >= 0  # a link of this sensor's region
        pp = pos.to(device=dev, dtype=a.dtype)[frames]
        ok &= torch.isfinite(pp).all(-1)
        li = local.clamp_min(0)
        ar = torch.arange(len(frames), device=dev)
        p_s = torch.einsum("nij,nj->ni", R[ar, li], torch.where(ok[:, None], pp, 0.0)) + p[ar, li]
        t = ((p_s - a[frames]) * u[frames]).sum(-1)
        return torch.where(ok, t, torch.full_like(t, math.nan)), li, ok, p_s


def _runs(status: Tensor, starts: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """``(in_run, first, last)`` ``(N,)``: the frames in a run of contact, its first and last.

    A run: consecutive frames without the bits 1, 2, 32, cut at time segment starts.
    """
    n = status.shape[0]
    dev = status.device
    idx = torch.arange(n, device=dev)
    in_run = (status & (_NONFINITE | _NO_CONTACT | int(LocalizeStatus.SKIN_CONTACT))) == 0
    seg = torch.zeros(n, dtype=torch.bool, device=dev) if starts is None else starts.to(dev)
    prev_in = torch.zeros(n, dtype=torch.bool, device=dev)
    next_in = torch.zeros(n, dtype=torch.bool, device=dev)
    if n > 1:
        prev_in[1:] = in_run[:-1] & ~seg[1:]
        next_in[:-1] = in_run[1:] & ~seg[1:]
    if n == 0:
        return in_run, idx, idx
    run_lo = torch.cummax(torch.where(in_run & ~prev_in, idx, -1), 0).values
    run_hi = torch.flip(torch.cummin(torch.flip(torch.where(in_run & ~next_in, idx, n), [0]),
                                     0).values, [0])  # fmt: skip
    return in_run, run_lo, run_hi


def stationary_choice(
    run: Tensor,
    link_a: Tensor,
    pos_a: Tensor,
    link_b: Tensor,
    pos_b: Tensor,
    ratio: float = 0.5,
    floor: float = 1e-3,
) -> tuple[Tensor, Tensor]:
    """Which of two hypotheses of each run's contact keeps its point fixed on its link.

    A contact that lasts stays at one point of its link (no sliding), while the line of action
    moves with the arm: the wrong one of two candidates (the first and the last entry of an
    ambiguous line) wanders over the other link's surface. Per run, the root-mean-square spread
    of each hypothesis's points (link frame) about their mean is compared; a hypothesis whose
    link changes within the run is out.

    Args:
        run: ``(K,)`` int64 run key of each frame (e.g. the index of its run's first frame).
        link_a: ``(K,)`` int64 link of hypothesis A per frame; ``pos_a`` ``(K, 3)`` its point.
        pos_a: ``(K, 3)`` m, link frame.
        link_b: ``(K,)`` int64 link of hypothesis B; ``pos_b`` ``(K, 3)``.
        pos_b: ``(K, 3)`` m.
        ratio: a hypothesis wins when its spread is below ``ratio`` times the other's...
        floor: ... and the other's is above ``floor``, m (two points that both stay put, as on
            a robot at rest, decide nothing).

    Returns:
        ``(take_a, take_b)`` ``(K,)`` bool per frame: its run chose A, or B (neither: undecided;
        runs of fewer than 3 frames are undecided).

    Example:
        >>> run = torch.zeros(4, dtype=torch.int64)
        >>> a = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0]])
        >>> b = torch.tensor([[0.0, 0.1, 0]]).expand(4, 3) + 1e-4
        >>> stationary_choice(run, torch.zeros(4, dtype=torch.int64), a,
        ...                   torch.ones(4, dtype=torch.int64), b)[1].tolist()
        [True, True, True, True]
    """
    K = run.shape[0]
    dev = run.device
    if K == 0:
        z = torch.zeros(0, dtype=torch.bool, device=dev)
        return z, z
    keys, inv = torch.unique(run, return_inverse=True)
    G = len(keys)
    cnt = torch.zeros(G, dtype=pos_a.dtype, device=dev).index_add_(0, inv, torch.ones_like(
        pos_a[:, 0]))  # fmt: skip

    def spread(link: Tensor, pos: Tensor) -> Tensor:
        lo = torch.full((G,), link.numel() + 1, dtype=link.dtype, device=dev)
        lo = lo.scatter_reduce(0, inv, link, "amin")
        hi = torch.full((G,), -1, dtype=link.dtype, device=dev).scatter_reduce(0, inv, link, "amax")
        mean = torch.zeros(G, 3, dtype=pos.dtype, device=dev).index_add_(0, inv, pos)
        mean = mean / cnt[:, None]
        sq = ((pos - mean[inv]) ** 2).sum(-1)
        var = torch.zeros(G, dtype=pos.dtype, device=dev).index_add_(0, inv, sq) / cnt
        bad = (lo != hi) | (lo < 0) | ~torch.isfinite(var)
        return torch.where(bad, math.inf, var.sqrt())

    sa, sb = spread(link_a, pos_a), spread(link_b, pos_b)
    enough = cnt >= 3
    pick_a = enough & torch.isfinite(sa) & (sa < ratio * sb) & (sb > floor)
    pick_b = enough & torch.isfinite(sb) & (sb < ratio * sa) & (sa > floor)
    return pick_a[inv], pick_b[inv]


def temporal_prior(
    status: Tensor,
    link: Tensor,
    position: Tensor,
    starts: Tensor | None = None,
    normal: Tensor | None = None,
    every: bool = False,
) -> tuple[Tensor, ...]:
    """For each ambiguous frame of a sequence, the contact of its nearest unambiguous neighbour.

    A contact persists while it lasts: within a *run* (consecutive frames whose status has none
    of the bits 1, 2, 32: a force above the threshold, finite input, no skin contact; cut at
    time segment starts), an ambiguous frame (bit 16) takes as its prior the link and point of
    the nearest frame with status 0 of the same run (the earlier one on a tie) on the link that
    at least two thirds of the run's status-0 frames are on (noise near a silhouette flips a few
    frames to the other link; a run without such a majority gets no prior). Vectorised with
    running maxima and minima of frame indices and per-run votes, no loop over frames.

    Args:
        status: ``(N,)`` int64 localization status bits (:data:`LOCALIZE_STATUS`).
        link: ``(N,)`` int64 link index (-1 none).
        position: ``(N, 3)`` contact point in the link's frame, m.
        starts: ``(N,)`` bool, True where a time segment starts; None: one segment.
        normal: ``(N, 3)`` outward normals (link frame): the prior's normal is returned too.
        every: a prior for every frame of a run but its anchors (the status-0 frames on the
            majority link), not only for the ambiguous ones (``hold_distance``).

    Returns:
        ``(prior_link (N,), prior_position (N, 3)[, prior_normal (N, 3)])``: -1 and NaN where a
        frame is not ambiguous or its run has no unambiguous frame; the
        :meth:`Localizer.localize` ``prior`` format.

    Example:
        >>> st = torch.tensor([0, 16, 16, 2, 16, 0])
        >>> lk = torch.tensor([1, 0, 0, -1, 0, 1])
        >>> pos = torch.arange(18.0).reshape(6, 3)
        >>> pl, pp = temporal_prior(st, lk, pos)
        >>> pl.tolist(), pp[1].tolist(), pp[4].tolist()
        ([-1, 1, 1, -1, 1, -1], [0.0, 1.0, 2.0], [15.0, 16.0, 17.0])
    """
    n = status.shape[0]
    idx = torch.arange(n, device=status.device)
    in_run, run_lo, run_hi = _runs(status, starts)
    anchor = in_run & (status == 0) & (link >= 0)
    if n:  # only the anchors on the link most of the run's anchors are on (noise flips a few)
        L = int(link.max().clamp_min(0)) + 1
        votes = torch.zeros(n, L, dtype=torch.int64, device=idx.device)
        votes.index_put_((run_lo[anchor], link[anchor]), torch.ones_like(link[anchor]),
                         accumulate=True)  # fmt: skip
        best, top = votes.max(1)
        clear = 3 * best >= 2 * votes.sum(1)  # two thirds of the run's anchors on one link
        rl = run_lo.clamp_min(0)
        anchor &= (link == top[rl]) & clear[rl]
    before = torch.cummax(torch.where(anchor, idx, -1), 0).values
    after = torch.flip(torch.cummin(torch.flip(torch.where(anchor, idx, n), [0]), 0).values, [0])
    ok_b = before >= run_lo
    ok_a = (after <= run_hi) & (after < n)
    take_b = ok_b & (~ok_a | (idx - before <= after - idx))
    src = torch.where(take_b, before, after)
    use = in_run & (~anchor if every else (status & _AMBIGUOUS) != 0) & (ok_b | ok_a)
    src = torch.where(use, src, 0).clamp(0, max(n - 1, 0))
    prior_link = torch.where(use, link[src], -1) if n else link.clone()
    prior_pos = torch.where(use[:, None], position[src], math.nan) if n else position.clone()
    if normal is None:
        return prior_link, prior_pos
    prior_n = torch.where(use[:, None], normal[src], math.nan) if n else normal.clone()
    return prior_link, prior_pos, prior_n


def _point_covariance(f: Tensor, m: Tensor, s: Tensor, n: Tensor, sigma: Tensor) -> Tensor:
    """``J Sigma J^T`` of the hit point ``p = a + s u`` on the plane of normal ``n`` (sensor frame).

    ``a = f x m / |f|^2``, ``u = f / |f|``; moving the wrench moves the line, and the point moves
    along the plane: ``dp = Q (da + s du)`` with ``Q = I - u n^T / (n . u)``.
    """
    phi = (f * f).sum(-1)
    fn = phi.sqrt()
    u = f / fn.unsqueeze(-1)
    eye = torch.eye(3, dtype=f.dtype, device=f.device).expand(f.shape[0], 3, 3)
    nu = (n * u).sum(-1)
    Q = eye - u.unsqueeze(-1) * n.unsqueeze(-2) / nu[:, None, None]
    fxm = torch.linalg.cross(f, m)
    Jm = Q @ sp.skew(f) / phi[:, None, None]
    da_df = (
        -sp.skew(m) / phi[:, None, None]
        - 2 * fxm.unsqueeze(-1) * f.unsqueeze(-2) / (phi * phi)[:, None, None]
    )
    du_df = (eye - u.unsqueeze(-1) * u.unsqueeze(-2)) / fn[:, None, None]
    Jf = Q @ (da_df + s[:, None, None] * du_df)
    J = torch.cat([Jf, Jm], -1)  # (h, 3, 6)
    return J @ sigma @ J.transpose(-1, -2)


# ------------------------------------------------------------------------------ log chunks
class LocalizedChunk(NamedTuple):
    """One log chunk with its localized contacts (:func:`localize_chunk`).

    Attributes:
        records: the chunk's contact records with one ``force`` record added per localized
            contact (link, point, outward normal), ordered by frame.
        source: ``(M',)`` int64 per record of ``records``, the index of the input record it is,
            -1 for an added one (take the input's other struct fields with it; null for -1).
        columns: the localization columns, name -> pyarrow array of the chunk's rows, in the
            order of :func:`torchcontact.logs.format.localization_fields`.
        results: localizing sensor -> the :class:`Localization` (numpy-convertible tensors).
    """

    records: object
    source: np.ndarray
    columns: dict
    results: dict[str, Localization]


def localized_frames(
    code: np.ndarray, has_point: np.ndarray, accept_ambiguous: bool = False
) -> np.ndarray:
    """The frames whose localized contact is added to the estimate (``estimate --localize``).

    A frame's contact is used when it has a point and no status bit but the caveats
    ``OUTSIDE_CONE`` (64) and ``NEAR_MISS`` (128), and ``AMBIGUOUS`` (16) with
    ``accept_ambiguous``.

    Args:
        code: ``(N,)`` int localization status codes (:data:`LOCALIZE_STATUS` bits).
        has_point: ``(N,)`` bool, the frame has a contact point (a link).
        accept_ambiguous: also use ambiguous frames' first candidate.

    Returns:
        ``(N,)`` bool.

    Example:
        >>> localized_frames(np.array([0, 16, 64, 2]), np.array([True, True, True, False]))
        array([ True, False,  True, False])
    """
    soft = SOFT_BITS if accept_ambiguous else SOFT_BITS & ~_AMBIGUOUS
    return ((np.asarray(code) & ~soft) == 0) & np.asarray(has_point, bool)


def localize_chunk(
    localizer: Localizer,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    ft: Mapping[str, np.ndarray],
    records: object,
    *,
    base: Mapping[str, np.ndarray] | None = None,
    ft_covariance: Mapping[str, np.ndarray] | None = None,
    accept_ambiguous: bool = False,
    starts: np.ndarray | None = None,
    temporal: bool = False,
) -> LocalizedChunk:
    """Localize the contacts of a decoded log chunk and add them as ``force`` records.

    The per-chunk part of ``torchcontact estimate --localize``: in each localizing sensor's
    region, a frame without a skin contact there (no record on a link of the region) gets the
    localized contact as a ``force`` record at the point (with its outward normal), so that the
    estimator then runs as usual on the records; frames with skin contacts in the region keep
    theirs (status bit 32). Everything is vectorised over the chunk's frames.

    Args:
        localizer: the :class:`Localizer` (its model's dtype and device are used).
        q: ``(N, nv)`` joint positions in the model's order; ``qd``, ``qdd`` likewise.
        qd: ``(N, nv)``.
        qdd: ``(N, nv)``.
        ft: sensor -> ``(N, 6)`` readings (every sensor of ``localizer.estimator_sensors``).
        records: the chunk's skin contact records
            (:class:`~torchcontact.contacts.ContactRecords`, frames ``0 .. N-1``): a frame with
            a record on a link of a region is not localized there.
        base: ``omega``, ``domega``, ``proper_acc`` -> ``(N, 3)`` IMU of a moving base, or None.
        ft_covariance: sensor -> ``(6, 6)`` reading noise covariance (fills the position std).
        accept_ambiguous: also add the first candidate of ambiguous frames (status 16); frames
            flagged outside the friction cone (64) or snapped (128) are always added.
        starts: ``(N,)`` bool, True where a time segment starts (with ``temporal``; None: the
            chunk is one segment).
        temporal: resolve ambiguous frames by their neighbours' contacts
            (:meth:`Localizer.localize_sequence`; frames with skin contacts in the region end
            runs); such frames (status 256) are added.

    Returns:
        :class:`LocalizedChunk`.
    """
    import pyarrow as pa

    from torchcontact.contacts import ContactRecords
    from torchcontact.logs.format import (
        fixed_list,
        localization_fields,
        numpy_to_arrow,
        string_array,
    )
    from torchcontact.status import localize_messages

    model = localizer.model
    N = q.shape[0]

    def t(x: np.ndarray) -> Tensor:
        return torch.tensor(np.asarray(x, np.float64), dtype=model.dtype, device=model.device)

    bm = None if not base else BaseMotion(*(t(base[k]) for k in BaseMotion._fields))
    cov = None
    if ft_covariance:
        cov = {s: t(c) for s, c in ft_covariance.items()}
    recs: ContactRecords = records  # type: ignore[assignment]
    # the region of each input record's link (-1: outside, or not a frame)
    region = localizer.em.region_of_body
    ln, lc, _, _ = recs.name_codes()
    rec_region = np.array([region[model.frame(n).body] if isinstance(n, str) and n in
                           model.frames else -1 for n in ln], np.int64)[lc]  # fmt: skip
    names = localizer.estimator_sensors
    skins = {}
    for s in localizer.sensor_names:
        skins[s] = np.zeros(N, bool)
        skins[s][recs.frame[rec_region == names.index(s)]] = True
    args = (t(q), t(qd), t(qdd), {s: t(v) for s, v in ft.items()})
    if temporal:
        st = None if starts is None else torch.as_tensor(np.asarray(starts, bool))
        res = localizer.localize_sequence(
            *args, starts=st, skip={s: torch.as_tensor(v) for s, v in skins.items()}, base=bm,
            ft_covariance=cov,
        )  # fmt: skip
    else:
        res = localizer.localize(*args, base=bm, ft_covariance=cov)
    columns: dict[str, object] = {}
    add_frame, add_link, add_pos, add_nrm = [], [], [], []
    link_names = np.array([*localizer.links, None], dtype=object)
    for s in localizer.sensor_names:
        r = res[s]
        code = r.status.cpu().numpy().astype(np.int64)
        skin = skins[s]
        code = np.where(skin, code | int(LocalizeStatus.SKIN_CONTACT), code)
        link = r.link.cpu().numpy()
        pos = r.position.detach().cpu().double().numpy()
        nrm = r.normal.detach().cpu().double().numpy()
        idx = np.flatnonzero(localized_frames(code, link >= 0, accept_ambiguous))
        add_frame.append(idx)
        add_link.append(link_names[link[idx]])
        add_pos.append(pos[idx])
        add_nrm.append(nrm[idx])
        has = link >= 0
        text = np.full(N, "ok", dtype=object)
        for c in np.unique(code[code != 0]):
            text[code == c] = localize_messages(int(c))
        std = (np.full(N, np.nan) if r.position_std is None
               else r.position_std.detach().cpu().double().numpy())  # fmt: skip
        values = {
            "localize_link": string_array(link_names[np.where(has, link, -1)].tolist()),
            "localize_position": fixed_list(pos),
            "localize_normal": fixed_list(nrm),
            "localize_force": fixed_list(r.force.detach().cpu().double().numpy()),
            "localize_moment_residual": numpy_to_arrow(
                r.moment_residual.detach().cpu().double().numpy(), pa.float64()
            ),
            "localize_position_std": numpy_to_arrow(std, pa.float64()),
            "localize_candidates": numpy_to_arrow(r.candidates.cpu().numpy().astype(np.int64)),
            "localize_status_code": numpy_to_arrow(code),
            "localize_status": string_array(text.tolist()),
        }
        for name, typ in localization_fields([s]):
            columns[name] = values[name[: -len(s) - 1]].cast(typ)
    frame = np.concatenate(add_frame)
    added = ContactRecords(
        frame,
        np.concatenate(add_link),
        np.full(len(frame), "force", dtype=object),
        np.concatenate(add_pos).reshape(-1, 3),
        normals=np.concatenate(add_nrm).reshape(-1, 3),
    )
    merged = ContactRecords.concat([recs, added]) if len(recs) else added
    source = np.r_[np.arange(len(recs)), np.full(len(added), -1)].astype(np.int64)
    order = np.argsort(merged.frame, kind="stable")
    return LocalizedChunk(merged.select(order), source[order], columns, res)
