"""Time stamps where qd/qdd are derived: repeated, backward, gapped and too-short logs.

The reference is the same simulated trajectory with its exact qd/qdd logged: a frame whose
derived derivatives are wrong must not be ``ok``, and a frame that is ``ok`` must be as close to
the reference as the differentiator's smoothing allows."""

import json
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.logs import LogConstraints, estimate_file
from torchcontact.logs.decode import NOT_DIFFERENTIABLE
from torchcontact.logs.derive import GAP_FACTOR, time_segments
from torchcontact.status import STATUS, status_messages


@pytest.fixture(scope="module")
def exact(model, sim_log, tmp_path_factory):
    """Joint torques with the logged (exact) qd/qdd."""
    out = tmp_path_factory.mktemp("exact") / "o.parquet"
    tab = pq.read_table(estimate_file(sim_log, model, out)["output"])
    return np.stack(tab["joint_torques"].to_numpy(zero_copy_only=False))


def _variant(src, tmp_path, name, t_ns, rows=None):
    tab = pq.read_table(src)
    tab = tab if rows is None else tab.take(rows)
    path = tmp_path / f"{name}.parquet"
    pq.write_table(tab.set_column(0, "t_ns", pa.array(np.asarray(t_ns, np.int64))), path)
    return path


def _run(model, path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = estimate_file(path, model, path.with_name(path.stem + "_out.parquet"), **kw)
    tab = pq.read_table(s["output"])
    lines = [str(w.message) for w in caught if "time segments" in str(w.message)]
    return s, tab, lines


def _check_no_wrong_ok(tab, want):
    """Frames marked ok are within 1 % of the exact-derivative torques (smoothing error)."""
    jt = np.stack(tab["joint_torques"].to_numpy(zero_copy_only=False))
    ok = tab["status_code"].to_numpy() == 0
    err = np.abs(jt - want).max(1)
    assert (err[ok] <= 0.01 * np.abs(want).max()).all(), err[ok].max()
    return ok


def test_segments_cut_at_untrusted_stamps_and_gaps():
    t = np.array([0, 10, 20, 20, 30, 40, 100, 110, 105, 120]) * 1_000_000
    starts = time_segments(t, 10e6)
    assert np.flatnonzero(starts).tolist() == [0, 3, 4, 6, 8, 9]
    # the same cut, one chunk at a time with two stamps of context
    part = time_segments(t[4:], 10e6)[2:]
    assert part.tolist() == time_segments(t, 10e6)[6:].tolist()
    assert GAP_FACTOR == 5.0 and STATUS[NOT_DIFFERENTIABLE].startswith("too few frames")


def test_repeated_stamps_are_never_ok_with_wrong_derivatives(
    model, sim_log_q_only, exact, tmp_path
):
    t = pq.read_table(sim_log_q_only)["t_ns"].to_numpy().copy()
    t[201:300:2] = t[200:300:2]  # stamps repeated in pairs (a clock at half the frame rate)
    s, tab, lines = _run(model, _variant(sim_log_q_only, tmp_path, "rep", t), batch_size=100)
    ok = _check_no_wrong_ok(tab, exact)
    code, detail = tab["status_code"].to_numpy(), tab["status_detail"].to_pylist()
    assert set(np.flatnonzero(~ok)) == set(range(201, 300))  # frame 200 closes the segment before
    assert (code[~ok] == NOT_DIFFERENTIABLE).all()
    assert tab["status"][250].as_py() == status_messages(NOT_DIFFERENTIABLE)
    assert detail[250].startswith("too few frames to derive qd/qdd: its t_ns segment has 1 frame")
    # the summary counts segments and frames, and one warning line says so
    assert s["time_segments"] == 101 and s["not_differentiable"] == 99
    assert s["bad_frames"] == 99 and s["bad_details"][0][1] == 99
    assert len(lines) == 1 and "101 time segments" in lines[0] and "99 frames" in lines[0]
    # the segment after the repeated stamps is derived within itself, whatever the chunking
    _, tab7, _ = _run(model, _variant(sim_log_q_only, tmp_path, "rep7", t), batch_size=37)
    np.testing.assert_array_equal(tab7["status_code"].to_numpy(), code)
    a = np.stack(tab["joint_torques"].to_numpy(zero_copy_only=False))
    b = np.stack(tab7["joint_torques"].to_numpy(zero_copy_only=False))
    np.testing.assert_allclose(a[ok], b[ok], rtol=0, atol=1e-9)


def test_backward_and_gapped_stamps(model, sim_log_q_only, exact, tmp_path):
    t = pq.read_table(sim_log_q_only)["t_ns"].to_numpy().copy()
    back = t.copy()
    back[300:350] = back[300:350][::-1]  # t_ns running backwards for 50 frames
    _, tab, lines = _run(model, _variant(sim_log_q_only, tmp_path, "back", back))
    ok = _check_no_wrong_ok(tab, exact)
    assert set(np.flatnonzero(~ok)) == set(range(300, 350)) and len(lines) == 1
    # 50 frames missing: a gap of 51 steps; each side is differentiated on its own
    rows = np.r_[0:300, 350:600]
    s, tab, lines = _run(model, _variant(sim_log_q_only, tmp_path, "gap", t[rows], rows))
    ok = _check_no_wrong_ok(tab, exact[rows])
    assert ok.all() and s["time_segments"] == 2 and s["not_differentiable"] == 0
    assert len(lines) == 1 and "1 gaps over 5 x the median step 10 ms" in lines[0]


@pytest.mark.parametrize("frames", [1, 2])
def test_too_short_log_says_so(model, sim_log_q_only, tmp_path, frames):
    t = pq.read_table(sim_log_q_only)["t_ns"].to_numpy()[:frames]
    path = _variant(sim_log_q_only, tmp_path, "short", t, np.arange(frames))
    s, tab, lines = _run(model, path)
    assert tab["status_code"].to_pylist() == [NOT_DIFFERENTIABLE] * frames  # not bit 2
    plural = "s" if frames > 1 else ""
    want = f"too few frames to derive qd/qdd: the log has {frames} frame{plural}"
    assert tab["status_detail"].to_pylist() == [want] * frames
    assert s["time_segments"] == 1 and s["not_differentiable"] == frames and not lines


def test_logged_derivatives_are_not_cut(model, sim_log, tmp_path):
    t = pq.read_table(sim_log)["t_ns"].to_numpy().copy()
    t[201:300:2] = t[200:300:2]
    s, tab, lines = _run(model, _variant(sim_log, tmp_path, "logged", t))
    assert s["derived"] == [] and "not_differentiable" not in s and not lines
    assert (tab["status_code"].to_numpy() == 0).all()


def test_warm_start_restarts_at_every_segment(model, sim_log, tmp_path):
    """With --constraints, a segment's first frame starts cold: it equals the first frame of a
    log made of that segment alone, bit for bit, where a warm start gives another iterate."""
    tab = pq.read_table(sim_log).slice(280, 96)  # frames with contacts
    kw = dict(batch_size=128, constraints=LogConstraints(friction=0.2, wave=32))  # 3 waves
    whole = tmp_path / "whole.parquet"
    pq.write_table(tab, whole)
    w = pq.read_table(estimate_file(whole, model, tmp_path / "w.parquet", **kw)["output"])
    its = np.nan_to_num(np.array(w["iterations.base_ft"].to_pylist(), float))
    # a frame warm-started from its predecessor (not in wave 0), both solved by iterations
    g = next(i for i in range(10, 90) if i % 3 and its[i] > 0 and its[i - 1] > 0)
    t = tab["t_ns"].to_numpy().copy()
    t[g:] += 100 * (t[1] - t[0])  # a gap before frame g, inside the chunk
    gapped = tmp_path / "gapped.parquet"
    pq.write_table(tab.set_column(0, "t_ns", pa.array(t)), gapped)
    tail = tmp_path / "tail.parquet"
    pq.write_table(tab.slice(g).set_column(0, "t_ns", pa.array(t[g:])), tail)
    a = pq.read_table(estimate_file(gapped, model, tmp_path / "a.parquet", **kw)["output"])
    b = pq.read_table(estimate_file(tail, model, tmp_path / "b.parquet", **kw)["output"])
    ra, rb = a["contacts"][g].as_py(), b["contacts"][0].as_py()
    assert [c["force"] for c in ra] == [c["force"] for c in rb]
    assert a["iterations.base_ft"][g].as_py() == b["iterations.base_ft"][0].as_py()
    assert [c["force"] for c in w["contacts"][g].as_py()] != [c["force"] for c in ra]
    # before the gap, the gapped log is the whole log (same waves, same warm starts)
    assert a["iterations.base_ft"].to_pylist()[:g] == w["iterations.base_ft"].to_pylist()[:g]
    assert json.loads(a.schema.metadata[b"torchcontact.derived"])["columns"] == []


def test_stamp_types_and_null_stamps(model, sim_log, tmp_path):
    from torchcontact.errors import LogError

    tab = pq.read_table(sim_log).slice(0, 40)
    t = tab["t_ns"].to_numpy()
    ref = tmp_path / "ns.parquet"
    pq.write_table(tab, ref)
    want = pq.read_table(estimate_file(ref, model, tmp_path / "a.parquet")["output"])
    us = tmp_path / "us.parquet"  # a timestamp column in microseconds: the same instants
    pq.write_table(tab.set_column(0, "t_ns", pa.array(t // 1000, pa.timestamp("us"))), us)
    got = pq.read_table(estimate_file(us, model, tmp_path / "b.parquet")["output"])
    assert got.equals(want)
    null = tmp_path / "null.parquet"
    pq.write_table(tab.set_column(0, "t_ns", pa.array([*t[:7], None, *t[8:]], pa.int64())), null)
    with pytest.raises(LogError, match="1 frames have no time stamp \\(null t_ns\\)"):
        estimate_file(null, model, tmp_path / "c.parquet")
    assert not (tmp_path / "c.parquet.partial").exists()
