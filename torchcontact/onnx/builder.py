"""ONNX graph construction: the one builder of every graph torchcontact writes (extra ``export``).

Used by :mod:`torchcontact.onnx.batched`, :mod:`torchcontact.onnx.step` and
:mod:`torchcontact.onnx.export`:

* :class:`GraphBuilder`: nodes, deduplicated constants, inputs and outputs of one graph, typed in
  the graph's float dtype (float32 or float64), opset :data:`OPSET`.
* :func:`bilinear`: one *row-wise bilinear stage*. The physics is written once, on scalars
  (:mod:`torchcontact._scalar`, :mod:`torchcontact.spatial`); a stage such as
  ``spatial.motion_to_child(T, v)`` is traced on symbols for every row (body or slot), expanded
  into monomials of degree <= 2 of its two operands, and emitted as four to five nodes whatever
  the number of rows: two ``Gather`` of the factors, ``Mul`` (and a ``Mul`` by per-row
  coefficients when rows differ, e.g. by their inertia), one ``Gemm`` summing the terms into the
  outputs. This is what keeps the single-frame graph at a few hundred nodes: onnxruntime spends
  0.3-0.7 µs per node on one frame, whatever its size.
* :func:`emit_program`: a whole :class:`torchcontact.kernels.Program` as one node per scalar
  operation on ``(N, 1)`` columns (the batched graph: every node runs over ``N`` frames).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from torchcontact._scalar import Sym, Trace

__all__ = [
    "OPSET",
    "GraphBuilder",
    "Operand",
    "bilinear",
    "emit_program",
    "fold_linear_chains",
    "inline",
    "onnx_type",
]

#: ONNX opset of the graphs written here (onnxruntime >= 1.14 runs it).
OPSET = 18
#: IR version of the files (onnxruntime >= 1.16 loads it).
IR_VERSION = 9


def onnx_type(dtype) -> int:
    """ONNX element type of a numpy dtype."""
    from onnx import helper

    return helper.np_dtype_to_tensor_dtype(np.dtype(dtype))


class GraphBuilder:
    """Nodes, constants, inputs and outputs of one ONNX graph.

    Args:
        dtype: numpy float dtype of the graph's float tensors (float32 or float64).
        name: graph name.
    """

    def __init__(self, dtype: np.dtype | type, name: str = "torchcontact") -> None:
        self.dtype = np.dtype(dtype)
        self.name = name
        self.nodes: list = []
        self.initializers: list = []
        self.inputs: list = []
        self.outputs: list = []
        self._consts: dict = {}
        self._count = 0

    def fresh(self, hint: str = "t") -> str:
        """A new value name."""
        self._count += 1
        return f"{hint}{self._count}"

    def input(self, name: str, shape: Sequence[int | str], dtype=None) -> str:
        """Declare a graph input; returns its name."""
        from onnx import helper

        dt = helper.np_dtype_to_tensor_dtype(np.dtype(dtype or self.dtype))
        self.inputs.append(helper.make_tensor_value_info(name, dt, list(shape)))
        return name

    def output(self, name: str, shape: Sequence[int | str] | None = None, dtype=None) -> None:
        """Declare ``name`` (already produced by a node) as a graph output."""
        from onnx import helper

        dt = helper.np_dtype_to_tensor_dtype(np.dtype(dtype or self.dtype))
        self.outputs.append(helper.make_tensor_value_info(name, dt, shape))

    def const(self, value, dtype=None, scalar: bool = False) -> str:
        """A constant (deduplicated by dtype, shape and bytes); floats take the graph dtype.

        A single value is stored with shape ``(1,)`` (it broadcasts as a scalar), or ``()`` with
        ``scalar`` (where ONNX wants a true scalar: a ``Loop``'s trip count and condition).
        """
        from onnx import numpy_helper

        arr = np.asarray(value)
        if dtype is None:
            dtype = (
                np.int64 if arr.dtype.kind in "iu" else (bool if arr.dtype == bool else self.dtype)
            )
        arr = np.array(arr, dtype=dtype) if scalar else np.ascontiguousarray(arr, dtype=dtype)
        key = (arr.dtype.str, arr.shape, arr.tobytes())
        name = self._consts.get(key)
        if name is None:
            name = self.fresh("c")
            self.initializers.append(numpy_helper.from_array(arr, name))
            self._consts[key] = name
        return name

    def f(self, value) -> str:
        """A float constant in the graph dtype."""
        return self.const(np.asarray(value, dtype=float), self.dtype)

    def i(self, value) -> str:
        """An int64 constant."""
        return self.const(np.asarray(value, dtype=np.int64), np.int64)

    def op(self, op_type: str, *inputs: str, n_out: int = 1, out: str | None = None, **attrs):
        """Append a node; returns its output name (a list when ``n_out > 1``)."""
        from onnx import helper

        outs = [out] if out is not None else [self.fresh() for _ in range(n_out)]
        self.nodes.append(helper.make_node(op_type, list(inputs), outs, name=outs[0], **attrs))
        return outs[0] if n_out == 1 else outs

    def cast(self, x: str, to_float: bool = True) -> str:
        """Cast to the graph float dtype (or to bool)."""
        from onnx import helper

        to = helper.np_dtype_to_tensor_dtype(self.dtype if to_float else np.dtype(bool))
        return self.op("Cast", x, to=to)

    def branch(self, build: Callable[[], Sequence[str]], name: str = "branch"):
        """A subgraph (an ``If`` branch) of the nodes ``build()`` emits; returns its GraphProto.

        ``build`` emits nodes through this builder as usual (they go to the subgraph; constants
        stay initializers of the main graph, which the subgraph reads from the outer scope) and
        returns the values the branch outputs, in order (of the graph's float dtype; a value the
        branch does not compute, a constant or an outer value, gets an ``Identity``).
        """
        from onnx import helper

        outer = self.nodes
        self.nodes = []
        try:
            vals = list(build())
            made = {o for n in self.nodes for o in n.output}
            outs = [v if v in made else self.op("Identity", v) for v in vals]
            nodes = self.nodes
        finally:
            self.nodes = outer
        infos = [helper.make_tensor_value_info(o, onnx_type(self.dtype), None) for o in outs]
        return helper.make_graph(nodes, self.fresh(name), [], infos)

    def model(self, metadata: dict[str, str] | None = None):
        """The ``onnx.ModelProto``."""
        from onnx import helper

        g = helper.make_graph(
            self.nodes, self.name, self.inputs, self.outputs, initializer=self.initializers
        )
        m = helper.make_model(
            g, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="torchcontact"
        )
        m.ir_version = IR_VERSION
        for k, v in (metadata or {}).items():
            m.metadata_props.add(key=k, value=v)
        return m


# -------------------------------------------------------------------------------- bilinear stages


@dataclass(frozen=True)
class Operand:
    """One factor of a :func:`bilinear` stage: where row ``r``'s symbol ``j`` lives.

    Four layouts (``kind``):

    * ``"rows"``: ``tensor`` is ``(rows, n)``; symbol ``j`` of every row is column ``j``
      (``one``: the index of a column holding 1, or None);
    * ``"vec"``: ``tensor`` is 1-D; symbol ``j`` of row ``r`` is element ``index[r][j]``
      (``one``: the element holding 1);
    * ``"nd"``: ``tensor`` is ``(m, n)``; symbol ``j`` of row ``r`` is
      ``tensor[row_of[r], j]`` (``one`` as for ``"rows"``);
    * ``"col"``: ``tensor`` is an ``(n, 1)`` column shared by every row: symbol ``j`` is its
      entry ``j`` (``one`` as for ``"rows"``). Its symbols are selected as one ``(1, m)`` row
      (one ``Gemm``, no ``Reshape``) that broadcasts over the other operand's rows; it cannot
      be a stage's only factor.
    """

    tensor: str
    n: int
    kind: str = "rows"
    one: int | None = None
    index: np.ndarray | None = None
    row_of: Sequence[int] | None = None

    def position(self, r: int, j: int):
        """Gather index of symbol ``j`` of row ``r``."""
        if self.kind == "rows":
            return j
        if self.kind == "vec":
            return int(self.index[r][j])
        if self.kind == "col":
            return j
        return (int(self.row_of[r]), j)


def _polys(trace: Trace, outs: Sequence) -> list[dict]:
    """Expand traced outputs into polynomials of the inputs: ``{monomial: coefficient}``.

    A monomial is a sorted tuple of ``(input name, index)``; degrees above 2 and operations other
    than ``+ - *`` are refused (a stage must be bilinear).
    """
    memo: dict[int, dict] = {}

    def poly(x) -> dict:
        if isinstance(x, bool):
            raise ValueError("masks are not polynomial")
        if not isinstance(x, Sym):
            return {(): float(x)} if float(x) != 0.0 else {}
        if x.index in memo:
            return memo[x.index]
        op, args = x.op, x.args
        if op == "in":
            p = {((args[0], args[1]),): 1.0}
        elif op in ("add", "sub"):
            a, b = poly(args[0]), poly(args[1])
            p = dict(a)
            s = 1.0 if op == "add" else -1.0
            for m, c in b.items():
                p[m] = p.get(m, 0.0) + s * c
        elif op == "neg":
            p = {m: -c for m, c in poly(args[0]).items()}
        elif op == "mul":
            a, b = poly(args[0]), poly(args[1])
            p = {}
            for ma, ca in a.items():
                for mb, cb in b.items():
                    m = tuple(sorted(ma + mb))
                    if len(m) > 2:
                        raise ValueError("a bilinear stage produced a term of degree > 2")
                    p[m] = p.get(m, 0.0) + ca * cb
        else:
            raise ValueError(f"a bilinear stage cannot contain {op!r}")
        p = {m: c for m, c in p.items() if c != 0.0}
        memo[x.index] = p
        return p

    return [poly(o) for o in outs]


def bilinear(
    gb: GraphBuilder,
    a: Operand,
    b: Operand | None,
    rows: int,
    fn: Callable[[int, list, list], Sequence],
    n_out: int,
    one: bool = True,
    hint: str = "stage",
    add: str | None = None,
    beta: float = 1.0,
    transpose: bool = False,
    parts: Sequence[tuple[int, int]] | None = None,
) -> str | list[str]:
    """Emit the stage ``out[r] = fn(r, A[r], B[r])`` for every row ``r`` as four to five nodes.

    ``fn`` is ordinary scalar physics code (:mod:`torchcontact.spatial`); it must be polynomial of
    degree <= 2 in the operands' symbols (products of one ``A`` and one ``B`` symbol, or of two
    ``A`` symbols when ``b`` is None), with any row-dependent constants (inertia, slot frames)
    folded in by ``fn`` itself. Linear terms pair a symbol with the other operand's ``one``
    column; constant terms enter through the ``Gemm`` bias.

    Args:
        gb: the graph.
        a: first operand.
        b: second operand, or None for products within ``a``.
        rows: number of rows.
        fn: ``fn(r, a_syms, b_syms) -> n_out scalars``.
        n_out: outputs per row.
        one: append a column holding 1 to the result (so it can serve as an operand).
        hint: name prefix of the nodes' values.
        add: a value of the graph broadcastable to the result, added as ``beta * add`` (the
            final product's ``Gemm`` bias when the stage has no constant terms: no node of its
            own), or None.
        beta: its factor, 1 or -1.
        transpose: return the result transposed, ``(n_out [+ 1], rows)``, from the same final
            product (``W^T x^T``: no ``Transpose`` or ``Reshape`` after it; ``add`` then
            broadcasts to the transposed result). Not for linear stages.
        parts: column ranges ``[(start, stop)]`` of the result: the stage's final product
            emitted once per range, from the same terms (a ``Slice`` of the result costs
            onnxruntime more than a second product); returns the list of those results. Not
            with ``add`` or ``transpose``.

    Returns:
        The ``(rows, n_out [+ 1])`` result (plus ``beta * add``).
    """
    if beta not in (1.0, -1.0):
        raise ValueError(f"stage {hint}: beta must be 1 or -1, got {beta}")
    same = b is None
    bb = a if same else b
    per_row = []
    for r in range(rows):
        tr = Trace()
        sa = tr.input("a", a.n)
        sb = sa if same else tr.input("b", bb.n)
        outs = list(fn(r, sa, sb))
        if len(outs) != n_out:
            raise ValueError(f"stage {hint}: {len(outs)} outputs, expected {n_out}")
        per_row.append(_polys(tr, outs))
    n_cols = n_out + (1 if one else 0)
    bias = np.zeros((rows, n_cols))
    if one:
        bias[:, n_out] = 1.0

    def factors(mono) -> tuple[tuple[str, int], tuple[str, int]]:
        """The (A symbol, B symbol) whose product is ``mono``."""
        if len(mono) == 1:
            (src, j) = mono[0]
            if src == "a" and not same:
                if bb.one is None:
                    raise ValueError(f"stage {hint}: linear term in A but B has no 1 column")
                return ("a", j), ("b", bb.one)
            if a.one is None:
                raise ValueError(f"stage {hint}: linear term but A has no 1 column")
            return ("a", a.one), (src, j)
        (s1, j1), (s2, j2) = mono
        if same:
            return ("a", j1), ("a", j2)
        if s1 == s2:
            raise ValueError(f"stage {hint}: product of two {s1!r} symbols ({j1}, {j2})")
        return ((s1, j1), (s2, j2)) if s1 == "a" else ((s2, j2), (s1, j1))

    def shared(op: Operand) -> bool:
        """An ``"nd"`` operand reading one and the same row for every row."""
        return op.kind == "nd" and rows > 1 and len(set(op.row_of)) == 1

    def gather(op: Operand, syms: list[tuple[str, int]], one_row: bool = False) -> str:
        # columns are selected by a constant 0/1 matrix product: several times cheaper in
        # onnxruntime than Gather along axis 1 (and than GatherND) at these sizes
        if one_row:  # the row once, (1, m): it broadcasts over the other operand's rows
            src = gb.op("Gather", op.tensor, gb.i([int(op.row_of[0])]), axis=0)
            sel = np.zeros((op.n, len(syms)))
            sel[[j for _, j in syms], np.arange(len(syms))] = 1.0
            return gb.op("MatMul", src, gb.f(sel))
        if op.kind == "vec":
            idx = [[op.position(r, j) for _, j in syms] for r in range(rows)]
            return gb.op("Gather", op.tensor, gb.i(idx), axis=0)
        src = op.tensor
        if op.kind == "col":  # the column's symbols as one (1, m) row: src^T sel
            sel = np.zeros((op.n, len(syms)))
            sel[[j for _, j in syms], np.arange(len(syms))] = 1.0
            return gb.op("Gemm", src, gb.f(sel), transA=1)
        if op.kind == "nd" and list(op.row_of) != list(range(rows)):
            src = gb.op("Gather", src, gb.i(list(op.row_of)), axis=0)
        cols = [j for _, j in syms]
        if cols == list(range(op.n)):
            return src  # every column in order
        sel = np.zeros((op.n, len(cols)))
        sel[cols, np.arange(len(cols))] = 1.0
        return gb.op("MatMul", src, gb.f(sel))

    monos: list = []
    seen: dict = {}
    for polys in per_row:
        for p in polys:
            for m in p:
                if m == ():
                    continue
                if m not in seen:
                    seen[m] = len(monos)
                    monos.append(m)
    for r, polys in enumerate(per_row):
        for o, p in enumerate(polys):
            bias[r, o] += p.get((), 0.0)
    # shared coefficients when every row expands to the same polynomials
    coef = np.zeros((rows, len(monos), n_out))
    for r, polys in enumerate(per_row):
        for o, p in enumerate(polys):
            for m, c in p.items():
                if m != ():
                    coef[r, seen[m], o] = c
    uniform = bool(np.all(coef == coef[:1]))
    if uniform:
        terms = [(m, None) for m in monos]
        W = np.zeros((len(terms), n_cols))
        W[:, :n_out] = coef[0]
        row_coef = None
    else:
        terms = [(m, o) for m in monos for o in range(n_out) if np.any(coef[:, seen[m], o])]
        W = np.zeros((len(terms), n_cols))
        row_coef = np.zeros((rows, len(terms)))
        for t, (m, o) in enumerate(terms):
            W[t, o] = 1.0
            row_coef[:, t] = coef[:, seen[m], o]

    def product(x: str) -> str:
        """``x W + bias (+ beta add)``."""
        if transpose:  # (x W + bias)^T = W^T x^T + bias^T
            if add is None:
                return gb.op("Gemm", gb.f(W.T), x, gb.f(bias.T), transB=1)
            if not np.any(bias):
                return gb.op("Gemm", gb.f(W.T), x, add, transB=1, beta=beta)
            out = gb.op("Gemm", gb.f(W.T), x, gb.f(bias.T), transB=1)
            return gb.op("Add" if beta > 0 else "Sub", out, add)
        if add is None:
            if not np.any(bias):
                return gb.op("MatMul", x, gb.f(W))
            return gb.op("Gemm", x, gb.f(W), gb.f(bias))
        if not np.any(bias):
            return gb.op("Gemm", x, gb.f(W), add, beta=beta)
        return gb.op("Add" if beta > 0 else "Sub", gb.op("Gemm", x, gb.f(W), gb.f(bias)), add)

    if transpose and (not terms or all(len(m) == 1 for m, _ in terms)):
        raise ValueError(f"stage {hint}: a transposed result needs a bilinear stage")
    if parts is not None:
        if add is not None or transpose or not terms:
            raise ValueError(f"stage {hint}: parts need a stage without add or transpose")
        W_all, bias_all = W, bias

        def product(x: str) -> list[str]:  # noqa: F811 - one product per column range
            out = []
            for a0, b0 in parts:
                w, c = W_all[:, a0:b0], bias_all[:, a0:b0]
                out.append(
                    gb.op("Gemm", x, gb.f(w), gb.f(c)) if np.any(c)
                    else gb.op("MatMul", x, gb.f(w))
                )  # fmt: skip
            return out

    if not terms:
        const = gb.f(np.broadcast_to(bias, (rows, n_cols)).copy())
        return const if add is None else gb.op("Add" if beta > 0 else "Sub", const, add)
    linear = all(len(m) == 1 for m, _ in terms)
    if linear and (same or len({m[0][0] for m, _ in terms}) == 1):
        # a linear stage: gather the symbols, no products
        src = a if same or terms[0][0][0][0] == "a" else bb
        if src.kind == "col" and rows != 1:
            raise ValueError(f"stage {hint}: a shared column cannot be the only factor")
        g = gather(src, [m[0] for m, _ in terms])
        if row_coef is not None:
            g = gb.op("Mul", g, gb.f(row_coef))
        return product(g)
    fa = [factors(m) for m, _ in terms]

    # an operand reading one row for all (a sensor's pose beside its slots) is gathered once
    # and broadcast, when the other one has every row
    a_once = not same and shared(a) and not shared(bb)
    b_once = not same and shared(bb) and not shared(a)
    ga = gather(a, [x for x, _ in fa], a_once)
    gbb = gather(a if same else bb, [y for _, y in fa], b_once)
    prod = gb.op("Mul", ga, gbb)
    if row_coef is not None:
        prod = gb.op("Mul", prod, gb.f(row_coef))
    return product(prod)


# ------------------------------------------------------------------------------ batched programs


def emit_program(
    gb: GraphBuilder,
    program,
    inputs: dict[str, str],
    outputs: dict[str, str],
    n_name: str,
) -> None:
    """Emit a :class:`~torchcontact.kernels.Program` as one node per scalar operation.

    Every scalar is an ``(N,)`` vector, so each node processes all ``N`` frames (throughput; an
    ``(N, 1)`` column took onnxruntime's slow broadcasting path, ~100x slower against scalar
    constants); constants of the model are folded at trace time, as in the generated C++
    kernels. A :func:`torchcontact._scalar.loop` (the friction-cone iterations) becomes one ONNX
    ``Loop`` whose body is the code of one iteration; it leaves early once every frame has
    stopped (a stopped frame is a fixed point of the body, so the result is that of the whole
    budget).

    Args:
        gb: the graph (its dtype is the program's).
        program: the program.
        inputs: program input name -> a ``(N, k)`` value of the graph.
        outputs: program output name -> the name of the ``(N, k)`` value to produce.
        n_name: a ``(1,)`` int64 value holding ``N`` (for constant outputs).
    """
    tr, out = program.trace()
    vals: dict[int, str] = {}
    for name, syms in tr.inputs.items():
        if not syms:
            continue
        # Split + Squeeze: per-column Gathers get fused by onnxruntime into a Split whose
        # (N, 1) outputs take the slow broadcasting path
        cols = (
            [inputs[name]]
            if len(syms) == 1
            else gb.op("Split", inputs[name], axis=1, num_outputs=len(syms), n_out=len(syms))
        )
        for s, c in zip(syms, cols, strict=True):
            vals[s.index] = gb.op("Squeeze", c, gb.i([1]))
    needed = _live(tr, out)
    body_of = {}  # body node index -> its loop node
    for node in tr.nodes:
        if node.op == "loop":
            spec = node.args[0]
            body_of.update({k: node for k in range(spec.start, spec.end)})
    em = _Emitter(gb, vals, n_name)
    for node in tr.nodes:
        if node.op in ("in", "carry") or node.index not in needed or node.index in body_of:
            continue
        if node.op == "loop":
            em.loop(node, tr, needed)
        else:
            em.node(node)
    for name, xs in out.items():
        cols = [em.column(x) for x in xs]
        if not cols:
            zero_shape = gb.op("Concat", n_name, gb.i([0]), axis=0)
            gb.op("Expand", gb.f(np.zeros((1, 0))), zero_shape, out=outputs[name])
        else:
            flat = cols[0] if len(cols) == 1 else gb.op("Concat", *cols, axis=0)
            rows = gb.op("Reshape", flat, gb.i([len(cols), -1]))
            gb.op("Transpose", rows, perm=[1, 0], out=outputs[name])


_BINARY = {"add": "Add", "sub": "Sub", "mul": "Mul", "div": "Div", "gt": "Greater", "and": "And",
           "or": "Or"}  # fmt: skip
_UNARY = {"neg": "Neg", "sqrt": "Sqrt", "sin": "Sin", "cos": "Cos", "not": "Not"}


class _Emitter:
    """Emits trace nodes into a graph (or a loop body), one ONNX node each."""

    def __init__(self, gb: GraphBuilder, vals: dict[int, str], n_name: str) -> None:
        self.gb, self.vals, self.n = gb, vals, n_name

    def value(self, x) -> str:
        """The graph value of a symbol or constant (constants broadcast)."""
        if isinstance(x, Sym):
            return self.vals[x.index]
        if isinstance(x, bool):
            return self.gb.const(np.array(x), bool)
        return self.gb.f(float(x))

    def column(self, x) -> str:
        """``(N,)`` float values of a symbol, mask or constant."""
        gb = self.gb
        if isinstance(x, Sym):
            col = self.vals[x.index]
            return gb.cast(col) if x.mask else col
        return gb.op("Expand", gb.f([float(x)]), self.n)

    def node(self, node: Sym) -> None:
        """One scalar operation."""
        gb, a, v = self.gb, node.args, self.value
        if node.op in _BINARY:
            r = gb.op(_BINARY[node.op], v(a[0]), v(a[1]))
        elif node.op in _UNARY:
            r = gb.op(_UNARY[node.op], v(a[0]))
        elif node.op == "sel":
            r = gb.op("Where", v(a[0]), v(a[1]), v(a[2]))
        elif node.op == "finite":  # x - x is NaN exactly for NaN and inf
            r = gb.op("Not", gb.op("IsNaN", gb.op("Sub", v(a[0]), v(a[0]))))
        elif node.op == "loopout":
            r = self.vals[(a[0].index, a[1])]
        else:
            raise ValueError(f"no ONNX emission for {node.op!r}")
        self.vals[node.index] = r

    def loop(self, node: Sym, tr: Trace, needed: set[int]) -> None:
        """A ``Loop`` node: the body (one iteration) as its subgraph, early exit when all stop."""
        from onnx import TensorProto, helper

        gb, spec = self.gb, node.args[0]
        elem = onnx_type(gb.dtype)
        outer_nodes = gb.nodes
        gb.nodes = []
        try:
            it, cond_in = gb.fresh("iter"), gb.fresh("cond")
            carried = [gb.fresh("carry") for _ in spec.carries]
            for c, name in zip(spec.carries, carried, strict=True):
                self.vals[c.index] = name
            for k in range(spec.start, spec.end):
                body_node = tr.nodes[k]
                if body_node.op != "carry" and k in needed:
                    self.node(body_node)
            stop = spec.stop
            if isinstance(stop, Sym):  # go on while any frame has not stopped
                going = gb.cast(gb.op("Not", self.value(stop)))
                half = gb.const(0.5, gb.dtype, scalar=True)
                cond_out = gb.op("Greater", gb.op("ReduceMax", going, keepdims=0), half)
            else:
                cond_out = gb.const(np.array(not stop), bool, scalar=True)
            new = [gb.op("Identity", self.column(x)) for x in spec.new]
            body_nodes = gb.nodes
        finally:
            gb.nodes = outer_nodes
        body = helper.make_graph(
            body_nodes,
            gb.fresh("loop_body"),
            [helper.make_tensor_value_info(it, TensorProto.INT64, []),
             helper.make_tensor_value_info(cond_in, TensorProto.BOOL, []),
             *(helper.make_tensor_value_info(c, elem, ["N"]) for c in carried)],
            [helper.make_tensor_value_info(cond_out, TensorProto.BOOL, []),
             *(helper.make_tensor_value_info(x, elem, ["N"]) for x in new)],
        )  # fmt: skip
        init = [self.column(x) for x in spec.init]
        trips, go = gb.const(spec.n, np.int64, scalar=True), gb.const(True, bool, scalar=True)
        outs = gb.op("Loop", trips, go, *init,
                     n_out=len(init), body=body)  # fmt: skip
        outs = [outs] if isinstance(outs, str) else outs
        for i, o in enumerate(outs):
            self.vals[(node.index, i)] = o


def _live(tr: Trace, out: dict[str, list]) -> set[int]:
    """Indices of the trace nodes the outputs depend on (through loops too)."""
    from torchcontact._scalar import loop_deps

    stack = [x for xs in out.values() for x in xs if isinstance(x, Sym)]
    live: set[int] = set()
    while stack:
        s = stack.pop()
        if s.index in live:
            continue
        live.add(s.index)
        if s.op == "loopout":
            stack.append(s.args[0])
        else:
            stack.extend(loop_deps(s))
    return live


def inline(gb: GraphBuilder, model, prefix: str, inputs: dict[str, str]) -> dict[str, str]:
    """Copy another graph into ``gb`` (names prefixed); returns its outputs' values in ``gb``.

    Args:
        gb: the graph to extend (same opset as ``model``).
        model: the ``onnx.ModelProto`` to inline (no control-flow subgraphs).
        prefix: prepended to its value and initializer names.
        inputs: its input name -> a value of ``gb`` (of the input's dtype).

    Raises:
        ValueError: an input without a value, or a control-flow node.
    """
    from onnx import AttributeProto, NodeProto, TensorProto

    g = model.graph
    rename: dict[str, str] = {}
    for t in g.initializer:
        new = TensorProto()
        new.CopyFrom(t)
        new.name = prefix + t.name
        gb.initializers.append(new)
        rename[t.name] = new.name
    for i in g.input:
        if i.name in rename:
            continue
        if i.name not in inputs:
            raise ValueError(f"inlined graph input {i.name!r} has no value")
        rename[i.name] = inputs[i.name]
    for node in g.node:
        if any(a.type in (AttributeProto.GRAPH, AttributeProto.GRAPHS) for a in node.attribute):
            raise ValueError(f"cannot inline control flow ({node.op_type})")
        n = NodeProto()
        n.CopyFrom(node)
        del n.input[:]
        n.input.extend(rename.get(x, prefix + x) if x else "" for x in node.input)
        del n.output[:]
        n.output.extend(prefix + x if x else "" for x in node.output)
        n.name = prefix + (node.name or node.output[0])
        for x in node.output:
            if x:
                rename[x] = prefix + x
        gb.nodes.append(n)
    return {o.name: rename[o.name] for o in g.output}


def fold_linear_chains(gb: GraphBuilder, keep: Sequence[str] = (), max_growth: float = 2.0) -> int:
    """Merge chains of products with constant matrices (the model's constants folded once).

    A value used once, ``v = x C1 (+ c1)`` (``MatMul``/``Gemm`` with constant weights), feeding
    ``v C2 (+ c2)`` or ``v * c`` (``c`` one scale per column) becomes one node,
    ``x (C1 C2) (+ c1 C2 + c2)``; likewise ``Cl (Cl1 x)`` on the left. On one frame onnxruntime's
    cost is per node (:mod:`torchcontact.onnx.step`), so each merge saves one. The products are
    taken in float64 and stored in the graph's dtype. A right-hand merge whose matrix has more
    than ``max_growth`` times the entries of the two it replaces is not made: the product then
    costs more than the node (a stage's 138 terms times 54 selected columns measured 1.2 % of
    the step slower than the two products).

    Args:
        gb: the graph, changed in place (its main graph; values read inside subgraphs are kept).
        keep: values that must stay (graph outputs).
        max_growth: the largest ratio of multiply-adds per row, merged over unmerged.

    Returns:
        The number of nodes removed.
    """
    from onnx import AttributeProto, helper, numpy_helper

    const = {t.name: t for t in gb.initializers}
    arrays: dict[str, np.ndarray] = {}

    def value(name: str) -> np.ndarray | None:
        if name not in const:
            return None
        if name not in arrays:
            arrays[name] = numpy_helper.to_array(const[name]).astype(np.float64)
        return arrays[name]

    def sub_reads(graph, out: set) -> None:
        for n in graph.node:
            out.update(n.input)
            for a in n.attribute:
                if a.type == AttributeProto.GRAPH:
                    sub_reads(a.g, out)
                elif a.type == AttributeProto.GRAPHS:
                    for g in a.graphs:
                        sub_reads(g, out)

    pinned = set(keep) | {o.name for o in gb.outputs}
    for n in gb.nodes:
        for a in n.attribute:
            if a.type in (AttributeProto.GRAPH, AttributeProto.GRAPHS):
                for g in [a.g] if a.type == AttributeProto.GRAPH else list(a.graphs):
                    sub_reads(g, pinned)

    def attrs(n) -> dict:
        return {a.name: helper.get_attribute_value(a) for a in n.attribute}

    def right(n):
        """``(x, C, c)`` of ``x C + c`` (c None: no bias), or None."""
        if n.op_type == "MatMul" and len(n.input) == 2 and value(n.input[1]) is not None:
            C = value(n.input[1])
            return (n.input[0], C, None) if C.ndim == 2 and value(n.input[0]) is None else None
        if n.op_type != "Gemm" or value(n.input[0]) is not None or value(n.input[1]) is None:
            return None
        a = attrs(n)
        if a.get("transA", 0) or a.get("alpha", 1.0) != 1.0 or a.get("beta", 1.0) != 1.0:
            return None
        C = value(n.input[1])
        C = C.T if a.get("transB", 0) else C
        if len(n.input) < 3 or not n.input[2]:
            return n.input[0], C, None
        c = value(n.input[2])
        if c is None:
            return None
        return n.input[0], C, np.broadcast_to(c, (1, C.shape[1])) if c.ndim < 2 else c

    def left(n):
        """``(Cl, x)`` of a ``MatMul`` ``Cl x`` with a constant 2-D ``Cl``, or None."""
        if n.op_type != "MatMul" or value(n.input[0]) is None or value(n.input[1]) is not None:
            return None
        Cl = value(n.input[0])
        return (Cl, n.input[1]) if Cl.ndim == 2 else None

    gb_new: dict[str, np.ndarray] = {}

    def fresh(arr: np.ndarray) -> str:
        """A placeholder for a new constant (made in the replaced one's dtype)."""
        key = f"__fold{len(gb_new)}"
        gb_new[key] = np.asarray(arr, np.float64)
        return key

    removed = 0
    changed = True
    while changed:
        changed = False
        producer = {o: n for n in gb.nodes for o in n.output}
        uses: dict[str, int] = {}
        for n in gb.nodes:
            for i in n.input:
                uses[i] = uses.get(i, 0) + 1
        for n2 in list(gb.nodes):
            v = n2.input[0] if n2.op_type in ("MatMul", "Gemm", "Mul") else None
            if n2.op_type == "MatMul" and left(n2) is not None:
                v = n2.input[1]
            if v is None or v in pinned or uses.get(v) != 1 or v not in producer:
                continue
            n1 = producer[v]
            new = None
            if n2.op_type == "MatMul" and left(n2) is not None:
                l1 = left(n1)
                if l1 is not None:
                    Cl = left(n2)[0] @ l1[0]
                    new = helper.make_node("MatMul", [fresh(Cl), l1[1]], list(n2.output),
                                           name=n2.name)  # fmt: skip
            else:
                r1 = right(n1)
                if r1 is None:
                    continue
                x, C1, c1 = r1
                if n2.op_type == "Mul":
                    s = value(n2.input[1])
                    if s is None or s.ndim > 2 or (s.ndim == 2 and s.shape[0] != 1):
                        continue
                    s = np.broadcast_to(s.reshape(1, -1), (1, C1.shape[1]))
                    C, c = C1 * s, None if c1 is None else c1 * s
                else:
                    r2 = right(n2)
                    dyn_c = None
                    if r2 is None and n2.op_type == "Gemm":  # a dynamic C: x C1 C2 + Y
                        a = attrs(n2)
                        plain = a.get("alpha", 1.0) == 1.0 and a.get("beta", 1.0) == 1.0
                        if (not plain or a.get("transA", 0) or c1 is not None
                                or value(n2.input[1]) is None):  # fmt: skip
                            continue
                        C2 = value(n2.input[1])
                        r2 = (v, C2.T if a.get("transB", 0) else C2, None)
                        dyn_c = n2.input[2]
                    if r2 is None:
                        continue
                    _, C2, c2 = r2
                    (n1_, n2_), n3_ = C1.shape, C2.shape[1]
                    if n1_ * n3_ > max_growth * (n1_ * n2_ + n2_ * n3_):
                        continue  # the merged product would cost more than the node it saves
                    C = C1 @ C2
                    c = None if c1 is None else c1 @ C2
                    if c2 is not None:
                        c = c2 if c is None else c + c2
                    if dyn_c is not None:
                        new = helper.make_node("Gemm", [x, fresh(C), dyn_c], list(n2.output),
                                               name=n2.name)  # fmt: skip
                if new is None:
                    if c is None and n1.op_type == "MatMul" and n2.op_type in ("MatMul", "Mul"):
                        new = helper.make_node("MatMul", [x, fresh(C)], list(n2.output),
                                               name=n2.name)  # fmt: skip
                    else:
                        bias = np.zeros((1, C.shape[1])) if c is None else c
                        new = helper.make_node("Gemm", [x, fresh(C), fresh(bias)], list(n2.output),
                                               name=n2.name)  # fmt: skip
            if new is None:
                continue
            k = gb.nodes.index(n2)
            # the new constants in the dtype of the ones they replace (a float32 graph's
            # float64 solve keeps its float64)
            dt = numpy_helper.to_array(const[next(i for i in n1.input if i in const)]).dtype
            for j, name in enumerate(new.input):
                if name not in const and name in gb_new:
                    new.input[j] = gb.const(gb_new[name], dt)
                    const[new.input[j]] = next(t for t in gb.initializers
                                               if t.name == new.input[j])  # fmt: skip
            gb.nodes[k] = new
            gb.nodes.remove(n1)
            removed += 1
            changed = True
            break
    used = {i for n in gb.nodes for i in n.input} | pinned
    gb.initializers = [t for t in gb.initializers if t.name in used]
    gb._consts = {k: name for k, name in gb._consts.items() if name in used}
    return removed
