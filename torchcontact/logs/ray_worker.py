"""What the Ray engine's worker processes run: a run's setup, the model, the units.

The driver (:mod:`torchcontact.logs.ray_engine`) imports neither torch nor this module: it sends
these functions to Ray's worker processes by name (thin wrappers there import this module in the
worker), and a worker process keeps what it built (the model, the estimator, the opened log)
from one task to the next:

- :func:`setup_run`: the run's model, the log's scan, its F/T noise and the config of its
  units, on one worker (the driver's ``import torch`` was 2 s of its start-up on 2 cores and
  the largest part of it on 16, where it delayed every unit);
- :func:`warm_worker`: a worker process builds the model before its first unit;
- :func:`estimate_units`: a unit's rows, read, decoded, estimated and journalled as a part.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.errors import LogError
from torchcontact.identity import RobotIdentity
from torchcontact.logs._alloc import keep_freed_memory
from torchcontact.logs.chunks import (
    LogEstimator,
    LogLocalize,
    decoded_chunks,
    estimate_stream,
)
from torchcontact.logs.decode import stamps_and_positions
from torchcontact.logs.format import open_log, write_encoded_part
from torchcontact.logs.pipeline import (
    kernel_backend,
    load_residual,
    load_robot,
    localize_tally,
    log_noise,
    log_summary,
    prepare,
    recorded_noise,
    resolve_device,
    run_ident,
    run_localize,
)
from torchcontact.logs.ray_engine import plan_units
from torchcontact.logs.run import background
from torchcontact.robots import RobotSpec, ft_sensor_specs

__all__ = ["estimate_units", "setup_run", "unit_config", "warm_worker", "worker_args"]


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


#: Per worker process: (path, robot, LogEstimator arguments, job) -> (LogEstimator, file).
#: Ray reuses worker processes across tasks, so the model is built once per process and config.
_WORKER_CACHE: dict[str, tuple[LogEstimator, Any]] = {}
#: Per worker process: the robot model of (robot, dtype, device), built by :func:`warm_worker`
#: ahead of the units, or by the first unit.
_MODEL_CACHE: dict[str, Any] = {}


def _worker_threads(job: dict) -> None:
    """Size this worker process's threads and set its allocators as the CLI's.

    torch's threads to ``threads``, pyarrow's CPU pool to ``cpus`` (the CPUs Ray reserved for a
    task; pyarrow would otherwise start one thread per core of the node in every worker process:
    16 processes of 16 threads on 16 cores), the allocators by
    :func:`~torchcontact.logs._alloc.keep_freed_memory`.
    """
    import pyarrow as pa

    keep_freed_memory()  # as the CLI's process (its environment part: the runtime's)
    if job["threads"]:
        torch.set_num_threads(job["threads"])
    pa.set_cpu_count(max(1, int(job.get("cpus", 1))))


def _worker_model(robot: dict, job: dict) -> tuple[RobotSpec, Any]:
    """The robot's spec and model in this worker process (built once per robot, dtype, device)."""
    key = json.dumps([robot["robot"], robot["ft_sensors"], job["dtype"], job["device"]])
    spec = RobotSpec(robot["robot"], ft_sensor_specs(robot["ft_sensors"]))
    if key not in _MODEL_CACHE:
        _worker_threads(job)
        _MODEL_CACHE.clear()
        _MODEL_CACHE[key] = load_robot(spec, getattr(torch, job["dtype"]), job["device"])
    return spec, _MODEL_CACHE[key]


def warm_worker(robot: dict, job: dict) -> str | None:
    """Ray task sent as Ray starts: a worker process builds the robot model before any unit.

    It runs while one worker runs the run's setup (:func:`setup_run`), so that the process has
    imported torchcontact and built the model by the time its first unit arrives.

    Returns:
        None, or the error's text: a failure here is the first unit's to report (it builds the
        model again and raises), not this task's.
    """
    try:
        _worker_model(robot, job)
    except Exception as exc:  # noqa: BLE001 - reported by the unit that needs the model
        return f"{type(exc).__name__}: {exc}"
    return None


def _worker_state(path: str, robot: dict, le_args: dict, job: dict) -> tuple:
    key = json.dumps([path, robot, le_args, job], sort_keys=True, default=str)
    if key not in _WORKER_CACHE:
        _worker_threads(job)
        spec, model = _worker_model(robot, job)
        if model.identity.sha256 != robot["identity"]:  # another URDF on this node
            driver = RobotIdentity.from_json(robot["identity_entries"])
            raise LogError(
                f"the Ray worker on {os.uname().nodename} built robot {spec} unlike the"
                f" driver's: {driver.difference(model.identity) or 'another identity'}"
            )
        res = None if job["residual"] is None else load_residual(job["residual"], model)
        args = dict(le_args)
        layout = args.pop("layout")
        opts = args.pop("localize")
        if opts is not None:  # the meshes loaded once per worker process and config
            opts = dict(opts)
            args["localize"] = LogLocalize.load(model, spec, opts.pop("links"), **opts)
        le = LogEstimator(model, residual=res, **args)
        if layout is not None:
            from torchcontact.contacts import SlotLayout

            le.layout = le.decoder.layout = SlotLayout(*layout)
        le.decoder.whole_log_segment = job["whole_log_segment"]
        _WORKER_CACHE.clear()
        _WORKER_CACHE[key] = (le, open_log(path))
    return _WORKER_CACHE[key]


def estimate_units(units: Sequence[int], config: tuple) -> dict[str, Any]:
    """Ray task: estimate ``units`` and journal them; their row counts and this node's id."""
    path, robot, le_args, job = config
    le, pf = _worker_state(path, robot, le_args, job)
    h, derive = job["half_window"], bool(le.derived)
    n, bs = pf.metadata.num_rows, job["batch_size"]
    rows = []
    for u in units:
        start, stop = job["units"][int(u)]
        # context across the unit's edges, as the local engine has: 2 h frames each side for
        # derived qd/qdd, else the two stamps before (a time segment may start at the unit)
        c = 2 * h if derive else 2
        lo, hi = max(0, start - c), min(n, stop + 2 * h) if derive else stop
        tab = _read_unit(pf, job["columns"], lo, hi, path)
        unit = tab.slice(start - lo, stop - start)
        before = after = None
        width = len(le.input_joint_names)  # the log's joints (le.perm: the model's)
        if start > lo:
            before = stamps_and_positions(tab.slice(0, start - lo), le.perm, width, path, lo)
        if derive and hi > stop:
            after = stamps_and_positions(tab.slice(stop - lo), le.perm, width, path, stop)
        chunks = (unit.slice(i, bs) for i in range(0, unit.num_rows, bs))
        decoded = decoded_chunks(le, chunks, h, start, before, after)
        part = Path(job["partial"]) / f"part-{int(u):08d}.parquet"
        # a unit's first frame starts cold: units run in parallel and in any order; the part is
        # encoded here, in parallel, and the driver appends its bytes as they are
        if job["cpus"] < 2:  # the one CPU Ray reserved: decode, estimate, encode in turn
            write_encoded_part(estimate_stream(le, decoded, None, job["backend"]), part,
                               job["schema"])  # fmt: skip
        else:  # as the local engine: decoding on a reader thread, the estimate on another, the
            # encoding here (pyarrow and the kernels release the GIL)
            with (
                background(decoded, name="reader") as ready,
                background(
                    estimate_stream(le, iter(ready), None, job["backend"]), name="est"
                ) as tabs,  # fmt: skip
            ):
                write_encoded_part(iter(tabs), part, job["schema"])
        rows.append(stop - start)
    import ray

    return {"units": [int(u) for u in units], "rows": rows,
            "node": ray.get_runtime_context().get_node_id()}  # fmt: skip


def worker_args(le: LogEstimator, path: str | Path) -> dict[str, Any]:
    """The :class:`LogEstimator` arguments a worker process rebuilds it from (picklable).

    The layout is the driver's (the log's scan); a localization travels as its options, and each
    worker process loads the meshes from the robot's URDF once (:func:`_worker_state`).
    """
    return {
        "input_joint_names": list(le.input_joint_names),
        "sensors": list(le.sensors),
        "contact_fields": list(le.contact_fields),
        "source": str(path),
        "derived": list(le.derived),
        "velocity_margin": le.velocity_margin,
        "ft_range": {s: v.tolist() for s, v in le._ft_range.items()},
        "constraints": le.constraints,
        "noise": le.noise,
        "step_ns": le.step_ns,
        "layout": None if le.layout is None else (le.layout.links, le.layout.kinds),
        "localize": None if le.localize is None else le.localize.options(),
    }


def robot_arg(robot: RobotSpec, model: Any) -> dict[str, Any]:
    """The robot as the driver has it, for the workers (:func:`_worker_state`).

    The URDF with the declared ``--ft-sensor`` sensors, and the model's identity, which each
    worker's model must have.
    """
    return {
        "robot": robot.robot,
        "ft_sensors": [str(s) for s in robot.ft_sensors],
        "identity": model.identity.sha256,
        "identity_entries": model.identity.to_json(),
    }


def unit_config(
    path: str | Path,
    robot: RobotSpec,
    model: Any,
    le: LogEstimator,
    units: Sequence[tuple[int, int]],
    columns: list[str],
    partial: Path,
    res: Any,
    options: dict,
) -> tuple:
    """The one argument every :func:`_estimate_units` task of a run gets (picklable).

    Args:
        path: the log.
        robot: the driver's robot spec.
        model: its model (each worker checks its own model's identity against it).
        le: the driver's estimator (its arguments, layout, noise and output schema).
        units: the run's units, ``(start, stop)`` rows each (:func:`plan_units`).
        columns: the log's columns to read.
        partial: the folder of the run's parts (``OUT.partial``).
        res: the residual correction, or None.
        options: ``batch_size``, ``half_window``, ``backend``, ``threads``, ``device``,
            ``dtype`` and ``cpus`` (the CPUs Ray reserves per task).
    """
    job = {
        "units": list(units),
        "columns": columns,
        "partial": str(Path(partial).resolve()),
        "residual": None if res is None else res.source,
        "whole_log_segment": le.decoder.whole_log_segment,
        "schema": le.output_schema(),  # the driver's: every part has the output's schema
        **options,
    }
    return str(Path(path).resolve()), robot_arg(robot, model), worker_args(le, path), job


def setup_run(request: Mapping[str, Any]) -> dict[str, Any]:
    """A run's setup on a Ray worker: the model, the log's scan and noise, the units' config.

    The driver sends it to one worker process (a pool actor, or a task with the units'
    resources) once Ray has started, and imports no torch itself; that process keeps the model
    it built for its units.

    Args:
        request: what the driver knows: ``path`` (the log, absolute), ``robot`` (``robot`` and
            ``ft_sensors`` of its spec), ``job`` (the units' ``threads``, ``device``,
            ``dtype``, ``cpus``), ``partial`` (the run's ``OUT.partial``, absolute),
            ``previous`` (the interrupted run's record on a resume, else None),
            ``batch_size``, ``half_window``, ``task_rows``, and the options of
            :func:`~torchcontact.logs.ray_engine.estimate_file_ray` that shape the estimate:
            ``sensors``, ``residual`` (absolute), ``velocity_margin``, ``ft_range``,
            ``constraints``, ``ft_noise``, ``unweighted``, ``localize``.

    Returns:
        Values the driver reads without torch: ``ident`` (the run's identity,
        :func:`~torchcontact.logs.pipeline.run_ident`), ``units`` (:func:`plan_units`),
        ``schema`` (the output's), ``summary``
        (:func:`~torchcontact.logs.pipeline.log_summary`), ``localize``
        (:func:`~torchcontact.logs.pipeline.localize_tally`), ``config`` (the argument of
        every :func:`estimate_units`; its ``robot`` holds the model's identity).

    Raises:
        InputError, LogError, URDFError: as :func:`~torchcontact.logs.estimate_file` (the
            driver raises them as they are), or a recurrent (GRU) residual, or ``cuda`` on a
            worker without CUDA.
    """
    path, job = request["path"], dict(request["job"])
    job["device"] = resolve_device(job["device"])
    spec, model = _worker_model(request["robot"], job)
    res = None if request["residual"] is None else load_residual(request["residual"], model)
    if res is not None and res.recurrent:
        raise LogError(
            f"{path}: --engine ray cannot use a recurrent (GRU) residual (units run in any"
            " order); use --engine local"
        )
    localize = run_localize(request["localize"], model, spec)
    h, batch_size, task_rows = request["half_window"], request["batch_size"], request["task_rows"]
    # the scan on the node's cores, as a driver's ran (the other workers wait for this setup);
    # then pyarrow's threads as the units' CPUs again
    import pyarrow as pa

    cpus = pa.cpu_count()
    pa.set_cpu_count(os.cpu_count() or 1)
    try:
        pf, le, columns, scan = prepare(path, model, request["sensors"], res,
                                        request["velocity_margin"], request["ft_range"],
                                        request["constraints"], localize=localize)  # fmt: skip
        log_noise(pf, le, columns, h, request["ft_noise"], request["unweighted"], path)
    finally:
        pa.set_cpu_count(cpus)
    recorded_noise(le, request["previous"])
    ident = run_ident(path, model, le, engine="ray", dtype=job["dtype"], half_window=h,
                      batch_size=batch_size, task_rows=task_rows)  # fmt: skip
    total = pf.metadata.num_rows
    units = plan_units(total, task_rows)
    options = dict(batch_size=batch_size, half_window=h,
                   backend=kernel_backend(total, job["device"], shared=True), **job)  # fmt: skip
    config = unit_config(path, spec, model, le, units, columns, request["partial"], res, options)
    return {"ident": ident, "units": units, "schema": le.output_schema(),
            "summary": log_summary(le, scan), "localize": localize_tally(le),
            "config": config}  # fmt: skip
