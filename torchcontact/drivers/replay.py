"""``torchcontact run --onnx GRAPH --log LOG.parquet``: a recorded log through the runtime.

The log is read by the log pipeline's own reader (:func:`torchcontact.logs.pipeline.prepare`:
the schema checks, one scan for the time segments, :class:`~torchcontact.logs.decode.
ChunkDecoder` for the typed columns in the model's joint order, the record checks, and
:func:`~torchcontact.logs.chunks.decoded_chunks` for ``qd``/``qdd`` derived within time segments
when the log lacks them), so a log means the same here as to ``torchcontact estimate``.

Each frame then goes through the exported estimator one step at a time, as the live loop runs it
(:class:`~torchcontact.drivers.live.RuntimeEstimator`: the online state, ``--track-bias``,
``--tare``, ``--payload``, with the log's ``t_ns`` as the tracker's clock): its F/T readings, its
joint state, and its contact records placed in the file's slots (the ``r``-th record of a
``(link, kind)`` pair in a frame takes the ``r``-th slot of that pair,
:meth:`~torchcontact.contacts.SlotLayout.fill`). Logged ``tau_measured`` and base motion go in
where the file takes them, and the columns its chained corrections read as ``extra``.

Every frame publishes one record, as the live loop's: ``t_ns``, ``row`` (the log's row),
``ft`` (the readings, sensors in the file's order), ``estimate`` (the step's outputs; forces per
slot), ``record_slots`` (per contact record of the frame, in the log's order, the slot it was
placed in, or null: a record the decoder refused or the file has no free slot for), and
``log_issues`` (the decoder's detail text) where the frame has one. A frame whose joint state or
reading is unusable (non-finite, malformed, not differentiable) gets ``estimate: {"error": ...}``
instead of a step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, ModelMismatchError

__all__ = ["UNUSABLE_BITS", "replay_log"]

#: Decoder status bits that leave a frame without a usable step input: a bad F/T reading (1), a
#: bad joint state (2), derivatives that cannot be derived (512, ``Status.NOT_DIFFERENTIABLE``).
UNUSABLE_BITS = 1 | 2 | 512


def replay_log(
    path: str | Path,
    estimator: Any,
    robot: Any,
    publishers: Sequence[Any],
    *,
    log: Any = None,
    batch_size: int = 8192,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Replay a recorded log through an exported estimator, frame by frame.

    Args:
        path: the log (the torchcontact log format).
        estimator: a :class:`~torchcontact.drivers.live.RuntimeEstimator`.
        robot: the robot the log was recorded on (a :class:`~torchcontact.robots.RobotSpec`, a
            robot argument or a ``RobotModel``); the file must have been exported for it.
        publishers: objects with ``publish(record)`` (JSON lines on stdout, UDP).
        log: an :class:`~torchcontact.drivers.log.FTLogWriter` (``--out``) or None.
        batch_size: frames read and decoded at once.
        on_record: called with each published record.

    Returns:
        Summary: ``frames``, ``published``, ``log_errors`` (frames without a usable input),
        ``estimator_errors``, ``records``, ``records_without_slot`` (per ``link:kind``),
        ``sensors``, ``derived`` and ``seconds``.

    Raises:
        LogError: a log the pipeline refuses (no joint names, a missing ``ft.<sensor>`` column
            of the file's sensors, a bad ``t_ns``, ...).
        ModelMismatchError: the file's joints are not the robot's.
    """
    import time

    from torchcontact.contacts import SlotLayout
    from torchcontact.drivers.live import _jsonable
    from torchcontact.logs.chunks import decoded_chunks
    from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
    from torchcontact.logs.pipeline import load_robot, prepare, read_chunks

    t0 = time.perf_counter()
    rt = estimator.runtime
    model = load_robot(robot)
    missing = [j for j in rt.joint_names if j not in model.joint_names]
    if missing:
        raise ModelMismatchError(f"{rt.path} has joints {missing} that {model.name} lacks")
    perm = np.array([model.joint_names.index(j) for j in rt.joint_names])
    src = str(path)
    # the graph's correction columns are read like a residual checkpoint's features
    pf, le, columns, _ = prepare(path, model, list(rt.sensor_names))
    absent = [c for c in rt.extra if c not in pf.schema_arrow.names]
    if absent:
        raise InputError(f"{rt.path} reads extra columns {absent}, which {src} lacks")
    le.decoder.extra_columns = list(rt.extra)
    columns += [c for c in rt.extra if c not in columns]
    layout = SlotLayout(rt.slot_links, rt.slot_kinds)
    takes = rt.input_names
    summary: dict[str, Any] = {"log": src, "frames": 0, "published": 0, "log_errors": 0,
                               "estimator_errors": 0, "records": 0}  # fmt: skip
    unplaced: dict[str, int] = {}
    tables = read_chunks(pf, columns, batch_size, src)
    row = 0
    for d in decoded_chunks(le, tables, DEFAULT_HALF_WINDOW):
        n = d.n
        good = np.flatnonzero(d.slot >= 0)  # records the decoder accepts
        arrays, slot_good = layout.fill(d.records.select(good), d.n)
        slot = np.full(len(d.records), -1, np.int64)
        slot[good] = slot_good
        # per frame: its records (the records are in frame order)
        bounds = np.searchsorted(d.records.frame, np.arange(d.n + 1))
        for i in good[slot_good < 0]:  # records the decoder accepts, with no free slot
            key = f"{d.records.links[i]}:{d.records.kinds[i]}"
            unplaced[key] = unplaced.get(key, 0) + 1
        details = d.issues.details().to_pylist()
        per_frame = {k: v for k, v in arrays.items() if k in takes}
        if "tau_measured" in takes and d.tau is not None:
            per_frame["tau_measured"] = d.tau[:, perm]
        for key, v in d.base.items():
            if key in takes:
                per_frame[key] = v
        q, qd, qdd = (x[:, perm] for x in (d.q, d.qd, d.qdd))
        ft = np.stack([d.ft[s] for s in rt.sensor_names], 1)  # (n, S, 6)
        for i in range(n):
            inputs = {k: v[i] for k, v in per_frame.items()}
            if rt.extra:
                inputs["extra"] = {c: float(d.extra[c][i]) for c in rt.extra}
            if d.issues.code[i] & UNUSABLE_BITS:
                estimate: dict[str, Any] = {"error": f"log: {details[i]}"}
                summary["log_errors"] += 1
            else:
                try:
                    estimate = estimator.estimate(q[i], qd[i], qdd[i], ft[i], inputs, int(d.t[i]))
                except ModelMismatchError:
                    raise
                except Exception as exc:  # noqa: BLE001 - as the live loop: one frame's error
                    summary["estimator_errors"] += 1
                    estimate = {"error": f"{type(exc).__name__}: {exc}"}
            if log is not None:
                log.append(int(d.t[i]), ft[i].reshape(-1), estimate.get("bias"))
            s = slot[bounds[i] : bounds[i + 1]]
            record = {"t_ns": int(d.t[i]), "row": row + i, "ft": ft[i], "estimate": estimate,
                      "record_slots": [int(k) if k >= 0 else None for k in s]}  # fmt: skip
            if details[i] is not None:
                record["log_issues"] = details[i]
            record = _jsonable(record)
            for pub in publishers:
                pub.publish(record)
            if on_record is not None:
                on_record(record)
            summary["published"] += 1
        summary["records"] += int(bounds[n])
        row += n
    summary["frames"] = row
    summary["records_without_slot"] = unplaced
    summary["sensors"] = list(rt.sensor_names)
    summary["derived"] = list(le.derived)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary
