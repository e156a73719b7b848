"""One writer per output: an OS lock on ``OUT.lock`` held for the life of a command.

Commands that write an output (``estimate``, ``plot --out``, ``train fit --out``) hold an
exclusive ``fcntl.flock`` on ``OUT.lock`` beside it (``OUT`` is a file or a folder) while they
run, and write their pid, host and start time into it. A second command on the same output stops
at once with an error that names the first; the operating system drops the lock when its process
ends in any way (``kill -9`` included), so a crash never needs a manual unlock: a later command
takes the lock over. The lock file is removed when the command ends.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any

from torchcontact.errors import OutputBusyError

__all__ = ["OutputLock", "lock_path"]


def lock_path(out: str | Path) -> Path:
    """The lock file of an output: ``OUT.lock`` beside it."""
    out = Path(out)
    return out.with_name(out.name + ".lock")


class OutputLock:
    """An exclusive OS lock on ``OUT.lock``, held from :meth:`acquire` to :meth:`release`.

    Args:
        out: the output (file or folder) the holder writes.
        what: the command, for the message (``estimate``, ``plot``, ...).

    Example:
        >>> import tempfile
        >>> out = Path(tempfile.mkdtemp()) / "est.parquet"
        >>> with OutputLock(out):
        ...     OutputLock(out).acquire()
        Traceback (most recent call last):
        ...
        torchcontact.errors.OutputBusyError: ...
        >>> lock_path(out).exists()
        False
    """

    def __init__(self, out: str | Path, what: str = "torchcontact") -> None:
        self.out = Path(out)
        self.path = lock_path(self.out)
        self.what = what
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock or raise at once.

        Raises:
            OutputBusyError: another live process holds it; the message names its pid, host,
                start time and command. Nothing is written.
        """
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise OutputBusyError(self._busy_message()) from None
            except BaseException:
                os.close(fd)
                raise
            # the holder before may have removed the file after this open: lock the live file
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self._fd = fd
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S %z"),
            "command": " ".join([os.path.basename(sys.argv[0]), *sys.argv[1:]])[:300],
            "what": self.what,
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)

    def _busy_message(self) -> str:
        info: dict[str, Any] = {}
        for _ in range(20):  # the holder writes its record right after taking the lock
            try:
                info = json.loads(self.path.read_text() or "{}")
                break
            except (OSError, ValueError):
                time.sleep(0.01)
        who = (
            f"pid {info.get('pid', '?')} on {info.get('host', '?')}, started"
            f" {info.get('started', '?')}"
        )
        cmd = info.get("command")
        return (
            f"{self.out}: another process is writing it ({who}"
            + (f": {cmd}" if cmd else "")
            + "); nothing was written: wait for it to end (or stop it, then rerun;"
            " an interrupted estimate continues with --resume)"
        )

    def release(self) -> None:
        """Remove the lock file and drop the lock (idempotent)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
