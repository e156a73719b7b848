"""First run (empty kernel cache) against the second, with and without the tape VM, interleaved.

``torchcontact estimate`` of ``benchmarks/pipeline.py``'s log (its ``e2e`` child: the CLI's
work in one process), in rounds; each round runs, one after the other:

* ``warm``: the kernel cache filled (the estimator's kernel built);
* ``cold, VM, kernel built after the run``: an empty cache, the default
  (``$TORCHCONTACT_VM=1``): the VM builds (under a second; the run waits for it), runs the log,
  and the estimator's kernel builds once the run's process exits (detached, ``nice 19``);
* ``cold, VM (already built), ...``: the same with the VM's entry copied into the empty cache
  (a new robot, or a new torchcontact version, on a machine that has run torchcontact before);
* ``cold, VM + kernel built behind it``: ``$TORCHCONTACT_VM=behind``: the kernel builds during
  the run at ``nice 19`` and the run switches to it at the next chunk after the build;
* ``cold, VM only``: an empty cache, ``$TORCHCONTACT_VM=only`` (no kernel build);
* ``cold, eager while building``: an empty cache, ``$TORCHCONTACT_VM=0`` (before the VM).

After each cold run the script waits for the builds it left (and reports how long they went on
after the run), so that no compiler runs during the next one. Rounds interleave the variants,
so that a loaded machine's changes spread over all of them; the table gives medians of the wall
and CPU seconds of the run's process and their ratios to the warm run. Run on a quiet machine::

    python benchmarks/vm_cold.py                       # 1 M iCub frames, 2 rounds
    python benchmarks/vm_cold.py --frames 200000 --rounds 3 --tmp /tmp/tc-vm-cold

``--against SRC`` compares this checkout's first run with another torchcontact's (a source tree,
such as ``git archive fe83dd1 | tar -x -C /tmp/main``, run with ``PYTHONPATH=SRC``): each round
runs, for each of the two in turn (the order alternating), a warm run and a first run (the
default variant), and the table gives the ratio of each round's pair, so that a loaded
machine's changes fall on both alike.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402
from pipeline import cmdlines, run_child, write_log  # noqa: E402

VARIANTS = [
    ("warm", None),
    ("cold, VM, kernel built after the run (default)", "1"),
    ("cold, VM (already built), kernel after the run", "1+vm"),
    ("cold, VM + kernel built behind it (nice 19)", "behind"),
    ("cold, VM only", "only"),
    ("cold, eager while building (no VM)", "0"),
]


def compilers(cache: str) -> int:
    """Compiler processes whose command line names ``cache``."""
    return sum(
        1 for cmd in cmdlines() if cache in cmd and re.search(r"\b(cc1plus|_store\.py)\b", cmd)
    )


def settle(cache: str, limit: float = 900.0) -> float:
    """Wait until no build runs in ``cache``; returns the seconds waited."""
    t = time.perf_counter()
    while compilers(cache) and time.perf_counter() - t < limit:
        time.sleep(0.2)
    return time.perf_counter() - t


def against(args, log: Path, out: Path, tmp: Path) -> None:
    """``--against``: warm and first (default) runs of this checkout and ``args.against``."""
    here = str(Path(__file__).resolve().parents[1])
    trees = {"this checkout": here, f"--against {args.against}": str(Path(args.against).resolve())}
    warm_caches = {}
    for i, (name, src) in enumerate(trees.items()):
        cache = str(tmp / f"cache-warm-{i}")
        env = {**os.environ, "PYTHONPATH": src, "TORCHCONTACT_CACHE": cache}
        run_child("e2e", args.robot, log, out, "cpu", env)  # fills the warm cache
        settle(cache)
        run_child("e2e", args.robot, log, out, "cpu", env)
        warm_caches[name] = env
    pairs: dict[str, list[tuple[float, float]]] = {name: [] for name in trees}
    load0 = os.getloadavg()[0]
    for r in range(args.rounds):
        for name in list(trees)[:: 1 if r % 2 == 0 else -1]:
            warm = run_child("e2e", args.robot, log, out, "cpu", warm_caches[name])
            cache = str(tmp / f"cache-cold-{time.time_ns()}-{r}")
            env = {**warm_caches[name], "TORCHCONTACT_CACHE": cache, "TORCHCONTACT_VM": "1"}
            cold = run_child("e2e", args.robot, log, out, "cpu", env)
            settle(cache)
            pairs[name].append((warm["seconds"], cold["seconds"]))
            print(f"round {r}: {name}: warm {warm['seconds']:.2f} s, first {cold['seconds']:.2f} s:"
                  f" {cold['seconds'] / warm['seconds']:.2f}x", flush=True)  # fmt: skip
    print()
    print(metadata())
    print(f"log: {log.name}, {args.frames:,} frames, robot {args.robot}; rounds {args.rounds};"
          f" load average at start {load0:.1f}, at end {os.getloadavg()[0]:.1f}")  # fmt: skip
    print()
    print("| torchcontact | warm (median s) | first run (median s) | first / warm per round |"
          " median of the rounds' ratios |")  # fmt: skip
    print("|---|---:|---:|---|---:|")
    for name, ps in pairs.items():
        ratios = [c / w for w, c in ps]
        print(f"| {name} | {statistics.median(w for w, _ in ps):.2f}"
              f" | {statistics.median(c for _, c in ps):.2f} | {[round(x, 2) for x in ratios]}"
              f" | {statistics.median(ratios):.2f}x |")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", choices=["icub", "tcarm"], default="icub")
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--tmp", default=None, help="folder for the log and caches (kept; reused)")
    ap.add_argument("--against", default=None, help="another torchcontact's source tree")
    args = ap.parse_args()
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="tc-vm-cold-"))
    tmp.mkdir(parents=True, exist_ok=True)
    log = write_log(args.robot, args.frames, tmp / f"{args.robot}{args.frames}.parquet")
    out = tmp / "out.parquet"
    if args.against:
        against(args, log, out, tmp)
        return
    warm_cache = str(tmp / "cache-warm")
    warm_env = {**os.environ, "TORCHCONTACT_CACHE": warm_cache}
    run_child("e2e", args.robot, log, out, "cpu", warm_env)  # fills the warm cache
    code = "import torch; from torchcontact import kernels; kernels._vm_function(torch.float64,"
    subprocess.run([sys.executable, "-c", code + " False, wait=True)"], env=warm_env, check=True)
    settle(warm_cache)
    run_child("e2e", args.robot, log, out, "cpu", warm_env)  # loads what the first one built
    times: dict[str, list[float]] = {name: [] for name, _ in VARIANTS}
    cpu: dict[str, list[float]] = {name: [] for name, _ in VARIANTS}
    after: dict[str, list[float]] = {name: [] for name, _ in VARIANTS}
    load0 = os.getloadavg()[0]
    for r in range(args.rounds):
        for name, mode in VARIANTS:
            if mode is None:
                env, cache = warm_env, warm_cache
            else:
                cache = str(tmp / f"cache-cold-{time.time_ns()}-{r}")
                if mode.endswith("+vm"):  # a new robot on a machine that ran torchcontact before
                    mode = mode[: -len("+vm")]
                    for vm in Path(warm_cache, "kernels").glob("tck_vm-*"):
                        shutil.copytree(vm, Path(cache, "kernels", vm.name))
                env = {**os.environ, "TORCHCONTACT_CACHE": cache, "TORCHCONTACT_VM": mode}
            res = run_child("e2e", args.robot, log, out, "cpu", env)
            times[name].append(res["seconds"])
            cpu[name].append(res["cpu"])
            after[name].append(settle(cache))
            print(f"round {r}: {name}: {res['seconds']:.2f} s ({res['cpu']:.2f} CPU s), builds"
                  f" went on {after[name][-1]:.1f} s after it", flush=True)  # fmt: skip
    print()
    print(metadata())
    print(f"log: {log.name}, {args.frames:,} frames, robot {args.robot}; rounds {args.rounds};"
          f" load average at start {load0:.1f}, at end {os.getloadavg()[0]:.1f}")  # fmt: skip
    print()
    print("| run | seconds (median) | vs warm | CPU seconds (median) | vs warm | builds after"
          " the run (s) | runs (s) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---|")
    warm, warm_cpu = statistics.median(times["warm"]), statistics.median(cpu["warm"])
    for name, _ in VARIANTS:
        m, c = statistics.median(times[name]), statistics.median(cpu[name])
        print(
            f"| {name} | {m:.2f} | {m / warm:.2f}x | {c:.2f} | {c / warm_cpu:.2f}x"
            f" | {statistics.median(after[name]):.1f} | {[round(t, 2) for t in times[name]]} |"
        )
    print("\n(CPU seconds: the run's own process; a detached build's compilers are not in them)")


if __name__ == "__main__":
    main()
