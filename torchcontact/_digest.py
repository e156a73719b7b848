"""The digest of torchcontact's own code, without importing torch.

The kernel cache's keys and the Ray worker pool's namespace name the code with it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

_code: list[str] = []


def code_digest() -> str:
    """sha256 of torchcontact's Python sources (once per process, 6-20 ms; thread-safe).

    A kernel program's key names its constants (model, layout, flags); the code that turns them
    into a program is named by this digest, so a kernel cache's index record never outlives the
    code it was made with, and a Ray worker pool never serves another code than the driver's.
    The first kernel lookup of a process needs it: a log run computes it on a thread of its own
    beside its first chunks (:func:`torchcontact.logs.pipeline.open_prepared`).
    """
    if not _code:
        root = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
        _code.append(h.hexdigest())  # two threads at once: the same value, the first kept
    return _code[0]
