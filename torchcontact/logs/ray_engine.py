"""``--engine ray``: the same per-chunk estimation (:class:`LogEstimator`) on a Ray cluster.

The log is cut into *units* of ``task_rows`` consecutive frames (unit ``u`` holds rows
``[u * task_rows, (u + 1) * task_rows)``, so every row's index is known). A Ray Data
dataset of unit indices goes through ``map_batches`` (Ray tasks; each worker process builds the
model and estimator once): a task reads its unit's rows straight from the Parquet file, estimates
them in chunks of ``batch_size`` and writes ``OUT.partial/part-<u>.arrow`` (temporary name,
atomic rename). The driver shows a progress bar as units finish and then merges the parts in unit
order, which is the row order: no sort, and memory does not grow with the log.

As the local engine: ``qd``/``qdd`` missing from the log are derived with ``h`` frames of context
read across unit edges, so the rows equal the local engine's; ``--resume`` keeps the parts an
interrupted run wrote (``OUT.progress.json`` records the run); the summary has the same keys. A
residual checkpoint must be stateless (MLP): units run in parallel and in any order, so a recurrent
(GRU) residual, which needs every frame in time order, is refused.

``workers`` tasks run at once, each holding ``worker_cpus`` CPUs.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.errors import LogError, TorchContactError
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
from torchcontact.logs.format import LogWriter, check_outputs, open_log, read_journal
from torchcontact.logs.pipeline import (
    DEFAULT_VELOCITY_MARGIN,
    LogEstimator,
    RunState,
    _ConeTally,
    chunks_with_derivatives,
    estimate_chunks,
    expand_inputs,
    load_residual,
    load_robot,
    output_paths,
    prepare,
    resolve_device,
    run_ident,
    summary,
    times_and_positions,
    write_part,
)

__all__ = ["estimate_file_ray", "estimate_files_ray", "plan_units"]


def plan_units(rows: int, task_rows: int) -> list[tuple[int, int]]:
    """Cut ``rows`` frames into units of ``task_rows`` consecutive frames (the last shorter).

    Example:
        >>> plan_units(250, 100)
        [(0, 100), (100, 200), (200, 250)]
    """
    return [(a, min(a + task_rows, rows)) for a in range(0, rows, task_rows)]


def _read_unit(pf: Any, columns: list[str], lo: int, hi: int, source: str) -> Any:
    """Rows ``[lo, hi)`` of the log: the row groups holding them are read, then sliced."""
    import pyarrow as pa

    sizes = [pf.metadata.row_group(g).num_rows for g in range(pf.num_row_groups)]
    bounds = np.cumsum([0, *sizes])
    groups = [g for g in range(len(sizes)) if bounds[g] < hi and bounds[g + 1] > lo]
    try:
        tab = pf.read_row_groups(groups, columns=columns)
    except (OSError, pa.ArrowException) as exc:
        raise LogError(f"{source}: corrupted data in rows {lo}-{hi - 1}: {exc}") from None
    return tab.slice(lo - int(bounds[groups[0]]), hi - lo)


#: Per worker process: (path, robot, LogEstimator arguments, job) -> (LogEstimator, file, schema).
#: Ray reuses worker processes across tasks, so the model is built once per process and config.
_WORKER_CACHE: dict[str, tuple[LogEstimator, Any, Any]] = {}


def _worker_state(path: str, robot: str, le_args: dict, job: dict) -> tuple:
    key = json.dumps([path, robot, le_args, job], sort_keys=True, default=str)
    if key not in _WORKER_CACHE:
        if job["threads"]:
            torch.set_num_threads(job["threads"])
        model = load_robot(robot, getattr(torch, job["dtype"]), job["device"])
        res = None if job["residual"] is None else load_residual(job["residual"], model)
        le = LogEstimator(model, residual=res, **le_args)
        _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = (le, open_log(path), le.output_schema())
    return _WORKER_CACHE[key]


def _estimate_units(batch: dict[str, np.ndarray], config: tuple) -> dict[str, np.ndarray]:
    """Ray Data task: estimate the units of ``batch["unit"]`` and write their parts."""
    path, robot, le_args, job = config
    le, pf, schema = _worker_state(path, robot, le_args, job)
    h, derive = job["half_window"], bool(le.derived)
    n, bs = pf.metadata.num_rows, job["batch_size"]
    rows, ok = [], []
    for u in batch["unit"]:
        start, stop = job["units"][int(u)]
        # h frames of context across the unit's edges, as the local engine has
        lo, hi = (max(0, start - h), min(n, stop + h)) if derive else (start, stop)
        tab = _read_unit(pf, job["columns"], lo, hi, path)
        unit = tab.slice(start - lo, stop - start)
        before = after = None
        width = len(le.input_joint_names)  # the log's joints (le.perm: the model's)
        if derive:
            before = times_and_positions(tab.slice(0, start - lo), le.perm, width)
            after = times_and_positions(tab.slice(stop - lo), le.perm, width)
        chunks = (unit.slice(i, bs) for i in range(0, unit.num_rows, bs))
        tables = estimate_chunks(
            le, chunks_with_derivatives(chunks, le.perm, derive, h, before, after, width)
        )
        part = Path(job["partial"]) / f"part-{int(u):08d}.arrow"
        n_rows, n_ok = write_part(part, tables)
        rows.append(n_rows)
        ok.append(n_ok)
    return {"unit": batch["unit"], "rows": np.array(rows), "ok": np.array(ok)}


def _ensure_ray(num_cpus: int | None) -> Any:
    import ray
    import ray.data

    # Ray's INFO/WARNING lines and Ray Data's progress bars would drown the run's one progress
    # bar: the console shows errors only (Ray Data's log file keeps everything)
    logging.getLogger("ray").setLevel(logging.ERROR)
    for handler in logging.getLogger("ray.data").handlers:
        if not isinstance(handler, logging.FileHandler) and "File" not in type(handler).__name__:
            handler.setLevel(logging.ERROR)
    if not ray.is_initialized():
        # workers import the same torchcontact as this process
        root = str(Path(__file__).resolve().parents[2])
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
        ray.init(
            num_cpus=num_cpus,
            include_dashboard=False,
            log_to_driver=False,
            logging_level=logging.ERROR,
            runtime_env={"env_vars": {"PYTHONPATH": path}},
        )
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    if hasattr(ctx, "print_on_execution_start"):
        ctx.print_on_execution_start = False
    return ray


def _user_error(exc: BaseException) -> BaseException:
    """The library error behind a Ray task failure (Ray wraps it), else ``exc`` itself."""
    seen = exc
    for _ in range(5):
        cause = getattr(seen, "cause", None) or seen.__cause__
        if isinstance(seen, TorchContactError) and not type(seen).__name__.startswith("RayTask"):
            return seen
        if isinstance(cause, TorchContactError):
            return type(cause)(str(cause))
        if cause is None:
            break
        seen = cause
    return exc


def _unit_dataset(
    ray: Any,
    todo: list[int],
    path: str | Path,
    robot: str | Path,
    le: LogEstimator,
    run: RunState,
    units: list[tuple[int, int]],
    columns: list[str],
    res: Any,
    workers: int,
    worker_cpus: float,
    options: dict,
) -> Any:
    """The Ray Data pipeline: unit indices -> ``_estimate_units`` tasks -> per-unit counts."""
    job = {
        "units": units,
        "columns": columns,
        "partial": str(run.partial.resolve()),
        "residual": None if res is None else res.source,
        **options,
    }
    le_args = {
        "input_joint_names": list(le.input_joint_names),
        "sensors": list(le.sensors),
        "contact_fields": list(le.contact_fields),
        "source": str(path),
        "derived": list(le.derived),
        "velocity_margin": le.velocity_margin,
        "ft_range": {s: v.tolist() for s, v in le._ft_range.items()},
        "constraints": le.constraints,
    }
    ds = ray.data.from_items([{"unit": u} for u in todo], override_num_blocks=len(todo))
    config = (str(Path(path).resolve()), str(Path(robot).resolve()), le_args, job)
    return ds.map_batches(
        _estimate_units,
        fn_kwargs={"config": config},
        batch_format="numpy",
        batch_size=1,
        compute=ray.data.TaskPoolStrategy(size=workers),
        num_cpus=worker_cpus,
        num_gpus=1 if options["device"].startswith("cuda") else 0,
    )


def estimate_file_ray(
    path: str | Path,
    robot: str | Path,
    out: str | Path,
    *,
    sensors: Sequence[str] | None = None,
    batch_size: int = 8192,
    task_rows: int | None = None,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    resume: bool = False,
    progress: bool | None = None,
    half_window: int = DEFAULT_HALF_WINDOW,
    workers: int = 1,
    worker_cpus: float = 1.0,
    threads: int = 1,
    num_cpus: int | None = None,
    residual: str | Path | None = None,
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: Any = None,
) -> dict:
    """Estimate a log with Ray; same rows and summary as :func:`torchcontact.logs.estimate_file`.

    Args:
        path: input log.
        robot: URDF path.
        out: output Parquet file.
        sensors: sensors to use (default: those with a column).
        batch_size: frames per estimator call inside a unit.
        task_rows: frames of a unit (one Ray task; default ``8 * batch_size``).
        device: ``auto``, ``cpu`` or ``cuda`` (``cuda`` asks Ray for one GPU per actor).
        dtype: computation dtype.
        resume: finish an interrupted Ray run from its parts.
        progress: show a progress bar (default: when stderr is a terminal).
        half_window: ``h`` of the Savitzky-Golay differentiator when ``qd``/``qdd`` are derived.
        workers: Ray tasks running at once (each estimates one unit at a time).
        worker_cpus: CPUs reserved per task.
        threads: torch threads per task.
        num_cpus: CPUs of a local Ray instance started here (default: all).
        residual: stateless (MLP) residual checkpoint directory, as :func:`estimate_file`; each
            worker process loads it once.
        velocity_margin: as :func:`estimate_file`.
        ft_range: as :func:`estimate_file`.
        constraints: as :func:`estimate_file` (warm starts run within a unit; a unit's first
            frame starts cold).

    Returns:
        Summary dict as :func:`estimate_file` (``engine`` is ``"ray"``, chunks count units).

    Raises:
        InputError: as :func:`estimate_file`, or ``workers`` < 1.
        LogError: as :func:`estimate_file`, or a recurrent (GRU) residual.
    """
    from tqdm import tqdm

    from torchcontact.logs.pipeline import _check_positive

    t0 = time.perf_counter()
    task_rows = 8 * batch_size if task_rows is None else task_rows
    _check_positive(
        batch_size=batch_size, half_window=half_window, workers=workers, task_rows=task_rows
    )
    out = Path(out)
    check_outputs([out, *RunState.side_paths(out)], [path, robot, residual])
    device = resolve_device(device)
    model = load_robot(robot, dtype)
    res = None if residual is None else load_residual(residual, model)
    if res is not None and res.recurrent:
        raise LogError(
            f"{path}: --engine ray cannot use a recurrent (GRU) residual (units run in any"
            " order); use --engine local"
        )
    pf, le, columns = prepare(path, model, sensors, res, velocity_margin, ft_range, constraints)
    total = pf.metadata.num_rows
    units = plan_units(total, task_rows)
    ident = run_ident(
        path,
        model,
        le,
        engine="ray",
        dtype=str(dtype),
        half_window=half_window,
        batch_size=batch_size,
        task_rows=task_rows,
    )
    run = RunState(out, *RunState.side_paths(out)[:2], ident)
    run.start(resume)
    todo = [u for u in range(len(units)) if u not in run.done]
    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=total, unit="frames", disable=not show, desc=f"{Path(path).name} (ray)")
    bar.update(total - sum(units[u][1] - units[u][0] for u in todo))
    counts = {"ok": 0, "bad": 0}
    writer = LogWriter(out, le.output_schema())  # the output, renamed into place when complete
    written = 0  # units written to the output: 0 .. written - 1, in order
    cones, now = _ConeTally(le), set(todo)

    def drain() -> None:
        """Write the units that are done and next in order (journal -> output)."""
        nonlocal written
        while written < len(units) and written in run.done:
            tab = read_journal(run.part(written))
            writer.write(tab)
            if written in now:
                cones.add(tab)
            written += 1

    try:
        drain()  # units journalled by an interrupted run
        if todo:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
                ray = _ensure_ray(num_cpus)
                ds = _unit_dataset(
                    ray, todo, path, robot, le, run, units, columns, res, workers, worker_cpus,
                    dict(batch_size=batch_size, half_window=half_window, threads=threads,
                         device=device, dtype=str(dtype).removeprefix("torch.")),
                )  # fmt: skip
                try:
                    batches = ds.iter_batches(
                        batch_size=1, batch_format="numpy", prefetch_batches=0
                    )
                    for b in batches:
                        for u, n, k in zip(b["unit"], b["rows"], b["ok"], strict=True):
                            run.done.add(int(u))
                            counts["ok"] += int(k)
                            counts["bad"] += int(n - k)
                            bar.update(int(n))
                        run.record()
                        drain()  # overlaps writing the output with the estimation
                except Exception as exc:
                    err = _user_error(exc)
                    if isinstance(err, TorchContactError):
                        raise type(err)(
                            f"{err}; {len(run.done)} of {len(units)} units are estimated in"
                            f" {run.partial}"
                        ) from None
                    raise
        if written != len(units):
            raise LogError(f"{out}: units {written}.. missing; delete {run.partial} and rerun")
        rows = writer.rows
        writer.close()
    except BaseException:
        writer.abort()
        raise
    finally:
        bar.close()
    run.clean()
    return summary(
        path,
        out,
        rows,
        counts,
        t0,
        le,
        resumed_chunks=len(units) - len(todo),
        chunks=len(units),
        engine="ray",
        **cones.summary(),
    )


def estimate_files_ray(
    inputs: Sequence[str | Path], robot: str | Path, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file_ray` over files, folders or globs (``out`` a folder for several)."""
    files = expand_inputs(inputs)
    outs = output_paths(files, out)
    for o in outs:
        check_outputs([o, *RunState.side_paths(o)], [*files, robot, kwargs.get("residual")])
    return [estimate_file_ray(f, robot, o, **kwargs) for f, o in zip(files, outs, strict=True)]
