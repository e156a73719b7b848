"""``--engine ray`` on a local two-node cluster (``ray.cluster_utils.Cluster``): the local
engine's rows and summary, qd/qdd derived across unit edges, a worker killed mid-run, a driver
killed mid-run then ``--resume``, the refusals. One cluster and one small log for the module."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

ray = pytest.importorskip("ray")
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    c.add_node(num_cpus=1)  # a second node: one task on each
    c.wait_for_nodes()
    ray.init(address=c.address, log_to_driver=False, logging_level="ERROR")
    yield c
    ray.shutdown()
    c.shutdown()


@pytest.fixture(scope="module")
def small_groups(sim_log_q_only, tmp_path_factory):
    """The q-only simulated log in row groups of 100 frames (units cut through them)."""
    path = tmp_path_factory.mktemp("ray") / "q.parquet"
    pq.write_table(pq.read_table(sim_log_q_only), path, row_group_size=100)
    return path


@pytest.fixture(scope="module")
def local(model, small_groups, tmp_path_factory):
    from torchcontact.logs import estimate_file

    out = tmp_path_factory.mktemp("local") / "local.parquet"
    return estimate_file(small_groups, model, out, batch_size=64)


KW = dict(batch_size=64, task_rows=200, workers=2)  # 3 units, one task per node at a time


def _same_rows(a, b):
    assert a["t_ns"].equals(b["t_ns"]) and a["status"].equals(b["status"])
    assert a.schema.metadata == b.schema.metadata
    # one slot layout for the log, so the same program (the summaries' "slots" are compared where
    # there is one); the engines' processes may run it on different CPU backends (compiled
    # kernel, tape VM, eager, as their kernel caches stand), which differ by rounding only
    np.testing.assert_allclose(
        np.stack(a["joint_torques"].to_numpy(zero_copy_only=False)),
        np.stack(b["joint_torques"].to_numpy(zero_copy_only=False)), rtol=1e-11, atol=1e-11,
    )  # fmt: skip
    fa = [c["force"] for row in a["contacts"].to_pylist() for c in row]
    fb = [c["force"] for row in b["contacts"].to_pylist() for c in row]
    np.testing.assert_allclose(fa, fb, rtol=1e-11, atol=1e-11)


def _task_pids(what: bytes = b"_estimate_units"):
    """Ray worker processes running one of our units now (their title names the task)."""
    pids = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if cmd.startswith(b"ray::") and what in cmd:
                pids.append(int(pid))
    return pids


def test_two_nodes_same_rows_and_summary_as_local(cluster, small_groups, local, tmp_path, capfd):
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    # a unit goes where a warm-up has ended: while one node's process still imports torch or
    # builds the model (a loaded machine), the other may run every unit of 200 frames. Runs
    # until one ran units on both nodes (the first run starts the processes); each run gives
    # the local engine's rows
    nodes = []
    for k in range(4):
        capfd.readouterr()
        r = estimate_file_ray(small_groups, tcarm_path(), tmp_path / f"ray{k}.parquet", **KW)
        err = capfd.readouterr().err
        assert "INFO" not in err and "WARNING" not in err  # no Ray log lines, one progress bar
        _same_rows(pq.read_table(r["output"]), pq.read_table(local["output"]))
        nodes.append(r["nodes"])
        if r["nodes"] == 2:
            break
    assert nodes[-1] == 2, nodes  # the units ran on both nodes
    assert set(r) == set(local) | {"nodes", "phases_s"} and r["engine"] == "ray"
    assert r["chunks"] == 3
    ph = r["phases_s"]  # the driver's phases, in order
    assert list(ph) == ["ray_started", "log_scanned", "first_unit_done", "published"]
    assert 0 <= ph["ray_started"] <= ph["first_unit_done"] <= ph["published"] == r["seconds"]
    assert ph["log_scanned"] <= ph["first_unit_done"]
    for k in ("frames", "processed_now", "ok_now", "bad_now", "sensors", "derived", "slots"):
        assert r[k] == local[k], k
    assert r["derived"] == ["qd", "qdd"]  # derived across the edges of the units
    _same_rows(pq.read_table(r["output"]), pq.read_table(local["output"]))


def test_a_task_on_one_cpu_writes_the_part_of_a_task_on_three(cluster, small_groups, tmp_path):
    """A task that Ray gives one CPU decodes, estimates and encodes in turn; with 2 or more it
    overlaps them on threads: the same unit's part, byte for byte, either way."""
    from torchcontact.logs.derive import DEFAULT_HALF_WINDOW
    from torchcontact.logs.pipeline import load_robot, log_noise, prepare
    from torchcontact.logs.ray_engine import _estimate_units, plan_units
    from torchcontact.logs.ray_worker import unit_config
    from torchcontact.robots import RobotSpec

    spec = RobotSpec.of("tcarm")
    model = load_robot(spec)
    pf, le, columns, _ = prepare(small_groups, model, None, None, None, None, None)
    log_noise(pf, le, columns, DEFAULT_HALF_WINDOW, None, False, str(small_groups))
    parts = []
    for cpus in (1, 3):
        options = dict(batch_size=64, half_window=DEFAULT_HALF_WINDOW, backend="auto", threads=1,
                       device="cpu", dtype="float64", cpus=cpus)  # fmt: skip
        partial = tmp_path / f"cpus{cpus}"
        partial.mkdir()
        config = unit_config(small_groups, spec, model, le, plan_units(600, 200), columns,
                             partial, None, options)  # fmt: skip
        r = _estimate_units([1], config)  # rows 200-399: context on both sides
        assert r["units"] == [1] and r["rows"] == [200]
        parts.append((partial / "part-00000001.parquet").read_bytes())
    assert parts[0] == parts[1]
    assert pq.read_table(pa.BufferReader(parts[0])).num_rows == 200


def _killing_one(what: bytes, run):
    """``run()`` while a thread SIGKILLs the first Ray worker process that runs a unit (its title
    names ``what``); asserts that one was killed."""
    killed, done = [], threading.Event()

    def killer():
        while not done.is_set() and not killed:
            for pid in _task_pids(what):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                break
            time.sleep(0.002)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    try:
        result = run()
    finally:
        done.set()
        t.join()
    assert killed, "no unit was running to be killed"
    return result


def test_a_killed_worker_costs_a_retry_not_the_run(cluster, small_groups, local, tmp_path):
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    kw = dict(KW, batch_size=32)  # several chunks per unit: a unit takes a while
    r = _killing_one(b"_estimate_units", lambda: estimate_file_ray(
        small_groups, tcarm_path(), tmp_path / "k.parquet", **kw))  # fmt: skip
    assert r["frames"] == 600 and r["processed_now"] == 600
    _same_rows(pq.read_table(r["output"]), pq.read_table(local["output"]))


def _our_actors():
    """The live actors of this code's worker pool, by name."""
    from torchcontact.logs._ray_boot import pool_actors

    return set(pool_actors(ray))


def test_a_worker_pool_outlives_its_run(cluster, small_groups, local, tmp_path):
    """``keep_workers``: the units go to detached actors, which the next runs find with the
    model built (reused; the second a console-script process that ends without Ray's shutdown),
    with the local rows each time; an actor killed during a unit is
    replaced and its units go again (the same rows); idle actors end by themselves after the
    seconds given, and with them their CPUs (the other tests' tasks need them)."""
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    kw = dict(KW, batch_size=32)  # units of 256 frames in chunks of 32: a unit takes a while
    try:
        a = estimate_file_ray(small_groups, tcarm_path(), tmp_path / "a.parquet",
                              keep_workers=120, **kw)  # fmt: skip
        assert a["pool"] == {"workers": 2, "reused": 0} and len(_our_actors()) == 2
        _same_rows(pq.read_table(a["output"]), pq.read_table(local["output"]))
        first = _our_actors()
        # the console script joined to the cluster finds them too, imports no torch (an actor
        # ran the setup), and ends without Ray's shutdown (the cluster ends its job): the actors
        # stay for the next run
        entry = "from torchcontact.cli import console_main; console_main()"
        r = subprocess.run(
            [sys.executable, "-X", "importtime", "-c", entry, "estimate", str(small_groups), "--out",
             str(tmp_path / "b.parquet"), "--engine", "ray", "--workers", "2", "--batch-size",
             "32", "--keep-workers", "120", "--quiet", "--json"],
            env={**os.environ, "RAY_ADDRESS": cluster.address, "PYTHONPATH": str(ROOT)},
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        imported = {line.rsplit("|", 1)[1].strip() for line in r.stderr.splitlines()
                    if line.startswith("import time:")}  # fmt: skip
        assert "ray" in imported and "torchcontact.logs.ray_engine" in imported
        assert "torch" not in imported and "torchcontact.logs.ray_worker" not in imported
        b = json.loads(r.stdout)
        assert b["pool"] == {"workers": 2, "reused": 2} and _our_actors() == first
        _same_rows(pq.read_table(b["output"]), pq.read_table(local["output"]))

        c = _killing_one(b"PoolWorker.estimate_units", lambda: estimate_file_ray(
            small_groups, tcarm_path(), tmp_path / "c.parquet", keep_workers=1, **kw))  # fmt: skip
        assert c["frames"] == c["processed_now"] == 600 and c["pool"]["workers"] == 2
        _same_rows(pq.read_table(c["output"]), pq.read_table(local["output"]))
        assert _our_actors() != first  # the killed one was replaced
        deadline = time.monotonic() + 60  # idle for 1 s: they end
        while _our_actors() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _our_actors()
    finally:
        from torchcontact.logs._ray_boot import end_pool

        end_pool(ray)  # a failed check's actors: their CPUs free for the other tests


@pytest.mark.parametrize("keep", [0, 2])
def test_a_killed_driver_resumes(cluster, model, small_groups, local, tmp_path, keep):
    """A driver killed mid-run, then ``--resume``: the local rows. With a worker pool
    (``keep``), the killed driver's actors outlive it and may still write its queued units while
    the resumed run writes them again: the same rows, and no stray folder after the run."""
    from torchcontact.logs._ray_boot import end_pool
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    out = tmp_path / "d.parquet"
    # units of about 8 x --batch-size = 256 frames, as many as a multiple of the 2 workers: 4
    # units of 150 frames
    cmd = [sys.executable, "-m", "torchcontact.cli", "estimate", str(small_groups), "--out",
           str(out), "--engine", "ray", "--workers", "2", "--batch-size", "32", "--quiet",
           "--keep-workers", str(keep)]  # fmt: skip
    env = {**os.environ, "RAY_ADDRESS": cluster.address, "PYTHONPATH": str(ROOT)}
    driver = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    partial = tmp_path / "d.parquet.partial"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and driver.poll() is None:
        if list(partial.glob("part-*.parquet")):
            break
        time.sleep(0.005)
    if driver.poll() is not None:
        pytest.fail(f"the driver ended before it could be killed: {driver.communicate()}")
    driver.kill()  # SIGKILL
    driver.wait()
    assert not out.exists() and partial.is_dir()
    sidecar = json.loads((tmp_path / "d.parquet.progress.json").read_text())
    assert sidecar["engine"] == "ray" and sidecar["task_rows"] == 150
    try:
        r = estimate_file_ray(small_groups, tcarm_path(), out, batch_size=32, workers=2,
                              resume=True, keep_workers=keep)  # fmt: skip
        assert r["resumed_chunks"] >= 1 and r["frames"] == 600 and r["chunks"] == 4
        assert not partial.exists()
        _same_rows(pq.read_table(out), pq.read_table(local["output"]))
        if keep:  # the actors end idle; a late part of the killed driver made no folder
            deadline = time.monotonic() + 60
            while _our_actors() and time.monotonic() < deadline:
                time.sleep(0.2)
            assert not _our_actors() and not partial.exists()
    finally:
        end_pool(ray)


def test_ray_engine_resume_refusals(cluster, small_groups, tmp_path, monkeypatch):
    from torchcontact.logs import LogError
    from torchcontact.logs import format as pl
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    out = tmp_path / "r.parquet"

    def crash(self, *a, **k):  # killed after every unit, before the output is complete
        raise KeyboardInterrupt

    monkeypatch.setattr(pl.PartsWriter, "close", crash)
    with pytest.raises(KeyboardInterrupt):
        estimate_file_ray(small_groups, tcarm_path(), out, **KW)
    monkeypatch.undo()
    # every unit is in r.parquet.tmp (recorded in the journal), the footer not written
    assert not out.exists() and (tmp_path / "r.parquet.tmp").exists()
    with pytest.raises(LogError, match="pass --resume"):
        estimate_file_ray(small_groups, tcarm_path(), out, **KW)
    with pytest.raises(LogError, match="other inputs or options"):
        estimate_file_ray(small_groups, tcarm_path(), out, batch_size=32, resume=True)
    s = estimate_file_ray(small_groups, tcarm_path(), out, resume=True, **KW)
    assert s["resumed_chunks"] == 3 and s["processed_now"] == 0 and s["frames"] == 600
    # the default units (a multiple of the workers: 4 for 2) kept by a resume with 1 worker
    out = tmp_path / "d.parquet"
    monkeypatch.setattr(pl.PartsWriter, "close", crash)
    with pytest.raises(KeyboardInterrupt):
        estimate_file_ray(small_groups, tcarm_path(), out, batch_size=16, workers=2)
    monkeypatch.undo()
    s = estimate_file_ray(small_groups, tcarm_path(), out, batch_size=16, workers=1, resume=True)
    assert s["resumed_chunks"] == s["chunks"] == 6 and s["processed_now"] == 0


def test_a_mistake_the_setup_finds_reads_as_itself(cluster, small_groups, tmp_path):
    """The driver builds no model: a mistake only the model or the log shows (a sensor the log
    lacks) is found by the setup's worker, and reaches the user as the local engine says it,
    with nothing left behind."""
    from torchcontact.errors import TorchContactError
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.robots import tcarm_path

    out = tmp_path / "o.parquet"
    with pytest.raises(TorchContactError, match=r"no column for sensors \['nope'\]") as err:
        estimate_file_ray(small_groups, tcarm_path(), out, sensors=["nope"], **KW)
    assert "Ray" not in type(err.value).__name__  # the library's error, not Ray's wrapper
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_ray_engine_refuses_what_it_cannot_do(model, sim_log, tmp_path, capsys, monkeypatch):
    import torch

    from torchcontact._lock import OutputLock
    from torchcontact.cli import main
    from torchcontact.errors import OutputBusyError
    from torchcontact.logs import LogError
    from torchcontact.logs.ray_engine import estimate_file_ray
    from torchcontact.residual import FeatureSpec, ResidualCorrection, ResidualGRU
    from torchcontact.robots import tcarm_path

    spec = FeatureSpec.default(model, "base_ft")
    torch.manual_seed(0)
    stack = ResidualCorrection(
        model, "base_ft", learned=ResidualGRU(len(spec.names(model)), 4), features=spec
    )
    gru = stack.save(tmp_path / "gru")
    with pytest.raises(LogError, match="cannot use a recurrent"):
        estimate_file_ray(sim_log, tcarm_path(), tmp_path / "o.parquet", residual=gru)
    from torchcontact.logs import _ray_boot

    out = str(tmp_path / "o.parquet")
    booted = len(_ray_boot._booting)  # runs refused before Ray's start-up start no task
    assert main(["estimate", str(sim_log), "--out", out, "--engine", "ray", "--workers", "0"]) == 2
    assert "--workers must be an integer >= 1" in capsys.readouterr().err
    assert (
        main(["estimate", str(sim_log), "--out", out, "--engine", "ray", "--worker-cpus", "0"]) == 2
    )
    assert "--worker-cpus must be a number > 0, got 0.0" in capsys.readouterr().err
    assert main(["estimate", str(sim_log), "--out", out, "--worker-cpus", "2"]) == 2
    assert "--worker-cpus applies to --engine ray only" in capsys.readouterr().err
    assert main(["estimate", str(sim_log), "--out", out, "--keep-workers", "60"]) == 2
    assert "--keep-workers applies to --engine ray only" in capsys.readouterr().err
    keep = ["estimate", str(sim_log), "--out", out, "--engine", "ray", "--keep-workers"]
    assert main([*keep, "-1"]) == 2
    assert "--keep-workers must be seconds >= 0, got -1.0" in capsys.readouterr().err
    from torchcontact.logs import ray_engine

    with monkeypatch.context() as m:  # no cluster running apart from the command: refused
        m.setattr(_ray_boot, "running_cluster", lambda: False)
        m.setattr(ray_engine, "running_cluster", lambda: False)
        assert main([*keep, "60"]) == 2
    assert "--keep-workers needs a running Ray cluster (set RAY_ADDRESS" in capsys.readouterr().err
    missing = str(tmp_path / "missing.parquet")
    assert main(["estimate", missing, "--out", out, "--engine", "ray"]) == 1
    assert "missing.parquet" in capsys.readouterr().err
    assert main(["estimate", str(sim_log), "--out", out, "--engine", "ray", "--track-bias"]) == 2
    assert "--track-bias applies to --engine local only" in capsys.readouterr().err
    assert len(_ray_boot._booting) == booted
    with monkeypatch.context() as m:  # an install without the ray extra: its name, at once
        m.setitem(sys.modules, "ray", None)
        assert main(["estimate", str(sim_log), "--out", out, "--engine", "ray"]) == 1
    err = capsys.readouterr().err
    assert "needs ray, which is not installed: pip install 'torchcontact[ray]'" in err
    with OutputLock(out), pytest.raises(OutputBusyError, match="another process is writing"):
        estimate_file_ray(sim_log, tcarm_path(), out, resume=True)  # before Ray starts


def test_a_declared_ft_sensor_reaches_the_workers(cluster, tmp_path, capsys):
    """``--ft-sensor`` with ``--engine ray``: every worker builds the robot with the declared
    sensor (and checks its identity against the driver's); the rows equal the local engine's."""
    from torchcontact.cli import main
    from torchcontact.logs import estimate_file, write_simulated_log
    from torchcontact.robots import RobotSpec

    decl = ["wrist_ft:hand_skin"]  # tcarm declares base_ft only
    spec = RobotSpec.of("tcarm", decl)
    log = write_simulated_log(spec.load(), 300, tmp_path / "w.parquet", seed=5, robot="tcarm",
                              ft_sensors=decl, sensor="wrist_ft", links=["hand_skin"])  # fmt: skip
    local = estimate_file(log, spec, tmp_path / "local.parquet", batch_size=16)
    out = tmp_path / "ray.parquet"
    argv = ["estimate", str(log), "--out", str(out), "--robot", "tcarm", "--ft-sensor", decl[0],
            "--engine", "ray", "--workers", "2", "--batch-size", "16", "--quiet", "--json"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    r = json.loads(capsys.readouterr().out)
    # units of 8 chunks of 16 frames, their count rounded up to a multiple of the 2 workers: 4
    assert r["sensors"] == ["wrist_ft"] and r["chunks"] == 4 and r["ok_now"] == 300
    # the CLI started the workers' imports before its own (two import tasks, both ended)
    from torchcontact.logs import _ray_boot

    assert len(_ray_boot._booting) >= 2 and ray.get(_ray_boot._booting[-2:]) == [None, None]
    _same_rows(pq.read_table(out), pq.read_table(local["output"]))


def test_a_worker_whose_robot_differs_from_the_drivers_stops_the_run():
    """The identity check of ``_worker_state`` (in-process): a worker building tcarm without the
    driver's declared sensor (another URDF on its node, say) names the difference."""
    from torchcontact.logs import LogError
    from torchcontact.logs.ray_worker import _worker_state
    from torchcontact.robots import RobotSpec

    driver = RobotSpec.of("tcarm", ["wrist_ft:hand_skin"]).load().identity
    robot = {"robot": "tcarm", "ft_sensors": [], "identity": driver.sha256,
             "identity_entries": driver.to_json()}  # fmt: skip
    job = {"threads": 0, "dtype": "float64", "device": "cpu"}
    with pytest.raises(LogError, match=r"Ray worker on .* built robot tcarm unlike the driver's: "):
        _worker_state("unused.parquet", robot, {}, job)


def test_the_setup_worker_must_have_read_the_drivers_robot(tmp_path):
    """The driver builds no model: the worker that ran the setup must have built the robot the
    driver's URDF describes. The same text passes as it is; another text passes when it
    describes the same robot (a reformatted copy on that node) and stops the run otherwise,
    naming the difference."""
    from torchcontact.logs import LogError
    from torchcontact.logs.ray_engine import _check_robot, _urdf_sha256
    from torchcontact.robots import RobotSpec, tcarm_path

    spec = RobotSpec.of("tcarm", ["wrist_ft:hand_skin"])
    model = spec.load()

    def setup(model, sha):
        robot = {"identity": model.identity.sha256, "identity_entries": model.identity.to_json()}
        return {"ident": {"urdf_sha256": sha}, "config": ("log", robot, {}, {})}

    assert _urdf_sha256(spec) == model.urdf_sha256
    _check_robot(spec, model.urdf_sha256, setup(model, model.urdf_sha256))
    _check_robot(spec, model.urdf_sha256, setup(model, "another copy of the text"))
    text = tcarm_path().read_text()
    copy = tmp_path / "copy.urdf"  # the same robot, written differently
    copy.write_text(text.replace("<robot", "<robot ", 1) + "<!-- a copy -->\n")
    assert _urdf_sha256(RobotSpec.of(copy)) != model.urdf_sha256
    copied = RobotSpec.of(copy, ["wrist_ft:hand_skin"])
    _check_robot(copied, _urdf_sha256(copied), setup(model, "x"))
    other = RobotSpec.of("tcarm").load()  # without the declared sensor
    with pytest.raises(LogError, match=r"worker that scanned the log built robot tcarm --ft-sensor"
                       r" wrist_ft:hand_skin unlike the driver's: .*wrist_ft"):  # fmt: skip
        _check_robot(spec, model.urdf_sha256, setup(other, other.urdf_sha256 + "x"))


def test_units_fill_the_last_round():
    """By default the units' count is a multiple of the workers (every worker busy in the last
    round), about 8 chunks each (a resume keeps its run's: test_ray_engine_resume_refusals)."""
    from torchcontact.logs.ray_engine import default_task_rows, plan_units

    for rows, bs, workers in ((12_000_000, 8192, 16), (1_000_000, 8192, 3), (300, 16, 2),
                              (65_536 * 16, 8192, 16), (7, 8192, 4)):  # fmt: skip
        units = plan_units(rows, default_task_rows(rows, bs, workers))
        assert len(units) % workers == 0 or len(units) == rows  # one frame a unit at the least
        assert units[-1][1] == rows and all(b - a <= 8 * bs for a, b in units)
        assert len(units) < -(-rows // (8 * bs)) + workers  # at most workers - 1 more units


def test_the_device_is_the_clusters():
    """``auto`` is CUDA where the cluster has a GPU (not where the driver has one); ``cuda`` on a
    cluster without a GPU is refused in the user's words."""
    from torchcontact.errors import InputError
    from torchcontact.logs._ray_boot import cluster_device

    class Cluster:
        def __init__(self, gpus):
            self.gpus = gpus

        def cluster_resources(self):
            return {"CPU": 16.0, **({"GPU": self.gpus} if self.gpus else {})}

    assert cluster_device(Cluster(0), "auto") == "cpu"
    assert cluster_device(Cluster(2), "auto") == "cuda"
    assert cluster_device(Cluster(2), "cpu") == "cpu"
    assert cluster_device(Cluster(1), "cuda:0") == "cuda:0"
    with pytest.raises(InputError, match="--device cuda: the Ray cluster has no GPU"):
        cluster_device(Cluster(0), "cuda")
    with pytest.raises(InputError, match="--device tpu: expected auto, cpu or cuda"):
        cluster_device(Cluster(0), "tpu")


def test_the_workers_allocators_are_set_as_the_clis(cluster, monkeypatch):
    """A worker process keeps freed memory as the CLI's does (a unit of 65,536 iCub frames took
    0.36 s instead of 0.47 s, 2-core machine): the runtime environment a driver joins a cluster
    with sets mimalloc's variable before pyarrow loads, and each worker sets glibc's options."""
    from torchcontact.logs import _ray_boot

    def probe():
        from torchcontact.logs import _alloc
        from torchcontact.logs.ray_worker import _worker_threads

        _worker_threads({"threads": 1, "cpus": 1})
        return os.environ.get("MIMALLOC_PURGE_DELAY"), bool(_alloc._set)

    assert ray.get(ray.remote(probe).remote()) == ("-1", True)
    seen = {}
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", lambda **kw: seen.update(kw))
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    _ray_boot.ensure_ray(None)
    env = seen["runtime_env"]["env_vars"]
    assert env["MIMALLOC_PURGE_DELAY"] == "-1" and str(ROOT) in env["PYTHONPATH"].split(os.pathsep)
