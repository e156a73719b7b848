"""The C++ text the kernels and the tape VM share, and the VM's own source: standard library only.

The generated kernels (:mod:`torchcontact.kernels._cpp`) and the tape VM
(:mod:`torchcontact.kernels._vm`) start with the same prelude (vector types, ``vsincos``), so
their sines and cosines are one function. The VM's source depends on nothing but the dtype and
the machine's vector width, so its cache entry is known before anything is traced: a command
can start the VM's build before it imports torch (:func:`torchcontact._lightkernels.start_vm_build`,
which loads this file by path, as it loads :mod:`torchcontact.kernels._store`).
"""

from __future__ import annotations

import functools
import hashlib
import math
import platform
from typing import Any

# ------------------------------------------------------------------ shared prelude
PRELUDE = r"""
#include <stdint.h>
typedef TC_T T;
typedef T V __attribute__((vector_size(TC_VBYTES)));
enum { W = TC_VBYTES / sizeof(T) };
typedef decltype(V{} < V{}) M;
static inline V splat(T c) { return V{} + c; }
// libm by its builtins (<cmath> alone takes 0.2 s of every compile), float or double as std::
static inline T tc_sqrt(T x) {
  if constexpr (sizeof(T) == 4) return __builtin_sqrtf(x); else return __builtin_sqrt(x);
}
static inline T tc_sin(T x) {
  if constexpr (sizeof(T) == 4) return __builtin_sinf(x); else return __builtin_sin(x);
}
static inline T tc_cos(T x) {
  if constexpr (sizeof(T) == 4) return __builtin_cosf(x); else return __builtin_cos(x);
}
static inline V vsqrt(V x) { V r; for (int i = 0; i < W; ++i) r[i] = tc_sqrt(x[i]); return r; }
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
  for (int l = 0; l < W; ++l) big |= !(__builtin_fabs(x[l]) <= (T)TC_SC_LIMIT);
  if (__builtin_expect(big, 0)) {
    for (int l = 0; l < W; ++l) {
      if (!(__builtin_fabs(x[l]) <= (T)TC_SC_LIMIT)) {
        (*s)[l] = tc_sin(x[l]);
        (*c)[l] = tc_cos(x[l]);
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


def emit_prelude(dtype: str, vbytes: int) -> str:
    """:data:`PRELUDE` for ``dtype`` (``"double"`` or ``"float"``) and ``vbytes``-byte vectors.

    The generated kernels and the tape VM share it, so their
    sines and cosines (``vsincos``) are the same function.
    """
    lanes = vbytes // (8 if dtype == "double" else 4)
    prelude = PRELUDE
    for k, val in _sincos_constants(dtype).items():
        prelude = prelude.replace(k, val)
    return (
        prelude.replace("TC_T", dtype)
        .replace("TC_VBYTES", str(vbytes))
        .replace("TC_LOAD", ", ".join(f"p[{i} * s + j]" for i in range(lanes)))
        .replace("TC_STORE", " ".join(f"p[{i} * s + j] = x[{i}];" for i in range(lanes)))
    )


# ------------------------------------------------------------------ the machine
@functools.cache
def machine_tag() -> str:
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


@functools.cache
def vector_bytes() -> int:
    """Bytes of one SIMD register: 64 with AVX-512, else 32 (AVX2; other ISAs split it)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return 64 if " avx512f" in line else 32
    except OSError:
        pass
    return 32


# ------------------------------------------------------------------ the tape VM
#: Environment variable choosing how programs without a built kernel run
#: (:data:`torchcontact.kernels.VM_ENV`): ``0`` turns the tape VM off.
VM_ENV = "TORCHCONTACT_VM"
#: Frames per block: each instruction runs on this many frames (a slot is ``VM_BLOCK`` values).
#: Measured in ``benchmarks/vm.py`` (iCub estimator, AVX2): 32 and 128 within a few percent of
#: 64; larger blocks spill the live slots out of L2.
VM_BLOCK = 64

#: Bump when the bytecode or the interpreter's calling convention changes.
VM_VERSION = "2"

VM_SOURCE = r"""
#include <stdlib.h>
enum { B = TC_BLOCK, NV = B / W };
typedef decltype(M{}[0] + 0) MI;  // one lane of a mask: 0 or all ones
// opcode = 16 * base + flags: an operand a, b, c or e with its flag set is a constant (an index
// into the constants) instead of a slot
enum { KA = 1, KB = 2, KC = 4, KE = 8 };
enum {
  LOAD, STORE, MOV, ADD, SUB, MUL, DIV, NEG, SQRT, SIN, COS, SINCOS, SEL, GT, FINITE, AND, OR,
  NOT, LOOP, ENDLOOP, FMA, FMS, MMA, MMS, ADD3, FNM, DOT3, DOT3S
};
// three products (dot3, dot3s): the flags name a pattern instead, P_G: g is a constant, P_BEG:
// b, e and g are (the second factor of each product)
enum { P_G = 1, P_BEG = 2 };
struct Ins { int32_t op, d, a, b, c, e, f, g; };

extern "C" int tc_vm_abi(void) { return TC_VM_ABI; }
extern "C" int64_t tc_vm_block(void) { return B; }

// operand P of field F: the slot's vectors P##s, or the constant's splat P##k
#define SL(P, F) const V* P##s = S + (int64_t)x.F * NV;
#define SK(P, F) const V P##k = splat(K[x.F]);
// the same where the field may hold a slot (its flag FLAG unset): constant 0 then
#define SKF(P, F, FLAG) const V P##k = splat(K[(x.op & FLAG) ? x.F : 0]);
// The arithmetic opcodes are cases of their own per constant pattern (one dispatch, and each
// loop vectorised), named by the opcode with its flags.
#define C1(OPC, EXPR) \
  case 16 * OPC: { SL(a, a) for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v]); break; } \
  case 16 * OPC + KA: { SK(a, a) for (int v = 0; v < NV; ++v) D[v] = EXPR(ak); break; }
#define C2(OPC, EXPR) \
  case 16 * OPC: { SL(a, a) SL(b, b) for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v]); \
    break; } \
  case 16 * OPC + KA: { SK(a, a) SL(b, b) for (int v = 0; v < NV; ++v) D[v] = EXPR(ak, bs[v]); \
    break; } \
  case 16 * OPC + KB: { SL(a, a) SK(b, b) for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bk); \
    break; }
#define C3(OPC, EXPR) \
  case 16 * OPC: { SL(a, a) SL(b, b) SL(c, c) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], cs[v]); break; } \
  case 16 * OPC + KA: { SK(a, a) SL(b, b) SL(c, c) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(ak, bs[v], cs[v]); break; } \
  case 16 * OPC + KB: { SL(a, a) SK(b, b) SL(c, c) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bk, cs[v]); break; } \
  case 16 * OPC + KC: { SL(a, a) SL(b, b) SK(c, c) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], ck); break; }
// two products: a * b and c * e, a constant only as the second factor of each
#define C4(OPC, EXPR) \
  case 16 * OPC: { SL(a, a) SL(b, b) SL(c, c) SL(e, e) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], cs[v], es[v]); break; } \
  case 16 * OPC + KB: { SL(a, a) SK(b, b) SL(c, c) SL(e, e) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bk, cs[v], es[v]); break; } \
  case 16 * OPC + KE: { SL(a, a) SL(b, b) SL(c, c) SK(e, e) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], cs[v], ek); break; } \
  case 16 * OPC + KB + KE: { SL(a, a) SK(b, b) SL(c, c) SK(e, e) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bk, cs[v], ek); break; }
#define C6(OPC, EXPR) \
  case 16 * OPC: { SL(a, a) SL(b, b) SL(c, c) SL(e, e) SL(f, f) SL(g, g) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], cs[v], es[v], fs[v], gs[v]); break; } \
  case 16 * OPC + P_G: { SL(a, a) SL(b, b) SL(c, c) SL(e, e) SL(f, f) SK(g, g) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bs[v], cs[v], es[v], fs[v], gk); break; } \
  case 16 * OPC + P_BEG: { SL(a, a) SK(b, b) SL(c, c) SK(e, e) SL(f, f) SK(g, g) \
    for (int v = 0; v < NV; ++v) D[v] = EXPR(as[v], bk, cs[v], ek, fs[v], gk); break; }
#define E_ID(a) a
#define E_ADD(a, b) (a) + (b)
#define E_SUB(a, b) (a) - (b)
#define E_MUL(a, b) (a) * (b)
#define E_DIV(a, b) (a) / (b)
#define E_FMA(a, b, c) (a) * (b) + (c)
#define E_FMS(a, b, c) (a) * (b) - (c)
#define E_ADD3(a, b, c) ((a) + (b)) + (c)
#define E_MMA(a, b, c, e) (a) * (b) + (c) * (e)
#define E_MMS(a, b, c, e) (a) * (b) - (c) * (e)
#define E_FNM(a, b, c) (c) - (a) * (b)
#define E_DOT3(a, b, c, e, f, g) (a) * (b) + (c) * (e) + (f) * (g)
#define E_DOT3S(a, b, c, e, f, g) (a) * (b) - (c) * (e) + (f) * (g)

// Runs the bytecode on frames [0, n): blocks of B frames, one instruction at a time on a block.
// Slot k is S[k * NV .. k * NV + NV) (B values; a mask slot holds MI lanes). Returns 0, or 1
// when the slots cannot be allocated.
extern "C" int tc_vm(const int32_t* code, int64_t ncode, const T* K, int64_t nconst,
                     int64_t nslots, int64_t n, const T* const* in, const int64_t* in_stride,
                     T* const* out, const int64_t* out_stride) {
  (void)nconst;
  V* S = (V*)aligned_alloc(64, (size_t)(nslots > 0 ? nslots : 1) * NV * sizeof(V));
  if (!S) return 1;
  const T zero[1] = {0};
  if (nconst == 0) K = zero;
  const Ins* P = (const Ins*)code;
  for (int64_t f0 = 0; f0 < n; f0 += B) {
    const int64_t nl = n - f0 < B ? n - f0 : B;
    int64_t it = 0;
    for (int64_t pc = 0; pc < ncode; ++pc) {
      const Ins& x = P[pc];
      V* D = S + (int64_t)x.d * NV;
      switch (x.op) {
        C2(ADD, E_ADD) C2(SUB, E_SUB) C2(MUL, E_MUL) C2(DIV, E_DIV)
        C3(FMA, E_FMA) C3(FMS, E_FMS) C3(ADD3, E_ADD3) C3(FNM, E_FNM)
        C4(MMA, E_MMA) C4(MMS, E_MMS)
        C6(DOT3, E_DOT3) C6(DOT3S, E_DOT3S)
        C1(MOV, E_ID)
        default:
      switch (x.op >> 4) {
        case LOAD: {  // slot d = column b of input a
          T* d = (T*)D;
          const int64_t s = in_stride[x.a];
          const T* p = in[x.a] + f0 * s + x.b;
          if (nl == B) {
            for (int f = 0; f < B; ++f) d[f] = p[f * s];
          } else {  // the last, partial block: zero-padded
            for (int f = 0; f < B; ++f) d[f] = f < nl ? p[f * s] : (T)0;
          }
          break;
        }
        case STORE: {  // column b of output a = slot (or constant) c
          const int64_t s = out_stride[x.a];
          T* p = out[x.a] + f0 * s + x.b;
          if (x.op & KC) {
            for (int64_t f = 0; f < nl; ++f) p[f * s] = K[x.c];
          } else {
            const T* c = (const T*)(S + (int64_t)x.c * NV);
            for (int64_t f = 0; f < nl; ++f) p[f * s] = c[f];
          }
          break;
        }
        case NEG: {
          const V* A = S + (int64_t)x.a * NV;
          for (int v = 0; v < NV; ++v) D[v] = -A[v];
          break;
        }
        case SQRT: {
          T* d = (T*)D;
          const T* a = (const T*)(S + (int64_t)x.a * NV);
          for (int f = 0; f < B; ++f) d[f] = tc_sqrt(a[f]);
          break;
        }
        case SIN: case COS: case SINCOS: {  // sincos: d = sin a, c = cos a (one reduction)
          const V* A = S + (int64_t)x.a * NV;
          V* Cw = S + (int64_t)x.c * NV;
          const int k = x.op >> 4;
          for (int v = 0; v < NV; ++v) {
            V s, c;
            vsincos(A[v], &s, &c);
            if (k == COS) D[v] = c; else D[v] = s;
            if (k == SINCOS) Cw[v] = c;
          }
          break;
        }
        case SEL: {  // d = mask a ? b : c
          const M* m = (const M*)(S + (int64_t)x.a * NV);
          SL(b, b) SL(c, c) SKF(b, b, KB) SKF(c, c, KC)
          const bool bc = x.op & KB, cc = x.op & KC;
          if (bc && cc) { for (int v = 0; v < NV; ++v) D[v] = m[v] ? bk : ck; }
          else if (bc) { for (int v = 0; v < NV; ++v) D[v] = m[v] ? bk : cs[v]; }
          else if (cc) { for (int v = 0; v < NV; ++v) D[v] = m[v] ? bs[v] : ck; }
          else { for (int v = 0; v < NV; ++v) D[v] = m[v] ? bs[v] : cs[v]; }
          break;
        }
        case GT: {
          M* d = (M*)D;
          SL(a, a) SL(b, b) SKF(a, a, KA) SKF(b, b, KB)
          if (x.op & KA) { for (int v = 0; v < NV; ++v) d[v] = ak > bs[v]; }
          else if (x.op & KB) { for (int v = 0; v < NV; ++v) d[v] = as[v] > bk; }
          else { for (int v = 0; v < NV; ++v) d[v] = as[v] > bs[v]; }
          break;
        }
        case FINITE: {  // x - x is 0 for finite x, NaN for NaN and +-inf
          M* d = (M*)D;
          const V* A = S + (int64_t)x.a * NV;
          for (int v = 0; v < NV; ++v) { V y = A[v] - A[v]; d[v] = y == y; }
          break;
        }
        case AND: case OR: {
          M* d = (M*)D;
          const M* a = (const M*)(S + (int64_t)x.a * NV);
          const M* b = (const M*)(S + (int64_t)x.b * NV);
          if ((x.op >> 4) == AND) { for (int v = 0; v < NV; ++v) d[v] = a[v] & b[v]; }
          else { for (int v = 0; v < NV; ++v) d[v] = a[v] | b[v]; }
          break;
        }
        case NOT: {
          M* d = (M*)D;
          const M* a = (const M*)(S + (int64_t)x.a * NV);
          for (int v = 0; v < NV; ++v) d[v] = ~a[v];
          break;
        }
        case LOOP:  // a: the budget, b: the instruction after the loop
          it = 0;
          if (x.a <= 0) pc = x.b - 1;
          break;
        case ENDLOOP: {  // a: the stop mask's slot (or -1 never, -2 always), b: the body, c: budget
          ++it;
          bool stop = x.a == -2;
          if (x.a >= 0) {
            const MI* m = (const MI*)(S + (int64_t)x.a * NV);
            stop = true;
            for (int64_t f = 0; f < nl; ++f) stop = stop && m[f];
          }
          if (!stop && it < x.c) pc = x.b - 1;
          break;
        }
      }
      }
    }
  }
  free(S);
  return 0;
}
"""


def vm_source(dtype: str, vbytes: int, block: int = VM_BLOCK) -> str:
    """The VM's C++ source for ``dtype`` (``"double"``/``"float"``), ``vbytes``-byte vectors."""
    lanes = vbytes // (8 if dtype == "double" else 4)
    if block % lanes:
        raise ValueError(f"block {block} is not a multiple of {lanes} lanes")
    body = VM_SOURCE.replace("TC_BLOCK", str(block)).replace("TC_VM_ABI", VM_VERSION)
    return f"// torchcontact tape VM {VM_VERSION}\n{emit_prelude(dtype, vbytes)}{body}"


def vm_entry(store: Any, dtype: str, vbytes: int | None = None, machine: str | None = None):
    """The VM's cache entry for ``dtype`` (``"double"``/``"float"``) and its source.

    The entry is named by the hash of the source, the VM's version, the machine and the VM's
    compiler flags.

    Args:
        store: :mod:`torchcontact.kernels._store` (the package's, or one loaded by path).
        dtype: ``"double"`` or ``"float"``.
        vbytes: vector bytes (default :func:`vector_bytes`).
        machine: the machine's tag (default :func:`machine_tag`).

    Returns:
        ``(store.Entry, source)``.
    """
    vbytes = vector_bytes() if vbytes is None else vbytes
    machine = machine_tag() if machine is None else machine
    src = vm_source(dtype, vbytes)
    h = hashlib.sha256(f"{VM_VERSION}|{machine}|{store.VM_FLAGS}|{src}".encode()).hexdigest()[:20]
    return store.Entry(store.cache_dir() / "kernels", f"{store.VM_PREFIX}{dtype}_{h}"), src
