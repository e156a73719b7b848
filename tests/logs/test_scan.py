"""The log's scan (time steps, segments, the contacts' most records per frame) read in ranges of
row groups on threads: the same :class:`LogScan` as one pass in file order, and as the same
quantities computed from the whole arrays at once."""

import itertools
from collections import Counter

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchcontact.logs.decode import LogScan, scan_log, scan_threads
from torchcontact.logs.derive import (
    GAP_FACTOR,
    MIN_SEGMENT_FRAMES,
    median_step,
    step_histogram,
    time_segments,
)
from torchcontact.logs.format import open_log

STEP = 10_000_000  # ns
_names = itertools.count()


def _reference(t: np.ndarray, contacts: list) -> LogScan:
    """The scan's quantities from the whole arrays at once."""
    hist: dict[int, int] = {}
    step_histogram(t, hist)
    step = median_step(hist)
    starts = np.flatnonzero(time_segments(t, step))
    lengths = np.diff(np.r_[starts, len(t)])
    d = np.diff(t)
    pairs: dict = {}
    for row in contacts:
        for k, m in Counter((c["link"], c["kind"]) for c in row or []).items():
            pairs[k] = max(pairs.get(k, 0), m)
    return LogScan(
        len(t),
        pairs,
        step,
        max(len(starts), 1),
        int((d <= 0).sum()),
        int((d > GAP_FACTOR * step).sum()) if step > 0 else 0,
        int(lengths[lengths < MIN_SEGMENT_FRAMES].sum()),
    )


@st.composite
def stamps_and_groups(draw, n: int):
    """``n`` stamps at 10 ms with repeats, backward runs and gaps, and row-group sizes."""
    t = np.arange(n, dtype=np.int64) * STEP
    for _ in range(draw(st.integers(0, 6))):
        i = draw(st.integers(1, n - 1))
        what = draw(st.sampled_from(["repeat", "back", "gap"]))
        if what == "repeat":
            t[i] = t[i - 1]
        elif what == "back":
            k = draw(st.integers(2, 12))
            t[i : i + k] = t[i : i + k][::-1].copy()
        else:
            t[i:] += draw(st.integers(6, 60)) * STEP
    cuts = sorted(draw(st.sets(st.integers(1, n - 1), max_size=14)))
    return t, cuts


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=stamps_and_groups(600))
def test_scan_in_ranges_on_threads_is_the_one_pass_scan(changing, tmp_path_factory, data):
    t, cuts = data
    tab = pq.read_table(changing)
    tab = tab.set_column(0, "t_ns", pa.array(t))
    path = tmp_path_factory.mktemp("scan") / f"log{next(_names)}.parquet"
    with pq.ParquetWriter(path, tab.schema) as w:  # one row group per slice: 1 row and up
        for a, b in zip([0, *cuts], [*cuts, len(t)], strict=True):
            w.write_table(tab.slice(a, b - a))
    src = str(path)
    one = scan_log(open_log(path), src, True)
    assert one == _reference(t, tab["contacts"].to_pylist())
    for threads in (2, 3, 8):
        assert scan_log(open_log(path), src, True, threads) == one, threads


def test_scan_threads_rule():
    """Half the cores, at most 8, and a thread per half a million frames at least."""
    import os

    half = max(1, (os.cpu_count() or 1) // 2)
    assert scan_threads(0) == scan_threads(100_000) == 1
    assert scan_threads(100_000_000) == min(8, half)
    assert scan_threads(3 << 19) == min(3, half)


def test_small_row_groups_estimate_as_one(model, changing, tmp_path):
    """A log in row groups of 100 frames gives the output of the same log in one row group.

    Regression: the overlapped scan read the contacts' names as dictionary arrays, which pyarrow
    cannot join across row groups ("Nested data conversions not implemented"): such a log failed
    as "corrupted data".
    """
    from torchcontact.logs import estimate_file

    small = tmp_path / "small.parquet"
    pq.write_table(pq.read_table(changing), small, row_group_size=100)
    a = estimate_file(changing, model, tmp_path / "a.parquet")
    b = estimate_file(small, model, tmp_path / "b.parquet")
    assert a["frames"] == b["frames"] == 600 and a["slots"] == b["slots"]
    assert pq.read_table(a["output"]).equals(pq.read_table(b["output"]))


def test_damage_is_reported_as_one_pass_reports_it(changing, tmp_path):
    """A damaged page in row group 3 of 6: the scan in ranges on threads raises the error a pass
    in file order raises (the first damage in file order, its row group named), whichever
    thread met it."""
    import pytest

    from torchcontact.errors import LogError
    from torchcontact.logs.format import write_table

    path = write_table(pq.read_table(changing), tmp_path / "log.parquet", row_group_size=100)
    meta = pq.ParquetFile(path).metadata
    chunk = meta.row_group(3).column(0)  # t_ns of rows 300-399 (page checksums: detected)
    data = bytearray(path.read_bytes())
    at = chunk.data_page_offset + chunk.total_compressed_size // 2
    data[at : at + 16] = bytes(16)
    path.write_bytes(bytes(data))
    errors = []
    for threads in (1, 3, 6):
        with pytest.raises(LogError) as e:
            scan_log(open_log(path), str(path), True, threads)
        errors.append(str(e.value))
    assert "corrupted data in row group 3 (rows 300-399)" in errors[0]
    assert errors == [errors[0]] * 3
