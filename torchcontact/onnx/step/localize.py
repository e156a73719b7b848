"""Contact localization inside the single-frame graph (``export estimator --localize LINK``).

Intrinsic contact sensing for one candidate link (:mod:`torchcontact.localize`, stages 2-4): a
pure force explains the region's ``b`` (the contact wrench in the sensor frame about its origin)
only on its line of action ``r = a + s u``, ``a = (f x m) / |f|^2``, ``u = f / |f|``; the contact
is where that line enters the link's mesh. Here every triangle is tested at once with one
``Gemm``: Moller-Trumbore's determinants are linear in the line's Plücker coordinates
``[d, o x d, o]`` (link frame), so the ``(9, 5 F)`` matrix of a mesh of ``F`` faces is a
constant of the graph; an entering hit (``det > 0``) lies in its triangle when three of them
are >= 0, and the entry of smallest line parameter is the contact (the first hit from far
behind is always an entry; ambiguity is not counted).

In the step graph (:func:`stage`), the localized point becomes the contact point of LINK's
``force`` slot in a step whose input has no active slot in LINK's region (no skin contact
there): its row of the slot geometry and its activity are replaced (two ``Where``), so the
Gram matrices, the solve, the contact wrenches, torques, rank and residual use it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from torchcontact import spatial as sp
from torchcontact.errors import InputError, MissingExtraError
from torchcontact.meshes import LinkMesh, RobotMeshes
from torchcontact.onnx.builder import GraphBuilder, Operand, bilinear
from torchcontact.onnx.step.context import StepContext
from torchcontact.onnx.step.forms import TP_ONE, flat, rows, tp
from torchcontact.status import LocalizeStatus

__all__ = [
    "DEFAULT_MAX_FACES",
    "LineHit",
    "LocalizeLink",
    "emit_line_hit",
    "link_pose",
    "localize_link",
    "onnx_single_link",
    "stage",
]

#: Above this many faces the step graph carries the collision mesh's convex hull instead.
DEFAULT_MAX_FACES = 1000


@dataclass(frozen=True)
class LocalizeLink:
    """What a step graph localizes: one candidate link and the mesh the graph carries.

    Attributes:
        link: the URDF link; the layout must hold a ``force`` slot on it.
        mesh: the triangles the graph tests (link frame; the collision mesh or its hull).
        force_threshold: below this force (N) a step has no contact (status bit 2).
        mesh_choice: how the mesh was chosen (recorded in the metadata), e.g.
            ``"collision mesh (400 faces)"``.
    """

    link: str
    mesh: LinkMesh
    force_threshold: float = 1.0
    mesh_choice: str = ""


class LineHit(NamedTuple):
    """The graph values of one localization (``(1, n)`` rows, the graph's float dtype).

    Attributes:
        found: ``(1, 1)`` bool: the force is above the threshold and its line enters the mesh.
        point_sensor: ``(1, 3)`` the contact point in the sensor frame (meaningless where not
            ``found``).
        point_link: ``(1, 3)`` the same in the link frame.
        t: ``(1, 1)`` the line parameter of the entry (inf where none).
        face: ``(1, 1)`` int64 index of the entered triangle (``with_face``; else ``""``).
        live: ``(1, 1)`` bool: the force is above the threshold.
        f: ``(1, 3)`` force, sensor frame.
        u: ``(1, 3)`` unit force direction, sensor frame.
        status: ``(1, 1)`` float bits 2 (no contact) and 4 (no intersection) of
            :class:`~torchcontact.status.LocalizeStatus`.
    """

    found: str
    point_sensor: str
    point_link: str
    t: str
    face: str
    live: str
    f: str
    u: str
    status: str


def localize_link(model, em, links: Sequence[str], kinds: Sequence[str], link: str,
                  meshes: RobotMeshes | Mapping[str, LinkMesh] | None,
                  force_threshold: float = 1.0,
                  max_faces: int = DEFAULT_MAX_FACES) -> LocalizeLink:  # fmt: skip
    """Check ``--localize LINK`` against a layout and choose the mesh the graph carries.

    The link's collision mesh when it has at most ``max_faces`` faces, else its convex hull
    (the hull's surface is where the graph localizes: exact on the convex parts of the link,
    on the hull across concave ones); a hull still above ``max_faces`` is refused.

    Args:
        model: the robot (:class:`~torchcontact.RobotModel`).
        em: an estimation model of the sensors (its regions; any slots).
        links: the layout's slot links.
        kinds: their kinds.
        link: the candidate link.
        meshes: the robot's collision meshes (:func:`torchcontact.meshes.load_meshes`) or a
            mapping link -> :class:`~torchcontact.meshes.LinkMesh`.
        force_threshold: below this force (N) a step has no contact.
        max_faces: the most faces the graph carries (its cost grows with them).

    Returns:
        The :class:`LocalizeLink`, its ``mesh_choice`` saying which mesh was taken.

    Raises:
        InputError: a link the robot lacks, outside every sensor's subtree, without a
            ``force`` slot in the layout, without collision geometry, or a hull above
            ``max_faces``; a threshold that is not > 0.
    """
    if not force_threshold > 0:
        raise InputError(f"--localize-threshold must be > 0 N, got {force_threshold!r}")
    if max_faces < 4:
        raise InputError(f"--localize-max-faces must be >= 4, got {max_faces!r}")
    if link not in model.frames:
        raise InputError(f"--localize {link}: not a link of {model.name}")
    if em.region_of_body[model.frame(link).body] < 0:
        raise InputError(
            f"--localize {link}: {link} lies outside the subtree of every F/T sensor"
            f" {[r.sensor for r in em.regions]}: no sensor measures a contact there"
        )
    if (link, "force") not in set(zip(links, kinds, strict=True)):
        raise InputError(
            f"--localize {link}: the layout has no force slot on {link} (add --slot {link}:force;"
            " the localized contact is a pure force)"
        )
    missing = ""
    if isinstance(meshes, RobotMeshes):
        missing = "; ".join(f"{f}: {why}" for lk, f, why in meshes.missing if lk == link)
        meshes = meshes.links
    mesh = (meshes or {}).get(link)
    if mesh is None or not len(mesh.faces):
        raise InputError(
            f"--localize {link}: {link} has no collision geometry"
            + (f" ({missing})" if missing else " (no <collision> element in the URDF)")
        )
    n = len(mesh.faces)
    choice = f"collision mesh ({n} faces)"
    if n > max_faces:
        import trimesh

        hull = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).convex_hull
        if len(hull.faces) > max_faces:
            raise InputError(
                f"--localize {link}: its collision mesh has {n} faces and its convex hull"
                f" {len(hull.faces)}, above --localize-max-faces {max_faces} (raise it)"
            )
        mesh = replace(mesh, vertices=np.asarray(hull.vertices, np.float64),
                       faces=np.asarray(hull.faces, np.int64), vertex_colors=None)  # fmt: skip
        choice = f"convex hull ({len(hull.faces)} faces) of the collision mesh ({n} faces)"
    return LocalizeLink(link, mesh, float(force_threshold), choice)


def _plucker_matrix(mesh: LinkMesh) -> tuple[np.ndarray, np.ndarray]:
    """``(W, c)``: ``[d, o x d, o] W + c = [det, det u, det v, det (1 - u - v), det t]``.

    Per face, ``(9, 5 F)``: Moller-Trumbore with ``N = E1 x E2``: ``det = -d . N``, ``det u =
    E2 . (o x d) - d . (E2 x V0)``, ``det v = -E1 . (o x d) - d . (V0 x E1)``, ``det t = o . N -
    E2 . (V0 x E1)``; with ``det > 0`` (entering) the barycentric test is three signs.
    """
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces, np.int64)]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    F = len(tri)
    W = np.zeros((9, 5 * F))
    W[0:3, 0:F] = -n.T
    W[0:3, F : 2 * F] = -np.cross(e2, v0).T
    W[3:6, F : 2 * F] = e2.T
    W[0:3, 2 * F : 3 * F] = -np.cross(v0, e1).T
    W[3:6, 2 * F : 3 * F] = -e1.T
    W[:, 3 * F : 4 * F] = W[:, 0:F] - W[:, F : 2 * F] - W[:, 2 * F : 3 * F]
    W[6:9, 4 * F :] = n.T
    c = np.zeros((1, 5 * F))
    c[0, 4 * F :] = -np.einsum("fi,fi->f", e2, np.cross(v0, e1))
    return W, c


def emit_line_hit(gb: GraphBuilder, mesh: LinkMesh, wrench: str, R: str, p: str,
                  force_threshold: float, with_face: bool = False) -> LineHit:  # fmt: skip
    """Emit the localization of one frame's contact on one link (about 40 nodes, any mesh).

    Args:
        gb: the graph.
        mesh: the link's triangles (link frame).
        wrench: ``(1, 6)`` the region's ``b`` ``[force; moment]``, sensor frame, about its
            origin (N, N m).
        R: ``(3, 3)`` ``R_sensor_link``.
        p: ``(1, 3)`` ``p_sensor_link`` (m).
        force_threshold: N.
        with_face: also the index of the entered triangle (``face``; else ``""``).

    Returns:
        The :class:`LineHit` values.
    """
    axis1 = gb.i([1])
    f = gb.op("Slice", wrench, gb.i([0]), gb.i([3]), axis1)
    # the line of action: a = f x m / |f|^2, u = f / |f| (sensor frame)
    fn2 = gb.op("ReduceSumSquare", f, axis1, keepdims=1)
    live = gb.op("GreaterOrEqual", fn2, gb.f(force_threshold**2))
    safe = gb.op("Where", live, fn2, gb.f(1.0))
    fxm = bilinear(gb, Operand(wrench, 6), None, 1,
                   lambda _r, w, _b: sp.v_cross(tuple(w[0:3]), tuple(w[3:6])), 3, one=False,
                   hint="fxm")  # fmt: skip
    a = gb.op("Div", fxm, safe)
    u = gb.op("Div", f, gb.op("Sqrt", safe))
    # in the link frame (row vectors: x R = (R^T x)^T): origin o, direction d; the Plücker
    # coordinates [d, o x d, o]
    o = gb.op("MatMul", gb.op("Sub", a, p), R)
    d = gb.op("MatMul", u, R)
    od1 = gb.op("Concat", o, d, gb.f([[1.0]]), axis=1)

    def plucker(_r: int, v: list, _b: list) -> list:
        o_, d_ = tuple(v[0:3]), tuple(v[3:6])
        return [*d_, *sp.v_cross(o_, d_), *o_]

    X = bilinear(gb, Operand(od1, 7, one=6), None, 1, plucker, 9, one=False, hint="plucker")
    # Moller-Trumbore against every face: one Gemm; entering (det > 0), inside (three signs)
    W, c = _plucker_matrix(mesh)
    F = len(mesh.faces)
    det, uvw, dt = gb.op("Split", gb.op("Reshape", gb.op("Gemm", X, gb.f(W), gb.f(c)),
                         gb.i([5, F])), gb.i([1, 3, 1]), axis=0, n_out=3)  # fmt: skip
    zero = gb.f(0.0)
    inside = gb.op("GreaterOrEqual", gb.op("ReduceMin", uvw, gb.i([0]), keepdims=1), zero)
    ok = gb.op("And", gb.op("Greater", det, gb.f(1e-12)), inside)  # d . n < 0, in the triangle
    tm = gb.op("Where", ok, gb.op("Div", dt, det), gb.f(np.inf))  # (1, F)
    if with_face:  # the entered triangle (its normal)
        face = gb.op("ArgMin", tm, axis=1, keepdims=1)
        t = gb.op("GatherElements", tm, face, axis=1)
    else:
        face, t = "", gb.op("ReduceMin", tm, axis1, keepdims=1)
    found = gb.op("And", live, gb.op("Less", t, gb.f(np.inf)))
    t0 = gb.op("Where", found, t, zero)  # finite where unused
    point_sensor = gb.op("Add", a, gb.op("Mul", u, t0))
    point_link = gb.op("Add", o, gb.op("Mul", d, t0))
    bits = gb.op("Where", live, gb.f(float(LocalizeStatus.NO_INTERSECTION)),
                 gb.f(float(LocalizeStatus.NO_CONTACT)))  # fmt: skip
    status = gb.op("Where", found, zero, bits)
    return LineHit(found, point_sensor, point_link, t, face, live, f, u, status)


def link_pose(ctx: StepContext, TP: str, k: int) -> str:
    """``[R_sensor_link (row-major), p_sensor_link]`` of slot ``k``'s link, ``(1, 12)``."""
    em = ctx.em
    slot = em.slots[k]
    reg = em.regions[slot.region]

    def rel(_n: int, tc: list, tb: list) -> list:
        # T_sensor_link = T_child_sensor^-1 T_root_child^-1 T_root_body T_body_link
        Rc, _, _, pinv = tp(tc)
        T_sc = sp.pose_inverse(reg.T_child_sensor)
        T_cb = sp.pose_compose((sp.m_T(Rc), pinv), (rows(tb[0:9]), tuple(tb[9:12])))
        R, p = sp.pose_compose(sp.pose_compose(T_sc, T_cb), (slot.R, slot.p))
        return [*flat(R), *p]

    return bilinear(ctx.gb, Operand(TP, 25, "nd", one=TP_ONE, row_of=[reg.child]),
                    Operand(TP, 25, "nd", one=TP_ONE, row_of=[slot.body]), 1, rel, 12,
                    one=False, hint="locpose")  # fmt: skip


class Localized(NamedTuple):
    """What :func:`stage` leaves: the slot geometry and activity to use, and the outputs.

    Attributes:
        Cg: ``(K, 13)`` slot geometry with LINK's slot at the localized point where used.
        actK: ``(K, 1)`` slot activity with LINK's slot active where used.
        outputs: ``[([(field, shape)], (1, n) value)]``: ``localize_status (1,)``,
            ``localize_position (3,)`` (link frame, NaN without a localized contact).
    """

    Cg: str
    actK: str  # noqa: N815 - K slots
    outputs: list


def stage(ctx: StepContext, spec: LocalizeLink, TP: str, b_all: list[str], Cg: str,
          actK: str) -> Localized:  # fmt: skip
    """Localize LINK's contact from its region's ``b`` and make it the slot's contact.

    Used where no slot of LINK's region is active (the input reports no skin contact there);
    otherwise the status gets bit 32 (:attr:`LocalizeStatus.SKIN_CONTACT`) and the position is
    NaN.

    Args:
        ctx: the graph.
        spec: the link, mesh and threshold.
        TP: pose features.
        b_all: per region its ``b`` ``(R, 1)`` (sensor rows first).
        Cg: ``(K, 13)`` slot geometry ``[c (sensor frame), R_sensor_body, 1]``.
        actK: ``(K, 1)`` slot activity from the input.

    Returns:
        :class:`Localized`.
    """
    gb, em = ctx.gb, ctx.em
    k = next(i for i, s in enumerate(em.slots)
             if s.link == spec.link and s.kind == "force")  # fmt: skip
    r = em.slots[k].region
    wrench = gb.op("Reshape", gb.op("Slice", b_all[r], gb.i([0]), gb.i([6]), gb.i([0])),
                   gb.i([1, 6]))  # fmt: skip
    pose = link_pose(ctx, TP, k)
    R = gb.op("Reshape", gb.op("Slice", pose, gb.i([0]), gb.i([9]), gb.i([1])), gb.i([3, 3]))
    p = gb.op("Slice", pose, gb.i([9]), gb.i([12]), gb.i([1]))
    hit = emit_line_hit(gb, spec.mesh, wrench, R, p, spec.force_threshold)
    # skin contact in the region: the localization is not used (one contact per region)
    memb = np.zeros((1, ctx.K))
    memb[0, list(em.regions[r].slots)] = 1.0
    skin = gb.op("Greater", gb.op("MatMul", gb.f(memb), actK), gb.f(0.5))
    use = gb.op("And", hit.found, gb.op("Not", skin))
    # LINK's slot: its row of the geometry at the point, and active, where used
    rowk = np.zeros((ctx.K, 13), dtype=bool)
    rowk[k, 0:3] = True
    Cg = gb.op("Where", gb.op("And", gb.const(rowk), use),
               gb.op("Concat", hit.point_sensor, gb.f(np.zeros((1, 10))), axis=1), Cg)  # fmt: skip
    onek = np.zeros((ctx.K, 1), dtype=bool)
    onek[k, 0] = True
    actK = gb.op("Where", gb.op("And", gb.const(onek), use), gb.f(1.0), actK)
    skin_bit = gb.op("Where", skin, gb.f(float(LocalizeStatus.SKIN_CONTACT)), gb.f(0.0))
    status = gb.op("Add", hit.status, skin_bit)
    position = gb.op("Where", use, hit.point_link, gb.f(np.nan))
    outputs = [([("localize_status", (1,))], status), ([("localize_position", (3,))], position)]
    return Localized(Cg, actK, outputs)


def onnx_single_link(mesh: LinkMesh, force_threshold: float = 1.0, opset: int | None = None):
    """An ONNX graph that localizes one frame's contact on one link (stages 2-4, float32).

    The piece of the single-frame step graph that localization needs (:func:`emit_line_hit`,
    which ``export estimator --localize LINK`` wires into the step graph by :func:`stage`):
    every triangle is tested at once (Moller-Trumbore's determinants as one ``Gemm`` on the
    line's Plücker coordinates), and the hit of smallest line parameter among those entering
    the surface is the contact (the first hit along the line from far behind is always an entry
    into the mesh, so no ordering of the other hits is needed; the graph does not count
    ambiguous entries). The node count does not depend on the mesh; the cost grows with the face
    count.

    Inputs: ``wrench`` ``(6,)`` the region's ``b`` (sensor frame), ``R_sensor_link`` ``(3, 3)``,
    ``p_sensor_link`` ``(3,)``. Outputs: ``position`` ``(3,)`` and ``normal`` ``(3,)`` (link
    frame, NaN without contact), ``force`` ``(3,)`` (link frame), ``moment_residual`` ``(1,)`` and
    ``status`` ``(1,)`` int64 (bits 2 and 4 of :data:`~torchcontact.status.LOCALIZE_STATUS`).

    Args:
        mesh: the link's collision mesh.
        force_threshold: N.
        opset: ONNX opset (None: :data:`torchcontact.onnx.builder.OPSET`, the lowest it takes).

    Returns:
        An ``onnx.ModelProto``.

    Raises:
        MissingExtraError: onnx is not installed (extra ``export``).
    """
    try:
        import onnx
        from onnx import TensorProto
    except ImportError:
        raise MissingExtraError("onnx", "export") from None
    gb = GraphBuilder(np.float32, f"localize_{mesh.link}")
    w = gb.op("Reshape", gb.input("wrench", [6]), gb.i([1, 6]))
    R = gb.input("R_sensor_link", [3, 3])
    p = gb.op("Reshape", gb.input("p_sensor_link", [3]), gb.i([1, 3]))
    hit = emit_line_hit(gb, mesh, w, R, p, force_threshold, with_face=True)
    nan, shape3 = gb.f(np.nan), gb.i([3])
    nrm = mesh.face_normals()
    normal = gb.op("Reshape", gb.op("Gather", gb.f(nrm), hit.face, axis=0), shape3)
    gb.op("Reshape", gb.op("Where", hit.found, hit.point_link, nan), shape3, out="position")
    gb.op("Reshape", gb.op("Where", hit.found, normal, nan), shape3, out="normal")
    gb.op("Reshape", gb.op("MatMul", hit.f, R), shape3, out="force")
    m = gb.op("Slice", w, gb.i([3]), gb.i([6]), gb.i([1]))
    m_along = gb.op("Abs", gb.op("ReduceSum", gb.op("Mul", hit.u, m), keepdims=0))
    m_norm = gb.op("Sqrt", gb.op("ReduceSumSquare", m, keepdims=0))  # no force: all of m
    gb.op("Reshape", gb.op("Where", hit.live, m_along, m_norm), gb.i([1]), out="moment_residual")
    gb.op("Reshape", gb.op("Cast", hit.status, to=TensorProto.INT64), gb.i([1]), out="status")
    for name, shape in (("position", [3]), ("normal", [3]), ("force", [3]),
                        ("moment_residual", [1])):  # fmt: skip
        gb.output(name, shape)
    gb.output("status", [1], np.int64)
    model = gb.model()
    if opset is not None:
        model.opset_import[0].version = opset
    onnx.checker.check_model(model)
    return model
