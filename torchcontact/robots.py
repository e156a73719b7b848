"""Robots by name and by file: the bundled descriptions, and what every ``--robot`` accepts.

Small robot descriptions written by this project, for examples, tests and first runs
(:func:`tcarm_path`, :func:`pendulum_urdf`); :func:`robot_urdf` resolves a robot argument (a
name of :data:`ROBOT_NAMES` or a URDF path) and :func:`load_robot_model` builds the model with the
F/T sensors a URDF lacks declared on it (:class:`FTSensorSpec`, the ``--ft-sensor`` option).

Imports nothing heavy at module level (the command line's ``--help`` reads :data:`ROBOT_NAMES`).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchcontact.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from torchcontact.model import RobotModel

__all__ = [
    "ROBOT_NAMES",
    "TCARM_SKIN_FRAMES",
    "FTSensorSpec",
    "RobotSpec",
    "ft_sensor_specs",
    "load_robot_model",
    "pendulum_urdf",
    "robot_urdf",
    "tcarm_path",
]

#: Robots known by name (what ``--robot NAME`` means); any other value is a URDF path.
ROBOT_NAMES = {
    "tcarm": "the bundled 7-joint arm on a base F/T sensor",
    "icub": "iCubGenova04 of the icub-models package (pip install icub-models)",
}

#: Skin patch frames of the bundled arm (fixed frames on its links; contacts lie on them).
TCARM_SKIN_FRAMES = ("upper_arm_skin", "forearm_skin", "hand_skin")


def tcarm_path() -> Path:
    """Path of the bundled robot ``tcarm``: a 7-joint arm on a base F/T sensor (``base_ft``).

    Written by this project for examples, tests and first runs (not a real product). Skin
    patches are the fixed frames :data:`TCARM_SKIN_FRAMES`; ``tool`` is the flange.

    Example:
        >>> import torchcontact as tc
        >>> tc.RobotModel.from_urdf(tc.robots.tcarm_path()).joint_names[:2]
        ('shoulder_yaw', 'shoulder_pitch')
    """
    return Path(str(resources.files("torchcontact") / "data" / "robots" / "tcarm.urdf"))


def pendulum_urdf(length: float = 1.0, mass: float = 1.0) -> str:
    """URDF text of a pendulum: a uniform rod on a revolute joint about y, horizontal at q = 0.

    Args:
        length: rod length, m (the rod lies along +x from the joint).
        mass: rod mass, kg.

    Returns:
        The URDF XML as a string.

    Example:
        >>> "<robot" in pendulum_urdf()
        True
    """
    i_end = mass * length**2 / 12.0
    return f"""<?xml version="1.0"?>
<robot name="pendulum">
  <link name="base"/>
  <link name="rod">
    <inertial>
      <origin xyz="{length / 2} 0 0" rpy="0 0 0"/>
      <mass value="{mass}"/>
      <inertia ixx="1e-6" ixy="0" ixz="0" iyy="{i_end}" iyz="0" izz="{i_end}"/>
    </inertial>
  </link>
  <joint name="hinge" type="revolute">
    <parent link="base"/>
    <child link="rod"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-3.14" upper="3.14" effort="100" velocity="10"/>
  </joint>
</robot>
"""


def _root_tag(path: Path) -> str | None:
    """Tag of the root element of an XML file (namespace dropped), None when it is not XML."""
    from xml.etree import ElementTree

    try:
        for _, el in ElementTree.iterparse(path, events=("start",)):
            return el.tag.rsplit("}", 1)[-1]
    except (ElementTree.ParseError, UnicodeDecodeError, ValueError):
        return None
    return None


def robot_urdf(robot: str | os.PathLike, option: str = "--robot") -> Path:
    """The URDF file of a robot argument: a name of :data:`ROBOT_NAMES` or a URDF path.

    ``tcarm`` is the bundled arm (:func:`tcarm_path`), ``icub`` is ``iCubGenova04`` of the
    installed ``icub-models`` package; anything else is a path to a URDF file.

    Args:
        robot: the argument as the user gave it.
        option: the option named in error messages.

    Returns:
        Path of the URDF file.

    Raises:
        InputError: a folder, a missing file, a file whose root element is not ``<robot>`` (or
            not XML at all), or ``icub`` without icub-models installed; one line naming it.

    Example:
        >>> robot_urdf("tcarm").name
        'tcarm.urdf'
    """
    text = os.fspath(robot)
    key = str(text).lower()
    if key == "tcarm":
        return tcarm_path()
    if key in ("icub", "icubgenova04"):
        try:
            import icub_models
        except ImportError:
            raise InputError(
                f"{option} icub needs the icub-models package (pip install icub-models), which is"
                " not installed"
            ) from None
        return Path(icub_models.get_model_file("iCubGenova04"))
    path = Path(text)
    names = ", ".join(ROBOT_NAMES)
    if path.is_dir():
        raise InputError(f"{option} {text}: a folder, not a URDF file (give {names} or a .urdf)")
    if not path.is_file():
        raise InputError(f"{option} {text}: no such URDF file (nor a robot name: {names})")
    tag = _root_tag(path)
    if tag != "robot":
        what = "not an XML file" if tag is None else f"its root element is <{tag}>, not <robot>"
        raise InputError(f"{option} {text}: not a URDF file ({what})")
    return path


_OPTIONS = ("frame", "direction", "xyz", "rpy")


@dataclass(frozen=True)
class FTSensorSpec:
    """A 6-axis F/T sensor declared on a robot whose URDF lacks it (``--ft-sensor``).

    The text form is ``NAME:JOINT_OR_LINK[:frame=child|parent][:direction=child_to_parent|
    parent_to_child][:xyz=X,Y,Z][:rpy=R,P,Y]``. The sensor sits on a fixed joint, named directly
    or by the link it carries (the joint's child link). Its readings are expressed in the child
    link's frame (``frame=child``, the default), the parent link's (``frame=parent``), or in a
    frame at ``xyz`` (m) rotated by URDF roll-pitch-yaw ``rpy`` (rad) in the child link's frame
    (either one selects it); ``direction`` is iDynTree's measure direction (default
    ``child_to_parent``). :meth:`torchcontact.RobotModel.with_ft_sensor` adds it.

    Attributes:
        name: sensor name (its log column is ``ft.<name>``).
        at: the fixed joint, or the link it carries.
        frame: ``child``, ``parent`` or ``sensor`` (set by ``xyz``/``rpy``).
        direction: ``child_to_parent`` or ``parent_to_child``.
        xyz: ``(3,)`` sensor origin in the child link frame, m (``frame == "sensor"``).
        rpy: ``(3,)`` sensor orientation in the child link frame, rad (``frame == "sensor"``).

    Example:
        >>> s = FTSensorSpec.parse("wrist_ft:panda_hand:xyz=0,0,0.1")
        >>> s.frame, s.xyz, str(s)
        ('sensor', (0.0, 0.0, 0.1), 'wrist_ft:panda_hand:frame=sensor:xyz=0.0,0.0,0.1')
    """

    name: str
    at: str
    frame: str = "child"
    direction: str = "child_to_parent"
    xyz: tuple[float, float, float] | None = None
    rpy: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        bad = None
        if not re.fullmatch(r"[A-Za-z_][\w.-]*", self.name or ""):
            bad = f"sensor name {self.name!r} (letters, digits, _ . -)"
        elif not self.at:
            bad = "no joint or link"
        elif self.frame not in ("child", "parent", "sensor"):
            bad = f"frame={self.frame} (child, parent, or xyz=/rpy= for a sensor frame)"
        elif self.direction not in ("child_to_parent", "parent_to_child"):
            bad = f"direction={self.direction} (child_to_parent or parent_to_child)"
        elif (self.frame == "sensor") != (self.xyz is not None or self.rpy is not None):
            bad = "frame=sensor goes with xyz= and/or rpy= (and only it)"
        if bad:
            raise InputError(f"--ft-sensor {self}: {bad}")

    @classmethod
    def parse(cls, text: str) -> FTSensorSpec:
        """A spec from its text form (see the class).

        Raises:
            InputError: a malformed spec (the message shows the expected form).
        """
        form = (
            "expected NAME:JOINT_OR_LINK[:frame=child|parent][:direction=child_to_parent|"
            "parent_to_child][:xyz=X,Y,Z][:rpy=R,P,Y] or a .toml file"
        )
        parts = text.split(":")
        if len(parts) < 2:
            raise InputError(f"--ft-sensor {text}: {form}")
        kw: dict[str, Any] = {}
        for opt in parts[2:]:
            key, sep, value = opt.partition("=")
            if not sep or key not in _OPTIONS or key in kw:
                raise InputError(f"--ft-sensor {text}: bad option {opt!r}; {form}")
            if key in ("xyz", "rpy"):
                try:
                    nums = tuple(float(v) for v in value.split(","))
                except ValueError:
                    nums = ()
                if len(nums) != 3 or not all(abs(v) < float("inf") for v in nums):
                    raise InputError(f"--ft-sensor {text}: {key}= takes 3 finite numbers")
                kw[key] = nums
            else:
                kw[key] = value
        if "xyz" in kw or "rpy" in kw:
            kw.setdefault("frame", "sensor")
        return cls(parts[0], parts[1], **kw)

    def __str__(self) -> str:
        out = f"{self.name}:{self.at}"
        if self.frame != "child":
            out += f":frame={self.frame}"
        if self.direction != "child_to_parent":
            out += f":direction={self.direction}"
        for key in ("xyz", "rpy"):
            value = getattr(self, key)
            if value is not None:
                out += f":{key}=" + ",".join(repr(float(v)) for v in value)
        return out


def _specs_from_toml(path: Path) -> list[FTSensorSpec]:
    """``[[ft_sensor]]`` tables (name, joint or link, frame, direction, xyz, rpy) of a TOML file."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"--ft-sensor {path}: not a readable TOML file ({exc})") from None
    tables = data.get("ft_sensor")
    if not isinstance(tables, list) or not tables or set(data) != {"ft_sensor"}:
        raise InputError(f"--ft-sensor {path}: expected [[ft_sensor]] tables only")
    out = []
    for i, tab in enumerate(tables):
        keys = set(tab) if isinstance(tab, dict) else {"?"}
        unknown = keys - {"name", "joint", "link", "frame", "direction", "xyz", "rpy"}
        at = [tab[k] for k in ("joint", "link") if k in tab] if not unknown else []
        if unknown or len(at) != 1 or "name" not in tab:
            raise InputError(
                f"--ft-sensor {path}: [[ft_sensor]] #{i + 1} needs name and one of joint or link,"
                f" with optional frame, direction, xyz, rpy (unknown keys: {sorted(unknown)})"
            )
        kw: dict[str, Any] = {k: tab[k] for k in ("frame", "direction") if k in tab}
        for key in ("xyz", "rpy"):
            if key in tab:
                v = tab[key]
                if not isinstance(v, list) or len(v) != 3:
                    raise InputError(
                        f"--ft-sensor {path}: {key} of {tab['name']!r} is not 3 numbers"
                    )
                kw[key] = tuple(float(x) for x in v)
        if "xyz" in kw or "rpy" in kw:
            kw.setdefault("frame", "sensor")
        out.append(FTSensorSpec(str(tab["name"]), str(at[0]), **kw))
    return out


def ft_sensor_specs(values: Iterable[str | FTSensorSpec] | None) -> tuple[FTSensorSpec, ...]:
    """Specs of ``--ft-sensor`` values: each a spec text (:class:`FTSensorSpec`) or a TOML file.

    A TOML file holds ``[[ft_sensor]]`` tables with ``name``, ``joint`` or ``link``, and optional
    ``frame``, ``direction``, ``xyz``, ``rpy`` (as the text form's options).

    Raises:
        InputError: a malformed spec or file, or a sensor name given twice.

    Example:
        >>> [s.at for s in ft_sensor_specs(["a:j1", "b:link2:frame=parent"])]
        ['j1', 'link2']
    """
    out: list[FTSensorSpec] = []
    for v in values or ():
        if isinstance(v, FTSensorSpec):
            out.append(v)
        elif v.endswith(".toml") and ":" not in v:
            if not Path(v).is_file():
                raise InputError(f"--ft-sensor {v}: no such file")
            out += _specs_from_toml(Path(v))
        else:
            out.append(FTSensorSpec.parse(v))
    names = [s.name for s in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"--ft-sensor: sensor {twice} declared twice")
    return tuple(out)


@dataclass(frozen=True)
class RobotSpec:
    """A robot as the command line names it: ``--robot`` and the ``--ft-sensor`` declarations.

    A path-like value: ``os.fspath(spec)`` is the URDF file, so functions that take a URDF path
    accept it, and :func:`torchcontact.logs.pipeline.load_robot` builds the model with the
    declared sensors (:func:`load_robot_model`).

    Attributes:
        robot: a name of :data:`ROBOT_NAMES` or a URDF path (made absolute).
        ft_sensors: sensors declared on it.

    Example:
        >>> spec = RobotSpec.of("tcarm", ["wrist_ft:hand_skin"])
        >>> spec.robot, str(spec), os.fspath(spec).endswith("tcarm.urdf")
        ('tcarm', 'tcarm --ft-sensor wrist_ft:hand_skin', True)
    """

    robot: str
    ft_sensors: tuple[FTSensorSpec, ...] = ()

    @classmethod
    def of(
        cls, robot: str | os.PathLike, ft_sensors: Iterable[str | FTSensorSpec] | None = ()
    ) -> RobotSpec:
        """A checked spec: the robot resolves to a URDF file and the sensor specs parse.

        Raises:
            InputError: as :func:`robot_urdf` and :func:`ft_sensor_specs`.
        """
        path = robot_urdf(robot)
        name = os.fspath(robot)
        name = name.lower() if name.lower() in ROBOT_NAMES else str(path.absolute())
        return cls(name, ft_sensor_specs(ft_sensors))

    def __fspath__(self) -> str:
        return str(robot_urdf(self.robot))

    def __str__(self) -> str:
        return " ".join([self.robot, *(f"--ft-sensor {s}" for s in self.ft_sensors)])

    def load(self, dtype: torch.dtype | None = None, device: str = "cpu") -> RobotModel:
        """The model (:func:`load_robot_model`)."""
        return load_robot_model(self.robot, self.ft_sensors, dtype=dtype, device=device)


def load_robot_model(
    robot: str | os.PathLike | RobotSpec,
    ft_sensors: Sequence[str | FTSensorSpec] = (),
    *,
    dtype: torch.dtype | None = None,
    device: str = "cpu",
    option: str = "--robot",
) -> RobotModel:
    """Build the model of a robot argument, with F/T sensors its URDF lacks declared on it.

    Each declared sensor's fixed joint is kept as a body boundary (``keep_fixed`` of
    :meth:`~torchcontact.RobotModel.from_urdf`), then the sensor is added with
    :meth:`~torchcontact.RobotModel.with_ft_sensor`.

    Args:
        robot: a name of :data:`ROBOT_NAMES`, a URDF path (:func:`robot_urdf`), or a
            :class:`RobotSpec` (its sensors come first).
        ft_sensors: :class:`FTSensorSpec` or their text forms / TOML files.
        dtype: the model's dtype (default float64).
        device: the model's device.
        option: the option named in error messages.

    Returns:
        The :class:`~torchcontact.RobotModel`.

    Raises:
        InputError: a bad robot argument (:func:`robot_urdf`), a sensor on no joint or link of
            the robot, on a moving joint, or named like one the URDF declares.
        URDFError: a URDF torchcontact cannot model (the message names the element).

    Example:
        >>> m = load_robot_model("tcarm", ["hand_ft:hand_skin_joint"])
        >>> sorted(m.ft_sensors)
        ['base_ft', 'hand_ft']
    """
    import torch

    from torchcontact import _urdf
    from torchcontact.model import RobotModel

    dtype = torch.float64 if dtype is None else dtype
    if isinstance(robot, RobotSpec):
        robot, ft_sensors = robot.robot, (*robot.ft_sensors, *ft_sensors)
    path = robot_urdf(robot, option)
    specs = ft_sensor_specs(ft_sensors)
    if not specs:
        return RobotModel.from_urdf(path, dtype=dtype, device=device)
    text, source = _urdf.read_text(path)
    parsed = _urdf.parse(text, source)
    by_name = {j["name"]: j for j in parsed["joints"]}
    by_child = {j["child"]: j for j in parsed["joints"]}
    declared = {s["name"] for s in parsed["sensors"]}
    fixed = [j["name"] for j in parsed["joints"] if j["type"] == "fixed"]
    joints = []
    for s in specs:
        j = by_name.get(s.at) or by_child.get(s.at)
        if j is None:
            raise InputError(
                f"--ft-sensor {s}: {s.at!r} is no joint or link of {parsed['name']} (fixed"
                f" joints: {fixed})"
            )
        if j["type"] != "fixed":
            raise InputError(
                f"--ft-sensor {s}: joint {j['name']!r} is {j['type']}; an F/T sensor sits on a"
                f" fixed joint (fixed joints of {parsed['name']}: {fixed})"
            )
        if s.name in declared:
            raise InputError(
                f"--ft-sensor {s}: {parsed['name']} already declares sensor {s.name!r}"
            )
        joints.append(j["name"])
    model = RobotModel.from_urdf(path, dtype=dtype, device=device, keep_fixed=joints)
    for s, joint in zip(specs, joints, strict=True):
        R = p = None
        if s.frame == "sensor":
            from torchcontact.spatial import rpy_to_matrix

            R = rpy_to_matrix(torch.tensor(s.rpy or (0.0, 0.0, 0.0), dtype=torch.float64))
            R, p = R.numpy(), list(s.xyz or (0.0, 0.0, 0.0))
        try:
            model = model.with_ft_sensor(s.name, joint, s.frame, s.direction, R, p)  # type: ignore[arg-type]
        except ValueError as exc:
            raise InputError(f"--ft-sensor {s}: {exc}") from None
    return model
