"""Estimate the contacts of every frame of a Parquet log: the entry points and the local engine.

The data's way through a run:

1. **Decoding** (:mod:`torchcontact.logs.decode`): the schema is checked, one pass over the cheap
   columns of the whole file fixes **one slot layout for the log** (the most records of each
   ``(link, kind)`` pair in one frame; slots a frame does not use are inactive) and the log's time
   segments; each chunk's Arrow columns become numpy arrays with per-frame problems.
2. **The per-chunk estimate** (:mod:`torchcontact.logs.chunks`, :class:`LogEstimator`): every
   chunk runs the same compiled program (one layout, one kernel), then its output rows are built
   with vectorised numpy and pyarrow only.
3. **The run** (:mod:`torchcontact.logs.run`, shared with the Ray engine): an OS lock on the
   output, the journal for ``--resume``, an ordered writer thread, cleanup, the summary.

:func:`prepare` does step 1 for a log and builds its :class:`LogEstimator`. The local engine
(:func:`estimate_file`) overlaps the three steps on threads joined by bounded queues: a reader
thread reads and decodes chunks and slots their contacts (pyarrow's reads release the GIL), the
calling thread estimates them (the kernels release the GIL), two encoder threads encode their
output tables as Parquet row groups and the writer thread appends those to the output in order,
recording each in the journal. Order, resume and checksums are those of a sequential run.

Kernels: a log's one kernel is built in the background while the first chunks run eagerly, and the
run switches to it at the first chunk after the build (``backend="auto"`` of
:mod:`torchcontact.kernels`); a kernel in the cache is loaded at once. Measured on first runs
(empty cache), this beats waiting for the build at every log length tried (docs/pipeline.md):
with one kernel per log, the eager frames only fill the one build's time. Ray tasks wait for the
build instead (:func:`kernel_backend`): several worker processes share a machine, and one of them
builds while the others wait for it. A failed build falls back to eager torch.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact import kernels
from torchcontact.errors import InputError, LogError
from torchcontact.logs.chunks import (
    DEFAULT_VELOCITY_MARGIN,
    LogBias,
    LogConstraints,
    LogEstimator,
    LogLocalize,
    decoded_chunks,
    estimate_stream,
    localized_layout,
)
from torchcontact.logs.decode import (
    LogScan,
    log_columns,
    scan_rest,
    scan_step,
    scan_threads,
    stamps_and_positions,
)
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
from torchcontact.logs.format import (
    check_outputs,
    expand_inputs,
    iter_chunks,
    open_log,
    output_paths,
)
from torchcontact.logs.run import Done, Run, background, check_positive, side_paths
from torchcontact.model import RobotModel

__all__ = [
    "DEFAULT_VELOCITY_MARGIN",
    "WAIT_FOR_KERNEL_FRAMES",
    "LogBias",
    "LogConstraints",
    "LogError",
    "LogEstimator",
    "LogLocalize",
    "estimate_file",
    "estimate_files",
    "expand_inputs",
    "load_robot",
    "open_prepared",
    "prepare",
]

#: Frames to estimate from which the local engine waits for its kernel to be built rather than
#: estimating while it builds; None: never. Measured on a 2-core machine (first runs of the iCub
#: benchmark log, docs/pipeline.md): estimating eagerly while the kernel builds was faster than
#: waiting at 50 k, 200 k and 1 M frames (15 vs 48 s, 49 vs 62 s, 81 vs 92 s). Since the tape VM
#: (``auto`` runs the program on it, at ~8x eager's speed, and its kernel builds after the run),
#: there is less still to gain from waiting for a build (docs/kernel_cache.md,
#: benchmarks/vm_cold.py).
WAIT_FOR_KERNEL_FRAMES: int | None = None

#: Frames from which Ray tasks wait for the kernel: below, estimating them eagerly costs less
#: than building it (building the whole-robot kernel costs as much CPU as ~200,000 eager frames,
#: for the 7-joint tcarm and the 32-joint iCub alike).
SHARED_WAIT_FRAMES = 200_000


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
    """The robot model of a robot argument (or a model, moved to ``device`` and ``dtype``).

    ``robot`` is ``tcarm``, ``icub``, a URDF path or a :class:`~torchcontact.robots.RobotSpec`
    (with declared F/T sensors): :func:`torchcontact.robots.load_robot_model`.

    Raises:
        InputError: no such URDF file, not a URDF, or an unusable device.
        URDFError: a URDF torchcontact cannot model (the message names the element).
    """
    from torchcontact.robots import load_robot_model

    device = resolve_device(device)
    if isinstance(robot, RobotModel):
        if robot.dtype == dtype and str(robot.device) == device:
            return robot
        return robot.to(device, dtype)
    return load_robot_model(robot, dtype=dtype, device=device)


def kernel_backend(frames: int, device: str, shared: bool = False) -> str:
    """The estimator backend of a run: ``"auto"``, or ``"cpu"``/``"cuda"`` to wait for the kernel.

    Args:
        frames: frames the run will estimate.
        device: the computation's device.
        shared: several processes of the run share a machine (Ray tasks): from
            :data:`SHARED_WAIT_FRAMES` on, wait, so that one of them builds the kernel while the
            others wait for it (a build lock per kernel) instead of each building it.
    """
    kind = torch.device(device).type
    if kind not in ("cpu", "cuda"):
        return "auto"
    limit = SHARED_WAIT_FRAMES if shared else WAIT_FOR_KERNEL_FRAMES
    return kind if limit is not None and frames >= limit else "auto"


#: Rows of the chunks the contact-free noise estimate reads from a log's start (fixed: a resume
#: with another ``batch_size`` finds the same noise).
NOISE_BATCH = 8192
#: Of those chunks, how many the run keeps to use again instead of reading them twice (memory:
#: a few chunks, once, at the start).
NOISE_KEEP = 8


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
    # the rows skipped are read in one table (not batch_size rows at a time: a resume's context
    # of 2 frames would be thousands of tables); each table read is combined once
    step = max(batch_size, skip)
    for tab in iter_chunks(pf, columns, step, source, range(g0, len(sizes))):
        if skip:
            cut = min(skip, tab.num_rows)
            tab, skip = tab.slice(cut), skip - cut
        buf.append(tab)
        have += tab.num_rows
        if have < batch_size:
            continue
        t = buf[0] if len(buf) == 1 else pa.concat_tables(buf).combine_chunks()
        at = 0
        while have - at >= batch_size:
            yield t.slice(at, batch_size)
            at += batch_size
        buf, have = [t.slice(at)], have - at
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
    path: str | Path, model: RobotModel, *args: Any, **kwargs: Any
) -> tuple[Any, LogEstimator, list[str], LogScan]:
    """Open a log, scan it and build its :class:`LogEstimator` with the log's slot layout.

    :func:`open_prepared` (the same arguments; the scan on the calling thread) and
    :meth:`Prepared.finish` at once.

    Returns:
        ``(ParquetFile, LogEstimator, columns to read, LogScan)``.

    Raises:
        LogError, InputError: as :func:`open_prepared` and :meth:`Prepared.finish`.
    """
    p = open_prepared(path, model, *args, **kwargs)
    return p.pf, p.le, p.columns, p.finish()


@dataclass
class Prepared:
    """A log opened for a run whose scan's second pass may still be running on a thread.

    The estimator is usable for decoding at once (its time step is known); its slot layout is
    set by :meth:`finish`, which waits for the scan. Until then, chunks are decoded without
    slots (``decoder.layout_pending``): :func:`with_head` or :meth:`LogEstimator.estimate` slots
    them later.

    Attributes:
        pf: the opened log.
        le: its estimator.
        columns: the columns to read.
    """

    pf: Any
    le: LogEstimator
    columns: list[str]
    _scan: Any

    def finish(self) -> LogScan:
        """Wait for the scan and set the slot layout; the scan (its errors are raised here)."""
        if not isinstance(self._scan, LogScan):
            self._scan = self._scan.result()
            _use_scan(self.le, self._scan)
        return self._scan

    def close(self) -> None:
        """Wait for the scan's thread to end, without raising its error (:meth:`finish` does)."""
        if not isinstance(self._scan, LogScan):
            self._scan.exception()


def _use_scan(le: LogEstimator, scan: LogScan) -> None:
    """Set what the decoding takes from the scan: the slot layout, whether one segment."""
    le.layout = le.decoder.layout = scan.layout(le.decoder.usable)
    if le.localizer is not None:
        le.layout = le.decoder.layout = localized_layout(le.layout, le.localizer.links)
    le.decoder.whole_log_segment = scan.segments == 1
    le.decoder.layout_pending = False


def open_prepared(
    path: str | Path,
    model: RobotModel,
    sensors: Sequence[str] | None = None,
    residual: Any = None,
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: LogConstraints | None = None,
    causal: tuple[int, int] | None = None,
    bias: LogBias | None = None,
    localize: LogLocalize | None = None,
    overlap: bool = False,
) -> Prepared:
    """Open a log, find its time step and build its :class:`LogEstimator`; scan the rest.

    The scan's first pass (``t_ns``: the median step, every stamp checked) runs here. Its second
    pass (time segments, the contacts' names: the slot layout) runs on a thread with
    ``overlap``, beside what the caller does next (the noise estimate's first chunks), else here
    too. Overlap applies to logs with ``qd``/``qdd`` and without localization: a derived log's
    decoding needs its time segments, a localizing one its layout.

    A log without a ``contacts`` column is estimated as contact-free, with one warning (unless
    its contacts are localized); a log whose ``qd``/``qdd`` are derived and whose ``t_ns``
    splits into several time segments gets one warning that counts them.

    Args:
        path: the log.
        model: the robot.
        sensors: sensors to use (default: those with a column).
        residual: a loaded :class:`~torchcontact.residual.ResidualCorrection` or None.
        velocity_margin: see :class:`LogEstimator`.
        ft_range: see :class:`LogEstimator`.
        constraints: see :class:`LogEstimator`.
        causal: see :class:`LogEstimator` (``--derivatives causal``).
        bias: see :class:`LogEstimator` (``--track-bias``).
        localize: see :class:`LogEstimator` (the layout gets a ``force`` slot per candidate).
        overlap: the scan's second pass on a thread (see above).

    Raises:
        LogError: not Parquet, no joint names, mismatched joints, no sensor column, no ``q``, a
            bad ``t_ns``, a residual whose sensor is not in use or whose feature columns the
            log lacks. Unreadable contact names are raised by :meth:`Prepared.finish`.
        InputError: ``constraints`` on a log whose contacts have no ``normal`` field, or no
            ``friction``/``cone_angle`` field and no default friction.
    """
    import warnings

    src = str(path)
    pf = open_log(path)
    rows = pf.metadata.num_rows
    if model.device.type == "cpu" and rows >= kernels.AUTO_BUILD_MIN_FRAMES:
        if kernel_backend(rows, "cpu") == "auto":  # the VM runs what is not built yet: on a
            kernels.prepare_vm(model.dtype)  # machine without it, it builds while we scan
    extra = [] if residual is None else residual.extra_columns
    cols = log_columns(pf.schema_arrow, model, src, sensors, constraints, extra, bool(localize))
    threads = scan_threads(rows)  # ranges of the log at once on a many-core machine
    step = scan_step(pf, src, threads)
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
        step_ns=step,
        causal=causal,
        bias=bias,
        localize=localize,
    )
    contacts = bool(cols.contact_fields)
    if overlap and not cols.derived and le.localizer is None:
        from concurrent.futures import Future

        scan = Future()
        twin = open_log(path, pf.metadata)  # a reader of its own for the thread

        def run() -> None:
            try:
                kernels.code_digest()  # the first kernel lookup's, off the noise estimate's way
                scan.set_result(scan_rest(twin, src, contacts, step, threads))
            except BaseException as exc:  # raised by finish()
                scan.set_exception(exc)

        le.decoder.layout_pending = True
        threading.Thread(target=run, name="torchcontact-scan", daemon=True).start()
        return Prepared(pf, le, cols.columns, scan)
    done = scan_rest(pf, src, contacts, step, threads)
    _use_scan(le, done)
    if cols.derived and done.segments > 1:
        warnings.warn(f"{src}: {done.describe_time()}", UserWarning, stacklevel=3)
    return Prepared(pf, le, cols.columns, done)


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
    if le.noise is not None:  # ... and the same noise
        ident["noise"] = le.noise.summary()
    if le.localize is not None:
        ident["localize"] = le.localize.options()
    return ident


def log_noise(
    pf: Any,
    le: LogEstimator,
    columns: list[str],
    half_window: int,
    ft_noise: Mapping[str, Any] | None,
    unweighted: bool,
    source: str,
) -> NoiseHead:
    """Resolve the run's F/T noise (:mod:`torchcontact.logs.noise`) and set it on ``le``.

    Each sensor's noise comes from ``ft_noise``, the log's ``ft_cov.<sensor>`` column, its
    profile in the log's metadata, or its contact-free frames (read from the log's start in
    chunks of :data:`NOISE_BATCH` rows, so that a resume with another ``batch_size`` finds the
    same noise); ``columns`` gains the covariance columns to read.

    Returns:
        The first chunks that the contact-free estimate read and decoded (at most
        :data:`NOISE_KEEP`, consecutive from row 0, :data:`NOISE_BATCH` rows each but the log's
        last), so that the run neither reads nor decodes them again (:func:`with_head`); empty
        when it read none, or when the run decodes otherwise (``ft_cov`` columns to read, a
        localizing estimate).

    Raises:
        InputError: an ``ft_noise`` sensor the robot lacks or the run does not use, a bad
            standard deviation or profile, ``ft_noise`` with ``unweighted``.
    """
    from torchcontact.logs.format import ft_cov_column
    from torchcontact.logs.noise import contact_free_noise, parse_ft_noise, resolve

    given = ft_noise if isinstance(ft_noise, Mapping) else parse_ft_noise(ft_noise)

    kept: list[Any] = []
    # the decoding goes on where the estimate stopped when it kept every chunk it decoded
    tables = read_chunks(pf, columns, NOISE_BATCH, source)
    stream = decoded_chunks(le, tables, half_window, slots=True)  # slotted: the run's too
    state = {"whole": True}

    def chunks() -> Iterator[Any]:
        try:
            for d in stream:
                if len(kept) < NOISE_KEEP:
                    kept.append(d)  # decoded as the run decodes it (same rows, same context)
                else:
                    state["whole"] = False
                yield d
        except LogError:  # damaged data: the noise is estimated from the frames before it, and
            state["whole"] = False  # the run meets the damage after estimating those (kept
            return  # for --resume)

    def estimate(sensors: list[str]) -> dict:
        return contact_free_noise(le, chunks(), sensors)

    schema = pf.schema_arrow
    noise = resolve(le.sensors, list(le.model.ft_sensors), given, schema.names, schema.metadata,
                    estimate, unweighted=unweighted, torques="tau_measured" in columns,
                    source=source)  # fmt: skip
    le.set_noise(noise)
    cov = [ft_cov_column(s) for s in noise.column_sensors()]
    columns += cov
    if cov or le.localizer is not None:
        # chunks decoded without the covariance columns the run reads, or localized before
        # the noise was known
        kept.clear()
    return NoiseHead(kept, stream if kept and state["whole"] else None)


def recorded_noise(le: LogEstimator, previous: Mapping[str, Any] | None) -> None:
    """A resume weighs the solve by its interrupted run's noise when only rounding differs.

    The contact-free estimate's forward model runs compiled when its kernel is in the cache and
    on the tape VM or eagerly otherwise (its kernel builds after the run), which differ in the
    last bits: a run resumed after the kernel was built takes the interrupted run's values
    (every source and reason the same, the standard deviations within 1e-9 relative), so that
    its chunks are estimated with the same weights as those kept.

    Args:
        le: the run's estimator, its noise resolved (:func:`log_noise`).
        previous: the interrupted run's record (``Run.previous``), or None.
    """
    from torchcontact.noise import FTNoise, SensorNoise

    rec = previous.get("noise") if isinstance(previous, Mapping) else None
    if le.noise is None or not isinstance(rec, dict):
        return
    now = le.noise.summary()
    if rec == now or {k: v for k, v in rec.items() if k != "sensors"} != {
        k: v for k, v in now.items() if k != "sensors"
    }:
        return
    a, b = rec.get("sensors"), now["sensors"]
    if not isinstance(a, dict) or a.keys() != b.keys():
        return
    for s, n in b.items():
        r = a[s]
        if not isinstance(r, dict) or r.get("source") != n["source"]:
            return
        if (r.get("std") is None) != (n["std"] is None):
            return
        if n["std"] is not None and not (
            len(r["std"]) == len(n["std"]) and np.allclose(r["std"], n["std"], rtol=1e-9, atol=0)
        ):
            return
    sensors = {s: SensorNoise(r["source"], None if r["std"] is None else tuple(r["std"]))
               for s, r in a.items()}  # fmt: skip
    le.set_noise(FTNoise(sensors, rec.get("reason")))


@dataclass
class NoiseHead:
    """The chunks :func:`log_noise` decoded, for the run to take (:func:`with_head`).

    Attributes:
        chunks: decoded chunks from row 0, :data:`NOISE_BATCH` rows each (at most
            :data:`NOISE_KEEP`).
        rest: the decoding that gave them, to go on with (the chunks after), or None when it
            cannot (it decoded more chunks than it kept, or met damaged data).
    """

    chunks: list[Any]
    rest: Iterator[Any] | None = None


def with_head(
    head: NoiseHead,
    pf: Any,
    le: LogEstimator,
    columns: Sequence[str],
    batch_size: int,
    half_window: int,
    first: int,
) -> Iterator[Any]:
    """The decoded chunks of a run from row ``first``, taking those :func:`log_noise` decoded.

    ``head`` (emptied as it goes, so that memory stays flat) is used when it starts at
    ``first`` with chunks of ``batch_size`` rows: the chunks that decoding would give. The rest
    comes from the decoding that gave them, or else is read and decoded from the row after
    them, with the frames before as context (as a resumed run starts).
    """
    kept = head.chunks
    if first != 0 or batch_size != NOISE_BATCH:
        kept.clear()
    rest = head.rest if kept else None
    rows = first + sum(d.n for d in kept)
    while kept:
        d = kept.pop(0)
        if d.contacts is None and le.localizer is None:  # decoded before the layout was known
            le.decoder.slots(d, le.model.dtype, le.model.device)
        yield d
    if rest is not None:
        yield from rest
        return
    before = _context(pf, le, rows, half_window, le.source)
    if rows < pf.metadata.num_rows:
        tables = read_chunks(pf, columns, batch_size, le.source, rows)
        yield from decoded_chunks(le, tables, half_window, rows, before, slots=True)


def log_summary(le: LogEstimator, scan: LogScan) -> dict:
    """Summary keys that describe the log itself (the same for both engines)."""
    out: dict[str, Any] = {"sensors": list(le.sensors), "derived": list(le.derived)}
    if le.noise is not None:
        out["noise"] = le.noise.summary()
    out["slots"] = len(le.layout.links) if le.layout is not None else None
    out["time_segments"] = scan.segments
    if le.derived and le.causal is None:  # causal: the first frames of segments, per chunk
        out["not_differentiable"] = scan.short_frames
    if le.localizer is not None:
        out["localize_links"] = list(le.localizer.links)
    return out


def run_localize(
    localize: LogLocalize | Mapping[str, Any] | None, model: RobotModel, robot: Any
) -> LogLocalize | None:
    """A run's :class:`LogLocalize`: as given, or loaded from ``robot``'s URDF with options.

    Args:
        localize: a :class:`LogLocalize`, its options (``links`` and the keyword options of
            :class:`LogLocalize`), or None.
        model: the robot.
        robot: its URDF path or :class:`~torchcontact.robots.RobotSpec` (options only).

    Raises:
        InputError: options with a robot given as a model (pass a :class:`LogLocalize`), or as
            :meth:`LogLocalize.load`.
        MissingExtraError: the ``meshes`` extra is missing.
    """
    if localize is None or isinstance(localize, LogLocalize):
        return localize
    if isinstance(robot, RobotModel):
        raise InputError("localize options need the robot's URDF path: pass a LogLocalize")
    opts = dict(localize)
    return LogLocalize.load(model, robot, opts.pop("links", "subtree"), **opts)


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
    derivatives: str = "centred",
    derivative_window: int = 15,
    derivative_order: int = 3,
    track_bias: LogBias | bool | None = None,
    ft_noise: Mapping[str, Any] | Sequence[str] | None = None,
    unweighted: bool = False,
    localize: LogLocalize | Mapping[str, Any] | None = None,
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
        derivatives: ``"centred"`` (the Savitzky-Golay of :mod:`torchcontact.logs.derive`,
            ``half_window``) or ``"causal"`` (the live loop's one-sided filter,
            :mod:`torchcontact.online.derivatives`, ``derivative_window`` frames, polynomial
            ``derivative_order``) for derived ``qd``/``qdd``; the output metadata says which,
            with the causal filter's delay.
        derivative_window: frames of the causal fit.
        derivative_order: its polynomial degree (>= 2).
        track_bias: track the F/T offsets over the log from the model (:class:`LogBias`, True:
            its defaults): two passes, the output gets ``bias.<s>``/``bias_std.<s>`` columns
            and the summary ``bias``.
        ft_noise: ``{sensor: (6,) standard deviations [N; N m] or a profile name}`` or the
            ``--ft-noise`` strings (:func:`torchcontact.logs.noise.parse_ft_noise`): the noise
            weighing the solve; sensors not given take theirs from the log
            (:mod:`torchcontact.logs.noise`).
        unweighted: the paper's unweighted ``pinv(A) b`` (no ``ft_noise`` then).
        localize: contact localization from the F/T wrench and the collision meshes in frames
            without skin contact (:class:`LogLocalize`, or its options with ``robot`` a URDF
            path), or None.

    Returns:
        A summary dict: input, output, frames, processed_now, ok_now, bad_now, seconds,
        frames_per_s, sensors, derived, slots (of the log's layout), time_segments (and with
        derived ``qd``/``qdd`` not_differentiable), resumed_chunks, chunks, engine, bad_frames
        (frames of the output with a non-zero status), bad_details (the most frequent details
        of those, with counts), noise (:meth:`~torchcontact.logs.noise.FTNoise.summary`: which
        source weighed each sensor, or why the solve is unweighted); with constraints also
        ``cones`` (:func:`~torchcontact.logs.run.unusable`'s tally: solves, frames converged
        and not, frames with an active cone, well-posed frames whose unconstrained estimate
        lies outside a cone) over the frames estimated now; with ``track_bias`` also ``bias``
        (:meth:`LogEstimator.bias_done`); with ``localize`` also ``localize_links`` (the
        candidates) and ``localize``: per localizing sensor, ``localized`` (frames whose
        localized contact was estimated) and ``status`` (frames with each
        :class:`~torchcontact.status.LocalizeStatus` bit, by name) over the output's frames.

    Raises:
        InputError: ``batch_size`` or ``half_window`` < 1, an unknown ``derivatives``, a bad
            causal window or order, an unusable device, an output that is
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
    check_positive(batch_size=batch_size, half_window=half_window)
    causal = derivative_options(derivatives, derivative_window, derivative_order)
    bias = LogBias() if track_bias is True else (track_bias or None)
    out = Path(out)
    robot_file = None if isinstance(robot, RobotModel) else robot
    check_outputs([out, *side_paths(out)], [path, robot_file, _path_or_none(residual)])
    with Run(out, path) as run:  # the lock first: a second run stops before any work
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
        localize = run_localize(localize, model, robot)
        # the scan's second pass (the slot layout) runs beside the noise estimate's chunks
        prep = open_prepared(path, model, sensors, residual, velocity_margin, ft_range,
                             constraints, causal, bias, localize, overlap=True)  # fmt: skip
        pf, le, columns = prep.pf, prep.le, prep.columns
        try:
            head = log_noise(pf, le, columns, half_window, ft_noise, unweighted, str(path))
        finally:
            prep.close()
        scan = prep.finish()
        total = pf.metadata.num_rows
        show = sys.stderr.isatty() if progress is None else progress
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
        recorded_noise(le, prev)
        ident = run_ident(path, model, le, engine="local", dtype=str(dtype),
                          half_window=half_window, batch_size=batch_size)  # fmt: skip
        # always present (None when off): a resume with or without them must match
        ident["derivatives"] = None if causal is None else ["causal", *causal]
        ident["track_bias"] = None if bias is None else bias.describe()
        units = [(a, min(a + batch_size, total)) for a in range(0, total, batch_size)]
        run.start(ident, units, resume, recurrent)
        extra: dict[str, Any] = {}
        if bias is not None:  # pass 1: the whole log, whatever a resume skips
            extra["bias"] = bias_pass(pf, le, columns, batch_size, half_window, run.partial)
        done = len(run.done)
        if run.done != set(range(done)):
            raise LogError(
                f"{out}: parts of {run.partial} are not consecutive; delete it and rerun"
            )
        first = done * batch_size
        if derivatives == "causal":
            extra["derivatives"] = le.derivative_method()
        previous = run.read_part(done - 1) if done and constraints else None
        backend = kernel_backend(total - first, str(model.device))

        def produce() -> Iterator[Done]:
            decoded = with_head(head, pf, le, columns, batch_size, half_window, first)
            with background(decoded, name="reader") as chunks:
                for k, tab in enumerate(estimate_stream(le, iter(chunks), previous, backend)):
                    yield Done(done + k, tab.num_rows, tab)

        try:
            return run.execute(
                produce(),
                le.output_schema(),
                progress=show,
                cone_sensors=list(le.sensors) if constraints is not None else [],
                localize=localize_tally(le),
                t0=t0,
                **log_summary(le, scan),
                **extra,
                engine="local",
            )
        finally:
            if le.smoother is not None:
                le.smoother.close()


def derivative_options(method: str, window: int, order: int) -> tuple[int, int] | None:
    """``--derivatives``: None for ``centred``, ``(window, order)`` for ``causal``.

    Raises:
        InputError: another method, a window or order the causal fit cannot use.
    """
    if method == "centred":
        return None
    if method != "causal":
        raise InputError(f"--derivatives {method}: expected centred or causal")
    from torchcontact.online.derivatives import _check

    _check(window, order)
    return int(window), int(order)


def bias_pass(
    pf: Any,
    le: LogEstimator,
    columns: Sequence[str],
    batch_size: int,
    half_window: int,
    folder: Path,
) -> dict:
    """Pass 1 of ``--track-bias``: the tracker's filter and smoother over the whole log.

    The per-frame filter states go to ``folder/bias.states`` (``64 S`` bytes a frame; the run's
    ``OUT.partial/``, removed with it), so memory stays one chunk whatever the log's length.

    Returns:
        The summary's ``bias`` entry (:meth:`LogEstimator.bias_done`).
    """
    le.bias_start(Path(folder) / "bias.states")
    tables = read_chunks(pf, columns, batch_size, le.source, 0)
    for d in decoded_chunks(le, tables, half_window, 0, None):
        le.bias_pass(d)
    return le.bias_done()


def localize_tally(le: LogEstimator) -> tuple[list[str], bool] | None:
    """``(localizing sensors, accept_ambiguous)`` for the run's summary, None without."""
    if le.localizer is None or le.localize is None:
        return None
    return list(le.localizer.sensor_names), le.localize.accept_ambiguous


def _context(
    pf: Any, le: LogEstimator, first: int, half_window: int, source: str
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(t_ns, q)`` of the frames before row ``first`` that a resumed run needs (None: none).

    Derived ``qd``/``qdd`` need ``2 h`` frames (model joint order), time segments two stamps.
    """
    if not first:
        return None
    need = (le.causal[0] - 1 if le.causal else 2 * half_window) if le.derived else 2
    lo = max(0, first - need)
    tab = next(read_chunks(pf, ["t_ns", "q"], first - lo, source, lo))
    return stamps_and_positions(tab, le.perm, len(le.input_joint_names), source, lo)


def _path_or_none(x: Any) -> str | Path | None:
    return x if isinstance(x, (str, Path)) else None


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
    if kwargs.get("localize") is not None:  # the meshes loaded once for all files
        kwargs["localize"] = loc = run_localize(kwargs["localize"], model, robot)
        sensors = kwargs.get("sensors") or list(model.ft_sensors)
        loc.localizer(model, sensors)  # bad links are refused before any file is read
    return [
        estimate_file(f, model, o, device=str(model.device), **kwargs)
        for f, o in zip(files, outs, strict=True)
    ]
