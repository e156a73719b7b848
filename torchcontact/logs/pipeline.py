"""Estimate the contacts of every frame of a Parquet log: per-chunk estimate, local engine.

The data's way through a run:

1. **Decoding** (:mod:`torchcontact.logs.decode`): the schema is checked, one pass over the cheap
   columns of the whole file fixes **one slot layout for the log** (the most records of each
   ``(link, kind)`` pair in one frame; slots a frame does not use are inactive) and the log's time
   segments; each chunk's Arrow columns become numpy arrays with per-frame problems.
2. **The per-chunk estimate** (:class:`LogEstimator`): every chunk runs the same compiled
   program (one layout, one kernel), then its output rows are built with vectorised numpy and
   pyarrow only.
3. **The run** (:mod:`torchcontact.logs.run`, shared with the Ray engine): an OS lock on the
   output, the journal for ``--resume``, an ordered writer thread, the summary.

The local engine (:func:`estimate_file`) overlaps the three on threads joined by bounded queues:
a reader thread reads and decodes chunks (pyarrow's reads release the GIL), the calling thread
estimates them (the kernels release the GIL), the writer thread journals them and writes the
Parquet output. Order, resume and checksums are those of a sequential run.

Kernels: a log with at least :data:`WAIT_FOR_KERNEL_FRAMES` frames to estimate waits for its
kernel to be built (or loaded from the cache) before its first chunk; a shorter one runs eagerly
while the kernel builds in the background and switches to it at the first chunk after the build
(``backend="auto"`` of :mod:`torchcontact.kernels`). A failed build falls back to eager torch.

Status: every output row has ``status_code`` (the bits of :data:`torchcontact.STATUS`), ``status``
(its text) and ``status_detail`` (what the pipeline found: a malformed vector, an unknown link, a
joint beyond its velocity limit, a frame too short to differentiate, ...). Frames with a non-zero
code have NaN outputs; the rest of the log is processed.

Friction cones (:class:`LogConstraints`, ``estimate --constraints``): every pushing contact's force
is kept inside the friction cone of its ``normal`` (contact field) and friction coefficient
(``friction`` or ``cone_angle`` field, else the run's default); the output adds per sensor
``converged.<sensor>`` and ``iterations.<sensor>`` and per contact ``cone_active``. Frames are
warm-started from their predecessor's estimate (:class:`~torchcontact.PreviousFrame`), across
chunks too (a chunk's first frame starts from the previous chunk's last estimates, matched by
link, kind and order), but never across a time-segment boundary (a repeated, backward or gapped
``t_ns``): a segment's first frame starts cold. Non-convergence is not a status bit (status bits
mean NaN outputs; a frame that did not converge keeps its last interior-point iterate, inside
the cones): it is ``converged.<sensor> = false``.
"""

from __future__ import annotations

import glob
import json
import os
import time
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.constrained import FrictionCones, PreviousFrame
from torchcontact.contacts import Contacts, SlotLayout
from torchcontact.errors import InputError, KernelBuildError, LogError
from torchcontact.estimation import ContactEstimator
from torchcontact.logs.decode import (
    ChunkDecoder,
    Decoded,
    FrameIssues,
    LogScan,
    log_columns,
    scan_log,
    status_text,
)
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW, DerivativeStream, time_segments
from torchcontact.logs.format import (
    META_DERIVED,
    META_RESIDUAL,
    META_SENSORS,
    META_URDF_SHA256,
    META_VERSION,
    check_outputs,
    fixed_list,
    ft_column,
    iter_chunks,
    joint_permutation,
    open_log,
    output_schema,
    read_journal,
    struct_list,
)
from torchcontact.logs.run import Done, Run, background, side_paths
from torchcontact.model import RobotModel

__all__ = [
    "DEFAULT_VELOCITY_MARGIN",
    "WAIT_FOR_KERNEL_FRAMES",
    "LogConstraints",
    "LogError",
    "LogEstimator",
    "estimate_file",
    "estimate_files",
    "expand_inputs",
    "load_robot",
]

#: Default ``velocity_margin``: a joint faster than twice its URDF velocity limit is implausible.
DEFAULT_VELOCITY_MARGIN = 2.0

#: A run with at least this many frames to estimate waits for its kernel rather than running
#: eagerly while it builds. Measured (docs/pipeline.md): building a whole-robot estimator kernel
#: costs about as much CPU as estimating ~200,000 frames eagerly, for the 7-joint tcarm (2.7 s vs
#: 78 k frames/s) and the 32-joint iCub (7.5 s vs 28 k frames/s) alike; past that the kernel
#: (30-40x faster) wins, and on a small machine the eager frames and the compiler share cores.
WAIT_FOR_KERNEL_FRAMES = 200_000

# The plausibility bit (64) and the non-finite-output bit (32) are set by the estimator
# (ContactEstimator(..., velocity_margin=..., ft_range=...)), one meaning in Python and logs.


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cuda`` must be available.

    Raises:
        InputError: an unknown device, or ``cuda`` without a usable CUDA device.
    """
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError(f"--device {device}: expected auto, cpu or cuda")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(
            f"--device {device}: CUDA is not available (torch {torch.__version__}"
            f"{' has no CUDA support' if torch.version.cuda is None else ' sees no GPU'});"
            " use --device cpu or auto"
        )
    return device


def load_robot(
    robot: str | Path | RobotModel,
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
) -> RobotModel:
    """The robot model from a URDF path (or a model, moved to ``device`` and ``dtype``).

    Raises:
        InputError: no such URDF file, or an unusable device.
        URDFError: a URDF torchcontact cannot model (the message names the element).
    """
    device = resolve_device(device)
    if isinstance(robot, RobotModel):
        if robot.dtype == dtype and str(robot.device) == device:
            return robot
        return robot.to(device, dtype)
    if not Path(robot).is_file():
        raise InputError(f"--robot {robot}: no such URDF file")
    return RobotModel.from_urdf(robot, dtype=dtype, device=device)


def _check_positive(**values: int) -> None:
    for name, value in values.items():
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")


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


# ---------------------------------------------------------------------- the per-chunk estimate
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
            self.model, self.perm, self.sensors, self.contact_fields, self.derived,
            self.estimator.region, self.layout, None if cons is None else cons.friction,
            cons is not None, self.residual_columns(), self.source,
        )  # fmt: skip
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

        derived = {
            "columns": list(self.derived),
            "method": f"Savitzky-Golay order 2 over t_ns, {2 * DEFAULT_HALF_WINDOW + 1} frames"
            if self.derived
            else "",
        }
        meta = {
            META_URDF_SHA256: self.model.urdf_sha256,
            META_VERSION: __version__,
            META_SENSORS: json.dumps(list(self.sensors)),
            META_DERIVED: json.dumps(derived),
        }
        if self.residual is not None:
            meta[META_RESIDUAL] = json.dumps(
                {
                    "checkpoint": self.residual.source,
                    "weights_sha256": self.residual.meta.get("weights_sha256"),
                    "sensor": self.residual.sensor,
                    "kind": "+".join(self.residual.layers),
                }
            )
        self._schema = output_schema(
            self.model.joint_names,
            self.sensors,
            self.contact_fields,
            meta,
            constraints=self.constraints is not None,
        )
        return self._schema

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
        if d.contacts is None:
            self.decoder.slots(d, model.dtype, model.device)
        contacts, records, slot = d.contacts, d.records, d.slot
        assert contacts is not None
        if d.qd is None or d.qdd is None:
            raise LogError(f"{self.source}: qd/qdd of a chunk were not derived")
        ft = dict(d.ft)
        if self.residual is not None:
            ft[self.residual.sensor] = self._corrected(d, ft[self.residual.sensor])
        res = self._solve(d, ft, contacts, previous, backend)

        code = res["status"]
        if d.short is not None and d.short.any():
            # derivatives that cannot be derived are NaN by design: bit 256 (from the decoder's
            # issues) says so instead of bit 2, unless the state itself is bad
            state_ok = np.isfinite(d.q).all(1)
            for v in d.base.values():
                state_ok &= np.isfinite(v).all(1)
            code = np.where(d.short & state_ok, code & ~2, code)
        code = code | d.issues.code
        self._explain(code, d.qd, ft, d.issues)
        # ---- outputs of frames with a non-zero status are NaN (the estimator's own rows are)
        bad = code != 0
        jt = np.where(bad[:, None], np.nan, res["tau"])

        # ---- output rows: input contacts with force and moment added, in record order
        M = len(records)
        cf = np.full((M, 3), np.nan)
        cm = np.full((M, 3), np.nan)
        ok_c = (slot >= 0) & ~bad[records.frame] if M else np.zeros(0, bool)
        if ok_c.any():
            cf[ok_c] = res["force"][records.frame[ok_c], slot[ok_c]]
            cm[ok_c] = res["moment"][records.frame[ok_c], slot[ok_c]]
        schema = self.output_schema()
        ctype = schema.field("contacts").type.value_type
        children = {n: d.fields[n] for n, _ in self.contact_fields}
        children["force"], children["moment"] = fixed_list(cf), fixed_list(cm)
        cons = self.constraints
        if cons is not None:  # the cone binds; null where the contact was not estimated
            ca = np.zeros(M, bool)
            ca[ok_c] = res["active"][records.frame[ok_c], slot[ok_c]]
            children["cone_active"] = pa.array(ca, mask=~ok_c)
        out: dict[str, Any] = {"t_ns": d.t_ns}
        out["contacts"] = struct_list(children, records.frame, N, ctype)
        out["joint_torques"] = fixed_list(jt)
        for s in self.sensors:
            rank, unknowns = res[f"rank.{s}"], res[f"unknowns.{s}"]
            out[f"rank.{s}"], out[f"unknowns.{s}"] = pa.array(rank), pa.array(unknowns)
            out[f"nullity.{s}"] = pa.array(unknowns - rank)
            out[f"residual.{s}"] = pa.array(np.where(bad, np.nan, res[f"residual.{s}"]))
            if cons is not None:  # the solver's status; null on frames with a non-zero status
                out[f"converged.{s}"] = pa.array(res[f"converged.{s}"], mask=bad)
                out[f"iterations.{s}"] = pa.array(res[f"iterations.{s}"], mask=bad)
        out["status_code"] = pa.array(code)
        out["status"] = status_text(code)
        out["status_detail"] = d.issues.details()
        return pa.table(out, schema=schema)

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
            return torch.tensor(x, dtype=model.dtype, device=model.device)  # Arrow memory is r/o

        args = {
            "q": t(d.q), "qd": t(d.qd), "qdd": t(d.qdd),  # type: ignore[arg-type]
            "ft": {s: t(v) for s, v in ft.items()},
        }  # fmt: skip
        kw: dict[str, Any] = {"backend": backend}
        if d.base:
            kw["base"] = _base_motion(d.base, t)
        if d.tau is not None:
            kw["tau_measured"] = t(d.tau)
        if cons is None:
            return _arrays(est.estimate(**args, contacts=contacts, **kw), self.sensors)
        kw["constraints"] = cons.cones
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
) -> Iterator[Decoded]:
    """Decode consecutive tables of a log: arrays, time segments, derived ``qd``/``qdd``, slots.

    Args:
        le: the log's estimator.
        tables: consecutive tables (chunks) of the log.
        half_window: ``h`` of the differentiator; ``2 h`` frames of context are carried.
        first_row: the first table's first row in the log.
        before: ``(t_ns, q)`` of the up to ``2 h`` frames preceding the first table (model
            order), or None at the log's start.
        after: ``(t_ns, q)`` of the up to ``2 h`` frames following the last table, or None at
            the log's end.

    Yields:
        :class:`~torchcontact.logs.decode.Decoded`, ready for :meth:`LogEstimator.estimate`.
    """
    dec = le.decoder
    c = 2 * half_window
    stream = DerivativeStream(half_window, le.step_ns, before) if le.derived else None
    # the last two stamps before a chunk (time segments of a log without derived qd/qdd)
    last_t = np.zeros(0, np.int64) if before is None else np.asarray(before[0][-2:], np.int64)
    ahead: deque[Decoded] = deque()
    row = first_row
    for tab in tables:
        ahead.append(dec.decode(tab, row))
        row += tab.num_rows
        while len(ahead) > 1 and sum(x.n for x in list(ahead)[1:]) >= c:
            yield _finish_chunk(le, ahead, stream, after, c, last_t)
            last_t = np.r_[last_t, ahead.popleft().t][-2:]
    while ahead:
        yield _finish_chunk(le, ahead, stream, after, c, last_t)
        last_t = np.r_[last_t, ahead.popleft().t][-2:]


def _finish_chunk(
    le: LogEstimator,
    ahead: deque,
    stream: DerivativeStream | None,
    after: tuple[np.ndarray, np.ndarray] | None,
    c: int,
    last_t: np.ndarray,
) -> Decoded:
    """Derivatives (with the frames ahead as context), segment starts and slots of ``ahead[0]``."""
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


def kernel_backend(frames: int, device: str) -> str:
    """The estimator backend of a run with ``frames`` frames to estimate (see the module doc)."""
    kind = torch.device(device).type
    return kind if frames >= WAIT_FOR_KERNEL_FRAMES and kind in ("cpu", "cuda") else "auto"


def read_chunks(
    pf: Any, columns: Sequence[str], batch_size: int, source: str, first_row: int = 0
) -> Iterator[Any]:
    """Tables of ``batch_size`` rows from row ``first_row`` on (only the row groups needed)."""
    import pyarrow as pa

    if first_row == 0:
        yield from iter_chunks(pf, columns, batch_size, source)
        return
    sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.num_row_groups)]
    bounds = np.cumsum([0, *sizes])
    g0 = int(np.searchsorted(bounds, first_row, side="right") - 1)
    skip = first_row - int(bounds[g0])
    buf: list[Any] = []
    have = 0
    for tab in iter_chunks(pf, columns, batch_size, source, range(g0, len(sizes))):
        if skip:
            cut = min(skip, tab.num_rows)
            tab, skip = tab.slice(cut), skip - cut
        buf.append(tab)
        have += tab.num_rows
        while have >= batch_size:
            t = pa.concat_tables(buf).combine_chunks()
            yield t.slice(0, batch_size)
            rest = t.slice(batch_size)
            buf, have = [rest], rest.num_rows
    if have:
        yield pa.concat_tables(buf).combine_chunks()


# ---------------------------------------------------------------------- preparing a log
def load_residual(checkpoint: str | Path, model: RobotModel) -> Any:
    """Load a residual checkpoint for ``model`` (its robot hash must match).

    Args:
        checkpoint: directory written by ``torchcontact train fit`` or
            :meth:`~torchcontact.residual.ResidualCorrection.save`.
        model: the robot the log is estimated with.

    Returns:
        A :class:`~torchcontact.residual.ResidualCorrection`.

    Raises:
        LogError: unreadable, tampered or foreign checkpoint, or one trained for another robot.
    """
    from torchcontact.residual import CheckpointError, ResidualCorrection

    try:
        return ResidualCorrection.load(checkpoint, model)
    except CheckpointError as exc:
        raise LogError(f"--residual: {exc}") from None


def prepare(
    path: str | Path,
    model: RobotModel,
    sensors: Sequence[str] | None = None,
    residual: Any = None,
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: LogConstraints | None = None,
) -> tuple[Any, LogEstimator, list[str], LogScan]:
    """Open a log, scan it once and build its :class:`LogEstimator` with the log's slot layout.

    A log without a ``contacts`` column is estimated as contact-free, with one warning; a log
    whose ``qd``/``qdd`` are derived and whose ``t_ns`` splits into several time segments gets
    one warning that counts them.

    Args:
        path: the log.
        model: the robot.
        sensors: sensors to use (default: those with a column).
        residual: a loaded :class:`~torchcontact.residual.ResidualCorrection` or None.
        velocity_margin: see :class:`LogEstimator`.
        ft_range: see :class:`LogEstimator`.
        constraints: see :class:`LogEstimator`.

    Returns:
        ``(ParquetFile, LogEstimator, columns to read, LogScan)``.

    Raises:
        LogError: not Parquet, no joint names, mismatched joints, no sensor column, no ``q``, a
            bad ``t_ns``, a residual whose sensor is not in use or whose feature columns the
            log lacks.
        InputError: ``constraints`` on a log whose contacts have no ``normal`` field, or no
            ``friction``/``cone_angle`` field and no default friction.
    """
    import warnings

    src = str(path)
    pf = open_log(path)
    extra = [] if residual is None else residual.extra_columns
    cols = log_columns(pf.schema_arrow, model, src, sensors, constraints, extra)
    scan = scan_log(pf, src, bool(cols.contact_fields))
    le = LogEstimator(
        model,
        cols.joint_names,
        cols.sensors,
        cols.contact_fields,
        src,
        cols.derived,
        residual,
        velocity_margin=velocity_margin,
        ft_range=ft_range,
        constraints=constraints,
        step_ns=scan.step_ns,
    )
    le.layout = le.decoder.layout = scan.layout(le.decoder.usable)
    le.decoder.whole_log_segment = scan.segments == 1
    if cols.derived and scan.segments > 1:
        warnings.warn(f"{src}: {scan.describe_time()}", UserWarning, stacklevel=3)
    return pf, le, cols.columns, scan


def run_ident(path: str | Path, model: RobotModel, le: LogEstimator, **options: Any) -> dict:
    """What a run is: input file identity, robot, sensors and options (a resume must match)."""
    st = os.stat(path)
    ident = {
        "input": str(Path(path).resolve()),
        "input_size": st.st_size,
        "input_mtime_ns": st.st_mtime_ns,
        "urdf_sha256": model.urdf_sha256,
        "sensors": list(le.sensors),
        "velocity_margin": le.velocity_margin,
        "ft_range": {s: v.tolist() for s, v in le._ft_range.items()},
        **options,
    }
    if le.residual is not None:
        ident["residual_weights_sha256"] = le.residual.meta.get("weights_sha256")
    if le.constraints is not None:  # a resume must estimate with the same cones
        ident["constraints"] = repr(le.constraints)
    return ident


def log_summary(le: LogEstimator, scan: LogScan) -> dict:
    """Summary keys that describe the log itself (the same for both engines)."""
    out: dict[str, Any] = {"sensors": list(le.sensors), "derived": list(le.derived)}
    out["slots"] = len(le.layout.links) if le.layout is not None else None
    out["time_segments"] = scan.segments
    if le.derived:
        out["not_differentiable"] = scan.short_frames
    return out


# ---------------------------------------------------------------------- the local engine
def estimate_file(
    path: str | Path,
    robot: str | Path | RobotModel,
    out: str | Path,
    *,
    sensors: Sequence[str] | None = None,
    batch_size: int = 8192,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    resume: bool = False,
    progress: bool | None = None,
    half_window: int = DEFAULT_HALF_WINDOW,
    residual: Any = None,
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: LogConstraints | None = None,
) -> dict:
    """Estimate every frame of a log and write the output log (local engine).

    Args:
        path: input Parquet log (format of :mod:`torchcontact.logs.format`).
        robot: URDF path or a :class:`RobotModel`.
        out: output Parquet file; ``out.partial/``, ``out.progress.json`` and ``out.lock`` exist
            while running.
        sensors: sensors to use (default: those with an ``ft.<sensor>`` column).
        batch_size: frames per chunk (memory is flat in the log length).
        device: ``auto``, ``cpu`` or ``cuda``.
        dtype: computation dtype (float64 recommended).
        resume: finish an interrupted run from its parts (same chunking as recorded).
        progress: show a progress bar (default: when stderr is a terminal).
        half_window: ``h`` of the Savitzky-Golay differentiator when ``qd``/``qdd`` are derived.
        residual: residual checkpoint directory (or a loaded
            :class:`~torchcontact.residual.ResidualCorrection`): its correction [N; N m] is
            subtracted from its sensor's reading before estimation and the output metadata
            ``torchcontact.residual`` names the checkpoint and its weights' sha256. A recurrent
            (GRU) residual sees the frames in time order across chunks; it cannot ``resume``.
        velocity_margin: frames with ``|qd|`` beyond this times the URDF velocity limit get
            status bit 64 (None: no check).
        ft_range: ``{sensor: (6,) or scalar}`` [N; N m]; readings beyond it get status bit 64.
        constraints: friction-cone constrained estimation (:class:`LogConstraints`), or None.

    Returns:
        A summary dict: input, output, frames, processed_now, ok_now, bad_now, seconds,
        frames_per_s, sensors, derived, slots (of the log's layout), time_segments (and with
        derived ``qd``/``qdd`` not_differentiable), resumed_chunks, chunks, engine, bad_frames
        (frames of the output with a non-zero status), bad_details (the most frequent details
        of those, with counts); with constraints also ``cones``: ``converged`` share,
        ``iterations_mean`` and ``iterations_max`` over the frames estimated now.

    Raises:
        InputError: ``batch_size`` or ``half_window`` < 1, an unusable device, an output that is
            or contains an input, a missing URDF.
        OutputBusyError: another live process is writing ``out`` (nothing was written).
        LogError: the input cannot be processed at all (message names the file), or is
            corrupted (the chunks before the damage stay in ``out.partial`` for a resume); an
            existing ``out.partial`` without ``resume``; a ``resume`` whose input or options
            changed; a residual checkpoint for another robot, an unused sensor or with a column
            the log lacks; ``resume`` with a recurrent residual; an I/O error writing (the
            message names the path and what is kept for ``resume``).
        URDFError: an unusable URDF.
    """
    import sys

    t0 = time.perf_counter()
    _check_positive(batch_size=batch_size, half_window=half_window)
    out = Path(out)
    robot_file = None if isinstance(robot, RobotModel) else robot
    check_outputs([out, *side_paths(out)], [path, robot_file, _path_or_none(residual)])
    model = load_robot(robot, dtype, device)
    if residual is not None and not hasattr(residual, "correct"):
        residual = load_residual(residual, model)
    if residual is not None:
        residual.reset()  # a GRU's state starts afresh with each log
    recurrent = residual is not None and residual.recurrent
    if recurrent and resume:
        raise LogError(
            f"{path}: --resume (resume=True) is not supported with a recurrent (GRU) residual:"
            " its state depends on every earlier frame; rerun from the start"
        )
    pf, le, columns, scan = prepare(
        path, model, sensors, residual, velocity_margin, ft_range, constraints
    )
    total = pf.metadata.num_rows
    show = sys.stderr.isatty() if progress is None else progress
    with Run(out, path) as run:
        # an interrupted run keeps its chunk size: read it before the ident is compared
        prev = run.previous() if resume else None
        if prev is not None:
            try:
                batch_size = int(prev["batch_size"])
            except (KeyError, TypeError, ValueError):
                pass
            if batch_size < 1:
                raise LogError(
                    f"{run.sidecar}: batch_size {batch_size} is invalid; delete it and rerun"
                )
        ident = run_ident(path, model, le, engine="local", dtype=str(dtype),
                          half_window=half_window, batch_size=batch_size)  # fmt: skip
        units = [(a, min(a + batch_size, total)) for a in range(0, total, batch_size)]
        run.start(ident, units, resume, recurrent)
        done = len(run.done)
        if run.done != set(range(done)):
            raise LogError(
                f"{out}: parts of {run.partial} are not consecutive; delete it and rerun"
            )
        first = done * batch_size
        before = None
        if le.derived and first:  # the frames before the first chunk: derivative context
            ctx = read_chunks(pf, ["t_ns", "q"], 2 * half_window, str(path),
                              max(0, first - 2 * half_window))  # fmt: skip
            from torchcontact.logs.decode import stamps_and_positions

            before = stamps_and_positions(next(ctx), le.perm, str(path))
        elif first:  # the stamps before the first chunk: time segments
            before = (_stamps_at(pf, first - 2, first, str(path)), np.zeros((2, model.nv)))
        previous = read_journal(run.part(done - 1)) if done and constraints else None
        backend = kernel_backend(total - first, str(model.device))

        def produce() -> Iterator[Done]:
            tables = read_chunks(pf, columns, batch_size, str(path), first)
            decoded = decoded_chunks(le, tables, half_window, first, before)
            with background(decoded, name="reader") as chunks:
                for k, tab in enumerate(estimate_stream(le, iter(chunks), previous, backend)):
                    yield Done(done + k, tab.num_rows, tab)

        return run.execute(
            produce(),
            le.output_schema(),
            progress=show,
            cone_sensors=list(le.sensors) if constraints is not None else [],
            t0=t0,
            **log_summary(le, scan),
            engine="local",
        )


def _stamps_at(pf: Any, lo: int, hi: int, source: str) -> np.ndarray:
    """``t_ns`` of rows ``[max(lo, 0), hi)`` (the stamps before a resumed run's first chunk)."""
    from torchcontact.logs.decode import _stamps

    lo = max(lo, 0)
    tab = next(read_chunks(pf, ["t_ns"], hi - lo, source, lo))
    return _stamps(tab.column("t_ns"), source, lo)


def _path_or_none(x: Any) -> str | Path | None:
    return x if isinstance(x, (str, Path)) else None


def expand_inputs(inputs: Sequence[str | Path]) -> list[Path]:
    """Files, folders (their ``*.parquet``) and globs -> a sorted list of files.

    Raises:
        LogError: an input that matches nothing.
    """
    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(p.glob("*.parquet"))
        elif p.exists():
            found = [p]
        else:
            found = sorted(Path(m) for m in glob.glob(str(item)))
        if not found:
            raise LogError(f"{item}: no such file, folder or glob match")
        files += found
    return files


def output_paths(inputs: Sequence[Path], out: str | Path) -> list[Path]:
    """Output file per input: ``out`` itself for one file, ``out/<name>`` for several."""
    out = Path(out)
    if len(inputs) == 1 and not out.is_dir():
        return [out]
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: several inputs need a folder, and {out} is a file")
    names = [p.name for p in inputs]
    if len(set(names)) != len(names):
        raise LogError(f"inputs share file names {names}; give them distinct names")
    return [out / n for n in names]


def estimate_files(
    inputs: Sequence[str | Path], robot: str | Path, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file` over files, folders or globs (``out`` a folder for several).

    Every output is checked against every input before the first file is processed.
    """
    files = expand_inputs(inputs)
    outs = output_paths(files, out)
    for o in outs:
        check_outputs([o, *side_paths(o)], [*files, robot, kwargs.get("residual")])
    model = load_robot(robot, kwargs.get("dtype", torch.float64), kwargs.pop("device", "cpu"))
    if kwargs.get("residual") is not None:  # load and verify once for all files
        kwargs["residual"] = load_residual(kwargs["residual"], model)
    return [
        estimate_file(f, model, o, device=str(model.device), **kwargs)
        for f, o in zip(files, outs, strict=True)
    ]
