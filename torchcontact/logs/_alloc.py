"""The allocator and collector settings of a log job's processes: the CLI's and each Ray worker's.

Imports neither torch nor pyarrow: the settings must come before pyarrow loads.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator
from contextlib import contextmanager

#: Environment of a log job's processes: pyarrow's mimalloc keeps the pages it frees (read when
#: pyarrow loads; a Ray worker gets it from its runtime environment).
ALLOC_ENV = {"MIMALLOC_PURGE_DELAY": "-1"}

#: glibc's ``mallopt`` parameters (``<malloc.h>``).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

_set: list[bool] = []


def keep_freed_memory() -> None:
    """Have the allocators keep freed memory for the next chunk rather than return it to the OS.

    A log job allocates and frees buffers of the same sizes (0.1-20 MB) for every chunk. pyarrow's
    mimalloc returns freed pages after 10 ms, and glibc's malloc maps each array above its
    threshold anew and trims its heap: every chunk faulted its pages in again, zero-filled by
    the kernel (219 k page faults in a warm 1 M-frame run, about 6% of its CPU; 88 k with these
    settings). In a Ray worker, a unit of 65,536 iCub frames took 0.36 s instead of 0.47 s with
    them (and no page fault instead of about 7,000; 2-core machine, session 11). mimalloc keeps
    its pages (:data:`ALLOC_ENV`, read when pyarrow loads, so this runs before it is imported);
    glibc serves blocks up to 32 MiB from its heap and trims only above 1 GiB free (once per
    process). The bounded queues still bound the peak memory.
    """
    for key, value in ALLOC_ENV.items():
        os.environ.setdefault(key, value)
    if _set:
        return
    _set.append(True)
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_THRESHOLD, 32 << 20)
    mallopt(_M_TRIM_THRESHOLD, 1 << 30)


@contextmanager
def imports_uncollected() -> Iterator[None]:
    """Import a log job's modules without the cyclic collector, then freeze what they made.

    torch's import alone triggers 3 full and 33 partial collections, each walking every object
    made so far: 0.1-0.3 CPU-s of a process's start on the 2-core machine (2.0-2.8 against
    1.7-1.9 CPU-s for torch, pyarrow and the pipeline). The modules live as long as the process,
    so :func:`gc.freeze` then moves them out of the collector's reach: the full passes during the
    run need not walk them again (one took 0.14 s of a 1 M-frame run). What the imports left
    unreachable (about 7,000 objects) is frozen with them, never freed, as in a process that
    forks after its imports. The collector is on afterwards unless it was off before.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()
