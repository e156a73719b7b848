"""The tape VM (torchcontact.kernels._vm) against eager torch, and its place in the cache.

The VM runs a program's bytecode instead of the program's own compiled kernel: the same
operations in the same order, fused multiply-adds where a product is read once (as the
kernels' ``-ffp-contract=fast``), so it agrees with eager torch to rounding. Programs are the
estimators the log pipeline runs (iCub, the bundled arm), the cone solver's MAP loop and small
programs for the edge cases (NaN and inf, partial blocks, float32). The VM's library is built
once into the user cache (as the kernels in test_kernels.py); the damaged-library test uses a
temporary cache.
"""

from __future__ import annotations

import io
import warnings

import pytest
import torch
from robots import load_model, random_state
from test_constrained import _tcarm_pushes
from test_kernels_loop import _inputs, _newton_sqrt

import torchcontact as tc
from torchcontact import _scalar as S
from torchcontact import dynamics, kernels
from torchcontact.constrained import FrictionCones
from torchcontact.estimation import estimator as est_mod
from torchcontact.kernels import _store, _vm

#: VM against eager torch (float64): the kernels' tolerance (test_kernels.py), FMA rounding.
VM_VS_EAGER = 1e-12
#: Outputs of the estimator's solve: rank-deficient frames amplify rounding (test_kernels.py).
SOLVE_VS_EAGER = 1e-9


def _programs_of(fn) -> list[tuple[kernels.Program, dict]]:
    """The programs (and their input tensors) an estimator call runs, run eagerly."""
    seen = []
    run = est_mod.run_program

    def spy(prog, tensors, backend, chunk_size):
        seen.append((prog, {k: v.clone() for k, v in tensors.items()}))
        return run(prog, tensors, "eager", chunk_size)

    est_mod.run_program = spy
    try:
        fn()
    finally:
        est_mod.run_program = run
    return seen


def _vm_matches_eager(prog, tensors, atol, exact=("status", "rank", "iterations")) -> None:
    """The VM's outputs equal eager torch's: NaN patterns, exactly the integer-valued outputs
    (statuses, ranks, iteration counts), the rest to ``atol`` (relative to 1 + |value|)."""
    dtype = next(iter(tensors.values())).dtype
    got = kernels.vm_kernel(prog, dtype, wait=True)(tensors)
    ref = kernels.run_eager(prog, tensors)
    assert set(got) == set(ref)
    for k in ref:
        assert torch.equal(got[k].isnan(), ref[k].isnan()), k
        if any(k.startswith(e) for e in exact):
            assert torch.equal(got[k].nan_to_num(-1), ref[k].nan_to_num(-1)), k
        d = ((got[k] - ref[k]).abs() / (1 + ref[k].abs())).nan_to_num(0.0)
        assert float(d.max()) <= atol if d.numel() else True, (k, float(d.max()))


def _icub_estimate(n: int):
    model = load_model("icub")
    est = tc.ContactEstimator(model)
    links = ["l_hand", "l_forearm", "l_forearm", "r_hand"]
    kinds = ["force", "force_dir", "known", "wrench"]
    q, qd, qdd = random_state(model, n, seed=21)
    g = torch.Generator().manual_seed(22)
    pos = torch.randn(n, 4, 3, generator=g, dtype=torch.float64) * 0.05
    dirs = torch.randn(n, 4, 3, generator=g, dtype=torch.float64)
    wr = torch.randn(n, 4, 6, generator=g, dtype=torch.float64)
    active = torch.rand(n, 4, generator=g) > 0.3
    ft = {s: torch.randn(n, 6, generator=g, dtype=torch.float64) * 20 for s in est.sensor_names}
    ft["l_arm_ft"][3, 2] = float("nan")  # a bad frame: status 1, NaN outputs
    ft["r_arm_ft"][70, 0] = float("inf")
    q[5, 0] = 1e6  # a large angle: sin/cos beyond the fast reduction's range
    dirs[9, 1] = 0.0  # a zero direction
    c = tc.Contacts(links, kinds, pos, dirs, wr, active)
    return lambda: est.estimate(q, qd, qdd, ft, c, backend="eager")


def test_vm_equals_eager_on_the_icub_estimator():
    """The whole-iCub estimator (the log pipeline's program): 130 frames, two full blocks and a
    partial one, with NaN, inf, a huge angle and a zero direction in them."""
    progs = _programs_of(_icub_estimate(130))
    assert [p.name for p, _ in progs] == ["estimator"]
    prog, tensors = progs[0]
    out = kernels.vm_kernel(prog, torch.float64, wait=True)(tensors)
    assert (out["status"][3] != 0) and (out["status"] == 0).sum() > 40
    _vm_matches_eager(prog, tensors, SOLVE_VS_EAGER)


def test_vm_equals_eager_on_the_tcarm_estimator_and_its_map_loop():
    """The bundled arm's estimator with friction cones: the MAP loop (a jump back over the body,
    leaving once every frame of the block has stopped) gives eager's statuses, iteration counts
    and forces; a warm start far from the answer runs out of budget and restarts. In float32
    the same frames are finite."""
    est, state, c, kw, _, _ = _tcarm_pushes(24, seed=12, weighted=True)
    cold = est.estimate(*state, c, constraints=FrictionCones(), backend="eager", **kw)
    far = (-cold.force, torch.zeros_like(cold.moment))
    progs = _programs_of(lambda: est.estimate(*state, c, constraints=FrictionCones(),
                                              warm_start=far, backend="eager", **kw))  # fmt: skip
    assert any(tr_has_loop(p) for p, _ in progs)
    for prog, tensors in progs:
        _vm_matches_eager(prog, tensors, 1e-9)
        t32 = {k: v.float() for k, v in tensors.items()}
        out = kernels.vm_kernel(prog, torch.float32, wait=True)(t32)
        ref = kernels.run_eager(prog, t32)
        for k in ref:
            assert torch.equal(out[k].isfinite(), ref[k].isfinite()), k


def tr_has_loop(prog: kernels.Program) -> bool:
    tr, _ = prog.trace()
    return any(n.op == "loop" for n in tr.nodes)


@pytest.mark.parametrize("budget", [0, 1, 8, 40])
def test_vm_loop_exits_per_block_with_eager_counts(budget):
    """Newton's sqrt with a carried count (test_kernels_loop.py): exact counts, the root to
    rounding, a zero-trip loop keeping its initial values."""
    prog = _newton_sqrt(budget)
    _vm_matches_eager(prog, _inputs(200), VM_VS_EAGER, exact=("count",))


def _edge_program() -> kernels.Program:
    def fn(d):
        x, y = d["x"]
        return {
            "o": [
                S.add(S.mul(x, y), S.sin(x)),  # a fused multiply-add, sin and cos of one angle
                S.sub(S.mul(x, 3.0), S.cos(x)),
                S.div(x, y),  # 0/0, x/0, inf/inf
                S.sqrt(y),  # negative: NaN
                S.select(S.gt(x, y), 1.0, 0.0),  # NaN compares false
                S.select(S.isfinite(S.div(x, y)), x, -2.0),
                S.select(S.logical_or(S.gt(x, 0.5), S.logical_not(S.isfinite(y))), y, 7.0),
                S.neg(x),
                2.5,  # a constant output
                y,  # an input as an output
            ]
        }

    return kernels.Program("vm_edges", fn, {"x": 2}, {"o": 10}, "vm_edges|1")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("n", [1, 63, 64, 65, 5000])
def test_vm_nan_inf_partial_blocks_and_threads(dtype, n):
    """NaN and inf propagate as in eager torch (no -ffast-math); a last block of 1 to B-1
    frames; 5000 frames split over threads; float32 and float64."""
    g = torch.Generator().manual_seed(n)
    x = torch.randn(n, 2, generator=g, dtype=torch.float64).to(dtype)
    special = [float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e30]
    for i, v in enumerate(special):
        x[(7 * i) % n, i % 2] = v
    x[n // 2, 0] = 1e7  # beyond vsincos's reduction range: libm's sin/cos
    tol = VM_VS_EAGER if dtype == torch.float64 else 1e-5
    with torch.inference_mode():
        threads = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            _vm_matches_eager(_edge_program(), {"x": x}, tol)
        finally:
            torch.set_num_threads(threads)


def test_vm_float32_rnea_relative_to_float64():
    model = load_model("panda")
    prog = dynamics.program(model, "id", False, False)
    q, qd, qdd = random_state(model, 70, seed=3)
    x64 = {"q": q, "qd": qd, "qdd": qdd}
    ref = kernels.run_eager(prog, x64)["tau"]
    vm = kernels.vm_kernel(prog, torch.float32, wait=True)
    got = vm({k: v.float() for k, v in x64.items()})["tau"]
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), ref, atol=2e-4 * float(ref.abs().max()), rtol=0)


def _pendulum(length: float) -> tc.RobotModel:
    return tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=length)))


def test_a_damaged_vm_library_is_rebuilt_and_its_bytecode_is_cached(tmp_path, monkeypatch):
    """A damaged VM library warns, is removed and rebuilt; a program's bytecode is saved with
    its key, so another process (here: emptied memory) runs it without tracing it; a damaged
    bytecode file is a miss (traced again)."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    for name in ("_vm_fns", "_vm_builds", "_vm_failed", "_vm_calls", "_vm_code"):
        monkeypatch.setattr(kernels, name, {})
    monkeypatch.setattr(kernels, "_healed", set())
    entry, src = kernels._vm_entry(torch.float64)
    _vm.write_source(entry, src)
    _vm.build(entry)
    good = entry.library.read_bytes()
    tmp = entry.library.with_name("damaged")
    tmp.write_bytes(good[: len(good) // 2])  # a half-written library, through a rename
    tmp.replace(entry.library)
    prog = dynamics.program(_pendulum(0.83), "id", False, False)
    q = torch.linspace(-3, 3, 100, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vm = kernels.vm_kernel(prog, torch.float64, wait=True)
    assert [w for w in caught if "damaged" in str(w.message)]
    assert entry.check() == ("ok", "") and entry.library.read_bytes() != good[: len(good) // 2]
    ref = kernels.run_eager(prog, x)["tau"]
    torch.testing.assert_close(vm(x)["tau"], ref, atol=VM_VS_EAGER, rtol=0)
    # the bytecode is in the cache: a process that has not traced the program runs it
    saved = kernels._bytecode_path(kernels._key_hash(prog, torch.float64))
    assert _vm.Bytecode.load(saved) is not None
    fresh = dynamics.program(_pendulum(0.83), "id", False, False)
    fresh._traced.clear()
    monkeypatch.setattr(kernels, "_vm_calls", {})
    monkeypatch.setattr(kernels, "_vm_code", {})
    monkeypatch.setattr(type(fresh), "trace", lambda self: pytest.fail("traced again"))
    torch.testing.assert_close(kernels.vm_kernel(fresh, torch.float64)(x)["tau"], ref,
                               atol=VM_VS_EAGER, rtol=0)  # fmt: skip
    monkeypatch.undo()
    # a damaged bytecode file is a miss
    data = bytearray(saved.read_bytes())
    data[-3] ^= 0xFF
    saved.write_bytes(bytes(data))
    assert _vm.Bytecode.load(saved) is None


def test_auto_and_cached_run_the_vm_while_the_kernel_is_not_built(tmp_path, monkeypatch):
    """With the VM built and a program's kernel not: ``cached`` runs the VM and starts no
    build (the kernel's is left for the process's exit); ``auto`` runs the VM, then switches to
    the kernel once built."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    kernels.vm_kernel(dynamics.program(_pendulum(0.84), "id", False, False), torch.float64,
                      wait=True)  # fmt: skip
    prog = dynamics.program(_pendulum(0.85), "id", False, False)
    q = torch.linspace(-3, 3, kernels.AUTO_BUILD_MIN_FRAMES, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    ref = kernels.run_eager(prog, x)["tau"]
    ckey = f"{prog.key}|{torch.float64}|cpu"
    out = kernels.run(prog, x, "cached")["tau"]
    assert ckey in kernels._vm_calls and ckey not in kernels._building
    assert ckey in kernels._deferred  # built once the process exits, not during the run
    torch.testing.assert_close(out, ref, atol=VM_VS_EAGER, rtol=0)
    out = kernels.run(prog, x, "auto")["tau"]
    torch.testing.assert_close(out, ref, atol=VM_VS_EAGER, rtol=0)
    assert kernels.background_builds() or kernels._ready(prog, q)
    kernels.wait_for_builds(timeout=300)
    kernels.run(prog, x, "auto")
    assert kernels._ready(prog, q)  # the compiled kernel, once built
    assert all(e["state"] == "ok" for e in _store.entries(tmp_path / "kernels"))


def test_cached_builds_the_vm_once_and_no_kernel_during_the_run(tmp_path, monkeypatch):
    """On a machine without the VM, ``cached`` (a log's noise estimate) builds the VM alone,
    waits for it and runs on it: no kernel build starts (the program's is left for the
    process's exit)."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    for name in ("_vm_fns", "_vm_builds", "_vm_failed", "_vm_calls", "_vm_code"):
        monkeypatch.setattr(kernels, name, {})
    prog = dynamics.program(_pendulum(0.86), "id", False, False)
    q = torch.linspace(-3, 3, kernels.AUTO_BUILD_MIN_FRAMES, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    out = kernels.run(prog, x, "cached")["tau"]
    torch.testing.assert_close(out, kernels.run_eager(prog, x)["tau"], atol=VM_VS_EAGER, rtol=0)
    ckey = f"{prog.key}|{torch.float64}|cpu"
    assert ckey in kernels._vm_calls  # it ran on the VM
    assert ckey not in kernels._building and ckey in kernels._deferred
    kernels._deferred.pop(ckey)  # (the exit's build is test_auto_and_cached_run_the_vm_...'s)
    kernels.wait_for_builds(timeout=120)
    assert not kernels.background_builds() and not kernels._ready(prog, q)
    states = {e["name"].split("_")[1]: e["state"] for e in _store.entries(tmp_path / "kernels")}
    assert states["vm-double"] == "ok" and states.get("rnea", "source only") == "source only"


#: The superinstructions the encoder fuses (``_vm._fuse``) and an output of each.
FUSED = ("mma", "mms", "fnm", "dot3", "dot3s", "add3")


def _fused_program() -> kernels.Program:
    def fn(d):
        x = d["x"]
        m = S.mul
        return {  # every product of two values once (a product read twice is not fused)
            "o": [
                S.add(m(x[0], x[1]), m(x[2], x[3])),  # mma
                S.sub(m(x[4], x[5]), m(x[6], x[7])),  # mms
                S.add(m(x[8], 2.5), m(-1.5, x[9])),  # mma, constants second
                S.sub(x[10], m(x[11], x[0])),  # fnm
                S.add(m(x[1], x[2]), S.add(m(x[3], x[4]), m(x[5], x[6]))),  # dot3
                S.add(m(0.3, x[7]), S.add(m(x[8], 0.7), m(x[9], -0.2))),  # dot3, constants
                S.add(x[10], S.sub(m(x[1], x[3]), m(x[2], x[4]))),  # dot3s, x10 * 1
                S.add(x[11], S.sub(m(x[0], 2.0), m(x[1], 3.0))),  # dot3s, constants
                S.sub(S.add(m(x[5], x[7]), m(x[6], x[8])), x[9]),  # dot3, x9 * -1
                S.add(S.add(x[0], x[1]), x[2]),  # add3 (exact)
                S.add(x[3], S.add(x[4], x[5])),  # add3 (exact)
                S.add(x[6], S.neg(x[7])),  # a difference (exact)
                S.add(m(x[8], x[9]), S.neg(x[10])),  # fms
                S.mul(S.add(m(x[10], x[11]), m(x[0], x[2])), x[3]),  # a fused value, read
            ]
        }

    return kernels.Program("vm_fused", fn, {"x": 12}, {"o": 14}, "vm_fused|1")


#: outputs of ``_fused_program`` computed with the same roundings as eager torch
EXACT_FUSED = (9, 10, 11)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_vm_superinstructions_equal_the_plain_sequence(dtype):
    """Each superinstruction (two and three products, c - a*b, (a+b)+c, x+(-y)) is in the
    bytecode and gives eager torch's values (its plain sequence of operations) to rounding,
    exactly where no product is fused; NaN and inf propagate; 70 frames (a partial block)."""
    prog = _fused_program()
    tr, out = prog.trace()
    bc = _vm.encode(tr, out)
    ops = {_vm.OPS[op >> 4] for op in bc.code[:, 0]}
    assert set(FUSED) <= ops, set(FUSED) - ops
    assert "neg" not in ops  # every negation folded
    g = torch.Generator().manual_seed(5)
    x = torch.randn(70, 12, generator=g, dtype=torch.float64)
    x[3, 0], x[8, 2], x[69, 4] = float("nan"), float("inf"), -float("inf")
    x[12, 0], x[12, 2] = float("inf"), float("inf")  # inf - inf: NaN
    x = x.to(dtype)
    got = kernels.vm_kernel(prog, dtype, wait=True)({"x": x})["o"]
    ref = kernels.run_eager(prog, {"x": x})["o"]
    assert torch.equal(got.isnan(), ref.isnan())
    tol = VM_VS_EAGER if dtype == torch.float64 else 1e-6
    d = ((got - ref).abs() / (1 + ref.abs())).nan_to_num(0.0)
    assert float(d.max()) <= tol, d.amax(0)
    for k in EXACT_FUSED:
        assert torch.equal(got[:, k].nan_to_num(7.0), ref[:, k].nan_to_num(7.0)), k


def test_no_fusion_across_a_write_of_an_operand():
    """A product is not moved past a write to its operand (a loop's carried slot): the loop
    body's ``a * b`` read after the carried ``a`` is rewritten stays a separate ``mul``."""
    code = [
        ["mul", 2, 0, 1, 0],  # t = a * b
        ["mov", 0, 1, 0, 0],  # a = b (a carried slot written again)
        ["mov", 0, 3, 0, 0],
        ["add", 4, 2, 3, 0],  # t + c: fusing would read the new a
        ["store", 0, 0, 0, 4],
    ]
    out, _ = _vm._fuse([list(i) for i in code], lambda v: ("k", 0))
    assert [i[0] for i in out] == ["mul", "mov", "mov", "add", "store"]
    code[1], code[2] = ["mov", 5, 1, 0, 0], ["mov", 6, 3, 0, 0]  # no write to a: fused
    out, _ = _vm._fuse([list(i) for i in code], lambda v: ("k", 0))
    assert [i[0] for i in out] == ["mov", "mov", "fma", "store"]


def test_prepare_vm_starts_the_build_once_and_loads_it(tmp_path, monkeypatch):
    """A log job calls prepare_vm before it scans the log: on an empty cache it starts the
    VM's detached build and returns at once; once built, it loads it; off with
    ``$TORCHCONTACT_VM=0``."""
    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    for name in ("_vm_fns", "_vm_builds", "_vm_failed", "_vm_calls", "_vm_code"):
        monkeypatch.setattr(kernels, name, {})
    monkeypatch.setenv("TORCHCONTACT_VM", "0")
    assert kernels.prepare_vm(torch.float64) is False
    assert not (tmp_path / "kernels").exists()
    monkeypatch.setenv("TORCHCONTACT_VM", "1")
    assert kernels.prepare_vm(torch.float64) is False
    assert kernels._vm_state(torch.float64) == "building"
    kernels._wait_for_vm(torch.float64, 60)
    assert kernels.prepare_vm(torch.float64) is True
    assert kernels._vm_state(torch.float64) == "ready"


def test_the_kernel_builds_during_the_run_by_default_only_on_many_cores(monkeypatch):
    """Unset ``$TORCHCONTACT_VM``: ``behind`` (the kernel built during the run, on the cores the
    run leaves idle) from ``BEHIND_MIN_CPUS`` CPUs of this process's affinity, else ``1`` (after
    the run); a value given always wins."""
    import os

    monkeypatch.delenv("TORCHCONTACT_VM", raising=False)
    for cpus, mode in ((2, "1"), (kernels.BEHIND_MIN_CPUS - 1, "1"),
                       (kernels.BEHIND_MIN_CPUS, "behind"), (64, "behind")):  # fmt: skip
        monkeypatch.setattr(os, "sched_getaffinity", lambda _pid, n=cpus: set(range(n)))
        assert kernels._vm_mode() == mode
        assert kernels._build_behind_vm() is (mode == "behind") and kernels.vm_enabled()
    for given in ("1", "only", "0", "Behind "):
        monkeypatch.setenv("TORCHCONTACT_VM", given)
        assert kernels._vm_mode() == given.strip().lower()


def test_a_vm_build_started_before_torch_is_adopted_not_repeated(tmp_path, monkeypatch):
    """``torchcontact._lightkernels.start_vm_build`` (a command, before it imports torch) starts
    the VM's detached build on an empty cache, once; the kernels package then waits for that
    builder (``building``) and loads its library, starting no compiler of its own; nothing is
    started when the VM is built or with ``$TORCHCONTACT_VM=0``."""
    from torchcontact import _lightkernels as lk

    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    monkeypatch.setenv("TORCHCONTACT_VM", "1")
    for name in ("_vm_fns", "_vm_builds", "_vm_failed", "_vm_calls", "_vm_code"):
        monkeypatch.setattr(kernels, name, {})
    monkeypatch.setattr(lk, "_builds", {})
    assert lk.start_vm_build("double") is True
    assert lk.start_vm_build("double") is False  # its builder runs
    ((name, proc),) = lk._builds.items()
    assert name == kernels._vm_entry(torch.float64)[0].name  # one VM entry, either way
    spawned = []
    monkeypatch.setattr(kernels._store, "spawn_build", lambda *a, **k: spawned.append(a))
    if kernels.prepare_vm(torch.float64) is False:  # still compiling: adopted
        assert kernels._vm_state(torch.float64) == "building"
        assert kernels._vm_builds[torch.float64].proc is proc
        kernels._wait_for_vm(torch.float64, 120)
    assert kernels.prepare_vm(torch.float64) is True and spawned == []
    assert lk.start_vm_build("double") is False  # built
    monkeypatch.setenv("TORCHCONTACT_VM", "0")
    monkeypatch.setattr(lk, "_builds", {})
    assert lk.start_vm_build("float") is False and lk._builds == {}


def test_without_a_compiler_the_vm_warns_once_and_auto_runs_eagerly(tmp_path, monkeypatch):
    """No C++ compiler: the VM's build fails, with one warning naming it; ``auto`` runs
    eagerly (the eager result), and a second call warns no more."""
    import warnings

    monkeypatch.setenv("TORCHCONTACT_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("TORCHCONTACT_VM", "1")
    for name in ("_vm_fns", "_vm_builds", "_vm_failed", "_vm_calls", "_vm_code"):
        monkeypatch.setattr(kernels, name, {})
    prog = dynamics.program(_pendulum(0.91), "id", False, False)
    q = torch.linspace(-3, 3, kernels.AUTO_BUILD_MIN_FRAMES, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    want = kernels.run_eager(prog, x)["tau"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = kernels.run(prog, x, "auto")["tau"]
        kernels.wait_for_builds(timeout=60)  # the kernel's own detached build fails too
        second = kernels.run(prog, x, "auto")["tau"]
    torch.testing.assert_close(first, want, atol=0, rtol=0)
    torch.testing.assert_close(second, want, atol=0, rtol=0)
    vm = [str(w.message) for w in caught if "tape VM" in str(w.message)]
    assert len(vm) == 1 and "not available" in vm[0] and "no-such-compiler" in vm[0]
