"""CUDA code generation for a traced physics program: one GPU thread per frame.

The SSA graph of :class:`torchcontact._scalar.Trace` becomes straight-line scalar CUDA C in a
``__global__`` kernel; a thread reads its frame's rows of the ``(N, k)`` inputs, computes every
output and writes its rows (the same calling convention as :mod:`torchcontact.kernels._cpp`).
``sin``/``cos`` use CUDA's ``sincos`` (1 ulp in double), masks are ``bool`` and selects ternaries;
no fast-math flags. The host entry ``tc_launch`` takes device pointers and a stream, so the kernel
runs on torch's current stream. It is built with ``torch.utils.cpp_extension.load`` (nvcc) and
cached on disk like the CPU kernels (checked before loading, published atomically). A
:func:`torchcontact._scalar.loop` is a ``for`` loop around the code of one iteration (loop
invariants computed before it) that a thread leaves once its frame's ``stop`` mask holds.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path

import torch
from torch import Tensor

from torchcontact._scalar import Sym, Trace
from torchcontact.errors import KernelBuildError
from torchcontact.kernels import _store
from torchcontact.kernels._store import build_dir_lock

_BINARY = {"add": "+", "sub": "-", "mul": "*", "div": "/"}


def emit(trace: Trace, outputs: dict[str, list], dtype: str, symbol: str = "tc_launch") -> str:
    """CUDA source of one kernel and its host launcher.

    Args:
        trace: the traced program; its ``inputs`` fix the input order.
        outputs: output name -> scalars, in the caller's output order.
        dtype: ``"double"`` or ``"float"``.
        symbol: name of the exported host function ``symbol(n, in, in_stride, out, out_stride,
            stream)``; the pointer arrays are host arrays of device pointers.
    """
    from torchcontact.kernels._cpp import emit_loop, live_nodes, loop_bodies

    flat = [x for xs in outputs.values() for x in xs]
    nodes = live_nodes(trace, flat)
    bodies = loop_bodies(nodes)
    deferred = {b.index for body in bodies.values() for b in body}
    in_index = {k: i for i, k in enumerate(trace.inputs)}
    n_in, n_out = len(trace.inputs), len(outputs)
    lines: list[str] = []

    def ref(a) -> str:
        if isinstance(a, Sym):
            return f"t{a.index}"
        c = float(a)
        if c != c:
            return "(T)CUDART_NAN"
        if c in (float("inf"), float("-inf")):
            return f"({'-' if c < 0 else ''}(T)CUDART_INF)"
        return f"(T){c!r}"

    done_sincos: dict[str, tuple[str, str]] = {}

    def emit_node(s: Sym) -> None:
        v = f"t{s.index}"
        if s.op == "in":
            arr, j = s.args
            a = in_index[arr]
            lines.append(f"  const T {v} = p.in[{a}][f * p.in_stride[{a}] + {j}];")
        elif s.op in _BINARY:
            x, y = s.args
            lines.append(f"  const T {v} = {ref(x)} {_BINARY[s.op]} {ref(y)};")
        elif s.op == "neg":
            lines.append(f"  const T {v} = -{ref(s.args[0])};")
        elif s.op == "sqrt":
            lines.append(f"  const T {v} = sqrt({ref(s.args[0])});")
        elif s.op in ("sin", "cos"):
            x = ref(s.args[0])
            if x not in done_sincos:
                sn, cs = f"sn{s.index}", f"cs{s.index}"
                done_sincos[x] = (sn, cs)
                lines.append(f"  T {sn}, {cs}; sincos({x}, &{sn}, &{cs});")
            sn, cs = done_sincos[x]
            lines.append(f"  const T {v} = {sn if s.op == 'sin' else cs};")
        elif s.op == "gt":
            lines.append(f"  const bool {v} = {ref(s.args[0])} > {ref(s.args[1])};")
        elif s.op == "finite":
            lines.append(f"  const bool {v} = isfinite({ref(s.args[0])});")
        elif s.op == "and":
            lines.append(f"  const bool {v} = {ref(s.args[0])} && {ref(s.args[1])};")
        elif s.op == "or":
            lines.append(f"  const bool {v} = {ref(s.args[0])} || {ref(s.args[1])};")
        elif s.op == "not":
            lines.append(f"  const bool {v} = !{ref(s.args[0])};")
        elif s.op == "loopout":
            lines.append(f"  const T {v} = {ref(s.args[0].args[0].carries[s.args[1]])};")
        elif s.op == "sel":
            m, x, y = s.args
            lines.append(f"  const T {v} = {ref(m)} ? {ref(x)} : {ref(y)};")
        else:  # pragma: no cover - every op of _scalar is handled above
            raise ValueError(f"no CUDA for op {s.op!r}")

    for s in nodes:
        if s.index in deferred or s.op == "carry":
            continue
        if s.op == "loop":
            emit_loop(s, bodies[s.index], lines, ref, emit_node, done_sincos, "T", "{}")
        else:
            emit_node(s)
    for k, xs in enumerate(outputs.values()):
        for j, x in enumerate(xs):
            lines.append(f"  p.out[{k}][f * p.out_stride[{k}] + {j}] = {ref(x)};")
    body = "\n".join(lines)
    return f"""#include <cstdint>
#include <cuda_runtime.h>
#include <math_constants.h>
typedef {dtype} T;
struct Params {{
  const T* in[{max(n_in, 1)}];
  int64_t in_stride[{max(n_in, 1)}];
  T* out[{max(n_out, 1)}];
  int64_t out_stride[{max(n_out, 1)}];
}};

__global__ void __launch_bounds__(128) tc_kernel(int64_t n, const Params p) {{
  const int64_t f = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (f >= n) return;
{body}
}}

extern "C" int {symbol}(int64_t n, const T* const* in, const int64_t* in_stride,
                         T* const* out, const int64_t* out_stride, void* stream) {{
  Params p;
  for (int a = 0; a < {n_in}; ++a) {{ p.in[a] = in[a]; p.in_stride[a] = in_stride[a]; }}
  for (int a = 0; a < {n_out}; ++a) {{ p.out[a] = out[a]; p.out_stride[a] = out_stride[a]; }}
  if (n <= 0) return 0;
  const int threads = 128;
  const int64_t blocks = (n + threads - 1) / threads;
  tc_kernel<<<(unsigned)blocks, threads, 0, (cudaStream_t)stream>>>(n, p);
  return (int)cudaGetLastError();
}}
"""


def source(program, dtype: torch.dtype) -> str:
    """The CUDA source of ``program`` for ``dtype`` (also usable without a GPU, e.g. to check)."""
    tr, out = program.trace()
    return emit(tr, out, {torch.float64: "double", torch.float32: "float"}[dtype])


def build(program, dtype: torch.dtype, cache: Path) -> Callable:
    """Build (or load from ``cache``) the CUDA kernel of ``program``; returns its caller.

    The entry is checked and published like a CPU kernel's (:mod:`torchcontact.kernels._store`):
    under its build lock, a library whose size or sha256 differs from its record, or that does
    not load, warns and is rebuilt; nvcc builds in a private folder under a compile slot, and
    the library is renamed into place before its record is written.

    Raises:
        KernelBuildError: nvcc is missing or fails, or the rebuilt library does not load.
    """
    src = source(program, dtype)
    cap = torch.cuda.get_device_capability()
    h = hashlib.sha256(f"{torch.__version__}|{cap}|{src}".encode()).hexdigest()[:20]
    entry = _store.Entry(cache / "kernels", f"tckc_{program.name}_{h}", ".cu")
    with build_dir_lock(entry.dir):
        state, why = entry.check()
        fn = None
        if state == "ok":
            try:
                fn = _open(entry)
            except (OSError, AttributeError) as e:
                state, why = "damaged", f"{entry.library.name} does not load ({e})"
        if fn is None:
            if state == "damaged":
                warnings.warn(
                    f"kernel cache entry {entry.dir} is damaged ({why}): removed and rebuilt",
                    RuntimeWarning,
                    stacklevel=2,
                )
            entry.remove_library()
            _compile(entry, src)
            try:
                fn = _open(entry)
            except (OSError, AttributeError) as e:
                raise KernelBuildError(f"CUDA kernel {entry.name} does not load: {e}") from None
    names_in, names_out = list(program.inputs), list(program.outputs)
    name = entry.name

    def call(tensors: Mapping[str, Tensor]) -> dict[str, Tensor]:
        first = tensors[names_in[0]]
        n, dev = first.shape[0], first.device
        ins = [tensors[k].contiguous() for k in names_in]
        outs = {k: torch.empty(n, m, dtype=dtype, device=dev) for k, m in program.outputs.items()}
        outl = [outs[k] for k in names_out]
        ptr = ctypes.c_void_p
        rc = fn(
            n,
            (ptr * len(ins))(*[x.data_ptr() for x in ins]),
            (ctypes.c_int64 * len(ins))(*[x.stride(0) for x in ins]),
            (ptr * len(outl))(*[x.data_ptr() for x in outl]),
            (ctypes.c_int64 * len(outl))(*[x.stride(0) for x in outl]),
            ptr(torch.cuda.current_stream(dev).cuda_stream),
        )
        if rc:
            raise KernelBuildError(f"CUDA kernel {name} failed to launch (cudaError {rc})")
        return outs

    return call


def _open(entry: _store.Entry):
    """The ``tc_launch`` function of a checked entry's library (OSError, AttributeError)."""
    fn = ctypes.CDLL(str(entry.library)).tc_launch
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                   ctypes.c_void_p, ctypes.c_void_p]  # fmt: skip
    return fn


def _compile(entry: _store.Entry, src: str) -> None:
    """nvcc-compile an entry's source (its build lock held) and publish the library.

    torch's extension builder writes into a private folder ``build-<pid>`` under a compile
    slot; the library is then renamed into the entry with its record.
    """
    from torch.utils import cpp_extension

    for stale in entry.dir.glob("build-*"):  # builds killed part-way (the lock is held)
        shutil.rmtree(stale, ignore_errors=True)
    _store.write_atomic(entry.source, src)
    stage = entry.dir / f"build-{os.getpid()}"
    stage.mkdir()
    try:
        with _store.build_slot(entry.root):
            t0 = time.perf_counter()
            cpp_extension.load(
                entry.name,
                [str(entry.source)],
                extra_cuda_cflags=["-O3", "--fmad=true"],
                build_directory=str(stage),
                is_python_module=False,
                with_cuda=True,
                verbose=False,
            )
            seconds = time.perf_counter() - t0
        entry.publish(stage / f"{entry.name}.so", compiler="nvcc", seconds=round(seconds, 2),
                      source_sha256=_store.file_digest(entry.source)[1])  # fmt: skip
    except Exception as e:
        raise KernelBuildError(f"building CUDA kernel {entry.name} failed: {e}") from e
    finally:
        shutil.rmtree(stage, ignore_errors=True)
