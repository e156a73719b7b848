"""Write simulated logs (:func:`torchcontact.simulation.simulate`) in the log format.

The true contact forces are kept in the contact struct field ``true_force`` (3 float64, link frame,
N) and carried unchanged into the estimator's output, where :mod:`torchcontact.logs.plot` draws
them next to the estimates. Contacts are pure forces (kind ``force``) on skin frames.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.logs.format import fixed_list, ft_column, input_schema
from torchcontact.model import RobotModel
from torchcontact.simulation import SimulatedLog, UnmodeledEffects, simulate

__all__ = ["simulated_table", "write_simulated_log"]


def _contact_extra() -> list[tuple[str, Any]]:
    import pyarrow as pa

    return [("true_force", pa.list_(pa.float64(), 3))]


def simulated_table(log: SimulatedLog, *, derivatives: bool = True, t0_ns: int = 0) -> Any:
    """A pyarrow table in the log format from a :class:`SimulatedLog`.

    Args:
        log: simulated columns.
        derivatives: write ``qd`` and ``qdd`` (False: only ``q``, the pipeline derives them).
        t0_ns: added to ``t_ns``.

    Returns:
        Table with ``t_ns, q[, qd, qdd], ft.<sensor>, contacts, temperature``.
    """
    import pyarrow as pa

    from torchcontact.logs.format import contact_struct_type

    N, K = log.contact_link.shape
    schema = input_schema(
        log.joint_names,
        [log.sensor],
        derivatives=derivatives,
        contact_extra=_contact_extra(),
        extra=[("temperature", pa.float64())],
    )
    on = log.contact_link >= 0  # (N, K), flattened in (frame, slot) order
    M = int(on.sum())
    names = np.asarray(log.links, dtype=object)
    ctype = contact_struct_type(_contact_extra())
    struct = pa.StructArray.from_arrays(
        [
            pa.array(names[log.contact_link[on]].tolist(), pa.string()),
            pa.array(["force"] * M, pa.string()),
            fixed_list(log.contact_position[on]),
            pa.nulls(M, pa.list_(pa.float64(), 3)),
            pa.nulls(M, pa.list_(pa.float64(), 6)),
            fixed_list(log.contact_force[on]),
        ],
        fields=list(ctype),
    )
    offsets = np.r_[0, np.cumsum(on.sum(1))].astype(np.int32)
    cols: dict[str, Any] = {"t_ns": pa.array(log.t_ns + t0_ns, pa.int64()), "q": fixed_list(log.q)}
    if derivatives:
        cols["qd"], cols["qdd"] = fixed_list(log.qd), fixed_list(log.qdd)
    cols[ft_column(log.sensor)] = fixed_list(log.ft)
    cols["contacts"] = pa.ListArray.from_arrays(pa.array(offsets), struct)
    cols["temperature"] = pa.array(log.temperature, pa.float64())
    return pa.table(cols, schema=schema)


def write_simulated_log(
    model: RobotModel,
    frames: int,
    out: str | Path,
    *,
    seed: int = 0,
    effects: UnmodeledEffects | None = None,
    derivatives: bool = True,
    chunk: int = 200_000,
    temperature: bool = True,
    **kwargs: Any,
) -> Path:
    """Simulate ``frames`` frames and write them as a Parquet log, streamed in chunks.

    Logs longer than ``chunk`` are written as independent simulated segments (seed
    ``seed + i``) with continuous time stamps; the joint trajectory jumps between segments, so
    derive nothing across them (``derivatives=True`` writes the exact ``qd``/``qdd``).

    Args:
        model: the robot.
        frames: number of frames.
        out: output file.
        seed: random seed.
        effects: unmodeled effects (offset, drift, cable, payload, noise).
        derivatives: write ``qd`` and ``qdd``.
        chunk: frames simulated per segment (memory is flat in ``frames``).
        temperature: keep the ``temperature`` column.
        **kwargs: passed to :func:`torchcontact.simulation.simulate`.

    Returns:
        The output path.
    """
    import pyarrow.parquet as pq

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    writer = None
    t0 = 0
    for i, start in enumerate(range(0, max(frames, 1), chunk)):
        n = min(chunk, frames - start)
        if n <= 0:
            break
        log = simulate(model, n, seed=seed + i, effects=effects, **kwargs)
        tab = simulated_table(log, derivatives=derivatives, t0_ns=t0)
        if not temperature:
            tab = tab.drop_columns(["temperature"])
        t0 = int(tab.column("t_ns")[-1].as_py()) + int(log.t_ns[1] - log.t_ns[0] if n > 1 else 0)
        if writer is None:
            writer = pq.ParquetWriter(tmp, tab.schema)
        writer.write_table(tab, row_group_size=65536)
    if writer is not None:
        writer.close()
    tmp.replace(out)
    return out
