"""``torchcontact estimate --residual``: a correction stack applied before estimation.

The corrections are built here, not trained: an offset layer equal to a known sensor offset, and
an inertial layer whose parameter change is exactly a payload's, explain a simulated log's
readings exactly, so its contacts are estimated exactly with the correction and wrongly without.
"""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from torchcontact.cli import main
from torchcontact.logs import LogError, estimate_file, write_simulated_log
from torchcontact.logs.format import META_RESIDUAL
from torchcontact.residual import (
    FeatureSpec,
    ResidualCorrection,
    ResidualGRU,
    inertial_params,
    subtree_bodies,
)
from torchcontact.simulation import UnmodeledEffects

OFFSET = [2.5, -1.25, 4.0, 0.125, -0.25, 0.5]  # [N; N m]
PAYLOAD = dict(payload_mass=0.4, payload_com=(0.01, 0.02, 0.08))


def _exact(model, directory, payload=False, **kw):
    """Offset (and the payload's exact inertial change): the log's effects, nothing else."""
    layers: dict = {"offset": torch.tensor(OFFSET, dtype=torch.float64)}
    if payload:
        bodies = subtree_bodies(model, "base_ft")
        true = model.with_point_mass("hand", PAYLOAD["payload_mass"], PAYLOAD["payload_com"])
        delta = inertial_params(true, bodies) - inertial_params(model, bodies)
        layers.update(
            inertial_bodies=tuple(model.body_names[b] for b in bodies),
            delta=torch.as_tensor(delta),
        )
    c = ResidualCorrection(model, "base_ft", **layers, **kw)
    return c.save(directory)


@pytest.fixture(scope="module")
def offset_log(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("offset") / "log.parquet"
    return write_simulated_log(model, 400, path, seed=3, effects=UnmodeledEffects(offset=OFFSET))


@pytest.fixture(scope="module")
def payload_log(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("payload") / "log.parquet"
    fx = UnmodeledEffects(offset=OFFSET, **PAYLOAD)
    return write_simulated_log(model, 400, path, seed=4, effects=fx)


def _single_contact_errors(path):
    rows = pq.read_table(path).column("contacts").to_pylist()
    errs = [
        np.abs(np.subtract(r[0]["force"], r[0]["true_force"])).max() for r in rows if len(r) == 1
    ]
    assert len(errs) > 20
    return np.asarray(errs)


@pytest.mark.parametrize("payload", [False, True])
def test_residual_cli_recovers_forces_that_the_effects_spoil(
    model, offset_log, payload_log, tmp_path, capsys, payload
):
    log = payload_log if payload else offset_log
    ckpt = _exact(model, tmp_path / "ckpt", payload=payload)
    with_res, without = tmp_path / "with.parquet", tmp_path / "without.parquet"
    args = ["estimate", str(log), "--quiet", "--batch-size", "64"]
    assert main([*args, "--out", str(with_res), "--residual", str(ckpt)]) == 0
    assert main([*args, "--out", str(without)]) == 0
    capsys.readouterr()
    assert _single_contact_errors(with_res).max() < 1e-8
    assert _single_contact_errors(without).min() > 0.1
    meta = pq.read_schema(with_res).metadata
    rec = json.loads(meta[META_RESIDUAL])
    weights = json.loads((ckpt / "checkpoint.json").read_text())["weights_sha256"]
    assert rec == {
        "checkpoint": str(ckpt.resolve()),
        "weights_sha256": weights,
        "sensor": "base_ft",
        "kind": "offset+inertial" if payload else "offset",
    }
    assert META_RESIDUAL not in pq.read_schema(without).metadata


def test_foreign_robot_and_unknown_sensor_are_refused(model, offset_log, tmp_path, capsys):
    ckpt = _exact(model, tmp_path / "ckpt")
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    # a checkpoint of another robot: its recorded identity differs (here: the base link's mass)
    other = json.loads(json.dumps(meta))
    entry = next(e for e in other["robot_identity"] if e[:2] == ["link base_link", "mass"])
    entry[2] = [entry[2][0] + 0.01]
    (ckpt / "checkpoint.json").write_text(json.dumps(other))
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(offset_log), "--out", str(out), "--residual", str(ckpt)]) == 1
    err = capsys.readouterr().err
    assert "not this robot" in err and "link base_link: mass 4.01 vs 4 kg" in err, err
    assert not out.exists() and not out.with_name("o.parquet.partial").exists()
    (ckpt / "checkpoint.json").write_text(json.dumps({**meta, "sensor": "wrist_ft"}))
    with pytest.raises(LogError, match="corrects sensor 'wrist_ft', which tcarm does not have"):
        estimate_file(offset_log, model, tmp_path / "o2.parquet", residual=ckpt)


def _gru_ckpt(model, directory):
    spec = FeatureSpec.default(model, "base_ft", extra=("temperature",))
    torch.manual_seed(0)
    net = ResidualGRU(len(spec.names(model)), hidden=8)
    offset = torch.tensor(OFFSET, dtype=torch.float64)
    return ResidualCorrection(model, "base_ft", offset, learned=net, features=spec).save(directory)


def test_missing_feature_column_is_named(model, tmp_path):
    ckpt = _gru_ckpt(model, tmp_path / "gru")
    no_temp = write_simulated_log(model, 50, tmp_path / "nt.parquet", seed=1, temperature=False)
    with pytest.raises(LogError, match="needs column 'temperature', which the log lacks"):
        estimate_file(no_temp, model, tmp_path / "o.parquet", residual=ckpt)


def test_gru_state_carries_across_chunks_and_resume_is_refused(model, offset_log, tmp_path):
    ckpt = _gru_ckpt(model, tmp_path / "gru")
    one = estimate_file(
        offset_log, model, tmp_path / "one.parquet", batch_size=10_000, residual=ckpt
    )
    many = estimate_file(offset_log, model, tmp_path / "many.parquet", batch_size=37, residual=ckpt)
    a = np.stack(pq.read_table(one["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    b = np.stack(pq.read_table(many["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    # a chunked run equals one sequence: the state was not reset between chunks (float32 GRU)
    np.testing.assert_allclose(a, b, atol=1e-5)
    plain = estimate_file(offset_log, model, tmp_path / "plain.parquet")
    c = np.stack(pq.read_table(plain["output"])["joint_torques"].to_numpy(zero_copy_only=False))
    assert np.abs(a - c).max() > 1e-3  # the correction did change the estimates
    with pytest.raises(LogError, match="not supported with a recurrent"):
        estimate_file(offset_log, model, tmp_path / "r.parquet", residual=ckpt, resume=True)


def test_frames_the_correction_cannot_use_are_flagged_and_the_rest_processed(model, tmp_path):
    import pyarrow as pa

    log = write_simulated_log(model, 120, tmp_path / "l.parquet", seed=5)
    t = pq.read_table(log)
    temp = t.column("temperature").to_numpy().copy()
    temp[[7, 40]] = np.nan
    t = t.set_column(t.column_names.index("temperature"), "temperature", pa.array(temp))
    pq.write_table(t, log)
    ckpt = _gru_ckpt(model, tmp_path / "gru")
    res = estimate_file(log, model, tmp_path / "o.parquet", residual=ckpt)
    status = pq.read_table(res["output"]).column("status").to_pylist()
    assert res["frames"] == 120
    bad = [i for i, s in enumerate(status) if s != "ok"]
    assert bad == [7, 40] and "F/T" in status[7]


def test_frames_outside_the_training_range_get_a_bit_and_a_count(model, offset_log, tmp_path):
    """Issue 20: a learned layer's checkpoint records its features' training range; estimate
    flags the frames beyond it (outputs kept) and counts them; old checkpoints load unflagged."""
    from torchcontact.residual import RANGE_MARGIN, ResidualMLP
    from torchcontact.status import Status
    from training.pipeline import workspace_markdown

    spec = FeatureSpec.default(model, "base_ft", extra=("temperature",))
    torch.manual_seed(0)
    net = ResidualMLP(len(spec.names(model)), hidden=8)
    corr = ResidualCorrection(model, "base_ft", torch.tensor(OFFSET, dtype=torch.float64),
                              learned=net, features=spec)  # fmt: skip
    t = pq.read_table(offset_log)
    q, qd, qdd = (np.stack(t.column(c).to_numpy(zero_copy_only=False)) for c in ("q", "qd", "qdd"))
    temp = t.column("temperature").to_numpy()
    first = slice(0, 200)  # "trained" on the first half of the log only
    entry = corr.record_ranges(q[first], qd[first], qdd[first], {"temperature": temp[first]})
    assert entry["names"] == spec.names(model) and entry["frames"] == 200
    assert entry["margin"] == RANGE_MARGIN
    ckpt = corr.save(tmp_path / "mlp")
    loaded = ResidualCorrection.load(ckpt, model)
    expected = loaded.outside_range(q, qd, qdd, {"temperature": temp}).any(1)
    assert not expected[first].any() and 20 < expected.sum() < 200  # the other half leaves it
    res = estimate_file(offset_log, model, tmp_path / "o.parquet", residual=ckpt)
    assert res["outside_training"] == int(expected.sum()) and res["bad_frames"] == 0
    assert "training range" in res["outside_training_details"][0][0]
    out = pq.read_table(res["output"])
    code = out.column("status_code").to_numpy()
    np.testing.assert_array_equal((code & int(Status.OUTSIDE_TRAINING)) != 0, expected)
    forces = [c["force"] for r in out.column("contacts").to_pylist() for c in r]
    assert np.isfinite(forces).all()  # a warning: the outputs are kept
    assert "training range" in out.column("status_detail")[int(np.argmax(expected))].as_py()
    # a checkpoint written before ranges were recorded: loads, nothing flagged
    meta = json.loads((ckpt / "checkpoint.json").read_text())
    del meta["feature_ranges"]
    (ckpt / "checkpoint.json").write_text(json.dumps(meta))
    old = estimate_file(offset_log, model, tmp_path / "old.parquet", residual=ckpt)
    assert "outside_training" not in old and old["bad_frames"] == 0
    # train fit's report: the joints' trained ranges against the limits, how to cover them
    from training.data import ResidualDataset

    ds = ResidualDataset(
        t.column("t_ns").to_numpy()[first], q[first], qd[first], qdd[first],
        np.zeros((200, 6)), np.ones(200, bool), {"temperature": temp[first]},
        np.zeros(200, np.int64), tuple(model.joint_names), "base_ft",
    )  # fmt: skip
    text = "\n".join(workspace_markdown(corr, ds))
    assert "## Training range" in text and "outside_training" in text
    assert all(f"| {j} |" in text for j in spec.joints)
    assert "To cover the workspace" in text or "span most" in text
