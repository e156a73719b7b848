import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from torchcontact.logs import format as fmt
from torchcontact.logs.derive import savgol_derivatives


def test_vectors_fixed_plain_and_bad_rows():
    v, bad = fmt.vectors(pa.array([[1.0, 2.0, 3.0], [4.0, 5.0], None, [7.0, 8.0, 9.0]]), 3)
    assert bad.tolist() == [False, True, True, False]
    assert v[3].tolist() == [7.0, 8.0, 9.0] and np.isnan(v[1]).all()
    fixed = fmt.fixed_list(np.arange(6.0).reshape(2, 3))
    v, bad = fmt.vectors(fixed.slice(1), 3)  # offsets of a slice are honoured
    assert v.tolist() == [[3.0, 4.0, 5.0]] and not bad.any()


def test_input_schema_metadata_roundtrip(tmp_path):
    schema = fmt.input_schema(["a", "b"], ["s"], derivatives=False)
    pq.write_table(schema.empty_table(), tmp_path / "x.parquet")
    back = pq.read_schema(tmp_path / "x.parquet")
    assert fmt.joint_names_of(back) == ["a", "b"]
    assert json.loads(back.metadata[fmt.META_JOINT_NAMES]) == ["a", "b"]
    assert back.names == ["t_ns", "q", "ft.s", "contacts"]
    with pytest.raises(ValueError, match="torchcontact.joint_names"):
        fmt.joint_names_of(pa.schema([("q", pa.float64())]), "f.parquet")


def test_savgol_exact_on_quadratics_uneven_time():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(8_000_000, 12_000_000, 40))  # jittered 100 Hz
    s = t * 1e-9
    q = np.stack([1 + 2 * s - 3 * s**2, np.full_like(s, 0.5)], -1)
    qd, qdd = savgol_derivatives(t, q, 4)
    np.testing.assert_allclose(qd[:, 0], 2 - 6 * s, atol=1e-7)
    np.testing.assert_allclose(qdd[:, 0], -6.0, atol=1e-5)
    np.testing.assert_allclose(qd[:, 1], 0.0, atol=1e-9)


def test_savgol_chunked_with_context_equals_whole():
    rng = np.random.default_rng(1)
    t = np.arange(100) * 10_000_000
    q = np.sin(np.arange(100)[:, None] * 0.1 + rng.uniform(size=3))
    whole = savgol_derivatives(t, q, 5)
    # rows 40..60 with 5 frames of context on each side
    part = savgol_derivatives(t[35:65], q[35:65], 5, 5, 25)
    np.testing.assert_array_equal(part[0], whole[0][40:60])
    np.testing.assert_array_equal(part[1], whole[1][40:60])
