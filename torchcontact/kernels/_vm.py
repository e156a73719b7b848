"""The tape VM: one compiled interpreter that runs any traced program, built once per machine.

A per-robot kernel (:mod:`torchcontact.kernels._cpp`) is straight-line C++ of one program: fast,
but tens of compiler-seconds for a whole robot. The VM is a small C++ interpreter (a second or
two of the compiler, once per machine and dtype, cached in the kernel store like the kernels)
that runs a program's trace encoded as **bytecode** by :func:`encode`:

* every instruction processes a block of :data:`BLOCK` frames: a *slot* holds one scalar of the
  program for the block's frames (``BLOCK`` values, ``BLOCK / W`` SIMD vectors), so decoding an
  instruction costs little next to its work, and the inner loops are vector code;
* slots are allocated by liveness over the SSA trace (a linear scan: a slot is reused once its
  value's last reader has run), constants are slots filled once per call;
* inputs are loaded from the caller's ``(N, k)`` rows just before their first reader, outputs
  stored right after their writer (so neither lives long);
* a :func:`torchcontact._scalar.loop` is a jump back over its body's instructions with the
  carried slots, leaving early once every frame of the block has stopped (the generated
  kernels' rule, per block of frames instead of per vector);
* ``sin``/``cos`` are the kernels' ``vsincos`` (the same prelude), IEEE semantics (no
  ``-ffast-math``): NaN and inf propagate as in eager torch.
* superinstructions (:func:`_fuse`): a value read by one instruction only is folded into it
  where a rule matches, ``a*b + c``, ``a*b + c*e``, ``a*b + c*e + f*g``, ``c - a*b``,
  ``(a + b) + c`` and the like (the RNEA's cross products and rotations times vectors), so
  fewer instructions decode and fewer intermediate slots go through memory.

The calling convention is the kernels' (``(N, k)`` strided arrays, one pointer and row stride
per array), with the bytecode in front: ``tc_vm(code, ncode, consts, nconst, nslots, n, in,
in_stride, out, out_stride)``; :func:`torchcontact.kernels._wrap` splits the frames over threads
and ctypes releases the GIL. Measured (``benchmarks/vm.py``, docs/kernel_cache.md): the VM runs
the iCub estimator at a fraction of the compiled kernel's speed but several times eager torch's.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcontact._scalar import Sym, Trace, loop_deps
from torchcontact.kernels import _cpp, _csource, _store

__all__ = ["BLOCK", "Bytecode", "encode", "source"]

#: Frames per block (:data:`~torchcontact.kernels._csource.VM_BLOCK`; a benchmark may set this
#: one to time other blocks with their own source).
BLOCK = _csource.VM_BLOCK
#: The bytecode's and the interpreter's version (:data:`~torchcontact.kernels._csource.VM_VERSION`).
VERSION = _csource.VM_VERSION
#: The interpreter's C++ (:data:`~torchcontact.kernels._csource.VM_SOURCE`), and its source for a
#: dtype and vector width.
SOURCE = _csource.VM_SOURCE
source = _csource.vm_source

# opcodes (the interpreter's C++ enum, ``_csource.VM_SOURCE``, has the same numbers)
OPS = ("load", "store", "mov", "add", "sub", "mul", "div", "neg", "sqrt", "sin", "cos", "sincos",
       "sel", "gt", "finite", "and", "or", "not", "loop", "endloop", "fma", "fms", "mma", "mms",
       "add3", "fnm", "dot3", "dot3s")  # fmt: skip
#: Operand flags of an opcode (``16 * op + flags``): operand a, b, c or e is a constant's index.
_KFLAG = {"a": 1, "b": 2, "c": 4, "e": 8}
#: ... except for the three-product opcodes (``dot3``, ``dot3s``), whose flags name the pattern
#: of constants: none, ``g`` alone, or ``b``, ``e`` and ``g``.
_KPATTERN = {"": 0, "g": 1, "beg": 2}
#: Fields of an instruction: ``(op, d, a, b, c, e, f, g)``.
WIDTH = 8
OP = {name: i for i, name in enumerate(OPS)}
#: ``endloop``'s stop field: never stop early / always stop after one iteration.
STOP_NEVER, STOP_ALWAYS = -1, -2


@dataclass(frozen=True)
class Bytecode:
    """A program encoded for the VM.

    Attributes:
        code: ``(ncode, 8)`` int32 instructions ``(op, d, a, b, c, e, f, g)``.
        consts: ``(nconst,)`` float64 constants, the values of slots ``0 .. nconst - 1``.
        nslots: slots the program uses (constants included).
    """

    code: np.ndarray
    consts: np.ndarray
    nslots: int

    def to_bytes(self) -> bytes:
        """A self-checking serialisation: a JSON header line (with the payload's sha256)."""
        payload = self.code.astype("<i4").tobytes() + self.consts.astype("<f8").tobytes()
        head = {"vm": VERSION, "ncode": len(self.code), "nconst": len(self.consts),
                "nslots": self.nslots, "sha256": hashlib.sha256(payload).hexdigest()}  # fmt: skip
        return json.dumps(head).encode() + b"\n" + payload

    @classmethod
    def from_bytes(cls, data: bytes) -> Bytecode | None:
        """The bytecode of :meth:`to_bytes`, or None when damaged or of another VM version."""
        try:
            line, payload = data.split(b"\n", 1)
            head = json.loads(line)
            if head.get("vm") != VERSION:
                return None
            if hashlib.sha256(payload).hexdigest() != head["sha256"]:
                return None
            nc, nk = int(head["ncode"]), int(head["nconst"])
            w = 4 * WIDTH
            if len(payload) != nc * w + nk * 8:
                return None
            code = np.frombuffer(payload[: nc * w], "<i4").reshape(nc, WIDTH).astype(np.int32)
            consts = np.frombuffer(payload[nc * w :], "<f8").astype(np.float64)
            return cls(code, consts, int(head["nslots"]))
        except (ValueError, KeyError, TypeError):
            return None

    def save(self, path: Path) -> None:
        """Write atomically to ``path`` (the kernel store's :func:`write_atomic`)."""
        from torchcontact.kernels import _store

        path.parent.mkdir(parents=True, exist_ok=True)
        _store.write_atomic(path, self.to_bytes())

    @classmethod
    def load(cls, path: Path) -> Bytecode | None:
        """Read and check a saved bytecode; None when missing or damaged."""
        try:
            return cls.from_bytes(path.read_bytes())
        except OSError:
            return None


# ------------------------------------------------------------------------------------ encoding
# Roles of an instruction's fields: which hold slots written (defs) and read (uses).
_DEFS = {"load": "d", "sincos": "dc", "loop": "", "endloop": "", "store": ""}
_USES = {"load": "", "store": "c", "mov": "a", "neg": "a", "sqrt": "a", "sin": "a", "cos": "a",
         "sincos": "a", "finite": "a", "not": "a", "sel": "abc", "loop": "", "endloop": "a",
         "fma": "abc", "fms": "abc", "mma": "abce", "mms": "abce", "add3": "abc", "fnm": "abc",
         "dot3": "abcefg", "dot3s": "abcefg"}  # fmt: skip
_FIELD = {"d": 1, "a": 2, "b": 3, "c": 4, "e": 5, "f": 6, "g": 7}


def encode(trace: Trace, outputs: dict[str, list]) -> Bytecode:
    """Encode a traced program as VM bytecode.

    Live nodes (:func:`torchcontact.kernels._cpp.live_nodes`) become instructions in trace
    order; a loop's body (the nodes that depend on its carried values,
    :func:`torchcontact.kernels._cpp.loop_bodies`) becomes ``loop``, the body, the parallel copy
    of the new values into the carried slots, ``endloop``. Values are virtual registers, then
    slots by a linear scan over their live intervals (a value read inside a loop but defined
    before it lives to the loop's end).

    Args:
        trace: the traced program; its ``inputs`` fix the input order.
        outputs: output name -> scalars (symbols or constants), in the caller's output order.

    Returns:
        The bytecode.
    """
    flat_out = [x for xs in outputs.values() for x in xs]
    nodes = _cpp.live_nodes(trace, flat_out)
    bodies = _cpp.loop_bodies(nodes)
    deferred = {b.index for body in bodies.values() for b in body}
    in_index = {k: i for i, k in enumerate(trace.inputs)}
    # where each output column is stored from: node index -> [(array, column)]
    stores: dict[int, list[tuple[int, int]]] = {}
    const_out: list[tuple[int, int, float]] = []
    for a, xs in enumerate(outputs.values()):
        for j, x in enumerate(xs):
            if isinstance(x, Sym):
                stores.setdefault(x.index, []).append((a, j))
            else:
                const_out.append((a, j, float(x)))
    # sine and cosine of one angle: one instruction (one range reduction)
    trig: dict[tuple[str, int], int] = {}
    for s in nodes:
        if s.op in ("sin", "cos") and isinstance(s.args[0], Sym):
            trig[(s.op, s.args[0].index)] = s.index

    consts: dict[bytes, int] = {}  # constant (by its bits: -0.0 and NaN kept) -> slot
    const_vals: list[float] = []
    vreg: dict[int, int] = {}  # node index -> virtual register
    nvreg = [0]
    code: list[list] = []  # [op name, d, a, b, c] with virtual registers (consts as ("k", slot))

    def new_vreg() -> int:
        nvreg[0] += 1
        return nvreg[0] - 1

    def const(c: float) -> tuple[str, int]:
        key = np.float64(float(c)).tobytes()
        if key not in consts:
            consts[key] = len(const_vals)
            const_vals.append(float(c))
        return ("k", consts[key])

    def ref(x):
        if not isinstance(x, Sym):
            return const(x)
        if x.index not in vreg:
            if x.op != "in":  # pragma: no cover - trace order defines operands first
                raise ValueError(f"VM encoding: %{x.index} ({x.op}) read before it is defined")
            arr, j = x.args
            v = new_vreg()
            vreg[x.index] = v
            code.append(["load", v, in_index[arr], j, 0])
            store_of(x.index)
        return vreg[x.index]

    def store_of(i: int) -> None:
        for a, j in stores.get(i, ()):
            code.append(["store", 0, a, j, vreg[i]])

    def emit(s: Sym) -> None:
        op = s.op
        if op == "in":
            ref(s)
        elif op in ("add", "sub", "mul", "div", "gt", "and", "or"):
            a, b = ref(s.args[0]), ref(s.args[1])
            vreg[s.index] = v = new_vreg()
            code.append([op, v, a, b, 0])
        elif op in ("neg", "sqrt", "finite", "not"):
            a = ref(s.args[0])
            vreg[s.index] = v = new_vreg()
            code.append([op, v, a, 0, 0])
        elif op in ("sin", "cos"):
            if s.index in vreg:  # defined with its twin by a sincos
                store_of(s.index)
                return
            x = s.args[0]
            a = ref(x)
            vreg[s.index] = v = new_vreg()
            other = "cos" if op == "sin" else "sin"
            twin = trig.get((other, x.index)) if isinstance(x, Sym) else None
            if twin is not None and twin not in vreg:
                vreg[twin] = w = new_vreg()
                sn, cs = (v, w) if op == "sin" else (w, v)
                code.append(["sincos", sn, a, 0, cs])
            else:
                code.append([op, v, a, 0, 0])
        elif op == "sel":
            m, a, b = (ref(x) for x in s.args)
            vreg[s.index] = v = new_vreg()
            code.append(["sel", v, m, a, b])
        elif op == "loopout":
            lp, k = s.args
            vreg[s.index] = vreg[lp.args[0].carries[k].index]
        elif op == "loop":
            emit_loop(s)
            return
        else:  # pragma: no cover - every op of _scalar is handled
            raise ValueError(f"no VM instruction for op {op!r}")
        store_of(s.index)

    def emit_loop(s: Sym) -> None:
        spec = s.args[0]
        body = bodies[s.index]
        # inputs the body reads are loaded before the loop (a zero-trip loop reads none)
        for b in body:
            for d in loop_deps(b):
                if d.op == "in":
                    ref(d)
        for x in (*spec.new, spec.stop):
            if isinstance(x, Sym) and x.op == "in":
                ref(x)
        for c, x in zip(spec.carries, spec.init, strict=True):
            a = ref(x)
            vreg[c.index] = v = new_vreg()
            code.append(["mov", v, a, 0, 0])
        start = len(code)
        code.append(["loop", 0, spec.n, 0, 0])
        for b in body:
            emit(b)
        # parallel copy: every new value first to a temporary, then into the carried slots
        temps = []
        for x in spec.new:
            a = ref(x)
            t = new_vreg()
            code.append(["mov", t, a, 0, 0])
            temps.append(t)
        for c, t in zip(spec.carries, temps, strict=True):
            code.append(["mov", vreg[c.index], t, 0, 0])
        if isinstance(spec.stop, Sym):
            stop = ref(spec.stop)
        else:
            stop = STOP_ALWAYS if spec.stop is True else STOP_NEVER
        end = len(code)
        code.append(["endloop", 0, stop, start + 1, spec.n])
        code[start][3] = end + 1

    for s in nodes:
        if s.index in deferred or s.op == "carry":
            continue
        emit(s)
    for a, j, c in const_out:
        code.append(["store", 0, a, j, const(c)])
    code, loops = _fuse(code, const)
    return _allocate(code, loops, const_vals, nvreg[0])


def _fuse(code: list[list], const) -> tuple[list[list], list[tuple[int, int]]]:
    """Fold values read once into the instruction reading them (superinstructions).

    In one pass over ``code``, an instruction takes in the definition of an operand that only it
    reads (written once, so not a loop's carried slot) while a rule matches:

    * a negation into a sum: ``x + (-y)`` is ``x - y``, ``a * b + (-y)`` is ``a * b - y``
      (exact);
    * a product into a sum or difference: ``a * b + c``, ``a * b - c`` (``fma``/``fms``, a fused
      multiply-add, as the compiled kernels' C++ gets from ``-ffp-contract=fast``: results
      differ from eager torch by rounding only);
    * a second product: ``a * b + c * e``, ``a * b - c * e`` (``mma``/``mms``: a 3-vector's
      cross product, a row of a rotation times a vector, two terms of a dot product);
    * a product into the difference it is subtracted from: ``c - a * b`` (``fnm``);
    * a third product: ``a * b + (c * e + f * g)`` (``dot3``: a row of a rotation times a
      vector), and a sum or difference of two products into a sum or difference, as a third
      product by a constant ``+-1`` (exact): ``x + (a * b - c * e)`` (``dot3s``),
      ``(a * b + c * e) - x``; only the patterns of constants the interpreter has a loop for
      (none, the ``+-1`` alone, or every product's second factor);
    * a sum into a sum: ``(a + b) + c`` (``add3``; the same additions in the same order).

    ``const(value)`` is the encoder's constant operand of a value (the ``+-1`` factors).

    Each fused instruction reads its operands where the last one read them; an operand written
    again in between (a carried slot) keeps the two instructions apart. Also returns the
    loops' ``(loop, endloop)`` positions in the new code, with its jumps updated.
    """
    uses: dict[int, int] = {}
    for ins in code:
        for f in _fields(ins)[1]:
            r = ins[_FIELD[f]]
            if isinstance(r, int) and r >= 0:
                uses[r] = uses.get(r, 0) + 1
    # a value written twice is a carried slot: never fused, and its writes are positions
    defs: dict[int, int] = {}
    writes: dict[int, list[int]] = {}
    for p, ins in enumerate(code):
        for f in _fields(ins)[0]:
            r = ins[_FIELD[f]]
            defs[r] = -1 if r in defs else p
            writes.setdefault(r, []).append(p)
    dead: set[int] = set()

    def inner(r, op: str, at: int) -> list | None:
        """The instruction ``op`` defining operand ``r``, when only ``at`` reads it."""
        if not isinstance(r, int) or uses.get(r) != 1 or defs.get(r, -1) < 0:
            return None
        p = defs[r]
        m = code[p]
        if m[0] != op or p in dead:
            return None
        for f in _fields(m)[1]:  # its operands still hold their values at ``at``
            x = m[_FIELD[f]]
            if isinstance(x, int) and any(p < w < at for w in writes.get(x, ())):
                return None
        return m

    def nconst(*xs) -> int:
        return sum(isinstance(x, tuple) for x in xs)

    def pair(x, y) -> tuple | None:
        """A product's factors with its constant second; None for two constants."""
        if isinstance(x, tuple):
            x, y = y, x
        return None if isinstance(x, tuple) else (x, y)

    def rewrite(ins: list, at: int) -> bool:
        op = ins[0]
        if op in ("add", "fma"):  # x + (-y), a * b + (-y)
            sides = (2, 3) if op == "add" else (4,)
            for k in sides:
                m = inner(ins[k], "neg", at)
                rest = (ins[5 - k],) if op == "add" else (ins[2], ins[3])
                if m is not None and nconst(m[2], *rest) <= 1:
                    dead.add(defs[ins[k]])
                    if op == "add":
                        ins[:] = ["sub", ins[1], ins[5 - k], m[2], 0]
                    else:
                        ins[:] = ["fms", ins[1], ins[2], ins[3], m[2]]
                    return True
        if op in ("add", "sub"):  # a * b + c, c + a * b, a * b - c, c - a * b
            for k in (2, 3):
                other = ins[5 - k]
                m = inner(ins[k], "mul", at)
                if m is None or nconst(m[2], m[3], other) > 1:
                    continue  # the interpreter takes one constant operand per instruction
                dead.add(defs[ins[k]])
                name = "fma" if op == "add" else "fms" if k == 2 else "fnm"
                ins[:] = [name, ins[1], m[2], m[3], other]
                return True
            # x + (a * b +- c * e), (a * b +- c * e) - x: a third product x * (+-1)
            for k in (2, 3) if op == "add" else (2,):
                x = ins[5 - k]
                m = inner(ins[k], "mma", at) or inner(ins[k], "mms", at)
                if m is None or isinstance(x, tuple) or nconst(m[3], m[5]) == 1:
                    continue
                dead.add(defs[ins[k]])
                one = const(1.0 if op == "add" else -1.0)
                ins[:] = ["dot3" if m[0] == "mma" else "dot3s", ins[1], *m[2:6], x, one]
                return True
        if op in ("fma", "fms"):  # a * b + c * e, a * b - c * e
            m = inner(ins[4], "mul", at)
            if m is not None:
                p, q = pair(ins[2], ins[3]), pair(m[2], m[3])
                if p is not None and q is not None:
                    dead.add(defs[ins[4]])
                    ins[:] = ["mma" if op == "fma" else "mms", ins[1], *p, *q]
                    return True
        if op == "fma":  # a * b + (c * e + f * g)
            m = inner(ins[4], "mma", at)
            p = pair(ins[2], ins[3])
            if m is not None and p is not None and nconst(p[1], m[3], m[5]) in (0, 3):
                dead.add(defs[ins[4]])
                ins[:] = ["dot3", ins[1], *p, *m[2:6]]
                return True
        if op == "add" and not nconst(ins[2], ins[3]):  # (a + b) + c, c + (a + b)
            for k in (2, 3):
                m = inner(ins[k], "add", at)
                if m is not None and not nconst(m[2], m[3]):
                    dead.add(defs[ins[k]])
                    ins[:] = ["add3", ins[1], m[2], m[3], ins[5 - k]]
                    return True
        return False

    for p, ins in enumerate(code):
        while rewrite(ins, p):
            pass
    new_pos, out = {}, []
    for p, ins in enumerate(code):
        if p not in dead:
            new_pos[p] = len(out)
            out.append(ins)
    loops = []
    for p, ins in enumerate(out):
        if ins[0] == "loop":
            ins[3] = new_pos[ins[3] - 1] + 1  # after the endloop
            loops.append((p, ins[3] - 1))
        elif ins[0] == "endloop":
            ins[3] = new_pos[ins[3] - 1] + 1  # the body's first instruction
    return out, loops


def _fields(ins: list) -> tuple[str, str]:
    op = ins[0]
    return _DEFS.get(op, "d"), _USES.get(op, "ab")


def _allocate(code: list[list], loops: list[tuple[int, int]], const_vals: list[float],
              nvreg: int) -> Bytecode:  # fmt: skip
    """Slots for the virtual registers of ``code`` by a linear scan over their live intervals."""
    first = [-1] * nvreg
    last = [-1] * nvreg
    for p, ins in enumerate(code):
        defs, uses = _fields(ins)
        for f in uses:
            r = ins[_FIELD[f]]
            if isinstance(r, int) and r >= 0:  # not a constant, not endloop's stop flags
                last[r] = p
        for f in defs:
            r = ins[_FIELD[f]]
            if first[r] < 0:
                first[r] = p
            last[r] = max(last[r], p)  # a write to a carried slot keeps it live
    # a value defined before a loop and read (or written) inside lives to the loop's end
    for start, end in loops:
        for r in range(nvreg):
            if 0 <= first[r] < start and start <= last[r] < end:
                last[r] = end
    free: list[int] = []
    nslots = 0
    slot = [-1] * nvreg
    ending: dict[int, list[int]] = {}
    for r in range(nvreg):
        if last[r] >= 0:
            ending.setdefault(last[r], []).append(r)
    out = np.zeros((len(code), WIDTH), dtype=np.int32)
    for p, ins in enumerate(code):
        defs, uses = _fields(ins)
        row = [16 * OP[ins[0]], *ins[1:], *[0] * (WIDTH - len(ins))]
        konst = ""
        for f in uses:
            r = ins[_FIELD[f]]
            if isinstance(r, tuple):  # a constant: its index, flagged in the opcode
                row[_FIELD[f]] = r[1]
                konst += f
            elif r >= 0 or ins[0] != "endloop":
                row[_FIELD[f]] = slot[r]
        # operands read for the last time free their slots before the results take one (an
        # instruction reads a vector of each operand before it writes the result's)
        for r in ending.get(p, ()):
            if slot[r] >= 0 and first[r] < p:
                free.append(slot[r])
        for f in defs:
            r = ins[_FIELD[f]]
            if slot[r] < 0:
                if free:
                    slot[r] = free.pop()
                else:
                    slot[r] = nslots
                    nslots += 1
            row[_FIELD[f]] = slot[r]
        if ins[0] in ("dot3", "dot3s"):
            row[0] += _KPATTERN[konst]
        else:
            row[0] += sum(_KFLAG[f] for f in konst)
        for r in ending.get(p, ()):
            if first[r] == p:  # written and never read: free at once
                free.append(slot[r])
        out[p] = row
    return Bytecode(out, np.asarray(const_vals, dtype=np.float64), nslots)


# ----------------------------------------------------------------------------- the interpreter


def write_source(e: _store.Entry, src: str) -> None:
    """Write the VM's source into its entry (unless it is there already)."""
    _store.write_source(e.source, src)


def build(e: _store.Entry) -> Path:
    """Compile the VM's entry (its source written), publish it atomically; returns the library.

    Raises:
        KernelBuildError: the compiler is missing or fails.
    """
    return _store.build(e, flags=_store.VM_FLAGS)


def load_function(e: _store.Entry):
    """The ``tc_vm`` function of a checked entry's library (ctypes), its ABI checked.

    Raises:
        OSError: the library does not load, lacks the symbols or has another ABI.
    """
    import ctypes

    try:
        lib = ctypes.CDLL(str(e.library))
        fn, abi = lib.tc_vm, lib.tc_vm_abi
    except AttributeError as err:
        raise OSError(f"{e.library.name} lacks the VM's symbols ({err})") from None
    abi.restype = ctypes.c_int
    if str(abi()) != VERSION:
        raise OSError(f"{e.library.name} is VM {abi()}, expected {VERSION}")
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    fn.argtypes = [p, i64, p, i64, i64, i64, p, p, p, p]
    fn.restype = ctypes.c_int
    return fn


def bind(fn, program, dtype, bc: Bytecode):
    """``call(tensors) -> outputs`` running ``program``'s bytecode ``bc`` on the VM ``fn``."""
    import ctypes

    import torch

    from torchcontact.kernels import _wrap

    code = np.ascontiguousarray(bc.code, dtype=np.int32)
    consts = torch.tensor(bc.consts, dtype=torch.float64).to(dtype)
    lead = (code.ctypes.data_as(ctypes.c_void_p), len(code), ctypes.c_void_p(consts.data_ptr()),
            len(consts), max(bc.nslots, 1))  # fmt: skip
    call = _wrap(fn, program, dtype, lead, block=BLOCK)
    call.keep = (code, consts)  # the arrays the pointers point into live as long as the call
    return call
