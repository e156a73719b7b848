"""Training reads the documented log format as written; splits are contiguous time blocks."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.errors import LogError
from torchcontact.logs import write_simulated_log
from torchcontact.logs.format import fixed_list
from torchcontact.simulation import UnmodeledEffects, simulate
from training.data import ResidualDataset, fold_splits, load_parquet, split_blocks, time_blocks


@pytest.mark.parametrize("lengths,block", [((1000,), 100), ((350, 17, 640), 64), ((5,), 2)])
def test_split_by_contiguous_blocks_leaks_no_frame(lengths, block):
    file_id = np.concatenate([np.full(n, i) for i, n in enumerate(lengths)])
    s = split_blocks(file_id, block, seed=1)
    parts = [s.train, s.val, s.test]
    allidx = np.concatenate(parts)
    assert len(allidx) == len(file_id) and len(np.unique(allidx)) == len(file_id)
    for a in range(3):
        for b in range(a + 1, 3):
            assert not np.intersect1d(parts[a], parts[b]).size
    for name, idx in zip(("train", "val", "test"), parts, strict=True):
        assert len(idx) > 0
        rebuilt = np.concatenate([np.arange(x, y) for x, y in s.blocks[name]])
        np.testing.assert_array_equal(rebuilt, idx)
        for x, y in s.blocks[name]:
            assert 0 < y - x <= block
            assert len(np.unique(file_id[x:y])) == 1  # a block never crosses files
    # blocks, not frames: far fewer runs than frames
    runs = np.count_nonzero(np.diff(s.test) != 1) + 1
    assert runs <= len(s.blocks["test"])


def test_split_is_seeded_and_a_zero_share_is_empty():
    f = np.zeros(500, int)
    a, b, c = split_blocks(f, 50, seed=0), split_blocks(f, 50, seed=0), split_blocks(f, 50, seed=1)
    np.testing.assert_array_equal(a.test, b.test)
    assert not np.array_equal(a.test, c.test)
    d = split_blocks(f, 50, (0.8, 0.2, 0.0))
    assert len(d.test) == 0 and len(d.val) == 100 and len(d.train) == 400


@pytest.mark.parametrize("folds", [2, 3, 5])
def test_folds_test_every_block_exactly_once(folds):
    file_id = np.r_[np.zeros(730, int), np.ones(400, int)]
    splits = fold_splits(file_id, 50, folds, seed=3)
    assert len(splits) == folds
    tested = np.concatenate([s.test for s in splits])
    np.testing.assert_array_equal(np.sort(tested), np.arange(len(file_id)))
    blocks = time_blocks(file_id, 50)
    for s in splits:
        assert len(s.val) and len(s.train) and len(s.test)
        names = [set(s.blocks[n]) for n in ("train", "val", "test")]
        assert set.union(*names) == set(blocks)  # every block has a role in every fold
        assert not (names[0] & names[1] or names[0] & names[2] or names[1] & names[2])
    with pytest.raises(ValueError, match="cannot make 5 folds"):
        fold_splits(np.zeros(100, int), 50, 5)


def _reordered_log(arm, path, frames=400, seed=2, drop=(), derivatives=True, **kw):
    """A log as another system writes it: joints in another order, vectors as plain lists, no
    contacts column (optionally)."""
    log = simulate(arm, frames, seed=seed, effects=UnmodeledEffects(offset=(1, 2, 3, 0, 0, 0)))
    order = list(arm.joint_names)[::-1]
    perm = [arm.joint_names.index(j) for j in order]

    def joints(x):
        return pa.array(x[:, perm].tolist(), pa.list_(pa.float64()))

    cols = {"t_ns": pa.array(log.t_ns), "q": joints(log.q)}
    if derivatives:
        cols.update(qd=joints(log.qd), qdd=joints(log.qdd))
    cols["ft.base_ft"] = fixed_list(log.ft)
    contacts = [
        [{"link": log.links[li], "kind": "force"} for li in row if li >= 0]
        for row in log.contact_link
    ]
    struct = pa.list_(pa.struct([("link", pa.string()), ("kind", pa.string())]))
    cols["contacts"] = pa.array(contacts, struct)
    cols["temperature"] = pa.array(log.temperature)
    for c in drop:
        cols.pop(c, None)
    table = pa.table(cols).replace_schema_metadata({"torchcontact.joint_names": json.dumps(order)})
    pq.write_table(table, path, **kw)
    return log


def test_log_joints_are_mapped_by_name(tmp_path, arm):
    p = tmp_path / "a.parquet"
    log = _reordered_log(arm, p)
    ds = load_parquet([p], arm, "base_ft", extra=["temperature", "time"])
    ref = ResidualDataset.from_simulated(log, ["temperature", "time"])
    assert ds.joint_names == arm.joint_names
    for k in ("q", "qd", "qdd", "ft", "contact_free"):
        np.testing.assert_array_equal(getattr(ds, k), getattr(ref, k))
    np.testing.assert_array_equal(ds.extra["temperature"], ref.extra["temperature"])
    assert ref.contact_free.any() and not ref.contact_free.all() and ds.usable.all()


def test_several_files_and_the_simulated_log_writer(tmp_path, arm):
    a = write_simulated_log(arm, 300, tmp_path / "a.parquet", seed=1)
    b = write_simulated_log(arm, 120, tmp_path / "b.parquet", seed=2)
    ds = load_parquet([a, b], arm, "base_ft", extra=["temperature", "time"])
    ref = ResidualDataset.from_simulated(simulate(arm, 120, seed=2), ["temperature"])
    assert len(ds) == 420
    np.testing.assert_array_equal(ds.q[300:], ref.q)
    np.testing.assert_array_equal(ds.file_id, np.r_[np.zeros(300), np.ones(120)])
    assert ds.extra["time"][300] == 0.0  # time since each file's start
    assert [s["frames"] for s in ds.sources] == [300, 120]
    assert ds.sha256() != load_parquet([a], arm, "base_ft", extra=["temperature"]).sha256()


def test_missing_derivatives_are_derived_and_no_contacts_column_means_free(tmp_path, arm):
    p = tmp_path / "q_only.parquet"
    log = _reordered_log(arm, p, frames=600, drop=("qd", "qdd", "contacts"), derivatives=False)
    ds = load_parquet([p], arm, "base_ft")
    assert ds.sources[0]["derived"] == ["qd", "qdd"] and not ds.sources[0]["contacts_column"]
    assert ds.contact_free.all()
    inner = slice(10, -10)
    np.testing.assert_allclose(ds.qd[inner], log.qd[inner], atol=2e-3 * np.abs(log.qd).max())
    np.testing.assert_allclose(ds.qdd[inner], log.qdd[inner], atol=2e-2 * np.abs(log.qdd).max())


def test_bad_rows_are_kept_but_unusable_and_bad_files_are_named(tmp_path, arm):
    p = tmp_path / "bad.parquet"
    _reordered_log(arm, p, frames=50)
    t = pq.read_table(p)
    q = t.column("q").to_pylist()
    q[3] = q[3][:-2]  # a short vector
    q[9][1] = float("nan")
    ft = t.column("ft.base_ft").to_pylist()
    ft[20] = None
    t = t.set_column(1, "q", pa.array(q, pa.list_(pa.float64())))
    t = t.set_column(
        t.column_names.index("ft.base_ft"), "ft.base_ft", pa.array(ft, pa.list_(pa.float64(), 6))
    )
    pq.write_table(t, p)
    ds = load_parquet([p], arm, "base_ft")
    assert np.flatnonzero(~ds.usable).tolist() == [3, 9, 20] and len(ds) == 50
    # the short vector and the null reading read as NaN rows (the log format's reader), so they
    # count with the NaN value as unusable frames
    assert ds.sources[0]["malformed_frames"] == 3

    wrong = tmp_path / "wrong_joints.parquet"
    names = ["gripper", *list(arm.joint_names)[::-1][1:]]  # wrist_roll is missing, gripper extra
    pq.write_table(
        t.replace_schema_metadata({"torchcontact.joint_names": json.dumps(names)}), wrong
    )
    with pytest.raises(LogError, match="lacks joints \\['wrist_roll'\\] extra \\['gripper'\\]"):
        load_parquet([wrong], arm, "base_ft")
    renamed = tmp_path / "renamed.parquet"
    pq.write_table(
        t.rename_columns(
            [c.replace("base_ft", "other") for c in t.column_names]
        ).replace_schema_metadata(t.schema.metadata),
        renamed,
    )
    with pytest.raises(LogError, match="missing columns \\['ft.base_ft'\\]"):
        load_parquet([renamed], arm, "base_ft")
    with pytest.raises(LogError, match="missing columns \\['humidity'\\]"):
        load_parquet([p], arm, "base_ft", extra=["humidity"])
    with pytest.raises(LogError, match="no F/T sensor 'nope'"):
        load_parquet([p], arm, "nope")
    (tmp_path / "x.parquet").write_text("not parquet")
    with pytest.raises(LogError, match="x.parquet: not a readable Parquet file"):
        load_parquet([tmp_path / "x.parquet"], arm, "base_ft")
    pq.write_table(t.replace_schema_metadata({}), tmp_path / "nm.parquet")
    with pytest.raises(LogError, match="no joint names"):
        load_parquet([tmp_path / "nm.parquet"], arm, "base_ft")


def test_bias_smoothing_takes_each_logs_drift_out_of_the_residuals(arm):
    """``train fit --bias-time-constant``: the residuals lose the drift about its mean, keep the
    pose-dependent payload effect (for the inertial and learned layers) and the mean offset."""
    from dataclasses import replace

    from training.pipeline import Config, prepare, smooth_drift

    fx = UnmodeledEffects(offset=(1.0, 0.0, 0.0, 0.0, 0.0, 0.0), drift=(3.0, 0, 0, 0, 0, 0),
                          drift_time_constant=10.0, payload_mass=0.3, noise_std=(0.02,) * 6)  # fmt: skip
    log = simulate(arm, 3000, seed=4, effects=fx)
    ds = ResidualDataset.from_simulated(log, [])
    cfg = Config()
    cfg = replace(cfg, data=replace(cfg.data, block_seconds=5.0), stack=replace(
        cfg.stack, layers=["offset"]))  # fmt: skip
    plain = prepare(arm, ds, cfg).residual
    # a fast drift (10 s) in a 30 s log: a short time constant (measured: 2 s leaves 0.065 N of
    # the 0.78 N drift; 1 s starts to take the payload's pose effect, 5 s lags the drift)
    smooth = prepare(arm, ds, replace(cfg, data=replace(cfg.data, bias_time_constant=2.0)))
    free = ds.targets
    t = ds.t_ns * 1e-9
    true_drift = 3.0 * (1 - np.exp(-t / 10.0))
    true_drift -= true_drift[free].mean()
    drift = smooth_drift(ds, plain, 2.0)
    # what was taken off is the drift (about its mean), not the payload's pose-dependent part
    err = drift[free, 0] - true_drift[free]
    assert np.sqrt(np.mean(err**2)) < 0.15 * true_drift[free].std()
    np.testing.assert_allclose(smooth.residual, plain - drift)
    np.testing.assert_allclose(smooth.residual[free].mean(0), plain[free].mean(0), atol=1e-9)
    # the fx residual about the payload effect now varies far less
    payload = plain[free, 0] - true_drift[free]
    assert np.std(smooth.residual[free, 0] - payload) < 0.15 * np.std(plain[free, 0] - payload)
