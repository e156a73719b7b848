"""``torchcontact simulate --robot`` on robots other than the bundled arm: iCub (six F/T sensors,
from icub-models) and the panda (example-robot-data) with an F/T sensor declared on its hand
joint; the simulated contacts are estimated back."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from torchcontact.cli import main
from torchcontact.robots import tcarm_path

pytest.importorskip("icub_models")

from robots import ROBOTS  # noqa: E402


@pytest.fixture(scope="module")
def robot_paths():
    return {k: ROBOTS[k]() for k in ("icub", "panda")}


def panda_with_sensor(tmp_path):
    """The installed panda URDF with an iDynTree force_torque sensor on ``panda_hand_joint``
    (written to tmp_path; nothing is copied into the repository)."""
    text = ROBOTS["panda"]().read_text()
    sensor = (
        '<sensor name="wrist_ft" type="force_torque"><parent joint="panda_hand_joint"/>'
        "<force_torque><frame>child</frame><measure_direction>child_to_parent"
        "</measure_direction></force_torque></sensor>"
    )
    path = tmp_path / "panda_ft.urdf"
    path.write_text(text.replace("</robot>", sensor + "</robot>"))
    return path


def _single_contact_errors(est):
    rows = pq.read_table(est).column("contacts").to_pylist()
    errs = [
        np.abs(np.subtract(r[0]["force"], r[0]["true_force"])).max() for r in rows if len(r) == 1
    ]
    return np.asarray(errs)


@pytest.mark.parametrize("robot", ["icub", "panda"])
def test_simulate_any_robot_then_estimate(robot, robot_paths, tmp_path, capsys):
    urdf = panda_with_sensor(tmp_path) if robot == "panda" else robot_paths["icub"]
    log, est = tmp_path / "log.parquet", tmp_path / "est.parquet"
    args = ["simulate", "--robot", str(urdf), "--frames", "400", "--out", str(log), "--quiet"]
    args += ["--max-contacts", "1"]  # identifiable: one pure force at a time
    if robot == "icub":
        args += ["--sensor", "l_arm_ft"]
    assert main(args) == 0, capsys.readouterr().err
    tab = pq.read_table(log)
    sensor = "wrist_ft" if robot == "panda" else "l_arm_ft"
    assert f"ft.{sensor}" in tab.column_names
    links = {c["link"] for row in tab["contacts"].to_pylist() for c in row}
    assert links, "no contact simulated"
    assert main(["estimate", str(log), "--robot", str(urdf), "--out", str(est), "--quiet"]) == 0
    out = pq.read_table(est)
    assert set(out["status"].to_pylist()) == {"ok"}
    errs = _single_contact_errors(est)
    assert len(errs) > 20 and errs.max() < 1e-6  # one pure force: identifiable, recovered


def test_contact_links_and_sensor_are_chosen_and_checked(robot_paths, tmp_path, capsys):
    icub = str(robot_paths["icub"])
    log = tmp_path / "l.parquet"
    args = ["simulate", "--robot", icub, "--frames", "200", "--out", str(log), "--quiet"]
    assert main([*args, "--sensor", "r_arm_ft", "--contact-links", "r_hand,r_forearm"]) == 0
    links = {c["link"] for row in pq.read_table(log)["contacts"].to_pylist() for c in row}
    assert links <= {"r_hand", "r_forearm"} and links
    capsys.readouterr()
    assert main([*args, "--sensor", "nope"]) == 2
    assert "--sensor nope: not an F/T sensor of" in capsys.readouterr().err
    assert main([*args, "--sensor", "r_arm_ft", "--contact-links", "l_hand"]) == 2
    err = capsys.readouterr().err
    assert "--contact-links ['l_hand']: outside the subtree of sensor 'r_arm_ft'" in err
    assert main([*args, "--contact-links", "no_link"]) == 2
    assert "not links or frames" in capsys.readouterr().err
    # the effects follow the sensor on any robot: the default cable pulls inside its subtree
    cable = ["simulate", "--robot", icub, "--frames", "200", "--quiet"]
    assert main([*cable, "--out", str(tmp_path / "cable.parquet"), "--cable", "2"]) == 0
    tc_args = ["simulate", "--robot", str(tcarm_path()), "--frames", "50", "--quiet"]
    assert main([*tc_args, "--out", str(tmp_path / "t.parquet"), "--max-contacts", "0"]) == 2
