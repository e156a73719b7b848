"""Run metadata printed above every benchmark table."""

from __future__ import annotations

import platform
import subprocess

import torch


def git_commit() -> str:
    """Short hash of the checked-out commit, or ``"unknown"`` outside a git checkout."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
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
        f" | CPU {cpu} | GPU {gpu}"
    )
