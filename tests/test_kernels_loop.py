"""Loops in scalar programs (torchcontact._scalar.loop): eager, generated C++ and CUDA source.

The program below is Newton's iteration for ``sqrt(a)`` with a carried iteration count: frames
converge after different numbers of iterations, so a block of the CPU kernel leaves the loop when
its slowest lane has stopped while eager torch runs until every frame has. Both must give the
unrolled program's answer to rounding (FMA contraction), iteration counts exactly.
"""

from __future__ import annotations

import os
import subprocess

import pytest
import torch

from torchcontact import kernels
from torchcontact._scalar import (
    Trace,
    add,
    div,
    gt,
    logical_not,
    logical_or,
    loop,
    mul,
    select,
    sub,
    unrolled_loops,
)

KERNEL_VS_EAGER = 1e-12


def _newton_sqrt(budget: int) -> kernels.Program:
    def fn(x: dict[str, list]) -> dict[str, list]:
        a = x["a"][0]

        def body(state):
            r, count, stopped = state
            done = gt(stopped, 0.5)
            r_new = mul(0.5, add(r, div(a, r)))
            err = sub(mul(r_new, r_new), a)
            scale = mul(a, 1e-15)  # a loop invariant: computed once, before the loop
            conv = logical_not(gt(mul(err, err), mul(scale, scale)))
            stop = logical_or(done, conv)
            r = select(done, r, r_new)
            count = select(done, count, add(count, 1.0))
            return [r, count, select(stop, 1.0, 0.0)], stop

        r, count, _ = loop(budget, body, [add(a, 1.0), 0.0, 0.0])
        return {"root": [r], "count": [count]}

    return kernels.Program("loop_test", fn, {"a": 1}, {"root": 1, "count": 1},
                           f"loop_test|{budget}")  # fmt: skip


def _inputs(n: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    # values over 12 decades: Newton from a + 1 needs 6 to 20 iterations
    return {"a": torch.pow(10.0, 12 * torch.rand(n, 1, generator=g, dtype=torch.float64) - 4)}


@pytest.mark.parametrize("budget", [8, 40])
def test_loop_kernel_equals_eager_and_unrolled(budget):
    prog = _newton_sqrt(budget)
    x = _inputs(37)  # 37 frames: a partial vector block too
    eager = kernels.run_eager(prog, x)
    cpu = kernels.run(prog, x, "cpu")
    torch.testing.assert_close(cpu["root"], eager["root"], atol=0, rtol=KERNEL_VS_EAGER)
    assert torch.equal(cpu["count"], eager["count"])
    with unrolled_loops():
        tr = Trace()
        syms = {"a": tr.input("a", 1)}
        prog.fn(syms)
        assert "loop" not in {s.op for s in tr.nodes}  # every iteration recorded
        assert len(tr.nodes) > budget
        unrolled = kernels.run_eager(prog, x)
    torch.testing.assert_close(unrolled["root"], eager["root"], atol=0, rtol=0)
    counts = eager["count"][:, 0]
    if budget == 40:  # every frame converged, after different numbers of iterations
        torch.testing.assert_close(eager["root"][:, 0] ** 2, x["a"][:, 0], atol=0, rtol=1e-14)
        assert counts.min() < 10 < counts.max() < budget
    else:  # the budget stops the slow frames
        assert counts.max() == budget and counts.min() < budget


def test_loop_is_one_iteration_of_code_with_invariants_hoisted():
    from torchcontact.kernels import _cpp

    small, large = (_cpp.emit(*_newton_sqrt(b).trace(), "double") for b in (100, 300))
    assert len(small) == len(large)  # the budget is a loop bound, not unrolled code
    body = large[large.index("for (int it") :]
    assert body.count("for (int it") == 1 and "all_lanes(" in body
    tr, _ = _newton_sqrt(3).trace()
    (lp,) = [s for s in tr.nodes if s.op == "loop"]
    scale = [s for s in tr.nodes if s.op == "mul" and 1e-15 in s.args]
    assert lp.args[0].start <= scale[0].index < lp.args[0].end  # recorded inside the body
    assert body.find(f"t{scale[0].index} =") == -1  # but emitted before the loop


def test_loop_misuse_is_refused():
    tr = Trace()
    (a,) = tr.input("a", 1)

    def inner(s):
        return [add(s[0], 1.0)], False

    def outer(s):
        return loop(2, inner, s), False

    with pytest.raises(ValueError, match="do not nest"):
        loop(2, outer, [a])
    with pytest.raises(ValueError, match="masks"):
        loop(2, inner, [gt(a, 0.0)])
    with pytest.raises(ValueError, match="returned 2 values"):
        loop(2, lambda s: ([s[0], s[0]], False), [a])


@pytest.mark.skipif(
    not torch.cuda.is_available() and not os.path.exists("/usr/local/cuda/bin/nvcc"),
    reason="needs nvcc",
)
def test_loop_cuda_source_compiles_and_runs(tmp_path):
    from torchcontact.kernels import _cuda

    prog = _newton_sqrt(40)
    cu = tmp_path / "k.cu"
    cu.write_text(_cuda.source(prog, torch.float64))
    nvcc = "nvcc" if torch.cuda.is_available() else "/usr/local/cuda/bin/nvcc"
    r = subprocess.run([nvcc, "-c", "-arch=sm_80", str(cu), "-o", str(tmp_path / "k.o")],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    if torch.cuda.is_available():
        x = _inputs(1000)
        gpu = kernels.run(prog, {"a": x["a"].cuda()}, "cuda")
        eager = kernels.run_eager(prog, x)
        torch.testing.assert_close(gpu["root"].cpu(), eager["root"], atol=0, rtol=1e-13)
        assert torch.equal(gpu["count"].cpu(), eager["count"])
