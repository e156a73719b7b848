"""The single-frame steps the runtime drives: an ONNX step graph, or a C step library.

Both are the same thing to :class:`~torchcontact.onnx.runtime.EstimatorRuntime`: one packed
input vector ``x`` and one packed output vector, with a layout ``field -> (offset, shape)`` for
each, and a call that estimates one frame. The runtime fills ``x`` by field (the inputs of
:data:`~torchcontact.onnx.format.INPUTS`, and the online inputs ``bias``, ``theta.<sensor>``),
calls the step and reads the fields of its output, whichever backend it is; only the call and
the loading differ:

* :class:`OnnxStep`: the ``<name>.step.onnx`` graph in an onnxruntime session;
* :class:`CStep`: a C library of :func:`torchcontact.online.cstep.export_c_step` through ctypes
  (no onnxruntime, no torch), its buffers allocated once and passed by address.

This module imports neither torch nor onnxruntime (the session is made by the runtime).
"""

from __future__ import annotations

import ctypes
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, MissingExtraError, ModelMismatchError
from torchcontact.onnx.format import decode

__all__ = [
    "C_ABI",
    "C_FORMAT",
    "CStep",
    "Layout",
    "OnnxStep",
    "metadata_of",
    "onnxruntime",
    "open_session",
    "session_options",
]

#: ``metadata["format"]`` of the C step libraries this runtime reads
#: (:data:`torchcontact.online.cstep.C_FORMAT`).
C_FORMAT = "torchcontact.cstep/1"
#: The version of the C functions' signatures it calls.
C_ABI = 1
#: File suffixes of shared libraries (``EstimatorRuntime`` picks the C backend for them).
LIBRARY_SUFFIXES = (".so", ".dylib", ".dll")

Layout = dict[str, tuple[int, tuple[int, ...]]]


def onnxruntime() -> Any:
    """The ``onnxruntime`` module, imported on first use (the C backend does not need it).

    Raises:
        MissingExtraError: onnxruntime is not installed.
    """
    try:
        import onnxruntime as ort
    except ImportError:
        raise MissingExtraError("onnxruntime", "export") from None
    return ort


def session_options(intra_op_threads: int = 1) -> Any:
    """Onnxruntime options for one frame per call (chosen by measurement, benchmarks/runtime.py).

    One intra-op thread and sequential execution (a single frame has no parallel work worth a
    thread hand-off; more threads measured slower), no spinning (a spinning pool competes with the
    caller on a loaded machine), every graph optimisation (constant folding, Gemm fusion), memory
    arena and pattern planning on (output buffers are reused between calls).
    """
    ort = onnxruntime()
    so = ort.SessionOptions()
    so.intra_op_num_threads = intra_op_threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.log_severity_level = 3
    return so


def open_session(path: str | os.PathLike, options: Any) -> Any:
    """An onnxruntime session of ``path`` on the CPU."""
    return onnxruntime().InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def metadata_of(session: Any) -> dict[str, Any]:
    """A session's ``metadata_props``, JSON values decoded."""
    return decode(session.get_modelmeta().custom_metadata_map)


def _layout(d: Mapping[str, Sequence]) -> Layout:
    return {k: (int(o), tuple(int(s) for s in sh)) for k, (o, sh) in d.items()}


def _size(lay: Layout) -> int:
    return max((o + int(np.prod(sh)) for o, sh in lay.values()), default=0)


class OnnxStep:
    """An ONNX single-frame graph: ``out (1, O) = graph(x (1, F))``.

    Args:
        session: the graph's onnxruntime session.
        inputs: its packed input layout (``metadata["step_inputs"]``).
        outputs: its packed output layout (``metadata["step_outputs"]``).
        dtype: the graph's float dtype.

    Attributes:
        x: ``(F,)`` the packed input (a view of the ``(1, F)`` array fed to the graph).
        inputs, outputs: the layouts.
    """

    kind = "onnx"

    def __init__(self, session: Any, inputs: Layout, outputs: Layout, dtype: np.dtype) -> None:
        self.session = session
        self.inputs, self.outputs = _layout(inputs), _layout(outputs)
        self._x2 = np.zeros((1, _size(self.inputs)), dtype)
        self.x = self._x2[0]
        self._feed = {session.get_inputs()[0].name: self._x2}
        # the binding's own run (skips the Python wrapper's per-call checks)
        self._run = session._sess.run
        self._names = [o.name for o in session.get_outputs()]
        self._ro = onnxruntime().RunOptions()
        self.last: np.ndarray | None = None

    def call(self) -> np.ndarray:
        """Estimate the frame in :attr:`x`; returns the packed output ``(O,)`` (a new array)."""
        self.last = self._run(self._names, self._feed, self._ro)[0][0]
        return self.last

    def output(self, name: str) -> np.ndarray:
        """A field of the last call's output (a view)."""
        o, sh = self.outputs[name]
        return self.last[o : o + int(np.prod(sh))].reshape(sh)


class CStep:
    """A C step library (``NAME.so`` of ``export estimator --format c``) loaded with ctypes.

    Args:
        path: the library.
        prefix: its symbol prefix (``--prefix`` at export).

    Attributes:
        metadata: the library's metadata (JSON decoded; the keys of the ONNX graphs' where they
            mean the same: ``robot``, ``urdf_sha256``, ``robot_identity``, ``joint_names``,
            ``sensors``, ``slot_links``, ``slot_kinds``, ``torque_joints``, ``dtype``,
            ``online``).
        x: ``(in_size,)`` the packed input, filled with the library's defaults (the correction
            stack's offsets and inertial change).
        out: ``(out_size,)`` the packed output of the last call (reused by every call).
        inputs, outputs: the layouts.

    Raises:
        InputError: no such file.
        ModelMismatchError: not a C step library of this format and ABI.
    """

    kind = "c"

    def __init__(self, path: str | os.PathLike, prefix: str = "tc_estimator") -> None:
        p = Path(os.fspath(path))
        if not p.is_file():
            raise InputError(f"{p}: no such file")
        try:
            lib = ctypes.CDLL(str(p.resolve()))
            meta_fn = getattr(lib, f"{prefix}_metadata")
            abi = getattr(lib, f"{prefix}_abi")
        except (OSError, AttributeError) as e:
            raise ModelMismatchError(
                f"{p} is not a torchcontact C step library with prefix {prefix!r} ({e})"
            ) from None
        meta_fn.restype = ctypes.c_char_p
        try:
            meta = json.loads(meta_fn().decode())
        except ValueError as e:
            raise ModelMismatchError(f"{p}: unreadable metadata ({e})") from None
        if meta.get("format") != C_FORMAT or abi() != C_ABI:
            raise ModelMismatchError(
                f"{p} is a C step of format {meta.get('format')!r}, ABI {abi()}; this runtime"
                f" reads {C_FORMAT!r}, ABI {C_ABI}: re-export it"
            )
        self.path, self.metadata, self._lib = str(p), meta, lib
        self.inputs, self.outputs = _layout(meta["inputs"]), _layout(meta["outputs"])
        dtype = np.dtype(meta["dtype"])
        self.x = np.zeros(int(meta["in_size"]), dtype)
        self.out = np.zeros(int(meta["out_size"]), dtype)
        ptr = ctypes.POINTER(ctypes.c_double if dtype == np.float64 else ctypes.c_float)
        defaults = getattr(lib, f"{prefix}_defaults")
        defaults.argtypes, defaults.restype = [ptr], None
        defaults(self.x.ctypes.data_as(ptr))
        self.x0 = self.x.copy()
        step = getattr(lib, f"{prefix}_step")
        step.argtypes, step.restype = [ctypes.c_void_p, ctypes.c_void_p], ctypes.c_int
        run = getattr(lib, f"{prefix}_run")
        run.restype = None
        run.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p,
                        ctypes.c_int64]  # fmt: skip
        self._step, self._run = step, run
        # the buffers never move: their addresses are passed as plain integers
        self._xp, self._op = self.x.ctypes.data, self.out.ctypes.data
        self.last = self.out

    def call(self) -> np.ndarray:
        """Estimate the frame in :attr:`x`; returns :attr:`out` (overwritten by the next call)."""
        self._step(self._xp, self._op)
        return self.out

    def call_raw(self) -> int:
        """The library call alone on :attr:`x` as it stands; returns the status (benchmarks)."""
        return self._step(self._xp, self._op)

    def run(self, x: np.ndarray) -> np.ndarray:
        """Estimate ``N`` packed frames, rows of ``x`` ``(N, in_size)``; returns ``(N, out_size)``.

        Raises:
            InputError: ``x`` of another width.
        """
        x = np.ascontiguousarray(x, dtype=self.x.dtype)
        if x.ndim != 2 or x.shape[1] != self.x.size:
            raise InputError(f"x must be (N, {self.x.size}), got {x.shape}")
        out = np.empty((x.shape[0], self.out.size), self.x.dtype)
        self._run(x.shape[0], x.ctypes.data, x.shape[1], out.ctypes.data, out.shape[1])
        return out

    def pack(self, n: int, base: np.ndarray | None = None, **fields: Any) -> np.ndarray:
        """``(n, in_size)`` packed inputs for :meth:`run`.

        ``base`` (default: the library's defaults) in every row, then each given field
        ``(n, *shape)``.

        Raises:
            InputError: an unknown field or a wrong size.
        """
        x = np.broadcast_to(self.x0 if base is None else base, (n, self.x.size)).copy()
        for k, v in fields.items():
            if k not in self.inputs:
                raise InputError(f"unknown input {k!r}; the library has {list(self.inputs)}")
            o, sh = self.inputs[k]
            size = int(np.prod(sh))
            arr = np.asarray(v, dtype=np.float64)
            if arr.size != n * size:
                raise InputError(f"{k} must have shape ({n}, {', '.join(map(str, sh))})")
            x[:, o : o + size] = arr.reshape(n, size)
        return x

    def unpack(self, out: np.ndarray) -> dict[str, np.ndarray]:
        """Output fields ``(N, *shape)`` of :meth:`run`'s result."""
        n = out.shape[0]
        return {k: out[:, o : o + int(np.prod(sh))].reshape(n, *sh)
                for k, (o, sh) in self.outputs.items()}  # fmt: skip

    def output(self, name: str) -> np.ndarray:
        """A field of the last call's output (a view)."""
        o, sh = self.outputs[name]
        return self.out[o : o + int(np.prod(sh))].reshape(sh)
