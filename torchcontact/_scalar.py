"""Scalar arithmetic of the physics program: one source, three kinds of scalar.

torchcontact writes its physics (the RNEA passes, the contact maps, the solve) once, as
straight-line code on *scalars* (:mod:`torchcontact.spatial` builds 3-vectors, rotations and
spatial vectors as tuples of them). A scalar is one of:

* a Python ``float`` (or ``bool`` for masks): a constant of the model, folded at trace time, so
  that the exact zeros and ones of joint axes, placements and motion subspaces cost nothing;
* a torch ``Tensor`` holding one value per frame, ``(N,)``: the *eager* backend, differentiable,
  on any device and dtype, exportable with ``torch.onnx.export``;
* a :class:`Sym`, a node of a :class:`Trace`: running the same program on symbols records an SSA
  graph (common subexpressions merged, constants folded) that :mod:`torchcontact.kernels` turns
  into a compiled C++ (or CUDA) kernel processing many frames per instruction.

Every operation goes through the functions below (never through ``+`` or ``*`` on scalars), which
fold constants and dispatch on the kind of their operands. Masks (the results of comparisons) are
``bool`` constants, bool tensors or boolean symbols, consumed by :func:`select`.

Iterative algorithms with a fixed budget (the friction-cone solver) use :func:`loop`: eager torch
runs the body in a Python loop, a trace records the body once and generated kernels emit a real
loop around it (the code of one iteration, not of the whole budget), leaving it early once every
frame of a vector block (CPU) or the thread's frame (CUDA) has converged.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple, Union

import torch
from torch import Tensor

from torchcontact._internal import in_tracing

__all__ = [
    "Scalar",
    "Sym",
    "Trace",
    "add",
    "cos",
    "div",
    "float_dtype",
    "gt",
    "is_const",
    "isfinite",
    "logical_and",
    "logical_not",
    "logical_or",
    "lincomb",
    "loop",
    "mul",
    "neg",
    "rsqrt",
    "select",
    "sin",
    "sqrt",
    "sub",
    "sum_",
]


class Sym:
    """A value of a :class:`Trace`: an input, or an operation on earlier values and constants.

    Attributes:
        op: ``"in"`` (an input), ``"add"``, ``"sub"``, ``"mul"``, ``"div"``, ``"neg"``,
            ``"sqrt"``, ``"sin"``, ``"cos"``, ``"sel"`` (mask, a, b), ``"gt"``, ``"finite"``,
            ``"and"``, ``"or"``, ``"not"``.
        args: operands: :class:`Sym` or Python ``float``/``bool`` constants; for ``"in"``,
            ``(input name, index)``.
        index: position in the trace (topological order).
        mask: True for boolean values (comparisons and their combinations).
    """

    __slots__ = ("op", "args", "index", "mask", "trace")

    def __init__(self, trace: Trace, op: str, args: tuple, index: int, mask: bool) -> None:
        self.trace = trace
        self.op = op
        self.args = args
        self.index = index
        self.mask = mask

    def __repr__(self) -> str:
        return f"Sym(%{self.index} = {self.op}{self.args if self.op == 'in' else ''})"

    # Scalars are combined with the module functions only: a stray ``+`` is a bug.
    def __bool__(self) -> bool:
        raise TypeError("a traced value has no truth value; use select()")


Scalar = Union[float, bool, Tensor, Sym]  # noqa: UP007 (a runtime alias)


class Trace:
    """An SSA program recorded by running physics code on :class:`Sym` scalars.

    Nodes are hash-consed: the same operation on the same operands returns the existing node
    (common-subexpression elimination), with the operands of ``add``/``mul`` ordered so that
    ``a + b`` and ``b + a`` are one node.

    Example:
        >>> tr = Trace()
        >>> x, y = tr.input("x", 2)
        >>> z = add(mul(x, y), mul(y, x))  # one product, counted twice
        >>> len(tr.nodes), z.op
        (4, 'add')
    """

    def __init__(self) -> None:
        self.nodes: list[Sym] = []
        self.inputs: dict[str, list[Sym]] = {}
        self._cse: dict[tuple, Sym] = {}
        self._in_loop = False

    def input(self, name: str, n: int) -> list[Sym]:
        """Declare an input array of ``n`` scalars per frame; returns its symbols."""
        if name in self.inputs:
            raise ValueError(f"input {name!r} declared twice")
        syms = [self._new("in", (name, i), False) for i in range(n)]
        self.inputs[name] = syms
        return syms

    def _new(self, op: str, args: tuple, mask: bool) -> Sym:
        s = Sym(self, op, args, len(self.nodes), mask)
        self.nodes.append(s)
        return s

    def node(self, op: str, args: tuple, mask: bool = False) -> Sym:
        """The node ``op(*args)``, created unless an identical one exists."""
        key = (op, *(("s", a.index) if isinstance(a, Sym) else ("c", type(a), a) for a in args))
        hit = self._cse.get(key)
        if hit is None:
            hit = self._new(op, args, mask)
            self._cse[key] = hit
        return hit


def _trace_of(*xs: Any) -> Trace | None:
    for x in xs:
        if isinstance(x, Sym):
            return x.trace
    return None


def is_const(x: Any) -> bool:
    """True for a Python number (a constant folded at trace time)."""
    return isinstance(x, (float, int, bool))


def _ordered(a: Any, b: Any) -> tuple[Any, Any]:
    """Canonical operand order of a commutative op (constants last, then by node index)."""
    if is_const(a) or (isinstance(a, Sym) and isinstance(b, Sym) and a.index > b.index):
        return b, a
    return a, b


def add(a: Scalar, b: Scalar) -> Scalar:
    """``a + b``."""
    if is_const(a):
        if is_const(b):
            return float(a) + float(b)
        if a == 0:
            return b
    elif is_const(b) and b == 0:
        return a
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("add", _ordered(a, b))
    return a + b


def sub(a: Scalar, b: Scalar) -> Scalar:
    """``a - b``."""
    if is_const(b):
        if is_const(a):
            return float(a) - float(b)
        if b == 0:
            return a
    elif is_const(a) and a == 0:
        return neg(b)
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("sub", (a, b))
    return a - b


def neg(a: Scalar) -> Scalar:
    """``-a``."""
    if is_const(a):
        return -float(a)
    if isinstance(a, Sym):
        if a.op == "neg":
            return a.args[0]
        return a.trace.node("neg", (a,))
    return -a


def mul(a: Scalar, b: Scalar) -> Scalar:
    """``a * b``; a constant 0 gives 0 (a structural zero of the model), 1 and -1 fold."""
    if is_const(a) or is_const(b):
        if is_const(a) and is_const(b):
            return float(a) * float(b)
        c, x = (a, b) if is_const(a) else (b, a)
        if c == 0:
            return 0.0
        if c == 1:
            return x
        if c == -1:
            return neg(x)
        tr = _trace_of(x)
        if tr is not None:
            return tr.node("mul", (x, float(c)))
        return x * float(c)
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("mul", _ordered(a, b))
    return a * b


def div(a: Scalar, b: Scalar) -> Scalar:
    """``a / b``."""
    if is_const(b):
        if b == 1:
            return a
        if is_const(a):
            return float(a) / float(b)
        return mul(a, 1.0 / float(b))
    if is_const(a) and a == 0:
        return 0.0
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("div", (a, b))
    return a / b


def sqrt(a: Scalar) -> Scalar:
    """Square root."""
    if is_const(a):
        return math.sqrt(a)
    if isinstance(a, Sym):
        return a.trace.node("sqrt", (a,))
    return torch.sqrt(a)


def sin(a: Scalar) -> Scalar:
    """Sine (rad)."""
    if is_const(a):
        return math.sin(a)
    if isinstance(a, Sym):
        return a.trace.node("sin", (a,))
    return torch.sin(a)


def cos(a: Scalar) -> Scalar:
    """Cosine (rad)."""
    if is_const(a):
        return math.cos(a)
    if isinstance(a, Sym):
        return a.trace.node("cos", (a,))
    return torch.cos(a)


def rsqrt(a: Scalar) -> Scalar:
    """``1 / sqrt(a)``."""
    return div(1.0, sqrt(a))


def gt(a: Scalar, b: Scalar) -> Scalar:
    """Mask ``a > b``."""
    if is_const(a) and is_const(b):
        return bool(a > b)
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("gt", (a, b), mask=True)
    if is_const(a):
        return torch.lt(b, a)
    return torch.gt(a, b)


def isfinite(a: Scalar) -> Scalar:
    """Mask: ``a`` is neither NaN nor infinite."""
    if is_const(a):
        return math.isfinite(a)
    if isinstance(a, Sym):
        return a.trace.node("finite", (a,), mask=True)
    return torch.isfinite(a)


def logical_and(a: Scalar, b: Scalar) -> Scalar:
    """Mask ``a and b``."""
    if is_const(a) or is_const(b):
        if is_const(a) and is_const(b):
            return bool(a) and bool(b)
        c, x = (a, b) if is_const(a) else (b, a)
        return x if c else False
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("and", _ordered(a, b), mask=True)
    return torch.logical_and(a, b)


def logical_or(a: Scalar, b: Scalar) -> Scalar:
    """Mask ``a or b``."""
    if is_const(a) or is_const(b):
        if is_const(a) and is_const(b):
            return bool(a) or bool(b)
        c, x = (a, b) if is_const(a) else (b, a)
        return True if c else x
    tr = _trace_of(a, b)
    if tr is not None:
        return tr.node("or", _ordered(a, b), mask=True)
    return torch.logical_or(a, b)


def logical_not(a: Scalar) -> Scalar:
    """Mask ``not a``."""
    if is_const(a):
        return not a
    if isinstance(a, Sym):
        if a.op == "not":
            return a.args[0]
        return a.trace.node("not", (a,), mask=True)
    return torch.logical_not(a)


_FLOAT_DTYPE: contextvars.ContextVar[torch.dtype] = contextvars.ContextVar(
    "torchcontact_float_dtype", default=torch.float64
)


@contextlib.contextmanager
def float_dtype(dtype: torch.dtype) -> Iterator[None]:
    """Within the block, tensors made from two constants (``select(mask, 1.0, 0.0)``) get ``dtype``.

    The eager backend runs a program inside it with the dtype of the program's inputs.
    """
    token = _FLOAT_DTYPE.set(dtype)
    try:
        yield
    finally:
        _FLOAT_DTYPE.reset(token)


def select(m: Scalar, a: Scalar, b: Scalar) -> Scalar:
    """``a`` where the mask ``m`` holds, else ``b`` (elementwise, branch-free)."""
    if is_const(m):
        return a if m else b
    if is_const(a) and is_const(b) and float(a) == float(b):
        return a
    tr = _trace_of(m, a, b)
    if tr is not None:
        return tr.node("sel", (m, a, b))
    like = a if isinstance(a, Tensor) else b if isinstance(b, Tensor) else None
    if like is None:
        like = torch.zeros(m.shape, dtype=_FLOAT_DTYPE.get(), device=m.device)
    if not isinstance(a, Tensor):
        a = like.new_full((), float(a))
    if not isinstance(b, Tensor):
        b = like.new_full((), float(b))
    return torch.where(m, a, b)


def sum_(xs: Sequence[Scalar]) -> Scalar:
    """Sum of scalars (constants folded; a balanced tree keeps dependency chains short)."""
    terms = [x for x in xs if not (is_const(x) and x == 0)]
    if not terms:
        return 0.0
    while len(terms) > 1:
        nxt = [add(terms[i], terms[i + 1]) for i in range(0, len(terms) - 1, 2)]
        if len(terms) % 2:
            nxt.append(terms[-1])
        terms = nxt
    return terms[0]


def lincomb(coeffs: Sequence[float], xs: Sequence[Scalar]) -> Scalar:
    """``sum_i coeffs[i] * xs[i]`` for constant coefficients (zeros skipped, +-1 folded)."""
    return sum_([mul(float(c), x) for c, x in zip(coeffs, xs, strict=True) if c != 0])


class Loop(NamedTuple):
    """The recorded body of a :func:`loop` (the ``args[0]`` of its ``"loop"`` node).

    Attributes:
        n: the iteration budget.
        init: the carried values' initial values (scalars from before the loop).
        carries: the ``"carry"`` symbols standing for the carried values inside the body.
        new: the carried values at the end of one iteration (scalars).
        stop: mask: this frame is at a fixed point of the body (it may leave the loop).
        start: index of the body's first node; the body's nodes are ``start <= index < end``.
        end: index one past the body's last node (the ``"loop"`` node's own index).
    """

    n: int
    init: tuple
    carries: tuple
    new: tuple
    stop: Any
    start: int
    end: int


_UNROLL: contextvars.ContextVar[bool] = contextvars.ContextVar("torchcontact_unroll", default=False)


@contextlib.contextmanager
def unrolled_loops() -> Iterator[None]:
    """Within the block, :func:`loop` on symbols records every iteration (no ``"loop"`` node).

    For consumers of a :class:`Trace` that have no loop construct (a node-per-op ONNX emitter).
    """
    token = _UNROLL.set(True)
    try:
        yield
    finally:
        _UNROLL.reset(token)


def loop(
    n: int,
    body: Callable[[list[Scalar]], tuple[list[Scalar], Scalar]],
    init: Sequence[Scalar],
) -> list[Scalar]:
    """``n`` iterations of ``state, stop = body(state)`` from ``init``; returns the final state.

    The body must leave a frame's state unchanged once it has returned ``stop`` for that frame
    (a converged frame is a fixed point). Then leaving early changes nothing, and the backends do:
    eager torch once every frame has stopped (never while tracing for export: the traced graph
    keeps the whole budget), a generated CPU kernel once every frame of its vector block has, a
    CUDA thread once its frame has. On symbols the body is traced once into a ``"loop"`` node
    (:class:`Loop`); values it computes are not visible after the loop (common subexpressions
    are not shared across the loop's boundary). Loops do not nest.

    Args:
        n: the iteration budget (>= 0).
        body: ``state -> (new state, stop mask)``; state entries are float scalars (not masks).
        init: the initial state.

    Returns:
        The state after the loop.

    Example:
        >>> def halve(s):  # halve while above 1
        ...     new = select(gt(s[0], 1.0), mul(s[0], 0.5), s[0])
        ...     return [new], logical_not(gt(new, 1.0))
        >>> loop(10, halve, [torch.tensor([8.0, 3000.0])])[0]  # 3000 uses the whole budget
        tensor([1.0000, 2.9297])
    """
    state = list(init)
    tr = _trace_of(*state)
    if tr is None or _UNROLL.get():
        for _ in range(n):
            state, stop = body(state)
            state = list(state)
            if isinstance(stop, bool) and stop:
                break
            if isinstance(stop, Tensor) and not in_tracing() and bool(stop.all()):
                break
        return state
    if tr._in_loop:
        raise ValueError("loops do not nest")
    if any(isinstance(x, Sym) and x.mask for x in state):
        raise ValueError("a loop carries float scalars; turn masks into select(m, 1.0, 0.0)")
    lid = sum(1 for s in tr.nodes if s.op == "loop")
    carries = [tr._new("carry", (lid, i), False) for i in range(len(state))]
    start, known = len(tr.nodes), len(tr._cse)
    tr._in_loop = True
    try:
        new, stop = body(list(carries))
    finally:
        tr._in_loop = False
        # values of the body are not visible after the loop: forget them for hash-consing
        for key in list(tr._cse)[known:]:
            del tr._cse[key]
    new = list(new)
    if len(new) != len(state):
        raise ValueError(f"loop body returned {len(new)} values for a state of {len(state)}")
    spec = Loop(int(n), tuple(state), tuple(carries), tuple(new), stop, start, len(tr.nodes))
    node = tr._new("loop", (spec,), False)
    return [tr._new("loopout", (node, i), False) for i in range(len(state))]


def loop_deps(s: Sym) -> list[Sym]:
    """The symbols a node reads (a ``"loop"`` node: its initial values, body results and stop)."""
    if s.op == "loop":
        spec: Loop = s.args[0]
        vals = [*spec.init, *spec.new, spec.stop]
        return [v for v in vals if isinstance(v, Sym)]
    if s.op == "in" or s.op == "carry":
        return []
    return [a for a in s.args if isinstance(a, Sym)]


def map_tensors(fn: Callable[[Tensor], Tensor], xs: Sequence[Scalar]) -> list[Scalar]:
    """Apply ``fn`` to the tensor scalars of ``xs`` (constants and symbols pass through)."""
    return [fn(x) if isinstance(x, Tensor) else x for x in xs]
