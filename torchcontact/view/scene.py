"""Draw a robot, its contacts and their estimates into a rerun recording.

:class:`RerunScene` owns one recording: it logs the static parts once (the robot's visual meshes
in their link frames, the F/T sensor frames, the styles of the time series, a legend and the
viewer layout) and then draws batches of frames (:class:`ViewFrames`) with ``send_columns``, one
call per entity and batch, so a long log streams through with flat memory.

Entities (``world`` is the robot's root frame, m; forces are drawn at ``scale`` N per m):

- ``world/robot/<body>``: the body's pose per frame; ``world/robot/<body>/<link>``: the link's
  visual mesh in its frame (static), or its axes when the mesh is missing;
  ``world/robot/skeleton``: segments between body origins, when some mesh is missing.
- ``world/robot/<body>/ft_<sensor>``: the sensor frame; ``.../measured`` and ``.../residual``:
  the measured force and the force part of the residual ``A x - b`` as arrows (sensor frame).
- ``world/contacts/points``, ``world/contacts/estimate``, ``world/contacts/truth``: contact
  points and forces, one colour per contact slot (:func:`torchcontact.logs.plot.slot_rgb`), the
  truth at :data:`~torchcontact.logs.plot.TRUTH_ALPHA` opacity; ``world/contacts/cone_active``:
  contacts whose friction cone binds.
- ``world/nullspace/<sensor>/dir<j>``: on ill-posed frames, the null-space directions
  (:func:`torchcontact.logs.plot.null_directions`) as forces at the contacts, the largest 25 % of
  the robot's size.
- ``plots/...``: time series (force norm per slot, rank, unknowns, null-space dimension and
  ill-posed flag per sensor, residual norm, measured wrench and residual per sensor, status code,
  cone iterations and active cones); ``states/...``: lanes of the status (bits by name), of the
  posedness and of the cones' convergence; ``log``: text entries at non-zero statuses and where
  frames become ill- or well-posed; ``legend``: the scale and the slot colours.

Timelines: ``time`` is the log's ``t_ns`` (a date when it looks like one, else a duration) and
``frame`` is the row of the log.
"""

from __future__ import annotations

import math
import uuid
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, MissingExtraError, URDFError
from torchcontact.logs.plot import (
    BAD_STATUS_RGB,
    ILL_POSED_RGB,
    MAX_DIRECTIONS,
    NULLSPACE_RGB,
    SLOT_COLORS,
    TRUTH_ALPHA,
    NullDirection,
    ill_posed_note,
    rank_deficient,
    slot_label,
    slot_rgb,
)
from torchcontact.status import STATUS, STATUS_NAMES, status_bits

__all__ = ["RERUN_VERSION", "LiveView", "RerunScene", "ViewFrames", "log_to_rerun", "nice_scale"]

#: The rerun-sdk version this module is tested with (the ``view`` extra pins it).
RERUN_VERSION = "0.41.0"
#: ``t_ns`` at or above this (1973) is a date: the ``time`` timeline shows dates, else durations.
_DATE_NS = 10**17
_AXES = ("fx", "fy", "fz", "mx", "my", "mz")
_MEASURED_RGB = (40, 40, 40, 255)
_RESIDUAL_RGB = (*BAD_STATUS_RGB, 255)
_OK_RGB = (120, 190, 120, 255)


def import_rerun() -> Any:
    """The ``rerun`` module.

    Raises:
        MissingExtraError: rerun-sdk is not installed (extra ``view``; Python 3.11 or later).
    """
    try:
        import rerun
    except ImportError:
        raise MissingExtraError("rerun-sdk", "view") from None
    return rerun


def nice_scale(force: float, length: float) -> float:
    """Arrow scale in N per m that draws ``force`` about ``length`` long: 1, 2 or 5 x 10^k.

    Args:
        force: a typical force, N (e.g. the 95th percentile of a log's contact forces).
        length: the arrow length wanted for it, m (e.g. a quarter of the robot's size).

    Example:
        >>> nice_scale(12.0, 0.25), nice_scale(0.0, 0.25)
        (50.0, 1.0)
    """
    if not force > 0 or not length > 0:
        return 1.0
    raw = force / length
    e = 10.0 ** math.floor(math.log10(raw))
    m = raw / e
    return (1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * e


@dataclass(frozen=True)
class ViewFrames:
    """N frames of a robot: its joint positions and readings, contacts, and their estimate.

    Only ``t_ns`` and ``q`` are needed; what is None is not drawn.

    Attributes:
        t_ns: ``(N,)`` int64 time stamps, ns (the ``time`` timeline).
        q: ``(N, nv)`` joint positions in ``model.joint_names`` order, rad or m.
        rows: ``(N,)`` int64 rows of the frames in their log (the ``frame`` timeline); default:
            the frames drawn so far by the scene, counted on.
        ft: sensor -> ``(N, 6)`` reading ``[force (N); moment (N m)]`` in the sensor frame.
        records: the contacts (:class:`~torchcontact.contacts.ContactRecords`, ``frame`` in
            ``0 .. N-1``, positions in link frames, m).
        slot: ``(M,)`` contact slot of each record (its colour; -1: not drawn).
        force: ``(M, 3)`` estimated force of each record, link frame, N (NaN: no estimate).
        moment: ``(M, 3)`` estimated moment about the contact point, link frame, N m.
        true_force: ``(M, 3)`` true force (simulated logs), link frame, N.
        cone_active: ``(M,)`` bool, the record's friction cone binds (constrained estimate).
        rank, unknowns, nullity: sensor -> ``(N,)`` rank of ``A``, its unknowns and
            ``unknowns - rank``.
        residual: sensor -> ``(N,)`` ``|A x - b|`` of the estimate.
        residual_wrench: sensor -> ``(N, 6)`` ``A x - b`` as a wrench in the sensor frame: what
            the estimate predicts the sensor reads minus what it read, ``[N; N m]``.
        converged: sensor -> ``(N,)`` bool, the interior-point solve converged.
        iterations: sensor -> ``(N,)`` its iterations.
        status: ``(N,)`` int64 status code (bits of :data:`torchcontact.STATUS`).
        null: per frame, its :class:`~torchcontact.logs.plot.NullDirection` s (None: not
            computed for that frame).
    """

    t_ns: np.ndarray
    q: np.ndarray
    rows: np.ndarray | None = None
    ft: Mapping[str, np.ndarray] = field(default_factory=dict)
    records: Any = None
    slot: np.ndarray | None = None
    force: np.ndarray | None = None
    moment: np.ndarray | None = None
    true_force: np.ndarray | None = None
    cone_active: np.ndarray | None = None
    rank: Mapping[str, np.ndarray] | None = None
    unknowns: Mapping[str, np.ndarray] | None = None
    nullity: Mapping[str, np.ndarray] | None = None
    residual: Mapping[str, np.ndarray] | None = None
    residual_wrench: Mapping[str, np.ndarray] | None = None
    converged: Mapping[str, np.ndarray] | None = None
    iterations: Mapping[str, np.ndarray] | None = None
    status: np.ndarray | None = None
    null: Sequence[list[NullDirection] | None] | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t_ns, np.int64).reshape(-1)
        object.__setattr__(self, "t_ns", t)
        N = len(t)
        q = np.asarray(self.q, np.float64)
        if q.ndim != 2 or q.shape[0] != N:
            raise InputError(f"q must be (N, nv) with N = {N} time stamps, got {q.shape}")
        object.__setattr__(self, "q", q)
        if self.rows is not None:
            rows = np.asarray(self.rows, np.int64).reshape(-1)
            if rows.shape != (N,):
                raise InputError(f"rows must be (N,) = ({N},), got {rows.shape}")
            object.__setattr__(self, "rows", rows)
        for s, w in self.ft.items():
            if np.shape(w) != (N, 6):
                raise InputError(f"ft[{s!r}] must be (N, 6) = ({N}, 6), got {np.shape(w)}")
        M = 0 if self.records is None else len(self.records)
        if self.records is not None and M and self.records.frame.max() >= N:
            raise InputError(f"contact records of frames beyond the {N} frames given")
        for name in ("force", "moment", "true_force"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != (M, 3):
                raise InputError(f"{name} must be (M, 3) = ({M}, 3), one per record")

    def __len__(self) -> int:
        return len(self.t_ns)


def _esc(name: str) -> str:
    from rerun import escape_entity_path_part

    return str(escape_entity_path_part(name))


def _vertex_normals(v: np.ndarray, faces: np.ndarray, face_n: np.ndarray) -> np.ndarray:
    """Area-independent average of the adjacent faces' normals per vertex (smooth shading)."""
    n = np.zeros_like(v)
    for c in range(3):
        np.add.at(n, faces[:, c], face_n)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0).astype(np.float32)


class RerunScene:
    """One robot drawn into one rerun recording, batch after batch of frames.

    The static parts (meshes, sensor frames, styles, legend, layout) are logged with the first
    batch, so the recording can be sent to a file or a viewer after the scene is made.

    Args:
        model: the robot (:class:`~torchcontact.RobotModel`).
        recording: a ``rerun.RecordingStream`` (default: a new one with a random id, not yet
            saved or connected: call ``scene.recording.save(path)`` or ``.spawn()``).
        urdf: the URDF the model was built from, for its visual meshes (loaded with
            :func:`torchcontact.meshes.load_meshes`, ``package://`` URIs resolved from the
            installed packages); None draws the link frames.
        layout: the contact slots (:class:`~torchcontact.contacts.SlotLayout`) the records'
            ``slot`` index, for the legend and series names (default: slots named as seen).
        scale: arrow scale, N per m (one for the whole recording; default: from the first batch,
            its 95th percentile force a quarter of the robot's size, :func:`nice_scale`).
        sensors: the F/T sensors drawn (default: the model's).
        constrained: the estimate is friction-cone constrained (captions; cone lanes).
        require_meshes: raise instead of warning when a visual mesh is missing.
        package_dirs: extra folders for ``package://`` URIs.
        links: draw the meshes of these URDF links only (default: every link's).

    Raises:
        MissingExtraError: rerun-sdk (extra ``view``) or trimesh (extra ``meshes``) missing.
        URDFError: ``require_meshes`` and a mesh could not be loaded (the message lists them).
        InputError: a sensor the model lacks, a scale that is not positive.
    """

    def __init__(
        self,
        model: Any,
        recording: Any = None,
        *,
        urdf: str | Path | None = None,
        layout: Any = None,
        scale: float | None = None,
        sensors: Sequence[str] | None = None,
        constrained: bool = False,
        require_meshes: bool = False,
        package_dirs: Sequence[str | Path] = (),
        links: Sequence[str] | None = None,
    ) -> None:
        self.rr = import_rerun()
        self.model = model
        self.recording = recording
        if recording is None:
            self.recording = self.rr.RecordingStream("torchcontact", recording_id=uuid.uuid4())
        self.sensors = list(model.ft_sensors) if sensors is None else list(sensors)
        unknown = [s for s in self.sensors if s not in model.ft_sensors]
        if unknown:
            raise InputError(f"sensors {unknown} are not F/T sensors of {model.name}")
        if scale is not None and not scale > 0:
            raise InputError(f"scale must be > 0 N per m, got {scale!r}")
        self.layout = layout
        self.scale = scale
        self.constrained = constrained
        self.meshes: Any = None
        self.missing: tuple[tuple[str, str, str], ...] = ()
        if urdf is not None:
            self._load_meshes(urdf, require_meshes, package_dirs, links)
        self.size = 1.0
        self.ft_scale = 1.0
        self._started = False
        self._dates = False
        self._styled: set[str] = set()
        self._state: dict[str, str] = {}
        self._next_row = 0
        self.frames_logged = 0

    # ------------------------------------------------------------------ static parts
    def _load_meshes(
        self, urdf: str | Path, required: bool, package_dirs: Sequence, links: Sequence[str] | None
    ) -> None:
        from torchcontact.meshes import load_meshes

        self.meshes = load_meshes(self.model, urdf, "visual", links, package_dirs)
        self.missing = self.meshes.missing
        if self.missing:
            names = "; ".join(f"{link}: {Path(f).name}" for link, f, _ in self.missing)
            why = self.missing[0][2]
            msg = (
                f"{urdf}: {len(self.missing)} visual mesh(es) of {self.model.name} could not be"
                f" loaded ({names}; first reason: {why})"
            )
            if required:
                raise URDFError(msg)
            warnings.warn(f"{msg}: drawing those links' frames instead", UserWarning, stacklevel=3)

    def _body_path(self, b: int) -> str:
        return f"world/robot/{_esc(self.model.body_names[b])}"

    def _sensor_path(self, s: str) -> str:
        ft = self.model.ft_sensors[s]
        return f"{self._body_path(ft.child_body)}/{_esc('ft_' + s)}"

    def _start(self, frames: ViewFrames) -> None:
        """Log the static parts; the first batch gives the robot's size and the default scale."""
        import torch

        import torchcontact as tc

        rr, rec, model = self.rr, self.recording, self.model
        self._dates = bool(len(frames.t_ns)) and int(frames.t_ns[0]) >= _DATE_NS
        q0 = torch.as_tensor(frames.q[:1], dtype=model.dtype)
        p = tc.forward_pass(model, q0, torch.zeros_like(q0), torch.zeros_like(q0)).p[0].numpy()
        self.size = max(float(np.max(p.max(0) - p.min(0))), 0.2)
        if self.scale is None:
            mags = [
                np.linalg.norm(x, axis=-1)
                for x in (frames.force, frames.true_force)
                if x is not None and len(x)
            ]
            mags = np.concatenate(mags) if mags else np.zeros(0)
            mags = mags[np.isfinite(mags)]
            typical = float(np.percentile(mags, 95)) if len(mags) else 0.0
            self.scale = nice_scale(typical, 0.25 * self.size)
        # the readings carry the robot's weight: their own scale, the median force half its size
        ft = [np.linalg.norm(np.asarray(w)[:, :3], axis=-1) for w in frames.ft.values()]
        ft_mags = np.concatenate(ft) if ft else np.zeros(0)
        ft_mags = ft_mags[np.isfinite(ft_mags)]
        self.ft_scale = nice_scale(float(np.median(ft_mags)) if len(ft_mags) else 0.0,
                                   0.5 * self.size)  # fmt: skip
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        # meshes in their link frames; axes for links without one
        drawn: set[str] = set()
        if self.meshes is not None:
            for link, lm in self.meshes.links.items():
                path = f"{self._body_path(lm.body)}/{_esc(link)}"
                normals = _vertex_normals(lm.vertices, lm.faces, lm.face_normals())
                rec.log(
                    path,
                    rr.Transform3D(translation=lm.p_body_link, mat3x3=lm.R_body_link),
                    rr.Mesh3D(
                        vertex_positions=lm.vertices.astype(np.float32),
                        triangle_indices=lm.faces.astype(np.uint32),
                        vertex_normals=normals,
                        vertex_colors=lm.vertex_colors,
                        albedo_factor=None
                        if lm.vertex_colors is not None
                        else (170, 170, 170, 255),
                    ),
                    static=True,
                )
                drawn.add(link)
        missing_links = sorted({m[0] for m in self.missing})
        bare = self.meshes is None or not self.meshes.links
        self._skeleton = bare or bool(missing_links)
        frame_links = (list(model.body_names) if bare else []) + missing_links
        axis = 0.12 * self.size
        for link in dict.fromkeys(frame_links):
            fr = model.frame(link)
            rec.log(
                f"{self._body_path(fr.body)}/{_esc(link)}",
                rr.Transform3D(translation=fr.p_body_frame, mat3x3=fr.R_body_frame),
                rr.TransformAxes3D(axis),
                static=True,
            )
        for s in self.sensors:
            ft = model.ft_sensors[s]
            path = self._sensor_path(s)
            rec.log(
                path,
                rr.Transform3D(translation=ft.p_child_sensor, mat3x3=ft.R_child_sensor),
                rr.TransformAxes3D(0.5 * axis),
                static=True,
            )
        self._log_styles()
        self._log_legend()
        rec.send_blueprint(self._blueprint(), make_active=True, make_default=True)
        self._started = True

    def _series(self, path: str, archetype: Any) -> None:
        if path not in self._styled:
            self.recording.log(path, archetype, static=True)
            self._styled.add(path)

    def _slot_name(self, k: int) -> str:
        if self.layout is not None and 0 <= k < self.layout.K:
            return slot_label(self.layout, k)
        return f"slot {k}"

    def _style_slot(self, k: int, truth: bool) -> None:
        rr = self.rr
        name = self._slot_name(k)
        self._series(
            f"plots/forces/slot{k}/estimate",
            rr.SeriesPoints(
                colors=slot_rgb(k), names=f"{name} estimate", markers="circle", marker_sizes=1.5
            ),
        )
        if truth:
            self._series(
                f"plots/forces/slot{k}/truth",
                rr.SeriesLines(colors=slot_rgb(k, TRUTH_ALPHA), names=f"{name} truth", widths=1.5),
            )

    def _log_styles(self) -> None:
        rr = self.rr
        palette = list(SLOT_COLORS[: len(_AXES)])  # one colour per axis, plot.py's cycle
        for s in self.sensors:
            self._series(
                f"plots/identifiability/{s}/rank",
                rr.SeriesLines(names=f"rank {s}", widths=1.5, colors=slot_rgb(1)),
            )
            self._series(
                f"plots/identifiability/{s}/unknowns",
                rr.SeriesLines(names=f"unknowns {s}", widths=3, colors=slot_rgb(0, 0.5)),
            )
            self._series(
                f"plots/identifiability/{s}/nullity",
                rr.SeriesLines(
                    names=f"null-space dimension {s}", widths=1, colors=(*NULLSPACE_RGB, 255)
                ),
            )
            self._series(f"plots/residual/{s}", rr.SeriesLines(names=f"|A x - b| {s}"))
            for what in ("measured", "residual"):
                self._series(
                    f"plots/sensors/{s}/{what}",
                    rr.SeriesLines(names=[f"{what} {a}" for a in _AXES], colors=palette),
                )
            if self.constrained:
                self._series(f"plots/cones/{s}/iterations", rr.SeriesLines(names=f"iterations {s}"))
                self._series(
                    f"states/cones/{s}",
                    rr.StateConfiguration(
                        values=["converged", "not converged"], colors=[_OK_RGB, _RESIDUAL_RGB]
                    ),
                )
        self._series(
            "plots/identifiability/ill_posed",
            rr.SeriesLines(names="rank < unknowns (1)", colors=ILL_POSED_RGB),
        )
        self._series(
            "plots/status/code",
            rr.SeriesPoints(names="status code", colors=BAD_STATUS_RGB, markers="cross"),
        )
        if self.constrained:
            self._series("plots/cones/active", rr.SeriesLines(names="contacts with an active cone"))
        bits = [STATUS_NAMES.get(b, f"bit{b}") for b in STATUS]
        self._series(
            "states/status",
            rr.StateConfiguration(
                values=["ok", *bits], colors=[_OK_RGB] + [_RESIDUAL_RGB] * len(bits)
            ),
        )
        self._series(
            "states/posedness",
            rr.StateConfiguration(
                values=["well-posed", "ill-posed"],
                labels=["well-posed", "rank < unknowns"],
                colors=[_OK_RGB, (*ILL_POSED_RGB, 255)],
            ),
        )

    def _log_legend(self) -> None:
        lines = [
            "# torchcontact",
            f"Robot **{self.model.name}**, world frame = its root, z up; arrows: forces at"
            f" **{self.scale:g} N per m** (1 m of arrow = {self.scale:g} N).",
            "",
            f"Contacts, one colour per slot: estimate opaque, truth at {TRUTH_ALPHA:.0%} opacity.",
        ]
        if self.layout is not None:
            lines += [
                f"- slot {k}: rgb{slot_rgb(k)[:3]} {self._slot_name(k)}"
                for k in range(self.layout.K)
            ]
        lines += [
            "",
            f"F/T sensors, sensor frame: the measured force (dark) at **{self.ft_scale:g} N per m**"
            f" (it carries the robot's weight), the force part of A x - b (red) at {self.scale:g}"
            " N per m like the contacts.",
            "",
            f"Grey lane: {ill_posed_note(self.constrained)}; `--nullspace` draws the directions"
            " the sensors cannot see (purple, the largest 25 % of the robot's size).",
            "",
            "Status bits: "
            + ", ".join(f"{b} {STATUS_NAMES.get(b, b)} ({STATUS[b]})" for b in STATUS),
        ]
        missing = sorted({m[0] for m in self.missing})
        if missing:
            lines += ["", f"Meshes missing (link frames drawn instead): {', '.join(missing)}"]
        self.recording.log(
            "legend",
            self.rr.TextDocument("\n".join(lines), media_type="text/markdown"),
            static=True,
        )

    def _blueprint(self) -> Any:
        import rerun.blueprint as rrb

        tabs = [
            rrb.TimeSeriesView(origin="plots/residual", name="|A x - b| per sensor"),
            rrb.TimeSeriesView(origin="plots/sensors", name="F/T measured and A x - b [N, N m]"),
            rrb.TimeSeriesView(origin="plots/status", name="status code"),
        ]
        if self.constrained:
            tabs.insert(0, rrb.TimeSeriesView(origin="plots/cones", name="friction cones"))
        tabs += [
            rrb.TextLogView(origin="log", name="events"),
            rrb.TextDocumentView(origin="legend", name="legend"),
        ]
        eye = rrb.EyeControls3D(
            position=[1.2 * self.size, -1.2 * self.size, 0.9 * self.size],
            look_target=[0.0, 0.0, 0.4 * self.size],
            eye_up=[0.0, 0.0, 1.0],
        )
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial3DView(
                        origin="world",
                        name=f"robot; contact forces {self.scale:g} N per m, F/T readings"
                        f" {self.ft_scale:g} N per m",
                        eye_controls=eye,
                    ),
                    rrb.StateTimelineView(origin="states", name="status, posedness, cones"),
                    row_shares=[4, 1],
                ),
                rrb.Vertical(
                    rrb.TimeSeriesView(
                        origin="plots/forces", name="|force| per slot [N]: estimate (dots), truth"
                    ),
                    rrb.TimeSeriesView(
                        origin="plots/identifiability", name="rank, unknowns, null-space dimension"
                    ),
                    rrb.Tabs(*tabs),
                ),
                column_shares=[3, 2],
            ),
            rrb.TimePanel(timeline="time"),
            collapse_panels=True,
        )

    # ------------------------------------------------------------------ frames
    def _times(self, frames: ViewFrames, sel: np.ndarray | None = None) -> list:
        rr = self.rr
        t, rows = frames.t_ns, frames.rows
        if sel is not None:
            t, rows = t[sel], rows[sel]
        if self._dates:
            time = rr.TimeColumn("time", timestamp=t.astype("datetime64[ns]"))
        else:
            time = rr.TimeColumn("time", duration=t.astype("timedelta64[ns]"))
        return [time, rr.TimeColumn("frame", sequence=rows)]

    def _send(self, path: str, frames: ViewFrames, columns: Any, sel: Any = None) -> None:
        self.recording.send_columns(path, indexes=self._times(frames, sel), columns=columns)

    def _arrows(
        self,
        path: str,
        frames: ViewFrames,
        frame: np.ndarray,
        origins: np.ndarray,
        vectors: np.ndarray,
        colors: np.ndarray,
        radius: float,
    ) -> None:
        """Arrows of every frame (empty where a frame has none: it clears the previous ones)."""
        N = len(frames)
        order = np.argsort(frame, kind="stable")
        counts = np.bincount(frame, minlength=N)
        cols = self.rr.Arrows3D.columns(
            origins=origins[order].astype(np.float32),
            vectors=vectors[order].astype(np.float32),
            colors=colors[order],
            radii=np.full(len(frame), radius, np.float32),
        )
        self._send(path, frames, cols.partition(counts))

    def log(self, frames: ViewFrames) -> None:
        """Draw a batch of frames (after the previous ones, in time order).

        Args:
            frames: the frames; see :class:`ViewFrames`.

        Raises:
            InputError: ``q`` of another width than the model's joints.
        """
        import torch

        import torchcontact as tc

        model, rr = self.model, self.rr
        N = len(frames)
        if N == 0:
            return
        if frames.q.shape[1] != model.nv:
            raise InputError(f"q has {frames.q.shape[1]} joints, {model.name} has {model.nv}")
        if frames.rows is None:
            frames = replace(frames, rows=self._next_row + np.arange(N))
        self._next_row = int(frames.rows[-1]) + 1
        if not self._started:
            self._start(frames)
        # forward pass: every body's pose in the world frame
        q = torch.as_tensor(frames.q, dtype=model.dtype)
        bad_q = ~torch.isfinite(q).all(-1)
        q = torch.where(bad_q[:, None], torch.zeros_like(q), q)
        fp = tc.forward_pass(model, q, torch.zeros_like(q), torch.zeros_like(q))
        R, p = fp.R.numpy(), fp.p.numpy()
        for b in range(model.nb):
            self._send(
                self._body_path(b),
                frames,
                rr.Transform3D.columns(translation=p[:, b], mat3x3=R[:, b]),
            )
        if self._skeleton and model.nb > 1:
            parents = np.array(model.body_parent[1:])
            strips = np.stack([p[:, parents], p[:, 1:]], 2).reshape(-1, 2, 3)
            self._send(
                "world/robot/skeleton",
                frames,
                rr.LineStrips3D.columns(
                    strips=strips.astype(np.float32),
                    radii=np.full(len(strips), 0.01 * self.size, np.float32),
                    colors=np.tile([110, 110, 110, 255], (len(strips), 1)).astype(np.uint8),
                ).partition(np.full(N, model.nb - 1)),
            )
        self._log_sensors(frames)
        if frames.records is not None:
            self._log_contacts(frames, fp)
        self._log_quality(frames)
        if frames.null is not None:
            self._log_null(frames)
        self.frames_logged += N

    def _log_sensors(self, frames: ViewFrames) -> None:
        rr = self.rr
        N = len(frames)
        zero = np.zeros((N, 3), np.float32)
        for s in self.sensors:
            base = self._sensor_path(s)
            for what, data, color, scale in (
                ("measured", frames.ft.get(s), _MEASURED_RGB, self.ft_scale),
                ("residual", (frames.residual_wrench or {}).get(s), _RESIDUAL_RGB, self.scale),
            ):
                if data is None:
                    continue
                data = np.asarray(data, np.float64)
                ok = np.isfinite(data[:, :3]).all(-1)
                frame = np.flatnonzero(ok)
                self._arrows(
                    f"{base}/{what}",
                    frames,
                    frame,
                    zero[ok],
                    data[ok, :3] / scale,
                    np.tile(color, (len(frame), 1)),
                    0.012 * self.size,
                )
                self._send(
                    f"plots/sensors/{s}/{what}",
                    frames,
                    rr.Scalars.columns(scalars=data.reshape(-1)).partition(np.full(N, 6)),
                )

    def _log_contacts(self, frames: ViewFrames, fp: Any) -> None:
        rr, model = self.rr, self.model
        rec_ = frames.records
        N = len(frames)
        slot = np.full(len(rec_), -1) if frames.slot is None else np.asarray(frames.slot)
        drawn = np.flatnonzero((slot >= 0) & np.isfinite(rec_.positions).all(-1))
        f = rec_.frame[drawn]
        c = np.zeros((len(drawn), 3))
        R_rec = np.zeros((len(drawn), 3, 3))
        for link in set(rec_.links[drawn].tolist()):
            at = np.flatnonzero(rec_.links[drawn] == link)
            try:
                R, p = (x.numpy() for x in model.frame_pose(fp, link))
            except KeyError:
                raise InputError(f"contact link {link!r} is not a link of {model.name}") from None
            R_rec[at] = R[f[at]]
            c[at] = np.einsum("mij,mj->mi", R[f[at]], rec_.positions[drawn[at]]) + p[f[at]]
        k = slot[drawn]
        colors = np.array([slot_rgb(int(x)) for x in k], np.uint8).reshape(-1, 4)
        self._send(
            "world/contacts/points",
            frames,
            rr.Points3D.columns(
                positions=c.astype(np.float32),
                colors=colors,
                radii=np.full(len(c), 0.012 * self.size, np.float32),
            ).partition(np.bincount(f, minlength=N)),
        )
        radius = 0.012 * self.size
        for what, data, alpha, r in (
            ("estimate", frames.force, 1.0, radius),
            ("truth", frames.true_force, TRUTH_ALPHA, 0.6 * radius),
        ):
            if data is None:
                continue
            v = np.einsum("mij,mj->mi", R_rec, np.asarray(data, np.float64)[drawn])
            ok = np.isfinite(v).all(-1)
            cols = np.array([slot_rgb(int(x), alpha) for x in k[ok]], np.uint8).reshape(-1, 4)
            self._arrows(
                f"world/contacts/{what}", frames, f[ok], c[ok], v[ok] / self.scale, cols, r
            )
        if frames.cone_active is not None:
            act = np.asarray(frames.cone_active, bool)[drawn]
            self._send(
                "world/contacts/cone_active",
                frames,
                rr.Points3D.columns(
                    positions=c[act].astype(np.float32),
                    colors=colors[act],
                    radii=np.full(act.sum(), 0.025 * self.size, np.float32),
                    labels=["cone active"] * int(act.sum()),
                ).partition(np.bincount(f[act], minlength=N)),
            )
            self._send(
                "plots/cones/active",
                frames,
                rr.Scalars.columns(scalars=np.bincount(f[act], minlength=N).astype(float)),
            )
        # force norm per slot over time (NaN where the slot is not in contact: a gap)
        for kk in np.unique(k):
            self._style_slot(int(kk), truth=frames.true_force is not None)
            at = k == kk
            for what, data in (("estimate", frames.force), ("truth", frames.true_force)):
                if data is None:
                    continue
                y = np.full(N, np.nan)
                y[f[at]] = np.linalg.norm(np.asarray(data, np.float64)[drawn[at]], axis=-1)
                self._send(f"plots/forces/slot{kk}/{what}", frames, rr.Scalars.columns(scalars=y))

    def _changes(self, key: str, values: list[str]) -> np.ndarray:
        """Indices where ``values`` differ from the value before (across batches)."""
        prev = self._state.get(key)
        idx = [i for i, v in enumerate(values) if v != (prev if i == 0 else values[i - 1])]
        if values:
            self._state[key] = values[-1]
        return np.array(idx, np.int64)

    def _state_lane(self, path: str, frames: ViewFrames, values: list[str]) -> None:
        at = self._changes(path, values)
        if len(at):
            self._send(path, frames, self.rr.StateChange.columns(state=[values[i] for i in at]), at)

    def _log_quality(self, frames: ViewFrames) -> None:
        rr = self.rr
        rows = frames.rows
        events: list[tuple[int, str, str]] = []  # (index, level, text)
        if frames.rank is not None and frames.unknowns is not None:
            for s in frames.rank:
                r = np.asarray(frames.rank[s], float)
                u = np.asarray(frames.unknowns[s], float)
                n = (u - r) if frames.nullity is None else np.asarray(frames.nullity[s], float)
                for what, y in (("rank", r), ("unknowns", u), ("nullity", n)):
                    self._send(
                        f"plots/identifiability/{s}/{what}", frames, rr.Scalars.columns(scalars=y)
                    )
            ill = rank_deficient(frames.rank, frames.unknowns)
            self._send(
                "plots/identifiability/ill_posed",
                frames,
                rr.Scalars.columns(scalars=ill.astype(float)),
            )
            posed = ["ill-posed" if x else "well-posed" for x in ill]
            for i in self._changes("events/posedness", posed):
                if posed[i] == "ill-posed":
                    events.append(
                        (int(i), "WARN", f"row {rows[i]}: {ill_posed_note(self.constrained)}")
                    )
                else:
                    events.append((int(i), "INFO", f"row {rows[i]}: well-posed again"))
            self._state_lane("states/posedness", frames, posed)
        if frames.residual is not None:
            for s, y in frames.residual.items():
                self._send(
                    f"plots/residual/{s}", frames, rr.Scalars.columns(scalars=np.asarray(y, float))
                )
        if frames.status is not None:
            code = np.asarray(frames.status, np.int64)
            self._send("plots/status/code", frames, rr.Scalars.columns(scalars=code.astype(float)))
            names = ["+".join(status_bits(int(x))) or "ok" for x in code]
            self._state_lane("states/status", frames, names)
            for i in np.flatnonzero(code != 0):
                events.append((int(i), "ERROR", f"row {rows[i]}: status {code[i]} ({names[i]})"))
        if frames.converged is not None:
            for s, conv in frames.converged.items():
                lane = ["" if c is None else "converged" if c else "not converged" for c in conv]
                self._state_lane(f"states/cones/{s}", frames, lane)
            for s, it in (frames.iterations or {}).items():
                self._send(
                    f"plots/cones/{s}/iterations",
                    frames,
                    rr.Scalars.columns(scalars=np.asarray(it, float)),
                )
        if events:
            events.sort()
            at = np.array([e[0] for e in events])
            self._send(
                "log",
                frames,
                rr.TextLog.columns(text=[e[2] for e in events], level=[e[1] for e in events]),
                at,
            )

    def _log_null(self, frames: ViewFrames) -> None:
        by: dict[tuple[str, int], list] = {}
        for i, dirs in enumerate(frames.null or []):
            for d in dirs or []:
                if d.index < MAX_DIRECTIONS:
                    by.setdefault((d.sensor, d.index), []).append((i, d))
        keys = set(by) | {
            (s, j)
            for s in self.sensors
            for j in range(MAX_DIRECTIONS)
            if f"world/nullspace/{s}/dir{j}" in self._styled
        }
        for s, j in sorted(keys):
            path = f"world/nullspace/{_esc(s)}/dir{j}"
            self._styled.add(f"world/nullspace/{s}/dir{j}")
            frame, origins, vectors = [], [], []
            for i, d in by.get((s, j), []):
                fmax = max(max((np.linalg.norm(fk) for _, fk, _ in d.parts), default=0.0), 1e-12)
                for c, fk, _ in d.parts:
                    frame.append(i)
                    origins.append(c)
                    vectors.append(fk * 0.25 * self.size / fmax)
            color = np.tile([*NULLSPACE_RGB, 170], (len(frame), 1)).astype(np.uint8)
            self._arrows(
                path,
                frames,
                np.array(frame, np.int64),
                np.array(origins).reshape(-1, 3),
                np.array(vectors).reshape(-1, 3),
                color,
                0.006 * self.size,
            )

    def flush(self) -> None:
        """Hand everything logged so far to the recording's sink."""
        self.recording.flush()


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def frames_from_estimate(
    model: Any, frames: Mapping[str, Any], estimate: Any = None
) -> tuple[ViewFrames, Any]:
    """:class:`ViewFrames` from arrays and a :class:`~torchcontact.ContactEstimate` (flat batch).

    Args:
        model: the robot.
        frames: ``t_ns (N,)``, ``q (N, nv)`` (model order), optionally ``rows (N,)``, ``ft``
            (sensor -> ``(N, 6)``), ``contacts`` (a :class:`~torchcontact.Contacts` with K slots,
            the ones the estimate was made with), ``true_force`` ``(N, K, 3)`` link frame, N.
        estimate: the :class:`~torchcontact.ContactEstimate` of those frames (``(N, ...)``), or
            None.

    Returns:
        ``(frames, layout)``: slot ``k`` of ``contacts`` is drawn in colour ``k``.
    """
    from torchcontact.contacts import SlotLayout

    unknown = set(frames) - {"t_ns", "q", "rows", "ft", "contacts", "true_force"}
    if unknown:
        raise InputError(
            f"frames: unknown keys {sorted(unknown)} (t_ns, q, rows, ft, contacts, true_force)"
        )
    for need in ("t_ns", "q"):
        if need not in frames:
            raise InputError(f"frames needs {need!r}")
    t_ns = _np(frames["t_ns"]).astype(np.int64).reshape(-1)
    N = len(t_ns)
    kw: dict[str, Any] = {"t_ns": t_ns, "q": _np(frames["q"]).reshape(N, -1)}
    if "rows" in frames:
        kw["rows"] = _np(frames["rows"])
    kw["ft"] = {s: _np(v).reshape(N, 6) for s, v in (frames.get("ft") or {}).items()}
    layout = None
    contacts = frames.get("contacts")
    if contacts is not None:
        layout = SlotLayout(contacts.links, contacts.kinds)
        K = contacts.K
        act = (
            np.ones((N, K), bool)
            if contacts.active is None
            else _np(contacts.active).reshape(N, K).astype(bool)
        )
        f, k = np.nonzero(act)
        kw["records"] = contacts.to_records()
        kw["slot"] = k
        if "true_force" in frames:
            kw["true_force"] = _np(frames["true_force"]).reshape(N, K, 3)[f, k]
        if estimate is not None:
            kw["force"] = _np(estimate.force).reshape(N, K, 3)[f, k]
            kw["moment"] = _np(estimate.moment).reshape(N, K, 3)[f, k]
            if estimate.cones is not None:
                kw["cone_active"] = _np(estimate.cones.active).reshape(N, K)[f, k]
    if estimate is not None:
        for name in ("rank", "unknowns", "residual"):
            kw[name] = {s: _np(v).reshape(N) for s, v in getattr(estimate, name).items()}
        kw["nullity"] = {s: _np(v).reshape(N) for s, v in estimate.nullity.items()}
        kw["status"] = _np(estimate.status).reshape(N)
        if estimate.cones is not None:
            kw["converged"] = {s: _np(v).reshape(N) for s, v in estimate.cones.converged.items()}
            kw["iterations"] = {s: _np(v).reshape(N) for s, v in estimate.cones.iterations.items()}
    return ViewFrames(**kw), layout


def log_to_rerun(
    model: Any,
    frames: Mapping[str, Any] | ViewFrames,
    estimates: Any = None,
    *,
    scene: RerunScene | None = None,
    recording: Any = None,
    urdf: str | Path | None = None,
    scale: float | None = None,
) -> RerunScene:
    """Draw frames of a robot and their contact estimate into a rerun recording.

    For a notebook or a live stream: keep the returned scene and pass it back (``scene=``) with
    the next frames, so the static parts are logged once and the arrow scale stays the same.

    Args:
        model: the robot.
        frames: a :class:`ViewFrames`, or a dict with ``t_ns (N,)`` ns, ``q (N, nv)`` (model
            order), optionally ``ft`` (sensor -> ``(N, 6)`` ``[N; N m]``, sensor frame),
            ``contacts`` (the :class:`~torchcontact.Contacts` estimated, ``(N, K, ...)``),
            ``true_force`` ``(N, K, 3)`` and ``rows (N,)``; numpy arrays or tensors.
        estimates: the :class:`~torchcontact.ContactEstimate` of the frames (``(N, ...)``), or
            None (robot, readings and contact points only).
        scene: a scene returned by an earlier call (draws into its recording).
        recording: a ``rerun.RecordingStream`` for a new scene (default: a new recording; call
            ``scene.recording.save(path)``, ``.spawn()`` or ``.notebook_show()`` on it first).
        urdf: the robot's URDF, for its visual meshes (new scene).
        scale: arrow scale, N per m (new scene; default from these frames).

    Returns:
        The :class:`RerunScene`.

    Raises:
        InputError: frames of the wrong shapes, unknown keys.
        MissingExtraError: rerun-sdk is not installed (extra ``view``).

    Example:
        >>> import torch, torchcontact as tc
        >>> from torchcontact.view import log_to_rerun
        >>> model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> q = torch.zeros(3, model.nv, dtype=torch.float64)
        >>> c = tc.Contacts(["hand_skin"], ["force"], torch.zeros(3, 1, 3, dtype=torch.float64))
        >>> ft = tc.ContactEstimator(model).predict_ft(q, q, q, tc.Contacts(
        ...     ["hand_skin"], ["known"], c.positions,
        ...     wrenches=torch.tensor([0, 0, -5.0, 0, 0, 0]).expand(3, 1, 6).double()))
        >>> r = tc.ContactEstimator(model).estimate(q, q, q, ft, c)
        >>> scene = log_to_rerun(model, {"t_ns": [0, 10**7, 2 * 10**7], "q": q, "ft": ft,
        ...                              "contacts": c}, r)
        >>> scene.frames_logged
        3
    """
    layout = None
    if not isinstance(frames, ViewFrames):
        frames, layout = frames_from_estimate(model, frames, estimates)
    elif estimates is not None:
        raise InputError("a ViewFrames carries its estimate: pass estimates=None")
    if scene is None:
        constrained = frames.converged is not None
        scene = RerunScene(
            model,
            recording,
            urdf=urdf,
            layout=layout,
            scale=scale,
            sensors=list(frames.ft) or None,
            constrained=constrained,
        )
    scene.log(frames)
    return scene


class LiveView:
    """Draw the live loop's frames into a recording (``torchcontact run --onnx ... --view``).

    Buffers frames and draws them in batches (every ``every`` frames or ``period`` seconds).

    Args:
        scene: the :class:`RerunScene` to draw into (its layout: the graph's slots).
        sensors: the order of the sensors in a reading ``(6 S,)``.
        joint_names: the order of the joints in a joint state (default: the model's).
        contacts: the graph's contact inputs, a dict with ``positions (K, 3)`` and ``active (K,)``
            (:attr:`torchcontact.drivers.live.OnnxEstimator.contacts`), or None (no contact).
        every: most frames per batch.
        period: most seconds a frame waits.
        out: the file the recording goes to (renamed from ``out.tmp`` by :meth:`close`).
    """

    def __init__(
        self,
        scene: RerunScene,
        sensors: Sequence[str],
        joint_names: Sequence[str] | None = None,
        contacts: Mapping[str, Any] | None = None,
        every: int = 20,
        period: float = 0.1,
        out: str | Path | None = None,
    ) -> None:
        model = scene.model
        self.scene = scene
        self.sensors = list(sensors)
        names = list(model.joint_names if joint_names is None else joint_names)
        missing = [n for n in model.joint_names if n not in names]
        if missing:
            raise InputError(f"joint states lack joints {missing} of {model.name}")
        self.perm = np.array([names.index(n) for n in model.joint_names], np.int64)
        self.contacts = contacts
        self.every = every
        self.period = period
        self.out = out
        self._buf: list[dict[str, Any]] = []
        self._since = 0.0

    @classmethod
    def for_estimator(cls, estimator: Any, robot: str | Path | None, target: str) -> LiveView:
        """The live view of an :class:`~torchcontact.drivers.live.OnnxEstimator`.

        Args:
            estimator: the loop's estimator (its runtime gives the slots, sensors and joints).
            robot: the robot's URDF, or ``"tcarm"``.
            target: ``"spawn"`` (open a viewer) or a ``.rrd`` file to write.

        Raises:
            InputError: no robot given.
        """
        from torchcontact.contacts import SlotLayout
        from torchcontact.model import RobotModel
        from torchcontact.robots import tcarm_path

        if robot is None:
            raise InputError("--view needs --robot URDF (its meshes and kinematics)")
        urdf = tcarm_path() if str(robot) == "tcarm" else Path(robot)
        rt = estimator.runtime
        scene = RerunScene(
            RobotModel.from_urdf(urdf),
            urdf=urdf,
            layout=SlotLayout(rt.slot_links, rt.slot_kinds),
            sensors=list(rt.sensor_names),
        )
        out = None
        if target == "spawn":
            scene.recording.spawn(connect=True)
        else:
            out = Path(target)
            scene.recording.save(str(out) + ".tmp")
        contacts = estimator.contacts if isinstance(estimator.contacts, Mapping) else None
        return cls(scene, rt.sensor_names, rt.joint_names, contacts, out=out)

    def __call__(self, sample: Any, joints: Any, estimate: Mapping[str, Any]) -> None:
        """The live loop's hook: one F/T sample, its joint state and the estimate."""
        if joints is None or "error" in estimate:
            return
        K = self.scene.layout.K if self.scene.layout is not None else 0
        spec = self.contacts or {}
        self.add(
            sample.t_ns,
            np.asarray(joints.q, float)[self.perm],
            sample.wrench,
            estimate,
            np.asarray(spec.get("positions", np.zeros((K, 3))), float),
            np.asarray(spec.get("active", np.zeros(K)), float) > 0.5,
        )

    def add(
        self,
        t_ns: int,
        q: np.ndarray,
        ft: np.ndarray,
        estimate: Mapping[str, Any],
        positions: np.ndarray,
        active: np.ndarray,
    ) -> None:
        """Add one frame.

        Args:
            t_ns: time stamp, ns.
            q: ``(nv,)`` joint positions (model order).
            ft: ``(6 S,)`` readings of the sensors, ``[N; N m]``.
            estimate: the runtime's result (``force``/``moment`` ``(K, 3)``, ``rank``,
                ``unknowns``, ``residual`` ``(S,)``, ``status``).
            positions: ``(K, 3)`` contact points, link frames, m.
            active: ``(K,)`` which slots touch.
        """
        import time

        if not self._buf:
            self._since = time.monotonic()
        self._buf.append(
            {
                "t_ns": int(t_ns),
                "q": np.asarray(q, float),
                "ft": np.asarray(ft, float),
                "est": dict(estimate),
                "pos": np.asarray(positions, float),
                "act": np.asarray(active).astype(bool),
            }
        )
        if len(self._buf) >= self.every or time.monotonic() - self._since >= self.period:
            self.flush()

    def flush(self) -> None:
        """Draw the buffered frames."""
        from torchcontact.contacts import ContactRecords

        if not self._buf:
            return
        buf, self._buf = self._buf, []
        S = len(self.sensors)
        layout = self.scene.layout
        act = np.stack([b["act"] for b in buf])
        f, k = np.nonzero(act)
        pos = np.stack([b["pos"] for b in buf])

        def per_sensor(key: str) -> dict[str, np.ndarray] | None:
            if any(key not in b["est"] for b in buf):
                return None
            v = np.stack([np.asarray(b["est"][key], float).reshape(S) for b in buf])
            return {s: v[:, i] for i, s in enumerate(self.sensors)}

        def per_slot(key: str) -> np.ndarray | None:
            if any(key not in b["est"] for b in buf):
                return None
            return np.stack([np.asarray(b["est"][key], float).reshape(-1, 3) for b in buf])[f, k]

        records = ContactRecords(
            f, np.asarray(layout.links, object)[k], np.asarray(layout.kinds, object)[k], pos[f, k]
        )
        ft = np.stack([b["ft"].reshape(S, 6) for b in buf])
        status = None
        if all("status" in b["est"] for b in buf):
            status = np.array([int(np.asarray(b["est"]["status"]).reshape(-1)[0]) for b in buf])
        self.scene.log(
            ViewFrames(
                t_ns=np.array([b["t_ns"] for b in buf]),
                q=np.stack([b["q"] for b in buf]),
                ft={s: ft[:, i] for i, s in enumerate(self.sensors)},
                records=records,
                slot=k,
                force=per_slot("force"),
                moment=per_slot("moment"),
                rank=per_sensor("rank"),
                unknowns=per_sensor("unknowns"),
                residual=per_sensor("residual"),
                status=status,
            )
        )
        self.scene.flush()

    def close(self) -> None:
        """Draw what is buffered and finish the recording (a file gets its final name)."""
        import os

        self.flush()
        rec = self.scene.recording
        rec.flush()
        if self.out is not None:
            rec.disconnect()
            tmp = Path(str(self.out) + ".tmp")
            if tmp.exists():
                os.replace(tmp, self.out)
