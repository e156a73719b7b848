"""Bags made here with rosbags' own writers (ROS 1 v2.0 bag, ROS 2 sqlite3 and MCAP), from the
simulated log fixture; no ROS install."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from torchcontact.cli import main  # noqa: E402
from torchcontact.logs import estimate_file  # noqa: E402
from torchcontact.logs.convert import ConvertError, convert  # noqa: E402
from torchcontact.robots import tcarm_path  # noqa: E402

N = 120


def _frames(sim_log):
    tab = pq.read_table(sim_log).slice(0, N)
    names = json.loads(tab.schema.metadata[b"torchcontact.joint_names"])
    t = tab["t_ns"].to_numpy() + 1_000_000_000  # ROS stamps start after 0
    q = np.stack(tab["q"].to_numpy(zero_copy_only=False))
    qd = np.stack(tab["qd"].to_numpy(zero_copy_only=False))
    ft = np.stack(tab["ft.base_ft"].to_numpy(zero_copy_only=False))
    return names, t, q, qd, ft


def _write_bag(kind, path, sim_log, publishers="one", frame_id="base_ft"):
    """``publishers``: "one" (the arm), "gripper" (the arm plus an extra gripper joint in the
    same messages), "two" (arm and gripper drivers publishing separately on /joint_states, the
    gripper at a third of the rate and with other stamps)."""
    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    names, t, q, qd, ft = _frames(sim_log)
    # joint names in another order than the model's: the pipeline maps them by name
    perm = np.arange(len(names))[::-1]

    def header(tt, fid=frame_id):
        stamp = Time(sec=int(tt // 10**9), nanosec=int(tt % 10**9))
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=fid)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=fid)

    JS = T["sensor_msgs/msg/JointState"]
    msgs = []
    for i in range(N):
        arm = [names[j] for j in perm]
        if publishers == "gripper":  # one message with an extra joint
            js = JS(header=header(t[i]), name=[*arm, "gripper_finger"],
                    position=np.r_[q[i, perm], 0.01], velocity=np.r_[qd[i, perm], 0.0],
                    effort=np.zeros(0))  # fmt: skip
        else:
            js = JS(header=header(t[i]), name=arm, position=q[i, perm], velocity=qd[i, perm],
                    effort=np.zeros(0))  # fmt: skip
        if publishers == "two" and i % 3 == 0:  # the gripper's driver, stamps in between
            tg = t[i] + 3_000_000
            g = JS(header=header(tg), name=["gripper_finger"], position=np.array([0.02]),
                   velocity=np.zeros(0), effort=np.zeros(0))  # fmt: skip
            msgs += [("/joint_states", "sensor_msgs/msg/JointState", tg, g)]
        V3 = T["geometry_msgs/msg/Vector3"]
        w = T["geometry_msgs/msg/WrenchStamped"](
            header=header(t[i]),
            wrench=T["geometry_msgs/msg/Wrench"](force=V3(*ft[i, :3]), torque=V3(*ft[i, 3:])),
        )
        msgs += [("/joint_states", "sensor_msgs/msg/JointState", t[i], js)]
        msgs += [("/ft", "geometry_msgs/msg/WrenchStamped", t[i], w)]
    h = header(t[50])
    h.frame_id = "forearm_skin"
    pt = T["geometry_msgs/msg/PointStamped"](
        header=h, point=T["geometry_msgs/msg/Point"](0.01, 0.0, 0.0)
    )
    msgs.append(("/contacts", "geometry_msgs/msg/PointStamped", t[50], pt))
    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        conns = {}
        for topic, mtype, _, _ in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, mtype, typestore=ts)
        for topic, mtype, stamp, msg in msgs:
            data = ts.serialize_ros1(msg, mtype) if ros1 else ts.serialize_cdr(msg, mtype)
            writer.write(conns[topic], int(stamp), data)
    return names, t, q


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_bag_to_log_and_estimate(kind, sim_log, model, tmp_path):
    bag = tmp_path / ("in.bag" if kind == "ros1" else "bag2")
    names, t, q = _write_bag(kind, bag, sim_log)
    out = tmp_path / "log.parquet"
    s = convert(bag, out, wrench_topics=["/ft=base_ft"], contacts_topic="/contacts")
    assert s["frames"] == N
    tab = pq.read_table(out)
    assert tab["t_ns"].to_numpy().tolist() == t.tolist()
    got_names = json.loads(tab.schema.metadata[b"torchcontact.joint_names"])
    assert got_names == names[::-1]
    q_got = np.stack(tab["q"].to_numpy(zero_copy_only=False))[:, ::-1]
    np.testing.assert_allclose(q_got, q, rtol=0, atol=1e-12)
    contacts = tab["contacts"].to_pylist()
    assert contacts[50] == [
        dict(
            link="forearm_skin",
            kind="force",
            position=[0.01, 0.0, 0.0],
            direction=None,
            wrench=None,
        )
    ]
    assert sum(map(len, contacts)) == 1
    res = estimate_file(out, model, tmp_path / "est.parquet")
    assert res["derived"] == ["qdd"] and res["frames"] == N
    assert set(pq.read_table(res["output"])["status"].to_pylist()) == {"ok"}


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
@pytest.mark.parametrize("publishers", ["gripper", "two"])
def test_extra_joints_and_two_publishers_convert_and_estimate(
    kind, publishers, sim_log, model, tmp_path
):
    bag = tmp_path / ("in.bag" if kind == "ros1" else "bag2")
    names, t, q = _write_bag(kind, bag, sim_log, publishers=publishers)
    out = tmp_path / "log.parquet"
    robot = str(tcarm_path())
    s = convert(bag, out, wrench_topics=["/ft"], robot=robot)  # the robot's joints, its order
    assert s["joints"] == list(model.joint_names) and "ft.base_ft" in s["columns"]
    tab = pq.read_table(out)
    np.testing.assert_allclose(np.stack(tab["q"].to_numpy(zero_copy_only=False)), q, atol=1e-12)
    assert "qd" in tab.column_names  # every arm message had velocities
    res = estimate_file(out, model, tmp_path / "est.parquet")
    assert set(pq.read_table(res["output"])["status"].to_pylist()) == {"ok"}
    # without a robot, every joint is kept (the gripper's too), or as selected by name
    s = convert(bag, tmp_path / "all.parquet", wrench_topics=["/ft"])
    assert s["joints"][-1] == "gripper_finger" and len(s["joints"]) == len(names) + 1
    g = np.stack(pq.read_table(tmp_path / "all.parquet")["q"].to_numpy(zero_copy_only=False))[:, -1]
    assert np.allclose(g, 0.01 if publishers == "gripper" else 0.02)
    if publishers == "two":  # the gripper publishes no velocities: qd is left to the estimator
        assert "qd" not in pq.read_schema(tmp_path / "all.parquet").names
    s = convert(
        bag, tmp_path / "sel.parquet", wrench_topics=["/ft"], drop_joints=["gripper_finger"]
    )
    assert s["joints"] == names[::-1]
    s = convert(bag, tmp_path / "two.parquet", wrench_topics=["/ft"], joints=[names[1], names[0]])
    assert s["joints"] == [names[1], names[0]]


def test_joint_selection_errors(sim_log, tmp_path, capsys):
    bag = tmp_path / "b.bag"
    _write_bag("ros1", bag, sim_log, publishers="two")
    with pytest.raises(ConvertError, match=r"joints \['nope'\] of --joints are not in the input"):
        convert(bag, tmp_path / "o.parquet", wrench_topics=["/ft"], joints=["nope"])
    with pytest.raises(ConvertError, match=r"--drop-joints \['nope'\] are not in the input"):
        convert(bag, tmp_path / "o.parquet", wrench_topics=["/ft"], drop_joints=["nope"])
    args = ["convert", str(bag), "--out", str(tmp_path / "o.parquet"), "--wrench", "/ft"]
    assert main([*args, "--joints", "a,b"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "'a', 'b'" in err[0]
    assert main([*args, "--joints", "a", "--robot", str(tcarm_path())]) == 2
    assert main([*args, "--out", str(bag)]) == 2  # the output would replace the bag
    assert "is the input" in capsys.readouterr().err


def test_sensor_column_named_after_the_robot_sensor_frame(sim_log, tmp_path):
    bag = tmp_path / "b.bag"
    _write_bag("ros1", bag, sim_log, frame_id="ft_plate")  # base_ft's child link
    s = convert(bag, tmp_path / "o.parquet", wrench_topics=["/ft"], robot=str(tcarm_path()))
    assert "ft.base_ft" in s["columns"]
    s = convert(bag, tmp_path / "p.parquet", wrench_topics=["/ft"])  # no robot: the frame_id
    assert "ft.ft_plate" in s["columns"]


def test_sensor_name_from_frame_id(sim_log, tmp_path):
    bag = tmp_path / "b.bag"
    names, t, q = _write_bag("ros1", bag, sim_log)
    s = convert(bag, tmp_path / "o.parquet", wrench_topics=["/ft"])
    assert s["frames"] == N and "ft.base_ft" in s["columns"]  # sensor name from frame_id


def test_csv_and_toml_spec(tmp_path, capsys):
    spec = tmp_path / "contacts.toml"
    spec.write_text(
        '[[contact]]\nlink = "hand_skin"\nposition = [0, 0, 0]\nstart_ns = 10\nend_ns = 20\n'
    )

    csv = tmp_path / "log.csv"
    rows = ["t_ns,q.a,q.b,ft.s.fx,ft.s.fy,ft.s.fz,ft.s.mx,ft.s.my,ft.s.mz"]
    rows += [f"{i * 10},{i},{-i},1,2,3,4,5,6" for i in range(4)]
    csv.write_text("\n".join(rows) + "\n")
    out = tmp_path / "log.parquet"
    assert main(["convert", str(csv), "--out", str(out), "--contacts", str(spec)]) == 0
    tab = pq.read_table(out)
    assert json.loads(tab.schema.metadata[b"torchcontact.joint_names"]) == ["a", "b"]
    assert [len(c) for c in tab["contacts"].to_pylist()] == [0, 1, 1, 0]
    assert tab["ft.s"][0].as_py() == [1, 2, 3, 4, 5, 6]
    bad = tmp_path / "bad.json"
    bad.write_text(
        '{"contact": [{"link": "hand_skin", "kind": "force_dir", "position": [0, 0, 0]}]}'
    )
    assert (
        main(["convert", str(csv), "--out", str(tmp_path / "b.parquet"), "--contacts", str(bad)])
        == 2
    )
    assert "contact 0: a force_dir contact needs a direction" in capsys.readouterr().err


def test_convert_errors_name_the_file(tmp_path, sim_log):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"garbage")
    with pytest.raises(ConvertError, match="junk.bag"):
        convert(junk, tmp_path / "o.parquet", wrench_topics=["/ft"])
    bag = tmp_path / "b.bag"
    _write_bag("ros1", bag, sim_log)
    with pytest.raises(ConvertError, match="no topic '/nope'"):
        convert(bag, tmp_path / "o.parquet", wrench_topics=["/nope"])


def test_a_wrench_frame_naming_no_robot_sensor_is_kept_with_a_warning(sim_log, tmp_path, capsys):
    bag = tmp_path / "b.bag"
    _write_bag("ros1", bag, sim_log, frame_id="ft_sensor_link")
    args = ["convert", str(bag), "--wrench", "/ft", "--robot", "tcarm", "--quiet", "--out"]
    assert main([*args, str(tmp_path / "a.parquet")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: "), err
    assert "/ft: its frame_id 'ft_sensor_link' names no F/T sensor of tcarm" in err[0]
    assert "(its sensors: ['base_ft']" in err[0] and "--wrench /ft=SENSOR" in err[0]
    assert "ft.ft_sensor_link" in pq.read_schema(tmp_path / "a.parquet").names
    # an explicit TOPIC=SENSOR naming no sensor of the robot: warned as well
    args[3] = "/ft=wrist"
    assert main([*args, str(tmp_path / "b.parquet")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sensor 'wrist' names no F/T sensor of tcarm" in err[0]
    # a sensor declared with --ft-sensor matches the frame_id of its child link: no warning,
    # and the log records the robot with its sensor for estimate
    bag2 = tmp_path / "c.bag"
    _write_bag("ros1", bag2, sim_log, frame_id="hand_skin")
    out = tmp_path / "c.parquet"
    conv = ["convert", str(bag2), "--wrench", "/ft", "--robot", "tcarm", "--ft-sensor",
            "wrist_ft:hand_skin", "--out", str(out), "--quiet"]  # fmt: skip
    assert main(conv) == 0
    assert capsys.readouterr().err == ""
    meta = pq.read_schema(out).metadata
    assert "ft.wrist_ft" in pq.read_schema(out).names
    assert json.loads(meta[b"torchcontact.robot"]) == {
        "robot": "tcarm",
        "ft_sensors": ["wrist_ft:hand_skin"],
    }
    from torchcontact.robot_arg import robot_from_logs

    spec = robot_from_logs([out])
    assert spec.robot == "tcarm" and [str(s) for s in spec.ft_sensors] == ["wrist_ft:hand_skin"]
    assert "wrist_ft" in spec.load().ft_sensors
