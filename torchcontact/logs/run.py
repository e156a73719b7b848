"""The run of one estimate job, shared by the local and the Ray engine.

An engine only computes output tables; :class:`Run` does everything around them, the same way for
both:

1. **One writer**: an OS lock on ``OUT.lock`` (:class:`~torchcontact._lock.OutputLock`) is held
   from before anything is written until the end. A second run on the same output, with or
   without ``--resume``, stops at once naming the first (pid, host, start time); ``--resume`` and
   the "interrupted run" message apply only when no live process holds the lock.
2. **Output and journal in one**: units are encoded as Parquet row groups and appended to
   ``OUT.tmp`` in order (:class:`~torchcontact.logs.format.PartsWriter`), on a writer thread fed
   through a bounded queue (so writing overlaps the engine's work and memory stays flat); the
   footer is joined from the units' own at the end and ``OUT.tmp`` renamed to ``OUT``. Once a
   unit's bytes are in ``OUT.tmp``, ``OUT.partial/part-<k>.index`` records where (a small entry:
   offsets and the unit's footer, temporary name and atomic rename), and ``OUT.progress.json``
   records what the run is (:meth:`Run.start`). ``--resume`` keeps the recorded units of an
   interrupted run with the same inputs and options: ``OUT.tmp`` is cut after the last one and
   the run appends after it. The data are written once, never a second copy.
   A unit estimated out of order (a Ray worker's) waits in ``OUT.partial/part-<k>.parquet``
   (already encoded: its bytes are appended as they are) until its turn; journals of earlier
   versions (every unit an Arrow IPC ``.arrow`` part) are read and encoded then.
3. **Failures leave the ground clean**: a run that fails before recording any unit removes
   ``OUT.partial``, ``OUT.progress.json`` and ``OUT.tmp``; otherwise the message says how many
   units are kept for ``--resume``. An I/O error (a full disk, a read-only folder) names the path.
4. **Summary**: the same dict from both engines, with the frames whose status is not 0 and
   their most frequent details (:func:`unusable`, the CLI's ``--max-bad``).
"""

from __future__ import annotations

import errno
import json
import os
import queue
import re
import shutil
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact._lock import OutputLock, lock_path
from torchcontact.errors import InputError, LogError, TorchContactError
from torchcontact.logs.format import (
    PartIndex,
    PartsWriter,
    arrow_to_numpy,
    encode_part,
    encoded_part_table,
    numpy_to_arrow,
    read_encoded_part,
    read_journal,
    read_part,
    read_part_index,
    write_part_index,
)
from torchcontact.status import WARNINGS, Status

OUTSIDE = int(Status.OUTSIDE_TRAINING)

__all__ = ["Done", "Run", "background", "side_paths", "unusable"]

#: Items waiting between two pipeline stages (chunks in flight stay bounded: memory is flat).
QUEUE_DEPTH = 2
#: Threads encoding output chunks as Parquet at once (pyarrow releases the GIL): on many cores
#: the encoding is off the writer thread, which only appends the encoded bytes in order.
ENCODERS = 2
#: Ray workers' parts appended at once, when that many are ready in a row (each is read into
#: memory first: about 20 MB for a unit of 65,536 iCub frames).
PARTS_AT_ONCE = 8
NOT_CONVERGED = int(Status.NOT_CONVERGED)
#: Share of the well-posed frames whose unconstrained estimate lies outside a friction cone above
#: which ``estimate --constraints`` warns that the friction contradicts the data (with the right
#: friction only noise takes a force near a cone's rim outside it).
OUTSIDE_CONE_WARN = 0.10


def check_positive(**values: int) -> None:
    """Refuse a count option below 1 or not an integer (``batch_size=0``: ``--batch-size``)."""
    for name, value in values.items():
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")


def side_paths(out: Path) -> list[Path]:
    """Every path an estimate writes besides ``out``: journal, sidecar, temporary file, lock."""
    out = Path(out)
    return [out.with_name(out.name + s) for s in (".partial", ".progress.json", ".tmp")] + [
        lock_path(out)
    ]


@dataclass
class Done:
    """A unit the engine finished.

    Attributes:
        unit: its index.
        rows: its frames.
        table: its output table, journalled and written by the run; None when the engine has
            journalled it itself (a Ray worker).
    """

    unit: int
    rows: int
    table: Any = None


# ---------------------------------------------------------------------- threads
class background:  # noqa: N801 - used like a function: for item in background(it)
    """Iterate ``items`` on a thread, ``QUEUE_DEPTH`` items ahead (order kept).

    Exceptions of the thread are raised by the consumer; :meth:`close` (or leaving a ``with``
    block) stops the thread and waits for it.

    Example:
        >>> with background(iter(range(5))) as it:
        ...     list(it)
        [0, 1, 2, 3, 4]
    """

    _END = object()

    def __init__(self, items: Iterator[Any], depth: int = QUEUE_DEPTH, name: str = "reader"):
        self._items = items
        self._q: queue.Queue = queue.Queue(depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"torchcontact-{name}", daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            for item in self._items:
                if not self._put((True, item)):
                    break
        except BaseException as exc:  # handed to the consumer
            self._put((False, exc))
            return
        finally:
            close = getattr(self._items, "close", None)
            if close is not None:
                close()
        self._put((True, self._END))

    def __iter__(self) -> Iterator[Any]:
        while True:
            ok, item = self._q.get()
            if not ok:
                raise item
            if item is self._END:
                return
            yield item

    def close(self) -> None:
        """Stop the thread (the item it is working on is finished first)."""
        self._stop.set()
        while self._thread.is_alive():
            try:
                self._q.get(timeout=0.05)
            except queue.Empty:
                pass
        self._thread.join()

    def __enter__(self) -> background:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------- I/O errors
def io_error(path: Path | str, exc: BaseException) -> LogError:
    """A LogError naming ``path`` for an OS or Arrow I/O error (full disk, read-only, ...)."""
    code = getattr(exc, "errno", None)
    if code is None:
        m = re.search(r"errno (\d+)", str(exc), re.IGNORECASE)
        code = int(m.group(1)) if m else None
    if code is not None:
        what = os.strerror(code).lower()
        hint = {
            errno.ENOSPC: "free some space",
            errno.EDQUOT: "free some space",
            errno.EROFS: "write to another folder",
            errno.EACCES: "check the folder's permissions",
            errno.EPERM: "check the folder's permissions",
        }.get(code)
        return LogError(f"{path}: {what} (errno {code})" + (f"; {hint}" if hint else ""))
    return LogError(f"{path}: {exc}")


def _io(path: Path, fn: Callable[[], Any]) -> Any:
    import pyarrow as pa

    try:
        return fn()
    except (OSError, pa.ArrowException) as exc:
        raise io_error(path, exc) from None


def _atomic_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")

    def write() -> None:
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1)
            f.flush()
        os.replace(tmp, path)

    _io(tmp, write)


# ---------------------------------------------------------------------- tallies
def _part_table(
    path: Path, tally: _Tally | None = None, names: Sequence[str] = ()
) -> tuple[Any, Any]:
    """A worker's Parquet part: ``(its EncodedPart, its table)``.

    The table has every column, or with ``tally`` only the columns of ``names`` (the output's)
    that it reads.

    The status texts are read only for a part with a frame whose code needs them: decoding them
    cost 1.5 us per frame in the Ray driver, more than the rest of its work.
    """
    part, data = read_encoded_part(path)
    if tally is None:
        return part, encoded_part_table(data, path)
    tab = encoded_part_table(data, path, tally.columns(names))
    if tally.needs_texts(tab):
        texts = [n for n in ("status", "status_detail") if n in names]
        tab = encoded_part_table(data, path, [*tab.column_names, *texts])
    return part, tab


@dataclass
class _Tally:
    """Frames, statuses and cone solves of the tables written to the output."""

    cone_sensors: list[str]
    localize: tuple[list[str], bool] | None = None
    rows: int = 0
    bad: int = 0
    ok_now: int = 0
    bad_now: int = 0
    details: dict[str, int] = field(default_factory=dict)
    solved: int = 0
    converged: int = 0
    it_sum: int = 0
    it_max: int = 0
    outside: int = 0
    outside_details: dict[str, int] = field(default_factory=dict)
    cone_frames: int = 0
    converged_frames: int = 0
    not_converged_frames: int = 0
    active_frames: int = 0
    well_posed_frames: int = 0
    outside_frames: int = 0
    located: dict[str, int] = field(default_factory=dict)
    located_bits: dict[str, dict[str, int]] = field(default_factory=dict)

    def columns(self, names: list[str]) -> list[str]:
        """The columns of an output with ``names`` that :meth:`add` reads, but the status texts.

        The texts (``status``, ``status_detail``) matter only for a part with a frame whose code
        needs them (:meth:`needs_texts`).
        """
        want = {"status_code"}
        for s in self.cone_sensors:
            want |= {f"iterations.{s}", f"converged.{s}", "contacts"}
        for s in self.localize[0] if self.localize is not None else []:
            want |= {f"localize_status_code.{s}", f"localize_link.{s}"}
        return [n for n in names if n in want]

    @staticmethod
    def needs_texts(table: Any) -> bool:
        """Whether :meth:`add` reads the status texts of ``table`` (a bad or outside frame)."""
        code = arrow_to_numpy(table.column("status_code"), fill=0)
        return bool(((code & (~WARNINGS | OUTSIDE)) != 0).any())

    def add(self, table: Any, now: bool) -> None:
        import pyarrow.compute as pc

        if self.localize is not None:
            self._add_localized(table)

        code = arrow_to_numpy(table.column("status_code"), fill=0)
        # frames with NaN outputs: a status bit other than the warnings (outputs kept)
        bad = (code & ~WARNINGS) != 0
        outside = (code & OUTSIDE) != 0
        n_out = int(outside.sum())
        self.outside += n_out
        if n_out:  # which features, counted (the details of those frames)
            why = pc.filter(table.column("status_detail"), numpy_to_arrow(outside)).to_pylist()
            for text in why:
                for part in (text or "").split("; "):
                    if "training range" in part:
                        self.outside_details[part] = self.outside_details.get(part, 0) + 1
        n_bad = int(bad.sum())
        self.rows += table.num_rows
        self.bad += n_bad
        if now:
            self.ok_now += table.num_rows - n_bad
            self.bad_now += n_bad
        if n_bad:
            why = pc.coalesce(table.column("status_detail"), table.column("status"))
            counts = pc.value_counts(pc.filter(why, numpy_to_arrow(bad))).to_pylist()
            for c in counts:
                self.details[c["values"]] = self.details.get(c["values"], 0) + c["counts"]
        if now:
            for s in self.cone_sensors:
                its = arrow_to_numpy(table.column(f"iterations.{s}"), np.float64)  # null: NaN
                conv = arrow_to_numpy(table.column(f"converged.{s}"), bool, fill=False)
                ran = ~np.isnan(its) & (its > 0)
                self.solved += int(ran.sum())
                self.converged += int(conv[ran].sum())
                if ran.any():
                    self.it_sum += int(its[ran].sum())
                    self.it_max = max(self.it_max, int(its[ran].max()))
            if self.cone_sensors:
                self._cone_frames(table)

    def _cone_frames(self, table: Any) -> None:
        """Per-frame cone counts: solved, converged or not, cone active, outside the cone."""
        import pyarrow.compute as pc

        n = table.num_rows
        ran = np.zeros(n, bool)
        for s in self.cone_sensors:
            its = arrow_to_numpy(table.column(f"iterations.{s}"), np.float64)
            ran |= ~np.isnan(its) & (its > 0)
        code = arrow_to_numpy(table.column("status_code"), fill=0)
        failed = (code & NOT_CONVERGED) != 0
        self.cone_frames += int(ran.sum())
        self.not_converged_frames += int(failed.sum())
        self.converged_frames += int((ran & ~failed).sum())
        contacts = table.column("contacts")
        frame = arrow_to_numpy(pc.list_parent_indices(contacts))
        flat = pc.list_flatten(contacts)
        for name, attr in (("cone_active", "active_frames"), ("outside_cone", "outside_frames")):
            v = arrow_to_numpy(pc.struct_field(flat, name), bool, fill=False)
            hit = np.zeros(n, bool)
            hit[frame[v]] = True
            setattr(self, attr, getattr(self, attr) + int(hit.sum()))
        # well posed: the outside_cone test ran (non-null) on a frame's contacts
        tested = arrow_to_numpy(pc.is_valid(pc.struct_field(flat, "outside_cone")))
        well = np.zeros(n, bool)
        well[frame[tested]] = True
        self.well_posed_frames += int(well.sum())

    def _add_localized(self, table: Any) -> None:
        """Frames whose localized contact was estimated, and frames with each status bit."""
        from torchcontact.localize import localized_frames
        from torchcontact.status import LocalizeStatus

        sensors, ambiguous = self.localize  # type: ignore[misc]
        for s in sensors:
            code = arrow_to_numpy(table.column(f"localize_status_code.{s}"))
            has = arrow_to_numpy(table.column(f"localize_link.{s}").is_valid())
            used = localized_frames(code, has, ambiguous)
            self.located[s] = self.located.get(s, 0) + int(used.sum())
            bits = self.located_bits.setdefault(s, {b.name: 0 for b in LocalizeStatus})
            for b in LocalizeStatus:
                bits[b.name] += int(((code & int(b)) != 0).sum())

    def summary(self) -> dict:
        top = sorted(self.details.items(), key=lambda kv: (-kv[1], kv[0]))[:3]
        out: dict[str, Any] = {"bad_frames": self.bad, "bad_details": [list(t) for t in top]}
        if self.outside:  # frames where the learned correction extrapolates (outputs kept)
            out["outside_training"] = self.outside
            top = sorted(self.outside_details.items(), key=lambda kv: (-kv[1], kv[0]))[:5]
            out["outside_training_details"] = [list(t) for t in top]
        if self.cone_sensors:
            n = max(self.solved, 1)
            out["cones"] = {
                "solved": self.solved,
                "converged": round(self.converged / n, 4),
                "iterations_mean": round(self.it_sum / n, 2),
                "iterations_max": self.it_max,
                "frames": self.cone_frames,
                "converged_frames": self.converged_frames,
                "not_converged_frames": self.not_converged_frames,
                "cone_active_frames": self.active_frames,
                "well_posed_frames": self.well_posed_frames,
                "outside_cone_frames": self.outside_frames,
            }
        if self.localize is not None:
            out["localize"] = {
                s: {"localized": self.located.get(s, 0), "status": self.located_bits.get(s, {})}
                for s in self.localize[0]
            }
        return out


def cone_warning(source: str, tally: _Tally) -> None:
    """Warn once when too many well-posed frames contradict their friction cones.

    A well-posed frame (``rank == unknowns``) whose unconstrained estimate has a force outside
    its cone says that the data want a force the friction forbids: above
    :data:`OUTSIDE_CONE_WARN` of those frames, the friction coefficient is likely too small.
    """
    import warnings

    well, out = tally.well_posed_frames, tally.outside_frames
    if well and out > OUTSIDE_CONE_WARN * well:
        warnings.warn(
            f"{source}: {out} of {well} well-posed frames ({out / well:.0%}) have their"
            " unconstrained estimate outside the friction cone: the friction (--friction,"
            " --cone-angle or the contacts' own) contradicts the data, and the cones clip those"
            " frames' estimates; check it",
            UserWarning,
            stacklevel=2,
        )


def unusable(summary: dict, max_bad: float = 1.0) -> str | None:
    """Why an estimated input fails the CLI's ``--max-bad`` test, or None when it passes.

    An input fails when none of its frames is usable (every status is non-zero, or it has no
    frame), or when more than ``max_bad`` of its frames have a non-zero status.

    Args:
        summary: the dict :func:`~torchcontact.logs.estimate_file` returns.
        max_bad: the largest share of frames with a non-zero status that passes, in [0, 1].

    Example:
        >>> s = {"input": "a.parquet", "frames": 4, "bad_frames": 4,
        ...      "bad_details": [["q is not 7 floats", 4]]}
        >>> unusable(s)
        'a.parquet: no usable frame (4 of 4 frames have a non-zero status; most frequent: "q is not 7 floats" (4))'
        >>> unusable({**s, "bad_frames": 1}, 0.5) is None
        True
    """  # noqa: E501
    frames, bad = summary["frames"], summary["bad_frames"]
    if frames == 0:
        return f"{summary['input']}: no usable frame (the log has no rows)"
    if bad < frames and bad <= max_bad * frames:
        return None
    top = "; ".join(f'"{t}" ({n})' for t, n in summary.get("bad_details", []))
    head = "no usable frame" if bad == frames else f"more than {max_bad:g} of its frames unusable"
    return (
        f"{summary['input']}: {head} ({bad} of {frames} frames have a non-zero status"
        + (f"; most frequent: {top}" if top else "")
        + ")"
    )


# ---------------------------------------------------------------------- the run
class Run:
    """One estimate of one input into one output: lock, journal, ordered writer, summary.

    Use as a context manager: entering takes the lock (nothing else is written before), leaving
    releases it; an exception inside cleans up (see the module doc) and propagates.

    Args:
        out: the output Parquet file.
        source: the input (for messages and the summary).

    Raises:
        OutputBusyError: another live process holds the output's lock (on entering).
    """

    def __init__(self, out: str | Path, source: str | Path) -> None:
        self.out = Path(out)
        self.source = source
        self.partial, self.sidecar, self.tmp, _ = side_paths(self.out)
        self.lock = OutputLock(self.out, "estimate")
        self.ident: dict = {}
        self.units: list[tuple[int, int]] = []
        self.done: set[int] = set()

    # ------------------------------------------------------------------ lock and journal
    def __enter__(self) -> Run:
        self.lock.acquire()
        return self

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        try:
            if exc_type is not None:
                self._clean_failed()
        finally:
            self.lock.release()

    def previous(self) -> dict | None:
        """The record of an interrupted run of this output (None: none, or no part kept)."""
        if not self._parts():
            return None
        try:
            rec = json.loads(self.sidecar.read_text())
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) else None

    def _parts(self) -> list[Path]:
        if not self.partial.is_dir():
            return []
        return sorted(
            p for x in ("arrow", "parquet", "index") for p in self.partial.glob(f"part-*.{x}")
        )

    def part(self, k: int) -> Path:
        """Path of unit ``k``'s table waiting for its turn.

        A Ray worker's: a Parquet file (:func:`~torchcontact.logs.format.write_encoded_part`),
        appended as it is; Arrow IPC in journals of earlier versions.
        """
        arrow = self.partial / f"part-{k:08d}.arrow"
        parquet = arrow.with_suffix(".parquet")
        return parquet if parquet.is_file() else arrow

    def index(self, k: int) -> Path:
        """Path of unit ``k``'s journal entry (where it lies in ``OUT.tmp``)."""
        return self.partial / f"part-{k:08d}.index"

    def _written(self) -> list[PartIndex]:
        """The recorded units in ``OUT.tmp``, in order (units 0, 1, ...)."""
        out = []
        while self.index(len(out)).is_file():
            out.append(read_part_index(self.index(len(out))))
        return out

    def read_part(self, k: int) -> Any:
        """The output table of a unit done before (recorded in ``OUT.tmp``, or waiting).

        Raises:
            LogError: the unit is unreadable.
        """
        part = self.part(k)
        if part.is_file():
            if part.suffix == ".parquet":
                return _part_table(part)[1]
            return read_journal(part)
        return read_part(self.tmp, read_part_index(self.index(k)))

    def start(
        self, ident: dict, units: list[tuple[int, int]], resume: bool, recurrent: bool = False
    ) -> None:
        """Begin the journal, or take over an interrupted run's units (``resume``).

        Args:
            ident: what the run is (input identity, robot, options); a resume must match it.
            units: row ranges ``[lo, hi)`` of the units, in order.
            resume: keep the units an interrupted run journalled.
            recurrent: the estimate carries state across units (a GRU residual): no resume.

        Raises:
            LogError: an interrupted run's parts without ``resume`` (or with ``recurrent``), a run
                for other inputs or options, parts that do not fit the units.
        """
        self.ident, self.units = ident, units
        if self._parts():
            if recurrent:
                # the GRU state after the parts already written is not saved: refuse, not guess
                raise LogError(
                    f"{self.out}: an interrupted run left {self.partial.name}; a recurrent (GRU)"
                    " residual needs every frame in order and cannot resume: delete it and rerun"
                )
            if not resume:
                raise LogError(
                    f"{self.out}: an interrupted run left {self.partial.name} (no process is"
                    " writing it now); pass --resume (resume=True) to finish it, or delete it"
                )
            rec = self.previous()
            if rec is None or any(rec.get(k) != v for k, v in ident.items()):
                raise LogError(
                    f"{self.out}: the interrupted run was for other inputs or options (engine,"
                    f" batch size, sensors, ...); delete {self.partial} and"
                    f" {self.sidecar.name} to start afresh"
                )
            for tmp in self.partial.glob("*.tmp"):
                tmp.unlink()
            self._check_written()
            self.done = {int(p.stem.removeprefix("part-")) for p in self._parts()}
            if not self.done <= set(range(len(units))):
                raise LogError(
                    f"{self.out}: parts of {self.partial} do not fit the run; delete it and rerun"
                )
        try:
            if not self.done:
                # nothing journalled: leftovers of a run killed before its first unit go
                shutil.rmtree(self.partial, ignore_errors=True)
                self.out.parent.mkdir(parents=True, exist_ok=True)
                _io(self.partial, self.partial.mkdir)
            self.record()
        except LogError as exc:
            raise LogError(f"{exc}; {self.kept()}") from None

    def _check_written(self) -> None:
        """Recorded units must be consecutive from 0 and lie in ``OUT.tmp``.

        Raises:
            LogError: they do not (entries that skip a unit, an ``OUT.tmp`` shorter than them).
        """
        entries = sorted(self.partial.glob("part-*.index"))
        written = self._written()
        if len(entries) != len(written):
            raise LogError(
                f"{self.out}: the entries of {self.partial} are not consecutive; delete it and"
                " rerun"
            )
        if written:
            size = self.tmp.stat().st_size if self.tmp.is_file() else -1
            if size < 0 and self.out.is_file():
                # killed between publishing the output and removing the journal
                raise LogError(
                    f"{self.out}: {self.partial.name} is left by a run that had published"
                    f" {self.out.name} (no {self.tmp.name}): delete {self.partial} and"
                    f" {self.sidecar.name} (rerun to estimate it again)"
                )
            if size < written[-1].end:
                raise LogError(
                    f"{self.out}: {self.tmp.name} is shorter than the units {self.partial.name}"
                    f" records ({max(size, 0)} of {written[-1].end} bytes); delete"
                    f" {self.partial} and {self.sidecar.name}, and rerun"
                )

    def record(self) -> None:
        """Write the sidecar (atomically): what the run is, once at its start.

        The units done are the journal's entries (``OUT.partial``), not counted here: the
        sidecar is not rewritten per unit.
        """
        _atomic_json(self.sidecar, {**self.ident, "parts_done": len(self.done)})

    def _clean_failed(self) -> None:
        """After a failure: with no unit recorded, drop ``OUT.tmp`` and the journal."""
        if self.partial.is_dir():
            for tmp in self.partial.glob("*.tmp"):
                tmp.unlink(missing_ok=True)
        if not self.index(0).is_file():
            self.tmp.unlink(missing_ok=True)  # it holds no recorded unit
        if not self._parts():
            shutil.rmtree(self.partial, ignore_errors=True)
            self.sidecar.unlink(missing_ok=True)
            self.sidecar.with_name(self.sidecar.name + ".tmp").unlink(missing_ok=True)

    def kept(self) -> str:
        """What a failure leaves for ``--resume`` (the end of an error message)."""
        n = len(self._parts())
        if n == 0:
            return "nothing was kept (no unit had been estimated)"
        return f"{n} of {len(self.units)} chunks are kept in {self.partial} for --resume"

    # ------------------------------------------------------------------ running
    def execute(
        self,
        produce: Iterable[Done],
        schema: Any,
        *,
        progress: bool = False,
        cone_sensors: list[str] | None = None,
        localize: tuple[list[str], bool] | None = None,
        t0: float | None = None,
        **summary: Any,
    ) -> dict:
        """Write the engine's units into the output, in order, and return the summary.

        Args:
            produce: the engine's finished units (those not done yet), in any order; the local
                engine's come in order with their tables, the Ray engine's from its journal.
            schema: the output schema.
            progress: show a progress bar.
            cone_sensors: sensors with friction-cone columns (their solves are tallied).
            localize: ``(localizing sensors, accept_ambiguous)``: their localized frames and
                status bits are tallied (``estimate --localize``), or None.
            t0: ``time.perf_counter()`` when the job started (the summary's ``seconds`` count
                from there; default: now).
            **summary: more keys of the summary (input, sensors, derived, engine, ...).

        Returns:
            The summary: input, output, frames, processed_now, ok_now, bad_now, seconds,
            frames_per_s, resumed_chunks, chunks, bad_frames (NaN outputs: a status other than
            the warning bits), bad_details, outside_training and outside_training_details
            (frames whose learned correction extrapolates, when any), the given keys, with cones
            ``cones``, with ``localize`` ``localize`` (per sensor: ``localized`` frames and
            ``status``, frames per bit name).

        Raises:
            LogError: an I/O error (names the path), units missing at the end; an engine's
                error, with how many units are kept for ``--resume``.
        """
        from tqdm import tqdm

        t0 = time.perf_counter() if t0 is None else t0
        total = sum(hi - lo for lo, hi in self.units)
        resumed = len(self.done)
        bar = tqdm(total=total, unit="frames", disable=not progress, desc=Path(self.source).name)
        bar.update(sum(self.units[k][1] - self.units[k][0] for k in self.done))
        tally = _Tally(list(cone_sensors or []), localize)
        writer = _io(self.tmp, lambda: PartsWriter(self.out, schema, self._written()))
        sink = _OrderedSink(self, writer, tally, bar)
        try:
            try:
                for d in produce:
                    sink.put(d)
                sink.finish()
            except BaseException as exc:
                close = getattr(produce, "close", None)
                if close is not None:  # stops the engine's threads (a generator's finally)
                    close()
                sink.abort()
                writer.abort(keep=True)  # its recorded units stay for --resume
                if isinstance(exc, TorchContactError):
                    raise type(exc)(f"{exc}; {self.kept()}") from None
                raise
            if sink.written != len(self.units):
                writer.abort(keep=True)
                missing = len(self.units) - sink.written
                raise LogError(f"{self.out}: {missing} chunks missing; {self.kept()}")
            _io(self.tmp, writer.close)
        finally:
            bar.close()
            writer.abort(keep=True)  # closed already, unless an error left it open
        shutil.rmtree(self.partial)
        self.sidecar.unlink()
        seconds = time.perf_counter() - t0
        now = tally.ok_now + tally.bad_now
        cone_warning(str(self.source), tally)
        return {
            "input": str(self.source),
            "output": str(self.out),
            "frames": tally.rows,
            "processed_now": now,
            "ok_now": tally.ok_now,
            "bad_now": tally.bad_now,
            "seconds": round(seconds, 3),
            "frames_per_s": round(now / max(seconds, 1e-9), 1),
            **summary,
            "resumed_chunks": resumed,
            "chunks": len(self.units),
            **tally.summary(),
        }


class _OrderedSink:
    """The writer thread: encodes the units it is given and appends them to the output in order.

    A unit is recorded in the journal (:func:`~torchcontact.logs.format.write_part_index`) once
    its bytes are in ``OUT.tmp``. Units recorded before (a resume) are read back for the summary's
    tally; units the engine journalled itself (a Ray worker's Parquet part) are appended from
    their file when their turn comes; at most one estimated table waits in memory besides the
    queue.
    """

    def __init__(self, run: Run, writer: PartsWriter, tally: _Tally, bar: Any) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.run, self.writer, self.tally, self.bar = run, writer, tally, bar
        self._encoders = ThreadPoolExecutor(ENCODERS, thread_name_prefix="torchcontact-encoder")
        self.written = len(writer.parts)  # units already in OUT.tmp (a resume)
        self.now: set[int] = set()
        self._held: dict[int, Any] = {}
        self._q: queue.Queue = queue.Queue(QUEUE_DEPTH)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._work, name="torchcontact-writer", daemon=True)
        self._thread.start()

    # producer side (main thread)
    def put(self, d: Done) -> None:
        if d is not None and d.table is not None:  # encoded on a pool thread meanwhile
            d = Done(
                d.unit,
                d.rows,
                (d.table, self._encoders.submit(encode_part, d.table, self.writer.schema)),
            )
        while True:
            self._raise()
            try:
                self._q.put(d, timeout=0.1)
                return
            except queue.Full:
                continue

    def finish(self) -> None:
        """No more units: wait until everything is written."""
        self.put(None)  # type: ignore[arg-type]
        self._thread.join()
        self._encoders.shutdown()
        self._raise()

    def abort(self) -> None:
        """The engine failed: journal what was handed over already, then stop."""
        try:
            while self._thread.is_alive():
                try:
                    self._q.put(None, timeout=0.1)
                    break
                except queue.Full:
                    continue
        finally:
            self._thread.join()
            self._encoders.shutdown(cancel_futures=True)

    def _raise(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            if isinstance(err, TorchContactError):
                raise type(err)(f"{err}; {self.run.kept()}") from None
            raise err

    # writer thread
    def _work(self) -> None:
        try:
            for k in range(self.written):  # units of an interrupted run, in OUT.tmp already
                self.tally.add(self.run.read_part(k), False)
            self._drain()  # units of an interrupted run waiting in the journal
            while True:
                d = self._q.get()
                if d is None:
                    return
                run = self.run
                if d.table is not None:
                    self._held[d.unit] = d.table
                run.done.add(d.unit)
                self.now.add(d.unit)
                self.bar.update(d.rows)
                self._drain()
        except BaseException as exc:
            self._error = exc

    def _drain(self) -> None:
        run = self.run
        while self.written < len(run.units) and self.written in run.done:
            k = self.written
            if self._append_parts(k):
                continue
            held = self._held.pop(k, None)
            waiting = held is None  # journalled by an earlier version (Arrow IPC)
            if waiting:
                tab = read_journal(run.part(k))
                part = encode_part(tab, self.writer.schema)
            else:
                tab, encoding = held
                part = encoding.result()
            index = _io(run.tmp, lambda: self.writer.append(part))  # noqa: B023
            self._record(k, index, tab, waiting)

    def _record(self, k: int, index: PartIndex, tab: Any, journalled: bool) -> None:
        """Record unit ``k``, whose bytes are in ``OUT.tmp`` at ``index``.

        Journals it, drops its part file (``journalled``: the engine wrote one) and tallies its
        table.
        """
        entry = self.run.index(k)
        _io(entry, lambda: write_part_index(index, entry))
        if journalled:
            self.run.part(k).unlink()
        self.tally.add(tab, k in self.now)
        self.written += 1

    def _append_parts(self, k: int) -> int:
        """Append the Ray workers' parts ready from unit ``k`` on, several at once; how many.

        The consecutive units from ``k`` that a worker journalled as a Parquet part (at most
        :data:`PARTS_AT_ONCE`) are read on the encoder threads (the part, its tally columns) and
        written at their offsets at once (:meth:`PartsWriter.append_many`), then recorded in
        the journal in order, as one at a time would record them: a run killed in between keeps
        a prefix of them, and the rest stay in their part files. 0: unit ``k`` is not such a
        part (an estimated table, or an earlier version's journal).
        """
        run, ks = self.run, []
        while (
            k + len(ks) < len(run.units)
            and k + len(ks) in run.done
            and k + len(ks) not in self._held
            and len(ks) < PARTS_AT_ONCE
            and run.part(k + len(ks)).suffix == ".parquet"
        ):
            ks.append(k + len(ks))
        if not ks:
            return 0
        names = self.writer.schema.names
        reads = [self._encoders.submit(_part_table, run.part(u), self.tally, names) for u in ks]
        parts, error = [], None
        for f in reads:  # in order: the parts before a damaged one are appended
            try:
                parts.append(f.result())
            except BaseException as exc:  # noqa: BLE001 - raised once the others are recorded
                error = exc
                break
        if parts:
            pool = self._encoders if len(parts) > 1 else None
            written = _io(run.tmp, lambda: self.writer.append_many([p for p, _ in parts], pool))
            for u, index, (_, tab) in zip(ks, written, parts, strict=False):
                self._record(u, index, tab, True)
        for f in reads:
            f.cancel()
        if error is not None:
            raise error
        return len(parts)
