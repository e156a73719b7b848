"""One slot layout per log: every chunk runs the same program, with the same rows as one layout
per chunk; a log whose contact set changes mid-file; when a run waits for its kernel."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.contacts import SlotLayout
from torchcontact.errors import KernelBuildError
from torchcontact.estimation import ContactEstimator
from torchcontact.logs import estimate_file
from torchcontact.logs import pipeline as pl
from torchcontact.logs.format import read_contacts


def _per_chunk(model, path, batch_size):
    """The output with one layout per chunk (the layout covering each chunk's own records)."""
    pf, le, columns, _ = pl.prepare(path, model)
    le.layout = le.decoder.layout = None
    tables = pl.read_chunks(pf, columns, batch_size, str(path))
    return pa.concat_tables(pl.estimate_stream(le, pl.decoded_chunks(le, tables, 5)))


def _same_rows(a, b):
    assert a.schema == b.schema
    for name in a.column_names:
        if name not in ("contacts", "joint_torques"):
            assert a[name].equals(b[name]), name
    for name in ("force", "moment", "true_force"):
        fa = np.array([c[name] for row in a["contacts"].to_pylist() for c in row], float)
        fb = np.array([c[name] for row in b["contacts"].to_pylist() for c in row], float)
        np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(
        np.stack(a["joint_torques"].to_numpy(zero_copy_only=False)),
        np.stack(b["joint_torques"].to_numpy(zero_copy_only=False)),
        rtol=0,
        atol=1e-9,
    )


def _layouts_seen(monkeypatch):
    """The ``(links, kinds)`` of every ContactEstimator.estimate call from now on."""
    seen = []
    real = ContactEstimator.estimate

    def spy(self, q, qd, qdd, ft, contacts, **kw):
        seen.append((contacts.links, contacts.kinds))
        return real(self, q, qd, qdd, ft, contacts, **kw)

    monkeypatch.setattr(ContactEstimator, "estimate", spy)
    return seen


def test_one_layout_per_log_same_rows_as_one_per_chunk(model, changing, tmp_path, monkeypatch):
    seen = _layouts_seen(monkeypatch)
    s = estimate_file(changing, model, tmp_path / "o.parquet", batch_size=128)
    out = pq.read_table(s["output"])
    # the most records of each (link, kind) in one frame over the whole file
    records = read_contacts(pq.read_table(changing)["contacts"])[0]
    layout = SlotLayout.covering(records)
    assert s["slots"] == layout.K == len(seen[0][0]) and len(seen) == 5
    assert set(seen) == {(layout.links, layout.kinds)}  # every chunk: one program
    assert s["chunks"] == 5 and s["ok_now"] == 600
    # per-chunk layouts differ from chunk to chunk and give the same rows
    seen.clear()
    _same_rows(out, _per_chunk(model, changing, 128))
    assert len(set(seen)) >= 3 and seen[0] == ((), ())  # no contact in the first chunks
    # the doubled hand contacts share their force (the minimum-norm split), the truth is kept
    frame = next(i for i in range(300, 600) if sum(c["link"] == "hand_skin"
                                                   for c in out["contacts"][i].as_py()) == 2)  # fmt: skip
    hand = [c for c in out["contacts"][frame].as_py() if c["link"] == "hand_skin"]
    np.testing.assert_allclose(hand[0]["force"], hand[1]["force"], atol=1e-12)


def test_when_a_run_waits_for_its_kernel(model, sim_log, tmp_path, monkeypatch):
    """By default the local engine never waits (``auto``: eager while the kernel builds); with
    WAIT_FOR_KERNEL_FRAMES frames to estimate it builds (or loads) the kernel before its first
    chunk, and a kernel that cannot be built leaves the run eager, with the same rows."""
    backends = []
    real = pl.LogEstimator.estimate

    def spy(self, d, previous=None, backend=None):
        backends.append(backend)
        if backend == "cpu":  # no compiler on this machine, say
            raise KernelBuildError("building kernel tck_estimator_x failed: no compiler")
        return real(self, d, previous, backend)

    monkeypatch.setattr(pl.LogEstimator, "estimate", spy)
    a = pq.read_table(estimate_file(sim_log, model, tmp_path / "a.parquet", batch_size=256)
                      ["output"])  # fmt: skip
    assert pl.WAIT_FOR_KERNEL_FRAMES is None and backends == ["auto"] * 3
    backends.clear()
    monkeypatch.setattr(pl, "WAIT_FOR_KERNEL_FRAMES", 600)
    b = pq.read_table(estimate_file(sim_log, model, tmp_path / "b.parquet", batch_size=256)
                      ["output"])  # fmt: skip
    assert backends == ["cpu", "eager", "eager", "eager"]
    assert a.equals(b)
    assert pl.kernel_backend(599, "cpu") == "auto" and pl.kernel_backend(600, "cpu") == "cpu"
    monkeypatch.setattr(pl, "WAIT_FOR_KERNEL_FRAMES", None)
    assert pl.kernel_backend(10**9, "cpu") == "auto"
    big, small = pl.SHARED_WAIT_FRAMES, pl.SHARED_WAIT_FRAMES - 1  # Ray tasks of large logs wait
    assert (
        pl.kernel_backend(big, "cpu", True) == "cpu"
        and pl.kernel_backend(small, "cpu", True) == "auto"
    )


def test_scan_on_a_thread_beside_the_noise_estimate(model, sim_log, tmp_path, monkeypatch):
    """The scan's second pass (the layout) runs on a thread while the noise estimate decodes the
    first chunks: those get their slots once the layout is known, and the run is the same as
    with the scan done first; the scan's error reaches the caller, with nothing written."""
    import threading
    import time

    from torchcontact.errors import LogError

    real = pl.scan_rest
    pending = []

    def slow(*a, **k):  # the noise estimate decodes its chunk before the layout is known
        time.sleep(0.3)
        return real(*a, **k)

    def decode(self, *a, **k):
        pending.append(self.layout_pending)
        return real_decode(self, *a, **k)

    from torchcontact.logs.decode import ChunkDecoder

    real_decode = ChunkDecoder.decode
    monkeypatch.setattr(ChunkDecoder, "decode", decode)
    seen = _layouts_seen(monkeypatch)
    monkeypatch.setattr(pl, "scan_rest", slow)
    a = estimate_file(sim_log, model, tmp_path / "a.parquet", batch_size=pl.NOISE_BATCH)
    assert pending[0] is True  # decoded (for the noise) while the scan ran
    layout = pl.prepare(sim_log, model)[1].layout
    assert set(seen) == {(layout.links, layout.kinds)} and a["slots"] == layout.K
    # the same run with the scan done first
    opened = pl.open_prepared
    monkeypatch.setattr(pl, "open_prepared", lambda *a, **k: opened(*a, **{**k, "overlap": False}))
    pending.clear()
    b = estimate_file(sim_log, model, tmp_path / "b.parquet", batch_size=pl.NOISE_BATCH)
    assert not any(pending)
    assert pq.read_table(a["output"]).equals(pq.read_table(b["output"]), check_metadata=True)
    assert a["noise"] == b["noise"] and a["time_segments"] == b["time_segments"]

    # an unreadable contacts column found by the scan's thread: its error, no output
    def broken(*a, **k):
        assert threading.current_thread().name == "torchcontact-scan"
        raise LogError("log.parquet: corrupted data in row group 0 (rows 0-599)")

    monkeypatch.setattr(pl, "open_prepared", opened)
    monkeypatch.setattr(pl, "scan_rest", broken)
    with pytest.raises(LogError, match="corrupted data in row group 0"):
        estimate_file(sim_log, model, tmp_path / "c.parquet", batch_size=pl.NOISE_BATCH)
    assert not (tmp_path / "c.parquet").exists()
    assert not (tmp_path / "c.parquet.partial").exists()


def test_cone_fields_are_type_checked_not_read_without_constraints():
    """An estimate without constraints reads no friction-cone values, but a field of the wrong
    type is refused all the same."""
    from torchcontact.errors import LogError

    t = pa.struct([("link", pa.string()), ("kind", pa.string()),
                   ("position", pa.list_(pa.float64(), 3)), ("normal", pa.list_(pa.float64())),
                   ("friction", pa.float64()), ("pushing", pa.bool_())])  # fmt: skip
    rec = {"link": "a", "kind": "force", "position": [1.0, 2.0, 3.0], "normal": [0.0, 0.0, 1.0],
           "friction": 0.5, "pushing": True}  # fmt: skip
    col = pa.array([[rec], [], [rec, rec]], pa.list_(t))
    full, _, malformed = read_contacts(col)
    bare, _, bare_bad = read_contacts(col, cones=False)
    assert full.normals.shape == (3, 3) and full.friction.tolist() == [0.5] * 3
    assert bare.normals is None and bare.friction is None and bare.pushing is None
    assert "normal" in malformed and "normal" not in bare_bad
    np.testing.assert_array_equal(full.positions, bare.positions)
    assert full.frame.tolist() == bare.frame.tolist() == [0, 2, 2]
    bad_t = pa.struct([*[t.field(i) for i in range(4)], ("friction", pa.string())])
    bad = pa.array([[{**rec, "friction": "high"}]], pa.list_(bad_t))
    for cones in (True, False):
        with pytest.raises(LogError, match="contacts.friction"):
            read_contacts(bad, cones=cones)
    bad_n = pa.struct([*[t.field(i) for i in range(3)], ("normal", pa.list_(pa.string()))])
    for cones in (True, False):
        with pytest.raises(LogError, match="contacts.normal"):
            read_contacts(pa.array([[{**rec, "normal": ["x"]}]], pa.list_(bad_n)), cones=cones)
