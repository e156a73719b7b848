"""A generated CPU kernel cut into part functions, compiled as one or several translation units.

Large programs are emitted as several ``noinline`` functions (``_cpp.PART_NODES`` nodes each),
and the cache's builder compiles them as one unit per compile slot it can hold. Here a small
program is cut into one node per part, so that every kind of value crosses a part's boundary:
inputs, floats, masks, a sine whose cosine is in another part, a loop's carried values, outputs.
"""

from __future__ import annotations

import ctypes

import torch

from torchcontact import kernels
from torchcontact._scalar import (
    add,
    cos,
    div,
    gt,
    logical_not,
    logical_or,
    loop,
    mul,
    select,
    sin,
    sub,
)
from torchcontact.kernels import _cpp, _store
from torchcontact.kernels.runner import run_program


def _program() -> kernels.Program:
    def fn(x: dict[str, list]) -> dict[str, list]:
        a, b = x["ab"]
        m = gt(a, b)
        s, c = sin(a), cos(a)
        a2 = add(mul(a, a), 1.0)

        def body(state):  # Newton's iteration for sqrt(a2), a stopped frame left unchanged
            r, n, done = state
            d = gt(done, 0.5)
            r_new = mul(0.5, add(r, div(a2, r)))
            stop = logical_or(d, logical_not(gt(sub(r, r_new), mul(r, 1e-9))))
            new = [select(d, r, r_new), select(d, n, add(n, 1.0)), select(stop, 1.0, 0.0)]
            return new, stop

        r, n, _ = loop(60, body, [a2, 0.0, 0.0])
        return {"y": [select(m, s, c), mul(s, sub(c, b)), r, n]}

    return kernels.Program("parts_test", fn, {"ab": 2}, {"y": 4}, "parts_test")


def test_parts_built_as_several_units_equal_one_function_and_eager(tmp_path):
    prog = _program()
    tr, out = prog.trace()
    g = torch.Generator().manual_seed(0)
    x = {"ab": torch.randn(1001, 2, generator=g, dtype=torch.float64) * 3}
    x["ab"][:5, 0] = torch.tensor([1e7, -1e7, float("nan"), float("inf"), 0.0])
    eager = run_program(prog, x, "eager", 1001)["y"]
    got = {}
    for part_nodes, jobs in ((0, 1), (1, 1), (1, 3)):
        src = _cpp.emit(tr, out, "double", vbytes=kernels._vector_bytes(), part_nodes=part_nodes)
        entry = _store.Entry(tmp_path / f"c{part_nodes}{jobs}" / "kernels", "tck_parts_test")
        entry.dir.mkdir(parents=True)
        _store.write_atomic(entry.source, src)
        assert _store.source_parts(entry.source) == (
            1 if part_nodes == 0 else src.count("#if TC_HAS(")
        )
        _store.build(entry, jobs=jobs)
        assert entry.record()["units"] == jobs
        assert not list(entry.dir.glob("*.o"))  # the units' objects are removed
        fn = kernels._wrap(ctypes.CDLL(str(entry.library)).tc_kernel, prog, torch.float64)
        got[part_nodes, jobs] = y = fn(x)["y"]
        torch.testing.assert_close(y, eager, rtol=1e-12, atol=1e-12, equal_nan=True)
        assert torch.equal(y[:, 3], eager[:, 3])  # iteration counts exactly
    assert _store.source_parts(entry.source) >= 6
    # one unit or three: the same functions, the same machine code
    assert torch.equal(got[1, 1].nan_to_num(7.0), got[1, 3].nan_to_num(7.0))
