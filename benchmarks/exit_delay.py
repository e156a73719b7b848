"""How long a command lives after it has published its output, with and without the fast exit.

``torchcontact`` (the console script, :func:`torchcontact.cli.console_main`) ends its process with
``os._exit`` once the command has returned and its streams are flushed; before, the interpreter's
shutdown (idle pool threads joined, torch, pyarrow and every module torn down) ran after the
output was already published. Both entries run here side by side, alternating, on the same log:

- ``before``: ``sys.exit(main())``, what the console script did (and ``python -m torchcontact``
  still does);
- ``after``: ``console_main()``.

For ``estimate`` the time measured is from the moment the output file appears (the run publishes
it with a rename) to the moment the process has exited, polled every millisecond. For ``--help``
it is the whole command, beside ``python -c pass`` (the interpreter alone). ``--load N`` runs N
busy processes meanwhile (a loaded machine; the figures move with the load, the ratios less).

    python benchmarks/exit_delay.py                     # 20 k simulated tcarm frames, quiet
    python benchmarks/exit_delay.py --load 2 --repeat 5 # under load
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import metadata  # noqa: E402

ENTRIES = {
    "before": "import sys; from torchcontact.cli import main; sys.exit(main())",
    "after": "from torchcontact.cli import console_main; console_main()",
}


def _cmd(entry: str, args: list[str]) -> list[str]:
    return [sys.executable, "-c", ENTRIES[entry], *args]


def published_to_exit(entry: str, args: list[str], out: Path) -> tuple[float, float]:
    """(seconds from ``out`` appearing to the process's exit, seconds of the whole process)."""
    out.unlink(missing_ok=True)
    t0 = time.perf_counter()
    p = subprocess.Popen(_cmd(entry, args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    seen = None
    while p.poll() is None:
        if seen is None and out.exists():
            seen = time.perf_counter()
        time.sleep(0.001)
    end = time.perf_counter()
    err = p.stderr.read().decode() if p.stderr else ""
    if p.returncode != 0 or seen is None:
        raise SystemExit(f"{entry} {' '.join(args)} failed ({p.returncode}): {err}")
    return end - seen, end - t0


def wall(cmd: list[str]) -> float:
    """Seconds a process takes, start to exit."""
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def warm(est: list[str], timeout: float = 600.0) -> None:
    """Run ``est`` until its kernel is in the cache, so that both entries run the same work."""
    import json
    import re

    for _ in range(3):
        err = subprocess.run(_cmd("before", est), check=True, capture_output=True, text=True)
        names = re.findall(r"tck_\w+", err.stderr)
        if not names:
            return
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:  # the detached build fills the cache
            info = subprocess.run(_cmd("before", ["cache", "info", "--json"]), check=True,
                                  capture_output=True, text=True).stdout  # fmt: skip
            state = {e["name"]: e["state"] for e in json.loads(info)["entries"]}
            if all(state.get(n) == "ok" for n in names):
                break
            time.sleep(2)


def _busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _row(name: str, before: list[float], after: list[float]) -> str:
    b, a = statistics.median(before), statistics.median(after)
    return (
        f"| {name} | {b:.3f} ({min(before):.3f}-{max(before):.3f}) |"
        f" {a:.3f} ({min(after):.3f}-{max(after):.3f}) | {b / max(a, 1e-9):.1f}x |"
    )


def main() -> None:
    """Run the measurements and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="a log of the bundled arm (default: simulate one)")
    ap.add_argument("--frames", type=int, default=20000, help="frames simulated (default: 20000)")
    ap.add_argument("--repeat", type=int, default=5, help="runs of each entry (default: 5)")
    ap.add_argument("--load", type=int, default=0, help="busy processes meanwhile (default: 0)")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="tc-exit-"))
    try:
        run(a, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run(a: argparse.Namespace, tmp: Path) -> None:
    """The measurements of ``main``'s arguments ``a``, files under ``tmp``."""
    log = a.log
    if log is None:
        log = tmp / "sim.parquet"
        args = ["simulate", "--robot", "tcarm", "--frames", str(a.frames), "--out", str(log)]
        subprocess.run(_cmd("before", [*args, "--quiet"]), check=True)
    out = tmp / "est.parquet"
    est = ["estimate", str(log), "--robot", "tcarm", "--out", str(out), "--quiet"]
    warm(est)
    busy = _busy(a.load)
    try:
        times: dict[str, dict[str, list[float]]] = {
            k: {"exit": [], "total": [], "help": []} for k in ENTRIES
        }
        bare = []
        for _ in range(a.repeat):
            for entry in ENTRIES:  # alternating: both see the same load
                d, t = published_to_exit(entry, est, out)
                times[entry]["exit"].append(d)
                times[entry]["total"].append(t)
                times[entry]["help"].append(wall(_cmd(entry, ["--help"])))
            bare.append(wall([sys.executable, "-c", "pass"]))
    finally:
        for p in busy:
            p.kill()
            p.wait()
    print(metadata())
    print(f"log {log} | {a.repeat} runs each | {a.load} busy processes | median (min-max), s")
    print("| measure | before: sys.exit(main()) | after: console_main() | ratio |")
    print("|---|---|---|---|")
    b, f = times["before"], times["after"]
    print(_row("estimate: published -> exited", b["exit"], f["exit"]))
    print(_row("estimate: whole process", b["total"], f["total"]))
    print(_row("torchcontact --help", b["help"], f["help"]))
    p = statistics.median(bare)
    print(
        f"| python -c pass | {p:.3f} | {p:.3f} | --help / pass: before"
        f" {statistics.median(b['help']) / p:.1f}x, after {statistics.median(f['help']) / p:.1f}x |"
    )


if __name__ == "__main__":
    main()
