"""The on-disk kernel cache: entries with digests, locked and bounded builds, a key index.

Layout under ``<cache>/kernels/`` (``<cache>`` is :func:`torchcontact.kernels.cache_dir`):

* ``<name>/``: one **entry** per generated source, ``<name> = tck[c]_<program>_<source hash>``:
  the source (``<name>.cpp`` or ``.cu``), the library ``<name>.so``, the compiler's output
  ``<name>.log`` and the entry's **record** ``entry.json`` (the library's size and sha256, the
  source's sha256, the compiler, the build time). Libraries and records are written under a
  temporary name, flushed and renamed (``os.replace``): another process sees a whole library or
  none, and the record, renamed last, is the entry's commit point.
* ``index/<key hash>.json``: program key -> entry name (and the source's sha256), so a process
  finds a cached kernel from the program's key without tracing the program again.
* ``.slots/slot-<i>``: the compile slots (:func:`build_slot`); a build of a source cut into
  parts holds every slot free at once (up to one per part) and runs one compiler per slot.

Checked before use (ccache and Bazel's disk cache do the same): a library whose size or sha256
differs from its record is a damaged entry, never loaded; :mod:`torchcontact.kernels` removes
it, warns once and rebuilds it, running eagerly meanwhile.

Locks: ``fcntl.flock`` on ``<name>/build.flock`` (one builder per entry) and on one of the
slot files (at most :func:`build_jobs` compilers at once across every process sharing the
cache). The kernel releases both when the holder dies, and the compiler inherits them, so a
killed builder's compiler still holds its slot until it exits.

This module imports the standard library (and :mod:`torchcontact.errors`) only: it also runs by
path as the detached builder (``python .../_store.py build ENTRY_DIR``), which then needs no torch
(a build process costs a few MB and no import time).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

if __name__ == "__main__":  # run by path as the detached builder: import the package beside it
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchcontact.errors import KernelBuildError  # noqa: E402 - light: no torch

#: Compiler flags of the CPU kernels (IEEE semantics kept: no -ffast-math).
CFLAGS = (
    "-O2",
    "-march=native",
    "-fno-math-errno",
    "-fno-trapping-math",
    "-ffp-contract=fast",
    "-fno-semantic-interposition",
)
#: Compiler flags of the tape VM (:mod:`torchcontact.kernels._vm`): the kernels', and its
#: slots read as vectors of values or of masks (one memory, two types).
VM_FLAGS = (*CFLAGS, "-fno-strict-aliasing")
#: Name prefix of the tape VM's entries (``tck_vm-<dtype>_<hash>``).
VM_PREFIX = "tck_vm-"
#: Flags every CPU kernel build adds: a position-independent shared library, C++17.
LINK_FLAGS = ("-std=c++17", "-shared", "-fPIC")
#: First line of a generated CPU source that is cut into part functions: ``// tc-parts: <n>``.
#: Such a source compiles as several translation units at once (:func:`build`).
PARTS_MARK = "// tc-parts: "
#: The entry's record, written after its library.
RECORD = "entry.json"
#: Environment variable bounding the compilers at once (default :func:`build_jobs`).
JOBS_ENV = "TORCHCONTACT_BUILD_JOBS"
#: Seconds between two attempts at a busy compile slot.
SLOT_POLL_S = 0.2


def cache_dir() -> Path:
    """Root of the on-disk kernel cache (the kernels live in its ``kernels/`` folder).

    ``$TORCHCONTACT_CACHE``, else ``$XDG_CACHE_HOME/torchcontact`` or ``~/.cache/torchcontact``.
    """
    env = os.environ.get("TORCHCONTACT_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "torchcontact"


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def build_jobs() -> int:
    """The most compilers at once: ``$TORCHCONTACT_BUILD_JOBS``, else half the cores, 1 to 4.

    One on a 2-core machine: a kernel build is one compiler of a large straight-line function
    (hundreds of MB, seconds), and a second one would take the core the run itself uses.
    """
    raw = os.environ.get(JOBS_ENV, "")
    if raw.strip():
        try:
            return max(1, int(raw))
        except ValueError:
            pass
    return max(1, min(4, cores() // 2))


def compiler() -> list[str]:
    """The C++ compiler command: ``$CXX`` (split like a shell word list) or ``c++``."""
    return shlex.split(os.environ.get("CXX") or "c++") or ["c++"]


def file_digest(path: Path) -> tuple[int, str]:
    """``(size in bytes, sha256 hex)`` of a file."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
            size += len(chunk)
    return size, h.hexdigest()


def write_source(path: Path, src: str) -> None:
    """Write a generated source (its folder made), atomically, unless it holds ``src`` already."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(OSError):
        if path.read_text() == src:
            return
    write_atomic(path, src)


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write a file under a temporary name beside it, flush it to disk, rename it into place."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------- entries
@dataclass(frozen=True)
class Entry:
    """One kernel of the cache: its folder ``root / name`` and the files in it.

    Attributes:
        root: ``<cache>/kernels``.
        name: ``tck_<program>_<hash>`` (CPU) or ``tckc_<program>_<hash>`` (CUDA).
        suffix: the source's suffix, ``.cpp`` or ``.cu``.
    """

    root: Path
    name: str
    suffix: str = ".cpp"

    @property
    def dir(self) -> Path:
        """The entry's folder."""
        return self.root / self.name

    @property
    def source(self) -> Path:
        """The generated source."""
        return self.dir / f"{self.name}{self.suffix}"

    @property
    def library(self) -> Path:
        """The shared library."""
        return self.dir / f"{self.name}.so"

    @property
    def record_path(self) -> Path:
        """The record (``entry.json``)."""
        return self.dir / RECORD

    @property
    def log(self) -> Path:
        """The last build's compiler output."""
        return self.dir / f"{self.name}.log"

    def record(self) -> dict | None:
        """The record, or None when there is none or it does not parse."""
        try:
            rec = json.loads(self.record_path.read_text())
        except (OSError, ValueError):
            return None
        ok = isinstance(rec, dict) and isinstance(rec.get("size"), int)
        return rec if ok and isinstance(rec.get("sha256"), str) else None

    def check(self) -> tuple[str, str]:
        """The entry's state before its library is loaded.

        Returns:
            ``(state, why)``: ``("ok", "")``; ``("absent", why)`` when it was never built (or
            its build did not finish: no record); ``("damaged", why)`` when the record exists
            and the library is missing, or its size or sha256 differ from the record's.
        """
        rec = self.record()
        if rec is None:
            if self.record_path.exists():
                return "damaged", f"its record {RECORD} does not parse"
            return "absent", "not built"
        try:
            size, digest = file_digest(self.library)
        except OSError:
            return "damaged", f"{self.library.name} is missing"
        if size != rec["size"]:
            return "damaged", f"{self.library.name} has {size} bytes, its record says {rec['size']}"
        if digest != rec["sha256"]:
            return "damaged", f"the sha256 of {self.library.name} differs from its record's"
        return "ok", ""

    def remove_library(self) -> None:
        """Drop the record (first: the entry is then absent) and the library; keep the source."""
        self.record_path.unlink(missing_ok=True)
        self.library.unlink(missing_ok=True)

    def publish(self, built: Path, **info: Any) -> None:
        """Move a finished library into place and write its record (both atomically).

        Args:
            built: the library written under a temporary name in the entry's folder (or on the
                same file system).
            info: further record fields (compiler, seconds).
        """
        with open(built, "rb+") as f:
            os.fsync(f.fileno())  # the data is on disk before the name points at it
        size, digest = file_digest(built)
        os.replace(built, self.library)
        rec = {"name": self.name, "library": self.library.name, "size": size, "sha256": digest,
               "built": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **info}  # fmt: skip
        write_atomic(self.record_path, json.dumps(rec, indent=1))


@contextlib.contextmanager
def build_dir_lock(directory: Path, blocking: bool = True) -> Iterator[IO | None]:
    """Hold the build directory of one kernel for this process, clearing a dead build's baton.

    torch's extension builder guards a build directory with a ``lock`` file that it deletes when
    the build ends; a build killed part-way leaves it behind and every later build of that
    kernel would wait on it forever. Builders here first take an OS file lock (``fcntl.flock``,
    released by the kernel when its process dies) on ``build.flock``, so once it is held any
    ``lock`` file left in the directory belongs to a dead build and is removed.

    Args:
        directory: the entry's folder (created).
        blocking: wait for the lock; with False, yield None at once when another process
            holds it.

    Yields:
        The open lock file (its descriptor can be inherited by the compiler), or None.
    """
    import fcntl

    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / "build.flock", "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            yield None
            return
        try:
            (directory / "lock").unlink(missing_ok=True)
            yield f
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def locked(directory: Path) -> bool:
    """True while some process holds ``directory``'s build lock (a build is under way)."""
    if not (directory / "build.flock").exists():
        return False
    with build_dir_lock(directory, blocking=False) as f:
        return f is None


@contextlib.contextmanager
def build_slot(root: Path, jobs: int | None = None) -> Iterator[IO]:
    """Hold one of ``jobs`` compile slots shared by every process using the cache ``root``.

    Slot ``i`` is ``root/.slots/slot-<i>`` held with ``fcntl.flock``; a builder tries each and
    waits (polling every :data:`SLOT_POLL_S` s) until one is free, so at most ``jobs`` compilers
    run at once across processes.

    Args:
        root: ``<cache>/kernels``.
        jobs: number of slots (default :func:`build_jobs`).

    Yields:
        The open slot file.
    """
    with build_slots(root, jobs) as held:
        yield held[0]


@contextlib.contextmanager
def build_slots(root: Path, jobs: int | None = None, most: int = 1) -> Iterator[list[IO]]:
    """Hold one compile slot (waiting for it), and up to ``most - 1`` more that are free now.

    Like :func:`build_slot`, for a build that runs one compiler per slot it holds.

    Args:
        root: ``<cache>/kernels``.
        jobs: number of slots (default :func:`build_jobs`).
        most: the most slots to hold.

    Yields:
        The open slot files (at least one).
    """
    import fcntl

    jobs = build_jobs() if jobs is None else max(1, int(jobs))
    slots = root / ".slots"
    slots.mkdir(parents=True, exist_ok=True)
    held: list[IO] = []
    try:
        while not held:
            for i in range(jobs):
                if len(held) >= max(1, most):
                    break
                f = open(slots / f"slot-{i}", "a")  # noqa: SIM115 - held across the yield
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    f.close()
                    continue
                held.append(f)
            if not held:
                time.sleep(SLOT_POLL_S)
        yield held
    finally:
        for f in held:
            fcntl.flock(f, fcntl.LOCK_UN)
            f.close()


def source_parts(source: Path) -> int:
    """Part functions of a generated CPU source (its :data:`PARTS_MARK` line); 1 if unmarked."""
    try:
        with open(source, encoding="utf-8", errors="replace") as f:
            line = f.readline(100)
    except OSError:
        return 1
    if line.startswith(PARTS_MARK):
        with contextlib.suppress(ValueError):
            return max(1, int(line[len(PARTS_MARK) :]))
    return 1


def _compile(entry: Entry, tmp: Path, flags: tuple[str, ...], units: int, fds: tuple[int, ...]):
    """Run the compiler(s) of one build; returns ``(command shown in the log, returncode, output)``.

    One unit: one command, source to library. Several (a source cut into parts, several slots
    held): ``units`` compilers at once, unit ``g`` with ``-DTC_GROUPS=units -DTC_GROUP=g`` to an
    object file, then one link of the objects into ``tmp``.

    Raises:
        OSError: the compiler cannot run.
    """
    cxx = compiler()
    if units == 1:
        cmd = [*cxx, *flags, *LINK_FLAGS, "-o", str(tmp), str(entry.source)]
        res = subprocess.run(cmd, capture_output=True, text=True, cwd=entry.dir, pass_fds=fds)
        return shlex.join(cmd), res.returncode, res.stdout + res.stderr
    objs = [tmp.with_name(f"{tmp.name}.{g}.o") for g in range(units)]
    cmds = [[*cxx, *flags, *LINK_FLAGS[:1], "-fPIC", f"-DTC_GROUPS={units}", f"-DTC_GROUP={g}",
             "-c", "-o", str(o), str(entry.source)] for g, o in enumerate(objs)]  # fmt: skip
    link = [*cxx, *flags, *LINK_FLAGS, "-o", str(tmp), *map(str, objs)]
    shown = "\n".join(shlex.join(c) for c in [*cmds, link])
    try:
        procs = []
        try:
            for c in cmds:
                procs.append(subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                              text=True, cwd=entry.dir, pass_fds=fds))  # fmt: skip
        except OSError:
            for p in procs:
                p.kill()
            raise
        outs = [p.communicate()[0] for p in procs]
        codes = [p.returncode for p in procs]
        out = "".join(outs)
        if any(codes):
            return shown, next(c for c in codes if c), out
        res = subprocess.run(link, capture_output=True, text=True, cwd=entry.dir, pass_fds=fds)
        return shown, res.returncode, out + res.stdout + res.stderr
    finally:
        for o in objs:
            o.unlink(missing_ok=True)


def build(entry: Entry, jobs: int | None = None, flags: tuple[str, ...] = CFLAGS) -> Path:
    """Compile an entry's C++ source into its library (or find it built), publish it atomically.

    Holds the entry's build lock (one builder per entry: a second one waits, then finds the
    entry built), then a compile slot while the compiler runs. The compiler writes
    ``<name>.so.<pid>.tmp``; :meth:`Entry.publish` renames it and writes the record (with
    ``units``, the compilers the build ran at once).

    A source cut into parts (:data:`PARTS_MARK`) also takes the slots that are free at once, up
    to one per part, and compiles one translation unit per slot held, all at once (object files
    ``<name>.so.<pid>.tmp.<unit>.o``, then linked): on a machine with several slots a large
    kernel builds in a fraction of the time, and never with more compilers than
    :func:`build_jobs` across the cache's processes.

    Args:
        entry: the entry (its source written).
        jobs: compile slots (default :func:`build_jobs`).
        flags: compiler flags.

    Returns:
        The library's path.

    Raises:
        KernelBuildError: no source, a compiler that cannot run or fails (the message ends with the
            tail of its output, kept in ``entry.log``).
    """
    with build_dir_lock(entry.dir) as lock:
        if entry.check()[0] == "ok":  # another process built it while this one waited
            return entry.library
        for stale in entry.dir.glob(f"{entry.name}.so.*.tmp"):  # builds killed part-way
            stale.unlink(missing_ok=True)
        if not entry.source.is_file():
            raise KernelBuildError(f"building kernel {entry.name} failed: no source {entry.source}")
        entry.remove_library()
        source_sha256 = file_digest(entry.source)[1]
        tmp = entry.dir / f"{entry.name}.so.{os.getpid()}.tmp"
        for stale in entry.dir.glob(f"{entry.name}.so.*.tmp.*.o"):
            stale.unlink(missing_ok=True)
        cxx = compiler()
        parts = source_parts(entry.source) if entry.source.suffix == ".cpp" else 1
        # a source cut into parts compiles on every slot free now (one at least): units at once
        with build_slots(entry.root, jobs, most=parts) as slots:
            t0 = time.perf_counter()
            fds = (*(f.fileno() for f in slots), lock.fileno())
            try:
                shown, code, output = _compile(entry, tmp, flags, len(slots), fds)
            except OSError as e:
                write_atomic(entry.log, f"{shlex.join([*cxx, *flags])}\n{e}\n")
                raise KernelBuildError(
                    f"building kernel {entry.name} failed: the compiler {cxx[0]!r} cannot run"
                    f" ({e.strerror or e}); set CXX to a C++ compiler"
                ) from None
            seconds = time.perf_counter() - t0
        write_atomic(entry.log, f"{shown}\n{output}")
        if code != 0 or not tmp.is_file():
            tmp.unlink(missing_ok=True)
            tail = output.strip()[-1500:]
            raise KernelBuildError(
                f"building kernel {entry.name} failed: {cxx[0]} exited with {code}: {tail}"
            )
        entry.publish(tmp, compiler=shlex.join(cxx), seconds=round(seconds, 2),
                      units=len(slots), source_sha256=source_sha256)  # fmt: skip
    return entry.library


def spawn_build(
    entry: Entry | list[Entry], jobs: int | None = None, nice: int = 0
) -> subprocess.Popen:
    """Start :func:`build` of ``entry`` (or of several, in order) in a detached process.

    The process runs this file by path (the standard library only, no torch), in its own
    session, so the build finishes and fills the cache even when the process that asked for it
    exits first (a short CLI run). Its failures go to each ``entry.log``.

    Args:
        entry: the entry (its source written), or entries built in order (the tape VM first,
            then the kernel the VM runs meanwhile).
        jobs: compile slots (default :func:`build_jobs`).
        nice: priority increment of the kernels' compilers (``os.nice``; 19: they run on the
            CPU time other processes leave), taken after the tape VM's build.

    Returns:
        The builder process.
    """
    entries = entry if isinstance(entry, list) else [entry]
    cmd = [sys.executable, "-I", str(Path(__file__).resolve()), "build",
           *(str(e.dir) for e in entries)]  # fmt: skip
    if jobs is not None:
        cmd += ["--jobs", str(jobs)]
    if nice and hasattr(os, "nice"):
        cmd += ["--nice", str(int(nice))]
    return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip


# ---------------------------------------------------------------------------------------- index
def index_path(root: Path, key_hash: str) -> Path:
    """Index record of a program key's hash."""
    return root / "index" / f"{key_hash}.json"


def read_index(root: Path, key_hash: str) -> dict | None:
    """``{"entry", "source_sha256", ...}`` of a key, or None."""
    try:
        rec = json.loads(index_path(root, key_hash).read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(rec, dict) and isinstance(rec.get("entry"), str)
    return rec if ok and "/" not in rec["entry"] and rec["entry"] not in ("", ".", "..") else None


def write_index(root: Path, key_hash: str, record: dict) -> None:
    """Write a key's index record atomically."""
    path = index_path(root, key_hash)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps(record, indent=1))


# ------------------------------------------------------------------------------ info and clear
def _size(path: Path) -> int:
    total = 0
    for p in path.rglob("*"):
        with contextlib.suppress(OSError):
            if p.is_file():
                total += p.stat().st_size
    return total


def entries(root: Path) -> list[dict]:
    """Every entry of the cache with its state, library size and folder size.

    States: ``ok``; ``building`` (a process holds its build lock); ``failed`` (no library, a
    compiler log); ``source only`` (never built); ``damaged: <why>``.
    """
    out = []
    if not root.is_dir():
        return out
    for d in sorted(root.iterdir()):
        if not d.is_dir() or not d.name.startswith("tck"):
            continue
        suffix = ".cu" if d.name.startswith("tckc_") else ".cpp"
        e = Entry(root, d.name, suffix)
        state, why = e.check()
        if locked(d):
            state = "building"
        elif state == "damaged":
            state = f"damaged: {why}"
        elif state == "absent" and e.library.exists():
            state = "unrecorded (an older or unfinished build)"
        elif state == "absent":
            state = "failed" if e.log.exists() else "source only"
        rec = e.record() or {}
        out.append({"name": d.name, "state": state, "library_bytes": rec.get("size"),
                    "bytes": _size(d), "built": rec.get("built")})  # fmt: skip
    return out


def info(root: Path) -> dict:
    """The cache's location, compile bound, entries and index size (``cache info``)."""
    idx = root / "index"
    return {
        "location": str(root),
        "build_jobs": build_jobs(),
        "entries": entries(root),
        "index_keys": len(list(idx.glob("*.json"))) if idx.is_dir() else 0,
        "bytes": _size(root) if root.is_dir() else 0,
    }


def clear(root: Path) -> dict:
    """Empty the cache, but for the entries being built (``cache clear``).

    Returns:
        ``{"removed": entries removed, "bytes": bytes freed, "busy": names left (building)}``.
    """
    removed, freed, busy = 0, 0, []
    if not root.is_dir():
        return {"removed": 0, "bytes": 0, "busy": []}
    for d in sorted(root.iterdir()):
        if not d.is_dir() or d.name in (".slots",):
            continue
        size = _size(d)
        if d.name.startswith("tck"):
            with build_dir_lock(d, blocking=False) as held:
                if held is None:
                    busy.append(d.name)
                    continue
                shutil.rmtree(d, ignore_errors=True)
            removed += 1
        else:
            shutil.rmtree(d, ignore_errors=True)
        freed += size
    return {"removed": removed, "bytes": freed, "busy": busy}


def _human(n: int | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return str(n)  # pragma: no cover


def format_info(data: dict) -> str:
    """``cache info`` as text: the location, the bound, one line per entry."""
    lines = [
        f"kernel cache: {data['location']}",
        f"entries: {len(data['entries'])} ({_human(data['bytes'])}); index: {data['index_keys']}"
        f" program keys; compilers at once: {data['build_jobs']} (${JOBS_ENV})",
    ]
    for e in data["entries"]:
        lines.append(f"  {e['name']}  {e['state']}  library {_human(e['library_bytes'])}"
                     f"  folder {_human(e['bytes'])}  built {e['built'] or '-'}")  # fmt: skip
    return "\n".join(lines)


def lower_priority(nice: int) -> None:
    """Lower this process's CPU priority by ``nice`` (its compilers inherit it).

    ``os.nice`` alone does not do it for a detached builder on Linux with autogroup scheduling
    (``/proc/sys/kernel/sched_autogroup_enabled``): the builder's own session is a scheduling
    group of its own, weighed equally against the run's whatever the nice values inside it.
    The group's nice (``/proc/self/autogroup``) is lowered too.
    """
    with contextlib.suppress(OSError, ValueError):
        os.nice(nice)
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(max(-20, min(19, nice))))


def flags_for(entry: Entry) -> tuple[str, ...]:
    """Compiler flags of an entry: :data:`CFLAGS`, or :data:`VM_FLAGS` for the tape VM's."""
    return VM_FLAGS if entry.name.startswith(VM_PREFIX) else CFLAGS


def main(argv: list[str]) -> int:
    """The detached builder: ``python _store.py build ENTRY_DIR... [--jobs N] [--nice N]``.

    Builds the entries in order; ``--nice`` lowers the priority before the first entry that is
    not the tape VM (the run waits for the VM, not for its kernels).
    """
    if len(argv) < 2 or argv[0] != "build":
        print("usage: _store.py build ENTRY_DIR... [--jobs N] [--nice N]", file=sys.stderr)
        return 2
    opts = {argv[i]: argv[i + 1] for i in range(len(argv) - 1) if argv[i].startswith("--")}
    dirs = [Path(a) for i, a in enumerate(argv[1:], 1)
            if not a.startswith("--") and not argv[i - 1].startswith("--")]  # fmt: skip
    jobs = int(opts["--jobs"]) if "--jobs" in opts else None
    rc = 0
    for d in dirs:
        entry = Entry(d.parent, d.name, ".cu" if d.name.startswith("tckc_") else ".cpp")
        if "--nice" in opts and not d.name.startswith(VM_PREFIX):
            lower_priority(int(opts.pop("--nice")))
        try:
            build(entry, jobs, flags_for(entry))
        except Exception as e:  # noqa: BLE001 - the caller reads the log (stdout is not kept)
            with contextlib.suppress(OSError):
                with open(entry.log, "a") as f:
                    f.write(f"\n{e}\n")
            rc = 1
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
