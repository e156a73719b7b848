"""``--engine ray``: the same per-chunk estimation (:class:`LogEstimator`) through Ray Data.

``ray.data.read_parquet`` -> ``map_batches`` with a callable class (one model and estimator per
actor, ``batch_format="pyarrow"``) -> ``write_parquet`` into ``OUT.partial/``; the parts are then
merged in time order into ``OUT`` with the output schema and metadata, as the local engine does.
Needs ``qd`` and ``qdd`` in the log: derivatives from ``q`` need neighbouring frames across
blocks, which only the local engine carries. There is no ``--resume`` (Ray retries failed tasks
itself; an interrupted run leaves only ``OUT.partial/``). A residual checkpoint (``--residual``)
must be stateless (MLP): blocks run in parallel and in any order, so a recurrent (GRU) residual,
which needs every frame in time order, is refused; use the local engine for it.

On a small machine limit the actors (``actors``, ``actor_cpus``) so that read tasks still get a
CPU: with every CPU held by actors the pipeline stalls.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.logs.pipeline import (
    LogError,
    LogEstimator,
    expand_inputs,
    load_residual,
    merge_parts,
    output_paths,
    prepare,
    resolve_device,
)
from torchcontact.model import RobotModel

__all__ = ["estimate_file_ray", "estimate_files_ray"]


class _EstimateBatches:
    """Ray Data callable class: builds the model once per actor, estimates each batch."""

    def __init__(
        self,
        robot: str,
        joint_names: Sequence[str],
        sensors: Sequence[str],
        contact_fields: Sequence[tuple[str, Any]],
        device: str,
        dtype: str,
        threads: int,
        residual: str | None = None,
    ) -> None:
        if threads:
            torch.set_num_threads(threads)
        model = RobotModel.from_urdf(robot, dtype=getattr(torch, dtype), device=device)
        res = None if residual is None else load_residual(residual, model)
        self.le = LogEstimator(model, joint_names, sensors, contact_fields, robot, (), res)

    def __call__(self, batch: Any) -> Any:
        return self.le.process(batch)


def _ensure_ray(num_cpus: int | None) -> Any:
    import ray

    if not ray.is_initialized():
        # workers import the same torchcontact as this process
        root = str(Path(__file__).resolve().parents[2])
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            log_to_driver=False,
            runtime_env={"env_vars": {"PYTHONPATH": path}},
        )
    return ray


def estimate_file_ray(
    path: str | Path,
    robot: str | Path,
    out: str | Path,
    *,
    sensors: Sequence[str] | None = None,
    batch_size: int = 8192,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    actors: int = 1,
    actor_cpus: float = 1.0,
    threads: int = 1,
    num_cpus: int | None = None,
    residual: str | Path | None = None,
) -> dict:
    """Estimate a log with Ray Data; same rows as :func:`torchcontact.logs.estimate_file`.

    Args:
        path: input log (with ``qd`` and ``qdd``).
        robot: URDF path.
        out: output Parquet file.
        sensors: sensors to use (default: those with a column).
        batch_size: frames per ``map_batches`` batch.
        device: ``auto``, ``cpu`` or ``cuda`` (``cuda`` asks Ray for one GPU per actor).
        dtype: computation dtype.
        actors: actor pool size.
        actor_cpus: CPUs reserved per actor (keep some for the read tasks).
        threads: torch threads per actor.
        num_cpus: CPUs of a local Ray instance started here (default: all).
        residual: stateless (MLP) residual checkpoint directory, as :func:`estimate_file`; each
            actor loads it once.

    Returns:
        Summary dict as :func:`estimate_file`.

    Raises:
        LogError: as :func:`estimate_file`, a log without ``qd``/``qdd``, or a recurrent (GRU)
            residual.
    """
    t0 = time.perf_counter()
    device = resolve_device(device)
    model = RobotModel.from_urdf(robot, dtype=dtype)
    res = None if residual is None else load_residual(residual, model)
    if res is not None and res.recurrent:
        raise LogError(
            f"{path}: --engine ray cannot use a recurrent (GRU) residual (blocks run in any"
            " order); use --engine local"
        )
    pf, le, columns = prepare(path, model, sensors, res)
    if le.derived:
        raise LogError(
            f"{path}: --engine ray needs qd and qdd columns (missing {list(le.derived)});"
            " the local engine derives them from q"
        )
    ray = _ensure_ray(num_cpus)
    out = Path(out)
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    # Ray Data may reorder blocks between operators unless told not to: keep the input's row order
    # (the output contract is the local engine's rows, in order). The dataset captures the
    # context when it is created, so set it first; the caller's setting is restored at the end.
    options = ray.data.DataContext.get_current().execution_options
    preserve = options.preserve_order
    options.preserve_order = True
    ds = ray.data.read_parquet(str(Path(path).resolve())).select_columns(columns)
    ds = ds.map_batches(
        _EstimateBatches,
        fn_constructor_kwargs=dict(
            robot=str(robot),
            joint_names=list(le.input_joint_names),
            sensors=list(le.sensors),
            contact_fields=list(le.contact_fields),
            device=device,
            dtype=str(dtype).removeprefix("torch."),
            threads=threads,
            residual=None if res is None else res.source,
        ),
        batch_format="pyarrow",
        batch_size=batch_size,
        concurrency=actors,
        num_cpus=actor_cpus,
        num_gpus=1 if device == "cuda" else 0,
    )
    try:
        ds.write_parquet(str(partial.resolve()))
    finally:
        options.preserve_order = preserve
    parts = sorted(partial.glob("*.parquet"))
    schema = le.output_schema()
    # blocks may finish in any order: order the parts by time, rows are time-ordered inside
    import pyarrow.parquet as pq

    times = {p: pq.read_table(p, columns=["t_ns"]).column("t_ns").to_numpy() for p in parts}
    parts = sorted(
        parts, key=lambda p: int(times[p][0]) if len(times[p]) else np.iinfo(np.int64).max
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    t_all = np.concatenate([times[p] for p in parts]) if parts else np.zeros(0, np.int64)
    if np.all(np.diff(t_all) >= 0):
        rows = merge_parts(parts, out, schema)  # streamed: parts are in time order already
    else:
        # Ray reordered rows inside the parts despite preserve_order (seen with Ray 2.60 on a
        # 2-CPU machine): restore the input's time order in memory, stable for equal stamps
        import pyarrow as pa

        table = pa.concat_tables([pq.read_table(p).cast(schema) for p in parts])
        table = table.take(np.argsort(t_all, kind="stable"))
        tmp = out.with_name(out.name + ".tmp")
        pq.write_table(table, tmp)
        tmp.replace(out)
        rows = table.num_rows
    shutil.rmtree(partial)
    seconds = time.perf_counter() - t0
    return {
        "input": str(path),
        "output": str(out),
        "frames": rows,
        "processed_now": rows,
        "seconds": round(seconds, 3),
        "frames_per_s": round(rows / max(seconds, 1e-9), 1),
        "sensors": list(le.sensors),
        "derived": [],
        "resumed_chunks": 0,
        "engine": "ray",
    }


def estimate_files_ray(
    inputs: Sequence[str | Path], robot: str | Path, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file_ray` over files, folders or globs."""
    files = expand_inputs(inputs)
    return [
        estimate_file_ray(f, robot, o, **kwargs)
        for f, o in zip(files, output_paths(files, out), strict=True)
    ]
