"""Faults around one estimate: one writer per output, kill -9 then --resume, full or read-only
disks, runs that fail before their first chunk, and the exit codes a batch job relies on.

Second processes are forked from this one (torch is already imported), so each costs
milliseconds, not an interpreter start."""

import errno
import json
import multiprocessing
import os
import signal
import socket
import threading
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import torchcontact as tc
from torchcontact._lock import OutputLock
from torchcontact.cli import main
from torchcontact.errors import LogError, OutputBusyError
from torchcontact.logs import estimate_file, write_simulated_log
from torchcontact.logs import format as fmt

FORK = multiprocessing.get_context("fork")


@pytest.fixture(scope="module")
def small(model, tmp_path_factory):
    """200 frames (4 chunks of 50) and its estimate, written by a run on its own."""
    folder = tmp_path_factory.mktemp("faults")
    log = write_simulated_log(model, 200, folder / "log.parquet", seed=7)
    ref = folder / "ref.parquet"
    estimate_file(log, model, ref, batch_size=50)
    return log, ref


def _side(out):
    return [out.with_name(out.name + s) for s in (".partial", ".progress.json", ".tmp", ".lock")]


def _child_estimate(log, out, **kw):
    try:
        estimate_file(log, tc.robots.tcarm_path(), out, batch_size=50, **kw)
    except BaseException:
        os._exit(1)
    os._exit(0)


def _wait_for(path, proc, timeout=60.0, parts=0):
    """Wait until ``path`` (a run's sidecar) exists and the run's journal has ``parts`` entries."""
    partial = path.with_name(path.name.replace(".progress.json", ".partial"))
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.is_alive():
        if path.exists() and len(list(partial.glob("part-*.index"))) >= parts:
            return True
        time.sleep(0.005)
    return False


def test_a_live_run_locks_its_output(model, small, tmp_path, capsys):
    log, _ = small
    out = tmp_path / "o.parquet"
    with OutputLock(out, "estimate"):
        for resume in (False, True):
            with pytest.raises(OutputBusyError) as e:
                estimate_file(log, model, out, resume=resume)
            msg = str(e.value)
            assert f"pid {os.getpid()} on {socket.gethostname()}, started" in msg
            assert "nothing was written" in msg and "interrupted" not in msg.split(";")[0]
        assert sorted(p.name for p in tmp_path.iterdir()) == ["o.parquet.lock"]
        assert main(["estimate", str(log), "--out", str(out), "--resume", "--quiet"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "another process is writing it (pid" in err[0]
    assert list(tmp_path.iterdir()) == []  # the lock file goes with its holder
    # plot --out and train fit --out: one writer per output folder too
    plots = tmp_path / "plots"
    with OutputLock(plots):
        assert main(["plot", str(small[1]), "--out", str(plots)]) == 1
        assert "another process is writing it" in capsys.readouterr().err
        ckpt = tmp_path / "ckpt"
        with OutputLock(ckpt):
            assert main(["train", "fit", "--log", str(log), "--out", str(ckpt)]) == 1
            assert "another process is writing it" in capsys.readouterr().err
    assert not plots.exists() and not ckpt.exists()


def test_two_runs_on_one_output_never_corrupt_it(model, small, tmp_path):
    """The second run, with --resume, while the first one runs: refused; the output is the
    solo run's. Repeated: one try proves little."""
    log, ref = small
    want = pq.read_table(ref)
    out = tmp_path / "o.parquet"
    refused = 0
    for _ in range(6):
        out.unlink(missing_ok=True)
        first = FORK.Process(target=_child_estimate, args=(log, out))
        first.start()
        assert _wait_for(_side(out)[1], first), "the first run never started"
        try:
            estimate_file(log, model, out, batch_size=50, resume=True)
        except OutputBusyError as exc:
            assert f"pid {first.pid} on" in str(exc)
            refused += 1
        first.join(60)
        assert first.exitcode == 0
        assert pq.read_table(out).equals(want)  # never corrupt, whoever won
        assert not any(p.exists() for p in _side(out))
    assert refused >= 5


def test_kill_9_then_resume_is_byte_identical(model, small, tmp_path, capsys):
    log, ref = small
    out = tmp_path / "o.parquet"
    run = FORK.Process(target=_child_estimate, args=(log, out))
    run.start()
    if not _wait_for(_side(out)[1], run, parts=1):
        pytest.fail("the run ended before it could be killed")
    os.kill(run.pid, signal.SIGKILL)
    run.join()
    assert not out.exists() and _side(out)[0].is_dir()
    # the lock died with its process: a plain rerun is told to resume, not that it is busy
    assert main(["estimate", str(log), "--out", str(out), "--batch-size", "50", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "an interrupted run left o.parquet.partial (no process is writing it now)" in err
    s = estimate_file(log, model, out, batch_size=50, resume=True)
    assert s["resumed_chunks"] >= 1 and s["frames"] == 200
    assert out.read_bytes() == ref.read_bytes()
    assert not any(p.exists() for p in _side(out))


def test_failure_before_the_first_chunk_leaves_nothing(model, small, tmp_path, monkeypatch):
    log, _ = small
    out = tmp_path / "o.parquet"
    # a real full disk: the sidecar's temporary file is /dev/full
    os.symlink("/dev/full", tmp_path / "o.parquet.progress.json.tmp")
    with pytest.raises(LogError) as e:
        estimate_file(log, model, out)
    msg = str(e.value)
    assert "o.parquet.progress.json.tmp: no space left on device (errno 28)" in msg
    assert "nothing was kept" in msg
    assert list(tmp_path.iterdir()) == []

    # a read-only folder for the journal's first entry: the same (o.parquet.tmp goes too)
    def read_only(index, path):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr("torchcontact.logs.run.write_part_index", read_only)
    with pytest.raises(LogError, match="part-00000000.index: read-only file system"):
        estimate_file(log, model, out)
    assert list(tmp_path.iterdir()) == []


def test_disk_full_mid_run_names_the_path_and_keeps_the_chunks(model, small, tmp_path, monkeypatch):
    log, ref = small
    out = tmp_path / "o.parquet"
    calls = []
    real = fmt.PartsWriter.append

    def full_after_two(self, part):
        calls.append(1)
        if len(calls) > 2:  # a full disk (the OS error names no file)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, part)

    monkeypatch.setattr(fmt.PartsWriter, "append", full_after_two)
    with pytest.raises(LogError) as e:
        estimate_file(log, model, out, batch_size=50)
    msg = str(e.value)
    assert msg.startswith(f"{out}.tmp: no space left on device (errno 28); free some space")
    assert "2 of 4 chunks are kept in" in msg and msg.endswith("for --resume")
    assert not out.exists() and _side(out)[2].exists()  # o.parquet.tmp holds the kept chunks
    # the reader and writer threads ended with the run
    names = {t.name for t in threading.enumerate()}
    assert not names & {"torchcontact-reader", "torchcontact-writer"}
    monkeypatch.undo()
    s = estimate_file(log, model, out, batch_size=50, resume=True)
    assert s["resumed_chunks"] >= 2 and out.read_bytes() == ref.read_bytes()


def test_exit_codes(model, small, tmp_path, capsys):
    log, _ = small
    tab = pq.read_table(log)
    q = np.stack(tab["q"].to_numpy(zero_copy_only=False))
    # q with 6 values for the 7-joint robot: no frame is usable
    bad = tmp_path / "six.parquet"
    six = pa.array(q[:, :6].tolist(), pa.list_(pa.float64()))
    pq.write_table(tab.set_column(tab.schema.get_field_index("q"), "q", six), bad)
    out = tmp_path / "o.parquet"
    assert main(["estimate", str(bad), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    assert "six.parquet: no usable frame (200 of 200 frames have a non-zero status" in err[0]
    assert '"q is not 7 floats" (200)' in err[0] and out.exists()  # the statuses are written
    # 30 % of the frames unusable: fine by default, not with --max-bad 0.2
    part = tmp_path / "part.parquet"
    q_rows = q.tolist()
    for i in range(60):
        q_rows[i] = q_rows[i][:6]
    pq.write_table(tab.set_column(tab.schema.get_field_index("q"), "q", pa.array(q_rows)), part)
    args = ["estimate", str(part), "--quiet", "--json", "--out"]
    assert main([*args, str(tmp_path / "a.parquet")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["bad_frames"] == 60 and s["bad_details"] == [["q is not 7 floats", 60]]
    assert main([*args, str(tmp_path / "b.parquet"), "--max-bad", "0.2"]) == 1
    assert "more than 0.2 of its frames unusable (60 of 200" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "c.parquet"), "--max-bad", "0.3"]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main([*args, str(tmp_path / "d.parquet"), "--max-bad", "1.5"])
    assert e.value.code == 2 and "expected a fraction in [0, 1]" in capsys.readouterr().err


def test_resume_of_a_derived_log_in_small_chunks(model, sim_log_q_only, tmp_path, monkeypatch):
    """Chunks shorter than the derivative's context (2 h = 10 frames): a resumed run reads the
    frames before its first chunk again and gives the solo run's bytes."""
    log = tmp_path / "q.parquet"
    pq.write_table(pq.read_table(sim_log_q_only).slice(0, 60), log)
    ref = tmp_path / "ref.parquet"
    estimate_file(log, model, ref, batch_size=7)
    out = tmp_path / "o.parquet"
    real = fmt.PartsWriter.append
    calls = []

    def interrupted(self, part):
        calls.append(1)
        if len(calls) > 4:
            raise KeyboardInterrupt
        return real(self, part)

    monkeypatch.setattr(fmt.PartsWriter, "append", interrupted)
    with pytest.raises(KeyboardInterrupt):
        estimate_file(log, model, out, batch_size=7)
    monkeypatch.undo()
    s = estimate_file(log, model, out, batch_size=7, resume=True)
    assert s["resumed_chunks"] >= 4 and s["derived"] == ["qd", "qdd"]
    assert out.read_bytes() == ref.read_bytes()


def test_resume_after_a_chunk_written_but_not_recorded(model, small, tmp_path, monkeypatch):
    """Killed between a chunk's bytes and its journal entry: the bytes are cut, the chunk redone;
    and a journal of the earlier format (every chunk an Arrow part) is read, not refused."""
    log, ref = small
    out = tmp_path / "o.parquet"
    real = fmt.PartsWriter.append
    calls = []

    def torn(self, part):
        calls.append(1)
        if len(calls) > 2:  # the third chunk's bytes half written, then the process dies
            self._file.write(memoryview(part.data)[: len(part.data) // 2])
            raise KeyboardInterrupt
        return real(self, part)

    monkeypatch.setattr(fmt.PartsWriter, "append", torn)
    with pytest.raises(KeyboardInterrupt):
        estimate_file(log, model, out, batch_size=50)
    monkeypatch.undo()
    partial, sidecar = _side(out)[:2]
    ident = json.loads(sidecar.read_text())
    assert sorted(p.name for p in partial.iterdir()) == [
        "part-00000000.index",
        "part-00000001.index",
    ]
    s = estimate_file(log, model, out, batch_size=50, resume=True)
    assert s["resumed_chunks"] == 2 and s["frames"] == 200
    assert out.read_bytes() == ref.read_bytes()

    # the earlier journal: Arrow IPC parts of chunks 0 and 1, an OUT.tmp it never read back
    ref_tab = pq.read_table(ref)
    partial.mkdir()
    for k in (0, 1):
        fmt.write_journal([ref_tab.slice(50 * k, 50)], partial / f"part-{k:08d}.arrow")
    sidecar.write_text(json.dumps({**ident, "parts_done": 2}))
    _side(out)[2].write_bytes(b"PAR1 an old writer's unfinished file")
    out.unlink()
    s = estimate_file(log, model, out, batch_size=50, resume=True)
    assert s["resumed_chunks"] == 2 and out.read_bytes() == ref.read_bytes()
    assert not any(p.exists() for p in _side(out))

    # killed after publishing the output, before removing the journal: said so, nothing touched
    partial.mkdir()
    fmt.write_part_index(fmt.PartIndex(4, 10, 50, b""), partial / "part-00000000.index")
    sidecar.write_text(json.dumps({**ident, "parts_done": 1}))
    with pytest.raises(LogError, match="left by a run that had published o.parquet"):
        estimate_file(log, model, out, batch_size=50, resume=True)
    assert out.read_bytes() == ref.read_bytes()
