"""``torchcontact view``: a log (and its estimate) streamed into a rerun recording.

Two passes over the files, each in chunks (memory stays flat in the log's length):

1. the time stamps of the log and of the estimate, which must be the same row by row (an
   estimate of another log is refused before anything is written); within the time window, the
   contact slots of the whole log (:meth:`SlotLayout.covering` of every chunk, so a slot keeps its
   colour) and a sample of the force magnitudes (the default arrow scale);
2. the frames of the window, every ``every``-th row: joint positions (``qd``/``qdd`` derived from
   ``q`` as ``estimate`` does when the log lacks them), readings, contacts and the estimate's
   columns, the residual ``A x - b`` per sensor recomputed as the reading the estimated contacts
   predict (:meth:`ContactEstimator.predict_ft`) minus the measured one, and on demand the
   null-space directions of the ill-posed frames; drawn by :class:`~torchcontact.view.RerunScene`.

The recording is written to ``OUT.tmp`` and renamed to ``OUT`` when complete.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, LogError

__all__ = ["view_log"]

#: Force magnitudes kept to choose the default arrow scale (a uniform sample of the window).
_SAMPLE = 65536


def _rechunk(tables: Iterator[Any], skip: int, rows: int, size: int) -> Iterator[Any]:
    """``rows`` rows after the first ``skip`` in tables of ``size`` rows (the last shorter)."""
    import pyarrow as pa

    buf: list[Any] = []
    have = 0
    for tab in tables:
        if skip >= tab.num_rows:
            skip -= tab.num_rows
            continue
        tab = tab.slice(skip, rows)
        skip = 0
        rows -= tab.num_rows
        buf.append(tab)
        have += tab.num_rows
        while have >= size:
            t = pa.concat_tables(buf).combine_chunks()
            yield t.slice(0, size)
            rest = t.slice(size)
            buf, have = [rest], rest.num_rows
        if rows <= 0:
            break
    if have:
        yield pa.concat_tables(buf).combine_chunks()


def _rows(pf: Any, columns: Sequence[str], r0: int, r1: int, size: int, src: str) -> Iterator[Any]:
    """Rows ``[r0, r1)`` of a log in tables of ``size`` rows (only their row groups are read)."""
    from torchcontact.logs.format import iter_chunks

    sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.num_row_groups)]
    bounds = np.cumsum([0, *sizes])
    groups = [g for g in range(len(sizes)) if bounds[g] < r1 and bounds[g + 1] > r0]
    if not groups or r1 <= r0:
        return iter(())
    tables = iter_chunks(pf, columns, size, src, row_groups=groups)
    return _rechunk(tables, r0 - int(bounds[groups[0]]), r1 - r0, size)


def _check_estimate(pf: Any, est: str, model: Any, rows: int, log: str) -> list[str]:
    """The estimate's sensors; refuse a file that is no estimate, of another robot or length."""
    from torchcontact.logs.format import META_SENSORS, META_URDF_SHA256

    names = pf.schema_arrow.names
    need = [c for c in ("t_ns", "contacts", "status_code") if c not in names]
    if need or not any(c.startswith("rank.") for c in names):
        raise LogError(
            f"{est}: not an output of torchcontact estimate (missing {need or ['rank.*']})"
        )
    meta = pf.schema_arrow.metadata or {}
    logged = meta.get(META_URDF_SHA256, b"").decode()
    if logged and logged != model.urdf_sha256:
        raise LogError(
            f"{est}: estimated with another robot (URDF sha256 {logged[:12]}...), not"
            f" {model.name} ({model.urdf_sha256[:12]}...); pass that URDF with --robot"
        )
    if pf.metadata.num_rows != rows:
        raise LogError(
            f"{est}: {pf.metadata.num_rows} rows, {log} has {rows}: not an estimate of that log"
        )
    sensors = json.loads(meta.get(META_SENSORS, b"[]"))
    return sensors or [c[5:] for c in names if c.startswith("rank.")]


def _first_pass(
    pf: Any,
    epf: Any,
    log: str,
    est: str | None,
    window: tuple[float | None, float | None],
    size: int,
) -> tuple[int, int, int, Any, np.ndarray]:
    """Check the time stamps; the window's rows, its slot layout and a sample of its forces.

    Returns:
        ``(r0, r1, t0_ns, layout, force_sample, median_step_ns)``.

    Raises:
        LogError: the estimate's ``t_ns`` differ from the log's (another log), time stamps that
            are not numbers.
        InputError: no frame in the window.
    """
    from torchcontact.contacts import SlotLayout
    from torchcontact.logs.derive import median_step, step_histogram
    from torchcontact.logs.format import iter_chunks, read_contacts, vectors

    rng = np.random.default_rng(0)
    contacts_of = epf if epf is not None else pf
    has_contacts = "contacts" in contacts_of.schema_arrow.names
    est_it = None
    if epf is not None:
        est_it = iter_chunks(epf, ["t_ns", "contacts"], size, est)
    log_it = iter_chunks(
        pf, ["t_ns"] + (["contacts"] if has_contacts and epf is None else []), size, log
    )
    start, end = window
    mult: dict[tuple[str, str], int] = {}
    sample = np.zeros(0)
    seen = 0
    r0 = r1 = None
    t0 = None
    row = 0
    span = 0.0
    steps: dict[int, int] = {}  # the log's time steps, for the derivatives' gap rule
    for tab in log_it:
        t = tab.column("t_ns").to_numpy(zero_copy_only=False)
        step_histogram(t, steps)
        etab = None
        if est_it is not None:
            etab = next(est_it, None)
            et = etab.column("t_ns").to_numpy(zero_copy_only=False)
            n = min(len(et), len(t))
            differ = np.flatnonzero(et[:n] != t[:n])
            if len(differ) or len(et) != len(t):
                bad = row + (int(differ[0]) if len(differ) else n)
                raise LogError(
                    f"{est}: t_ns of row {bad} differ from {log}'s: an estimate of another log"
                    " (estimate that log, or give the log the estimate was made from)"
                )
        if t0 is None:
            t0 = int(t[0])
        s = (t - t0) * 1e-9
        span = float(s[-1])
        inside = np.ones(len(t), bool)
        if start is not None:
            inside &= s >= start
        if end is not None:
            inside &= s <= end
        idx = np.flatnonzero(inside)
        if len(idx):
            r0 = row + int(idx[0]) if r0 is None else r0
            r1 = row + int(idx[-1]) + 1
            src = etab if etab is not None else tab
            if has_contacts:
                records, fields, _ = read_contacts(src.column("contacts"))
                keep = inside[records.frame]
                records = records.select(keep)
                for key, m in zip(*_covering_pairs(records), strict=True):
                    mult[key] = max(mult.get(key, 0), m)
                for name in ("force", "true_force"):
                    if name in fields:
                        mag = np.linalg.norm(vectors(fields[name], 3)[0][keep], axis=-1)
                        mag = mag[np.isfinite(mag)]
                        seen += len(mag)
                        sample = np.concatenate([sample, mag])
                        if len(sample) > _SAMPLE:  # keep a uniform sample of what was seen
                            sample = rng.choice(sample, _SAMPLE, replace=False)
        row += len(t)
    if r0 is None:
        raise InputError(
            f"--start {start} --end {end}: no frame of {log} in that window (its frames span"
            f" 0 to {span:.3f} s after its first t_ns)"
        )
    links = [k[0] for k in sorted(mult) for _ in range(mult[k])]
    kinds = [k[1] for k in sorted(mult) for _ in range(mult[k])]
    layout = SlotLayout(tuple(links), tuple(kinds))
    return r0, r1, int(t0), layout, sample, median_step(steps)


def _with_derivatives(
    tables: Iterator[Any],
    joints: tuple[np.ndarray, int, str, int],
    derive: tuple[int, float] | None,
    before: tuple[np.ndarray, np.ndarray] | None,
    after: tuple[np.ndarray, np.ndarray] | None,
) -> Iterator[tuple[Any, np.ndarray | None, np.ndarray | None]]:
    """``(table, qd, qdd)`` of consecutive tables, derived as ``estimate`` derives them.

    The log pipeline's differentiator (:class:`~torchcontact.logs.derive.DerivativeStream`:
    Savitzky-Golay within each time segment, ``2 h`` frames of context across tables).

    Args:
        tables: consecutive tables of the log.
        joints: ``(perm, width, source, first_row)`` of the log's ``q`` columns.
        derive: ``(h, median_step_ns)``, or None when the log has ``qd``/``qdd``.
        before: ``(t_ns, q)`` of the frames preceding the first table (None at the start).
        after: ``(t_ns, q)`` of the frames following the last table (None at the end).
    """
    from collections import deque

    from torchcontact.logs.decode import stamps_and_positions
    from torchcontact.logs.derive import DerivativeStream

    if derive is None:
        for tab in tables:
            yield tab, None, None
        return
    perm, width, src, row = joints
    h, step_ns = derive
    stream, c = DerivativeStream(h, step_ns, before), 2 * h
    empty = (np.zeros(0, np.int64), np.zeros((0, len(perm))))
    ahead: deque = deque()

    def finish() -> tuple[Any, np.ndarray, np.ndarray]:
        tab, t, q = ahead.popleft()
        nxt = list(ahead)
        if nxt:
            t_n = np.concatenate([x[1] for x in nxt])[:c]
            q_n = np.concatenate([x[2] for x in nxt])[:c]
        else:
            t_n, q_n = after if after is not None else empty
        qd, qdd, _, _ = stream.derive(t, q, t_n, q_n)
        return tab, qd, qdd

    for tab in tables:
        t, q = stamps_and_positions(tab, perm, width, src, row)
        row += tab.num_rows
        ahead.append((tab, t, q))
        while len(ahead) > 1 and sum(len(x[1]) for x in list(ahead)[1:]) >= c:
            yield finish()
    while ahead:
        yield finish()


def _covering_pairs(records: Any) -> tuple[list[tuple[str, str]], list[int]]:
    """``(link, kind)`` pairs of a chunk's covering layout and their multiplicities."""
    from torchcontact.contacts import SlotLayout

    lay = SlotLayout.covering(records)
    pairs = list(dict.fromkeys(zip(lay.links, lay.kinds, strict=True)))
    pl = list(zip(lay.links, lay.kinds, strict=True))
    return pairs, [pl.count(p) for p in pairs]


class _Residual:
    """``A x - b`` per sensor: the reading the estimated contacts predict minus the measured one."""

    def __init__(self, model: Any, sensors: Sequence[str]) -> None:
        import torchcontact as tc

        self.model = model
        self.est = tc.ContactEstimator(model, list(sensors), backend="eager")
        self.sensors = list(sensors)

    def __call__(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        ft: dict[str, np.ndarray],
        records: Any,
        force: np.ndarray,
        moment: np.ndarray,
        status: np.ndarray,
        base: dict[str, np.ndarray] | None,
    ) -> dict[str, np.ndarray]:
        import torch

        import torchcontact as tc
        from torchcontact.contacts import ContactRecords

        N = len(q)
        wrench = np.concatenate([force, moment], -1)
        ok = (status == 0) & np.isfinite(q).all(-1) & np.isfinite(qd).all(-1)
        ok &= np.isfinite(qdd).all(-1)
        for s in self.sensors:
            ok &= np.isfinite(ft[s]).all(-1)
        good_rec = np.isfinite(wrench).all(-1) & np.isfinite(records.positions).all(-1)
        good_rec &= np.array(
            [isinstance(x, str) and x in self.model.frames for x in records.links], bool
        )
        bad_frames = np.unique(records.frame[~good_rec])
        ok[bad_frames] = False
        out = {s: np.full((N, 6), np.nan) for s in self.sensors}
        idx = np.flatnonzero(ok)
        if not len(idx):
            return out
        index = np.full(N, -1)
        index[idx] = np.arange(len(idx))
        keep = ok[records.frame]
        known = ContactRecords(
            index[records.frame[keep]],
            records.links[keep],
            np.full(int(keep.sum()), "known", object),
            records.positions[keep],
            wrenches=wrench[keep],
        )
        dt = self.model.dtype
        contacts, _ = tc.Contacts.from_records(known, len(idx), dtype=dt)

        def t(x: np.ndarray) -> Any:
            return torch.as_tensor(x[idx], dtype=dt)

        motion = None
        if base is not None:
            motion = tc.BaseMotion(t(base["omega"]), t(base["domega"]), t(base["proper_acc"]))
        pred = self.est.predict_ft(t(q), t(qd), t(qdd), contacts, base=motion)
        for s in self.sensors:
            out[s][idx] = pred[s].numpy() - ft[s][idx]
        return out


def view_log(
    log: str | Path,
    estimate: str | Path | None = None,
    robot: str | Path | None = None,
    out: str | Path | None = None,
    *,
    spawn: bool = False,
    every: int = 1,
    start: float | None = None,
    end: float | None = None,
    scale: float | None = None,
    nullspace: bool = False,
    require_meshes: bool = False,
    batch_size: int = 2000,
    progress: bool = False,
    recording: Any = None,
) -> dict[str, Any]:
    """Stream a log and its estimate into a rerun recording (``torchcontact view``).

    Args:
        log: the input log (joint positions, readings, contacts; log format).
        estimate: its output of ``torchcontact estimate`` (same rows), or None.
        robot: the URDF (its visual meshes are drawn).
        out: the ``.rrd`` file to write (written as ``OUT.tmp``, renamed when complete).
        spawn: open a rerun viewer and stream to it instead of (or besides) a file.
        every: draw every ``every``-th row of the window.
        start: window start, s after the log's first ``t_ns`` (default: the first frame).
        end: window end, s after the first ``t_ns`` (default: the last frame).
        scale: arrow scale, N per m (default: the window's 95th percentile force a quarter of
            the robot's size, rounded to 1, 2 or 5 x 10^k).
        nullspace: draw the null-space directions of the ill-posed frames (recomputed per frame).
        require_meshes: a visual mesh that cannot be loaded is an error, not a warning.
        batch_size: frames read and drawn at a time.
        progress: show a progress bar (rows of the window).
        recording: a ``rerun.RecordingStream`` to draw into instead (``out``/``spawn`` unused).

    Returns:
        Summary: ``frames`` drawn, ``rows`` ``[first, last]`` of the window, ``scale`` (N per
        m), ``out``, ``missing_meshes``, ``layout`` (slot links), ``seconds``.

    Raises:
        LogError: an unreadable or empty log, an estimate of another log or robot, or not an
            estimate.
        InputError: bad options (``every`` < 1, a window without frames, ``out`` an input).
        URDFError: a visual mesh that cannot be loaded, with ``require_meshes``.
        MissingExtraError: rerun-sdk (extra ``view``) or trimesh (extra ``meshes``) missing.
    """
    from tqdm import tqdm

    from torchcontact.logs.decode import stamps_and_positions
    from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
    from torchcontact.logs.format import (
        BASE_COLUMNS,
        META_RESIDUAL,
        check_outputs,
        ft_column,
        joint_names_of,
        joint_permutation,
        open_log,
        read_rows,
    )
    from torchcontact.logs.pipeline import load_robot
    from torchcontact.view.scene import RerunScene, import_rerun

    t_start = time.perf_counter()
    if not isinstance(every, int) or every < 1:
        raise InputError(f"--every must be an integer >= 1, got {every!r}")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise InputError(f"--batch-size must be an integer >= 1, got {batch_size!r}")
    if start is not None and end is not None and end < start:
        raise InputError(f"--end {end} is before --start {start}")
    if recording is None and out is None and not spawn:
        raise InputError("give --out FILE.rrd or --spawn")
    if robot is None:
        raise InputError("--robot: give the robot's URDF")
    outs = [] if out is None else [Path(out), Path(str(out) + ".tmp")]
    check_outputs(outs, [log, estimate, robot])
    import_rerun()  # before any work: a missing extra is one error line
    src, est_src = str(log), None if estimate is None else str(estimate)
    pf = open_log(log)
    schema = pf.schema_arrow
    for col in ("t_ns", "q"):
        if col not in schema.names:
            raise LogError(f"{src}: missing column {col!r} (found {schema.names})")
    rows = pf.metadata.num_rows
    if rows == 0:
        raise LogError(f"{src}: no frames to view (an empty log)")
    model = load_robot(robot)
    log_joints = joint_names_of(schema, src)
    perm = joint_permutation(log_joints, model.joint_names, model.name, src)
    width = len(log_joints)
    epf = None
    sensors = [s for s in model.ft_sensors if ft_column(s) in schema.names]
    if estimate is not None:
        epf = open_log(estimate)
        sensors = _check_estimate(epf, est_src, model, rows, src)  # type: ignore[arg-type]
    missing_ft = [s for s in sensors if ft_column(s) not in schema.names]
    if missing_ft:
        raise LogError(f"{src}: no reading of sensors {missing_ft} (columns ft.<sensor>)")
    unknown = [s for s in sensors if s not in model.ft_sensors]
    if unknown:
        raise LogError(f"{est_src}: sensors {unknown} are not F/T sensors of {model.name}")
    r0, r1, _, layout, sample, step_ns = _first_pass(
        pf, epf, src, est_src, (start, end), batch_size
    )
    econ = [] if epf is None else epf.schema_arrow.names
    constrained = any(c.startswith("converged.") for c in econ)
    correction = epf is not None and META_RESIDUAL in (epf.schema_arrow.metadata or {})
    if correction:
        warnings.warn(
            f"{est_src} was estimated with a learned F/T correction: the residual A x - b is"
            " drawn as its norm only (the vector would need the corrected readings)",
            UserWarning,
            stacklevel=2,
        )
    if scale is not None and not scale > 0:
        raise InputError(f"--scale must be > 0 N per m, got {scale}")
    scene = RerunScene(
        model,
        recording,
        urdf=robot,
        layout=layout,
        scale=scale,
        sensors=sensors,
        constrained=constrained,
        require_meshes=require_meshes,
    )
    if scale is None and len(sample):
        import torch

        import torchcontact as tc
        from torchcontact.view.scene import nice_scale

        q0 = stamps_and_positions(read_rows(log, r0, r0 + 1, ["t_ns", "q"]), perm, width)[1]
        q0 = torch.tensor(q0, dtype=model.dtype)
        p = tc.forward_pass(model, q0, torch.zeros_like(q0), torch.zeros_like(q0)).p[0].numpy()
        size = max(float(np.max(p.max(0) - p.min(0))), 0.2)
        scene.scale = nice_scale(float(np.percentile(sample, 95)), 0.25 * size)
    rec = scene.recording
    tmp = None
    if recording is None:
        if spawn:
            rec.spawn(connect=True)
        else:
            tmp = Path(str(out) + ".tmp")
            tmp.unlink(missing_ok=True)
            rec.save(tmp)
    derive = [c for c in ("qd", "qdd") if c not in schema.names]
    h = DEFAULT_HALF_WINDOW
    base_cols = [c for c in BASE_COLUMNS if c in schema.names]
    columns = ["t_ns", "q", *[c for c in ("qd", "qdd") if c in schema.names]]
    columns += [ft_column(s) for s in sensors] + base_cols
    if epf is None and "contacts" in schema.names:
        columns.append("contacts")
    ecolumns = (
        []
        if epf is None
        else [
            c
            for c in econ
            if c == "t_ns"
            or c == "contacts"
            or c == "status_code"
            or "." in c
            and c.split(".")[0]
            in ("rank", "unknowns", "nullity", "residual", "converged", "iterations")
        ]
    )
    before = after = None
    if derive:
        lo, hi = max(r0 - h, 0), min(r1 + h, rows)
        before = stamps_and_positions(read_rows(log, lo, r0, ["t_ns", "q"]), perm, width, src, lo)
        after = stamps_and_positions(read_rows(log, r1, hi, ["t_ns", "q"]), perm, width, src, r1)
    residual = None if epf is None or correction else _Residual(model, sensors)
    drawn = 0
    try:
        chunks = _with_derivatives(
            _rows(pf, columns, r0, r1, batch_size, src),
            (perm, width, src, r0),
            (h, step_ns) if derive else None,
            before,
            after,
        )
        echunks = None if epf is None else _rows(epf, ecolumns, r0, r1, batch_size, est_src)
        row = r0
        with tqdm(total=r1 - r0, unit="frame", desc="view", disable=not progress) as bar:
            for chunk, qd, qdd in chunks:
                etab = None if echunks is None else next(echunks)
                n = chunk.num_rows
                pick = np.flatnonzero((np.arange(row, row + n) - r0) % every == 0)
                frames = _frames(
                    model,
                    chunk,
                    etab,
                    perm,
                    qd,
                    qdd,
                    sensors,
                    base_cols,
                    layout,
                    row,
                    pick,
                    residual,
                    nullspace,
                )
                scene.log(frames)
                scene.flush()
                drawn += len(frames)
                row += n
                bar.update(n)
        if tmp is not None:
            rec.flush()
            rec.disconnect()
            os.replace(tmp, out)  # type: ignore[arg-type]
        elif recording is None:
            rec.flush()
    except BaseException:
        if tmp is not None:
            rec.disconnect()
            tmp.unlink(missing_ok=True)
        raise
    return {
        "log": src,
        "estimate": est_src,
        "out": None if out is None else str(out),
        "frames": drawn,
        "rows": [r0, r1 - 1],
        "every": every,
        "scale": scene.scale,
        "layout": list(layout.links),
        "missing_meshes": [f"{link}: {f}" for link, f, _ in scene.missing],
        "seconds": time.perf_counter() - t_start,
    }


def _frames(
    model: Any,
    chunk: Any,
    etab: Any,
    perm: np.ndarray,
    qd: np.ndarray | None,
    qdd: np.ndarray | None,
    sensors: Sequence[str],
    base_cols: Sequence[str],
    layout: Any,
    row: int,
    pick: np.ndarray,
    residual: _Residual | None,
    nullspace: bool,
) -> Any:
    """The :class:`ViewFrames` of rows ``pick`` of a chunk (and of its estimate)."""
    from torchcontact.logs.format import BASE_COLUMNS, ft_column, read_contacts, vectors
    from torchcontact.logs.plot import null_directions, rank_deficient
    from torchcontact.view.scene import ViewFrames

    nv = len(perm)
    chunk = chunk.take(pick)
    t = chunk.column("t_ns").to_numpy(zero_copy_only=False).astype(np.int64)
    q = vectors(chunk.column("q"), nv)[0][:, perm]
    qd = vectors(chunk.column("qd"), nv)[0][:, perm] if qd is None else qd[pick]
    qdd = vectors(chunk.column("qdd"), nv)[0][:, perm] if qdd is None else qdd[pick]
    ft = {s: vectors(chunk.column(ft_column(s)), 6)[0] for s in sensors}
    base = None
    if base_cols:
        base = {BASE_COLUMNS[c]: vectors(chunk.column(c), 3)[0] for c in base_cols}
        for c in BASE_COLUMNS.values():
            base.setdefault(c, np.zeros((len(t), 3)))
    kw: dict[str, Any] = {"t_ns": t, "q": q, "rows": row + pick, "ft": ft}
    src = etab.take(pick) if etab is not None else chunk
    if "contacts" in src.column_names:
        records, fields, _ = read_contacts(src.column("contacts"))
        kw["records"] = records
        kw["slot"] = layout.assign(records)
        for name in ("force", "moment", "true_force"):
            if name in fields:
                kw[name] = vectors(fields[name], 3)[0]
        if "cone_active" in fields:
            kw["cone_active"] = np.asarray(
                fields["cone_active"].fill_null(False).to_numpy(zero_copy_only=False), bool
            )
    if etab is None:
        return ViewFrames(**kw)

    def col(name: str) -> np.ndarray:
        return src.column(name).to_numpy(zero_copy_only=False)

    for key in ("rank", "unknowns", "nullity", "residual", "converged", "iterations"):
        if f"{key}.{sensors[0]}" in src.column_names:
            kw[key] = {s: col(f"{key}.{s}") for s in sensors}
    kw["status"] = col("status_code").astype(np.int64)
    if residual is not None and "force" in kw:
        kw["residual_wrench"] = residual(
            q, qd, qdd, ft, kw["records"], kw["force"], kw["moment"], kw["status"], base
        )
    if nullspace and "records" in kw:
        ill = rank_deficient(kw["rank"], kw["unknowns"]) & (kw["status"] == 0)
        null: list[Any] = [None] * len(t)
        idx = np.flatnonzero(ill)
        if len(idx):
            index = np.full(len(t), -1)
            index[idx] = np.arange(len(idx))
            recs = kw["records"]
            keep = ill[recs.frame]
            sub = recs.select(keep).with_frame(index[recs.frame[keep]])
            res = null_directions(model, sensors, q[idx], sub, rows=(row + pick)[idx])
            for i, (dirs, _, _) in zip(idx, res, strict=True):
                null[i] = dirs
        kw["null"] = null
    return ViewFrames(**kw)


def demo_recording(
    folder: str | Path, log: str | Path, estimate: str | Path, robot: str | Path, **kwargs: Any
) -> Path | None:
    """``demo.rrd`` of the demo's log and estimate (null-space directions drawn), if rerun is here.

    Args:
        folder: the demo's folder.
        log: its simulated log.
        estimate: its estimate.
        robot: its URDF.
        **kwargs: passed to :func:`view_log` (e.g. ``progress``).

    Returns:
        The recording's path, or None when rerun-sdk (extra ``view``) is not installed.
    """
    try:
        import rerun  # noqa: F401
    except ImportError:
        return None
    out = Path(folder) / "demo.rrd"
    view_log(log, estimate, robot, out, nullspace=True, **kwargs)
    return out
