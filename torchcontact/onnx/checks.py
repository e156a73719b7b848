"""Refusing a file made for another robot or layout: the one check of what the runtime loads.

Every file :class:`~torchcontact.onnx.runtime.EstimatorRuntime` loads (ONNX graphs, C step
libraries) records the robot it was exported for: its canonical identity
(:class:`~torchcontact.identity.RobotIdentity`, ``robot_identity``) and the URDF text's sha256
(``urdf_sha256``; files of earlier versions record only this). :func:`check_file` decides,
once for both backends: the same text is the same robot; another text is the same robot when
the parsed models agree (the refusal names the first quantity that differs); a file without an
identity needs the same text. Torch is imported only to parse a URDF whose text differs.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torchcontact.errors import ModelMismatchError
from torchcontact.identity import RobotIdentity
from torchcontact.onnx import format as fmt
from torchcontact.onnx.format import Key

__all__ = ["check_file", "identity_of", "robot_identity"]


def identity_of(robot: Any) -> RobotIdentity:
    """The :class:`~torchcontact.identity.RobotIdentity` of a model, URDF path or ``"tcarm"``.

    A model carries its identity; for a URDF the model is built (this imports torch).

    Raises:
        ModelMismatchError: ``robot`` names no readable URDF file, or torch is not installed.
    """
    ident = getattr(robot, "identity", None)
    if isinstance(ident, RobotIdentity):
        return ident
    try:
        from torchcontact.model import RobotModel
    except ImportError:  # pragma: no cover - a deployment without torch
        raise ModelMismatchError(
            "the URDF's text differs from the one the graph was exported with; comparing the"
            " parsed robots needs torch (pip install torch) or a re-export"
        ) from None
    if str(robot) == "tcarm":
        from torchcontact.robots import tcarm_path

        robot = tcarm_path()
    return RobotModel.from_urdf(robot).identity


def robot_identity(robot: Any) -> tuple[str, tuple[str, ...] | None]:
    """URDF sha256 and joint names of ``robot``, without torch.

    Args:
        robot: a :class:`torchcontact.RobotModel` (or anything with ``urdf_sha256`` and
            ``joint_names``), a URDF file path, or ``"tcarm"`` (the bundled arm).

    Returns:
        ``(sha256 of the URDF text, joint names or None)``; for a file the hash identifies the
        text, and with it the joint order the exporter derived from it.

    Raises:
        ModelMismatchError: ``robot`` names no readable URDF file.
    """
    if hasattr(robot, "urdf_sha256"):
        return str(robot.urdf_sha256), tuple(getattr(robot, "joint_names", ())) or None
    if str(robot) == "tcarm":
        from torchcontact.robots import tcarm_path

        robot = tcarm_path()
    p = Path(os.fspath(robot))
    if not p.is_file():
        raise ModelMismatchError(f"robot {str(robot)!r}: no such URDF file (or 'tcarm')")
    return hashlib.sha256(p.read_text().encode()).hexdigest(), None


def check_file(
    path: str,
    meta: Mapping[str, Any],
    robot: Any = None,
    sha256: str | None = None,
    joints: Sequence[str] | None = None,
    sensors: Sequence[str] | None = None,
    slots: tuple[Sequence[str], Sequence[str]] | None = None,
) -> None:
    """Refuse a file exported for another robot, joint order, sensor set or slot layout.

    Args:
        path: the file (named in the errors).
        meta: its metadata (``robot``, ``urdf_sha256``, ``robot_identity``,
            ``robot_identity_sha256``, ``joint_names``, ``sensors``, ``slot_links``,
            ``slot_kinds``).
        robot: the caller's robot (a model, a URDF path or ``"tcarm"``), or None.
        sha256: the URDF (or identity) hash the caller expects, or None.
        joints: the joint order the caller expects, or None.
        sensors: the sensors (in order) the caller expects, or None.
        slots: the ``(links, kinds)`` the caller expects, or None.

    Raises:
        ModelMismatchError: naming what differs.
    """
    name = meta.get(Key.ROBOT)
    have_joints = tuple(meta[Key.JOINT_NAMES])
    recorded = fmt.recorded_identity(meta)
    if robot is not None:
        h, names = robot_identity(robot)
        if h != meta[Key.URDF_SHA256]:
            # another text: the same robot when the parsed models agree (files that record the
            # robot's identity; earlier files compare the text only)
            why = f"URDF sha256 {h[:12]}..."
            if recorded is not None:
                why = recorded.difference(identity_of(robot))
            if why is not None:
                raise ModelMismatchError(
                    f"{path} was exported for robot {name!r} (URDF sha256"
                    f" {meta[Key.URDF_SHA256][:12]}...), not for this robot ({why}):"
                    " re-export it for this robot"
                )
        if names is not None and tuple(names) != have_joints:
            raise ModelMismatchError(
                f"{path} expects joints {list(have_joints)} (robot {name!r}), the robot"
                f" has {list(names)}"
            )
    accepted = {meta[Key.URDF_SHA256], meta.get(Key.ROBOT_IDENTITY_SHA256)}
    if sha256 is not None and sha256 not in accepted:
        raise ModelMismatchError(
            f"{path} was exported for robot {name!r} with URDF sha256 {meta[Key.URDF_SHA256]},"
            f" not {sha256}: re-export it for this robot"
        )
    if joints is not None and tuple(joints) != have_joints:
        raise ModelMismatchError(
            f"{path} expects joints {list(have_joints)} (robot {name!r}), got {list(joints)}"
        )
    have_sensors = tuple(s["name"] for s in meta[Key.SENSORS])
    if sensors is not None and tuple(sensors) != have_sensors:
        raise ModelMismatchError(
            f"{path} expects sensors {list(have_sensors)}, got {list(sensors)}"
        )
    links, kinds = tuple(meta[Key.SLOT_LINKS]), tuple(meta[Key.SLOT_KINDS])
    if slots is not None and (tuple(slots[0]), tuple(slots[1])) != (links, kinds):
        have = list(zip(links, kinds, strict=True))
        raise ModelMismatchError(
            f"{path} has contact slots {have}, got {list(zip(slots[0], slots[1], strict=True))}"
        )
