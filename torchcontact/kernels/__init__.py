"""Per-robot kernels generated from one Python source of the physics.

A :class:`Program` is a physics function written on scalars (:mod:`torchcontact._scalar`): it
maps named input arrays (``k`` scalars per frame each) to named output arrays. One program runs on
three backends:

* ``"eager"``: the function runs on torch tensors, one ``(N,)`` tensor per scalar. Always
  available, differentiable, any device and dtype; the reference the others are tested against.
* ``"cpu"``: the function runs once on symbols (:class:`torchcontact._scalar.Trace`); the SSA
  graph becomes straight-line C++ on vectors of frames (:mod:`torchcontact.kernels._cpp`),
  compiled into a shared library (``$CXX`` or ``c++``) and called through ctypes, the frames
  split over ``torch.get_num_threads()`` threads.
* ``"cuda"``: the same graph as a CUDA kernel, one thread per frame
  (:mod:`torchcontact.kernels._cuda`).
* the **tape VM** (:mod:`torchcontact.kernels._vm`, :func:`vm_kernel`): one C++ interpreter per
  machine and dtype (a second or two of the compiler, once) runs any program's graph encoded as
  bytecode, blocks of frames per instruction: several times eager torch's speed, a fraction of
  the compiled kernel's, without a per-program build. ``auto`` and ``cached`` use it on CPU
  while a program's kernel is not built (not a ``backend`` value of its own).

Builds are cached on disk (:mod:`torchcontact.kernels._store`) under ``$TORCHCONTACT_CACHE``
(default ``$XDG_CACHE_HOME/torchcontact`` or ``~/.cache/torchcontact``), one entry per generated
source (named by the hash of the source, the torch version and the CPU), so a later process loads
a kernel in milliseconds. An index maps each program's key (with a digest of torchcontact's code)
to its entry, so a cached kernel is found without tracing the program again. Each entry records
its library's size and sha256; a library is checked before it is loaded, and a damaged one warns,
is removed and rebuilt (never a crash). Libraries are published atomically, one builder per entry
(a build lock) and at most ``$TORCHCONTACT_BUILD_JOBS`` compilers at once across processes.

``backend="auto"`` uses a compiled kernel when one is loaded or cached. Otherwise (large batches
only) it runs the program on the tape VM, and the kernel is built once the process exits, in a
detached process at low priority (``nice 19``), for later runs (:func:`background_note` says
so). On a machine whose cache has no VM yet, a detached process first builds the VM and the call
waits for it (at most :data:`VM_WAIT_S`; eager after that). ``$TORCHCONTACT_VM``
(:data:`VM_ENV`): ``behind`` builds the kernel during the run (the run switches to it at the
first call after the build), ``only`` never builds kernels under ``auto``, ``0`` turns the VM
off (eager while the kernel builds, as before the VM). A build failure or a missing compiler
warns once and stays eager.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import subprocess
import threading
import warnings
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from torchcontact import _lightkernels
from torchcontact._digest import code_digest
from torchcontact._scalar import Sym, Trace, float_dtype
from torchcontact.errors import KernelBuildError
from torchcontact.kernels import _csource, _store
from torchcontact.kernels._store import build_dir_lock, cache_dir

#: The machine's tag and vector width (:mod:`torchcontact.kernels._csource`, which the VM's early
#: build uses without torch): a ``-march=native`` build only runs where it was built.
_machine_tag = _csource.machine_tag
_vector_bytes = _csource.vector_bytes

__all__ = [
    "BACKENDS",
    "CFLAGS",
    "Program",
    "background_builds",
    "background_note",
    "build_dir_lock",
    "build_source",
    "cache_dir",
    "code_digest",
    "compiled",
    "prepare_vm",
    "run",
    "start_deferred_builds",
    "vm_enabled",
    "vm_kernel",
    "wait_for_builds",
]

#: Accepted ``backend`` arguments. ``"cached"``: the kernel when it is built already (loaded or
#: in the disk cache), else the tape VM, else eager, and never a kernel build during the run (a
#: short side computation, such as a log's contact-free noise estimate, must not take the
#: compile slot from the run's own kernel; a program the VM ran gets its kernel built once the
#: process exits); from :data:`AUTO_BUILD_MIN_FRAMES` frames it builds the VM (once per machine
#: and dtype, under a second of the compiler) when the cache has none.
BACKENDS = ("auto", "eager", "cpu", "cuda", "cached")

#: Batches at least this large start a background build under ``backend="auto"``.
AUTO_BUILD_MIN_FRAMES = _lightkernels.AUTO_BUILD_MIN_FRAMES

_VERSION = "2"  # bump when the generated code's calling convention or the cache changes


@dataclass(frozen=True, eq=False)
class Program:
    """A physics program on scalars with its input and output layout.

    Attributes:
        name: short name (used in file names and messages).
        fn: ``fn(inputs: dict[str, list[Scalar]]) -> dict[str, list[Scalar]]``.
        inputs: input name -> scalars per frame, in calling order.
        outputs: output name -> scalars per frame, in order.
        key: a string that identifies the program's constants (model hash, layout, gravity...);
            two programs with one key must compute the same function.
    """

    name: str
    fn: Callable[[dict[str, list]], dict[str, list]]
    inputs: dict[str, int]
    outputs: dict[str, int]
    key: str
    _traced: dict = field(default_factory=dict, repr=False)

    def trace(self) -> tuple[Trace, dict[str, list]]:
        """Run the program on symbols (once; cached)."""
        if "t" not in self._traced:
            tr = Trace()
            syms = {k: tr.input(k, n) for k, n in self.inputs.items()}
            out = self.fn(syms)
            self._check_outputs(out)
            self._traced["t"] = (tr, out)
        return self._traced["t"]

    def _check_outputs(self, out: Mapping[str, list]) -> None:
        got = {k: len(v) for k, v in out.items()}
        if got != self.outputs:
            raise ValueError(f"program {self.name}: outputs {got}, declared {self.outputs}")


# --------------------------------------------------------------------------------------- eager


def run_eager(program: Program, tensors: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Run ``program`` on torch tensors ``(N, k)`` per input; returns ``(N, k)`` per output."""
    like = next(iter(tensors.values()))
    cols = {k: list(tensors[k].T.unbind(0)) for k in program.inputs}
    with float_dtype(like.dtype):
        out = program.fn(cols)
    program._check_outputs(out)
    n = like.shape[0]
    res = {}
    for k, xs in out.items():
        if not xs:
            res[k] = like.new_zeros(n, 0)
            continue
        res[k] = torch.stack(
            [x if isinstance(x, Tensor) else like.new_full((n,), float(x)) for x in xs], 1
        )
    return res


# ------------------------------------------------------------------------------------- compiled

_DTYPES = {torch.float64: "double", torch.float32: "float"}
_lock = threading.Lock()
_loaded: dict[str, Callable] = {}
_failed: dict[str, str] = {}
_building: dict[str, threading.Thread | _Build] = {}
#: (ckey, cache folder) -> the entry of a CPU kernel found not built by a call that does not
#: build (``auto`` while the VM runs the program, ``cached``): later calls stat its library
#: instead of checking the entry again (1.8 ms a chunk, 0.23 s per 1 M frames of a first run)
_unbuilt: dict[tuple[str, str], _store.Entry] = {}
_warned: set[str] = set()
_healed: set[str] = set()
_pool: ThreadPoolExecutor | None = None

#: Compiler flags of the CPU kernels (IEEE semantics kept: no -ffast-math).
CFLAGS = _store.CFLAGS


class _Unloadable(Exception):
    """A checked library that does not load (a damaged entry)."""


def _source(program: Program, dtype: torch.dtype) -> tuple[str, str]:
    """The C++ source of ``program`` and its hash (traces the program)."""
    from torchcontact.kernels import _cpp

    tr, out = program.trace()
    src = _cpp.emit(tr, out, _DTYPES[dtype], vbytes=_vector_bytes())
    h = hashlib.sha256(
        f"{_VERSION}|{torch.__version__}|{_machine_tag()}|{src}".encode()
    ).hexdigest()[:20]
    return src, h


def _paths(program: Program, h: str) -> tuple[str, Path, Path]:
    """Name, source file and shared library of a CPU kernel in the cache."""
    name = f"tck_{program.name}_{h}"
    e = _store.Entry(cache_dir() / "kernels", name)
    return name, e.source, e.library


def _key_hash(program: Program, dtype: torch.dtype) -> str:
    """Hash of what determines a CPU kernel's source without tracing: code, key, machine."""
    ident = (f"{_VERSION}|{code_digest()}|{torch.__version__}|{_machine_tag()}|"
             f"{_vector_bytes()}|{program.name}|{program.key}|{dtype}")  # fmt: skip
    return hashlib.sha256(ident.encode()).hexdigest()[:32]


def _cpu_entry(program: Program, dtype: torch.dtype) -> tuple[_store.Entry, tuple[str, str]]:
    """The cache entry of a CPU kernel and its state (:meth:`_store.Entry.check`).

    The index maps the program's key hash (:func:`_key_hash`) to the entry: a kernel in the
    cache is found without tracing the program (when the source it was built from has the
    sha256 the index records), and one not yet built is built from the source the entry keeps
    (when that source has it). Otherwise the program is traced, its source written to the entry
    and the index updated.
    """
    root = cache_dir() / "kernels"
    kh = _key_hash(program, dtype)
    rec = _store.read_index(root, kh)
    if rec is not None:
        entry = _store.Entry(root, rec["entry"])
        state = entry.check()
        built_from = (entry.record() or {}).get("source_sha256")
        if state[0] == "ok" and built_from == rec.get("source_sha256"):
            return entry, state
        with contextlib.suppress(OSError):
            if _store.file_digest(entry.source)[1] == rec.get("source_sha256"):
                return entry, state
    src, h = _source(program, dtype)
    _save_bytecode(program, kh)  # the VM's code of the same trace: no second trace for it
    program._traced.clear()  # the source is all the cache needs: free the trace's memory
    name, cpp, _ = _paths(program, h)
    _store.write_source(cpp, src)
    record = {"entry": name, "source_sha256": hashlib.sha256(src.encode()).hexdigest(),
              "program": program.name, "dtype": str(dtype), "key": program.key}  # fmt: skip
    _store.write_index(root, kh, record)
    entry = _store.Entry(root, name)
    return entry, entry.check()


def _load(entry: _store.Entry, program: Program, dtype: torch.dtype) -> Callable:
    """Load a checked entry's library and wrap its kernel.

    Raises:
        _Unloadable: the dynamic loader refuses it, or it lacks the kernel's symbol.
    """
    try:
        fn = ctypes.CDLL(str(entry.library)).tc_kernel
    except (OSError, AttributeError) as e:
        raise _Unloadable(f"{entry.library.name} does not load ({e})") from None
    return _wrap(fn, program, dtype)


def _load_built(entry: _store.Entry, program: Program, dtype: torch.dtype) -> Callable:
    """Load an entry just built (here or by a detached builder).

    Raises:
        KernelBuildError: the build failed (the message ends with its log), or its library does
            not check or load.
    """
    state, why = entry.check()
    if state != "ok":
        try:
            log = entry.log.read_text().strip()[-2000:]
        except OSError:
            log = "no log"
        raise KernelBuildError(f"building kernel {entry.name} failed ({why}): {log}")
    try:
        return _load(entry, program, dtype)
    except _Unloadable as e:
        raise KernelBuildError(f"kernel {entry.name} failed to load after its build: {e}") from None


def _build_now(entry: _store.Entry, program: Program, dtype: torch.dtype) -> Callable:
    try:
        _store.build(entry)
    except OSError as e:  # the cache cannot be written (full disk, read-only)
        where = f"{e.filename}: " if e.filename else ""
        raise KernelBuildError(f"building kernel {entry.name} failed: {where}{e}") from None
    return _load_built(entry, program, dtype)


def build_source(name: str, cpp: Path) -> Path:
    """Compile one kernel source of the cache (or find it built); returns the library's path.

    The library is published atomically with its record (:func:`_store.build`): the build
    lock of the entry, a compile slot, a temporary name, a rename.

    Args:
        name: the entry's name (``tck_<program>_<hash>``).
        cpp: its source, ``<cache>/kernels/<name>/<name>.cpp``.

    Raises:
        KernelBuildError: the compiler is missing or fails.
    """
    return _store.build(_store.Entry(Path(cpp).parent.parent, name, Path(cpp).suffix))


def _wrap(fn, program: Program, dtype: torch.dtype, lead: tuple = (), block: int = 16) -> Callable:
    """``call(tensors) -> outputs`` of a C kernel ``fn(n, in, in_stride, out, out_stride)``.

    Args:
        fn: the ctypes function (its ``argtypes`` are set here unless ``lead`` is given).
        program: the program (input and output arrays, in order).
        dtype: the kernel's dtype.
        lead: ctypes arguments passed before ``n`` (the VM's bytecode); the caller sets
            ``fn.argtypes`` and ``fn.restype`` (a non-zero ``int`` result raises MemoryError).
        block: frames a piece of a threaded call is a multiple of.
    """
    if not lead:
        fn.restype = None
        fn.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                       ctypes.c_void_p]  # fmt: skip
    names_in, names_out = list(program.inputs), list(program.outputs)

    def call(tensors: Mapping[str, Tensor]) -> dict[str, Tensor]:
        first = tensors[names_in[0]]
        n = first.shape[0]
        ins = [tensors[k].contiguous() for k in names_in]
        for k, x in zip(names_in, ins, strict=True):
            if x.dtype != dtype or x.device.type != "cpu" or x.dim() != 2 or x.shape[0] != n:
                raise ValueError(f"kernel input {k}: expected ({n}, k) {dtype} on cpu")
        outs = {k: torch.empty(n, m, dtype=dtype) for k, m in program.outputs.items()}
        outl = [outs[k] for k in names_out]
        nthreads = max(1, torch.get_num_threads())
        if n < 1024 or nthreads == 1:
            _invoke(fn, 0, n, ins, outl, lead)
        else:
            # several pieces per thread, taken as threads come free: a thread the OS does not
            # schedule (a busy neighbour on the other core) holds back one piece, not half
            pool = _get_pool(nthreads)
            step = max(512, -(-n // (4 * nthreads)))
            step = -(-step // block) * block  # whole blocks per piece
            futs = [pool.submit(_invoke, fn, s, min(n, s + step), ins, outl, lead)
                    for s in range(0, n, step)]  # fmt: skip
            for f in futs:
                f.result()
        return outs

    return call


def _get_pool(n: int) -> ThreadPoolExecutor:
    global _pool
    with _lock:
        if _pool is None or _pool._max_workers < n:
            _pool = ThreadPoolExecutor(n, thread_name_prefix="torchcontact-kernel")
        return _pool


def _invoke(fn, s: int, e: int, ins: list[Tensor], outs: list[Tensor], lead: tuple = ()) -> None:
    """Call the kernel on frames ``[s, e)`` (row offsets into each array; ctypes drops the GIL)."""
    if e <= s:
        return
    ptr = ctypes.c_void_p
    in_p = (ptr * len(ins))(*[x.data_ptr() + s * x.stride(0) * x.element_size() for x in ins])
    in_s = (ctypes.c_int64 * len(ins))(*[x.stride(0) for x in ins])
    out_p = (ptr * len(outs))(*[x.data_ptr() + s * x.stride(0) * x.element_size() for x in outs])
    out_s = (ctypes.c_int64 * len(outs))(*[x.stride(0) for x in outs])
    if fn(*lead, e - s, in_p, in_s, out_p, out_s):
        raise MemoryError("the kernel could not allocate its working memory")


def _heal(ckey: str, entry: _store.Entry, why: str, wait: bool) -> bool:
    """A damaged entry: warn, remove its library (unless a build holds it); once per kernel.

    Returns:
        False when this kernel was healed before in this process (its rebuild is damaged too).
    """
    if ckey in _healed:
        return False
    _healed.add(ckey)
    warnings.warn(
        f"kernel cache entry {entry.dir} is damaged ({why}): removed and rebuilt"
        + ("" if wait else "; running eagerly meanwhile"),
        RuntimeWarning,
        stacklevel=4,
    )
    with _store.build_dir_lock(entry.dir, blocking=False) as held:
        if held is not None:  # else a builder holds it: it replaces the library
            entry.remove_library()
    return True


def compiled(
    program: Program,
    dtype: torch.dtype,
    device: torch.device | str = "cpu",
    wait: bool = True,
    build: bool = True,
) -> Callable | None:
    """The compiled kernel of ``program`` for ``dtype`` on ``device``.

    A kernel in the disk cache is checked (size and sha256 against its entry's record) before
    it is loaded; a damaged entry (missing, short, altered or unloadable library) warns once,
    is removed and rebuilt, and the caller runs eagerly meanwhile (``wait=False``).

    Args:
        program: the program.
        dtype: float32 or float64.
        device: ``cpu`` (generated C++) or ``cuda`` (generated CUDA).
        wait: build now and return the kernel (raises :class:`KernelBuildError` on failure); with
            False, return the kernel if it is loaded or in the disk cache, else start a background
            build (a detached process for CPU kernels, bounded by the cache's compile slots) and
            return None.
        build: with ``wait=False``, False returns None for a kernel not built yet instead of
            starting its build (a damaged entry is still healed).

    Returns:
        ``call(tensors: dict[str, (N, k) Tensor]) -> dict[str, (N, k) Tensor]`` or None.
    """
    device = torch.device(device)
    if dtype not in _DTYPES:
        raise KernelBuildError(f"no kernel for dtype {dtype}; use float32 or float64")
    if device.type not in ("cpu", "cuda"):
        raise KernelBuildError(f"no kernel backend for device {device}")
    ckey = f"{program.key}|{dtype}|{device.type}"
    with _lock:
        if ckey in _loaded:
            return _loaded[ckey]
        if ckey in _failed:
            if wait:
                raise KernelBuildError(_failed[ckey])
            return None
        pending = _building.get(ckey)
    if pending is not None:
        if isinstance(pending, _Build):
            if not (wait or pending.done()):
                return None
            pending.join()
            with _lock:
                _building.pop(ckey, None)
            return _finish(ckey, pending.result, raise_=wait)
        if not wait:
            return None
        pending.join()
        return compiled(program, dtype, device, wait)
    if device.type == "cuda":
        return _compiled_cuda(program, dtype, ckey, wait) if wait or build else None
    try:
        return _compiled_cpu(program, dtype, ckey, wait, build)
    except OSError as e:  # an unwritable or full cache: eager, never a crash
        where = f"{e.filename}: " if e.filename else ""
        msg = f"kernel cache {cache_dir() / 'kernels'}: {where}{e.strerror or e}"
        return _finish(ckey, _failing(msg), raise_=wait)


def _compiled_cpu(
    program: Program, dtype: torch.dtype, ckey: str, wait: bool, build: bool = True
) -> Callable | None:
    """The CPU kernel from the cache: checked, healed, built now or by a detached process."""
    memo = (ckey, str(cache_dir()))
    if not (wait or build):
        with _lock:
            unbuilt = _unbuilt.get(memo)
        if unbuilt is not None and not unbuilt.library.exists():
            return None  # still not built (each chunk of a run on the VM asks)
    entry, (state, why) = _cpu_entry(program, dtype)
    if state != "absent" or wait or build:
        with _lock:
            _unbuilt.pop(memo, None)
    if state == "ok":
        try:
            return _finish(ckey, lambda: _load(entry, program, dtype), raise_=wait)
        except _Unloadable as e:
            state, why = "damaged", str(e)
    if state == "damaged" and not _heal(ckey, entry, why, wait):
        why = f"kernel cache entry {entry.dir} is damaged again after its rebuild ({why})"
        return _finish(ckey, _failing(why), raise_=wait)
    if wait:
        return _finish(ckey, lambda: _build_now(entry, program, dtype), raise_=True)
    if not build:
        if state == "absent":
            with _lock:
                _unbuilt[memo] = entry
        return None
    # the VM runs the program meanwhile: the kernel builds on the cores the run leaves
    nice = KERNEL_BUILD_NICE if _vm_state(dtype) == "ready" else 0
    with _lock:  # one builder per kernel, also when several threads ask at once
        if ckey not in _building and ckey not in _loaded:
            proc = _store.spawn_build(entry, nice=nice)
            _building[ckey] = _Build(proc, entry, lambda: _load_built(entry, program, dtype))
    return None


def _compiled_cuda(program: Program, dtype: torch.dtype, ckey: str, wait: bool) -> Callable | None:
    """The CUDA kernel: built in a thread of this process (nvcc needs the CUDA toolkit here)."""
    from torchcontact.kernels import _cuda

    if not torch.cuda.is_available():
        return _finish(ckey, _no_cuda, raise_=wait)

    def build() -> Callable:
        return _cuda.build(program, dtype, cache_dir())

    if wait:
        return _finish(ckey, build, raise_=True)
    t = threading.Thread(
        target=_finish, args=(ckey, build, False), name=f"torchcontact-build-{program.name}",
        daemon=True,
    )  # fmt: skip
    with _lock:
        _building[ckey] = t
    t.start()
    return None


@dataclass
class _Build:
    """A kernel being compiled by a detached process (:func:`_store.spawn_build`)."""

    proc: subprocess.Popen
    entry: _store.Entry
    result: Callable[[], Callable]  # loads the kernel once the process has ended

    def join(self, timeout: float | None = None) -> None:
        """Wait for the process."""
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout)

    def done(self) -> bool:
        return self.proc.poll() is not None


def wait_for_builds(timeout: float | None = None) -> None:
    """Wait until the kernels building in the background are built (or failed).

    Args:
        timeout: seconds to wait for each build (None: until it ends).
    """
    start_deferred_builds()
    with _lock:
        pending = [*_vm_builds.values(), *_building.values()]
    for b in pending:
        b.join(timeout)


def background_builds() -> list[str]:
    """Names of the kernels this process is building, or builds when it exits.

    The latter are the kernels of programs the tape VM ran (:func:`_defer_build`). Their
    builds are detached processes: they go on, and fill the cache, after this process exits.
    """
    with _lock:
        later = [entry.name for _, _, entry in _deferred.values()]
        return [b.entry.name for b in _building.values()
                if isinstance(b, _Build) and not b.done()] + later  # fmt: skip


def background_note(before: Collection[str] = ()) -> str | None:
    """One line saying which kernel builds go on after this process (for a CLI's stderr).

    Args:
        before: :func:`background_builds` at the start of a command: only the builds the
            command added are named.
    """
    names = [n for n in background_builds() if n not in set(before)]
    if not names:
        return None
    n = len(names)
    return (
        f"note: {n} kernel build{'s go' if n > 1 else ' goes'} on in the background"
        f" ({', '.join(names)}) and fill{'' if n > 1 else 's'} the cache"
        f" {cache_dir() / 'kernels'} for later runs"
    )


def _failing(msg: str) -> Callable[[], Callable]:
    def build() -> Callable:
        raise KernelBuildError(msg)

    return build


def _no_cuda() -> Callable:
    raise KernelBuildError("CUDA kernels need a CUDA device and a CUDA build of torch")


def _finish(ckey: str, build: Callable[[], Callable], raise_: bool) -> Callable | None:
    """Build (or load) a kernel and record the outcome; a failure warns once."""
    try:
        k = build()
    except KernelBuildError as e:
        with _lock:
            _failed[ckey] = str(e)
            _building.pop(ckey, None)
        if ckey not in _warned:
            _warned.add(ckey)
            warnings.warn(f"{e}; using the eager torch backend", RuntimeWarning, stacklevel=3)
        if raise_:
            raise
        return None
    with _lock:
        _loaded[ckey] = k
        _building.pop(ckey, None)
    return k


def run(
    program: Program, tensors: Mapping[str, Tensor], backend: str = "auto"
) -> dict[str, Tensor]:
    """Run ``program`` on ``(N, k)`` tensors with the chosen backend.

    Args:
        program: the program.
        tensors: input name -> ``(N, k)`` tensor (one dtype and device).
        backend: ``"auto"`` (compiled if ready, else eager while it builds), ``"eager"``,
            ``"cpu"`` or ``"cuda"`` (build now; :class:`KernelBuildError` on failure),
            ``"cached"`` (compiled if built already, else the tape VM, else eager; no kernel
            build during the run).

    Returns:
        Output name -> ``(N, k)`` tensor.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; expected one of {BACKENDS}")
    first = next(iter(tensors.values()))
    if backend == "eager" or (backend == "auto" and (first.requires_grad or _tracing())):
        return run_eager(program, tensors)
    if backend in ("cpu", "cuda"):
        if first.device.type != backend:
            raise ValueError(f"backend {backend!r} needs inputs on {backend}, got {first.device}")
        return compiled(program, first.dtype, first.device, wait=True)(tensors)
    k = _usable_kernel(program, first, backend)
    if k is None:
        return run_eager(program, tensors)
    return k(tensors)


def _usable_kernel(program: Program, like: Tensor, backend: str) -> Callable | None:
    """The compiled kernel ``backend`` ``"auto"`` or ``"cached"`` runs ``program`` with, or None.

    None (run eagerly) for inputs that need gradients, while tracing, and for a dtype or device
    without kernels. ``"auto"`` asks for the kernel of a batch of at least
    :data:`AUTO_BUILD_MIN_FRAMES` frames (starting its background build) or of a kernel already
    loaded; ``"cached"`` takes it only when built already and starts no kernel build during
    the run. On
    CPU, the tape VM where the kernel is not built (:func:`_usable_cpu`).
    """
    if like.requires_grad or _tracing():
        return None
    if like.dtype not in _DTYPES or like.device.type not in ("cpu", "cuda"):
        return None
    if like.device.type == "cpu":
        return _usable_cpu(program, like.dtype, backend, like.shape[0])
    if backend == "cached":
        return compiled(program, like.dtype, like.device, wait=False, build=False)
    if like.shape[0] >= AUTO_BUILD_MIN_FRAMES or _ready(program, like):
        return compiled(program, like.dtype, like.device, wait=False)
    return None


def _usable_cpu(program: Program, dtype: torch.dtype, backend: str, n: int) -> Callable | None:
    """The CPU kernel, else the tape VM, that ``"auto"``/``"cached"`` run ``program`` with.

    The compiled kernel when it is loaded or in the cache. Otherwise the VM (:func:`vm_kernel`)
    runs the program: ``"cached"`` (building the VM alone, from :data:`AUTO_BUILD_MIN_FRAMES`
    frames, when the cache has none; the program's kernel builds once the process exits, as
    :func:`_defer_build` has it, never during the run); ``"auto"`` (from
    :data:`AUTO_BUILD_MIN_FRAMES` frames, or for a program already running) also building the
    VM once per machine in a detached process (waiting for it up to :data:`VM_WAIT_S`), which then
    builds the program's kernel at low priority (:data:`KERNEL_BUILD_NICE`; not with
    ``$TORCHCONTACT_VM=only``). The run switches to the kernel at the first call after its
    build. None (eager) when neither is usable.
    """
    if backend == "cached":
        k = compiled(program, dtype, "cpu", wait=False, build=False)
        if k is not None or n < AUTO_BUILD_MIN_FRAMES:
            return k if k is not None else vm_kernel(program, dtype, build=False)
        # the VM is the machine's, not the program's: a short build, no kernel build after it
        vm = vm_kernel(program, dtype, build=True, kernel_after=False)
        if vm is None and _vm_state(dtype) == "building":
            _wait_for_vm(dtype, VM_WAIT_S)
            vm = vm_kernel(program, dtype, build=False)
        if vm is not None and _vm_mode() != "only":
            _defer_build(program, dtype)  # after the process: never a compile slot of the run's
        return vm
    ckey = f"{program.key}|{dtype}|cpu"
    with _lock:
        known = ckey in _loaded or ckey in _vm_calls
    if n < AUTO_BUILD_MIN_FRAMES and not known:
        return None
    k = compiled(program, dtype, "cpu", wait=False, build=False)
    if k is not None:
        return k
    vm = vm_kernel(program, dtype, build=True)
    if vm is None and _vm_state(dtype) == "building":
        # the VM's build is short: waiting for it leaves the compiler the cores that eager
        # torch would take (measured faster than running eagerly meanwhile)
        _wait_for_vm(dtype, VM_WAIT_S)
        vm = vm_kernel(program, dtype, build=False)
        if vm is None:
            return None  # eager while the VM builds (its process builds the kernel next)
    if vm is None or _build_behind_vm():
        compiled(program, dtype, "cpu", wait=False)
    elif _vm_mode() != "only":
        _defer_build(program, dtype)
    return vm


def _ready(program: Program, like: Tensor) -> bool:
    """True when the compiled kernel of ``program`` is loaded (not only the VM)."""
    with _lock:
        return f"{program.key}|{like.dtype}|{like.device.type}" in _loaded


# -------------------------------------------------------------------------------------- tape VM
#: Environment variable: ``0`` turns the tape VM off (``auto`` then runs eagerly while a kernel
#: builds, as before the VM); ``only``: the VM runs programs whose kernel is not built and no
#: kernel build starts; ``behind``: the VM, and the kernel built during the run at low
#: priority; ``1``: the VM, and the kernel built once the process exits (detached, low priority;
#: :func:`background_note` says so). Unset: ``behind`` on a machine with at least
#: :data:`BEHIND_MIN_CPUS` CPUs for this process, else ``1`` (both measured faster for the run
#: itself there: docs/kernel_cache.md).
VM_ENV = _csource.VM_ENV
#: CPUs (this process's affinity) from which an unset ``$TORCHCONTACT_VM`` means ``behind``: the
#: compiler takes cores the run leaves idle (a log job keeps about 4 busy), and a long log
#: switches to the kernel once it is built. Measured on a 16-core host (1 M iCub frames, empty
#: cache): 2.36 s with the kernel built during the run against 2.86 s with it built after, the
#: VM alone 2.42 s; on 2 cores a compiler beside the run slowed it (docs/kernel_cache.md).
BEHIND_MIN_CPUS = 16
#: ``nice`` increment of a kernel build started while the VM runs the program: the compiler
#: takes the cores the run leaves idle, not the run's.
KERNEL_BUILD_NICE = 19
#: Seconds ``auto`` waits for the VM's own build (under a second of the compiler) before it runs
#: a program eagerly instead (a compile slot held by another process's long build, say).
VM_WAIT_S = 10.0

_vm_fns: dict[torch.dtype, Callable] = {}  # the VM's ctypes function per dtype
_vm_builds: dict[torch.dtype, _Build] = {}  # the detached process building the VM
_vm_failed: dict[torch.dtype, str] = {}
_vm_calls: dict[str, Callable] = {}  # ckey -> the VM bound to the program's bytecode
_vm_code: dict[str, object] = {}  # key hash -> bytecode encoded in this process


def _vm_mode() -> str:
    """``$TORCHCONTACT_VM``, or the machine's default when unset (:data:`BEHIND_MIN_CPUS`)."""
    import os

    mode = os.environ.get(VM_ENV, "").strip().lower()
    if mode:
        return mode
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        cpus = os.cpu_count() or 1
    return "behind" if cpus >= BEHIND_MIN_CPUS else "1"


def vm_enabled() -> bool:
    """True unless ``$TORCHCONTACT_VM`` is ``0``.

    Then ``auto`` runs a program whose kernel is not built on the tape VM (when a compiler can
    build the VM).
    """
    return _vm_mode() != "0"


def prepare_vm(dtype: torch.dtype = torch.float64) -> bool:
    """Start building the tape VM for ``dtype`` now (detached) when the cache has none.

    For a caller that knows early that it will run programs on the CPU under ``"auto"`` or
    ``"cached"`` (a log job, before it scans the log): the VM's build (under a second of the
    compiler, once per machine and dtype) then overlaps that work instead of being waited for
    at the first program. Does nothing with ``$TORCHCONTACT_VM=0``; a VM in the cache is loaded.
    Never raises: a failed build warns once and ``auto`` stays eager, as it would later.

    Args:
        dtype: the programs' dtype (``torch.float64`` or ``torch.float32``).

    Returns:
        True when the VM is loaded, False while it builds (or when it is off or unavailable).
    """
    if not vm_enabled() or dtype not in _DTYPES:
        return False
    return _vm_function(dtype, build=True) is not None


def _build_behind_vm() -> bool:
    """True when ``$TORCHCONTACT_VM`` is ``behind``: the kernel builds during the run."""
    return _vm_mode() == "behind"


#: kernels to build when the process ends: ckey -> (program, dtype, cache entry), the entry in
#: the cache the program ran with (a later change of ``$TORCHCONTACT_CACHE`` does not move it)
_deferred: dict[str, tuple[Program, torch.dtype, _store.Entry]] = {}
_atexit: list[bool] = []


def _defer_build(program: Program, dtype: torch.dtype) -> None:
    """Build ``program``'s kernel once this process ends (or at :func:`wait_for_builds`).

    While the VM runs it, a compiler beside the run costs the run more than the kernel saves
    it (measured: docs/kernel_cache.md); later runs get the kernel.
    """
    import atexit

    ckey = f"{program.key}|{dtype}|cpu"
    with _lock:
        if ckey in _deferred or ckey in _building or ckey in _loaded or ckey in _failed:
            return
    try:
        entry = _cpu_entry(program, dtype)[0]
    except OSError:
        return
    with _lock:
        _deferred[ckey] = (program, dtype, entry)
        if not _atexit:
            _atexit.append(True)
            atexit.register(start_deferred_builds)


def start_deferred_builds() -> None:
    """Start the kernel builds deferred to this process's end (:func:`_defer_build`), now.

    One detached process builds them one after the other, at low priority
    (:data:`KERNEL_BUILD_NICE`). It runs at the interpreter's exit (``atexit``), when a caller
    waits for the builds (:func:`wait_for_builds`), and from a process that ends without the
    interpreter's shutdown: the ``torchcontact`` console script calls it before ``os._exit``.
    """
    with _lock:
        todo = list(_deferred.items())
        _deferred.clear()
    entries, loads = [], []
    for ckey, (program, dtype, entry) in todo:
        try:
            state, _ = entry.check()
        except OSError:
            continue
        if state != "ok":
            entries.append(entry)
            loads.append((ckey, entry, program, dtype))
    if not entries:
        return
    proc = _store.spawn_build(entries, nice=KERNEL_BUILD_NICE)
    with _lock:
        for ckey, entry, program, dtype in loads:
            _building.setdefault(
                ckey,
                _Build(proc, entry, functools.partial(_load_built, entry, program, dtype)),
            )


def _vm_entry(dtype: torch.dtype) -> tuple[_store.Entry, str]:
    return _csource.vm_entry(_store, _DTYPES[dtype], _vector_bytes(), _machine_tag())


def _vm_state(dtype: torch.dtype) -> str:
    """``"ready"``, ``"building"``, ``"failed"`` or ``"absent"`` (in this process)."""
    with _lock:
        if dtype in _vm_fns:
            return "ready"
        if dtype in _vm_failed:
            return "failed"
        b = _vm_builds.get(dtype)
        return "building" if b is not None and not b.done() else "absent"


def _vm_function(
    dtype: torch.dtype, build: bool, wait: bool = False, then: Program | None = None
) -> Callable | None:
    """The VM's ctypes function for ``dtype``: loaded, from the cache (checked), or None.

    A library missing from the cache is built by a detached process when ``build`` (None
    meanwhile; with ``then``, the same process builds that program's kernel next, at low
    priority), or now when ``wait``. A damaged one is removed and rebuilt (a warning, once);
    a failed build warns once and the VM stays off for ``dtype`` in this process.

    Raises:
        KernelBuildError: with ``wait``, the VM cannot be built or loaded.
    """
    from torchcontact.kernels import _vm

    with _lock:
        if dtype in _vm_fns:
            return _vm_fns[dtype]
        if dtype in _vm_failed:
            if wait:
                raise KernelBuildError(_vm_failed[dtype])
            return None
    try:
        entry, src = _vm_entry(dtype)
        for _ in range(2):  # a damaged library: healed, then built once more
            state, why = entry.check()
            if state == "ok":
                try:
                    fn = _vm.load_function(entry)
                except OSError as e:
                    state, why = "damaged", str(e)
                else:
                    with _lock:
                        _vm_fns[dtype] = fn
                    return fn
            if state == "damaged":
                if f"vm|{dtype}" in _healed:
                    raise KernelBuildError(f"the tape VM {entry.dir} is damaged after its rebuild"
                                           f" ({why})")  # fmt: skip
                _healed.add(f"vm|{dtype}")
                warnings.warn(f"kernel cache entry {entry.dir} (the tape VM) is damaged ({why}):"
                              " removed and rebuilt", RuntimeWarning, stacklevel=4)  # fmt: skip
                with _store.build_dir_lock(entry.dir, blocking=False) as held:
                    if held is not None:  # else a builder holds it: it replaces the library
                        entry.remove_library()
            with _lock:
                pending = _vm_builds.get(dtype)
                if pending is None:  # a build the command started before it imported torch
                    proc = _lightkernels.vm_build(entry.name)
                    if proc is not None:
                        pending = _vm_builds[dtype] = _Build(proc, entry, lambda: _vm_fns[dtype])
            if pending is not None and pending.done():  # it ended, and the VM is not there
                if entry.check()[0] == "ok":  # ... unless it ended after the check above
                    continue
                log = ""
                with contextlib.suppress(OSError):
                    log = entry.log.read_text().strip()[-1500:]
                raise KernelBuildError(f"building the tape VM {entry.name} failed: {log}")
            if pending is not None and not wait:
                return None
            if not (build or wait):
                return None
            _vm.write_source(entry, src)
            if not wait:
                _spawn_vm(dtype, entry, then)
                return None
            _vm.build(entry)
        raise KernelBuildError(f"the tape VM {entry.dir} does not load after its build")
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        _vm_fail(dtype, f"kernel cache {cache_dir() / 'kernels'}: {where}{e.strerror or e}", wait)
    except KernelBuildError as e:
        _vm_fail(dtype, str(e), wait)
    return None


def _wait_for_vm(dtype: torch.dtype, timeout: float) -> None:
    """Wait until the VM's library is published, its builder has ended, or ``timeout`` s."""
    import time

    entry, _ = _vm_entry(dtype)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with _lock:
            b = _vm_builds.get(dtype)
        if b is None or b.done() or entry.check()[0] == "ok":
            return
        time.sleep(0.05)


def _spawn_vm(dtype: torch.dtype, entry: _store.Entry, then: Program | None) -> None:
    """Start the detached build of the VM, and of ``then``'s kernel after it (low priority)."""
    with _lock:
        if dtype in _vm_builds and not _vm_builds[dtype].done():
            return
    entries, kernel = [entry], None
    if then is not None and _build_behind_vm():
        ckey = f"{then.key}|{dtype}|cpu"
        kentry, (kstate, _) = _cpu_entry(then, dtype)
        with _lock:
            free = ckey not in _building and ckey not in _loaded and ckey not in _failed
        if free and kstate == "absent":
            entries.append(kentry)
            kernel = (ckey, kentry, then)
    proc = _store.spawn_build(entries, nice=KERNEL_BUILD_NICE)
    with _lock:
        _vm_builds[dtype] = _Build(proc, entry, lambda: _vm_fns[dtype])
        if kernel is not None:
            ckey, kentry, prog = kernel
            _building[ckey] = _Build(proc, kentry, lambda: _load_built(kentry, prog, dtype))


def _vm_fail(dtype: torch.dtype, why: str, raise_: bool = False) -> None:
    with _lock:
        first = dtype not in _vm_failed
        _vm_failed[dtype] = why
    if raise_:
        raise KernelBuildError(why)
    if first:
        msg = f"the tape VM ({dtype}) is not available: {why}; running eagerly"
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def _bytecode_path(kh: str) -> Path:
    return cache_dir() / "kernels" / "vmcode" / f"{kh}.bc"


def _save_bytecode(program: Program, kh: str):
    """Encode ``program``'s trace for the VM and save it beside the index (once per key)."""
    from torchcontact.kernels import _vm

    if not vm_enabled():
        return None
    bc = _vm_code.get(kh)
    if bc is None:
        tr, out = program.trace()
        bc = _vm.encode(tr, out)
        _vm_code[kh] = bc
    with contextlib.suppress(OSError):
        bc.save(_bytecode_path(kh))
    return bc


def _bytecode(program: Program, dtype: torch.dtype):
    """The VM bytecode of ``program``.

    Encoded in this process, or saved in the cache (checked), or traced and encoded now (and
    saved).
    """
    from torchcontact.kernels import _vm

    kh = _key_hash(program, dtype)
    bc = _vm_code.get(kh)
    if bc is None:
        bc = _vm.Bytecode.load(_bytecode_path(kh))
        if bc is not None:
            _vm_code[kh] = bc
    if bc is None:
        bc = _save_bytecode(program, kh)
    return bc


def vm_kernel(
    program: Program,
    dtype: torch.dtype,
    build: bool = True,
    wait: bool = False,
    kernel_after: bool = True,
) -> Callable | None:
    """``program`` on the tape VM (:mod:`torchcontact.kernels._vm`) for ``dtype`` on CPU.

    The VM is one interpreter per machine and dtype, in the kernel cache: compiled once (a
    second or two), it runs any program from its bytecode, which is saved in the cache with the
    program's key (a later process neither traces nor encodes it again).

    Args:
        program: the program.
        dtype: float32 or float64.
        build: build the VM's library when it is not in the cache, in a detached process
            that then builds the program's own kernel at low priority
            (not with ``$TORCHCONTACT_VM=only``); None meanwhile. False returns None then.
        wait: build the VM's library now (a second or two) and return the VM.
        kernel_after: with ``build``, the detached process builds the program's kernel after
            the VM (False: the VM only).

    Returns:
        ``call(tensors: dict[str, (N, k) Tensor]) -> dict[str, (N, k) Tensor]``, or None while
        the VM builds, when it cannot be built, or when ``$TORCHCONTACT_VM`` is ``0``.

    Raises:
        KernelBuildError: with ``wait``, the VM cannot be built.
    """
    from torchcontact.kernels import _vm

    if dtype not in _DTYPES or not vm_enabled():
        return None
    ckey = f"{program.key}|{dtype}|cpu"
    with _lock:
        if ckey in _vm_calls:
            return _vm_calls[ckey]
    fn = _vm_function(dtype, build, wait, then=program if kernel_after else None)
    if fn is None:
        return None
    try:
        bc = _bytecode(program, dtype)
    except OSError as e:
        _vm_fail(dtype, f"kernel cache {cache_dir()}: {e}")
        return None
    call = _vm.bind(fn, program, dtype, bc)
    with _lock:
        _vm_calls[ckey] = call
    return call


def _tracing() -> bool:
    from torchcontact._internal import in_tracing

    return in_tracing()


def is_symbolic(x) -> bool:
    """True for a traced scalar."""
    return isinstance(x, Sym)
