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

The driver imports neither torch nor the estimator: one worker process builds the model, scans
the log, resolves its noise and returns the units' config
(:func:`~torchcontact.logs.ray_worker.setup_run`), and the driver checks that this worker read
the driver's URDF. Everything that runs in a worker process lives in
:mod:`torchcontact.logs.ray_worker`; this module sends it by name (the wrappers below import it
in the worker).

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
import hashlib
import os
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from torchcontact.errors import InputError, LogError, TorchContactError
from torchcontact.logs._ray_boot import (
    cluster_device,
    new_pool_actor,
    pool,
    prestarted_pool,
    running_cluster,
    worker_side,
)
from torchcontact.logs._ray_boot import ensure_ray as _ensure_ray
from torchcontact.logs._ray_boot import task_options as _task_options
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
from torchcontact.logs.format import check_outputs, expand_inputs, open_log, output_paths
from torchcontact.logs.run import Done, Run, check_positive, side_paths
from torchcontact.robots import RobotSpec
from torchcontact.status import DEFAULT_VELOCITY_MARGIN

__all__ = ["estimate_file_ray", "estimate_files_ray", "plan_units"]


def plan_units(rows: int, task_rows: int) -> list[tuple[int, int]]:
    """Cut ``rows`` frames into units of ``task_rows`` consecutive frames (the last shorter).

    Example:
        >>> plan_units(250, 100)
        [(0, 100), (100, 200), (200, 250)]
    """
    return [(a, min(a + task_rows, rows)) for a in range(0, rows, task_rows)]


#: Chunks of ``batch_size`` frames in a unit, about (:func:`default_task_rows`).
CHUNKS_PER_UNIT = 8


def default_task_rows(rows: int, batch_size: int, workers: int) -> int:
    """Frames of a unit: about :data:`CHUNKS_PER_UNIT` chunks, units a multiple of the workers.

    The units' count is rounded up to a multiple of ``workers``, so that the run's last round
    keeps every worker busy: 12 M frames cut into units of 65,536 gave 184 units, whose last
    round on 16 workers ran 8 of them while the other 8 workers idled (4.1 worker-seconds of the
    16-worker run, one unit's time at its end; Round 12 of docs/pipeline.md); 192 units of
    62,500 frames run in 12 full rounds.

    Example:
        >>> default_task_rows(12_000_000, 8192, 16), default_task_rows(12_000_000, 8192, 1)
        (62500, 65218)
    """
    units = -(-max(rows, 1) // (CHUNKS_PER_UNIT * batch_size))
    units = -(-units // workers) * workers
    return max(1, -(-rows // units))


# ------------------------------------------------------ what the worker processes run (by name)
def _warm_worker(robot: dict, job: dict) -> str | None:
    """Ray task: :func:`~torchcontact.logs.ray_worker.warm_worker` in a worker process."""
    return worker_side().warm_worker(robot, job)


def _setup_run(request: dict) -> dict:
    """Ray task: :func:`~torchcontact.logs.ray_worker.setup_run` in a worker process."""
    return worker_side().setup_run(request)


def _estimate_units(units: Sequence[int], config: tuple) -> dict[str, Any]:
    """Ray task: :func:`~torchcontact.logs.ray_worker.estimate_units` in a worker process."""
    return worker_side().estimate_units(units, config)


def _start_ray(
    num_cpus: int | None,
    device: str,
    robot: dict,
    job: dict,
    workers: int,
    worker_cpus: float,
    request: dict,
) -> tuple[Any, str, list[Any], Any]:
    """Start (or join) Ray; send the run's setup to one worker process, a warm-up to the others.

    The setup (:func:`_setup_run`) holds a unit's resources, as the warm-ups
    (:func:`_warm_worker`) do: its process builds the model, which its units then find, and no
    extra process imports torch beside the ``workers`` that will run the units (a setup task
    beside them, holding no CPU, made the run 0.5-0.8 s longer on 2 cores). On the caller's
    thread, which must live as long as Ray: a local instance's processes die with the thread that
    started them. ``job["device"]`` (``request``'s job too) is set to the cluster's device.

    Returns:
        The ``ray`` module, the device (:func:`cluster_device`), the references the units wait
        for before they go (:func:`_unit_tasks`: the setup's and the warm-ups'), and the setup's.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        ray = _ensure_ray(num_cpus)
        device = cluster_device(ray, device)
        job["device"] = device
        # with the units' resources, so that the units find these processes warm (a warm-up
        # holding no CPU ran in other processes than the units, measured)
        opts = _task_options(worker_cpus, device)
        setup = ray.remote(_setup_run).options(**opts, max_retries=TASK_RETRIES).remote(request)
        warm = ray.remote(_warm_worker).options(**opts)
        return ray, device, [setup, *(warm.remote(robot, job) for _ in range(workers - 1))], setup


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


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    """Raise a library error that a Ray call wrapped (:func:`_user_error`) as the library's."""
    try:
        yield
    except Exception as exc:
        err = _user_error(exc)
        if isinstance(err, TorchContactError):
            raise err from None
        raise


#: Seconds the units wait for the warm-ups at most (a cluster busy with other jobs may queue
#: them; the units then go all the same).
WARM_UP_WAIT_S = 60.0

#: Attempts of a unit whose worker process dies (a killed or crashed worker; the unit's journal
#: part is written under a temporary name, so a retry starts clean).
TASK_RETRIES = 3


def _setup(
    ray: Any,
    request: dict,
    sent: Any,
    actors: list[Any] | None,
    worker_cpus: float,
    device: str,
    keep_s: float,
) -> dict:
    """The result of the run's :func:`~torchcontact.logs.ray_worker.setup_run` on a worker.

    Without a pool, the task :func:`_start_ray` sent (``sent``); with one, the pool's first live
    actor runs it (after its warm-up: an actor runs its calls in order; an actor that ended is
    replaced).

    Raises:
        TorchContactError: the setup's error (a user's input), as the worker raised it.
    """
    with warnings.catch_warnings(), _user_errors():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        if actors is None:
            return ray.get(sent)
        for k, actor in enumerate(actors):
            try:
                return ray.get(actor.setup.remote(request))
            except ray.exceptions.RayActorError:  # it ended (idle, killed): the next one
                actors[k] = new_pool_actor(ray, worker_cpus, device, keep_s)
        return ray.get(actors[0].setup.remote(request))


def _urdf_sha256(spec: RobotSpec) -> str:
    """The sha256 of the robot's URDF text here, as :attr:`RobotModel.urdf_sha256` records it."""
    from torchcontact import _urdf

    text, _ = _urdf.read_text(os.fspath(spec))
    return hashlib.sha256(text.encode()).hexdigest()


def _check_robot(spec: RobotSpec, urdf_sha256: str, setup: dict) -> None:
    """Refuse a setup whose worker built another robot than the driver's URDF describes.

    ``urdf_sha256`` is the driver's URDF text's (:func:`_urdf_sha256`). The worker that ran
    :func:`~torchcontact.logs.ray_worker.setup_run` read ``spec``'s URDF on its node, and the
    units check their models against its identity. The same URDF text here means the same robot;
    another text (another copy of the file on that node) is checked by the model's identity,
    built here (which imports torch: a cluster whose nodes hold different files pays for it), so
    that a reformatted copy of the same robot still runs.

    Raises:
        LogError: the worker's robot differs from the driver's (the first difference named).
    """
    if setup["ident"]["urdf_sha256"] == urdf_sha256:
        return
    from torchcontact.identity import RobotIdentity

    mine = spec.load().identity
    robot = setup["config"][1]
    if mine.sha256 != robot["identity"]:
        theirs = RobotIdentity.from_json(robot["identity_entries"])
        raise LogError(
            f"the Ray worker that scanned the log built robot {spec} unlike the driver's:"
            f" {mine.difference(theirs) or 'another identity'}"
        )


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
    num_cpus: int | None,
    device: str,
    robot: dict,
    job: dict,
    workers: int,
    worker_cpus: float,
    keep_s: float,
) -> tuple[Any, str, list[Any], list[Any]]:
    """Join the running cluster, find or start ``workers`` pool actors, send each a warm-up.

    Returns:
        The ``ray`` module, the device (:func:`cluster_device`), the warm-ups' references
        (:meth:`~torchcontact.logs._ray_boot.PoolWorker.warm`), the actors.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        ray = _ensure_ray(num_cpus)
        device = cluster_device(ray, device)
        job["device"] = device
        members = prestarted_pool(workers, worker_cpus, device)  # the CLI's, moments ago
        if members is None:
            members = pool(ray, workers, worker_cpus, device, keep_s)
        actors = [a for a, _ in members]
        return ray, device, [a.warm.remote(robot, job, keep_s) for a in actors], actors


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
    dtype: Any = "float64",
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
    e.g. ``ray start --head`` and workers on other machines) when that variable is set. This
    process imports no torch (unless a cluster node's URDF differs from this one's: see
    :func:`_check_robot`): one worker builds the model and scans the log.

    Args:
        path: input log.
        robot: ``tcarm``, ``icub``, a URDF path, or a :class:`~torchcontact.robots.RobotSpec`
            with declared F/T sensors (``--ft-sensor``): every worker builds the same model
            and checks its identity against the one that scanned the log, which must have read
            the driver's robot.
        out: output Parquet file.
        sensors: sensors to use (default: those with a column).
        batch_size: frames per estimator call inside a unit.
        task_rows: frames of a unit (one Ray task; default :func:`default_task_rows`: about 8
            chunks, the units' count a multiple of ``workers``; a resume keeps its run's).
        device: ``auto``, ``cpu`` or ``cuda`` (``cuda`` asks Ray for one GPU per task;
            ``auto`` is ``cuda`` when the cluster has a GPU).
        dtype: computation dtype: ``"float64"``, ``"float32"`` or a torch dtype.
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
        ft_noise: as :func:`estimate_file` (resolved once, before the units run).
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
        log scanned (the setup returned: the model built, the log scanned and its noise
        estimated), the first unit done (absent when none ran now) and the output published.

    Raises:
        InputError: as :func:`estimate_file`, ``workers`` < 1, ``worker_cpus`` <= 0, or
            ``keep_workers`` < 0, or > 0 without a running cluster, ``cuda`` on a cluster
            without a GPU.
        OutputBusyError: another live process is writing ``out``.
        LogError: as :func:`estimate_file`, a recurrent (GRU) residual, or a worker whose
            robot differs from the driver's.
    """
    t0 = time.perf_counter()
    check_positive(batch_size=batch_size, half_window=half_window, workers=workers)
    if task_rows is not None:
        check_positive(task_rows=task_rows)
    if not (isinstance(worker_cpus, (int, float)) and 0 < worker_cpus < float("inf")):
        raise InputError(f"--worker-cpus must be a number > 0, got {worker_cpus!r}")
    if not (isinstance(keep_workers, (int, float)) and 0 <= keep_workers < float("inf")):
        raise InputError(f"--keep-workers must be seconds >= 0, got {keep_workers!r}")
    if keep_workers and not running_cluster():
        raise InputError(
            "--keep-workers needs a running Ray cluster (set RAY_ADDRESS, e.g. after `ray start"
            " --head`): a Ray instance that this command starts ends with it"
        )
    dtype = str(dtype).removeprefix("torch.")
    if dtype not in ("float64", "float32"):
        raise InputError(f"dtype {dtype}: expected float64 or float32")
    out = Path(out)
    check_outputs([out, *side_paths(out)], [path, robot, residual])
    spec = robot if isinstance(robot, RobotSpec) else RobotSpec.of(robot)
    with Run(out, path) as run:  # the lock first: a second run stops before any work
        # the worker processes' arguments: plain values (the workers build the model)
        robot_arg = {"robot": spec.robot, "ft_sensors": [str(s) for s in spec.ft_sensors]}
        job = dict(threads=threads, device=device, dtype=dtype, cpus=worker_cpus)
        previous = run.previous() if resume else None
        if task_rows is None:  # a resume cuts the log as its run did, whatever its workers
            kept = previous.get("task_rows") if previous is not None else None
            task_rows = kept if isinstance(kept, int) and kept > 0 else default_task_rows(
                open_log(path).metadata.num_rows, batch_size, workers)  # fmt: skip
        request = dict(
            path=str(Path(path).resolve()), robot=robot_arg, job=job,
            partial=str(run.partial.resolve()), previous=previous,
            batch_size=batch_size, half_window=half_window, task_rows=task_rows,
            sensors=sensors, velocity_margin=velocity_margin, ft_range=ft_range,
            constraints=constraints, ft_noise=ft_noise, unweighted=unweighted, localize=localize,
            residual=None if residual is None else str(Path(residual).resolve()),
        )  # fmt: skip
        sent = None
        if keep_workers:
            ray, device, warm, actors = _start_pool(
                num_cpus, device, robot_arg, job, workers, worker_cpus, keep_workers
            )
        else:
            ray, device, warm, sent = _start_ray(num_cpus, device, robot_arg, job, workers,
                                                 worker_cpus, request)  # fmt: skip
        phases = {"ray_started": time.perf_counter() - t0}
        setup = _setup(ray, request, sent, actors if keep_workers else None, worker_cpus, device,
                       keep_workers)  # fmt: skip
        urdf_sha256 = _urdf_sha256(spec)
        _check_robot(spec, urdf_sha256, setup)
        phases["log_scanned"] = time.perf_counter() - t0
        show = sys.stderr.isatty() if progress is None else progress
        st = os.stat(path)  # the input as the driver sees it (a resume compares it)
        ident = {**setup["ident"], "input": str(Path(path).resolve()), "input_size": st.st_size,
                 "input_mtime_ns": st.st_mtime_ns, "urdf_sha256": urdf_sha256}  # fmt: skip
        run.start(ident, [tuple(u) for u in setup["units"]], resume)
        todo = [u for u in range(len(run.units)) if u not in run.done]

        def produce() -> Iterator[Done]:
            if not todo:
                return
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
                config = ray.put(setup["config"])
                if keep_workers:
                    results = _pool_units(ray, actors, todo, config, lambda: new_pool_actor(
                        ray, worker_cpus, device, keep_workers), str(path))  # fmt: skip
                else:
                    results = _unit_tasks(ray, warm, todo, config, workers, worker_cpus, device)
                with _user_errors():
                    for r in results:
                        phases.setdefault("first_unit_done", time.perf_counter() - t0)
                        nodes.add(str(r["node"]))
                        for u, n in zip(r["units"], r["rows"], strict=True):
                            yield Done(u, n)

        nodes: set[str] = set()
        summary = run.execute(
            produce(),
            setup["schema"],
            progress=show,
            cone_sensors=list(setup["summary"]["sensors"]) if constraints is not None else [],
            localize=setup["localize"],
            t0=t0,
            **setup["summary"],
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
