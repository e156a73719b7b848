"""The log format's numpy <-> Arrow helpers (which never import pandas) against pyarrow's own
conversions (``Array.to_numpy``, ``pa.array``, ``pa.scalar``), which do: every dtype the log job
converts, nulls, NaN, empty and sliced arrays (``offset != 0``), several chunks."""

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.logs import format as fmt

DTYPES = {
    "float64": (np.float64, pa.float64()),
    "float32": (np.float32, pa.float32()),
    "int64": (np.int64, pa.int64()),
    "int32": (np.int32, pa.int32()),
    "uint8": (np.uint8, pa.uint8()),
    "bool": (np.bool_, pa.bool_()),
}


def _same(a: np.ndarray, b: np.ndarray) -> None:
    """Equal values and dtype, NaN where the other has NaN."""
    assert a.dtype == b.dtype and a.shape == b.shape
    assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def _arrow_same(a: pa.Array, b: pa.Array) -> None:
    """Equal type, nulls and values (NaN equal to NaN, which ``Array.equals`` does not say)."""
    assert a.type == b.type and a.null_count == b.null_count
    assert a.is_valid().equals(b.is_valid())
    valid = a.is_valid()
    _same(
        a.filter(valid).to_numpy(zero_copy_only=False),
        b.filter(valid).to_numpy(zero_copy_only=False),
    )


@st.composite
def arrays(draw):
    """A numpy array, a null mask (or None) and a slice of it (start, length)."""
    np_type, pa_type = DTYPES[draw(st.sampled_from(sorted(DTYPES)))]
    n = draw(st.integers(0, 40))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if np_type is np.bool_:
        x = rng.random(n) < 0.5
    elif np.issubdtype(np_type, np.floating):
        x = rng.normal(size=n).astype(np_type)
        x[rng.random(n) < 0.2] = np.nan  # NaN is a value, not a null
    else:
        x = rng.integers(0, 100, n).astype(np_type)
    mask = rng.random(n) < 0.3 if draw(st.booleans()) else None
    start = draw(st.integers(0, n))
    length = draw(st.integers(0, n - start))
    return x, mask, pa_type, start, length


@settings(max_examples=150, deadline=None, derandomize=True)
@given(arrays())
def test_numpy_to_arrow_and_back_equal_pyarrows_conversions(case):
    x, mask, pa_type, start, length = case
    arr = fmt.numpy_to_arrow(x, pa_type, mask=mask)
    ref = pa.array(x, pa_type, mask=mask)
    _arrow_same(arr, ref)
    part = arr.slice(start, length)  # a sliced array: offset != 0, bits not byte-aligned
    expected = ref.slice(start, length).to_numpy(zero_copy_only=False)
    if part.null_count and pa.types.is_boolean(pa_type):
        # pyarrow gives an object array of True/False/None; the helper asks for a fill
        with pytest.raises(TypeError, match="no fill"):
            fmt.arrow_to_numpy(part, bool)
        filled = fmt.arrow_to_numpy(part, bool, fill=False)
        _same(filled, np.array([bool(v) for v in expected], bool))
        return
    got = fmt.arrow_to_numpy(part)
    _same(got, expected)  # ints with nulls: float64 and NaN, as to_numpy
    if not part.null_count:
        # chunks: the same values, whichever way the array is cut
        cut = length // 2
        chunked = pa.chunked_array([part.slice(0, cut), part.slice(cut)], pa_type)
        _same(fmt.arrow_to_numpy(chunked), expected)
        assert fmt.arrow_to_numpy(pa.chunked_array([], pa_type)).dtype == expected.dtype
    else:
        filled = fmt.arrow_to_numpy(part, x.dtype, fill=7)
        ref_filled = ref.slice(start, length).fill_null(7).to_numpy(zero_copy_only=False)
        _same(filled, ref_filled.astype(x.dtype))


def test_arrow_to_numpy_shares_memory_without_nulls_and_copies_with_them():
    x = np.arange(10.0)
    arr = fmt.numpy_to_arrow(x)
    view = fmt.arrow_to_numpy(arr.slice(3, 4))
    assert np.shares_memory(view, x) and view.tolist() == [3.0, 4.0, 5.0, 6.0]
    assert not view.flags.writeable  # as to_numpy's zero-copy arrays
    nulls = fmt.numpy_to_arrow(x, mask=x > 7)
    out = fmt.arrow_to_numpy(nulls)
    assert not np.shares_memory(out, x) and np.isnan(out[8:]).all() and out[7] == 7.0
    # time stamps give their integers; types without fixed-width values are refused
    ts = fmt.numpy_to_arrow(np.array([5, 6]), pa.timestamp("ns"))
    assert fmt.arrow_to_numpy(ts).tolist() == [5, 6]
    with pytest.raises(TypeError, match="no numpy dtype"):
        fmt.arrow_to_numpy(fmt.string_array(["a"]))
    # an all-null column of the null type, and an empty one
    assert np.isnan(fmt.arrow_to_numpy(pa.nulls(3))).all()
    assert fmt.arrow_to_numpy(pa.nulls(0, pa.int64()), np.int64).tolist() == []


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(st.one_of(st.none(), st.text(max_size=6)), max_size=12), st.integers(0, 3))
def test_string_array_equals_pa_array(texts, start):
    arr = fmt.string_array(texts)
    ref = pa.array(texts, pa.string())
    assert arr.equals(ref) and arr.null_count == ref.null_count
    assert arr.slice(start).to_pylist() == texts[start:]
    assert fmt.string_array(texts, pa.large_string()).equals(ref.cast(pa.large_string()))


def test_arrow_scalar_equals_pa_scalar():
    struct = pa.struct([("link", pa.string()), ("position", pa.list_(pa.float64()))])
    cases = [
        (None, pa.int64()),
        (None, pa.list_(struct)),
        (2**53, pa.int64()),
        (-1.5, pa.float64()),
        (True, pa.bool_()),
        ("force", pa.string()),
        ([], pa.list_(struct)),
        ([], pa.list_(pa.float64())),
    ]
    for value, typ in cases:
        got, ref = fmt.arrow_scalar(value, typ), pa.scalar(value, typ)
        assert got.equals(ref) and got.type == ref.type, (value, typ)
