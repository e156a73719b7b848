"""C++ code generation for a traced physics program (:class:`torchcontact._scalar.Trace`).

The program is straight-line code on scalars. The generated kernel evaluates it on ``W`` frames at
once: every scalar becomes a GCC/Clang vector-extension value of ``W`` lanes, one SIMD register
(``W * sizeof(T)`` = 32 bytes with AVX2, 64 with AVX-512; wider values measured slower, from
register spills), so each instruction processes ``W`` frames. Masks are the integer vectors
comparisons return; ``select`` is the vector ternary. Inputs are read in the caller's layout,
``(N, k)`` rows with a row stride, one lane per frame, by an unrolled gather (a lane loop here
cost 2x through store-forwarding stalls); outputs are written the same way. The last, partial
block runs on zero-padded copies of its rows. ``sin``/``cos`` are computed in-kernel
(``vsincos``), so a joint angle is read once.

A :func:`torchcontact._scalar.loop` becomes a C++ ``for`` loop around the code of one iteration
(the body's nodes that do not depend on the carried values are computed once, before it); the
block leaves it once every lane's ``stop`` mask holds.

No ``-ffast-math``: the kernel keeps IEEE semantics (NaN and inf propagate as in eager torch);
only ``-ffp-contract=fast`` fuses multiply-adds, which changes results by rounding only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torchcontact._scalar import Sym, Trace, loop_deps
from torchcontact.kernels._csource import PRELUDE, emit_prelude
from torchcontact.kernels._store import PARTS_MARK

__all__ = ["PART_NODES", "PRELUDE", "emit", "emit_prelude"]

_BINARY = {"add": "+", "sub": "-", "mul": "*", "div": "/"}

#: Nodes per generated function (:func:`emit`): a program larger than this is cut into parts
#: (``benchmarks/kernel_build.py``: build time against kernel speed).
PART_NODES = 1000


#: The source compiles as one translation unit, or as ``TC_GROUPS`` units compiled in
#: parallel (``-DTC_GROUPS=G -DTC_GROUP=g``, then linked): unit ``g`` defines the parts ``k``
#: with ``k % G == g``, unit 0 also the entry point (:func:`torchcontact.kernels._store.build`).
GROUPS = r"""
#ifndef TC_GROUPS
#define TC_PART static
#define TC_HAS(k) 1
#define TC_HAS_MAIN 1
#else
#define TC_PART __attribute__((visibility("hidden")))
#define TC_HAS(k) ((k) % TC_GROUPS == TC_GROUP)
#define TC_HAS_MAIN (TC_GROUP == 0)
#endif
"""


def _const(c: float, dtype: str) -> str:
    if c != c:  # NaN
        return 'splat(__builtin_nan(""))'
    if c in (float("inf"), float("-inf")):
        return f"splat({'-' if c < 0 else ''}__builtin_inf())"
    return f"splat(({dtype}){float(c)!r})"


def live_nodes(trace: Trace, outputs: list) -> list[Sym]:
    """Nodes the outputs depend on, in trace (topological) order (dead code eliminated)."""
    seen: set[int] = set()
    stack = [o for o in outputs if isinstance(o, Sym)]
    while stack:
        s = stack.pop()
        if s.index in seen:
            continue
        seen.add(s.index)
        stack.extend(loop_deps(s))
        if s.op == "loop":  # every carried value is assigned, used or not
            stack.extend(s.args[0].carries)
    return [n for n in trace.nodes if n.index in seen]


def loop_bodies(nodes: list[Sym]) -> dict[int, list[Sym]]:
    """Per live ``"loop"`` node, its body's live nodes that depend on the carried values.

    These are emitted inside the loop, in order; the body's other nodes (loop invariants) are
    emitted where they stand, before the loop.
    """
    out: dict[int, list[Sym]] = {}
    for s in nodes:
        if s.op != "loop":
            continue
        spec = s.args[0]
        variant = {c.index for c in spec.carries}
        body = []
        for b in nodes:
            if spec.start <= b.index < spec.end and any(d.index in variant for d in loop_deps(b)):
                variant.add(b.index)
                body.append(b)
        out[s.index] = body
    return out


def emit_loop(
    s: Sym,
    body: list[Sym],
    lines: list[str],
    ref: Callable[[Any], str],
    emit_node: Callable[[Sym], None],
    scope: dict,
    value: str,
    stop: str,
) -> None:
    """Append the lines of a ``"loop"`` node (C++ and CUDA alike).

    The carried values ``t<index>`` start from the loop's ``init``; the loop runs ``spec.n``
    times: its ``body`` (:func:`loop_bodies`, emitted by ``emit_node``, indented one level), then
    the carries take their new values, then it exits early where ``spec.stop`` holds.

    Args:
        s: the ``"loop"`` node.
        body: its body's nodes, in order.
        lines: the kernel's lines so far (appended to).
        ref: the emitter's name of a scalar.
        emit_node: the emitter's line(s) of one node, appended to ``lines``.
        scope: the emitter's per-scope cache (shared sines/cosines), restored after the body.
        value: the type of a value (``"V"`` vector, ``"T"`` scalar).
        stop: the early-exit condition as a format string of the stop value (``"{}"``).
    """
    spec, i = s.args[0], s.index
    lines.extend(f"  {value} t{c.index} = {ref(x)};" for c, x in zip(spec.carries, spec.init,
                                                                       strict=True))  # fmt: skip
    lines.append(f"  for (int it{i} = 0; it{i} < {spec.n}; ++it{i}) {{")
    outer_lines, outer_scope = len(lines), dict(scope)
    for b in body:
        emit_node(b)
    for j in range(outer_lines, len(lines)):
        lines[j] = "  " + lines[j]
    scope.clear()
    scope.update(outer_scope)  # sines of the body live in its scope
    for j, x in enumerate(spec.new):
        lines.append(f"    const {value} nx{i}_{j} = {ref(x)};")
    lines.extend(f"    t{c.index} = nx{i}_{j};" for j, c in enumerate(spec.carries))
    if isinstance(spec.stop, Sym):
        lines.append(f"    if ({stop.format(ref(spec.stop))}) break;")
    elif spec.stop is True:
        lines.append("    break;")
    lines.append("  }")


def emit(
    trace: Trace,
    outputs: dict[str, list],
    dtype: str,
    vbytes: int = 32,
    symbol: str = "tc_kernel",
    part_nodes: int | None = None,
) -> str:
    """C++ source of one kernel.

    The program's code is cut into functions of about ``part_nodes`` nodes each (``noinline``,
    called one after the other; a loop with its body stays in one). A value one part computes
    and a later one reads passes through an array on the stack; inputs are loaded by each part
    that reads them. GCC's time grows faster than linearly with a function's size (the
    combiner and register allocation over one huge function), so the parts build in about half
    the compiler's time, and as several translation units at once where compile slots are free
    (:data:`GROUPS`, :func:`torchcontact.kernels._store.build`); the kernel runs about 15%
    slower (measured in ``docs/kernel_cache.md``). Rounding may differ from one function's:
    a product and the sum that reads it in another part are not fused into one multiply-add.

    Args:
        trace: the traced program; its ``inputs`` fix the input order.
        outputs: output name -> scalars (symbols or constants), in the caller's output order.
        dtype: ``"double"`` or ``"float"``.
        vbytes: bytes per vector value (lanes ``= vbytes / sizeof(T)``).
        symbol: name of the exported C function.
        part_nodes: nodes per function (default :data:`PART_NODES`; 0: one function).

    Returns:
        The source. The function is ``void symbol(int64_t n, const T* const* in, const int64_t*
        in_stride, T* const* out, const int64_t* out_stride)`` with one pointer and row stride
        (elements) per input array and per output array, in declaration order.
    """
    if part_nodes is None:
        part_nodes = PART_NODES
    flat_out = [x for xs in outputs.values() for x in xs]
    nodes = live_nodes(trace, flat_out)
    bodies = loop_bodies(nodes)
    deferred = {b.index for body in bodies.values() for b in body}
    name: dict[int, str] = {}
    consts: dict[float, str] = {}
    lines: list[str] = []
    sincos: dict[str, tuple[str, str]] = {}
    in_index = {k: i for i, k in enumerate(trace.inputs)}
    used: set = set()  # the current part's references: symbol indices and constant names
    masks = {s.index for s in nodes if s.mask}

    def ref(a) -> str:
        if isinstance(a, Sym):
            used.add(a.index)
            return name[a.index]
        key = float(a)
        if key not in consts:
            consts[key] = f"c{len(consts)}"
        used.add(consts[key])
        return consts[key]

    def emit_node(s: Sym) -> None:
        v = f"t{s.index}"
        name[s.index] = v
        if s.op == "in":
            arr, j = s.args
            a = in_index[arr]
            lines.append(f"  const V {v} = load(in[{a}], in_stride[{a}], {j});")
        elif s.op in _BINARY:
            x, y = s.args
            lines.append(f"  const V {v} = {ref(x)} {_BINARY[s.op]} {ref(y)};")
        elif s.op == "neg":
            lines.append(f"  const V {v} = -{ref(s.args[0])};")
        elif s.op in ("sin", "cos"):
            x = ref(s.args[0])
            if x not in sincos:  # one range reduction for the sine and cosine of an angle
                sn, cs = f"sn{s.index}", f"cs{s.index}"
                sincos[x] = (sn, cs)
                lines.append(f"  V {sn}, {cs}; vsincos({x}, &{sn}, &{cs});")
            sn, cs = sincos[x]
            lines.append(f"  const V {v} = {sn if s.op == 'sin' else cs};")
        elif s.op == "sqrt":
            lines.append(f"  const V {v} = vsqrt({ref(s.args[0])});")
        elif s.op == "gt":
            x, y = s.args
            lines.append(f"  const M {v} = {ref(x)} > {ref(y)};")
        elif s.op == "finite":  # x - x is 0 for finite x, NaN for NaN and +-inf
            x = ref(s.args[0])
            lines.append(f"  const M {v} = ({x} - {x}) == ({x} - {x});")
        elif s.op == "and":
            x, y = s.args
            lines.append(f"  const M {v} = {ref(x)} & {ref(y)};")
        elif s.op == "or":
            x, y = s.args
            lines.append(f"  const M {v} = {ref(x)} | {ref(y)};")
        elif s.op == "not":
            lines.append(f"  const M {v} = ~{ref(s.args[0])};")
        elif s.op == "loopout":
            lines.append(f"  const V {v} = {ref(s.args[0].args[0].carries[s.args[1]])};")
        elif s.op == "sel":
            m, x, y = s.args
            lines.append(f"  const V {v} = {ref(m)} ? {ref(x)} : {ref(y)};")
        else:  # pragma: no cover - every op of _scalar is handled above
            raise ValueError(f"no C++ for op {s.op!r}")

    # the parts: runs of nodes in trace order, a loop (with its body) whole
    parts: list[list[Sym]] = [[]]
    size = 0
    for s in nodes:
        if s.index in deferred or s.op == "carry":
            continue
        if part_nodes and size >= part_nodes:
            parts.append([])
            size = 0
        parts[-1].append(s)
        size += 1 + len(bodies.get(s.index, ()))
    emitted = []  # per part: its lines, the references it reads, the symbols it defines
    for k, part in enumerate(parts):
        lines, known = [], set(name)
        used.clear()
        sincos.clear()  # a sine's variables are local to its part
        for s in part:
            if s.op == "loop":
                name.update((c.index, f"t{c.index}") for c in s.args[0].carries)
                emit_loop(s, bodies[s.index], lines, ref, emit_node, sincos, "V", "all_lanes({})")
            else:
                emit_node(s)
        if k == len(parts) - 1:
            for a, xs in enumerate(outputs.values()):
                lines.extend(f"  store(out[{a}], out_stride[{a}], {j}, {ref(x)});"
                             for j, x in enumerate(xs))  # fmt: skip
        emitted.append((lines, set(used), set(name) - known))
    # a value crossing parts: stored by the part defining it, read by the parts using it
    # (an input is loaded again by each part that reads it)
    inputs = {s.index: s for s in nodes if s.op == "in"}
    slot: dict[int, str] = {}
    count = {"sv": 0, "sm": 0}  # values and masks crossing parts so far
    for _, refs, defs in emitted:
        for i in sorted(r for r in refs if isinstance(r, int) and r not in defs):
            if i not in slot and i not in inputs:
                kind = "sm" if i in masks else "sv"
                slot[i] = f"{kind}[{count[kind]}]"
                count[kind] += 1
    n_sv, n_sm = count["sv"], count["sm"]
    const_name = {n: c for c, n in consts.items()}
    funcs: list[str] = []
    calls: list[str] = []
    decls: list[str] = []
    for k, (lines_k, refs, defs) in enumerate(emitted):
        head = [
            f"  const V {n} = {_const(const_name[n], dtype)};"
            for n in sorted((r for r in refs if isinstance(r, str)), key=lambda n: int(n[1:]))
        ]
        for i in sorted(r for r in refs if isinstance(r, int) and r not in defs):
            if i in inputs:
                arr, j = inputs[i].args
                a = in_index[arr]
                head.append(f"  const V {name[i]} = load(in[{a}], in_stride[{a}], {j});")
            else:
                head.append(f"  const {'M' if i in masks else 'V'} {name[i]} = {slot[i]};")
        tail = [f"  {slot[i]} = {name[i]};" for i in sorted(defs) if i in slot]
        fn = f"{symbol}_part{k}"
        sig = (f"TC_PART __attribute__((noinline)) void {fn}(const T* const* in, const int64_t*"
               " in_stride, T* const* out, const int64_t* out_stride, V* sv, M* sm)")  # fmt: skip
        decls.append(sig + ";")
        funcs.append(f"#if TC_HAS({k})\n{sig} {{\n" + "\n".join(head + lines_k + tail)
                     + "\n}\n#endif\n")  # fmt: skip
        calls.append(f"  {fn}(in, in_stride, out, out_stride, sv, sm);")
    calls = [f"  V sv[{max(n_sv, 1)}];", f"  M sm[{max(n_sm, 1)}];", *calls]
    body = "\n".join(calls)
    prelude = emit_prelude(dtype, vbytes)
    n_in = [len(v) for v in trace.inputs.values()]
    n_out = [len(v) for v in outputs.values()]
    # the last, partial block runs on zero-padded copies of its rows
    pad_in = "\n".join(
        f"    T b{a}[W * {max(k, 1)}] = {{}};"
        f" for (int64_t r = 0; r < nl; ++r) for (int c = 0; c < {k}; ++c)"
        f" b{a}[r * {k} + c] = in[{a}][(f0 + r) * in_stride[{a}] + c];"
        for a, k in enumerate(n_in)
    )
    pad_out = "\n".join(f"    T o{a}[W * {max(k, 1)}];" for a, k in enumerate(n_out))
    unpad = "\n".join(
        f"    for (int64_t r = 0; r < nl; ++r) for (int c = 0; c < {k}; ++c)"
        f" out[{a}][(f0 + r) * out_stride[{a}] + c] = o{a}[r * {k} + c];"
        for a, k in enumerate(n_out)
    )
    return f"""{PARTS_MARK}{len(funcs)}
{prelude}
{GROUPS}
{chr(10).join(decls)}
{"".join(funcs)}
#if TC_HAS_MAIN
static inline void block(const T* const* in, const int64_t* in_stride, T* const* out,
                         const int64_t* out_stride) {{
{body}
}}

extern "C" void {symbol}(int64_t n, const T* const* in, const int64_t* in_stride,
                         T* const* out, const int64_t* out_stride) {{
  const T* ip[{max(len(n_in), 1)}];
  T* op[{max(len(n_out), 1)}];
  int64_t f0 = 0;
  for (; f0 + W <= n; f0 += W) {{
    for (int a = 0; a < {len(n_in)}; ++a) ip[a] = in[a] + f0 * in_stride[a];
    for (int a = 0; a < {len(n_out)}; ++a) op[a] = out[a] + f0 * out_stride[a];
    block(ip, in_stride, op, out_stride);
  }}
  if (f0 < n) {{
    const int64_t nl = n - f0;
{pad_in}
{pad_out}
    const T* pi[{max(len(n_in), 1)}] = {{{", ".join(f"b{a}" for a in range(len(n_in)))}}};
    T* po[{max(len(n_out), 1)}] = {{{", ".join(f"o{a}" for a in range(len(n_out)))}}};
    const int64_t si[{max(len(n_in), 1)}] = {{{", ".join(str(k) for k in n_in)}}};
    const int64_t so[{max(len(n_out), 1)}] = {{{", ".join(str(k) for k in n_out)}}};
    block(pi, si, po, so);
{unpad}
  }}
}}
#endif
"""
