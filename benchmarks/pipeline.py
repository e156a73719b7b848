"""``torchcontact estimate`` at the I/O limit: end to end against the pyarrow floor, cold and warm.

Run on a quiet machine (each mode writes its own table; every timing runs in its own process)::

    python benchmarks/pipeline.py                        # the issue's table: 1 M iCub frames
    python benchmarks/pipeline.py --frames 200000 --repeat 1          # quicker
    python benchmarks/pipeline.py --mem 1000000 10000000 --robot tcarm # peak RSS vs log length
    python benchmarks/pipeline.py --ray 1000000 --workers 1 2 4 8 16   # Ray scaling (many cores)
    RAY_ADDRESS=... python benchmarks/pipeline.py --ray 1000000 --workers 1 16 --keep-workers 60
    python benchmarks/pipeline.py --race 20                           # two runs on one output
    python benchmarks/pipeline.py --wait-rule 50000 200000 1000000    # wait for the kernel?
    python benchmarks/pipeline.py --device cuda                       # estimate --device cuda
    python benchmarks/pipeline.py --frames 200000 --warm 5 --compare-with /work/main  # CPU A/B

The log (written once into ``--tmp``, default a new temporary folder; pass a folder to reuse it):
the issue's iCub log, ``iCubGenova04`` from ``icub-models``, sensor ``l_arm_ft``, 0-2 pure-force
contacts per frame on ``l_forearm``/``l_hand`` (so the contact set changes from chunk to chunk),
a ``temperature`` column, ``qd``/``qdd`` logged, joints in the log's own (shuffled) order. A
block of 50,000 simulated frames is tiled with shifted ``t_ns`` up to ``--frames``. ``--robot
tcarm`` uses the bundled arm instead (base sensor, skin frames).

Default mode, every row in its own process, same log, medians of ``--repeat`` runs. The warm
rows (the floors, ``end to end, warm`` and ``--compare-with``'s) run in rounds, one of each per
round, and the ratios are also given as the median over rounds of each round's own ratio: this
machine's speed drifts by 10-20 % over minutes, which blocks of runs read as differences.

- ``pyarrow floor``: reading the columns ``estimate`` reads (page checksums verified, chunks of
  8192) plus writing the estimate table (loaded first, not timed) with the output's writer
  options: the floor of any Parquet-in, Parquet-out job on these columns.
- ``pyarrow floor, pyarrow's default writer options``: the same, written with
  ``pq.ParquetWriter``'s defaults (dictionaries and statistics on every column, no checksums).
- ``end to end, warm``: ``torchcontact estimate`` (the CLI's command, run in the timed process
  once Python, torch and the pipeline are imported) with every kernel in the cache (model
  loading, the log's scan, reading, estimating, journal, writing, rename: all timed). The
  floor's clock starts after pyarrow is imported; this one's includes it: ``end to end, warm,
  pyarrow imported before the clock`` is the same run with that import done first, after the
  allocator settings the CLI makes before it (``keep_freed_memory``). Two unmeasured runs come
  first, each followed by the kernel builds it started (the estimator's; the noise estimate's
  forward model, requested by the first run that finds the estimator's in the cache), so that
  "warm" means every kernel a run uses is cached.
- ``end to end, cold``: the same with an empty kernel cache (``TORCHCONTACT_CACHE`` a new folder);
  the most compilers seen running at once for that cache is counted from ``/proc``.
- ``in-memory kernel``: the estimator on the log's arrays already in memory (compiled kernel).
- ``a second run during the first's build``: a cold run, and a second process on the same cache
  started as soon as the first one's kernel source appears; it must end with exit 0.
- ``torchcontact --help``: a fresh process (median of 5), next to ``python -c pass``.

``--warm N`` (with ``--compare-with CHECKOUT``): the glue's CPU, old against new. N rounds, each
running, alternately, the pyarrow floor and, for each tree, one process that runs a warm
:func:`~torchcontact.logs.estimate_file` once (kernel traced and loaded, noise, ...) and then
twice more, measured: wall and CPU seconds of the whole process (``os.times``, every thread)
and the thread CPU of each stage (``time.thread_time`` around the pipeline's functions; the
pyarrow and encoder pool threads are in the process total only). Outputs are checked equal to
the floor's estimate table (``pq.read_table(a).equals(b)``, metadata too). Medians per tree.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
if os.environ.get("TC_BENCH_CODE"):  # --compare-with: that checkout's torchcontact
    sys.path.insert(0, os.environ["TC_BENCH_CODE"])
from _meta import metadata  # noqa: E402

BATCH = 8192
BLOCK = 50_000


# ---------------------------------------------------------------------- the log
def robot_setup(name: str) -> tuple[str, str, list[str]]:
    """URDF path, sensor and contact links of the benchmark robot."""
    if name == "icub":
        import icub_models

        return str(icub_models.get_model_file("iCubGenova04")), "l_arm_ft", ["l_forearm", "l_hand"]
    import torchcontact as tc

    return str(tc.robots.tcarm_path()), "base_ft", ["forearm_skin", "hand_skin"]


def write_log(robot: str, frames: int, path: Path, derivatives: bool = True) -> Path:
    """The benchmark log: a simulated block tiled with shifted t_ns, joints shuffled."""
    if path.exists():
        return path
    import pyarrow as pa
    import torch

    import torchcontact as tc
    from torchcontact.logs import simulated_table
    from torchcontact.logs.format import META_JOINT_NAMES, LogWriter
    from torchcontact.simulation import simulate

    torch.set_num_threads(1)
    urdf, sensor, links = robot_setup(robot)
    model = tc.RobotModel.from_urdf(urdf)
    log = simulate(model, min(BLOCK, frames), seed=0, sensor=sensor, links=links, max_contacts=2)
    tab = simulated_table(log, derivatives=derivatives)
    # the log's own joint order: shuffled columns, named in the metadata
    perm = np.random.default_rng(1).permutation(model.nv)
    names = [model.joint_names[i] for i in perm]
    for c in ("q", "qd", "qdd"):
        if c in tab.column_names:
            v = np.stack(tab[c].to_numpy(zero_copy_only=False))[:, perm]
            arr = pa.FixedSizeListArray.from_arrays(pa.array(v.reshape(-1)), model.nv)
            tab = tab.set_column(tab.schema.get_field_index(c), c, arr)
    meta = dict(tab.schema.metadata or {})
    meta[META_JOINT_NAMES] = json.dumps(names).encode()
    tab = tab.replace_schema_metadata(meta)
    step = int(log.t_ns[1] - log.t_ns[0])
    tmp = path.with_name(path.name + ".part")
    with LogWriter(tmp, tab.schema) as w:
        done = 0
        while done < frames:
            n = min(len(tab), frames - done)
            part = tab.slice(0, n)
            part = part.set_column(0, "t_ns", pa.array(part["t_ns"].to_numpy() + done * step))
            w.write(part, row_group_size=65536)
            done += n
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------------- children
def _rss_mb() -> float:
    """Peak RSS of this process (VmHWM: ru_maxrss would keep a parent's peak across exec)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _cpu() -> float:
    """CPU seconds of this process, every thread (user + system)."""
    t = os.times()
    return t.user + t.system


def child(kind: str, robot: str, log: str, out: str, extra: str) -> None:
    """One timed run; prints a JSON line."""
    import torch

    # one torch thread, as `torchcontact estimate` has by default (--threads 1; the e2e runs are
    # that command, which sets it itself)
    torch.set_num_threads(1)
    res: dict = {}
    if kind in ("floor", "floor-defaults"):
        import pyarrow as pa
        import pyarrow.parquet as pq

        from torchcontact.logs.format import WRITE_OPTIONS, open_log

        est = pq.read_table(extra)  # the estimate table, in memory (not timed)
        cols = json.loads(Path(extra + ".columns").read_text())
        t0, c0 = time.perf_counter(), _cpu()
        pf = open_log(log)
        n = sum(b.num_rows for b in pf.iter_batches(batch_size=BATCH, columns=cols))
        t1 = time.perf_counter()
        # the output's writer options, or pyarrow's defaults (dictionaries and statistics on
        # every column, no page checksums)
        opts = {"write_statistics": ["t_ns"], **WRITE_OPTIONS} if kind == "floor" else {}
        w = pq.ParquetWriter(out, est.schema, **opts)
        for b in est.to_batches(BATCH):
            w.write_table(pa.Table.from_batches([b]))
        w.close()
        t2 = time.perf_counter()
        res = {"seconds": t2 - t0, "cpu": _cpu() - c0, "read": t1 - t0, "write": t2 - t1,
               "frames": n}  # fmt: skip
    elif kind in ("e2e", "e2e-imported"):
        # the command a user runs, `torchcontact estimate`, in this process: its clock starts
        # once Python, torch and the pipeline are imported (the floor's, once pyarrow is)
        import contextlib
        import io

        import torchcontact.logs.pipeline  # noqa: F401 - torch and the pipeline
        from torchcontact.cli import main as cli_main

        if kind == "e2e-imported":  # as the floor: pyarrow's modules imported before the clock,
            # after the allocator settings the CLI makes before pyarrow loads
            from torchcontact.logs._alloc import keep_freed_memory

            keep_freed_memory()
            import pyarrow.compute  # noqa: F401
            import pyarrow.parquet  # noqa: F401

        if os.environ.get("TC_BENCH_WAIT"):  # --wait-rule: the kernel-wait threshold to use
            from torchcontact.logs import pipeline

            wait = os.environ["TC_BENCH_WAIT"]
            pipeline.WAIT_FOR_KERNEL_FRAMES = None if wait == "never" else int(wait)

        urdf, _, _ = robot_setup(robot)
        argv = ["estimate", log, "--robot", urdf, "--out", out, "--batch-size", str(BATCH),
                "--device", extra or "cpu", "--quiet", "--json"]  # fmt: skip
        printed = io.StringIO()
        t0, c0 = time.perf_counter(), _cpu()
        with contextlib.redirect_stdout(printed):
            rc = cli_main(argv)
        res = {"seconds": time.perf_counter() - t0, "cpu": _cpu() - c0}
        if rc:
            raise RuntimeError(f"torchcontact estimate exited with {rc}")
        s = json.loads(printed.getvalue().strip().splitlines()[-1])
        res.update(frames=s["frames"], slots=s.get("slots"))
    elif kind == "stages":
        res = _stages(robot, log, out, extra)
    elif kind == "inmem":
        import torchcontact as tc
        from torchcontact.contacts import Contacts
        from torchcontact.logs.format import read_log_columns

        urdf, sensor, _ = robot_setup(robot)
        model = tc.RobotModel.from_urdf(urdf)
        cols = read_log_columns(log, ["q", "qd", "qdd", f"ft.{sensor}", "contacts"],
                                joint_names=model.joint_names)  # fmt: skip
        n = len(cols["q"])
        est = tc.ContactEstimator(model, [sensor])
        rec = cols["contacts"]
        contacts, _ = Contacts.from_records(rec, n)  # one layout for the log, as estimate
        q, qd, qdd, ft = (torch.as_tensor(np.ascontiguousarray(cols[c]))
                          for c in ("q", "qd", "qdd", f"ft.{sensor}"))  # fmt: skip
        est.estimate(
            q[:BATCH],
            qd[:BATCH],
            qdd[:BATCH],
            {sensor: ft[:BATCH]},
            _rows(contacts, slice(0, BATCH)),
            backend="cpu",
        )  # build or load, untimed
        t0, c0 = time.perf_counter(), _cpu()
        for s0 in range(0, n, BATCH):
            sl = slice(s0, s0 + BATCH)
            est.estimate(q[sl], qd[sl], qdd[sl], {sensor: ft[sl]}, _rows(contacts, sl),
                         backend="cpu")  # fmt: skip
        res = {"seconds": time.perf_counter() - t0, "cpu": _cpu() - c0, "frames": n}
    res["maxrss_mb"] = _rss_mb()
    print(json.dumps(res), flush=True)
    if kind in ("e2e", "e2e-imported"):  # ends as the console script ends a command: its
        # teardown, then os._exit (no exit handler: what a user's run leaves is what it does)
        from torchcontact.cli import _finish_process

        _finish_process()
        sys.stderr.flush()
        os._exit(0)


def _stages(robot: str, log: str, out: str, ref: str) -> dict:
    """A warm estimate_file (after one unmeasured), twice: wall, process CPU, CPU per stage."""
    import collections
    import functools

    import pyarrow.parquet as pq

    import torchcontact as tc
    import torchcontact.logs.chunks as ch
    import torchcontact.logs.decode as dec
    import torchcontact.logs.pipeline as pl
    from torchcontact.logs import estimate_file

    acc: dict[str, float] = collections.defaultdict(float)

    def wrap(obj, name, label, gen=False):
        f = getattr(obj, name, None)
        if f is None:
            return

        @functools.wraps(f)
        def timed(*a, **k):
            t = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                acc[label] += time.thread_time() - t

        @functools.wraps(f)
        def timed_gen(*a, **k):
            it = f(*a, **k)
            while True:
                t = time.thread_time()
                try:
                    x = next(it)
                except StopIteration:
                    return
                finally:
                    acc[label] += time.thread_time() - t
                yield x

        setattr(obj, name, timed_gen if gen else timed)

    import torchcontact.logs.format as fmt
    import torchcontact.logs.run as run

    wrap(pl, "prepare", "prepare (scan)")  # an older tree's
    wrap(pl, "open_prepared", "prepare (the scan's first pass; its second on a thread)")
    wrap(getattr(pl, "Prepared", None), "finish", "waiting for the scan's second pass")
    wrap(pl, "log_noise", "noise estimate (its reading, decoding, kernel)")
    wrap(pl, "read_chunks", "Parquet read (calling thread; pyarrow's threads: total only)", True)
    wrap(dec.ChunkDecoder, "decode", "decoding (Arrow -> arrays, checks)")
    wrap(dec.ChunkDecoder, "slots", "contacts into the slots")
    wrap(ch.LogEstimator, "_solve", "estimator kernel (and its tensors)")
    wrap(ch.LogEstimator, "estimate", "per-chunk estimate (slots + kernel + output rows)")
    for mod in (run, fmt):  # this tree's journal and writer, or an older tree's
        wrap(mod, "encode_part", "Parquet encoding of the output (pool threads)")
        wrap(mod, "write_part_index", "journal entries")
        wrap(mod, "write_journal", "journal parts (Arrow IPC)")
    wrap(fmt.LogWriter, "write", "Parquet write of the output")
    wrap(getattr(fmt, "PartsWriter", None), "append", "appending the encoded output")
    wrap(run.Run, "record", "sidecar")
    wrap(run._Tally, "add", "summary tally")
    urdf, _, _ = robot_setup(robot)
    model = tc.RobotModel.from_urdf(urdf)
    estimate_file(log, model, out, batch_size=BATCH, progress=False)
    want = pq.read_table(ref)
    runs = []
    for _ in range(2):
        Path(out).unlink()
        acc.clear()
        t0, c0 = time.perf_counter(), _cpu()
        estimate_file(log, model, out, batch_size=BATCH, progress=False)
        runs.append({"seconds": time.perf_counter() - t0, "cpu": _cpu() - c0, "stages": dict(acc)})
    equal = pq.read_table(out).equals(want, check_metadata=True)
    return {"runs": runs, "equal": bool(equal), "frames": want.num_rows}


def _rows(contacts, sl):
    from dataclasses import fields, replace

    import torch

    tensors = [
        f.name for f in fields(contacts) if isinstance(getattr(contacts, f.name), torch.Tensor)
    ]
    return replace(contacts, **{n: getattr(contacts, n)[sl] for n in tensors})


def run_child(kind, robot, log, out, extra="", env=None, watch_cache=None) -> dict:
    Path(out).unlink(missing_ok=True)
    cmd = [sys.executable, __file__, "--child", kind, robot, str(log), str(out), extra]
    peak = [0]
    stop = threading.Event()
    if watch_cache:
        threading.Thread(
            target=_count_compilers, args=(watch_cache, stop, peak), daemon=True
        ).start()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    stop.set()
    if r.returncode:
        raise RuntimeError(r.stderr[-3000:])
    res = json.loads(r.stdout.strip().splitlines()[-1])
    res["compilers"] = peak[0]
    return res


def cmdlines() -> Iterator[str]:
    """The command lines of this machine's processes (arguments joined by spaces)."""
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            yield Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue


def _count_compilers(cache: str, stop: threading.Event, peak: list) -> None:
    """Most compiler processes at once whose command line names ``cache``."""
    while not stop.is_set():
        n = sum(1 for cmd in cmdlines()
                if cache in cmd and re.search(r"\b(cc1plus|nvcc|cicc)\b", cmd))  # fmt: skip
        peak[0] = max(peak[0], n)
        time.sleep(0.05)


def _settle(cache: str | Path, timeout: float = 600) -> None:
    """Wait until no kernel build for ``cache`` runs (detached builds outlive their run)."""
    mark = f"{cache}/kernels/"
    deadline = time.monotonic() + timeout
    quiet = 0
    while quiet < 3 and time.monotonic() < deadline:
        busy = any(mark in cmd for cmd in cmdlines())
        quiet = 0 if busy else quiet + 1
        time.sleep(0.2)


def warm_up(args, log, out, env) -> None:
    """Two runs, each followed by the kernel builds it started: then every kernel a run uses
    is in the cache (the estimator's, built by a first run; the noise estimate's forward model,
    requested by the first run that finds the estimator's)."""
    for _ in range(2):
        run_child("e2e", args.robot, log, out, args.device, env)
        _settle(env["TORCHCONTACT_CACHE"])


# ---------------------------------------------------------------------- modes
def median_of(runs: list) -> dict:
    """The median run (by seconds) of ``runs``, with ``all`` their seconds and ``compilers`` the
    most compilers any of them saw."""
    r = dict(sorted(runs, key=lambda x: x["seconds"])[len(runs) // 2])
    r["all"] = [round(x["seconds"], 3) for x in runs]
    r["compilers"] = max(x["compilers"] for x in runs)
    return r


def median_run(args, kind, log, out, extra="", env=None, watch=None):
    return median_of(
        [run_child(kind, args.robot, log, out, extra, env, watch) for _ in range(args.repeat)]
    )


#: :func:`interleaved_runs`: a spec whose runs each get a fresh, empty kernel cache.
FRESH_CACHE = "fresh cache"


def interleaved_runs(args, log, out, specs: dict) -> dict:
    """``args.repeat`` rounds of one run of each spec (``name: (kind, extra, env)``), in turn.

    A spec whose env is :data:`FRESH_CACHE` runs on an empty kernel cache of its own (a cold
    run), watched for compilers; the builds it leaves behind end before the next run starts.

    Returns:
        ``name ->`` its median run (:func:`median_of`), with ``runs``: every run, by round.
    """
    runs: dict = {name: [] for name in specs}
    for i in range(args.repeat):
        for name, (kind, extra, env) in specs.items():
            if env == FRESH_CACHE:
                cache = str(Path(out).parent / f"cache-cold-{time.time_ns()}-{i}")
                env_i = {**os.environ, "TORCHCONTACT_CACHE": cache}
                runs[name].append(run_child(kind, args.robot, log, out, extra, env_i, cache))
                _settle(cache)  # its builds go on after it: not into the next timing
            else:
                runs[name].append(run_child(kind, args.robot, log, out, extra, env))
    return {name: {**median_of(rs), "runs": rs} for name, rs in runs.items()}


def paired_ratio(rounds: dict, a: str, b: str) -> str:
    """Median over rounds of ``a``'s seconds / ``b``'s in the same round (drift cancels)."""
    pairs = zip(rounds[a]["runs"], rounds[b]["runs"], strict=True)
    r = [x["seconds"] / y["seconds"] for x, y in pairs]
    return f"{statistics.median(r):.2f}"


def help_seconds(n: int = 5) -> tuple[float, float]:
    """Median wall time of ``torchcontact --help`` and of ``python -c pass``."""
    exe = [sys.executable, "-m", "torchcontact.cli", "--help"]

    def wall(cmd):
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            subprocess.run(cmd, capture_output=True, check=True)
            ts.append(time.perf_counter() - t)
        return statistics.median(ts)

    return wall(exe), wall([sys.executable, "-c", "pass"])


def second_run_during_build(args, log, tmp) -> str:
    """A cold run; a second process on the same cache once the first's build has started."""
    cache = tempfile.mkdtemp(prefix="tc-cache-", dir=tmp)
    env = {**os.environ, "TORCHCONTACT_CACHE": cache}
    cmd = [sys.executable, "-m", "torchcontact.cli", "estimate", str(log), "--robot",
           robot_setup(args.robot)[0], "--quiet", "--out"]  # fmt: skip
    a = subprocess.Popen([*cmd, str(tmp / "race_a.parquet")], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and a.poll() is None:
        if list(Path(cache).glob("kernels/*/*.cpp")):
            break
        time.sleep(0.05)
    b = subprocess.run([*cmd, str(tmp / "race_b.parquet")], env=env, capture_output=True,
                       text=True)  # fmt: skip
    a.communicate()
    for p in ("race_a.parquet", "race_b.parquet"):
        (tmp / p).unlink(missing_ok=True)
    if b.returncode or a.returncode:
        return f"FAILED (rc {a.returncode}/{b.returncode}: {b.stderr.strip()[-300:]})"
    return "ran (exit 0, both)"


def mode_table(args, tmp: Path) -> None:
    log = write_log(args.robot, args.frames, tmp / f"{args.robot}{args.frames}.parquet")
    out = tmp / "out.parquet"
    warm_cache = str(tmp / "cache-warm")
    warm_env = {**os.environ, "TORCHCONTACT_CACHE": warm_cache}
    # the estimate table the floor writes, and the columns estimate reads
    warm_up(args, log, out, warm_env)
    est = tmp / "estimate.parquet"
    os.replace(out, est)
    import torchcontact as tc
    from torchcontact.logs.pipeline import prepare

    urdf, _, _ = robot_setup(args.robot)
    _, _, columns, _ = prepare(log, tc.RobotModel.from_urdf(urdf))
    Path(str(est) + ".columns").write_text(json.dumps(columns))

    # the warm runs in rounds (floor, this tree, the other tree, ...): this machine's speed
    # drifts by 10-20 % over minutes, which blocks of runs would read as differences
    specs = {
        "floor": ("floor", str(est), None),
        "floor-defaults": ("floor-defaults", str(est), None),
        "e2e": ("e2e", args.device, warm_env),
        "e2e-imported": ("e2e-imported", args.device, warm_env),
    }
    if args.compare_with:  # another checkout (e.g. the commit before), same log
        code = str(Path(args.compare_with).resolve())
        # its own cache: warm means the kernels that tree builds, not those this one adds
        env = {**warm_env, "PYTHONPATH": code, "TC_BENCH_CODE": code,
               "TORCHCONTACT_CACHE": str(tmp / "cache-compare")}  # fmt: skip
        warm_up(args, log, out, env)  # its kernels into the cache
        specs["base"] = ("e2e", args.device, env)
    # the cold runs in the same rounds: their ratio to the warm runs is read per round too
    specs["cold"] = ("e2e", args.device, FRESH_CACHE)
    rounds = interleaved_runs(args, log, out, specs)
    floor, floor_defaults = rounds["floor"], rounds["floor-defaults"]
    warm, warm_imported, base = rounds["e2e"], rounds["e2e-imported"], rounds.get("base")
    cold = rounds["cold"]
    inmem = median_run(args, "inmem", log, out, "", warm_env)
    second = second_run_during_build(args, log, tmp) if not args.no_race_build else "not run"
    helps, bare = help_seconds()
    n = floor["frames"]

    def fps(r):
        return n / r["seconds"]

    print(metadata())
    print(f"log: {log.name}, {n:,} frames, {log.stat().st_size / 1e6:.0f} MB, robot {args.robot},"
          f" {warm['slots']} slots; repeats {args.repeat}; load average at start"
          f" {os.getloadavg()[0]:.1f}")  # fmt: skip
    print()
    print("| run | seconds (median) | frames/s | CPU seconds | runs |")
    print("|---|---:|---:|---:|---|")
    rows = [
        ("pyarrow floor (read + write, the output's writer options)", floor),
        ("pyarrow floor, pyarrow's default writer options", floor_defaults),
        ("end to end, warm", warm),
        (
            "end to end, warm, pyarrow imported before the clock (as the floor)",
            warm_imported,
        ),
        ("end to end, cold (empty cache)", cold),
        ("in-memory kernel", inmem),
    ]
    if base is not None:
        rows.insert(2, (f"end to end, warm, {args.compare_with}", base))
    for label, r in rows:
        cpu = f"{r['cpu']:.2f}" if "cpu" in r else ""
        print(f"| {label} | {r['seconds']:.2f} | {fps(r):,.0f} | {cpu} | {r['all']} |")
    print(f"\n(floor: read {floor['read']:.2f} s + write {floor['write']:.2f} s)")
    print()
    ratio = floor["seconds"] / warm["seconds"]
    cpu_ratio = floor["cpu"] / warm["cpu"]
    paired = paired_ratio(rounds, "floor", "e2e")
    print("| goal | measured |")
    print("|---|---|")
    print(f"| end to end (warm) / pyarrow floor >= 0.8 | {ratio:.2f} (CPU: {cpu_ratio:.2f});"
          f" per round {paired} |")  # fmt: skip
    print(f"| end to end (warm, pyarrow imported first) / pyarrow floor |"
          f" {floor['seconds'] / warm_imported['seconds']:.2f}"
          f" (CPU: {floor['cpu'] / warm_imported['cpu']:.2f}) |")  # fmt: skip
    print(f"| end to end (warm) / pyarrow floor with pyarrow's defaults |"
          f" {floor_defaults['seconds'] / warm['seconds']:.2f}"
          f" (CPU: {floor_defaults['cpu'] / warm['cpu']:.2f}) |")  # fmt: skip
    first = cold["seconds"] / warm["seconds"]
    print(f"| first run (empty cache) / second run <= 1.5x | {first:.2f}x;"
          f" per round {paired_ratio(rounds, 'cold', 'e2e')}x |")  # fmt: skip
    print(f"| end to end (warm) / in-memory kernel | {inmem['seconds'] / warm['seconds']:.2f} |")
    if base is not None:
        print(f"| end to end (warm), this checkout vs {args.compare_with} |"
              f" {base['seconds'] / warm['seconds']:.2f}x faster"
              f" (CPU: {base['cpu'] / warm['cpu']:.2f}x); per round"
              f" {paired_ratio(rounds, 'base', 'e2e')}x |")  # fmt: skip
    print(f"| `torchcontact --help` <= 0.3 s | {helps:.3f} s (python -c pass: {bare:.3f} s) |")
    print(f"| a second run while the first one's kernel builds | {second} |")
    print(f"| compilers at once, cold run (one kernel per log) <= 1 | {cold['compilers']} |")


def mode_warm(args, tmp: Path) -> None:
    """The glue's CPU: floor, this tree and ``--compare-with`` alternated, warm, stage by stage."""
    log = write_log(args.robot, args.frames, tmp / f"{args.robot}{args.frames}.parquet")
    out = tmp / "out.parquet"
    cache = tmp / "cache-warm"
    env = {**os.environ, "TORCHCONTACT_CACHE": str(cache)}
    warm_up(args, log, out, env)  # every kernel in the cache; the reference: all compiled
    est = tmp / "estimate.parquet"
    os.replace(out, est)
    import torchcontact as tc
    from torchcontact.logs.pipeline import prepare

    urdf, _, _ = robot_setup(args.robot)
    _, _, columns, _ = prepare(log, tc.RobotModel.from_urdf(urdf))
    Path(str(est) + ".columns").write_text(json.dumps(columns))
    trees = {"this tree": env}
    if args.compare_with:
        code = str(Path(args.compare_with).resolve())
        trees[args.compare_with] = {**env, "PYTHONPATH": code, "TC_BENCH_CODE": code,
                                    "TORCHCONTACT_CACHE": str(tmp / "cache-compare")}  # fmt: skip
        warm_up(args, log, out, trees[args.compare_with])
    floors: list[dict] = []
    got: dict[str, list[dict]] = {k: [] for k in trees}
    equal = {k: True for k in trees}
    for _ in range(args.warm):
        floors.append(run_child("floor", args.robot, log, out, str(est)))
        for name, e in trees.items():
            r = run_child("stages", args.robot, log, out, str(est), e)
            got[name] += r["runs"]
            equal[name] &= r["equal"]
    n = floors[0]["frames"]
    per = 200_000 / n

    def med(xs):
        return statistics.median(xs)

    print(metadata())
    load = os.getloadavg()[0]
    print(f"log: {log.name}, {n:,} frames, robot {args.robot}; {args.warm} rounds (floor, then"
          f" each tree: one process, 2 warm runs); load average at the end {load:.1f}")  # fmt: skip
    print()
    names = list(trees)
    print("| measure (per 200 k frames, medians) | pyarrow floor | " + " | ".join(names) + " |")
    print("|---|---:|" + "---:|" * len(names))
    fl_s, fl_c = med([f["seconds"] for f in floors]), med([f["cpu"] for f in floors])
    print(
        f"| wall seconds | {fl_s * per:.2f} | "
        + " | ".join(f"{med([r['seconds'] for r in got[k]]) * per:.2f}" for k in names)
        + " |"
    )
    print(
        f"| CPU seconds (process) | {fl_c * per:.2f} | "
        + " | ".join(f"{med([r['cpu'] for r in got[k]]) * per:.2f}" for k in names)
        + " |"
    )
    print(
        "| warm / floor, wall (goal >= 0.8) | 1 | "
        + " | ".join(f"{fl_s / med([r['seconds'] for r in got[k]]):.2f}" for k in names)
        + " |"
    )
    print(
        "| warm / floor, CPU | 1 | "
        + " | ".join(f"{fl_c / med([r['cpu'] for r in got[k]]):.2f}" for k in names)
        + " |"
    )
    print("| output equal to the reference | | " + " | ".join(str(equal[k]) for k in names) + " |")
    print()
    print("| stage: thread CPU seconds per 200 k frames (medians) | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    stages = list(dict.fromkeys(s for k in names for r in got[k] for s in r["stages"]))
    for st in stages:
        cells = []
        for k in names:
            xs = [r["stages"][st] for r in got[k] if st in r["stages"]]
            cells.append(f"{med(xs) * per:.3f}" if xs else "-")
        print(f"| {st} | " + " | ".join(cells) + " |")


def mode_wait_rule(args, tmp: Path) -> None:
    """First runs (empty cache) that wait for the kernel against runs that go on eagerly while
    it builds, for several log lengths: the data behind WAIT_FOR_KERNEL_FRAMES."""
    print(metadata())
    print("| frames | waits for the kernel (s) | eager while it builds (s) | warm (s) |")
    print("|---:|---:|---:|---:|")
    for n in args.wait_rule:
        log = write_log(args.robot, n, tmp / f"{args.robot}{n}.parquet")
        out = tmp / "out.parquet"
        cells = []
        for wait in ("0", "never"):
            t = []
            for i in range(args.repeat):
                cache = str(tmp / f"cache-rule-{time.time_ns()}-{i}")
                env = {**os.environ, "TORCHCONTACT_CACHE": cache, "TC_BENCH_WAIT": wait}
                t.append(run_child("e2e", args.robot, log, out, args.device, env)["seconds"])
            cells.append(statistics.median(t))
        deadline = time.monotonic() + 600  # the last run's build may outlive it
        while not list(Path(cache).glob("kernels/*/*.so")) and time.monotonic() < deadline:
            time.sleep(0.5)
        warm = median_run(args, "e2e", log, out, args.device,
                          {**os.environ, "TORCHCONTACT_CACHE": cache})  # fmt: skip
        print(f"| {n:,} | {cells[0]:.1f} | {cells[1]:.1f} | {warm['seconds']:.1f} |", flush=True)


def mode_mem(args, tmp: Path) -> None:
    n0, n1 = args.mem
    rows = {}
    for n in (n0, n1):
        log = write_log(args.robot, n, tmp / f"{args.robot}{n}.parquet")
        rows[n] = median_run(args, "e2e", log, tmp / "out.parquet", args.device)
    print(metadata())
    print("| frames | seconds | frames/s | peak RSS (MB) |")
    print("|---:|---:|---:|---:|")
    for n, r in rows.items():
        print(f"| {n:,} | {r['seconds']:.1f} | {n / r['seconds']:,.0f} | {r['maxrss_mb']:.0f} |")
    print(f"\npeak RSS {n1:,} / {n0:,} frames (goal <= 1.2): "
          f"{rows[n1]['maxrss_mb'] / rows[n0]['maxrss_mb']:.2f}")  # fmt: skip


def _machine_cpu() -> float:
    """CPU seconds every process of this machine has used so far (``/proc/stat``): Ray's worker
    processes are no children of the command that drives them."""
    f = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq, steal = map(int, f[:8])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def mode_ray(args, tmp: Path) -> None:
    """Ray's scaling: the local engine and ``--engine ray`` with each ``--workers`` count.

    The kernel cache is filled on a short log of the same robot first (a warm-up on the whole log
    would cost a local run of it), so every timed run finds its kernels. Each row gives the wall
    time and the machine's busy cores during the run (``/proc/stat``: Ray's worker processes
    included), which bounds what more workers can gain: ``cores / busy cores of 1 worker``.
    """
    log = write_log(args.robot, args.ray, tmp / f"{args.robot}{args.ray}.parquet")
    small = write_log(args.robot, 200_000, tmp / f"{args.robot}200000.parquet")
    urdf, _, _ = robot_setup(args.robot)
    env = dict(os.environ)
    env.setdefault("TORCHCONTACT_CACHE", str(tmp / "cache"))
    warm_up(args, small, tmp / "out.parquet", env)  # the estimator's and the noise's kernels
    print(metadata())
    print(f"log: {log.name}, {args.ray:,} frames, {log.stat().st_size / 1e6:,.0f} MB;"
          f" {os.cpu_count()} logical CPUs")  # fmt: skip
    print("| engine | seconds | frames/s | vs local | busy cores |")
    print("|---|---:|---:|---:|---:|")

    def timed(run) -> tuple[float, float]:
        c0, t0 = _machine_cpu(), time.perf_counter()
        run()
        t = time.perf_counter() - t0
        return t, (_machine_cpu() - c0) / t

    local = None
    if not args.no_local:
        local, busy = timed(lambda: run_child("e2e", args.robot, log, tmp / "out.parquet",
                                              args.device, env))  # fmt: skip
        (tmp / "out.parquet").unlink(missing_ok=True)
        print(f"| local | {local:.1f} | {args.ray / local:,.0f} | 1.00 | {busy:.1f} |", flush=True)
    base = None
    spans = []  # (workers, epoch seconds at the command's start and end) of each Ray run
    phases = []  # (workers, the driver's phases from the run's summary)
    for w in args.workers:
        out = tmp / "ray.parquet"
        # the console script's entry (`torchcontact estimate`), which ends the process once the
        # output is published (no interpreter shutdown)
        cmd = [sys.executable, "-c", "from torchcontact.cli import console_main; console_main()",
               "estimate", str(log), "--robot", urdf, "--out", str(out), "--engine", "ray",
               "--workers", str(w), "--quiet", "--json", "--device", args.device]  # fmt: skip
        if args.keep_workers:  # a pool: a first run starts it, the timed runs find it warm
            cmd += ["--keep-workers", str(args.keep_workers)]
        t = []
        for _ in range(args.repeat + (1 if args.keep_workers else 0)):
            out.unlink(missing_ok=True)

            def one(cmd=cmd, w=w) -> None:
                e0 = time.time()
                r = subprocess.run(cmd, capture_output=True, text=True, env=env)
                if r.returncode:
                    raise RuntimeError(r.stderr[-2000:])
                spans.append((w, e0, time.time()))
                summary = json.loads(r.stdout)
                summary = summary[0] if isinstance(summary, list) else summary
                phases.append((w, summary.get("phases_s", {})))

            t.append(timed(one))
        label = f"ray, {w} workers"
        if args.keep_workers:
            (s0, busy0), t = t[0], t[1:]
            print(f"| {label}, the pool started | {s0:.1f} | {args.ray / s0:,.0f} | |"
                  f" {busy0:.1f} |", flush=True)  # fmt: skip
            label += ", warm pool"
            end = ("import ray; from torchcontact.logs._ray_boot import end_pool; ray.init("
                   "logging_level='ERROR'); print(end_pool(ray))")  # fmt: skip
            subprocess.run([sys.executable, "-c", end], env=env, timeout=120, capture_output=True)
        s, busy = sorted(t)[len(t) // 2]
        base = base or s
        vs_local = "" if local is None else f"{local / s:.2f} "
        print(f"| {label} | {s:.1f} | {args.ray / s:,.0f} | {vs_local}"
              f"(x{base / s:.1f} vs 1 worker) | {busy:.1f} |", flush=True)  # fmt: skip
    (tmp / "ray.parquet").unlink(missing_ok=True)
    print(
        "\nThe driver's phases (the summary's `phases_s`: seconds from the estimate's start, after"
        " the command's imports and Ray's connect):\n"
    )
    print("| workers | Ray started | log scanned | first unit done | published |")
    print("|---:|---:|---:|---:|---:|")
    for w, ph in phases:
        cells = [ph.get(k) for k in ("ray_started", "log_scanned", "first_unit_done", "published")]
        print(f"| {w} | " + " | ".join("" if c is None else f"{c:.2f}" for c in cells) + " |")
    if os.environ.get("RAY_ADDRESS"):  # a running cluster keeps its task events
        units = -(-args.ray // (8 * BATCH))  # the engine's default units
        code = f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); " \
            f"import pipeline; pipeline.ray_timelines({spans!r}, {units})"  # fmt: skip
        subprocess.run([sys.executable, "-c", code], env=env, timeout=120)


#: Ray's event names (their last dotted part) of the worker processes' warm-ups: the CLI's import
#: tasks and the model warm-ups, or a pool actor's (method events carry the method's name only).
WARM_UP_EVENTS = ("_import_engine", "_warm_worker", "imports", "warm")


def ray_timelines(spans, total_units: int) -> None:
    """Where each Ray run's seconds went, from Ray's task events (``ray.timeline()``).

    ``spans``: ``(workers, start, end)`` of each run, in epoch seconds. Printed, from the
    command's start: when the driver sent the first task (the workers' imports, or the model
    warm-ups), when the first of them ran (a worker process started), the first unit's start,
    the last unit's end, the run's end; and how busy the workers were between the first unit's
    start and the last one's end. Of ``total_units``, those whose events reached Ray (a worker
    ended with the job may not have sent its last ones, so "last unit ends" may be early).
    """
    import ray

    ray.init(address=os.environ["RAY_ADDRESS"], logging_level="ERROR", log_to_driver=False)
    time.sleep(3)  # the workers report their task events every second
    events = ray.timeline()
    print("| workers | warm-ups sent | first warm-up runs | first unit | last unit ends |"
          " run ends | units seen | unit s (median; mean) | workers busy | idle between a"
          " worker's units (median; total s) | a worker's first unit (last) |")  # fmt: skip
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for w, a, b in spans:
        ev = [e for e in events if a * 1e6 <= e.get("ts", 0) <= b * 1e6]

        def named(part, ev=ev, a=a):
            return [(e["ts"] / 1e6 - a, e.get("dur", 0) / 1e6) for e in ev
                    if part in e.get("name", "")]  # fmt: skip

        per_worker: dict = {}  # (node, worker) -> its units' (start, end), in order
        for e in ev:
            if "estimate_units" in e.get("name", ""):  # a task's or a pool actor's
                t = e["ts"] / 1e6 - a
                per_worker.setdefault((e.get("pid"), e.get("tid")), []).append(
                    (t, t + e.get("dur", 0) / 1e6)
                )
        idle = [b2 - e1 for us in per_worker.values() for (_, e1), (b2, _) in
                zip(sorted(us), sorted(us)[1:], strict=False)]  # fmt: skip
        starts = [min(us)[0] for us in per_worker.values()]

        sent = [t for t, _ in named("submit_task")]
        # the CLI's import tasks (or a new pool actor's imports), then the model warm-ups
        warm = [(e["ts"] / 1e6 - a, 0.0) for e in ev
                if e.get("name", "").split(".")[-1] in WARM_UP_EVENTS]  # fmt: skip
        units = named("estimate_units")
        if not units:
            print(f"| {w} | no task events |")
            continue
        first, last = min(t for t, _ in units), max(t + d for t, d in units)
        busy = sum(d for _, d in units) / (w * (last - first))
        print(f"| {w} | {min(sent, default=float('nan')):.2f} |"
              f" {min((t for t, _ in warm), default=float('nan')):.2f} | {first:.2f} |"
              f" {last:.2f} | {b - a:.2f} | {len(units)} of {total_units} |"
              f" {statistics.median(d for _, d in units):.2f};"
              f" {statistics.mean(d for _, d in units):.2f} | {busy:.0%} |"
              f" {statistics.median(idle) if idle else 0:.3f}; {sum(idle):.1f} |"
              f" {max(starts):.2f} |")  # fmt: skip


def mode_race(args, tmp: Path) -> None:
    """Two CLI runs on one output, the second with --resume while the first runs.

    The second process is started first and imports everything, then waits for the first one to
    hold the output (its progress file appears) before it runs ``main``: the two really overlap.
    An output is corrupt when it does not read back with the reference's rows: the same ``t_ns``
    and statuses, and values within 1e-9 (a run may use the eager backend while the kernel
    builds, or the kernel).
    """
    import pyarrow.parquet as pq

    log = write_log(args.robot, args.race_frames, tmp / f"{args.robot}{args.race_frames}.parquet")
    urdf, _, _ = robot_setup(args.robot)
    common = ["estimate", str(log), "--robot", urdf, "--quiet", "--batch-size", "2048", "--out"]
    ref = tmp / "race_ref.parquet"
    cli = [sys.executable, "-m", "torchcontact.cli"]
    subprocess.run([*cli, *common, str(ref)], check=True, capture_output=True)
    want = pq.read_table(ref)
    refused = corrupt = 0
    for i in range(args.race):
        out, flag = tmp / "race.parquet", tmp / f"race-go-{i}"
        out.unlink(missing_ok=True)
        second = (
            "import pathlib, sys, time\n"
            "from torchcontact.cli import main\n"
            "import torchcontact.logs.pipeline\n"
            f"while not pathlib.Path({str(flag)!r}).exists():\n"
            "    time.sleep(0.005)\n"
            f"sys.exit(main({[*common, str(out), '--resume']!r}))\n"
        )
        b = subprocess.Popen([sys.executable, "-c", second], stderr=subprocess.PIPE, text=True,
                             stdout=subprocess.DEVNULL)  # fmt: skip
        a = subprocess.Popen([*cli, *common, str(out)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE)  # fmt: skip
        side = tmp / "race.parquet.progress.json"
        while a.poll() is None and not side.exists():
            time.sleep(0.005)
        flag.touch()
        _, b_err = b.communicate()
        a.communicate()
        flag.unlink()
        if b.returncode == 1 and "another process is writing it" in b_err:
            refused += 1
        try:
            got = pq.read_table(out)
            ok = got["t_ns"].equals(want["t_ns"]) and got["status"].equals(want["status"])
            for c in [c for c in want.column_names if c.startswith("residual.")]:
                ok &= bool(np.allclose(got[c].to_numpy(), want[c].to_numpy(), rtol=0, atol=1e-9,
                                       equal_nan=True))  # fmt: skip
            jt = [np.stack(t["joint_torques"].to_numpy(zero_copy_only=False)) for t in (got, want)]
            ok &= bool(np.allclose(*jt, rtol=0, atol=1e-9, equal_nan=True))
        except Exception:
            ok = False
        corrupt += not ok
    print(metadata())
    print(f"| two runs on one output, the second with --resume ({args.race} tries) | refused "
          f"{refused} | corrupt outputs {corrupt} |")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", choices=["icub", "tcarm"], default="icub")
    ap.add_argument("--frames", type=int, default=1_000_000, help="frames of the log")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each timing (median)")
    ap.add_argument("--device", default="cpu", help="estimate --device")
    ap.add_argument("--tmp", default=None, help="folder for logs and caches (kept; reused)")
    ap.add_argument("--no-race-build", action="store_true", help="skip the second-run check")
    ap.add_argument(
        "--compare-with",
        metavar="CHECKOUT",
        help="another source tree (e.g. `git worktree add /tmp/old 4b41f9f`): its warm end to"
        " end on the same log, in the same run",
    )
    ap.add_argument("--mem", type=int, nargs=2, help="peak RSS of two log lengths")
    ap.add_argument(
        "--warm",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="the glue's CPU per stage, warm, alternating the floor, this tree and --compare-with",
    )
    ap.add_argument(
        "--wait-rule",
        type=int,
        nargs="+",
        metavar="FRAMES",
        help="first runs that wait for the kernel vs eager while it builds, per log length",
    )
    ap.add_argument("--ray", type=int, default=0, help="frames of the Ray comparison")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--no-local", action="store_true", help="Ray runs only (no local engine)")
    ap.add_argument(
        "--keep-workers", type=float, default=0.0, help="Ray runs on a worker pool (RAY_ADDRESS)"
    )
    ap.add_argument("--race", type=int, default=0, help="tries of two runs on one output")
    ap.add_argument("--race-frames", type=int, default=200_000)
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        return child(*a.child)
    tmp = Path(a.tmp or tempfile.mkdtemp(prefix="tc-bench-"))
    tmp.mkdir(parents=True, exist_ok=True)
    if a.mem:
        return mode_mem(a, tmp)
    if a.warm:
        return mode_warm(a, tmp)
    if a.wait_rule:
        return mode_wait_rule(a, tmp)
    if a.ray:
        return mode_ray(a, tmp)
    if a.race:
        return mode_race(a, tmp)
    return mode_table(a, tmp)


if __name__ == "__main__":
    main()
