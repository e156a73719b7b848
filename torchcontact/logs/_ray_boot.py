"""Ray's start for ``--engine ray``, light enough to run before torch is imported.

``torchcontact estimate --engine ray`` calls :func:`prestart` first thing: Ray starts (or is
joined at ``RAY_ADDRESS``) and one task per worker has a worker process import torch and
torchcontact, while the driver imports them itself, builds the model and scans the log. On a
16-core host the driver took 4.6 s before its first Ray call, and Ray 4.6 s more to start 16
worker processes that import torch (benchmarks/README.md, session 8): the two now overlap. This
module imports neither torch nor numpy (nor Ray until called).
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path
from typing import Any

#: The import tasks :func:`prestart` sent (kept referenced until the process ends).
_booting: list[Any] = []


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
        if os.environ.get("RAY_ADDRESS"):  # a running cluster: it has its own resources
            ray.init(address=os.environ["RAY_ADDRESS"], **kwargs,
                     runtime_env={"env_vars": {"PYTHONPATH": path}})  # fmt: skip
        else:
            before = os.environ.get("PYTHONPATH")
            os.environ["PYTHONPATH"] = path
            try:
                ray.init(num_cpus=num_cpus, include_dashboard=False, **kwargs)
            finally:
                if before is None:
                    del os.environ["PYTHONPATH"]
                else:
                    os.environ["PYTHONPATH"] = before
    return ray


def task_options(worker_cpus: float, device: str) -> dict[str, Any]:
    """Ray options of a worker's task: its CPUs, a GPU for CUDA, spread over the nodes."""
    return dict(
        num_cpus=worker_cpus,
        num_gpus=1 if device.startswith("cuda") else 0,
        scheduling_strategy="SPREAD",  # over the nodes, as a cluster's user expects
    )


def _import_engine() -> None:
    """Ray task: this worker process imports the Ray engine (torch, pyarrow, torchcontact)."""
    import torchcontact.logs.ray_engine  # noqa: F401


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
        task = ray.remote(_import_engine).options(**task_options(worker_cpus, device))
        _booting.extend(task.remote() for _ in range(workers))
