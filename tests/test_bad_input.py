"""Bad input through the installed ``torchcontact`` CLI (issue 19, items 4 and 5), and
property-based tests of log decoding.

The table: each case writes logs derived from one small simulated log of the bundled arm
(``write_simulated_log``, seeded), runs the installed ``torchcontact`` executable once, and
checks the exit code, the one ``error:`` line (never "unexpected ... please report it") and
what was written. Cases that succeed share one run over several inputs.

The properties (``hypothesis``): logs with random column types, list lengths, nulls, NaN and
time stamp orders either give a per-frame status for every frame or one
:class:`~torchcontact.errors.TorchContactError`, never another exception.
"""

from __future__ import annotations

import decimal
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchcontact as tc
from torchcontact.errors import TorchContactError
from torchcontact.logs import estimate_file, write_simulated_log

FRAMES = 300
#: more examples: TORCHCONTACT_HYPOTHESIS_EXAMPLES=500 pytest tests/test_bad_input.py
EXAMPLES = int(os.environ.get("TORCHCONTACT_HYPOTHESIS_EXAMPLES", "25"))


def _cli() -> str:
    """The installed ``torchcontact`` executable (beside this interpreter, else on PATH)."""
    here = str(Path(sys.executable).parent)
    exe = shutil.which("torchcontact", path=os.pathsep.join([here, os.environ.get("PATH", "")]))
    assert exe, "the torchcontact CLI is not installed (pip install -e .[all])"
    return exe


def _run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([_cli(), *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """300 frames of the arm with qd/qdd, one or two pushing forces on ~half of the frames."""
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    path = tmp_path_factory.mktemp("base") / "sim.parquet"
    return pq.read_table(write_simulated_log(model, FRAMES, path, seed=1))


def _with(table: pa.Table, path: Path, **columns) -> Path:
    """``table`` with columns replaced (same names, any type), its metadata kept."""
    for name, col in columns.items():
        table = table.set_column(table.schema.get_field_index(name), name, col)
    pq.write_table(table.replace_schema_metadata(table.schema.metadata), path)
    return path


def _one_error(res: subprocess.CompletedProcess) -> str:
    """The single ``error:`` line of a failed run (stderr holds nothing else of note)."""
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, res.stderr
    assert "unexpected" not in errors[0] and "please report" not in errors[0]
    return errors[0]


def _contacts(table: pa.Table, rows: list) -> pa.Array:
    return pa.array(rows, table.schema.field("contacts").type)


# --------------------------------------------------------------------------- the table
def _q_strings(t, d):
    q = [[repr(v) for v in row] for row in t["q"].to_pylist()]
    return [_with(t, d / "q_str.parquet", q=pa.array(q, pa.list_(pa.string())))]


def _five_frames(t, d):
    path = d / "five.parquet"
    pq.write_table(t.slice(0, 5), path)
    return [path]


def _no_usable_frame(t, d):
    rows = t["contacts"].to_pylist()
    touch = next(r for r in rows if r)
    return [_with(t, d / "all_contact.parquet", contacts=_contacts(t, [touch] * len(rows)))]


ERRORS = {
    # case: (write the inputs, CLI arguments after the inputs, text of the error line)
    "q as strings": (_q_strings, ["estimate", "--out", "{out}"],
                     "column 'q' is list<element: string>; expected a list of float64"),
    "train fit on 5 frames": (_five_frames, ["train", "fit", "--out", "{out}", "--log"],
                              "train fit needs at least 100 usable contact-free frames"),
    "train fit on no usable frame": (_no_usable_frame, ["train", "fit", "--out", "{out}",
                                                        "--log"],
                                     f"all_contact.parquet has 0 of {FRAMES} frames"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(ERRORS))
def test_bad_input_is_one_error_line_exit_1_nothing_written(case, base, tmp_path):
    write, argv, text = ERRORS[case]
    inputs = write(base, tmp_path)
    out = tmp_path / "out"
    args = [a.format(out=out) for a in argv]
    # subcommand first, then its inputs (train fit takes them after --log)
    res = _run(*args[:1], *inputs, *args[1:]) if argv[0] == "estimate" else _run(*args, *inputs)
    assert res.returncode == 1, res.stderr
    line = _one_error(res)
    assert text in line, line
    if case == "train fit on 5 frames":
        assert "five.parquet has" in line and "of 5 frames" in line
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("out")]  # nothing written


def test_numbers_that_convert_to_float64_are_accepted(base, tmp_path):
    """int counts (with null rows, null entries and a count beyond 2**53), decimals, float32:
    the same estimates and statuses as the float64 log of the same values, in one run over six
    inputs (before: unexpected ArrowInvalid / ArrowTypeError)."""
    ft = base["ft.base_ft"].to_pylist()
    counts = [[int(round(v)) for v in row] for row in ft]
    counts[3] = None  # a null row: status 1, the rest is processed
    counts[5][2] = None  # a null entry: NaN there
    as_float = [None if r is None else [np.nan if v is None else float(v) for v in r]
                for r in counts]  # fmt: skip
    counts[7][0] = 2**53 + 1  # no exact float64: NaN there, never a rounded number
    as_float[7][0] = np.nan
    dec = [[decimal.Decimal(f"{v:.6f}") for v in row] for row in ft]
    q32 = base["q"].cast(pa.list_(pa.float32(), 7))
    f64 = pa.list_(pa.float64())
    pairs = {
        "int": (pa.array(counts, pa.list_(pa.int64())), pa.array(as_float, f64)),
        "dec": (pa.array(dec, pa.list_(pa.decimal128(18, 6))),
                pa.array([[float(x) for x in r] for r in dec], f64)),
    }  # fmt: skip
    inputs = []
    for name, (typed, ref) in pairs.items():
        inputs.append(_with(base, tmp_path / f"{name}.parquet", **{"ft.base_ft": typed}))
        inputs.append(_with(base, tmp_path / f"{name}_ref.parquet", **{"ft.base_ft": ref}))
    inputs.append(_with(base, tmp_path / "f32.parquet", q=q32))
    inputs.append(_with(base, tmp_path / "f32_ref.parquet", q=q32.cast(pa.list_(pa.float64()))))
    out = tmp_path / "out"
    out.mkdir()
    res = _run("estimate", *inputs, "--out", out, "--quiet", "--json")
    assert res.returncode == 0, res.stderr
    assert "error" not in res.stderr
    for name in ("int", "dec", "f32"):
        a, b = pq.read_table(out / f"{name}.parquet"), pq.read_table(out / f"{name}_ref.parquet")
        assert a["status_code"].to_pylist() == b["status_code"].to_pylist()
        jt_a = np.array(a["joint_torques"].to_pylist(), float)
        jt_b = np.array(b["joint_torques"].to_pylist(), float)
        np.testing.assert_allclose(jt_a, jt_b, rtol=1e-12, atol=1e-12)
    codes = pq.read_table(out / "int.parquet")["status_code"].to_pylist()
    assert codes[3] == codes[5] == codes[7] == 1 and codes.count(0) >= FRAMES // 2


def _cone_logs(t: pa.Table, d: Path) -> dict[str, Path]:
    """Logs of every slot-list edge case; their contacts carry friction 0.5 but in "no friction"."""
    rows = [[{**c, "friction": 0.5} for c in r] for r in t["contacts"].to_pylist()]
    first = next(i for i, r in enumerate(rows) if r)
    one = [[] for _ in rows]
    one[10] = rows[first][:1]  # one valid pushing contact in the first chunk, none elsewhere
    return {
        "no contacts": _with(t, d / "none.parquet", contacts=_contacts(t, [[] for _ in rows])),
        "contact-free first chunk": _with(t, d / "late.parquet", contacts=_contacts(
            t, [[] if i < 100 else r for i, r in enumerate(rows)])),
        "all invalid": _with(t, d / "invalid.parquet", contacts=_contacts(
            t, [[{**c, "normal": None} for c in r] for r in rows])),
        "cone angles out of range": _with(t, d / "angle.parquet", contacts=_contacts(
            t, [[{**c, "friction": None, "cone_angle": 2.0} for c in r] for r in rows])),
        "no friction": _with(t, d / "nofriction.parquet", contacts=t["contacts"]),
        "one valid": _with(t, d / "one.parquet", contacts=_contacts(t, one)),
    }  # fmt: skip


#: Per-frame detail of each case's contact frames (the others are ok)
CONE_DETAILS = {
    "all invalid": "pushing contact without a finite 3-float normal (--constraints)",
    "cone angles out of range": "contact cone_angle is not in (0, pi/2) rad",
    "no friction": "contact without friction or cone_angle (give --friction or --cone-angle)",
}


def test_constraints_on_chunks_without_a_valid_pushing_contact(base, tmp_path):
    """``--constraints`` on every slot-list edge case, in 64-frame chunks, one run: frames
    without a cone to keep take the unconstrained path with their own status (before:
    unexpected NotImplementedError "bitwise_and_cpu" not implemented for 'Float')."""
    logs = _cone_logs(base, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    res = _run("estimate", *logs.values(), "--out", out, "--quiet", "--constraints",
               "--batch-size", "64")  # fmt: skip
    assert res.returncode == 0, res.stderr
    has = np.array([bool(r) for r in base["contacts"].to_pylist()])
    for case, path in logs.items():
        tab = pq.read_table(out / path.name)
        code = np.array(tab["status_code"].to_pylist())
        conv = np.array(tab["converged.base_ft"].to_pylist(), dtype=object)
        assert tab.num_rows == FRAMES, case
        if case in CONE_DETAILS:  # contact frames: status 4 and its detail; the others ok
            assert (code[has] == 4).all() and (code[~has] == 0).all(), case
            detail = tab["status_detail"].to_pylist()
            assert {detail[i] for i in np.flatnonzero(has)} == {CONE_DETAILS[case]}
            assert all(conv[~has]) and all(c is None for c in conv[has])
        else:
            assert (code == 0).all() and all(conv), case
    one = pq.read_table(out / logs["one valid"].name)["contacts"].to_pylist()
    assert one[10][0]["cone_active"] is not None and all(
        not r for i, r in enumerate(one) if i != 10
    )


# --------------------------------------------------------------------------- properties
NV = 7  # joints of the bundled arm


@pytest.fixture(scope="module")
def arm():
    torch.set_num_threads(1)
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


def _numbers(kind: str, rows: list, width: int | None) -> pa.Array:
    """Rows of floats (None: null row; NaN kept) as a list column of ``kind``."""

    def conv(v):
        if v is None or kind in ("float64", "float32"):
            return v
        if v != v:  # NaN has no int, decimal or string form: a null entry
            return None
        return {"int64": int, "decimal": lambda x: decimal.Decimal(f"{x:.4f}"),
                "string": repr, "bool": bool}[kind](v)  # fmt: skip

    typ = {"float64": pa.float64(), "float32": pa.float32(), "int64": pa.int64(),
           "decimal": pa.decimal128(12, 4), "string": pa.string(), "bool": pa.bool_()}[kind]  # fmt: skip
    vals = [None if r is None else [conv(v) for v in r] for r in rows]
    if width is not None and all(r is None or len(r) == width for r in vals):
        return pa.array(vals, pa.list_(typ, width))
    return pa.array(vals, pa.list_(typ))


@st.composite
def logs(draw):
    """A small log of the arm: random column types, row lengths, nulls, NaN and stamp orders."""
    n = draw(st.integers(0, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))

    def rows(width, scale=1.0, walk=False):
        """Rows of ``width`` numbers, one in four malformed: null, short, long or with a NaN."""
        vals = scale * rng.normal(size=(n, width))
        if walk:  # joint angles: a slow random walk, so derived velocities stay plausible
            vals = np.cumsum(0.01 * vals, 0)
        out = []
        for v in vals.tolist():
            r = draw(st.sampled_from(["ok"] * 12 + ["null", "short", "long", "nan"]))
            if r == "null":
                out.append(None)
            elif r == "short":
                out.append(v[:-1])
            elif r == "long":
                out.append(v + [0.0])
            else:
                if r == "nan":
                    v[rng.integers(width)] = float("nan")
                out.append(v)
        return out

    kinds = st.sampled_from(["float64"] * 3 + ["float32", "int64", "decimal", "string", "bool"])
    cols: dict[str, pa.Array] = {}
    order = draw(st.sampled_from(["increasing", "repeated", "backward", "random", "null"]))
    t = np.cumsum(rng.integers(5_000_000, 15_000_000, n))
    if order == "repeated":
        t = np.repeat(t[::2], 2)[:n]
    elif order == "backward":
        t = t[::-1].copy()
    elif order == "random":
        t = rng.permutation(t)
    stamps = t.tolist()
    if order == "null" and n > 1:
        stamps[rng.integers(n)] = None
    t_type = draw(st.sampled_from(["int64"] * 4 + ["int32", "uint64", "timestamp", "float64",
                                                    "string"]))  # fmt: skip
    if t_type == "string":
        cols["t_ns"] = pa.array([None if s is None else str(s) for s in stamps])
    elif t_type == "timestamp":
        cols["t_ns"] = pa.array(stamps, pa.timestamp("ns"))
    elif t_type == "float64":
        cols["t_ns"] = pa.array([None if s is None else float(s) for s in stamps])
    else:
        cols["t_ns"] = pa.array(stamps, getattr(pa, t_type)())
    cols["q"] = _numbers(draw(kinds), rows(NV, walk=True), NV)
    if draw(st.booleans()):  # logged derivatives, else derived from q and t_ns
        cols["qd"] = _numbers(draw(kinds), rows(NV, 0.1), NV)
        cols["qdd"] = _numbers(draw(kinds), rows(NV, 0.1), NV)
    cols["ft.base_ft"] = _numbers(draw(kinds), rows(6, 5.0), 6)
    if draw(st.booleans()):
        links = st.sampled_from(["hand_skin", "forearm_skin", "nowhere", None])
        kinds_c = st.sampled_from(["force", "force", "wrench", "force_dir", "known", "bogus"])
        positions = st.sampled_from([list(rng.normal(size=3) * 0.01), None, [0.0, np.nan, 0.0],
                                     [0.0]])  # fmt: skip
        records = [
            None if k == 0 and draw(st.booleans()) else [
                {"link": draw(links), "kind": draw(kinds_c), "position": draw(positions),
                 "direction": [0.0, 0.0, -1.0], "wrench": None}
                for _ in range(k)]
            for k in (draw(st.integers(0, 2)) for _ in range(n))
        ]  # fmt: skip
        pos_kind = draw(st.sampled_from(["float64"] * 4 + ["float32", "int64", "string"]))
        flat = [c for r in records if r for c in r]
        pos = _numbers(pos_kind, [c["position"] for c in flat], None)
        link_type = draw(st.sampled_from([pa.string()] * 4 + [pa.large_string(), pa.int64()]))
        links_arr = pa.array([c["link"] for c in flat], pa.string())
        if pa.types.is_integer(link_type):
            links_arr = pa.array(
                [None if c["link"] is None else len(c["link"]) for c in flat], pa.int64()
            )
        struct = pa.StructArray.from_arrays(
            [links_arr.cast(link_type) if not pa.types.is_integer(link_type) else links_arr,
             pa.array([c["kind"] for c in flat], pa.string()), pos,
             pa.array([c["direction"] for c in flat], pa.list_(pa.float64(), 3)),
             pa.array([None] * len(flat), pa.list_(pa.float64(), 6))],
            ["link", "kind", "position", "direction", "wrench"])  # fmt: skip
        offsets = np.r_[0, np.cumsum([len(r or []) for r in records])].astype(np.int32)
        mask = pa.array([r is None for r in records], pa.bool_())
        cols["contacts"] = pa.ListArray.from_arrays(pa.array(offsets), struct, mask=mask)
    return n, cols


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                 HealthCheck.data_too_large])  # fmt: skip
@given(log=logs())
def test_decoding_gives_a_status_per_frame_or_one_clean_error(log, arm, tmp_path_factory):
    n, cols = log
    d = tmp_path_factory.mktemp("prop")
    meta = {b"torchcontact.joint_names": json.dumps(list(arm.joint_names))}
    path = d / "log.parquet"
    pq.write_table(pa.table(cols).replace_schema_metadata(meta), path)
    out = d / "out.parquet"
    try:
        summary = estimate_file(path, arm, out, batch_size=5, progress=False)
    except TorchContactError as exc:  # one clean error, naming what is wrong
        assert str(exc) and "\n" not in str(exc).strip()
        return
    tab = pq.read_table(out)
    assert summary["frames"] == n and tab.num_rows == n
    codes = tab["status_code"].to_pylist()
    assert all(isinstance(c, int) and c >= 0 for c in codes)
    details = tab["status_detail"].to_pylist()
    for c, text, jt in zip(codes, details, tab["joint_torques"].to_pylist(), strict=True):
        if c:  # a bad frame says why (a bit, maybe a detail) and has no numbers
            assert tab["status"].to_pylist()[codes.index(c)] != "ok"
            assert all(v != v for v in jt)
        else:
            assert all(np.isfinite(jt)) and text is None
