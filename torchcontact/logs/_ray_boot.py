"""Ray's start for ``--engine ray``, light enough to run before torch is imported.

``torchcontact estimate --engine ray`` calls :func:`prestart` first thing: Ray starts (or is
joined at ``RAY_ADDRESS``) and one task per worker has a worker process import torch and
torchcontact, while the driver goes on. On a 16-core host the driver took 4.6 s before its first
Ray call, and Ray 4.6 s more to start 16 worker processes that import torch (benchmarks/README.md,
session 8): the two now overlap. The driver itself imports no torch: a worker builds the model
and scans the log (:func:`torchcontact.logs.ray_worker.setup_run`). This module imports neither
torch nor numpy (nor Ray until called).

It also holds the worker pool of ``--keep-workers`` (:class:`PoolWorker`): Ray actors that
outlive the run which started them, so that the next runs on the same cluster find their worker
processes started, with torch imported and the model built.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

from torchcontact.errors import InputError
from torchcontact.logs._alloc import ALLOC_ENV, imports_uncollected, keep_freed_memory

#: The import tasks :func:`prestart` sent (kept referenced until the process ends).
_booting: list[Any] = []
#: The pool :func:`prestart_pool` found or started, by its workers and actor label, until the
#: run takes it (:func:`prestarted_pool`).
_prestarted: dict[tuple, list[tuple[Any, bool]]] = {}
#: True once :func:`ensure_ray` has started a local Ray instance in this process (its head
#: processes end with this process's :func:`ray.shutdown`); a running cluster it joined is left
#: as it is.
_local_instance: list[bool] = []


def ensure_ray(num_cpus: int | None) -> Any:
    """The ``ray`` module, started here with ``num_cpus`` CPUs or joined at ``RAY_ADDRESS``.

    Ray's INFO and WARNING lines are off (they would drown the run's one progress bar). The
    worker processes import the same torchcontact as this process: a local instance inherits
    this process's ``PYTHONPATH`` (no ``runtime_env``, so that the worker processes Ray starts
    with it run the tasks); a running cluster gets it as a ``runtime_env``. A local instance must
    be started on a thread that lives as long as Ray: its processes die with that thread.
    """
    import ray

    logging.getLogger("ray").setLevel(logging.ERROR)
    if not ray.is_initialized():
        root = str(Path(__file__).resolve().parents[2])
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
        kwargs: dict[str, Any] = dict(log_to_driver=False, logging_level=logging.ERROR)
        env = {"PYTHONPATH": path, **ALLOC_ENV}  # the workers' allocators as the CLI's
        if os.environ.get("RAY_ADDRESS"):  # a running cluster: it has its own resources
            ray.init(address=os.environ["RAY_ADDRESS"], **kwargs, runtime_env={"env_vars": env})
        else:
            before = {k: os.environ.get(k) for k in env}
            os.environ.update(env)
            try:
                ray.init(num_cpus=num_cpus, include_dashboard=False, **kwargs)
                _local_instance.append(True)
            finally:
                for k, v in before.items():
                    if v is None:
                        del os.environ[k]
                    else:
                        os.environ[k] = v
    return ray


def started_local_instance() -> bool:
    """True when :func:`ensure_ray` started a local Ray instance in this process.

    Its head processes and workers end only with :func:`ray.shutdown`; a driver that joined a
    running cluster needs none at its end: the cluster ends the driver's job when its process
    exits (as for a killed driver), which a command ending with :func:`os._exit` does 0.3 s
    sooner than the shutdown (measured on 2 cores, a local head).
    """
    return bool(_local_instance)


def task_options(worker_cpus: float, device: str) -> dict[str, Any]:
    """Ray options of a worker's task: its CPUs, a GPU for CUDA, spread over the nodes."""
    return dict(
        num_cpus=worker_cpus,
        num_gpus=1 if device.startswith("cuda") else 0,
        scheduling_strategy="SPREAD",  # over the nodes, as a cluster's user expects
    )


def cluster_device(ray: Any, device: str) -> str:
    """The run's device on the cluster: ``auto`` is ``cuda`` where the cluster has a GPU.

    Resolved where Ray is started (the CLI's :func:`prestart` and the engine), so that the
    workers started ahead hold the resources the run's units ask for.

    Raises:
        InputError: an unknown device, or ``cuda`` on a cluster without GPUs.
    """
    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError(f"--device {device}: expected auto, cpu or cuda")
    gpus = ray.cluster_resources().get("GPU", 0) if device != "cpu" else 0
    if device == "auto":
        return "cuda" if gpus >= 1 else "cpu"
    if device.startswith("cuda") and gpus < 1:
        raise InputError(f"--device {device}: the Ray cluster has no GPU; use --device cpu or auto")
    return device


def worker_side() -> ModuleType:
    """:mod:`torchcontact.logs.ray_worker` in a worker process, imported once as the CLI imports.

    The first call imports it (torch, pyarrow, torchcontact) with the allocators set and the
    cyclic collector off, then freezes what the import made
    (:func:`~torchcontact.logs._alloc.imports_uncollected`); later calls return it as it is.
    """
    module = sys.modules.get("torchcontact.logs.ray_worker")
    if module is None:
        keep_freed_memory()  # before pyarrow loads
        with imports_uncollected():
            import torchcontact.logs.ray_worker as module
    return module


def _import_engine() -> None:
    """Ray task: this worker process imports the Ray engine's worker side (torch, torchcontact)."""
    worker_side()


def prestart(workers: int, worker_cpus: float, device: str, num_cpus: int | None = None) -> None:
    """Start Ray and send ``workers`` worker processes an import of the engine, now.

    The tasks hold the units' CPUs, so that the model warm-ups and then the units that the run
    sends later find these processes (:func:`torchcontact.logs.ray_engine.estimate_file_ray`).

    Args:
        workers: Ray tasks the run keeps in flight.
        worker_cpus: CPUs reserved per task.
        device: the run's ``--device`` (``cuda``: each task holds a GPU; ``auto``: none).
        num_cpus: CPUs of a local Ray instance started here (default: all).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Ray's deprecation and tuning hints are not ours
        ray = ensure_ray(num_cpus)
        device = cluster_device(ray, device)
        task = ray.remote(_import_engine).options(**task_options(worker_cpus, device))
        _booting.extend(task.remote() for _ in range(workers))


def prestart_pool(workers: int, worker_cpus: float, device: str, keep_s: float) -> None:
    """:func:`prestart` for ``--keep-workers``: find or start the pool's actors now.

    A new actor's process imports the engine at once (its first call); a live one has.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ray = ensure_ray(None)
        device = cluster_device(ray, device)
        members = pool(ray, workers, worker_cpus, device, keep_s)
        _prestarted[(workers, _pool_label(worker_cpus, device))] = members
        _booting.extend(actor.imports.remote() for actor, new in members if new)


def prestarted_pool(workers: int, worker_cpus: float, device: str) -> list[tuple[Any, bool]] | None:
    """The pool :func:`prestart_pool` found for these options (once), else None."""
    return _prestarted.pop((workers, _pool_label(worker_cpus, device)), None)


# ----------------------------------------------------------------------------- the worker pool
def running_cluster() -> bool:
    """True when Ray runs apart from this process: ``RAY_ADDRESS``, or joined already."""
    if os.environ.get("RAY_ADDRESS"):
        return True
    import sys

    ray = sys.modules.get("ray")
    return bool(ray is not None and ray.is_initialized())


def pool_namespace() -> str:
    """The Ray namespace of this code's worker pool (one per torchcontact code digest).

    A driver never sends units to workers of another code: a changed checkout or version starts
    a pool of its own, and the old one's actors end when idle.
    """
    from torchcontact._digest import code_digest

    return f"torchcontact-{code_digest()[:16]}"


def _pool_label(worker_cpus: float, device: str) -> str:
    """The start of the names of the pool's actors with these resources."""
    return f"cpus{worker_cpus:g}-{'cuda' if device.startswith('cuda') else 'cpu'}-"


def pool(
    ray: Any, workers: int, worker_cpus: float, device: str, keep_s: float
) -> list[tuple[Any, bool]]:
    """``workers`` actors of the worker pool for these resources: live ones, then new ones.

    Returns:
        ``(actor handle, new)`` pairs: ``new`` for an actor started here.
    """
    ns, label = pool_namespace(), _pool_label(worker_cpus, device)
    names = [n for n in pool_actors(ray) if n.startswith(label)]
    found = []
    for name in names:
        if len(found) == workers:
            break
        try:
            found.append((ray.get_actor(name, namespace=ns), False))
        except ValueError:  # it ended meanwhile (idle)
            continue
    while len(found) < workers:
        found.append((new_pool_actor(ray, worker_cpus, device, keep_s), True))
    return found


def pool_actors(ray: Any) -> list[str]:
    """Names of the live actors of this code's worker pool, any resources."""
    ns = pool_namespace()
    return sorted(a["name"] for a in ray.util.list_named_actors(all_namespaces=True)
                  if a.get("namespace") == ns)  # fmt: skip


def end_pool(ray: Any) -> int:
    """End this code's worker pool now (its actors and their CPUs); returns how many ended."""
    n = 0
    for name in pool_actors(ray):
        with contextlib.suppress(ValueError):  # ended meanwhile
            ray.kill(ray.get_actor(name, namespace=pool_namespace()))
            n += 1
    return n


def new_pool_actor(ray: Any, worker_cpus: float, device: str, keep_s: float) -> Any:
    """Start one actor of the worker pool (detached: it outlives this process)."""
    import uuid

    name = _pool_label(worker_cpus, device) + uuid.uuid4().hex[:12]
    opts = dict(name=name, namespace=pool_namespace(), lifetime="detached", max_restarts=0,
                **task_options(worker_cpus, device))  # fmt: skip
    return ray.remote(PoolWorker).options(**opts).remote(keep_s)


class PoolWorker:
    """A Ray actor of the worker pool (``--keep-workers SECONDS``).

    It runs the same units as the Ray engine's tasks (:func:`~torchcontact.logs.ray_worker.
    estimate_units`), one at a time, in its own worker process, which keeps torch imported, the
    model built and the kernels loaded from one run to the next; a run's first actor runs its
    setup too (:func:`~torchcontact.logs.ray_worker.setup_run`). It ends itself once it has been
    idle for ``keep_s`` seconds (the last run's ``--keep-workers``): an idle actor still holds
    the CPUs Ray reserved for it. Detached: a driver that ends (or is killed) leaves it.

    Args:
        keep_s: seconds of idleness after which the actor ends.
    """

    def __init__(self, keep_s: float) -> None:
        self._keep = float(keep_s)
        self._last = time.monotonic()
        self._busy = 0
        self._runs = 0
        self._guard = threading.Lock()
        threading.Thread(target=self._watch, name="torchcontact-pool-idle", daemon=True).start()

    @contextlib.contextmanager
    def _active(self) -> Iterator[None]:
        with self._guard:
            self._busy += 1
        try:
            yield
        finally:
            with self._guard:
                self._busy -= 1
                self._last = time.monotonic()

    def imports(self) -> None:
        """Import the engine (torch, pyarrow, torchcontact): sent to a new actor at once."""
        with self._active():
            _import_engine()

    def warm(self, robot: dict, job: dict, keep_s: float) -> dict:
        """A run's first call: its ``--keep-workers`` from now on, and the model built.

        Returns:
            ``error``: the model's error text or None (the first unit reports it), ``runs``:
            the runs this actor served before.
        """
        with self._active():
            self._keep = float(keep_s)
            error = worker_side().warm_worker(robot, job)
            runs, self._runs = self._runs, self._runs + 1
            return {"error": error, "runs": runs}

    def setup(self, request: dict) -> dict:
        """A run's setup (:func:`~torchcontact.logs.ray_worker.setup_run`), before its units."""
        with self._active():
            return worker_side().setup_run(request)

    def estimate_units(self, units: list[int], config: tuple) -> dict[str, Any]:
        """The Ray engine's unit task (:func:`~torchcontact.logs.ray_worker.estimate_units`)."""
        with self._active():
            return worker_side().estimate_units(units, config)

    def expire(self) -> bool:
        """End this actor if it is still idle (sent by its own watchdog); False if it is not."""
        with self._guard:
            if self._busy or time.monotonic() - self._last <= self._keep:
                return False
        import ray

        ray.actor.exit_actor()
        return True  # pragma: no cover - exit_actor does not return

    def _watch(self) -> None:
        import ray

        while True:
            time.sleep(min(1.0, max(0.05, self._keep / 4)))
            with self._guard:
                idle = not self._busy and time.monotonic() - self._last > self._keep
            if idle:
                with contextlib.suppress(Exception):  # the actor is ending anyway
                    ray.get(ray.get_runtime_context().current_actor.expire.remote())
