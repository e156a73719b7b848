"""Import ROS 1 / ROS 2 bags (sqlite3 and MCAP, via ``rosbags``; no ROS install) and CSV files.

Bags: ``sensor_msgs/JointState`` (``--joint-states``) and ``geometry_msgs/WrenchStamped``
(``--wrench TOPIC[=SENSOR]``, repeatable). One output row per message of the first wrench topic
(its header stamp, ns). Joint states are read *per joint name*: several publishers on one topic
(an arm and a gripper driver, each naming its own joints) merge, and each joint's positions (and
velocities, when every message of every kept joint has them) are linearly interpolated to the
output stamps; other wrench topics likewise. Frames outside the time range every kept joint
covers are dropped. ``qdd`` is left out (the estimator derives it).

Joints: with a robot (``--robot``), its joints in its order (other joints on the topic, e.g. a
gripper's or mimic joints, are dropped; a robot joint the bag lacks is an error); with
``--joints``, those; ``--drop-joints`` removes names; with none of these, every joint seen.

Sensor names: ``TOPIC=SENSOR`` names the column ``ft.SENSOR``. Without ``=SENSOR`` the header's
``frame_id`` is used, mapped to the robot's sensor whose frame it is (the sensor's name, or the
link its reading is expressed in: the child link for ``<frame>child``, the parent link for
``parent``).

Contacts: a ``geometry_msgs/PointStamped`` topic (frame_id = link, point = position in that link's
frame, a pure-force contact on the nearest F/T frame) and/or a contact-spec file (TOML or JSON,
:func:`torchcontact.contacts.load_contact_spec`, with optional ``start_ns``/``end_ns`` ranges).

CSV: a header with ``t_ns``, ``q.<joint>`` (and optionally ``qd.<joint>``, ``qdd.<joint>``) and
``ft.<sensor>.fx .fy .fz .mx .my .mz``; joints are named by the column suffixes.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.contacts import ContactRecords, ContactSpec, load_contact_spec
from torchcontact.errors import ConvertError, InputError
from torchcontact.logs.format import (
    META_JOINT_NAMES,
    META_SOURCE,
    META_URDF_SHA256,
    check_outputs,
    contact_struct_type,
    contacts_column,
    fixed_list,
    ft_column,
    robot_metadata,
    write_table,
)

__all__ = ["ConvertError", "convert", "select_joints", "sensor_for_frame"]

AXES = ("fx", "fy", "fz", "mx", "my", "mz")


def _stamp(msg: Any, fallback: int) -> int:
    h = getattr(msg, "header", None)
    if h is None:
        return fallback
    st = h.stamp
    ns = int(st.sec) * 1_000_000_000 + int(getattr(st, "nanosec", getattr(st, "nsec", 0)))
    return ns if ns > 0 else fallback


def select_joints(
    seen: Sequence[str],
    *,
    model: Any = None,
    joints: Sequence[str] | None = None,
    drop: Sequence[str] = (),
    source: object = "",
) -> list[str]:
    """The joints to keep, in output order.

    Args:
        seen: joint names in the input, in order of first appearance.
        model: a :class:`~torchcontact.RobotModel`: keep its joints, in its order.
        joints: keep these, in this order (instead of ``model``'s).
        drop: remove these names.
        source: input name for messages.

    Returns:
        The kept joint names.

    Raises:
        ConvertError: a wanted joint the input lacks, a dropped name it does not have, or no
            joint left.

    Example:
        >>> select_joints(["a", "b", "grip"], joints=["b", "a"])
        ['b', 'a']
        >>> select_joints(["a", "b", "grip"], drop=["grip"])
        ['a', 'b']
    """
    seen = list(seen)
    unknown = [d for d in drop if d not in seen]
    if unknown:
        raise ConvertError(
            f"{source}: --drop-joints {unknown} are not in the input (it has {seen})"
        )
    if joints is not None:
        keep, what = list(joints), "--joints"
    elif model is not None:
        keep, what = list(model.joint_names), f"robot {model.name!r}"
    else:
        keep, what = seen, ""
    keep = [j for j in keep if j not in set(drop)]
    missing = [j for j in keep if j not in seen]
    if missing:
        raise ConvertError(
            f"{source}: joints {missing} of {what} are not in the input (it has {seen})"
        )
    if not keep:
        raise ConvertError(f"{source}: no joint left to write")
    return keep


def sensor_for_frame(model: Any, frame_id: str) -> str | None:
    """The robot's F/T sensor whose reading frame is ``frame_id``, or None.

    A sensor matches by its name, its joint's name, or the link its reading is expressed in
    (the child link for ``<frame>child``, the parent link for ``parent``).

    Raises:
        ConvertError: several sensors match.
    """
    if model is None or not frame_id:
        return None
    found = []
    for name, s in model.ft_sensors.items():
        names = {name, s.joint}
        if s.frame == "child":
            names.add(model.body_names[s.child_body])
        elif s.frame == "parent":
            names.add(model.joint_parent_link.get(s.joint, ""))
        if frame_id in names:
            found.append(name)
    if len(found) > 1:
        raise ConvertError(
            f"frame_id {frame_id!r} matches several sensors {found}: use TOPIC=SENSOR"
        )
    return found[0] if found else None


def _contact_records(
    t_ns: np.ndarray, spec: ContactSpec | None, points: Sequence[tuple[int, str, list]]
) -> ContactRecords:
    """Records of the spec's entries and of the contact points (nearest frame), by frame."""
    parts = [spec.at(t_ns)] if spec is not None else []
    if points and len(t_ns):
        stamps = np.array([p[0] for p in points])
        j = np.searchsorted(t_ns, stamps).clip(0, len(t_ns) - 1)
        prev = (j - 1).clip(0)
        nearest = np.where(np.abs(t_ns[prev] - stamps) <= np.abs(t_ns[j] - stamps), prev, j)
        parts.append(
            ContactRecords(
                nearest,
                [p[1] for p in points],
                ["force"] * len(points),
                np.array([p[2] for p in points], np.float64).reshape(-1, 3),
            )
        )
    if not parts:
        return ContactRecords.empty()
    cat = ContactRecords.concat(parts)
    return cat.select(np.argsort(cat.frame, kind="stable"))


def _interp(t: np.ndarray, ts: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, ts, x[:, j]) for j in range(x.shape[1])], -1)


def _write(out: Path, cols: dict, joint_names: Sequence[str], source: str, robot: dict) -> dict:
    import pyarrow as pa

    meta = {META_JOINT_NAMES: json.dumps(list(joint_names)), META_SOURCE: source, **robot}
    table = pa.table(cols).replace_schema_metadata(meta)
    write_table(table, out)
    return {
        "output": str(out),
        "frames": table.num_rows,
        "columns": table.column_names,
        "joints": list(joint_names),
    }


def _convert_csv(
    path: Path, out: Path, spec: ContactSpec | None, select: dict, model: Any, robot: dict
) -> dict:
    import pyarrow.csv as pcsv

    try:
        tab = pcsv.read_csv(path)
    except Exception as exc:
        raise ConvertError(f"{path}: not a readable CSV file ({exc})") from None
    names = tab.column_names
    if "t_ns" not in names:
        raise ConvertError(f"{path}: needs a t_ns column (found {names[:8]}...)")
    seen = [n[2:] for n in names if n.startswith("q.")]
    if not seen:
        raise ConvertError(f"{path}: no q.<joint> columns")
    joints = select_joints(seen, model=model, source=path, **select)
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
    rec = _contact_records(t, spec, [])
    cols["contacts"] = contacts_column(
        rec, len(t), struct_type=contact_struct_type(cone=bool(rec.cone_fields))
    )
    return _write(out, cols, joints, f"csv:{path.name}", robot)


class _JointSeries:
    """Per joint name: time stamps, positions and velocities of every message naming it."""

    def __init__(self) -> None:
        self.t: dict[str, list[int]] = {}
        self.q: dict[str, list[float]] = {}
        self.qd: dict[str, list[float]] = {}

    def add(self, t: int, msg: Any) -> None:
        names = list(msg.name)
        pos = np.asarray(msg.position, float)
        vel = np.asarray(msg.velocity, float)
        if len(pos) != len(names):
            return  # a message without positions for its names carries nothing usable here
        has_vel = len(vel) == len(names)
        for i, n in enumerate(names):
            self.t.setdefault(n, []).append(t)
            self.q.setdefault(n, []).append(pos[i])
            self.qd.setdefault(n, []).append(vel[i] if has_vel else np.nan)

    def series(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(self.t[name], np.int64)
        o = np.argsort(t, kind="stable")
        return t[o], np.asarray(self.q[name])[o], np.asarray(self.qd[name])[o]


def _warn_unknown_sensor(path: Path, topic: str, model: Any, column: str, fid: str | None) -> None:
    """Warn that a wrench topic's readings name no F/T sensor of the robot (the column stays)."""
    what = f"its frame_id {fid!r}" if fid is not None else f"sensor {column!r}"
    sensors = list(model.ft_sensors) or "none (declare one with --ft-sensor)"
    warnings.warn(
        f"{path}: {topic}: {what} names no F/T sensor of {model.name} (its sensors: {sensors},"
        " matched by sensor, joint or reading-frame link name); the readings are written as"
        f" ft.{column}, which estimate will not use for a sensor of {model.name}: name the"
        f" sensor with --wrench {topic}=SENSOR",
        UserWarning,
        stacklevel=3,
    )


def _convert_bag(
    path: Path,
    out: Path,
    joint_states: str,
    wrench_topics: Sequence[str],
    contacts_topic: str | None,
    spec: ContactSpec | None,
    select: dict,
    model: Any,
    progress: bool,
    robot: dict,
) -> dict:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from tqdm import tqdm

    if not wrench_topics:
        raise ConvertError(f"{path}: name at least one WrenchStamped topic with --wrench")
    wrench = {}
    for w in wrench_topics:
        topic, _, sensor = w.partition("=")
        wrench[topic] = sensor or None
    for topic, sensor in wrench.items():
        if model is not None and sensor is not None and sensor not in model.ft_sensors:
            _warn_unknown_sensor(path, topic, model, sensor, None)
    js = _JointSeries()
    ft: dict[str, tuple[list, list, str | None]] = {t: ([], [], s) for t, s in wrench.items()}
    points: list[tuple[int, str, list]] = []
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:
        raise ConvertError(f"{path}: not a readable ROS 1/2 bag ({exc})") from None
    try:
        topics = {c.topic for c in reader.connections}
        for need in [joint_states, *wrench, *([contacts_topic] if contacts_topic else [])]:
            if need not in topics:
                raise ConvertError(f"{path}: no topic {need!r} (topics: {sorted(topics)})")
        wanted = [
            c for c in reader.connections if c.topic in {joint_states, *wrench, contacts_topic}
        ]
        total = sum(getattr(c, "msgcount", 0) for c in wanted) or None
        bar = tqdm(total=total, unit="msgs", desc=f"convert {path.name}", disable=not progress)
        try:
            for conn, ts, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                t = _stamp(msg, ts)
                bar.update(1)
                if conn.topic == joint_states:
                    js.add(t, msg)
                elif conn.topic in ft:
                    f, tq = msg.wrench.force, msg.wrench.torque
                    ft[conn.topic][0].append(t)
                    ft[conn.topic][1].append([f.x, f.y, f.z, tq.x, tq.y, tq.z])
                    if ft[conn.topic][2] is None:
                        fid = msg.header.frame_id
                        found = sensor_for_frame(model, fid)
                        name = found or fid or conn.topic.strip("/").replace("/", "_")
                        ft[conn.topic] = (ft[conn.topic][0], ft[conn.topic][1], name)
                        if model is not None and found is None:
                            _warn_unknown_sensor(path, conn.topic, model, name, fid)
                else:
                    p = msg.point
                    points.append((t, msg.header.frame_id, [p.x, p.y, p.z]))
        finally:
            bar.close()
    finally:
        reader.close()
    if not js.t:
        raise ConvertError(f"{path}: no messages on {joint_states}")
    joints = select_joints(list(js.t), model=model, source=path, **select)
    series = {j: js.series(j) for j in joints}
    lo = max(s[0][0] for s in series.values())
    hi = min(s[0][-1] for s in series.values())
    first = next(iter(ft))
    t = np.asarray(ft[first][0], np.int64)
    if not len(t):
        raise ConvertError(f"{path}: no messages on {first}")
    t = np.sort(t, kind="stable")
    t = t[(t >= lo) & (t <= hi)]
    if not len(t):
        raise ConvertError(
            f"{path}: no {first} message falls in the time range every kept joint covers"
        )
    q = np.stack([np.interp(t, *series[j][:2]) for j in joints], -1)
    cols: dict[str, Any] = {"t_ns": t, "q": fixed_list(q)}
    if all(np.isfinite(series[j][2]).all() for j in joints):
        cols["qd"] = fixed_list(np.stack([np.interp(t, s[0], s[2]) for s in series.values()], -1))
    for _topic, (ts, vals, sensor) in ft.items():
        ts_a = np.asarray(ts, np.int64)
        o = np.argsort(ts_a, kind="stable")
        col = ft_column(sensor or "ft")
        if col in cols:
            raise ConvertError(f"{path}: two wrench topics would both write {col}: name them")
        cols[col] = fixed_list(_interp(t, ts_a[o], np.asarray(vals)[o]))
    rec = _contact_records(t, spec, points)
    cols["contacts"] = contacts_column(
        rec, len(t), struct_type=contact_struct_type(cone=bool(rec.cone_fields))
    )
    return _write(out, cols, joints, f"bag:{path.name}", robot)


def convert(
    input: str | Path,
    out: str | Path,
    *,
    joint_states: str = "/joint_states",
    wrench_topics: Sequence[str] | None = None,
    contacts_topic: str | None = None,
    contacts_file: str | Path | None = None,
    robot: Any = None,
    joints: Sequence[str] | None = None,
    drop_joints: Sequence[str] = (),
    progress: bool = False,
) -> dict:
    """Convert a ROS 1 bag, a ROS 2 bag folder/file (sqlite3 or MCAP) or a CSV to the log format.

    Args:
        input: ``.bag`` (ROS 1), a ROS 2 bag folder or ``.db3``/``.mcap`` file, or ``.csv``.
        out: output Parquet file.
        joint_states: ``sensor_msgs/JointState`` topic (any number of publishers).
        wrench_topics: ``geometry_msgs/WrenchStamped`` topics, each ``TOPIC`` or ``TOPIC=SENSOR``.
        contacts_topic: ``geometry_msgs/PointStamped`` topic of contact points (frame_id = link).
        contacts_file: contact-spec file (TOML or JSON, see module doc).
        robot: ``tcarm``, ``icub``, a URDF path, a :class:`~torchcontact.robots.RobotSpec` or a
            :class:`~torchcontact.RobotModel`: keep its joints (in its order), name F/T columns
            after its sensors (a wrench topic naming none of them is kept with a warning), and
            record the robot in the log's metadata (name or path with its URDF sha256; only the
            sha256 for a model) for ``estimate`` without ``--robot``.
        joints: keep these joints, in this order.
        drop_joints: drop these joints.
        progress: show a progress bar over the bag's messages.

    Returns:
        Summary dict: output, frames, columns, joints.

    Raises:
        ConvertError: unreadable input, missing topics/columns/joints (names the file).
        InputError: an output that is, or contains, an input; a bad contact spec.
    """
    from torchcontact.model import RobotModel
    from torchcontact.robots import RobotSpec

    path, out = Path(input), Path(out)
    if isinstance(robot, (str, Path)):
        robot = RobotSpec.of(robot)
    robot_path = robot if isinstance(robot, RobotSpec) else None
    check_outputs([out, out.with_name(out.name + ".tmp")], [path, contacts_file, robot_path])
    if not path.exists():
        raise ConvertError(f"{path}: no such file or folder")
    if joints is not None and robot is not None:
        raise InputError("give --joints or --robot to select joints, not both")
    model, meta = robot, {}
    if robot_path is not None:
        from torchcontact.logs.pipeline import load_robot

        model = load_robot(robot_path)
        # the robot in the log's metadata: estimate without --robot finds it
        sensors = [str(s) for s in robot_path.ft_sensors]
        meta = robot_metadata(robot_path.robot, model.urdf_sha256, sensors)
    elif robot is not None and not isinstance(robot, RobotModel):
        raise InputError(
            f"robot must be a URDF path, a RobotSpec or a RobotModel, got {type(robot).__name__}"
        )
    elif robot is not None:
        meta = {META_URDF_SHA256: robot.urdf_sha256}
    spec = load_contact_spec(contacts_file) if contacts_file else None
    select = {"joints": joints, "drop": list(drop_joints)}
    if path.suffix.lower() == ".csv":
        return _convert_csv(path, out, spec, select, model, meta)
    return _convert_bag(
        path,
        out,
        joint_states,
        wrench_topics or [],
        contacts_topic,
        spec,
        select,
        model,
        progress,
        meta,
    )
