"""``torchcontact run --onnx GRAPH --log LOG``: a recorded log replayed through the exported
estimator frame by frame gives the forces and torques of ``torchcontact estimate`` on that log
(logged and derived ``qd``/``qdd``), every contact record in the slot the file has for it."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from torchcontact.cli import main

pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def graph(model, sim_log, tmp_path_factory):
    """The estimator exported (float64) with the log's own slot layout."""
    from torchcontact.export import export_estimator
    from torchcontact.logs.pipeline import prepare

    layout = prepare(sim_log, model)[1].layout
    path = tmp_path_factory.mktemp("replay") / "tcarm.onnx"
    export_estimator(model, ["base_ft"], list(layout.links), list(layout.kinds), path,
                     dtype=torch.float64)  # fmt: skip
    return path


def _replay(argv, capsys):
    assert main(argv) == 0
    out = capsys.readouterr()
    summary = json.loads(out.err.strip().splitlines()[-1])["summary"]
    return [json.loads(line) for line in out.out.splitlines()], summary


@pytest.mark.parametrize("which", ["sim_log", "sim_log_q_only"])
def test_replay_equals_estimate(which, graph, request, tmp_path, capsys):
    log = request.getfixturevalue(which)
    est = tmp_path / "est.parquet"
    # unweighted: the exported graph solves the paper's pinv (no --ft-noise at export)
    assert main(["estimate", str(log), "--out", str(est), "--quiet", "--unweighted"]) == 0
    capsys.readouterr()
    frames = tmp_path / "frames.parquet"  # --out: the frames' readings, as run writes them
    argv = ["run", "--onnx", str(graph), "--log", str(log), "--out", str(frames)]
    recs, summary = _replay(argv, capsys)
    assert pq.read_table(frames)["t_ns"].to_pylist() == [r["t_ns"] for r in recs]
    tab = pq.read_table(est).to_pydict()
    n = len(tab["t_ns"])
    assert len(recs) == n == 600 and summary["frames"] == summary["published"] == n
    assert summary["log_errors"] == summary["estimator_errors"] == 0
    assert summary["records_without_slot"] == {}
    assert summary["derived"] == ([] if which == "sim_log" else ["qd", "qdd"])
    assert [r["t_ns"] for r in recs] == tab["t_ns"] and [r["row"] for r in recs] == list(range(n))
    got, want, placed = [], [], 0
    for r, contacts, status in zip(recs, tab["contacts"], tab["status"], strict=True):
        e = r["estimate"]
        assert e["status"] == 0 and status == "ok"
        assert len(r["record_slots"]) == len(contacts)
        for k, c in zip(r["record_slots"], contacts, strict=True):
            got.append(e["force"][k])
            want.append(c["force"])
            placed += 1
    assert placed == sum(len(c) for c in tab["contacts"]) > 100
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)  # N
    tau = np.array([r["estimate"]["joint_torques"] for r in recs])
    np.testing.assert_allclose(tau, np.stack(tab["joint_torques"]), rtol=0, atol=1e-8)  # N m


def test_replay_refusals(graph, sim_log, capsys):
    assert main(["run", "--log", str(sim_log)]) == 2  # no exported estimator
    assert "give --onnx or --c-step" in capsys.readouterr().err
    argv = ["run", "--onnx", str(graph), "--log", str(sim_log), "--joints", "udp://127.0.0.1:9"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --joints: not with --log")


def test_records_without_a_slot_are_counted_and_named(model, sim_log, tmp_path, capsys):
    """A file without a slot for some records: those records get null, the summary names them."""
    from torchcontact.export import export_estimator
    from torchcontact.logs.pipeline import prepare

    layout = prepare(sim_log, model)[1].layout
    assert len(layout.links) == 2
    path = tmp_path / "one_slot.onnx"
    export_estimator(model, ["base_ft"], [layout.links[0]], [layout.kinds[0]], path)
    recs, summary = _replay(["run", "--onnx", str(path), "--log", str(sim_log)], capsys)
    left = sum(r["record_slots"].count(None) for r in recs)
    assert left > 0 and summary["records_without_slot"] == {f"{layout.links[1]}:force": left}
    assert all(k in (0, None) for r in recs for k in r["record_slots"])
