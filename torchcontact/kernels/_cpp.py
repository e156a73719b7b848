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

import math
from collections.abc import Callable
from typing import Any

from torchcontact._scalar import Sym, Trace, loop_deps

_BINARY = {"add": "+", "sub": "-", "mul": "*", "div": "/"}

PRELUDE = r"""
#include <cmath>
#include <cstdint>
typedef TC_T T;
typedef T V __attribute__((vector_size(TC_VBYTES)));
enum { W = TC_VBYTES / sizeof(T) };
typedef decltype(V{} < V{}) M;
static inline V splat(T c) { return V{} + c; }
static inline V vsqrt(V x) { V r; for (int i = 0; i < W; ++i) r[i] = std::sqrt(x[i]); return r; }
typedef TC_I I __attribute__((vector_size(TC_VBYTES)));
// sin and cos of every lane: x = r + k pi/2 with |r| <= pi/4 (Cody-Waite reduction in three
// exactly representable parts of pi/2, fused multiply-adds), Taylor polynomials of r (terms up
// to r^17 and r^18: below half an ulp on |r| <= pi/4), quadrant k mod 4 by selects. Lanes
// beyond the reduction's exact range (|x| > TC_SC_LIMIT) are recomputed with libm.
static inline void vsincos(V x, V* s, V* c) {
  const V k = (x * (T)TC_2_PI + (T)TC_MAGIC) - (T)TC_MAGIC;
  V r = x - k * (T)TC_C1;
  r = r - k * (T)TC_C2;
  r = r - k * (T)TC_C3;
  const V z = r * r;
  const V ps = r + r * z * (TC_SIN_POLY);
  const V pc = (T)1 + z * (TC_COS_POLY);
  const I q = __builtin_convertvector(k, I);
  const I odd = (q & 1) != 0;
  const V sn = odd ? pc : ps;
  const V cs = odd ? ps : pc;
  *s = ((q & 2) != 0) ? -sn : sn;
  *c = (((q + 1) & 2) != 0) ? -cs : cs;
  bool big = false;
  for (int l = 0; l < W; ++l) big |= !(std::fabs(x[l]) <= (T)TC_SC_LIMIT);
  if (__builtin_expect(big, 0)) {
    for (int l = 0; l < W; ++l) {
      if (!(std::fabs(x[l]) <= (T)TC_SC_LIMIT)) {
        (*s)[l] = std::sin(x[l]);
        (*c)[l] = std::cos(x[l]);
      }
    }
  }
}
static inline bool all_lanes(M m) {
  bool a = true;
  for (int l = 0; l < W; ++l) a = a && m[l];
  return a;
}
// one lane per frame: W rows of a (N, k) array, element j of each
static inline V load(const T* p, int64_t s, int j) { return V{TC_LOAD}; }
static inline void store(T* p, int64_t s, int j, V x) { TC_STORE }
"""


# pi/2 to 60 digits (a mathematical constant), split for the Cody-Waite reduction
_HALF_PI = "1.57079632679489661923132169163975144209858469968755291048747"


def _sincos_constants(dtype: str) -> dict[str, str]:
    """Constants of ``vsincos`` for ``double`` or ``float``: pi/2 in three parts, the range."""
    from decimal import Decimal, getcontext

    getcontext().prec = 80
    bits, mant, magic = (30, 53, "0x1.8p52") if dtype == "double" else (11, 24, "0x1.8p23")
    rest = Decimal(_HALF_PI)
    parts = []
    for _ in range(2):  # two parts of ``bits`` significant bits each: k * part is exact
        m, ex = math.frexp(float(rest))
        part = math.ldexp(math.floor(m * 2**bits), ex - bits)
        parts.append(part)
        rest -= Decimal(part)
    parts.append(float(rest))
    limit = 2.0 ** (mant - bits - 1) * float(Decimal(_HALF_PI))
    fact = [1.0]
    for n in range(1, 20):
        fact.append(fact[-1] * n)

    def horner(coeffs: list[float]) -> str:
        expr = f"(T){coeffs[-1]!r}"
        for c in reversed(coeffs[:-1]):
            expr = f"(T){c!r} + z * ({expr})"
        return expr

    sin_c = [(-1) ** k / fact[2 * k + 1] for k in range(1, 9)]  # r^3 .. r^17 over r^3
    cos_c = [(-1) ** k / fact[2 * k] for k in range(1, 10)]  # r^2 .. r^18 over r^2
    return {
        "TC_2_PI": repr(float(1 / Decimal(_HALF_PI))),
        "TC_MAGIC": magic,
        "TC_C1": repr(parts[0]),
        "TC_C2": repr(parts[1]),
        "TC_C3": repr(parts[2]),
        "TC_SIN_POLY": horner(sin_c),
        "TC_COS_POLY": horner(cos_c),
        "TC_SC_LIMIT": repr(limit),
        "TC_I": "int64_t" if dtype == "double" else "int32_t",
    }


def _const(c: float, dtype: str) -> str:
    if c != c:  # NaN
        return "splat(NAN)"
    if c in (float("inf"), float("-inf")):
        return f"splat({'-' if c < 0 else ''}INFINITY)"
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
) -> str:
    """C++ source of one kernel.

    Args:
        trace: the traced program; its ``inputs`` fix the input order.
        outputs: output name -> scalars (symbols or constants), in the caller's output order.
        dtype: ``"double"`` or ``"float"``.
        vbytes: bytes per vector value (lanes ``= vbytes / sizeof(T)``).
        symbol: name of the exported C function.

    Returns:
        The source. The function is ``void symbol(int64_t n, const T* const* in, const int64_t*
        in_stride, T* const* out, const int64_t* out_stride)`` with one pointer and row stride
        (elements) per input array and per output array, in declaration order.
    """
    flat_out = [x for xs in outputs.values() for x in xs]
    nodes = live_nodes(trace, flat_out)
    bodies = loop_bodies(nodes)
    deferred = {b.index for body in bodies.values() for b in body}
    name = {}
    consts: dict[float, str] = {}
    lines: list[str] = []
    sincos: dict[str, tuple[str, str]] = {}
    in_index = {k: i for i, k in enumerate(trace.inputs)}

    def ref(a) -> str:
        if isinstance(a, Sym):
            return name[a.index]
        key = float(a)
        if key not in consts:
            consts[key] = f"c{len(consts)}"
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

    for s in nodes:
        if s.index in deferred or s.op == "carry":
            continue
        if s.op == "loop":
            name.update((c.index, f"t{c.index}") for c in s.args[0].carries)
            emit_loop(s, bodies[s.index], lines, ref, emit_node, sincos, "V", "all_lanes({})")
            continue
        emit_node(s)

    stores = []
    for k, xs in enumerate(outputs.values()):
        for j, x in enumerate(xs):
            stores.append(f"  store(out[{k}], out_stride[{k}], {j}, {ref(x)});")
    const_lines = [f"  const V {n} = {_const(c, dtype)};" for c, n in consts.items()]
    body = "\n".join(const_lines + lines + stores)
    lanes = vbytes // (8 if dtype == "double" else 4)
    prelude = PRELUDE
    for k, val in _sincos_constants(dtype).items():
        prelude = prelude.replace(k, val)
    prelude = (
        prelude.replace("TC_T", dtype)
        .replace("TC_VBYTES", str(vbytes))
        .replace("TC_LOAD", ", ".join(f"p[{i} * s + j]" for i in range(lanes)))
        .replace("TC_STORE", " ".join(f"p[{i} * s + j] = x[{i}];" for i in range(lanes)))
    )
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
    return f"""{prelude}
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
"""
