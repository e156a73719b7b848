"""Per-robot kernels generated from one Python source of the physics.

A :class:`Program` is a physics function written on scalars (:mod:`torchcontact._scalar`): it
maps named input arrays (``k`` scalars per frame each) to named output arrays. One program runs on
three backends:

* ``"eager"``: the function runs on torch tensors, one ``(N,)`` tensor per scalar. Always
  available, differentiable, any device and dtype; the reference the others are tested against.
* ``"cpu"``: the function runs once on symbols (:class:`torchcontact._scalar.Trace`); the SSA
  graph becomes straight-line C++ on vectors of frames (:mod:`torchcontact.kernels._cpp`), built
  with torch's extension builder (``torch.utils.cpp_extension.load``) and called through ctypes,
  the frames split over ``torch.get_num_threads()`` threads.
* ``"cuda"``: the same graph as a CUDA kernel, one thread per frame
  (:mod:`torchcontact.kernels._cuda`).

Builds are cached on disk by the hash of the generated source, the compiler and the CPU, under
``$TORCHCONTACT_CACHE`` (default ``$XDG_CACHE_HOME/torchcontact`` or ``~/.cache/torchcontact``), so
a later process loads a kernel in milliseconds. ``backend="auto"`` uses a compiled kernel when one
is loaded or cached, and otherwise runs eagerly while the kernel builds in a background thread
(large batches only); a build failure or a missing compiler warns once and stays eager.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import platform
import subprocess
import sys
import threading
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from torchcontact._scalar import Sym, Trace, float_dtype
from torchcontact.errors import KernelBuildError

__all__ = [
    "BACKENDS",
    "CFLAGS",
    "Program",
    "build_dir_lock",
    "build_source",
    "cache_dir",
    "compiled",
    "run",
    "wait_for_builds",
]

#: Accepted ``backend`` arguments.
BACKENDS = ("auto", "eager", "cpu", "cuda")

#: Batches at least this large start a background build under ``backend="auto"``.
AUTO_BUILD_MIN_FRAMES = 2048

_VERSION = "1"  # bump when the generated code's calling convention changes


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


def cache_dir() -> Path:
    """Root of the on-disk kernel cache."""
    env = os.environ.get("TORCHCONTACT_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "torchcontact"


def _machine_tag() -> str:
    """CPU model and flags: a ``-march=native`` build only runs where it was built."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "model name")):
                    flags += line
                if line.startswith("flags"):
                    break
    except OSError:
        flags = platform.processor()
    return hashlib.sha256(f"{platform.machine()}|{flags}".encode()).hexdigest()[:12]


def _vector_bytes() -> int:
    """Bytes of one SIMD register: 64 with AVX-512, else 32 (AVX2; other ISAs split it)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return 64 if " avx512f" in line else 32
    except OSError:
        pass
    return 32


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
_building: dict[str, threading.Thread] = {}
_warned: set[str] = set()
_pool: ThreadPoolExecutor | None = None


def _source(program: Program, dtype: torch.dtype) -> tuple[str, str]:
    from torchcontact.kernels import _cpp

    tr, out = program.trace()
    src = _cpp.emit(tr, out, _DTYPES[dtype], vbytes=_vector_bytes())
    h = hashlib.sha256(
        f"{_VERSION}|{torch.__version__}|{_machine_tag()}|{src}".encode()
    ).hexdigest()[:20]
    return src, h


#: Compiler flags of the CPU kernels (IEEE semantics kept: no -ffast-math).
CFLAGS = (
    "-O2",
    "-march=native",
    "-fno-math-errno",
    "-fno-trapping-math",
    "-ffp-contract=fast",
    "-fno-semantic-interposition",
)


def _paths(program: Program, h: str) -> tuple[str, Path, Path]:
    """Name, source file and shared library of a CPU kernel in the cache."""
    name = f"tck_{program.name}_{h}"
    d = cache_dir() / "kernels" / name
    return name, d / f"{name}.cpp", d / f"{name}.so"


def _write_source(cpp: Path, src: str) -> None:
    cpp.parent.mkdir(parents=True, exist_ok=True)
    if not cpp.exists() or cpp.read_text() != src:
        tmp = cpp.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(src)
        tmp.replace(cpp)


def build_source(name: str, cpp: Path) -> Path:
    """Compile one kernel source with torch's extension builder; returns the library's path.

    Also the entry point of the detached build process (``python -m torchcontact.kernels``).

    Raises:
        KernelBuildError: the compiler is missing or fails.
    """
    from torch.utils import cpp_extension

    so = cpp.with_suffix(".so")
    with build_dir_lock(cpp.parent):
        if so.exists():  # another process built it while this one waited
            return so
        try:
            cpp_extension.load(
                name, [str(cpp)], extra_cflags=list(CFLAGS), build_directory=str(cpp.parent),
                is_python_module=False, verbose=False,
            )  # fmt: skip
        except Exception as e:  # compiler missing, internal compiler error, ...
            raise KernelBuildError(f"building kernel {name} failed: {e}") from e
    return so


@contextlib.contextmanager
def build_dir_lock(directory: Path):
    """Hold the build directory of one kernel for this process, clearing a dead build's baton.

    torch's extension builder guards a build directory with a ``lock`` file that it deletes when
    the build ends; a build killed part-way (a test run or CLI interrupted) leaves it behind and
    every later build of that kernel waits on it forever. Builders here first take an OS file
    lock (``fcntl.flock``, released by the kernel when its process dies) on ``build.flock``, so
    once it is held any ``lock`` file left in the directory belongs to a dead build and is removed.
    """
    import fcntl

    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / "build.flock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            (directory / "lock").unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _build(program: Program, dtype: torch.dtype, src: str, h: str) -> Callable:
    """Compile (or load from the cache) and wrap the kernel of ``program``."""
    name, cpp, so = _paths(program, h)
    if not so.exists():
        _write_source(cpp, src)
        build_source(name, cpp)
    lib = ctypes.CDLL(str(so))
    return _wrap(lib.tc_kernel, program, dtype)


def _wrap(fn, program: Program, dtype: torch.dtype) -> Callable:
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
            _invoke(fn, 0, n, ins, outl)
        else:
            # several pieces per thread, taken as threads come free: a thread the OS does not
            # schedule (a busy neighbour on the other core) holds back one piece, not half
            pool = _get_pool(nthreads)
            step = max(512, -(-n // (4 * nthreads)))
            step = -(-step // 16) * 16  # whole vector blocks per piece
            futs = [pool.submit(_invoke, fn, s, min(n, s + step), ins, outl)
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


def _invoke(fn, s: int, e: int, ins: list[Tensor], outs: list[Tensor]) -> None:
    """Call the kernel on frames ``[s, e)`` (row offsets into each array; ctypes drops the GIL)."""
    if e <= s:
        return
    ptr = ctypes.c_void_p
    in_p = (ptr * len(ins))(*[x.data_ptr() + s * x.stride(0) * x.element_size() for x in ins])
    in_s = (ctypes.c_int64 * len(ins))(*[x.stride(0) for x in ins])
    out_p = (ptr * len(outs))(*[x.data_ptr() + s * x.stride(0) * x.element_size() for x in outs])
    out_s = (ctypes.c_int64 * len(outs))(*[x.stride(0) for x in outs])
    fn(e - s, in_p, in_s, out_p, out_s)


def compiled(
    program: Program, dtype: torch.dtype, device: torch.device | str = "cpu", wait: bool = True
) -> Callable | None:
    """The compiled kernel of ``program`` for ``dtype`` on ``device``.

    Args:
        program: the program.
        dtype: float32 or float64.
        device: ``cpu`` (generated C++) or ``cuda`` (generated CUDA).
        wait: build now and return the kernel (raises :class:`KernelBuildError` on failure); with
            False, return the kernel if it is loaded or in the disk cache, else start a background
            build and return None.

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
        thread = _building.get(ckey)
    if thread is not None:
        if isinstance(thread, _Build) and (wait or thread.done()):
            thread.join()
            with _lock:
                _building.pop(ckey, None)
            if not thread.so.exists():
                log = thread.so.with_suffix(".log")
                why = log.read_text()[-2000:] if log.exists() else "no log"
                return _finish(ckey, _failing(f"building kernel {thread.so.stem} failed: {why}"),
                               raise_=wait)  # fmt: skip
            return _finish(ckey, thread.load, raise_=wait)
        if not wait:
            return None
        thread.join()
        return compiled(program, dtype, device, wait)
    if device.type == "cuda":
        from torchcontact.kernels import _cuda

        if not torch.cuda.is_available():
            return _finish(ckey, _no_cuda, raise_=wait)

        def build() -> Callable:
            return _cuda.build(program, dtype, cache_dir())

    else:
        src, h = _source(program, dtype)
        name, cpp, so = _paths(program, h)

        def build() -> Callable:
            return _build(program, dtype, src, h)

        if not (wait or so.exists()):
            # a detached process: the build goes on (and fills the cache) if this one exits
            _write_source(cpp, src)
            log = open(cpp.with_suffix(".log"), "w")  # noqa: SIM115 - the child writes it
            proc = subprocess.Popen(
                [sys.executable, "-m", "torchcontact.kernels", name, str(cpp)],
                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
            log.close()
            with _lock:
                _building[ckey] = _Build(proc, so, build)
            return None
        return _finish(ckey, build, raise_=wait)
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
    """A kernel being compiled by a detached process."""

    proc: subprocess.Popen
    so: Path
    load: Callable[[], Callable]

    def join(self, timeout: float | None = None) -> None:
        """Wait for the process."""
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout)

    def done(self) -> bool:
        return self.proc.poll() is not None


def wait_for_builds(timeout: float | None = None) -> None:
    """Wait until the kernels building in the background are built (or failed)."""
    with _lock:
        pending = list(_building.values())
    for b in pending:
        b.join(timeout)


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
            ``"cpu"`` or ``"cuda"`` (build now; :class:`KernelBuildError` on failure).

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
    if first.dtype not in _DTYPES or first.device.type not in ("cpu", "cuda"):
        return run_eager(program, tensors)
    k = compiled(program, first.dtype, first.device, wait=False) if (
        first.shape[0] >= AUTO_BUILD_MIN_FRAMES or _ready(program, first)
    ) else None  # fmt: skip
    if k is None:
        return run_eager(program, tensors)
    return k(tensors)


def _ready(program: Program, like: Tensor) -> bool:
    with _lock:
        return f"{program.key}|{like.dtype}|{like.device.type}" in _loaded


def _tracing() -> bool:
    from torchcontact._internal import in_tracing

    return in_tracing()


def is_symbolic(x) -> bool:
    """True for a traced scalar."""
    return isinstance(x, Sym)
