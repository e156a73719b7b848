"""Start-up: ``torchcontact --help`` imports neither torch nor numpy, and ``estimate`` none of the
modules it does not use (each checked in a fresh interpreter)."""

import errno
import json
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from torchcontact.cli import COMMANDS, build_parser
from torchcontact.errors import LogError
from torchcontact.logs import estimate_file
from torchcontact.logs import format as fmt

ROOT = Path(__file__).resolve().parents[2]
# pandas: pyarrow imports it (0.3-0.6 s) at its first numpy conversion; the log job converts with
# torchcontact.logs.format's helpers, which never do
UNUSED_BY_ESTIMATE = ("ray", "matplotlib", "onnx", "onnxruntime", "rosbags", "pymodbus", "serial",
                      "pandas")  # fmt: skip


def _estimate(*args: str) -> tuple[set[str], str]:
    """A console-script ``torchcontact estimate ARGS`` run, as users run it (its entry ends the
    process with os._exit once the output is published): the top-level modules it imported
    (``-X importtime`` lists every one) and its stdout."""
    code = "from torchcontact.cli import console_main; console_main()"
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", code, "estimate", *args],
                       capture_output=True, text=True, cwd=ROOT)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    imported = {line.split("|")[-1].strip().split(".")[0] for line in r.stderr.splitlines()
                if line.startswith("import time:")}  # fmt: skip
    return imported, r.stdout


def _fresh(code: str) -> list:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_help_imports_no_torch_or_numpy():
    code = (
        "import sys, json\n"
        "from torchcontact.cli import main\n"
        "for argv in (['--help'], ['estimate', '--help'], ['sensor', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "    if argv[0] == 'estimate':\n"
        "        est = [m for m in ('torch', 'numpy', 'pyarrow') if m in sys.modules]\n"
        "print(json.dumps([est, [m for m in ('torch', 'pyarrow') if m in sys.modules]]))\n"
    )
    estimate_help, after_sensor = _fresh(code)
    assert estimate_help == [] and after_sensor == []


def test_estimate_imports_only_what_it_uses(sim_log, tmp_path):
    """Run as users run it, through the console script's entry (which ends the process with
    os._exit once the output is published): the JSON summary and the output arrive whole, and
    ``-X importtime`` lists every module the process imported."""
    out = tmp_path / "o.parquet"
    imported, stdout = _estimate(str(sim_log), "--robot", "tcarm", "--out", str(out), "--quiet",
                                 "--json")  # fmt: skip
    assert "torch" in imported and not imported & set(UNUSED_BY_ESTIMATE)
    assert json.loads(stdout)["frames"] == 600 and pq.read_table(out).num_rows == 600


def test_estimate_imports_with_the_collector_off_then_freezes(sim_log, tmp_path):
    """``estimate`` imports torch, pyarrow and the pipeline without the cyclic collector (its
    full passes during torch's import cost 0.1-0.3 CPU-s of a start), then freezes what they
    made and turns the collector back on: in a fresh process, no full collection runs during
    the whole run of a small log (before: 3 during torch's import), and the collector is on
    afterwards. A caller who turned it off keeps it off."""
    code = (
        "import gc, json\n"
        "starts = []\n"
        "gc.callbacks.append(lambda phase, info: starts.append(info['generation'])\n"
        "                    if phase == 'start' else None)\n"
        "from torchcontact.cli import main\n"
        f"argv = ['estimate', {str(sim_log)!r}, '--robot', 'tcarm', '--quiet']\n"
        f"rc = main(argv + ['--out', {str(tmp_path / 'a.parquet')!r}])\n"
        "on, frozen = gc.isenabled(), gc.get_freeze_count()\n"
        "gc.disable()\n"
        f"rc2 = main(argv + ['--out', {str(tmp_path / 'b.parquet')!r}])\n"
        "print(json.dumps([rc, rc2, starts.count(2), on, frozen, gc.isenabled()]))\n"
    )
    rc, rc2, full, on, frozen, on_after_off = _fresh(code)
    assert rc == rc2 == 0 and full == 0
    assert on and frozen > 100_000 and not on_after_off


def test_a_ray_worker_imports_its_side_as_the_cli_does():
    """A Ray worker process imports the engine's worker side (torch, torchcontact) once, with the
    collector off and then frozen, as ``estimate`` does; later calls take the module as it is."""
    code = (
        "import gc, json, sys\n"
        "starts = []\n"
        "gc.callbacks.append(lambda phase, info: starts.append(info['generation'])\n"
        "                    if phase == 'start' else None)\n"
        "from torchcontact.logs._ray_boot import worker_side\n"
        "before = 'torch' in sys.modules\n"
        "m = worker_side()\n"
        "frozen, full = gc.get_freeze_count(), starts.count(2)\n"
        "again = worker_side() is m and gc.get_freeze_count() == frozen\n"
        "print(json.dumps([before, m.__name__, full, frozen, gc.isenabled(), again]))\n"
    )
    before, name, full, frozen, on, again = _fresh(code)
    assert not before and name == "torchcontact.logs.ray_worker"
    assert full == 0 and frozen > 100_000 and on and again


def test_the_console_script_starts_the_kernel_builds_it_deferred(model, tmp_path):
    """The console script ends with ``os._exit`` (no exit handler runs): the kernel builds that
    the tape VM's run deferred to the process's end start all the same, and fill the cache.

    Regression: they never started, so every run of ``torchcontact estimate`` ran on the VM
    (half the compiled kernel's speed) while its note said that the builds went on.
    """
    import os
    import re
    import time

    from torchcontact.logs import write_simulated_log

    log = write_simulated_log(model, 2500, tmp_path / "log.parquet", seed=1)  # >= 2048: auto
    cache = tmp_path / "cache"
    code = "from torchcontact.cli import console_main; console_main()"
    r = subprocess.run([sys.executable, "-c", code, "estimate", str(log), "--robot", "tcarm",
                        "--out", str(tmp_path / "o.parquet"), "--quiet"], capture_output=True,
                       text=True, cwd=ROOT, env={**os.environ, "TORCHCONTACT_CACHE": str(cache)})  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    note = next(line for line in r.stderr.splitlines() if line.startswith("note: "))
    names = re.findall(r"tck_estimator_\w+|tck_predict_\w+", note)
    assert names and "in the background" in note
    libs = [cache / "kernels" / n / f"{n}.so" for n in names]
    deadline = time.monotonic() + 300
    while not all(p.is_file() for p in libs) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert all(p.is_file() for p in libs), [p.name for p in libs if not p.is_file()]


def test_estimate_starts_the_vm_build_before_importing_torch(model, tmp_path):
    """On an empty cache, a CPU run of a log of ``AUTO_BUILD_MIN_FRAMES`` frames or more starts
    the tape VM's build before it imports torch (its compiler runs beside the import), once: the
    kernels package loads what it built (or adopts the builder while it runs:
    tests/test_kernels_vm.py) instead of starting its own."""
    import os

    from torchcontact.logs import write_simulated_log

    log = write_simulated_log(model, 2500, tmp_path / "log.parquet", seed=1)  # >= 2048
    code = (
        "import json, sys\n"
        "import torchcontact._lightkernels as lk\n"
        "calls, start = [], lk.start_vm_build\n"
        "def spy(dtype):\n"
        "    calls.append(['torch' in sys.modules, dtype])\n"
        "    return start(dtype)\n"
        "lk.start_vm_build = spy\n"
        "from torchcontact.cli import main\n"
        f"rc = main(['estimate', {str(log)!r}, '--robot', 'tcarm', '--out',"
        f" {str(tmp_path / 'o.parquet')!r}, '--quiet', '--device', 'cpu'])\n"
        "import torch\n"
        "from torchcontact import kernels\n"
        "b = kernels._vm_builds.get(torch.float64)\n"
        "own = b is not None and not any(p is b.proc for p in lk._builds.values())\n"
        "print(json.dumps([rc, calls, len(lk._builds), own, torch.float64 in kernels._vm_fns]))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "TORCHCONTACT_CACHE": str(tmp_path / "cache")})  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    rc, calls, started, own_build, vm_ran = json.loads(r.stdout.strip().splitlines()[-1])
    assert rc == 0 and calls == [[False, "double"]] and started == 1
    assert vm_ran and not own_build  # the run used the VM that build made, and started no other


def test_which_runs_start_the_vm_build_early(tmp_path, monkeypatch):
    """``_start_vm_build``: CPU runs (``--device cpu``, or ``auto`` without an NVIDIA driver) of
    a first log of ``AUTO_BUILD_MIN_FRAMES`` rows or more, with the run's dtype; an unreadable
    log is left to the run's own error."""
    import argparse

    import pyarrow as pa

    from torchcontact import _lightkernels
    from torchcontact.logs import cli as lcli

    calls = []
    monkeypatch.setattr(_lightkernels, "start_vm_build", calls.append)
    n = _lightkernels.AUTO_BUILD_MIN_FRAMES
    big, small, bad = tmp_path / "big.parquet", tmp_path / "small.parquet", tmp_path / "bad.parquet"
    pq.write_table(pa.table({"t_ns": list(range(n))}), big)
    pq.write_table(pa.table({"t_ns": list(range(n - 1))}), small)
    bad.write_text("not parquet")

    def run(files, device="cpu", dtype="float64", nvidia=False):
        monkeypatch.setattr(lcli, "_nvidia_driver", lambda: nvidia)
        lcli._start_vm_build(argparse.Namespace(device=device, dtype=dtype), files)

    run([big])
    run([big, small], dtype="float32")
    run([big], device="auto")
    for files, device, nvidia in (([small, big], "cpu", False), ([big], "cuda", False),
                                  ([big], "auto", True), ([bad], "cpu", False),
                                  ([tmp_path / "missing.parquet"], "cpu", False), ([], "cpu", False)):  # fmt: skip
        run(files, device, nvidia=nvidia)
    assert calls == ["double", "float", "double"]


def test_resume_imports_no_pandas(model, sim_log, tmp_path, monkeypatch):
    """``--resume`` reads the kept parts back without pandas either: a run stopped by a full disk
    after two of its three chunks, resumed by the console script."""
    out = tmp_path / "o.parquet"
    real, calls = fmt.PartsWriter.append, []

    def full_after_two(self, part):
        calls.append(1)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, part)

    monkeypatch.setattr(fmt.PartsWriter, "append", full_after_two)
    with pytest.raises(LogError, match="2 of 3 chunks are kept"):
        estimate_file(sim_log, model, out, batch_size=200)
    monkeypatch.undo()
    imported, stdout = _estimate(str(sim_log), "--robot", "tcarm", "--out", str(out), "--resume",
                                 "--batch-size", "200", "--quiet", "--json")  # fmt: skip
    summary = json.loads(stdout)
    assert summary["resumed_chunks"] == 2 and summary["processed_now"] == 200
    assert "torch" in imported and "pandas" not in imported
    assert pq.read_table(out).num_rows == 600


def test_the_command_table_is_what_the_modules_register():
    parser = build_parser("*")
    sub = next(a for a in parser._actions if a.dest == "command")
    registered = {a.dest: a.help for a in sub._choices_actions}
    for name, (_, help_text) in COMMANDS.items():
        assert registered[name] == help_text, name
