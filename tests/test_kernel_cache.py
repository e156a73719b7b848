"""The kernel cache under faults: damaged libraries, a second process during a build, the bound
on compilers across processes, ``torchcontact cache info|clear`` (issues 18 and 19).

Every test uses its own temporary cache and the smallest kernel there is (the inverse dynamics
of a one-joint pendulum, ~1 s to compile), each test's pendulum with its own length so that no
two tests share a kernel. A shell wrapper around the real compiler (``$CXX``) slows builds down,
writes a half library where the compiler's output goes, and logs when each compiler runs.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import torchcontact as tc
from torchcontact import dynamics, kernels
from torchcontact.cli import main
from torchcontact.kernels import _store

ROOT = Path(__file__).resolve().parents[1]
N = kernels.AUTO_BUILD_MIN_FRAMES  # frames that start a background build under "auto"

#: A compiler that logs its start and end (``$CC_LOG``), first writes 4000 bytes where its
#: output goes (a half-written library, as a linker leaves it while it runs), touches
#: ``$CC_MARK`` and waits ``$CC_SLEEP`` seconds, then compiles for real.
WRAPPER = """#!/bin/sh
out=""; prev=""
for a in "$@"; do [ "$prev" = "-o" ] && out="$a"; prev="$a"; done
echo "start $(date +%s.%N) $$" >> "$CC_LOG"
[ -n "$out" ] && head -c 4000 /dev/zero > "$out"
[ -n "$CC_MARK" ] && touch "$CC_MARK"
sleep "${CC_SLEEP:-0}"
c++ "$@"; rc=$?
echo "end $(date +%s.%N) $$" >> "$CC_LOG"
exit $rc
"""


def _pendulum(length: float) -> tc.RobotModel:
    return tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=length)))


def _snippet(lengths: list[float], body: str) -> str:
    """Python run in a fresh process: pendulums ``models``, ``q`` of N frames, then ``body``."""
    return (
        "import io, json, sys, warnings, torch, torchcontact as tc\n"
        "from torchcontact import dynamics, kernels\n"
        "warnings.simplefilter('always')\n"
        f"models = [tc.RobotModel.from_urdf(io.StringIO(tc.robots.pendulum_urdf(length=x)))"
        f" for x in {lengths!r}]\n"
        f"q = torch.linspace(-3, 3, {N}, dtype=torch.float64)[:, None]\n" + body
    )


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A temporary kernel cache (``$TORCHCONTACT_CACHE``) and a wrapped compiler."""
    wrapper = tmp_path / "cxx.sh"
    wrapper.write_text(WRAPPER)
    wrapper.chmod(0o755)
    # the tape VM off: these tests count the kernels' compilers (test_kernels_vm.py has the VM's)
    env = {"TORCHCONTACT_CACHE": str(tmp_path / "cache"), "CXX": str(wrapper),
           "CC_LOG": str(tmp_path / "cc.log"), "TORCHCONTACT_BUILD_JOBS": "1",
           "TORCHCONTACT_VM": "0"}  # fmt: skip
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    # the builds earlier tests left for this process's exit (programs the tape VM ran) are not
    # this test's: they would start under its compiler wrapper at wait_for_builds
    deferred = dict(kernels._deferred)
    kernels._deferred.clear()
    yield tmp_path
    kernels._deferred.update(deferred)


def _damage(library: Path, data: bytes) -> None:
    """Replace a library's content with ``data`` through a new file (a rename): a library this
    process has loaded keeps its pages (truncating the mapped file itself would make this
    process die of SIGBUS, as any program whose library is cut under it)."""
    tmp = library.with_name(library.name + ".damaged")
    tmp.write_bytes(data)
    os.replace(tmp, library)


def _entry(model: tc.RobotModel) -> _store.Entry:
    prog = dynamics.program(model, "id", False, False)
    return kernels._cpu_entry(prog, torch.float64)[0]


def _compilers_at_once(log: Path) -> int:
    """Most compilers running at once, from the wrapper's start/end lines."""
    events = sorted(
        (float(t), 1 if kind == "start" else -1)
        for kind, t, _ in (line.split() for line in log.read_text().splitlines())
    )
    running = most = 0
    for _, step in events:
        running += step
        most = max(most, running)
    return most


def test_a_damaged_library_warns_runs_eagerly_and_is_rebuilt(cache):
    """Truncated, empty, garbage and unloadable libraries: a warning, the eager result, then a
    rebuilt entry whose kernel a fresh process loads (before: Bus error or ``file too short``
    on every later run)."""
    lengths = [0.41, 0.42, 0.43, 0.44]
    damage = ["truncated", "empty", "garbage", "unloadable"]
    models = [_pendulum(x) for x in lengths]
    q = torch.linspace(-3, 3, N, dtype=torch.float64)[:, None]
    for m in models:  # build every kernel (here, waiting), then damage them
        m.inverse_dynamics(q[:8], q[:8], q[:8], backend="cpu")
    for m, how in zip(models, damage, strict=True):
        e = _entry(m)
        assert e.check() == ("ok", "")
        data = e.library.read_bytes()
        if how == "truncated":
            _damage(e.library, data[:4000])
        elif how == "empty":
            _damage(e.library, b"")
        else:  # random bytes of the same size; "unloadable": its record made to match them
            _damage(e.library, os.urandom(len(data)))
            if how == "unloadable":
                size, digest = _store.file_digest(e.library)
                rec = {**e.record(), "size": size, "sha256": digest}
                e.record_path.write_text(json.dumps(rec))
    body = (
        "out = {'warnings': [], 'eager': [], 'kernel': []}\n"
        "for m in models:\n"
        "    with warnings.catch_warnings(record=True) as w:\n"
        "        tau = m.inverse_dynamics(q, q, q)\n"  # auto: checks, warns, rebuilds
        "    out['warnings'].append([str(x.message) for x in w])\n"
        "    ref = m.inverse_dynamics(q, q, q, backend='eager')\n"
        "    out['eager'].append(bool(torch.equal(tau, ref)))\n"
        "out['note'] = kernels.background_note()\n"
        "kernels.wait_for_builds(timeout=120)\n"
        "for m in models:\n"
        "    p = dynamics.program(m, 'id', False, False)\n"
        "    tau = m.inverse_dynamics(q, q, q)\n"
        "    ref = m.inverse_dynamics(q, q, q, backend='eager')\n"
        "    out['kernel'].append([kernels._ready(p, q), float((tau - ref).abs().max())])\n"
        "print(json.dumps(out))\n"
    )
    run = subprocess.run([sys.executable, "-c", _snippet(lengths, body)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout)
    for how, msgs in zip(damage, out["warnings"], strict=True):
        assert len(msgs) == 1 and "is damaged" in msgs[0], (how, msgs)
        assert "removed and rebuilt; running eagerly meanwhile" in msgs[0]
    assert "has 4000 bytes" in out["warnings"][0][0] and "has 0 bytes" in out["warnings"][1][0]
    assert "sha256" in out["warnings"][2][0] and "does not load" in out["warnings"][3][0]
    assert all(out["eager"])  # the damaged runs gave the eager result
    assert out["note"].startswith("note: 4 kernel builds go on in the background")
    for ready, err in out["kernel"]:  # rebuilt, loaded, equal to eager
        assert ready and err < 1e-12
    for m in models:
        assert _entry(m).check() == ("ok", "")


def test_a_second_process_runs_while_a_build_is_being_written(cache, monkeypatch):
    """Process A builds; while its compiler has half a library on disk, this process loads the
    same kernel in a loop: every call runs (eagerly) and gives the eager result, and once A has
    published the library this process uses it (before: ``file too short``)."""
    mark = cache / "writing"
    monkeypatch.setenv("CC_MARK", str(mark))
    monkeypatch.setenv("CC_SLEEP", "3")
    model = _pendulum(0.45)
    prog = dynamics.program(model, "id", False, False)
    q = torch.linspace(-3, 3, N, dtype=torch.float64)[:, None]
    ref = model.inverse_dynamics(q, q, q, backend="eager")  # warm up before A starts
    kernels.code_digest()
    body = "models[0].inverse_dynamics(q[:8], q[:8], q[:8], backend='cpu')\n"  # builds, waits
    a = subprocess.Popen([sys.executable, "-c", _snippet([0.45], body)], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        for _ in range(1200):
            if mark.exists() or a.poll() is not None:
                break
            time.sleep(0.05)
        assert mark.exists(), a.stderr.read() if a.poll() is not None else "no build started"
        writing = list(_entry(model).dir.glob("*.so.*.tmp"))
        assert writing and writing[0].stat().st_size == 4000  # half a library is on disk
        calls = 0
        while not kernels._ready(prog, q):
            tau = model.inverse_dynamics(q, q, q)  # auto: eager while A builds, then the kernel
            calls += 1
            torch.testing.assert_close(tau, ref, atol=1e-12, rtol=0)
            if calls == 1:  # A's compiler still runs: this process's builder waits on its lock
                assert "end" not in (cache / "cc.log").read_text()
                assert kernels.background_builds() == [_entry(model).name]
                assert main(["cache", "info"]) == 0
            assert calls < 2000
            time.sleep(0.02)
        torch.testing.assert_close(model.inverse_dynamics(q, q, q), ref, atol=1e-12, rtol=0)
        assert a.wait(timeout=120) == 0, a.stderr.read()[-2000:]
    finally:
        if a.poll() is None:
            a.kill()
        a.wait()
        kernels.wait_for_builds(timeout=120)
    assert _compilers_at_once(cache / "cc.log") == 1
    assert len((cache / "cc.log").read_text().splitlines()) == 2  # one build, not two


def test_compilers_at_once_stay_within_the_bound_across_processes(cache):
    """Two processes ask for two kernels each in the background: with a bound of one, one
    compiler runs at a time, and every kernel gets built once (before: one compiler per
    kernel at once, detached)."""
    lengths = [[0.51, 0.52], [0.53, 0.52]]  # 0.52 in both: built once
    body = (
        "for m in models:\n"
        "    m.inverse_dynamics(q, q, q)\n"  # auto: eager now, a detached build starts
        "kernels.wait_for_builds(timeout=200)\n"
        "for m in models:\n"
        "    m.inverse_dynamics(q, q, q)\n"  # loads the finished build
        "print(json.dumps([kernels._ready(dynamics.program(m, 'id', False, False), q)"
        " for m in models]))\n"
    )
    procs = [subprocess.Popen([sys.executable, "-c", _snippet(x, body)], cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for x in lengths]  # fmt: skip
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
        assert json.loads(out) == [True, True]
    log = (cache / "cc.log").read_text().splitlines()
    assert len(log) == 2 * 3  # three distinct kernels, each compiled once
    assert _compilers_at_once(cache / "cc.log") == 1


def test_cache_info_and_clear(cache, capsys):
    model = _pendulum(0.61)
    q = torch.zeros(4, 1, dtype=torch.float64)
    model.inverse_dynamics(q, q, q, backend="cpu")
    e = _entry(model)
    assert main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert str(cache / "cache" / "kernels") in out and "compilers at once: 1" in out
    assert f"{e.name}  ok  library" in out
    _damage(e.library, b"")
    assert main(["cache", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [x["state"] for x in info["entries"]] == [f"damaged: {e.library.name} has 0 bytes,"
                                                     f" its record says {e.record()['size']}"]  # fmt: skip
    assert info["index_keys"] == 1
    assert main(["cache", "clear"]) == 0
    assert capsys.readouterr().out.startswith("removed 1 kernels")
    assert main(["cache", "info", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["entries"] == []
    assert not e.dir.exists() and not (cache / "cache" / "kernels" / "index").exists()


def test_a_cache_hit_does_not_trace_the_program(cache):
    """The index maps a program's key to its entry: a cached kernel is found without tracing
    the program (the trace of a whole-robot estimator costs ~0.2 s per kernel and process)."""
    built = dynamics.program(_pendulum(0.62), "id", False, False)
    kernels.compiled(built, torch.float64)
    assert not built._traced  # freed once the source was written
    calls = []

    def fn(x):
        calls.append(1)
        return built.fn(x)

    # the same program as a fresh process makes it: a new object, the same key
    fresh = kernels.Program(built.name, fn, built.inputs, built.outputs, built.key)
    entry, state = kernels._cpu_entry(fresh, torch.float64)
    assert state == ("ok", "") and calls == []
    index = list((cache / "cache" / "kernels" / "index").glob("*.json"))
    assert len(index) == 1 and json.loads(index[0].read_text())["entry"] == entry.name
    # not built yet, its source kept: still no trace (the build starts from the source)
    entry.remove_library()
    assert kernels._cpu_entry(fresh, torch.float64) == (entry, ("absent", "not built"))
    assert calls == []
    # the source lost (or altered): traced again, the source rewritten
    entry.source.write_text("// altered")
    assert kernels._cpu_entry(fresh, torch.float64)[0] == entry and calls == [1]
    assert entry.source.read_text().startswith(_store.PARTS_MARK)  # a generated source
    # an index record that names another source than the library was built from: traced again
    _store.build(entry)
    assert kernels._cpu_entry(fresh, torch.float64) == (entry, ("ok", "")) and calls == [1]
    rec = json.loads(index[0].read_text())
    index[0].write_text(json.dumps({**rec, "source_sha256": "0" * 64}))
    assert kernels._cpu_entry(fresh, torch.float64) == (entry, ("ok", "")) and calls == [1, 1]
    assert json.loads(index[0].read_text()) == rec  # rewritten


def test_the_cached_backend_uses_a_built_kernel_and_never_starts_a_build(cache):
    """``backend="cached"`` (a log's noise estimate): eager while the kernel is not built, and
    no build started (it would hold the compile slot the run's own kernel needs next)."""
    from torchcontact.kernels.runner import run_program

    prog = dynamics.program(_pendulum(0.64), "id", False, False)
    q = torch.linspace(-3, 3, N, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    eager = kernels.run(prog, x, "eager")
    for run in (lambda: kernels.run(prog, x, "cached"), lambda: run_program(prog, x, "cached")):
        out = run()
        assert not kernels.background_builds() and not (cache / "cc.log").exists()
        torch.testing.assert_close(out, eager, rtol=0, atol=0)  # eager: the same numbers
    assert kernels.compiled(prog, torch.float64, wait=False, build=False) is None
    kernels.compiled(prog, torch.float64)  # built now
    calls = (cache / "cc.log").read_text().count("start")
    out = kernels.run(prog, x, "cached")
    torch.testing.assert_close(out, eager, rtol=1e-12, atol=1e-12)  # the kernel's
    assert kernels._ready(prog, q) and (cache / "cc.log").read_text().count("start") == calls


def test_an_unbuilt_kernel_is_checked_once_then_found_when_another_process_builds_it(
    cache, monkeypatch
):
    """A call that does not build (``auto`` while the VM runs the program, ``cached``) checks
    the entry once; later calls stat its library instead (each chunk of a first run asked, 1.8
    ms each), and load the kernel as soon as another process has built it."""
    prog = dynamics.program(_pendulum(0.59), "id", False, False)
    q = torch.linspace(-3, 3, N, dtype=torch.float64)[:, None]
    x = {"q": q, "qd": q * 0.5, "qdd": q * 0.25}
    checks = []
    real = kernels._cpu_entry
    monkeypatch.setattr(kernels, "_cpu_entry", lambda *a: checks.append(1) or real(*a))
    for _ in range(5):
        assert kernels.compiled(prog, torch.float64, wait=False, build=False) is None
    assert len(checks) == 1
    _store.build(real(prog, torch.float64)[0])  # as another process's build
    k = kernels.compiled(prog, torch.float64, wait=False, build=False)
    assert k is not None and len(checks) == 2  # checked again once the library is there
    torch.testing.assert_close(k(x)["tau"], kernels.run_eager(prog, x)["tau"], rtol=1e-12,
                               atol=1e-12)  # fmt: skip


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (nvcc)")
def test_cuda_entry_is_checked_published_and_healed(cache):
    """CUDA entries: recorded after an nvcc build in a private folder; a truncated and an
    unloadable library each warn and are rebuilt, in fresh processes; ``auto`` runs eagerly
    while a CUDA kernel builds in a thread, then uses it."""
    body = (
        "m = models[0].to('cuda')\n"
        "x = q.cuda()\n"
        "ref = m.inverse_dynamics(x, x, x, backend='eager')\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    tau = m.inverse_dynamics(x, x, x, backend=sys.argv[1])\n"
        "    kernels.wait_for_builds(timeout=300)\n"
        "    tau2 = m.inverse_dynamics(x, x, x)\n"
        "p = dynamics.program(m, 'id', False, False)\n"
        "print(json.dumps({'warnings': [str(x.message) for x in w], 'ready': kernels._ready(p, x),"
        " 'err': float(max((tau - ref).abs().max(), (tau2 - ref).abs().max()))}))\n"
    )
    code = _snippet([0.71], body)

    def run(backend: str) -> dict:
        res = subprocess.run([sys.executable, "-c", code, backend], cwd=ROOT,
                             capture_output=True, text=True, timeout=600)  # fmt: skip
        assert res.returncode == 0, res.stderr[-3000:]
        return json.loads(res.stdout)

    def entry() -> _store.Entry:
        (d,) = (cache / "cache" / "kernels").glob("tckc_*")
        return _store.Entry(d.parent, d.name, ".cu")

    out = run("cuda")
    e = entry()
    assert out["warnings"] == [] and out["ready"] and out["err"] < 1e-9
    assert e.check() == ("ok", "") and not list(e.dir.glob("build-*"))
    data = e.library.read_bytes()
    _damage(e.library, data[:4000])
    out = run("cuda")
    assert len(out["warnings"]) == 1 and "has 4000 bytes" in out["warnings"][0]
    assert out["ready"] and out["err"] < 1e-9 and entry().check() == ("ok", "")
    _damage(e.library, os.urandom(len(data)))  # garbage, its record made to match it
    size, digest = _store.file_digest(e.library)
    e.record_path.write_text(json.dumps({**e.record(), "size": size, "sha256": digest}))
    out = run("cuda")
    assert len(out["warnings"]) == 1 and "does not load" in out["warnings"][0]
    assert out["ready"] and out["err"] < 1e-9 and entry().check() == ("ok", "")
    shutil.rmtree(e.dir)
    out = run("auto")  # eager now, a thread builds; then the kernel
    assert out["warnings"] == [] and out["ready"] and out["err"] < 1e-9
