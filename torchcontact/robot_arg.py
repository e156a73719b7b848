"""The robot argument of every command: ``--robot`` and ``--ft-sensor``, defined and resolved here.

Every command that takes a robot (``simulate``, ``demo``, ``estimate``, ``plot``, ``convert``,
``train``, ``export``, ``run``) adds it with :func:`add_robot_argument` and turns it into a
:class:`~torchcontact.robots.RobotSpec` with :func:`resolve_robot_argument`, so the forms
accepted (``tcarm``, ``icub``, a URDF path; sensors declared with ``--ft-sensor``), the help text
and the errors are the same everywhere. ``estimate`` without ``--robot`` takes the robot recorded
in its logs' metadata (:func:`robot_from_logs`) and never falls back to the bundled arm.

Imports nothing heavy at module level: parsers are built for ``--help``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchcontact.errors import InputError
from torchcontact.robots import ROBOT_NAMES, RobotSpec, ft_sensor_specs, robot_urdf

__all__ = [
    "ROBOT_HELP",
    "add_robot_argument",
    "add_strict_joints_argument",
    "check_log_joints",
    "resolve_robot_argument",
    "robot_from_logs",
]

#: What ``--robot`` accepts, in every command's help.
ROBOT_HELP = (
    "tcarm (the bundled arm), icub (iCubGenova04 of the icub-models package) or a URDF file"
)
FT_SENSOR_HELP = (
    "declare an F/T sensor the URDF lacks, on a fixed joint (named, or by the link it carries):"
    " NAME:JOINT_OR_LINK[:frame=child|parent][:direction=child_to_parent|parent_to_child]"
    "[:xyz=X,Y,Z][:rpy=R,P,Y] (xyz in m and rpy in rad give a sensor frame in the child link's"
    " frame), or a TOML file of [[ft_sensor]] tables with the same keys (name, joint or link,"
    " ...); repeatable (default: only the sensors the URDF declares)"
)


def add_robot_argument(
    parser: argparse.ArgumentParser,
    *,
    default: str | None = None,
    default_help: str = "",
    aliases: Sequence[str] = (),
    what: str = "",
    required: bool = False,
) -> None:
    """Add ``--robot`` (with ``aliases``) and ``--ft-sensor`` to a parser.

    Args:
        parser: the command's parser.
        default: default robot (e.g. ``tcarm``; shown by the help formatter), or None.
        default_help: with ``default`` None, what happens without ``--robot`` (the help says
            ``(default: <default_help>)``).
        aliases: other option strings of ``--robot`` (``--urdf`` where it was spelled so).
        what: what the robot is for in this command, leading the help text.
        required: the command needs ``--robot``.
    """
    text = f"{what}: {ROBOT_HELP}" if what else f"the robot: {ROBOT_HELP}"
    if default is None and default_help:
        text += f" (default: {default_help})"
    parser.add_argument(
        "--robot",
        *aliases,
        dest="robot",
        metavar="ROBOT",
        default=default,
        required=required,
        help=text,
    )
    parser.add_argument(
        "--ft-sensor",
        dest="ft_sensor",
        action="append",
        metavar="SPEC",
        help=FT_SENSOR_HELP,
    )


def add_strict_joints_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--strict-joints``: refuse logs naming joints the robot lacks."""
    parser.add_argument(
        "--strict-joints",
        action="store_true",
        help="refuse a log with joints the robot lacks (default: leave them out, with a warning"
        " naming them; a robot joint missing from the log is always an error)",
    )


def _urdf_sha256(path: Path) -> str:
    # as RobotModel.urdf_sha256: the hash of the URDF text
    return hashlib.sha256(path.read_text().encode()).hexdigest()


def robot_from_logs(files: Sequence[str | Path]) -> RobotSpec:
    """The robot recorded in logs' metadata (``torchcontact.robot`` and its URDF sha256).

    The recorded robot (a name or a URDF path) is used when its URDF still has the recorded
    sha256; otherwise a known robot (:data:`~torchcontact.robots.ROBOT_NAMES`) with that sha256
    (a log recorded on another machine, where the URDF lay elsewhere).

    Args:
        files: the logs (what each records must agree: an estimate's output records the URDF
            sha256 only).

    Returns:
        The :class:`~torchcontact.robots.RobotSpec` (with the recorded ``--ft-sensor``).

    Raises:
        InputError: no log records a robot, logs record different robots, or the recorded URDF
            cannot be found (or has changed); the message says to give ``--robot``.
        LogError: a file that is not a readable log.
    """
    from torchcontact.logs.format import logged_robot, open_log

    recorded = {Path(f): logged_robot(open_log(f).schema_arrow) for f in files}
    first = next(iter(recorded))
    # a log may record the sha256 only (estimate's output): logs agree when what they record does
    shas = {sha for _, sha in recorded.values() if sha}
    recs = {json.dumps(r, sort_keys=True): r for r, _ in recorded.values() if r is not None}
    if len(shas) > 1 or len(recs) > 1:
        seen = sorted(
            {f"{(r or {}).get('robot', '?')} ({sha[:12]})" for r, sha in recorded.values()}
        )
        raise InputError(f"the input logs record different robots {seen}: give --robot")
    rec = next(iter(recs.values()), None)
    sha = next(iter(shas), "")
    if rec is None and not sha:
        raise InputError(
            f"no --robot given, and {first} records no robot in its metadata: give --robot"
            f" ({ROBOT_HELP})"
        )
    sensors = ft_sensor_specs((rec or {}).get("ft_sensors", []))
    candidates = [rec["robot"]] if rec else []
    candidates += [n for n in ROBOT_NAMES if n not in candidates]
    changed, missing = None, ""
    for cand in candidates:
        try:
            path = robot_urdf(cand)
        except InputError as exc:  # not here (another machine's path, icub-models missing)
            if rec is not None and cand == rec["robot"] and cand in ROBOT_NAMES:
                missing = f" ({exc})"
            continue
        got = _urdf_sha256(path)
        if not sha or got == sha:
            return RobotSpec.of(cand, sensors)
        if rec is not None and cand == rec["robot"]:
            changed = got
    where = f"robot {rec['robot']}" if rec else "a robot"
    why = (
        f"whose URDF has changed since (sha256 {sha[:12]}... then, {changed[:12]}... now)"
        if changed
        else f"(URDF sha256 {sha[:12]}...), which is not found here{missing}"
    )
    raise InputError(f"{first} was recorded for {where} {why}: give --robot")


def resolve_robot_argument(
    args: argparse.Namespace, *, logs: Sequence[str | Path] = ()
) -> RobotSpec | None:
    """The robot of a parsed command line: ``args.robot`` with ``args.ft_sensor``.

    Without ``--robot``: the robot recorded in ``logs`` (:func:`robot_from_logs`) when logs are
    given, else None (the command's default, if any, is already in ``args.robot``).

    Args:
        args: parsed arguments of a parser given :func:`add_robot_argument`.
        logs: input logs whose metadata names the robot when ``--robot`` is absent.

    Returns:
        The checked :class:`~torchcontact.robots.RobotSpec` (the URDF exists and is a URDF, the
        sensor specs parse; the model is built when used), or None.

    Raises:
        InputError: as :func:`torchcontact.robots.robot_urdf`, :func:`robot_from_logs`, or
            ``--ft-sensor`` without a robot.
    """
    sensors = ft_sensor_specs(getattr(args, "ft_sensor", None))
    if args.robot is None:
        if logs:
            spec = robot_from_logs(logs)
            return RobotSpec(spec.robot, sensors) if sensors else spec
        if sensors:
            raise InputError("--ft-sensor declares a sensor on a robot: give --robot too")
        return None
    return RobotSpec.of(args.robot, sensors)


def check_log_joints(files: Sequence[str | Path], model: Any, strict: bool) -> None:
    """Match each log's joints to ``model`` (:func:`~torchcontact.logs.format.joint_permutation`).

    Raises:
        LogError: a robot joint a log lacks, or (``strict``) a log joint the robot lacks.
    """
    from torchcontact.logs.format import joint_names_of, joint_permutation, open_log

    for f in files:
        names = joint_names_of(open_log(f).schema_arrow, f)
        joint_permutation(names, model.joint_names, model.name, f, strict=strict)
