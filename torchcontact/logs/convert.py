"""Import ROS 1 / ROS 2 bags (sqlite3 and MCAP, via ``rosbags``; no ROS install) and CSV files.

Bags: ``sensor_msgs/JointState`` (``--joint-states``) and ``geometry_msgs/WrenchStamped``
(``--wrench TOPIC[=SENSOR]``, repeatable; the sensor name defaults to the header's frame_id).
One output row per message of the first wrench topic (its header stamp, ns); joint positions,
and velocities when every message has them, are linearly interpolated to those stamps, other
wrench topics likewise. Frames outside the joint-state time range are dropped. ``qdd`` is left
out (the estimator derives it). Contacts: a ``geometry_msgs/PointStamped`` topic (frame_id = link,
point = position in that link's frame, a pure-force contact on the nearest F/T frame) and/or a
TOML contact-spec file::

    [[contact]]
    link = "forearm_skin"
    kind = "force"            # wrench | force | force_dir | known
    position = [0.0, 0.0, 0.0]
    direction = [0, 0, -1]    # force_dir only
    wrench = [0, 0, 0, 0, 0, 0]  # known only
    start_ns = 0              # optional time range (inclusive)
    end_ns = 5_000_000_000

CSV: a header with ``t_ns``, ``q.<joint>`` (and optionally ``qd.<joint>``, ``qdd.<joint>``) and
``ft.<sensor>.fx .fy .fz .mx .my .mz``; joints are named by the column suffixes.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import ConvertError  # noqa: F401  (re-exported)
from torchcontact.logs.format import META_JOINT_NAMES, contact_struct_type, fixed_list, ft_column

__all__ = ["ConvertError", "convert"]

AXES = ("fx", "fy", "fz", "mx", "my", "mz")


def _stamp(msg: Any, fallback: int) -> int:
    h = getattr(msg, "header", None)
    if h is None:
        return fallback
    st = h.stamp
    ns = int(st.sec) * 1_000_000_000 + int(getattr(st, "nanosec", getattr(st, "nsec", 0)))
    return ns if ns > 0 else fallback


def _load_spec(path: str | Path) -> list[dict]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    try:
        spec = tomllib.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ConvertError(f"{path}: not a readable TOML contact spec ({exc})") from None
    items = spec.get("contact", [])
    for i, c in enumerate(items):
        if "link" not in c or "position" not in c:
            raise ConvertError(f"{path}: contact {i} needs link and position")
    return items


def _contacts_column(
    t_ns: np.ndarray, spec: Sequence[dict], points: Sequence[tuple[int, str, list]]
) -> Any:
    import pyarrow as pa

    rows: list[list[dict]] = [[] for _ in range(len(t_ns))]
    for c in spec:
        lo, hi = c.get("start_ns", -(2**63)), c.get("end_ns", 2**63 - 1)
        entry = {
            "link": c["link"],
            "kind": c.get("kind", "force"),
            "position": [float(x) for x in c["position"]],
            "direction": c.get("direction"),
            "wrench": c.get("wrench"),
        }
        for i in np.flatnonzero((t_ns >= lo) & (t_ns <= hi)):
            rows[i].append(entry)
    if points and len(t_ns):
        stamps = np.array([p[0] for p in points])
        j = np.clip(np.searchsorted(t_ns, stamps), 1, len(t_ns) - 1)
        nearest = np.where(np.abs(t_ns[j - 1] - stamps) <= np.abs(t_ns[j] - stamps), j - 1, j)
        for (_, link, pos), i in zip(points, nearest, strict=True):
            rows[i].append(
                {"link": link, "kind": "force", "position": pos, "direction": None, "wrench": None}
            )
    return pa.array(rows, pa.list_(contact_struct_type()))


def _interp(t: np.ndarray, ts: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, ts, x[:, j]) for j in range(x.shape[1])], -1)


def _write(out: Path, cols: dict, joint_names: Sequence[str], source: str) -> dict:
    import pyarrow as pa
    import pyarrow.parquet as pq

    meta = {META_JOINT_NAMES: json.dumps(list(joint_names)), b"torchcontact.source": source}
    table = pa.table(cols).replace_schema_metadata(meta)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    pq.write_table(table, tmp)
    tmp.replace(out)
    return {"output": str(out), "frames": table.num_rows, "columns": table.column_names}


def _convert_csv(path: Path, out: Path, spec: list[dict]) -> dict:
    import pyarrow.csv as pcsv

    try:
        tab = pcsv.read_csv(path)
    except Exception as exc:
        raise ConvertError(f"{path}: not a readable CSV file ({exc})") from None
    names = tab.column_names
    if "t_ns" not in names:
        raise ConvertError(f"{path}: needs a t_ns column (found {names[:8]}...)")
    joints = [n[2:] for n in names if n.startswith("q.")]
    if not joints:
        raise ConvertError(f"{path}: no q.<joint> columns")
    t = tab.column("t_ns").to_numpy().astype(np.int64)

    def block(prefix: str, keys: Sequence[str]) -> np.ndarray | None:
        cols = [f"{prefix}{k}" for k in keys]
        if not all(c in names for c in cols):
            return None
        return np.stack([tab.column(c).to_numpy().astype(np.float64) for c in cols], -1)

    cols: dict[str, Any] = {"t_ns": t}
    for v in ("q", "qd", "qdd"):
        arr = block(f"{v}.", joints)
        if arr is not None:
            cols[v] = fixed_list(arr)
    sensors = sorted({n.split(".")[1] for n in names if n.startswith("ft.")})
    if not sensors:
        raise ConvertError(f"{path}: no ft.<sensor>.fx ... columns")
    for s in sensors:
        arr = block(f"ft.{s}.", AXES)
        if arr is None:
            raise ConvertError(f"{path}: ft.{s} needs columns {[f'ft.{s}.{a}' for a in AXES]}")
        cols[ft_column(s)] = fixed_list(arr)
    cols["contacts"] = _contacts_column(t, spec, [])
    return _write(out, cols, joints, f"csv:{path.name}")


def _convert_bag(
    path: Path,
    out: Path,
    joint_states: str,
    wrench_topics: Sequence[str],
    contacts_topic: str | None,
    spec: list[dict],
) -> dict:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not wrench_topics:
        raise ConvertError(f"{path}: name at least one WrenchStamped topic with --wrench")
    wrench = {}
    for w in wrench_topics:
        topic, _, sensor = w.partition("=")
        wrench[topic] = sensor or None
    js_t, js_names, js_q, js_qd = [], None, [], []
    ft: dict[str, tuple[list, list, str | None]] = {t: ([], [], s) for t, s in wrench.items()}
    points: list[tuple[int, str, list]] = []
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:
        raise ConvertError(f"{path}: not a readable ROS 1/2 bag ({exc})") from None
    try:
        topics = {c.topic for c in reader.connections}
        for need in [joint_states, *wrench]:
            if need not in topics:
                raise ConvertError(f"{path}: no topic {need!r} (topics: {sorted(topics)})")
        wanted = [
            c for c in reader.connections if c.topic in {joint_states, *wrench, contacts_topic}
        ]
        for conn, ts, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, conn.msgtype)
            t = _stamp(msg, ts)
            if conn.topic == joint_states:
                names = list(msg.name)
                if js_names is None:
                    js_names = names
                order = [names.index(n) for n in js_names] if names != js_names else None
                q = np.asarray(msg.position, float)
                qd = np.asarray(msg.velocity, float)
                js_t.append(t)
                js_q.append(q if order is None else q[order])
                js_qd.append(
                    (qd if order is None else qd[order]) if len(qd) == len(names) else None
                )
            elif conn.topic in ft:
                f, tq = msg.wrench.force, msg.wrench.torque
                ft[conn.topic][0].append(t)
                ft[conn.topic][1].append([f.x, f.y, f.z, tq.x, tq.y, tq.z])
                if ft[conn.topic][2] is None:
                    name = msg.header.frame_id or conn.topic.strip("/").replace("/", "_")
                    ft[conn.topic] = (ft[conn.topic][0], ft[conn.topic][1], name)
            else:
                p = msg.point
                points.append((t, msg.header.frame_id, [p.x, p.y, p.z]))
    finally:
        reader.close()
    if not js_t:
        raise ConvertError(f"{path}: no messages on {joint_states}")
    jt = np.asarray(js_t)
    order = np.argsort(jt, kind="stable")
    jt, jq = jt[order], np.stack(js_q)[order]
    first = next(iter(ft))
    t = np.asarray(ft[first][0], np.int64)
    if not len(t):
        raise ConvertError(f"{path}: no messages on {first}")
    keep = (t >= jt[0]) & (t <= jt[-1])
    t = t[keep]
    cols: dict[str, Any] = {"t_ns": t, "q": fixed_list(_interp(t, jt, jq))}
    if all(v is not None for v in js_qd):
        cols["qd"] = fixed_list(_interp(t, jt, np.stack(js_qd)[order]))
    for _topic, (ts, vals, sensor) in ft.items():
        ts_a = np.asarray(ts, np.int64)
        o = np.argsort(ts_a, kind="stable")
        cols[ft_column(sensor or "ft")] = fixed_list(_interp(t, ts_a[o], np.asarray(vals)[o]))
    cols["contacts"] = _contacts_column(t, spec, points)
    return _write(out, cols, js_names or [], f"bag:{path.name}")


def convert(
    input: str | Path,
    out: str | Path,
    *,
    joint_states: str = "/joint_states",
    wrench_topics: Sequence[str] | None = None,
    contacts_topic: str | None = None,
    contacts_file: str | Path | None = None,
) -> dict:
    """Convert a ROS 1 bag, a ROS 2 bag folder/file (sqlite3 or MCAP) or a CSV to the log format.

    Args:
        input: ``.bag`` (ROS 1), a ROS 2 bag folder or ``.db3``/``.mcap`` file, or ``.csv``.
        out: output Parquet file.
        joint_states: ``sensor_msgs/JointState`` topic.
        wrench_topics: ``geometry_msgs/WrenchStamped`` topics, each ``TOPIC`` or ``TOPIC=SENSOR``.
        contacts_topic: ``geometry_msgs/PointStamped`` topic of contact points (frame_id = link).
        contacts_file: TOML contact spec (see module doc).

    Returns:
        Summary dict: output, frames, columns.

    Raises:
        ConvertError: unreadable input or missing topics/columns (names the file).
    """
    path, out = Path(input), Path(out)
    if not path.exists():
        raise ConvertError(f"{path}: no such file or folder")
    spec = _load_spec(contacts_file) if contacts_file else []
    if path.suffix.lower() == ".csv":
        return _convert_csv(path, out, spec)
    return _convert_bag(path, out, joint_states, wrench_topics or [], contacts_topic, spec)
