"""Robot geometry from the URDF: visual and collision meshes with ``package://`` URIs resolved.

Each link's ``<visual>`` or ``<collision>`` elements (meshes and box/cylinder/sphere primitives,
with their ``<origin>`` and mesh ``scale``) become one triangle mesh in the link frame, loaded with
trimesh (extra ``meshes``; COLLADA ``.dae`` files also need pycollada, which the extra brings).
Both consumers of robot geometry use this module: contact localization (collision meshes) and the
3D viewer (visual meshes).

``package://PKG/path`` URIs are resolved as pinocchio and yourdfpy resolve them, without ROS:
``PKG/path`` is looked up under, in order, the ``package_dirs`` given, every folder of
``ROS_PACKAGE_PATH``, ``share/`` of every prefix in ``AMENT_PREFIX_PATH``, and the folders that
contain the URDF (its own folder and each ancestor, which finds the meshes of an installed
``icub-models`` or ``example-robot-data``); a folder named ``PKG`` among the URDF's ancestors also
resolves ``path`` inside it. ``file://`` URIs and plain paths are taken relative to the URDF's
folder.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcontact.errors import InputError, MissingExtraError

__all__ = ["LinkMesh", "RobotMeshes", "load_meshes", "resolve_uri"]


@dataclass(frozen=True)
class LinkMesh:
    """All the ``<visual>`` or ``<collision>`` geometry of one URDF link, as one triangle mesh.

    Attributes:
        link: URDF link name.
        body: index of the model body the link is merged into (``model.frame(link).body``).
        vertices: ``(V, 3)`` float64 vertex positions in the link frame, m.
        faces: ``(F, 3)`` int64 vertex indices of each triangle, counter-clockwise seen from
            outside (outward normals), as the mesh files give them.
        R_body_link: ``(3, 3)`` rotation of the link frame in the body frame.
        p_body_link: ``(3,)`` origin of the link frame in the body frame, m.
        vertex_colors: ``(V, 4)`` uint8 RGBA per vertex, or ``None`` (no material or texture).
        sources: the mesh files (resolved paths) or primitive names the mesh was made of.
    """

    link: str
    body: int
    vertices: np.ndarray
    faces: np.ndarray
    R_body_link: np.ndarray
    p_body_link: np.ndarray
    vertex_colors: np.ndarray | None
    sources: tuple[str, ...]

    def vertices_in_body(self) -> np.ndarray:
        """``(V, 3)`` vertex positions in the body frame, m."""
        return self.vertices @ self.R_body_link.T + self.p_body_link

    def face_normals(self) -> np.ndarray:
        """``(F, 3)`` unit outward normals of the triangles in the link frame (0 if degenerate)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@dataclass(frozen=True)
class RobotMeshes:
    """The geometry of a robot's links, one kind (visual or collision).

    Attributes:
        kind: ``"visual"`` or ``"collision"``.
        links: URDF link name -> :class:`LinkMesh`, for the links that have geometry of this kind
            and whose files could all be read.
        missing: ``(link, filename, reason)`` for every geometry element that could not be loaded
            (file not found, unreadable, or a format needing a package that is not installed).
            Links with a missing element keep the elements that did load.
    """

    kind: str
    links: dict[str, LinkMesh]
    missing: tuple[tuple[str, str, str], ...]


def _search_dirs(urdf_path: Path, package_dirs: Iterable[str | os.PathLike]) -> list[Path]:
    dirs = [Path(d) for d in package_dirs]
    dirs += [Path(d) for d in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if d]
    prefixes = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    dirs += [Path(d) / "share" for d in prefixes if d]
    dirs += list(urdf_path.resolve().parents)
    return dirs


def resolve_uri(
    uri: str, urdf_path: str | os.PathLike, package_dirs: Iterable[str | os.PathLike] = ()
) -> Path:
    """The file a URDF's mesh ``filename`` points to (see the module docstring for the rule).

    Args:
        uri: ``package://PKG/path``, ``file://path``, an absolute path or a path relative to the
            URDF's folder.
        urdf_path: the URDF file the URI comes from.
        package_dirs: folders searched first for ``package://`` URIs (folders that contain
            package folders, like pinocchio's ``package_dirs``).

    Returns:
        The resolved path of an existing file.

    Raises:
        FileNotFoundError: no candidate exists; the message lists the folders tried.

    Example:
        >>> import torchcontact as tc
        >>> resolve_uri("tcarm.urdf", tc.robots.tcarm_path()).name
        'tcarm.urdf'
    """
    urdf_path = Path(urdf_path)
    if uri.startswith("package://"):
        pkg, _, rest = uri[len("package://") :].partition("/")
        tried = []
        for d in _search_dirs(urdf_path, package_dirs):
            for cand in (d / pkg / rest, d / rest if d.name == pkg else None):
                if cand is not None:
                    tried.append(str(cand.parent))
                    if cand.is_file():
                        return cand
        raise FileNotFoundError(
            f"{uri}: package {pkg!r} not found beside {urdf_path} (tried {len(tried)} folders,"
            " set ROS_PACKAGE_PATH or pass package_dirs)"
        )
    path = Path(uri[len("file://") :] if uri.startswith("file://") else uri)
    if not path.is_absolute():
        path = urdf_path.parent / path
    if not path.is_file():
        raise FileNotFoundError(f"{uri}: no such file ({path})")
    return path


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise MissingExtraError("trimesh", "meshes") from None
    return trimesh


def _primitive(trimesh, item: dict):
    size = item["size"]
    if item["type"] == "box":
        return trimesh.creation.box(extents=size)
    if item["type"] == "cylinder":
        return trimesh.creation.cylinder(radius=size[0], height=size[1], sections=32)
    return trimesh.creation.icosphere(subdivisions=2, radius=size[0])


def _load_file(trimesh, path: Path):
    """One trimesh.Trimesh from a mesh file (scenes flattened into one mesh)."""
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except ImportError as e:  # e.g. .dae without pycollada
        raise MissingExtraError(getattr(e, "name", None) or "pycollada", "meshes") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError("no triangles in the file")
    return loaded


def load_meshes(
    model,
    urdf: str | os.PathLike,
    kind: str = "collision",
    links: Sequence[str] | None = None,
    package_dirs: Iterable[str | os.PathLike] = (),
) -> RobotMeshes:
    """Load the visual or collision geometry of a robot's links from its URDF.

    Args:
        model: the :class:`~torchcontact.RobotModel` built from ``urdf`` (gives each link's body
            and its placement in that body).
        urdf: path of the URDF file (mesh paths are resolved relative to it).
        kind: ``"visual"`` or ``"collision"``.
        links: URDF link names to load (default: every link with geometry of this kind).
        package_dirs: extra folders for ``package://`` URIs (see :func:`resolve_uri`).

    Returns:
        A :class:`RobotMeshes`; files that cannot be found or read are listed in its ``missing``
        rather than raised, so a viewer can draw what exists.

    Raises:
        InputError: ``kind`` is not visual/collision, or ``links`` names a link the model lacks.
        MissingExtraError: trimesh is not installed (extra ``meshes``).
        URDFError: the URDF's geometry elements are malformed.

    Example:
        >>> import torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> load_meshes(m, tc.robots.tcarm_path(), "collision").kind  # doctest: +SKIP
        'collision'
    """
    from torchcontact import _urdf

    if kind not in ("visual", "collision"):
        raise InputError(f"kind must be 'visual' or 'collision', got {kind!r}")
    text, source = _urdf.read_text(urdf)
    items = _urdf.geometry(text, source, kind)
    if links is not None:
        unknown = [name for name in links if name not in model.frames]
        if unknown:
            raise InputError(f"links {unknown} are not links of {model.name}")
        wanted = set(links)
        items = [it for it in items if it["link"] in wanted]
    trimesh = _trimesh() if items else None
    parts: dict[str, list] = {}
    missing = []
    for it in items:
        try:
            if it["type"] == "mesh":
                path = resolve_uri(it["filename"], urdf, package_dirs)
                mesh = _load_file(trimesh, path)
                if np.any(it["scale"] != 1):
                    mesh.apply_scale(it["scale"])
                name = str(path)
            else:
                mesh = _primitive(trimesh, it)
                name = it["type"]
        except MissingExtraError as e:
            missing.append((it["link"], it["filename"] or it["type"], str(e)))
            continue
        except (OSError, ValueError) as e:
            missing.append((it["link"], it["filename"] or it["type"], str(e)))
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = it["R"], it["p"]
        v = np.asarray(mesh.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        colors = None
        if kind == "visual":
            if it["rgba"] is not None:
                colors = np.tile(
                    np.round(np.asarray(it["rgba"]) * 255).astype(np.uint8), (len(v), 1)
                )
            else:
                try:
                    colors = np.asarray(mesh.visual.to_color().vertex_colors, dtype=np.uint8)
                except Exception:  # noqa: BLE001 (a texture trimesh cannot convert: no colours)
                    colors = None
                if colors is not None and colors.shape != (len(v), 4):
                    colors = None
        parts.setdefault(it["link"], []).append((v, np.asarray(mesh.faces, np.int64), colors, name))
    out = {}
    for link, ps in parts.items():
        offsets = np.cumsum([0] + [len(p[0]) for p in ps])[:-1]
        fr = model.frame(link)
        colors = None
        if any(p[2] is not None for p in ps):  # parts without a colour drawn in neutral grey
            grey = np.array([170, 170, 170, 255], np.uint8)
            colors = np.concatenate(
                [np.tile(grey, (len(p[0]), 1)) if p[2] is None else p[2] for p in ps]
            )
        out[link] = LinkMesh(
            link=link,
            body=fr.body,
            vertices=np.concatenate([p[0] for p in ps]),
            faces=np.concatenate([p[1] + o for p, o in zip(ps, offsets, strict=True)]),
            R_body_link=np.asarray(fr.R_body_frame, np.float64),
            p_body_link=np.asarray(fr.p_body_frame, np.float64),
            vertex_colors=colors,
            sources=tuple(p[3] for p in ps),
        )
    return RobotMeshes(kind=kind, links=out, missing=tuple(missing))
