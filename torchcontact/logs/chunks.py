"""The per-chunk estimate: a decoded chunk of a log -> its output rows, the same for both engines.

:class:`LogEstimator` holds what is fixed for a log (the robot, the log's joint order and sensors,
its one slot layout, the options); :func:`decoded_chunks` turns consecutive Arrow tables into
decoded chunks (arrays, time segments, derived ``qd``/``qdd``, contacts in the log's slots:
:mod:`torchcontact.logs.decode`) and :func:`estimate_stream` estimates them in order, carrying the
last estimates of a chunk into the next one's warm start. The local engine runs these on its
threads (:mod:`torchcontact.logs.pipeline`), the Ray engine inside each task
(:mod:`torchcontact.logs.ray_engine`).

Status: every output row has ``status_code`` (the bits of :data:`torchcontact.STATUS`), ``status``
(its text) and ``status_detail`` (what the pipeline found: a malformed vector, an unknown link, a
joint beyond its velocity limit, a frame too short to differentiate, ...). Frames with a non-zero
code have NaN outputs, but for the warning bits alone (``NOT_CONVERGED`` 256: the last iterate, see
below; ``OUTSIDE_TRAINING`` 1024: a correction outside its training range); the rest of the log is
processed.

Friction cones (:class:`LogConstraints`, ``estimate --constraints``): every pushing contact's force
is kept inside the friction cone of its ``normal`` (contact field) and friction coefficient
(``friction`` or ``cone_angle`` field, else the run's default); the output adds per sensor
``converged.<sensor>`` and ``iterations.<sensor>`` and per contact ``cone_active``. Frames are
warm-started from their predecessor's estimate (:class:`~torchcontact.PreviousFrame`), across
chunks too (a chunk's first frame starts from the previous chunk's last estimates, matched by
link, kind and order), but never across a time-segment boundary (a repeated, backward or gapped
``t_ns``): a segment's first frame starts cold. A frame that does not converge (after the
estimator's restart from the pseudo-inverse) gets status bit 256 (``NOT_CONVERGED``) and
``converged.<sensor> = false``, and keeps its last interior-point iterate, inside the cones: the
a warning bit: its frames keep their outputs (never ``ok``, counted in the summary).

Noise (:attr:`LogEstimator.noise`, :mod:`torchcontact.logs.noise`): with a weighted noise every
chunk's solve is whitened by each sensor's covariance (fixed, or the frame's ``ft_cov.<sensor>``).

Localization (:class:`LogLocalize`, ``estimate --localize``): in each sensor region that holds
candidate links, a frame without a skin contact there gets the contact localized from the F/T
wrench and the collision meshes (:func:`torchcontact.localize.localize_chunk`) as a ``force``
record at the point, with its outward normal; the estimator then runs on the records as usual.
The output's contacts include these records (the input's other fields null) and each localizing
sensor's :func:`~torchcontact.logs.format.localization_fields`. The log's slot layout gets one
``force`` slot per candidate link, so every chunk still runs one program.
"""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from torchcontact.constrained import FrictionCones, PreviousFrame
from torchcontact.contacts import ContactRecords, Contacts, SlotLayout
from torchcontact.errors import InputError, KernelBuildError, LogError, MissingExtraError
from torchcontact.estimation import ContactEstimator
from torchcontact.logs.decode import ChunkDecoder, Decoded, FrameIssues, status_text
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW, DerivativeStream, time_segments
from torchcontact.logs.format import (
    ESTIMATE_BIAS_COLUMNS,
    META_BIAS,
    META_DERIVED,
    META_FT_NOISE,
    META_LOCALIZE,
    META_RESIDUAL,
    META_SENSORS,
    META_URDF_SHA256,
    META_VERSION,
    bias_column,
    contact_struct_type,
    fixed_list,
    ft_column,
    joint_permutation,
    numpy_to_arrow,
    output_schema,
    string_array,
    struct_list,
)
from torchcontact.logs.noise import FTNoise
from torchcontact.model import RobotModel
from torchcontact.status import DEFAULT_VELOCITY_MARGIN, WARNINGS, Status

__all__ = [
    "DEFAULT_VELOCITY_MARGIN",
    "LogBias",
    "LogConstraints",
    "LogLocalize",
    "LogEstimator",
    "decoded_chunks",
    "estimate_stream",
]

NOT_CONVERGED = int(Status.NOT_CONVERGED)


# The plausibility bit (64) and the non-finite-output bit (32) are set by the estimator
# (ContactEstimator(..., velocity_margin=..., ft_range=...)), one meaning in Python and logs.


def ft_ranges(ft_range: Mapping[str, Any] | None, sensors: Sequence[str]) -> dict[str, np.ndarray]:
    """``{sensor: (6,) or scalar}`` -> ``{sensor: (6,)}`` limits [N; N m], for sensors in use.

    Raises:
        InputError: a sensor not in use, a limit that is not 1 or 6 positive numbers.
    """
    out: dict[str, np.ndarray] = {}
    for s, v in (ft_range or {}).items():
        if s not in sensors:
            raise InputError(f"--ft-range {s}: not a sensor in use ({list(sensors)})")
        arr = np.broadcast_to(np.asarray(v, np.float64).reshape(-1), (6,)).copy()
        if np.asarray(v).size not in (1, 6) or not (arr > 0).all():
            raise InputError(f"--ft-range {s}: give 1 or 6 positive numbers [N; N m], got {v}")
        out[s] = arr
    return out


@dataclass(frozen=True)
class LogConstraints:
    """Friction-cone constrained estimation of a log (``estimate --constraints``).

    Attributes:
        cones: the solver's settings (iteration budget, ``eps``, ``tol``).
        friction: friction coefficient of the contacts whose records give neither ``friction``
            nor ``cone_angle`` (None: such a contact is an invalid record, status bit 4).
        warm_start: start each frame from its predecessor's estimate (else from the
            pseudo-inverse solution).
        wave: frames per batched call of the warm-started waves
            (:class:`~torchcontact.PreviousFrame`).

    Raises:
        InputError: a friction coefficient that is not a finite number > 0, a wave < 1.

    Example:
        >>> LogConstraints(friction=0.5).cones.iterations
        25
    """

    cones: FrictionCones = field(default_factory=FrictionCones)
    friction: float | None = None
    warm_start: bool = True
    wave: int = 1024

    def __post_init__(self) -> None:
        if self.friction is not None and not (0 < float(self.friction) < np.inf):
            raise InputError(f"--friction must be a finite number > 0, got {self.friction}")
        if not (isinstance(self.wave, int) and self.wave >= 1):
            raise InputError(f"the warm-start wave must be an integer >= 1, got {self.wave!r}")


@dataclass(frozen=True)
class LogBias:
    """F/T offsets tracked over a whole log from the model (``estimate --track-bias``).

    Two passes. Pass 1 reads the log once: per frame and sensor the residual ``z = ft -
    ft_model`` (``ft_model``: the model's contact-free reading, ``predict_ft``, plus the
    correction stack's inertial and learned layers:
    :meth:`torchcontact.online.estimator.OnlineEstimator.model_terms`) and whether the frame may
    measure the offset (no contact record in a slot of the sensor's region, the rule of
    :meth:`torchcontact.online.state.OnlineState.contact_free`; a record the layout cannot place
    blocks every sensor; a frame with a status or a non-finite residual never measures) go into
    the online tracker's filter (:class:`torchcontact.online.bias.BiasSmoother`, whose per-frame
    states go to a file in the run's ``OUT.partial/``: the process holds one chunk at a time),
    then the Rauch-Tung-Striebel pass runs backward over that file. Pass 2 is the estimate, with
    each reading less its frame's offset (which replaces the stack's constant offset, the prior)
    and the stack's other layers.

    Attributes:
        time_constant: s, the tracker's (:class:`~torchcontact.online.bias.BiasTracker`).
        ft_std: ``(6,)`` F/T noise standard deviations [N; N m] (None: the tracker's default):
            the reported uncertainty only.
        smoother: forward-backward (True) or the causal filter alone, as the robot sees it.

    Raises:
        InputError: a time constant that is not > 0, ``ft_std`` not 6 positive numbers.
    """

    time_constant: float = 0.5
    ft_std: tuple[float, ...] | None = None
    smoother: bool = True

    def __post_init__(self) -> None:
        if not (isinstance(self.time_constant, (int, float)) and self.time_constant > 0):
            raise InputError(f"--bias-time-constant must be > 0 s, got {self.time_constant!r}")
        if self.ft_std is not None:
            std = np.asarray(self.ft_std, np.float64)
            if std.shape != (6,) or not (np.isfinite(std).all() and (std > 0).all()):
                raise InputError(f"--ft-std: give 6 positive numbers [N; N m], got {self.ft_std}")

    def describe(self) -> dict[str, Any]:
        """JSON-ready settings (the output's :data:`~torchcontact.logs.format.META_BIAS`)."""
        return {
            "method": "Kalman filter + RTS smoother" if self.smoother else "Kalman filter",
            "time_constant": self.time_constant,
            "ft_std": None if self.ft_std is None else list(self.ft_std),
        }


#: Localize a chunk on the reader thread (overlapping the estimate of the chunk before; only
#: when no residual corrects the readings first) rather than on the estimating thread. Off:
#: measured on the loaded 2-vCPU machine (benchmarks/localize_pipeline.py), it was no faster
#: (Embree 13.7 k vs 16.1 k frames/s, torch 10.9 k vs 11.1 k); rerun on a quiet machine.
LOCALIZE_ON_READER = False

#: Fields a localized contact record fills in the output's contact struct (added when missing).
LOCALIZED_FIELDS = ("link", "kind", "position", "normal")


class LogLocalize:
    """Contact localization in a log estimate (``estimate --localize``): meshes loaded once.

    The collision meshes are loaded and the ray-casting trees built once per run; each set of
    sensors in use gets one :class:`~torchcontact.localize.Localizer` (built on first use and
    kept), shared by every chunk and every log of the run.

    Args:
        meshes: the robot's collision meshes (:func:`torchcontact.meshes.load_meshes`).
        links: candidate links, or ``"subtree"``: every meshed link in a sensor's region.
        force_threshold: below this force a frame has no contact, N.
        accept_ambiguous: also use the first candidate of ambiguous frames (status bit 16).
        ft_std: ``(6,)`` F/T noise standard deviations ``[N; N m]`` of every localizing sensor
            (fills ``localize_position_std``), or None (NaN).
        ray: the localizer's ray-casting backend (:data:`torchcontact.localize.RAY_BACKENDS`).
        temporal: resolve ambiguous frames by the contact of their neighbours in the same run
            of contact (:meth:`~torchcontact.localize.Localizer.localize_sequence`), within each
            chunk's time segments (a run that crosses a chunk boundary is resolved on each side
            apart).

    Raises:
        InputError: a threshold < 0, an ``ft_std`` that is not 6 numbers >= 0.
    """

    def __init__(
        self,
        meshes: Any,
        links: Sequence[str] | str = "subtree",
        *,
        force_threshold: float = 1.0,
        accept_ambiguous: bool = False,
        ft_std: Sequence[float] | None = None,
        ray: str = "auto",
        temporal: bool = False,
    ) -> None:
        if not force_threshold >= 0:
            raise InputError(f"--localize-threshold must be >= 0 N, got {force_threshold}")
        if ft_std is not None:
            std = np.asarray(ft_std, np.float64).reshape(-1)
            if std.shape != (6,) or not (std >= 0).all():
                raise InputError(f"--localize-ft-std takes 6 numbers >= 0 [N; N m], got {ft_std}")
            ft_std = std.tolist()
        self.meshes = meshes
        self.links = links if isinstance(links, str) else tuple(links)
        self.force_threshold = float(force_threshold)
        self.accept_ambiguous = bool(accept_ambiguous)
        self.ft_std = ft_std
        self.ray = ray
        self.temporal = bool(temporal)
        self._localizers: dict[tuple, Any] = {}

    @classmethod
    def load(
        cls, model: RobotModel, urdf: Any, links: Sequence[str] | str = "subtree", **options: Any
    ) -> LogLocalize:
        """Load the collision meshes of ``urdf`` (the file ``model`` was built from).

        Args:
            model: the robot.
            urdf: its URDF path (or a :class:`~torchcontact.robots.RobotSpec`).
            links: as the constructor.
            **options: the constructor's keyword options.

        Raises:
            InputError: the robot has no collision geometry, or a named link has none (with the
                files that failed to load), or is not a link of the robot.
            MissingExtraError: trimesh (or pycollada for ``.dae`` files) is not installed.
        """
        import os

        from torchcontact.meshes import load_meshes

        named = None if isinstance(links, str) else list(links)
        if isinstance(links, str) and links != "subtree":
            raise InputError(f"--localize takes link names or 'subtree', got {links!r}")
        meshes = load_meshes(model, os.fspath(urdf), "collision", links=named)
        for _, _, why in meshes.missing:  # a missing extra is the one thing to say
            if "pip install" in why and not meshes.links:
                raise MissingExtraError(why.split("'")[1], "meshes")
        if not meshes.links:
            why = "; ".join(f"{link}: {f}: {w}" for link, f, w in meshes.missing[:3])
            raise InputError(
                f"--localize: {model.name} ({os.fspath(urdf)}) has no collision mesh"
                + (f" that loads ({why})" if why else " (no <collision> element in the URDF)")
            )
        return cls(meshes, links, **options)

    def localizer(self, model: RobotModel, sensors: Sequence[str]) -> Any:
        """The :class:`~torchcontact.localize.Localizer` of a set of sensors (built once).

        Raises:
            InputError: a candidate link outside the regions of ``sensors`` or without geometry.
        """
        from torchcontact.localize import Localizer

        key = (id(model), tuple(sensors))
        if key not in self._localizers:
            try:
                self._localizers[key] = Localizer(
                    model, self.meshes, self.links, list(sensors),
                    force_threshold=self.force_threshold, ray=self.ray,
                )  # fmt: skip
            except InputError as exc:
                raise InputError(f"--localize: {exc}") from None
        return self._localizers[key]

    def covariance(self, sensors: Sequence[str]) -> dict[str, np.ndarray] | None:
        """``{sensor: (6, 6)}`` reading covariances from ``ft_std`` (None without it)."""
        if self.ft_std is None:
            return None
        return {s: np.diag(np.square(self.ft_std)) for s in sensors}

    def options(self) -> dict[str, Any]:
        """What the localization is (a resume must match; Ray workers rebuild it from this)."""
        return {
            "links": self.links if isinstance(self.links, str) else list(self.links),
            "force_threshold": self.force_threshold,
            "accept_ambiguous": self.accept_ambiguous,
            "ft_std": self.ft_std,
            "ray": self.ray,
            "temporal": self.temporal,
        }


def localized_layout(layout: SlotLayout | None, links: Sequence[str]) -> SlotLayout:
    """``layout`` with at least one ``force`` slot on each candidate link (sorted pairs).

    A localized contact is added only to frames without skin contacts in its region, so one
    ``force`` slot per candidate link is enough on top of the skin's own slots.
    """
    pairs: dict[tuple[str, str], int] = {}
    if layout is not None:
        for link, kind in zip(layout.links, layout.kinds, strict=True):
            pairs[(link, kind)] = pairs.get((link, kind), 0) + 1
    for link in links:
        pairs[(link, "force")] = max(pairs.get((link, "force"), 0), 1)
    out_links: list[str] = []
    out_kinds: list[str] = []
    for (link, kind), m in sorted(pairs.items()):
        out_links += [link] * m
        out_kinds += [kind] * m
    return SlotLayout(tuple(out_links), tuple(out_kinds))


# ---------------------------------------------------------------------- one chunk
@dataclass
class LogEstimator:
    """Per-chunk estimation for one robot and one input schema.

    Args:
        model: the robot (its dtype and device are those of the computation).
        input_joint_names: joint order of the log's ``q`` columns.
        sensors: F/T sensors to use (each needs an ``ft.<sensor>`` column).
        contact_fields: ``(name, type)`` fields of the input contact struct (output adds
            ``force`` and ``moment``); empty when the log has no ``contacts`` column.
        source: file name used in error messages.
        derived: ``qd``/``qdd`` when derived from ``q`` (recorded in the output metadata).
        residual: learned F/T correction (:class:`~torchcontact.residual.ResidualCorrection`)
            subtracted from its sensor's reading before estimation, or None.
        velocity_margin: frames with a joint velocity beyond ``margin`` times its URDF limit get
            status bit 64 (None: no check).
        ft_range: ``{sensor: (6,) or scalar}`` [N; N m]: frames with a reading beyond it get
            status bit 64.
        constraints: friction-cone constrained estimation (:class:`LogConstraints`), or None.
        layout: the log's slot layout (:meth:`LogScan.layout`): every chunk runs the same
            program; None: each chunk gets the layout covering its own records.
        step_ns: the log's median time step (segments: :mod:`torchcontact.logs.derive`).
        causal: ``(window, order)``: derive ``qd``/``qdd`` with the live loop's causal
            differentiator (``--derivatives causal``); None: the centred Savitzky-Golay.
        bias: track the F/T offsets over the log (:class:`LogBias`); the first pass is
            :meth:`bias_pass` over every chunk, then :meth:`bias_done`.
        noise: the F/T noise weighing the solve (:class:`~torchcontact.logs.noise.FTNoise`; set
            it with :meth:`set_noise` before the first chunk); None: the unweighted solve.
        localize: contact localization (:class:`LogLocalize`), or None.

    Raises:
        LogError: joints missing from or extra to the model (mimic joints are not coordinates),
            an unknown sensor, or a residual for a sensor or joints not in use.
        InputError: a bad ``ft_range``.
    """

    model: RobotModel
    input_joint_names: Sequence[str]
    sensors: Sequence[str]
    contact_fields: Sequence[tuple[str, Any]] = ()
    source: str = ""
    derived: Sequence[str] = ()
    residual: Any = None
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN
    ft_range: Mapping[str, Any] | None = None
    constraints: LogConstraints | None = None
    layout: SlotLayout | None = None
    step_ns: float = 0.0
    causal: tuple[int, int] | None = None
    bias: LogBias | None = None
    noise: FTNoise | None = None
    localize: LogLocalize | None = None
    estimator: ContactEstimator = field(init=False)
    perm: np.ndarray = field(init=False)
    decoder: ChunkDecoder = field(init=False)

    def __post_init__(self) -> None:
        self.perm = joint_permutation(
            self.input_joint_names, self.model.joint_names, self.model.name, self.source
        )
        if self.velocity_margin is not None and not self.velocity_margin > 0:
            raise InputError(f"--velocity-margin must be > 0, got {self.velocity_margin}")
        self._ft_range = ft_ranges(self.ft_range, self.sensors)
        guards = {"velocity_margin": self.velocity_margin, "ft_range": self._ft_range}
        try:
            self.estimator = ContactEstimator(self.model, list(self.sensors), **guards)
        except ValueError as exc:
            raise LogError(f"{self.source}: {exc}") from None
        if self.residual is not None and self.residual.sensor not in self.sensors:
            raise LogError(
                f"{self.source}: the residual checkpoint corrects sensor"
                f" {self.residual.sensor!r}, which is not among the sensors in use"
                f" {list(self.sensors)}"
            )
        cons = self.constraints
        self.decoder = ChunkDecoder(
            self.model, self.perm, len(self.input_joint_names), self.sensors,
            self.contact_fields, self.derived,
            self.estimator.region, self.layout, None if cons is None else cons.friction,
            cons is not None, self.residual_columns(), self.source,
        )  # fmt: skip
        self._schema = None
        self.smoother: Any = None  # the bias pass's BiasSmoother
        self._bias_stats: dict[str, Any] = {}
        if self.bias is not None:
            if self.residual is not None and self.residual.recurrent:
                raise LogError(
                    f"{self.source}: --track-bias with a recurrent (GRU) residual is not"
                    " supported (its state would need both passes); use a stack without GRU"
                )
            from torchcontact.online.estimator import OnlineEstimator

            self._online = OnlineEstimator(
                self.model, list(self.sensors), correction=self.residual, backend="eager"
            )
            self._slot_regions: dict[tuple, np.ndarray] = {}
        #: the localizer of the sensors in use (``localize``), or None
        self.localizer = None
        #: the output's contact struct fields besides force and moment
        self.output_fields = list(self.contact_fields)
        if self.localize is not None:
            self.localizer = self.localize.localizer(self.model, self.sensors)
            have = {n for n, _ in self.contact_fields}
            import pyarrow as pa

            types = {f.name: f.type for f in contact_struct_type(cone=True)}  # the format's
            self.output_fields += [(n, types[n]) for n in LOCALIZED_FIELDS if n not in have]
            # a localized record leaves the input's other fields null: fixed-size list fields
            # become plain lists (pyarrow < 26 cannot read a null fixed-size list entry back)
            self.output_fields = [
                (n, pa.list_(t.value_type))
                if pa.types.is_fixed_size_list(t) and n != "position"
                else (n, t)
                for n, t in self.output_fields
            ]
        self.set_noise(self.noise)

    def set_noise(self, noise: FTNoise | None) -> None:
        """Weigh the solve by ``noise`` (its column sensors' ``ft_cov`` are then decoded)."""
        self.noise = noise
        self.decoder.cov_sensors = [] if noise is None else noise.column_sensors()
        self._schema = None

    def residual_columns(self) -> list[str]:
        """Log columns the residual model reads besides ``q``/``qd``/``qdd`` (e.g. temperature)."""
        return [] if self.residual is None else self.residual.extra_columns

    # ------------------------------------------------------------------ schema
    def output_schema(self) -> Any:
        """Schema of the output rows, with joint names, robot hash and version in the metadata."""
        if self._schema is not None:
            return self._schema
        from torchcontact import __version__

        derived = {"columns": list(self.derived), "method": self.derivative_method()}
        meta = {
            META_URDF_SHA256: self.model.urdf_sha256,
            META_VERSION: __version__,
            META_SENSORS: json.dumps(list(self.sensors)),
            META_DERIVED: json.dumps(derived),
        }
        if self.noise is not None:
            meta[META_FT_NOISE] = self.noise.metadata()
        if self.residual is not None:
            meta[META_RESIDUAL] = json.dumps(
                {
                    "checkpoint": self.residual.source,
                    "weights_sha256": self.residual.meta.get("weights_sha256"),
                    "sensor": self.residual.sensor,
                    "kind": "+".join(self.residual.layers),
                }
            )
        if self.bias is not None:
            meta[META_BIAS] = json.dumps({**self.bias.describe(), "sensors": list(self.sensors)})
        if self.localize is not None:
            meta[META_LOCALIZE] = json.dumps(
                {**self.localize.options(), "candidates": list(self.localizer.links)}
            )
        self._schema = output_schema(
            self.model.joint_names,
            self.sensors,
            self.output_fields,
            meta,
            constraints=self.constraints is not None,
            bias=self.bias is not None,
            localize=self.localizer.sensor_names if self.localizer is not None else (),
        )
        return self._schema

    def derivative_method(self) -> str:
        """How derived ``qd``/``qdd`` are computed (the output's metadata; "" when logged)."""
        if not self.derived:
            return ""
        if self.causal is None:
            return f"Savitzky-Golay order 2 over t_ns, {2 * DEFAULT_HALF_WINDOW + 1} frames"
        from torchcontact.online.derivatives import CausalDerivatives

        w, o = self.causal
        period = self.step_ns * 1e-9 if self.step_ns > 0 else 0.01
        d = CausalDerivatives(self.model.nv, w, o).delay(period)
        return (
            f"causal Savitzky-Golay order {o} over t_ns, {w} frames (the live loop's);"
            f" low-frequency delay qd {d[1] * 1e3:.2f} ms, qdd {d[2] * 1e3:.2f} ms"
        )

    # ------------------------------------------------------------------ --track-bias
    def _contact_free(self, d: Decoded) -> np.ndarray:
        """``(n, S)``: frames that may measure each sensor's offset (see :class:`LogBias`)."""
        if d.contacts is None:
            self.decoder.slots(d, self.model.dtype, self.model.device)
        c = d.contacts
        assert c is not None
        S = len(self.sensors)
        free = np.broadcast_to((d.issues.code == 0)[:, None], (d.n, S)).copy()
        key = (tuple(c.links), tuple(c.kinds))
        if key not in self._slot_regions:
            em = self.estimator.layout(list(c.links), list(c.kinds))
            self._slot_regions[key] = np.array([sl.region for sl in em.slots], np.int64)
        regions = self._slot_regions[key]
        if c.K:
            active = c.active.cpu().numpy().reshape(d.n, c.K)
            for k, r in enumerate(regions.tolist()):
                if 0 <= r < S:
                    free[:, r] &= ~active[:, k]
        unplaced = d.records.frame[d.slot < 0] if len(d.slot) else np.zeros(0, np.int64)
        free[unplaced] = False
        return free

    def _model_terms(self, d: Decoded, explained_only: bool = False) -> tuple[Any, np.ndarray]:
        """``ft_model``, ``explained`` ``(n, S, 6)`` of a chunk (the online estimator's).

        Without a residual stack ``ft_model`` is the estimator's contact-free prediction (with
        the log's base motion) and ``explained`` zero; with one, the online estimator's
        :meth:`~torchcontact.online.estimator.OnlineEstimator.model_terms`. Frames with a
        non-finite joint state get NaN (they never measure the offset; their status says why).
        ``explained_only``: pass 2, ``ft_model`` is not needed (None).
        """
        S, n = len(self.sensors), d.n
        explained = np.zeros((n, S, 6))
        if self.residual is None and explained_only:
            return None, explained
        ok = np.isfinite(d.q).all(1) & np.isfinite(d.qd).all(1) & np.isfinite(d.qdd).all(1)
        for v in d.base.values():
            ok &= np.isfinite(v).all(1)
        ft_model = np.full((n, S, 6), np.nan)
        rows = np.flatnonzero(ok)
        if not len(rows):
            return ft_model, explained
        model = self.model

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.tensor(np.asarray(x, np.float64)[rows], dtype=model.dtype,
                                device=model.device)  # fmt: skip

        q, qd, qdd = t(d.q), t(d.qd), t(d.qdd)
        if self.residual is None:
            kw = {"base": _base_motion(d.base, t)} if d.base else {}
            none = Contacts((), (), q.new_zeros(len(rows), 0, 3))
            nominal = self.estimator.predict_ft(q, qd, qdd, none, backend="eager", **kw)
            for i, s in enumerate(self.sensors):
                ft_model[rows, i] = nominal[s].double().cpu().numpy()
            return ft_model, explained
        if d.base:
            raise LogError(
                f"{self.source}: --track-bias with --residual on a log with base motion columns"
                " is not supported (the correction stack's model terms assume a fixed base)"
            )
        extra = {k: np.asarray(v)[rows] for k, v in d.extra.items()}
        fm, ex, _ = self._online.model_terms(q, qd, qdd, extra)
        ft_model[rows], explained[rows] = fm, ex
        explained[~ok] = np.nan
        return ft_model, explained

    def bias_start(self, store: Any = None) -> None:
        """Begin the first pass (``store``: the file for the per-frame filter states)."""
        from torchcontact.online.bias import BiasSmoother

        assert self.bias is not None
        period = self.step_ns * 1e-9 if self.step_ns > 0 else 0.01
        opts: dict[str, Any] = {"time_constant": self.bias.time_constant, "period": period}
        if self.bias.ft_std is not None:
            opts["ft_std"] = list(self.bias.ft_std)
        if self.smoother is not None:
            self.smoother.close()
        self.smoother = BiasSmoother(
            len(self.sensors), offset=self._online.state.bias(), store=store, **opts
        )
        self._bias_stats = {"free": np.zeros(len(self.sensors), np.int64)}

    def bias_pass(self, d: Decoded) -> None:
        """First pass over one decoded chunk (in log order, derivatives set)."""
        ft = np.stack([d.ft[s] for s in self.sensors], 1)
        ft_model, _ = self._model_terms(d)
        free = self._contact_free(d)
        z = ft - ft_model
        free &= np.isfinite(z).all(-1)
        self._bias_stats["free"] += free.sum(0)
        self.smoother.forward(z, free, d.t * 1e-9)

    def bias_done(self) -> dict[str, Any]:
        """End the first pass (the backward pass); the summary's ``bias`` entry.

        Returns:
            Per sensor: ``contact_free_frames`` (that measured the offset), ``first``, ``last``,
            ``mean``, ``min``, ``max`` offset ``[N; N m]`` (6 each, over the log's frames),
            ``std_last`` (6), and the settings (``time_constant``, ``method``).
        """
        assert self.bias is not None
        sm = self.smoother
        sm.smooth(self.bias.smoother)
        N, S = sm.frames, len(self.sensors)
        out: dict[str, Any] = {**self.bias.describe(), "sensors": {}}
        if N == 0:
            return out
        total, lo_, hi_ = np.zeros((S, 6)), np.full((S, 6), np.inf), np.full((S, 6), -np.inf)
        for a in range(0, N, 65536):
            x, _ = sm.offsets(a, min(N, a + 65536))
            total += x.sum(0)
            lo_, hi_ = np.minimum(lo_, x.min(0)), np.maximum(hi_, x.max(0))
        first, _ = sm.offsets(0, 1)
        last, scale = sm.offsets(N - 1, N)
        std = sm.std(scale)
        for i, s in enumerate(self.sensors):
            out["sensors"][s] = {
                "contact_free_frames": int(self._bias_stats["free"][i]),
                "first": first[0, i].tolist(),
                "last": last[0, i].tolist(),
                "mean": (total[i] / N).tolist(),
                "min": lo_[i].tolist(),
                "max": hi_[i].tolist(),
                "std_last": std[0, i].tolist(),
            }
        return out

    def _bias_corrected(
        self, d: Decoded, ft: dict[str, np.ndarray]
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """Readings less the tracked offset and the stack's other layers; offsets and stds."""
        off, scale = self.smoother.offsets(d.row, d.row + d.n)
        if off.shape[0] != d.n:
            raise LogError(
                f"{self.source}: the bias pass saw {self.smoother.frames} frames, fewer than"
                f" row {d.row + d.n}; the log changed during the run"
            )
        _, explained = self._model_terms(d, explained_only=True)
        out = {s: ft[s] - off[:, i] - explained[:, i] for i, s in enumerate(self.sensors)}
        return out, off, self.smoother.std(scale)

    # ------------------------------------------------------------------ one chunk
    def process(
        self,
        table: Any,
        qd: np.ndarray | None = None,
        qdd: np.ndarray | None = None,
        previous: Any = None,
    ) -> Any:
        """Estimate every frame of one chunk on its own (no time segments across chunks).

        Args:
            table: pyarrow table or record batch in the log format.
            qd: ``(N, nv)`` velocities in the model's joint order when derived (else read).
            qdd: ``(N, nv)`` accelerations likewise.
            previous: the output of the chunk before (with constraints and warm starts, its last
                frame's estimates start this chunk's first frame), or None.

        Returns:
            A pyarrow table with :meth:`output_schema`.
        """
        d = self.decoder.decode(table)
        if self.derived:
            if qd is None or qdd is None:
                raise LogError(f"{self.source}: qd and qdd are derived: pass them")
            d.qd = qd if "qd" in self.derived else d.qd
            d.qdd = qdd if "qdd" in self.derived else d.qdd
        return self.estimate(d, previous)

    def estimate(self, d: Decoded, previous: Any = None, backend: str | None = None) -> Any:
        """Estimate a decoded chunk and build its output rows (Del Prete et al. 2012, Sec. 2).

        Args:
            d: the chunk (:meth:`ChunkDecoder.decode`, derivatives and segments set).
            previous: the output of the chunk before (warm starts of constrained estimates), or
                None.
            backend: the estimator's backend for this chunk (None: ``"auto"``).

        Returns:
            A pyarrow table with :meth:`output_schema`.

        Raises:
            KernelBuildError: ``backend`` ``"cpu"``/``"cuda"`` and the kernel cannot be built.
        """
        import pyarrow as pa

        model, N = self.model, d.n
        if d.qd is None or d.qdd is None:
            raise LogError(f"{self.source}: qd/qdd of a chunk were not derived")
        ft = dict(d.ft)
        bias = None
        if self.bias is not None:  # pass 2: the tracked offsets replace the stack's offset
            ft, *bias = self._bias_corrected(d, ft)
        elif self.residual is not None:
            ft[self.residual.sensor] = self._corrected(d, ft[self.residual.sensor])
        schema = self.output_schema()
        ctype = schema.field("contacts").type.value_type
        located: dict[str, Any] = {}
        if self.localizer is not None:
            if d.located is None:
                d.located = self.localized(d, ft)
            contacts, records, slot, children, located = d.located
        else:
            if d.contacts is None:
                self.decoder.slots(d, model.dtype, model.device)
            contacts, records, slot = d.contacts, d.records, d.slot
            children = {n: d.fields[n] for n, _ in self.contact_fields}
        assert contacts is not None
        res = self._solve(d, ft, contacts, previous, backend)

        code = res["status"]
        if d.short is not None and d.short.any():
            # derivatives that cannot be derived are NaN by design: Status.NOT_DIFFERENTIABLE
            # (from the decoder's issues) says so instead of bit 2, unless the state is bad
            state_ok = np.isfinite(d.q).all(1)
            for v in d.base.values():
                state_ok &= np.isfinite(v).all(1)
            code = np.where(d.short & state_ok, code & ~2, code)
        self._outside_training(d)
        code = code | d.issues.code
        self._explain(code, d.qd, ft, d.issues)
        # ---- outputs of frames with a non-zero status are NaN (the estimator's own rows are),
        # but for the warning bits (Status.OUTSIDE_TRAINING: the outputs are kept)
        bad = (code & ~WARNINGS) != 0
        any_bad = bool(bad.any())  # most chunks have no bad frame: their arrays as they are
        jt = np.where(bad[:, None], np.nan, res["tau"]) if any_bad else res["tau"]

        # ---- output rows: input contacts with force and moment added, in record order
        M = len(records)
        cf = np.full((M, 3), np.nan)
        cm = np.full((M, 3), np.nan)
        ok_c = (slot >= 0) & ~bad[records.frame] if M else np.zeros(0, bool)
        if ok_c.any():
            cf[ok_c] = res["force"][records.frame[ok_c], slot[ok_c]]
            cm[ok_c] = res["moment"][records.frame[ok_c], slot[ok_c]]
        children["force"], children["moment"] = fixed_list(cf), fixed_list(cm)
        cons = self.constraints
        if cons is not None:  # the cone binds; null where the contact was not estimated
            ca = np.zeros(M, bool)
            ca[ok_c] = res["active"][records.frame[ok_c], slot[ok_c]]
            children["cone_active"] = numpy_to_arrow(ca, mask=~ok_c)
            # the unconstrained estimate outside the cone: on well-posed frames only
            well = ~bad
            for sname in self.sensors:
                well &= res[f"rank.{sname}"] == res[f"unknowns.{sname}"]
            ok_w = ok_c & well[records.frame] if M else ok_c
            oc = np.zeros(M, bool)
            oc[ok_w] = res["outside"][records.frame[ok_w], slot[ok_w]]
            children["outside_cone"] = numpy_to_arrow(oc, mask=~ok_w)
        out: dict[str, Any] = {"t_ns": d.t_ns}
        out["contacts"] = struct_list(children, records.frame, N, ctype)
        out["joint_torques"] = fixed_list(jt)
        for s in self.sensors:
            rank, unknowns = res[f"rank.{s}"], res[f"unknowns.{s}"]
            out[f"rank.{s}"], out[f"unknowns.{s}"] = numpy_to_arrow(rank), numpy_to_arrow(unknowns)
            out[f"nullity.{s}"] = numpy_to_arrow(unknowns - rank)
            residual = res[f"residual.{s}"]
            residual = np.where(bad, np.nan, residual) if any_bad else residual
            out[f"residual.{s}"] = numpy_to_arrow(residual)
            if cons is not None:  # the solver's status; null on frames with a non-zero status
                out[f"converged.{s}"] = numpy_to_arrow(res[f"converged.{s}"], mask=bad)
                out[f"iterations.{s}"] = numpy_to_arrow(res[f"iterations.{s}"], mask=bad)
            if bias is not None:  # the tracked offset and its std, per frame
                i = list(self.sensors).index(s)
                for prefix, v in zip(ESTIMATE_BIAS_COLUMNS, bias, strict=True):
                    out[bias_column(prefix, s)] = fixed_list(v[:, i])
        out["status_code"] = numpy_to_arrow(code)
        out["status"] = status_text(code)
        out["status_detail"] = d.issues.details()
        out.update(located)
        return pa.table(out, schema=schema)

    def localized(
        self, d: Decoded, ft: dict[str, np.ndarray] | None = None
    ) -> tuple[Contacts, ContactRecords, np.ndarray, dict[str, Any], dict[str, Any]]:
        """Localize a chunk's contacts and slot the records with them added.

        Args:
            d: the chunk (derivatives set).
            ft: its readings (default ``d.ft``; with a residual, the corrected ones).

        Returns:
            ``(contacts, records, slot, children, columns)``: the slots; every input record and
            the localized ``force`` records, by frame; each one's slot (-1: not estimated); the
            output struct's child arrays but force and moment (an added record's input fields
            are null); the localization columns.
        """
        import pyarrow as pa

        from torchcontact.localize import localize_chunk

        model, loc, opts = self.model, self.localizer, self.localize
        assert loc is not None and opts is not None
        ft = d.ft if ft is None else ft
        ctype = self.output_schema().field("contacts").type.value_type
        good = d.slot >= 0
        # every skin record (a malformed one in a region also keeps the frame from localizing)
        lc = localize_chunk(
            loc, d.q, d.qd, d.qdd, ft, d.records,
            base=d.base or None, ft_covariance=opts.covariance(loc.sensor_names),
            accept_ambiguous=opts.accept_ambiguous,
            starts=d.starts if opts.temporal else None, temporal=opts.temporal,
        )  # fmt: skip
        records, source = lc.records, lc.source  # by frame; source -1: a localized record
        mine_rows = source < 0
        added = records.select(np.flatnonzero(mine_rows))
        M, A = len(d.records), len(added)
        usable = mine_rows.copy()
        usable[~mine_rows] = good[source[~mine_rows]]
        idx = np.flatnonzero(usable)
        sub = records.select(idx)
        friction = self.decoder.friction
        if friction is None and self.constraints is not None:
            friction = loc.friction  # the cone the localizer accepted the point in
        kw = dict(dtype=model.dtype, device=model.device, friction=friction)
        contacts, slot_good = Contacts.from_records(sub, d.n, self.layout, **kw)
        if self.layout is not None and (slot_good < 0).any():
            # a pair beyond the log's layout (the scan saw other data): this chunk gets its own
            contacts, slot_good = Contacts.from_records(sub, d.n, None, **kw)
        slot = np.full(M + A, -1, np.int64)
        slot[idx] = slot_good
        # each output record's row in [input records, localized records]
        take = numpy_to_arrow(np.where(mine_rows, M + np.cumsum(mine_rows) - 1, source))
        # the output struct's fields: the input's values, the localized records' own
        have = {n for n, _ in self.contact_fields}
        fill = {
            "link": lambda: string_array(added.links.tolist()),
            "kind": lambda: string_array(["force"] * A),
            "position": lambda: fixed_list(added.positions),
            "normal": lambda: fixed_list(
                np.full((A, 3), np.nan) if added.normals is None else added.normals
            ),
        }
        children: dict[str, Any] = {}
        for fld in ctype:
            n = fld.name
            if n in ("force", "moment", "cone_active"):
                continue
            mine = fill[n]().cast(fld.type) if n in fill else pa.nulls(A, fld.type)
            theirs = d.fields[n].cast(fld.type) if n in have else pa.nulls(M, fld.type)
            children[n] = pa.concat_arrays([theirs, mine]).take(take)
        return contacts, records, slot, children, lc.columns

    def _solve(
        self,
        d: Decoded,
        ft: dict[str, np.ndarray],
        contacts: Contacts,
        previous: Any,
        backend: str | None,
    ) -> dict[str, np.ndarray]:
        """Run the estimator on a chunk; its outputs as numpy arrays (:func:`_arrays`)."""
        model, est, cons = self.model, self.estimator, self.constraints

        share = model.dtype == torch.float64 and model.device.type == "cpu"

        def t(x: np.ndarray) -> torch.Tensor:
            if share and x.dtype == np.float64 and x.flags.writeable and x.flags.c_contiguous:
                return torch.from_numpy(x)  # the chunk's own array: no copy
            if share:  # Arrow memory is read-only: numpy copies it (torch's copy of a large
                # array is an OpenMP region, whose idle threads then spin for milliseconds)
                return torch.from_numpy(np.array(x, dtype=np.float64, order="C"))
            return torch.tensor(x, dtype=model.dtype, device=model.device)

        args = {
            "q": t(d.q), "qd": t(d.qd), "qdd": t(d.qdd),  # type: ignore[arg-type]
            "ft": {s: t(v) for s, v in ft.items()},
        }  # fmt: skip
        kw: dict[str, Any] = {"backend": backend}
        if d.base:
            kw["base"] = _base_motion(d.base, t)
        if d.tau is not None:
            kw["tau_measured"] = t(d.tau)
        cov = None if self.noise is None else self.noise.covariances(d.ft_cov)
        if cov is not None:  # the weights; the estimate's covariance is not written
            kw["ft_covariance"] = {s: t(c) for s, c in cov.items()}
            kw["covariance"] = False
        if cons is None:
            return _arrays(est.estimate(**args, contacts=contacts, **kw), self.sensors)
        # the unconstrained estimate (same weighting): is it outside a cone? (friction that
        # contradicts the data shows on the well-posed frames)
        free = est.estimate(**args, contacts=contacts, **kw)
        outside = est.outside_cones(contacts, free.force).cpu().numpy()
        out = self._constrained(d, args, contacts, previous, kw, t)
        out["outside"] = outside
        return out

    def _constrained(
        self,
        d: Decoded,
        args: dict[str, Any],
        contacts: Contacts,
        previous: Any,
        kw: dict[str, Any],
        t: Any,
    ) -> dict[str, np.ndarray]:
        """The constrained estimate of a chunk, warm-started as :class:`LogConstraints` says."""
        est, cons = self.estimator, self.constraints
        assert cons is not None
        kw = {**kw, "constraints": cons.cones}
        if not cons.warm_start:
            return _arrays(est.estimate(**args, contacts=contacts, **kw), self.sensors)
        starts = d.starts if d.starts is not None else np.zeros(d.n, bool)
        before = None
        if previous is not None and d.n and not starts[0]:
            before = _last_estimates(previous, contacts.links, contacts.kinds)
        restart = starts.copy()
        restart[:1] = False
        if not restart.any():  # one time segment: the estimator's own waves
            warm = PreviousFrame(None if before is None else (t(before[0]), t(before[1])),
                                 cons.wave)  # fmt: skip
            return _arrays(
                est.estimate(**args, contacts=contacts, warm_start=warm, **kw), self.sensors
            )
        return self._waves(args, contacts, before, restart, kw, t)

    def _waves(
        self,
        args: dict[str, Any],
        contacts: Contacts,
        before: tuple[np.ndarray, np.ndarray] | None,
        restart: np.ndarray,
        kw: dict[str, Any],
        t: Any,
    ) -> dict[str, np.ndarray]:
        """The waves of :class:`~torchcontact.PreviousFrame`, restarted at segment starts.

        Frames ``j, j + S, j + 2 S, ...`` form wave ``j`` (``S = ceil(n / wave)``); wave ``j``
        starts from wave ``j - 1``'s estimates, wave 0 cold but for frame 0 (``before``); a
        frame that starts a time segment (``restart``) starts cold. Without restarts this is
        exactly the estimator's ``PreviousFrame`` schedule.
        """
        assert self.constraints is not None
        n, K = len(restart), contacts.K
        S = max(1, -(-n // self.constraints.wave))
        out: dict[str, np.ndarray] = {}
        prev: np.ndarray | None = None
        for j in range(min(S, n)):
            rows = np.arange(j, n, S)
            idx = torch.as_tensor(rows, device=self.model.device)
            m = len(rows)
            start = np.full((m, K, 6), np.nan)
            if prev is not None:
                start[:] = prev[:m]
            elif before is not None:
                start[0] = np.concatenate(before, -1)
            start[restart[rows]] = np.nan
            sub = {k: v[idx] for k, v in args.items() if k != "ft"}
            sub["ft"] = {s: v[idx] for s, v in args["ft"].items()}
            skw = dict(kw)
            if "base" in kw:
                skw["base"] = type(kw["base"])(*(x[idx] for x in kw["base"]))
            if "tau_measured" in kw:
                skw["tau_measured"] = kw["tau_measured"][idx]
            if "ft_covariance" in kw:  # per-frame covariances of the log's column
                skw["ft_covariance"] = {
                    s: c[idx] if c.dim() == 3 else c for s, c in kw["ft_covariance"].items()
                }
            r = _arrays(
                self.estimator.estimate(
                    **sub, contacts=_take(contacts, idx),
                    warm_start=(t(start[..., :3]), t(start[..., 3:])), **skw,
                ),
                self.sensors,
            )  # fmt: skip
            for key, v in r.items():
                if key not in out:
                    out[key] = np.empty((n, *v.shape[1:]), v.dtype)
                out[key][rows] = v
            prev = np.concatenate([r["force"], r["moment"]], -1)
        return out

    def _explain(
        self, code: np.ndarray, qd: np.ndarray, ft: dict[str, np.ndarray], issues: FrameIssues
    ) -> None:
        """Details of the estimator's bits 64 (which value is implausible) and 32 (overflow)."""
        flagged = (code & 64) != 0
        if flagged.any():
            if self.velocity_margin is not None:
                limit = np.asarray(
                    self.model.joint_limits.get("velocity", np.full(self.model.nv, np.inf))
                )
                over = (np.abs(qd) > self.velocity_margin * limit) & flagged[:, None]
                for j in np.flatnonzero(over.any(0)):
                    issues.add(
                        over[:, j],
                        0,
                        f"qd of {self.model.joint_names[j]!r} beyond {self.velocity_margin:g} x"
                        f" its URDF velocity limit {limit[j]:g}",
                    )
            for s, lim in self._ft_range.items():
                beyond = (np.abs(ft[s]) > lim).any(1) & flagged
                issues.add(beyond, 0, f"{ft_column(s)} beyond its range {lim.tolist()}")
        issues.add((code & 32) != 0, 0, "non-finite output from finite inputs")

    def _outside_training(self, d: Decoded) -> None:
        """Status bit ``OUTSIDE_TRAINING`` where the residual's learned layer extrapolates.

        Where a feature lies outside its recorded training range (one detail per feature,
        naming the range); nothing for checkpoints without ranges.
        """
        if self.residual is None:
            return
        out = self.residual.outside_range(d.q, d.qd, d.qdd, d.extra)
        if out is None or not out.any():
            return
        names, lo, hi = self.residual.feature_ranges
        for j in np.flatnonzero(out.any(0)):
            d.issues.add(
                out[:, j], int(Status.OUTSIDE_TRAINING),
                f"{names[j]} outside the residual's training range [{lo[j]:.4g}, {hi[j]:.4g}]",
            )  # fmt: skip

    def _corrected(self, d: Decoded, ft: np.ndarray) -> np.ndarray:
        """``ft (N, 6) - correction`` [N; N m]; joints ``(N, nv)`` in the model's order."""
        joints = (torch.as_tensor(v) for v in (d.q, d.qd, d.qdd))
        return self.residual.correct(torch.tensor(ft), *joints, d.extra).cpu().numpy()


def _arrays(res: Any, sensors: Sequence[str]) -> dict[str, np.ndarray]:
    """A :class:`~torchcontact.ContactEstimate` as numpy arrays (flat keys, per-sensor dots)."""

    def np_(x: torch.Tensor) -> np.ndarray:
        return x.detach().cpu().numpy()

    out = {
        "force": np_(res.force),
        "moment": np_(res.moment),
        "tau": np_(res.joint_torques),
        "status": np_(res.status).astype(np.int64),
    }
    for s in sensors:
        out[f"rank.{s}"] = np_(res.rank[s]).astype(np.int64)
        out[f"unknowns.{s}"] = np_(res.unknowns[s]).astype(np.int64)
        out[f"residual.{s}"] = np_(res.residual[s]).astype(np.float64)
        if res.cones is not None:
            out[f"converged.{s}"] = np_(res.cones.converged[s])
            out[f"iterations.{s}"] = np_(res.cones.iterations[s]).astype(np.int64)
    if res.cones is not None:
        out["active"] = np_(res.cones.active)
    return out


def _take(contacts: Contacts, idx: torch.Tensor) -> Contacts:
    """The slots of some frames (every ``(B, K, ...)`` field indexed by ``idx``)."""
    from dataclasses import fields, replace

    sub = {
        f.name: getattr(contacts, f.name)[idx]
        for f in fields(contacts)
        if isinstance(getattr(contacts, f.name), torch.Tensor)
        and getattr(contacts, f.name).dim() >= 2
    }
    return replace(contacts, **sub)


def _last_estimates(
    previous: Any, links: Sequence[str], kinds: Sequence[str]
) -> tuple[np.ndarray, np.ndarray] | None:
    """The last frame's estimates of an output table, matched to slots: ``(force, moment)``.

    A slot takes the estimate of the previous frame's contact with its link and kind and the same
    rank among them (the slot assignment's rule); ``(K, 3)`` each, NaN where none matches (that
    slot starts cold). None without a previous table or contacts.
    """
    if previous is None or previous.num_rows == 0 or not len(links):
        return None
    last = previous.column("contacts")[previous.num_rows - 1].as_py() or []
    seen: dict[tuple[str, str], int] = {}
    found: dict[tuple[str, str, int], tuple] = {}
    for c in last:  # the records of one frame
        key = (c.get("link"), c.get("kind"))
        r = seen.get(key, 0)
        seen[key] = r + 1
        if c.get("force") is not None and c.get("moment") is not None:
            found[(*key, r)] = (c["force"], c["moment"])
    force = np.full((len(links), 3), np.nan)
    moment = np.full((len(links), 3), np.nan)
    rank: dict[tuple[str, str], int] = {}
    for k, key in enumerate(zip(links, kinds, strict=True)):
        r = rank.get(key, 0)
        rank[key] = r + 1
        if (*key, r) in found:
            force[k], moment[k] = found[(*key, r)]
    return force, moment


def _base_motion(base: dict, t: Any) -> Any:
    from torchcontact.dynamics import BaseMotion

    return BaseMotion(t(base["omega"]), t(base["domega"]), t(base["proper_acc"]))


# ---------------------------------------------------------------------- streaming
def decoded_chunks(
    le: LogEstimator,
    tables: Iterator[Any],
    half_window: int,
    first_row: int = 0,
    before: tuple[np.ndarray, np.ndarray] | None = None,
    after: tuple[np.ndarray, np.ndarray] | None = None,
    slots: bool = False,
) -> Iterator[Decoded]:
    """Decode consecutive tables of a log: arrays, time segments, derived ``qd``/``qdd``.

    Args:
        le: the log's estimator.
        tables: consecutive tables (chunks) of the log.
        half_window: ``h`` of the differentiator; ``2 h`` frames of context are carried.
        first_row: the first table's first row in the log.
        before: ``(t_ns, q)`` of the up to ``2 h`` frames preceding the first table (model
            order), or None at the log's start.
        after: ``(t_ns, q)`` of the up to ``2 h`` frames following the last table, or None at
            the log's end.
        slots: place each chunk's contacts in the log's slots here (the local engine's reader
            thread: off the estimating thread, which is the longest on many cores), from the
            first chunk decoded once the layout is set (``decoder.layout_pending``); else
            :meth:`LogEstimator.estimate` does.

    Yields:
        :class:`~torchcontact.logs.decode.Decoded`, ready for :meth:`LogEstimator.estimate`.
    """
    dec = le.decoder
    stream = DerivativeStream(half_window, le.step_ns, before, le.causal) if le.derived else None
    c = stream.context[1] if stream is not None else 2 * half_window  # frames needed ahead
    # the last two stamps before a chunk (time segments of a log without derived qd/qdd)
    last_t = np.zeros(0, np.int64) if before is None else np.asarray(before[0][-2:], np.int64)
    ahead: deque[Decoded] = deque()
    row = first_row
    for tab in tables:
        ahead.append(dec.decode(tab, row))
        row += tab.num_rows
        while ahead and sum(x.n for x in list(ahead)[1:]) >= c and (len(ahead) > 1 or not c):
            yield _finish_chunk(le, ahead, stream, after, c, last_t, slots)
            last_t = np.r_[last_t, ahead.popleft().t][-2:]
    while ahead:
        yield _finish_chunk(le, ahead, stream, after, c, last_t, slots)
        last_t = np.r_[last_t, ahead.popleft().t][-2:]


def _finish_chunk(
    le: LogEstimator,
    ahead: deque,
    stream: DerivativeStream | None,
    after: tuple[np.ndarray, np.ndarray] | None,
    c: int,
    last_t: np.ndarray,
    slots: bool = False,
) -> Decoded:
    """Derivatives (with the frames ahead as context) and segment starts of ``ahead[0]``."""
    d = ahead[0]
    if stream is not None:
        nxt = list(ahead)[1:]
        t_n = np.concatenate([x.t for x in nxt]) if nxt else np.zeros(0, np.int64)
        q_n = np.concatenate([x.q for x in nxt]) if nxt else np.zeros((0, d.q.shape[1]))
        if len(t_n) < c and after is not None:
            t_n, q_n = np.concatenate([t_n, after[0]]), np.concatenate([q_n, after[1]])
        qd, qdd, starts, length = stream.derive(d.t, d.q, t_n[:c], q_n[:c])
        le.decoder.derive(d, qd, qdd, starts, length)
    else:
        d.starts = time_segments(np.r_[last_t, d.t], le.step_ns)[len(last_t) :]
    if le.localizer is not None and le.residual is None and LOCALIZE_ON_READER:
        d.located = le.localized(d)  # overlaps the estimate of the chunk before
    elif slots and le.localizer is None and not le.decoder.layout_pending:
        le.decoder.slots(d, le.model.dtype, le.model.device)
    return d


def estimate_stream(
    le: LogEstimator,
    decoded: Iterator[Decoded],
    previous: Any = None,
    backend: str = "auto",
) -> Iterator[Any]:
    """Output tables of decoded chunks, in order (the calling thread runs the estimator).

    Each chunk gets the output of the one before (``previous`` for the first: e.g. the last part
    of an interrupted run), whose last frame warm-starts a constrained estimate. With ``backend``
    ``"cpu"``/``"cuda"`` the first chunk waits for its kernel; if it cannot be built the run goes
    on eagerly (the kernel layer warns once).
    """
    for d in decoded:
        try:
            previous = le.estimate(d, previous, backend)
        except KernelBuildError:
            backend = "eager"
            previous = le.estimate(d, previous, backend)
        if backend in ("cpu", "cuda"):
            backend = "auto"  # built or loaded: auto finds it ready from now on
        yield previous
