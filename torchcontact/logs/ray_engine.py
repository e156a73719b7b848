"""``--engine ray``: the same per-chunk estimate (:class:`LogEstimator`) on a Ray cluster.

The log is cut into *units* of ``task_rows`` consecutive frames (unit ``u`` holds rows
``[u * task_rows, (u + 1) * task_rows)``, so every row's index is known). Each unit is one Ray
task (plain Ray tasks, ``workers`` of them in flight at once, spread over the nodes; each worker
process builds the model and estimator once): a task reads its unit's rows straight from the
Parquet file (with ``2 h`` frames of context across the unit's edges), decodes and estimates
them in chunks of ``batch_size`` with the local engine's functions and the log's one slot
layout, and journals them as ``OUT.partial/part-<u>.parquet``, encoded with the output's schema
and writer options (temporary name, atomic rename). The driver runs the same
:class:`~torchcontact.logs.run.Run` as the local engine (lock, journal, ordered writer, summary)
and appends the parts' bytes to the output in unit order, which is the row order, as they
finish (:class:`~torchcontact.logs.format.PartsWriter`, as the local engine's chunks): the
encoding, the costly part of writing, runs in the workers, and the driver copies bytes and reads
the status columns for the summary.

A worker process that dies (killed, out of memory) costs a retry of its unit
(:data:`TASK_RETRIES`), not the run; a killed driver leaves the journal, and ``--resume`` keeps
its units. A residual checkpoint must be stateless (MLP): units run in parallel and in any order,
so a recurrent (GRU) residual, which needs every frame in time order, is refused. With
``--constraints`` a unit's first frame starts cold (no warm start across units).

``workers`` tasks run at once, each holding ``worker_cpus`` CPUs. With ``keep_workers`` the units
go to the actors of a worker pool instead (:class:`~torchcontact.logs._ray_boot.PoolWorker`), which
outlive the run on a running cluster: the next runs find their processes started, torch imported
and the model built (:func:`_pool_units`).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.errors import InputError, LogError, TorchContactError
from torchcontact.identity import RobotIdentity
from torchcontact.logs._alloc import keep_freed_memory
from torchcontact.logs._ray_boot import ensure_ray as _ensure_ray
from torchcontact.logs._ray_boot import (
    new_pool_actor,
    pool,
    prestarted_pool,
    running_cluster,
)
from torchcontact.logs._ray_boot import task_options as _task_options
from torchcontact.logs.chunks import (
    DEFAULT_VELOCITY_MARGIN,
    LogEstimator,
    LogLocalize,
    decoded_chunks,
    estimate_stream,
)
from torchcontact.logs.decode import stamps_and_positions
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
from torchcontact.logs.format import check_outputs, open_log, write_encoded_part
from torchcontact.logs.pipeline import (
    _check_positive,
    expand_inputs,
    kernel_backend,
    load_residual,
    load_robot,
    localize_tally,
    log_noise,
    log_summary,
    output_paths,
    prepare,
    recorded_noise,
    resolve_device,
    run_ident,
    run_localize,
)
from torchcontact.logs.run import Done, Run, background, side_paths
from torchcontact.robots import RobotSpec, ft_sensor_specs

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


#: Per worker process: (path, robot, LogEstimator arguments, job) -> (LogEstimator, file).
#: Ray reuses worker processes across tasks, so the model is built once per process and config.
_WORKER_CACHE: dict[str, tuple[LogEstimator, Any]] = {}
#: Per worker process: the robot model of (robot, dtype, device), built by :func:`_warm_worker`
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


def _warm_worker(robot: dict, job: dict) -> str | None:
    """Ray task sent as Ray starts: a worker process builds the robot model before any unit.

    It runs while the driver still reads the log, so that the process has imported torchcontact
    and built the model by the time its first unit arrives.

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


def _estimate_units(units: Sequence[int], config: tuple) -> dict[str, Any]:
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


def _start_ray(
    num_cpus: int | None, robot: dict, job: dict, workers: int, task_options: dict
) -> tuple[Any, list[Any]]:
    """Start (or join) Ray and send each of ``workers`` worker processes a :func:`_warm_worker`.

    Called while the noise scan runs on another thread: the worker processes import torchcontact
    and build the robot model beside the driver's own work. On the caller's thread, which must
    live as long as Ray: a local instance's processes die with the thread that started them.

    Returns:
        The ``ray`` module, and the warm-up tasks' references (:func:`_unit_tasks` waits for
        them before it sends the units).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        ray = _ensure_ray(num_cpus)
        # with the units' resources, so that the units find these processes warm (a warm-up
        # holding no CPU ran in other processes than the units, measured)
        warm = ray.remote(_warm_worker).options(**task_options)
        return ray, [warm.remote(robot, job) for _ in range(workers)]


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


#: Seconds the units wait for the warm-ups at most (a cluster busy with other jobs may queue
#: them; the units then go all the same).
WARM_UP_WAIT_S = 60.0

#: Attempts of a unit whose worker process dies (a killed or crashed worker; the unit's journal
#: part is written under a temporary name, so a retry starts clean).
TASK_RETRIES = 3


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


def _robot_arg(robot: RobotSpec, model: Any) -> dict[str, Any]:
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
    return str(Path(path).resolve()), _robot_arg(robot, model), worker_args(le, path), job


def _unit_tasks(
    ray: Any,
    warm: list[Any],
    todo: list[int],
    config: Any,
    workers: int,
    worker_cpus: float,
    device: str,
) -> Iterator[dict[str, Any]]:
    """Run ``_estimate_units`` on each unit of ``todo``, ``workers`` tasks in flight at once.

    ``config`` is the run's :func:`unit_config` in Ray's object store.

    Plain Ray tasks, not Ray Data: a unit is a coarse task with a side effect (its journal
    part), and Ray Data's streaming executor ramped its concurrency up slowly (16 tasks of 1 s
    with 8 workers on 8 CPUs: 10.9 s, against 7.0 s as plain tasks). Yields each task's result
    as it finishes (any order; the run writes the units in order). A unit goes each time a
    warm-up (:func:`_start_ray`) ends, so that it finds that worker process ready and its CPU
    free (a unit sent while every warm-up still ran would start a new, cold process on a node
    with CPUs to spare); after :data:`WARM_UP_WAIT_S`, the units go all the same. Waiting for
    every warm-up instead cost 2.4 s on 16 workers (the slowest process to import torch).
    """
    task = ray.remote(_estimate_units).options(
        **_task_options(worker_cpus, device),
        max_retries=TASK_RETRIES,  # a dead worker process: its unit again (not user errors)
    )
    queue = list(reversed(todo))
    pending: list[Any] = []
    warming, slots = list(warm), workers - len(warm)  # slots: units that may run now
    deadline = time.monotonic() + WARM_UP_WAIT_S
    try:
        while queue or pending:
            while queue and len(pending) < slots:
                pending.append(task.remote([queue.pop()], config))
            left = deadline - time.monotonic()
            if warming and left <= 0:  # a busy cluster queues them: the units go all the same
                slots, warming = workers, []
            ready, _ = ray.wait(pending + warming, num_returns=1,
                                timeout=left if warming else None)  # fmt: skip
            if ready and ready[0] in pending:
                pending.remove(ready[0])
                yield ray.get(ready[0])
            elif ready:  # a warm-up ended (its process is ready): a unit in its place
                warming.remove(ready[0])
                slots += 1
    finally:
        for ref in pending:  # an error or an interrupted run: stop what is still running
            ray.cancel(ref, force=True)


#: Units queued on each pool actor at once (one running, one waiting): an actor that ends a unit
#: starts the next without waiting for the driver.
UNITS_QUEUED = 2


def _start_pool(
    robot: dict, job: dict, workers: int, worker_cpus: float, device: str, keep_s: float
) -> tuple[Any, list[Any], list[Any]]:
    """Join the running cluster, find or start ``workers`` pool actors, send each a warm-up.

    Returns:
        The ``ray`` module, the warm-ups' references
        (:meth:`~torchcontact.logs._ray_boot.PoolWorker.warm`), the actors.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        ray = _ensure_ray(None)
        members = prestarted_pool(workers, worker_cpus, device)  # the CLI's, moments ago
        if members is None:
            members = pool(ray, workers, worker_cpus, device, keep_s)
        actors = [a for a, _ in members]
        return ray, [a.warm.remote(robot, job, keep_s) for a in actors], actors


def _reused(ray: Any, warm: list[Any]) -> int:
    """How many of the pool's actors had served a run before this one (their warm-ups)."""
    n = 0
    for ref in warm:
        with contextlib.suppress(Exception):  # an actor replaced during the run
            n += ray.get(ref, timeout=5)["runs"] > 0
    return n


def _pool_units(
    ray: Any,
    actors: list[Any],
    todo: list[int],
    config: Any,
    replace: Any,
    source: str,
) -> Iterator[dict[str, Any]]:
    """Run ``todo``'s units on the pool's actors, :data:`UNITS_QUEUED` queued on each.

    An actor runs its calls in order, so it starts its next unit as it ends one, and at most
    ``len(actors)`` units run at once. An actor that dies (killed, out of memory, ended idle
    while the run queued a unit on it) is replaced (``replace()``: a new actor) and its units go
    again, :data:`TASK_RETRIES` times at most each; a unit's own error ends the run. Yields each
    unit's result as it finishes (any order).
    """
    from collections import Counter, deque

    queue = deque(todo)
    pending: dict[Any, tuple[int, int, Any]] = {}  # reference -> (slot, unit, actor)
    load = [0] * len(actors)
    tries: Counter = Counter()

    def fill() -> None:
        for slot, actor in enumerate(actors):
            while queue and load[slot] < UNITS_QUEUED:
                u = queue.popleft()
                pending[actor.estimate_units.remote([u], config)] = (slot, u, actor)
                load[slot] += 1

    try:
        fill()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            slot, u, actor = pending.pop(ready[0])
            load[slot] -= 1
            try:
                result = ray.get(ready[0])
            except ray.exceptions.RayActorError:  # the actor is gone, not the unit's error
                tries[u] += 1
                if tries[u] > TASK_RETRIES:
                    raise LogError(
                        f"{source}: unit {u} lost its Ray worker {tries[u]} times (killed or out"
                        " of memory)"
                    ) from None
                queue.appendleft(u)
                if actors[slot] is actor:  # its other units fail too: one new actor
                    actors[slot] = replace()
            else:
                yield result
            fill()
    finally:
        for ref in pending:  # an error or an interrupted run: the queued units are dropped
            with contextlib.suppress(Exception):
                ray.cancel(ref)


def estimate_file_ray(
    path: str | Path,
    robot: str | Path | RobotSpec,
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
    ft_noise: Any = None,
    unweighted: bool = False,
    localize: Any = None,
    keep_workers: float = 0.0,
) -> dict:
    """Estimate a log with Ray; same rows and summary as :func:`torchcontact.logs.estimate_file`.

    Ray is started here with ``num_cpus`` CPUs, or joined at ``RAY_ADDRESS`` (a running cluster,
    e.g. ``ray start --head`` and workers on other machines) when that variable is set.

    Args:
        path: input log.
        robot: ``tcarm``, ``icub``, a URDF path, or a :class:`~torchcontact.robots.RobotSpec`
            with declared F/T sensors (``--ft-sensor``): every worker builds the same model
            and checks its identity against the driver's.
        out: output Parquet file.
        sensors: sensors to use (default: those with a column).
        batch_size: frames per estimator call inside a unit.
        task_rows: frames of a unit (one Ray task; default ``8 * batch_size``).
        device: ``auto``, ``cpu`` or ``cuda`` (``cuda`` asks Ray for one GPU per task).
        dtype: computation dtype.
        resume: finish an interrupted Ray run from its parts.
        progress: show a progress bar (default: when stderr is a terminal).
        half_window: ``h`` of the Savitzky-Golay differentiator when ``qd``/``qdd`` are derived.
        workers: Ray tasks running at once (each estimates one unit at a time).
        worker_cpus: CPUs Ray reserves per task. Below 2 a task decodes, estimates and encodes
            its unit in turn on one thread; from 2 on, on three overlapping threads (as the
            local engine). pyarrow's thread pool in each worker process has ``worker_cpus``
            threads (at least 1).
        threads: torch threads per task.
        num_cpus: CPUs of a local Ray instance started here (default: all).
        residual: stateless (MLP) residual checkpoint directory, as :func:`estimate_file`; each
            worker process loads it once.
        velocity_margin: as :func:`estimate_file`.
        ft_range: as :func:`estimate_file`.
        constraints: as :func:`estimate_file` (warm starts run within a unit; a unit's first
            frame starts cold, so its rows may differ from the local engine's within the
            solver's tolerance).
        ft_noise: as :func:`estimate_file` (resolved once here, before the units run).
        unweighted: as :func:`estimate_file`.
        localize: as :func:`estimate_file` (options or a :class:`LogLocalize`); each worker
            process loads the meshes once from ``robot``'s URDF.
        keep_workers: seconds (> 0) that the worker processes stay after the run, idle, for the
            next runs: the units go to a pool of detached actors on the running cluster
            (``RAY_ADDRESS``), which the next runs of this torchcontact with the same
            ``worker_cpus`` and device find started, with the model built. Each actor holds its
            CPUs until it ends, ``keep_workers`` seconds after its last unit. 0: plain tasks in
            this run's worker processes.

    Returns:
        Summary dict as :func:`estimate_file` (``engine`` is ``"ray"``, chunks count units),
        ``nodes``: the Ray nodes that ran the units estimated now, with ``keep_workers``
        ``pool``: ``{"workers": n, "reused": k}`` (``k`` of the ``n`` actors ran before this
        run), and ``phases_s``: seconds from the start to Ray started (the warm-ups sent), the
        log scanned (and its noise estimated), the first unit done (absent when none ran now)
        and the output published.

    Raises:
        InputError: as :func:`estimate_file`, ``workers`` < 1, ``worker_cpus`` <= 0, or
            ``keep_workers`` < 0, or > 0 without a running cluster.
        OutputBusyError: another live process is writing ``out``.
        LogError: as :func:`estimate_file`, or a recurrent (GRU) residual.
    """
    t0 = time.perf_counter()
    task_rows = 8 * batch_size if task_rows is None else task_rows
    _check_positive(
        batch_size=batch_size, half_window=half_window, workers=workers, task_rows=task_rows
    )
    if not (isinstance(worker_cpus, (int, float)) and 0 < worker_cpus < float("inf")):
        raise InputError(f"--worker-cpus must be a number > 0, got {worker_cpus!r}")
    if not (isinstance(keep_workers, (int, float)) and 0 <= keep_workers < float("inf")):
        raise InputError(f"--keep-workers must be seconds >= 0, got {keep_workers!r}")
    if keep_workers and not running_cluster():
        raise InputError(
            "--keep-workers needs a running Ray cluster (set RAY_ADDRESS, e.g. after `ray start"
            " --head`): a Ray instance that this command starts ends with it"
        )
    out = Path(out)
    check_outputs([out, *side_paths(out)], [path, robot, residual])
    device = resolve_device(device)
    spec = robot if isinstance(robot, RobotSpec) else RobotSpec.of(robot)
    with Run(out, path) as run:  # the lock first: a second run stops before any work
        model = load_robot(spec, dtype)
        res = None if residual is None else load_residual(residual, model)
        if res is not None and res.recurrent:
            raise LogError(
                f"{path}: --engine ray cannot use a recurrent (GRU) residual (units run in any"
                " order); use --engine local"
            )
        localize = run_localize(localize, model, robot)
        job = dict(threads=threads, device=device, dtype=str(dtype).removeprefix("torch."),
                   cpus=worker_cpus)  # fmt: skip

        def setup() -> tuple:  # the log's scan and noise: read the whole log's cheap columns
            pf, le, columns, scan = prepare(path, model, sensors, res, velocity_margin, ft_range,
                                            constraints, localize=localize)  # fmt: skip
            log_noise(pf, le, columns, half_window, ft_noise, unweighted, str(path))
            return pf, le, columns, scan

        # the driver reads the log on a thread while Ray starts here and its worker processes
        # import torchcontact and build the model (a log of 16 M frames takes seconds to scan)
        with ThreadPoolExecutor(1, thread_name_prefix="torchcontact-scan") as pool:
            scanned = pool.submit(setup)
            if keep_workers:
                ray, warm, actors = _start_pool(
                    _robot_arg(spec, model), job, workers, worker_cpus, device, keep_workers
                )
            else:
                ray, warm = _start_ray(num_cpus, _robot_arg(spec, model), job, workers,
                                       _task_options(worker_cpus, device))  # fmt: skip
            phases = {"ray_started": time.perf_counter() - t0}
            pf, le, columns, scan = scanned.result()
            phases["log_scanned"] = time.perf_counter() - t0
        total = pf.metadata.num_rows
        show = sys.stderr.isatty() if progress is None else progress
        recorded_noise(le, run.previous() if resume else None)
        ident = run_ident(path, model, le, engine="ray", dtype=str(dtype),
                          half_window=half_window, batch_size=batch_size,
                          task_rows=task_rows)  # fmt: skip
        run.start(ident, plan_units(total, task_rows), resume)
        todo = [u for u in range(len(run.units)) if u not in run.done]
        options = dict(batch_size=batch_size, half_window=half_window,
                       backend=kernel_backend(total, device, shared=True), **job)  # fmt: skip

        def produce() -> Iterator[Done]:
            if not todo:
                return
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
                config = ray.put(unit_config(path, spec, model, le, run.units, columns,
                                             run.partial, res, options))  # fmt: skip
                if keep_workers:
                    results = _pool_units(ray, actors, todo, config, lambda: new_pool_actor(
                        ray, worker_cpus, device, keep_workers), str(path))  # fmt: skip
                else:
                    results = _unit_tasks(ray, warm, todo, config, workers, worker_cpus, device)
                try:
                    for r in results:
                        phases.setdefault("first_unit_done", time.perf_counter() - t0)
                        nodes.add(str(r["node"]))
                        for u, n in zip(r["units"], r["rows"], strict=True):
                            yield Done(u, n)
                except Exception as exc:
                    err = _user_error(exc)
                    if isinstance(err, TorchContactError):
                        raise err from None
                    raise

        nodes: set[str] = set()
        summary = run.execute(
            produce(),
            le.output_schema(),
            progress=show,
            cone_sensors=list(le.sensors) if constraints is not None else [],
            localize=localize_tally(le),
            t0=t0,
            **log_summary(le, scan),
            engine="ray",
        )
    summary["nodes"] = len(nodes)  # Ray nodes that ran units now
    if keep_workers:
        summary["pool"] = {"workers": len(actors), "reused": _reused(ray, warm)}
    phases["published"] = summary["seconds"]
    summary["phases_s"] = {k: round(v, 3) for k, v in phases.items()}
    return summary


def estimate_files_ray(
    inputs: Sequence[str | Path], robot: str | Path | RobotSpec, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file_ray` over files, folders or globs (``out`` a folder for several)."""
    files = expand_inputs(inputs)
    outs = output_paths(files, out)
    for o in outs:
        check_outputs([o, *side_paths(o)], [*files, robot, kwargs.get("residual")])
    return [estimate_file_ray(f, robot, o, **kwargs) for f, o in zip(files, outs, strict=True)]
