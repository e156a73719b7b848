"""Run metadata and timing helpers shared by the benchmark scripts."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch
import torch.utils.benchmark as tb

ROOT = Path(__file__).resolve().parents[1]


def git_commit() -> str:
    """Short hash of the checked-out commit, or ``"unknown"`` outside a git checkout."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=ROOT,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def metadata() -> str:
    """One line: commit, torch version, device, threads, CPU."""
    commit = git_commit()
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "none"
    return (
        f"commit {commit} | torch {torch.__version__} | threads {torch.get_num_threads()}"
        f" | CPU {cpu} ({os.cpu_count()} logical) | GPU {gpu} | python {platform.python_version()}"
    )


def rate(fn: Callable[[], object], frames: int, min_run_time: float = 1.0) -> tuple[float, float]:
    """Frames per second of ``fn`` (median of ``torch.utils.benchmark``) and the IQR's share."""
    # num_threads: torch.utils.benchmark runs fn under ONE torch thread unless told otherwise,
    # which would time every multi-threaded CPU path single-threaded
    timer = tb.Timer(stmt="fn()", globals={"fn": fn}, num_threads=torch.get_num_threads())
    m = timer.blocked_autorange(min_run_time=min_run_time)
    return frames / m.median, m.iqr / m.median


def first_call(code: str, cache: str | None = None) -> float:
    """Seconds a fresh Python process takes to run ``code`` (which prints nothing else).

    ``code`` must print one float, the seconds from its own start to its first result. With
    ``cache`` None a new empty kernel cache is used (a cold start); pass a path to reuse one.
    """
    cache = cache or tempfile.mkdtemp(prefix="tc-cache-")
    env = {**os.environ, "TORCHCONTACT_CACHE": cache}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
        check=True,
    ).stdout  # fmt: skip
    return float(out.strip().splitlines()[-1])


def load_old_package(commit: str, into: Path, name: str = "tc_old"):
    """torchcontact as of ``commit``, importable beside this tree as package ``name``.

    The commit's ``torchcontact/`` (``git archive``) is copied to ``into/name`` with its imports
    of ``torchcontact`` renamed, so both versions run in one process (torch-free modules such
    as the runtime; the graphs are exported by each version in its own process). Returns the
    package module.
    """
    import importlib
    import re
    import tarfile

    arch = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "torchcontact"],
                          capture_output=True, check=True).stdout  # fmt: skip
    tar = into / f"{name}.tar"
    tar.write_bytes(arch)
    tree = into / f"{name}-tree"
    tree.mkdir(exist_ok=True)
    with tarfile.open(tar) as t:
        t.extractall(tree, filter="data")
    pat = re.compile(r"(\bfrom |\bimport |import_module\(f?\")torchcontact\b")
    for src in (tree / "torchcontact").rglob("*.py"):
        dst = into / name / src.relative_to(tree / "torchcontact")
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(pat.sub(lambda m: m.group(1) + name, src.read_text()))
    sys.path.insert(0, str(into))
    return importlib.import_module(name)
