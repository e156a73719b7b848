"""Write simulated logs (:func:`torchcontact.simulation.simulate`) in the log format.

The true contact forces are kept in the contact struct field ``true_force`` (3 float64, link frame,
N) and carried unchanged into the estimator's output, where :mod:`torchcontact.logs.plot` draws
them next to the estimates. Contacts are pure forces (kind ``force``) on skin frames; their
``normal`` is the frame's +z (the simulated patches lie in its xy plane and the forces push
within 0.62 rad of -z), for ``estimate --constraints``. Contacts sampled on collision meshes
(``surface=``) carry the mesh's outward normal.

A log *without skin* (``skin=False``, ``simulate --no-skin``) has the same F/T readings but an
empty ``contacts`` list in every frame, as a robot without tactile skin records; the truth moves
to the ``true_contacts`` column (same struct), for ``estimate --localize``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.contacts import ContactRecords
from torchcontact.errors import InputError
from torchcontact.logs.format import (
    META_URDF_SHA256,
    LogWriter,
    contacts_column,
    fixed_list,
    ft_column,
    input_schema,
    robot_metadata,
)
from torchcontact.model import RobotModel
from torchcontact.simulation import SimulatedLog, UnmodeledEffects, simulate

__all__ = ["simulated_table", "write_simulated_log"]


def _contact_extra() -> list[tuple[str, Any]]:
    import pyarrow as pa

    return [("true_force", pa.list_(pa.float64(), 3))]


def simulated_table(
    log: SimulatedLog,
    *,
    derivatives: bool = True,
    t0_ns: int = 0,
    skin: bool = True,
    metadata: Mapping[bytes, bytes | str] | None = None,
) -> Any:
    """A pyarrow table in the log format from a :class:`SimulatedLog`.

    Args:
        log: simulated columns.
        derivatives: write ``qd`` and ``qdd`` (False: only ``q``, the pipeline derives them).
        t0_ns: added to ``t_ns``.
        skin: the contacts go to ``contacts`` (True) or, as for a robot without skin, to
            ``true_contacts`` with ``contacts`` empty (False).
        metadata: further schema metadata (the robot: :func:`~torchcontact.logs.format.
            robot_metadata`).

    Returns:
        Table with ``t_ns, q[, qd, qdd], ft.<sensor>, contacts, temperature`` (and
        ``true_contacts`` without skin).
    """
    import pyarrow as pa

    N, K = log.contact_link.shape
    schema = input_schema(
        log.joint_names,
        [log.sensor],
        derivatives=derivatives,
        contact_extra=_contact_extra(),
        extra=[("temperature", pa.float64())],
        metadata=metadata,
        cone=True,
    )
    ctype = schema.field("contacts").type.value_type
    if not skin:
        schema = schema.append(pa.field("true_contacts", pa.list_(ctype)))
    f, k = np.nonzero(log.contact_link >= 0)  # records in (frame, slot) order
    normals = (np.tile([0.0, 0.0, 1.0], (len(f), 1)) if log.contact_normal is None
               else log.contact_normal[f, k])  # fmt: skip
    records = ContactRecords(
        f,
        np.asarray(log.links, dtype=object)[log.contact_link[f, k]],
        ["force"] * len(f),
        log.contact_position[f, k],
        normals=normals,
    )
    truth = contacts_column(records, N, {"true_force": log.contact_force[f, k]}, ctype)
    contacts = truth
    if not skin:
        contacts = contacts_column(
            records.select(np.zeros(len(f), bool)), N, {"true_force": np.zeros((0, 3))}, ctype
        )
    cols: dict[str, Any] = {"t_ns": pa.array(log.t_ns + t0_ns, pa.int64()), "q": fixed_list(log.q)}
    if derivatives:
        cols["qd"], cols["qdd"] = fixed_list(log.qd), fixed_list(log.qdd)
    cols[ft_column(log.sensor)] = fixed_list(log.ft)
    cols["contacts"] = contacts
    cols["temperature"] = pa.array(log.temperature, pa.float64())
    if not skin:
        cols["true_contacts"] = truth
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
    progress: bool = False,
    skin: bool = True,
    robot: str | None = None,
    ft_sensors: Sequence[str] = (),
    **kwargs: Any,
) -> Path:
    """Simulate ``frames`` frames and write them as a Parquet log, streamed in chunks.

    Logs longer than ``chunk`` are written as independent simulated segments (seed
    ``seed + i``) with continuous time stamps; the joint trajectory jumps between segments, so
    derive nothing across them (``derivatives=True`` writes the exact ``qd``/``qdd``).

    Args:
        model: the robot.
        frames: number of frames (>= 1).
        out: output file.
        seed: random seed.
        effects: unmodeled effects (offset, drift, cable, payload, noise).
        derivatives: write ``qd`` and ``qdd``.
        chunk: frames simulated per segment (memory is flat in ``frames``).
        temperature: keep the ``temperature`` column.
        progress: show a progress bar (per segment).
        skin: False writes a log without skin contacts (the truth in ``true_contacts``).
        robot: the robot argument ``model`` was built from (a name or an absolute URDF path),
            recorded in the log's metadata with its URDF sha256 (:data:`~torchcontact.logs.format.
            META_ROBOT`) so that ``estimate`` finds it; None records the sha256 only.
        ft_sensors: the ``--ft-sensor`` specs ``model`` was built with, recorded with ``robot``.
        **kwargs: passed to :func:`torchcontact.simulation.simulate` (``sensor``, ``links``,
            ``max_contacts``, ``surface``, ...).

    Returns:
        The output path.

    Raises:
        InputError: ``frames`` or ``chunk`` < 1.
    """
    from tqdm import tqdm

    if not isinstance(frames, (int, np.integer)) or frames < 1:
        raise InputError(f"--frames must be an integer >= 1, got {frames!r}")
    if chunk < 1:
        raise InputError(f"chunk must be >= 1, got {chunk}")
    out = Path(out)
    meta = {META_URDF_SHA256: model.urdf_sha256}
    if robot is not None:
        meta = robot_metadata(robot, model.urdf_sha256, ft_sensors)
    t0 = 0
    writer = None
    bar = tqdm(total=frames, unit="frames", desc="simulate", disable=not progress)
    try:
        for i, start in enumerate(range(0, frames, chunk)):
            n = min(chunk, frames - start)
            log = simulate(model, n, seed=seed + i, effects=effects, **kwargs)
            tab = simulated_table(log, derivatives=derivatives, t0_ns=t0, skin=skin, metadata=meta)
            if not temperature:
                tab = tab.drop_columns(["temperature"])
            step = int(log.t_ns[1] - log.t_ns[0]) if n > 1 else 0
            t0 = int(tab.column("t_ns")[-1].as_py()) + step
            writer = writer or LogWriter(out, tab.schema)
            writer.write(tab, row_group_size=65536)
            bar.update(n)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    finally:
        bar.close()
    writer.close()  # type: ignore[union-attr]  (frames >= 1: at least one segment)
    return out
