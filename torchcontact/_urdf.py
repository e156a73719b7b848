"""URDF reading (private): yourdfpy for the robot tree, lxml for the F/T ``<sensor>`` extension.

Returns plain numpy/float data; :mod:`torchcontact.model` turns it into tensors.
"""

from __future__ import annotations

import io
import logging
import os
from pathlib import Path

import numpy as np
import torch

from torchcontact.model import URDFError


def read_text(urdf) -> tuple[str, str]:
    """Return the URDF's text and a name for messages."""
    if isinstance(urdf, io.IOBase):
        data = urdf.read()
        text = data.decode() if isinstance(data, bytes) else data
        return text, getattr(urdf, "name", "<urdf stream>")
    path = Path(os.fspath(urdf))
    if not path.is_file():
        raise FileNotFoundError(f"URDF file not found: {path}")
    return path.read_text(), str(path)


def _rotation(rpy: np.ndarray) -> np.ndarray:
    from torchcontact.spatial import rpy_to_matrix

    return rpy_to_matrix(torch.as_tensor(rpy, dtype=torch.float64)).numpy()


def _floats(text: str | None, n: int, what: str, source: str) -> np.ndarray:
    if text is None:
        return np.zeros(n)
    try:
        vals = np.array([float(v) for v in text.split()])
    except ValueError:
        raise URDFError(f"{source}: {what} is not a list of numbers: {text!r}") from None
    if vals.shape != (n,) or not np.all(np.isfinite(vals)):
        raise URDFError(f"{source}: {what} needs {n} finite numbers, got {text!r}")
    return vals


def parse(text: str, source: str) -> dict:
    """Parse URDF text into ``{"name", "links", "joints", "sensors"}`` with numpy data.

    Raises:
        URDFError: the XML or its robot description is malformed; the message names the element.
    """
    import yourdfpy
    from lxml import etree

    try:
        root = etree.fromstring(text.encode())
    except etree.XMLSyntaxError as e:
        raise URDFError(f"{source}: malformed XML: {e}") from None
    if root.tag != "robot":
        raise URDFError(f"{source}: root element is <{root.tag}>, expected <robot>")
    # Joint types are checked before yourdfpy, which would accept any string silently.
    for je in root.findall("joint"):
        jtype = je.get("type")
        if jtype not in ("revolute", "continuous", "prismatic", "fixed", "floating", "planar"):
            raise URDFError(f"{source}: joint {je.get('name')!r} has unknown type {jtype!r}")

    log = logging.getLogger("yourdfpy")
    level = log.level
    log.setLevel(logging.ERROR)  # mesh and validation chatter is not ours to print
    try:
        urdf = yourdfpy.URDF.load(
            io.BytesIO(text.encode()),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except Exception as e:  # yourdfpy raises assorted types on bad input
        raise URDFError(f"{source}: cannot parse URDF: {e}") from None
    finally:
        log.setLevel(level)
    robot = urdf.robot

    links: dict[str, dict] = {}
    for link in robot.links:
        if link.name in links:
            raise URDFError(f"{source}: link {link.name!r} is defined twice")
        inertial = None
        if link.inertial is not None:
            m = float(link.inertial.mass if link.inertial.mass is not None else 0.0)
            origin = np.eye(4) if link.inertial.origin is None else link.inertial.origin
            inertia = link.inertial.inertia
            inertia = np.zeros((3, 3)) if inertia is None else np.asarray(inertia, float)
            if m < 0 or not np.isfinite(m) or not np.all(np.isfinite(inertia)):
                raise URDFError(f"{source}: link {link.name!r} has an invalid <inertial>")
            inertial = (m, origin[:3, :3].copy(), origin[:3, 3].copy(), inertia)
        links[link.name] = {"name": link.name, "inertial": inertial}

    joints: list[dict] = []
    names = set()
    for j in robot.joints:
        if j.name in names:
            raise URDFError(f"{source}: joint {j.name!r} is defined twice")
        names.add(j.name)
        origin = np.eye(4) if j.origin is None else j.origin
        axis = np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, float)
        norm = float(np.linalg.norm(axis))
        if j.type != "fixed" and not (norm > 0 and np.isfinite(norm)):
            raise URDFError(f"{source}: joint {j.name!r} has a zero or invalid <axis>")
        mimic = None
        if j.mimic is not None:
            mimic = {
                "joint": j.mimic.joint,
                "multiplier": 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier),
                "offset": 0.0 if j.mimic.offset is None else float(j.mimic.offset),
            }
        joints.append(
            {
                "name": j.name,
                "type": j.type,
                "parent": j.parent,
                "child": j.child,
                "R": origin[:3, :3].copy(),
                "p": origin[:3, 3].copy(),
                "axis": axis / norm if norm > 0 else axis,
                "mimic": mimic,
                "limit": _limit(j.limit),
            }
        )

    # F/T sensors, iDynTree's URDF extension: <robot><sensor type="force_torque">...
    sensors = []
    for se in root.findall("sensor"):
        if se.get("type") != "force_torque":
            continue
        name = se.get("name")
        parent = se.find("parent")
        if name is None or parent is None or parent.get("joint") is None:
            raise URDFError(
                f"{source}: force_torque <sensor name={name!r}> needs <parent joint=...>"
            )
        ftel = se.find("force_torque")
        frame = (ftel.findtext("frame") if ftel is not None else None) or "child"
        direction = (ftel.findtext("measure_direction") if ftel is not None else None) or (
            "child_to_parent"
        )
        origin = se.find("origin")
        xyz = _floats(
            None if origin is None else origin.get("xyz"), 3, f"sensor {name!r} xyz", source
        )
        rpy = _floats(
            None if origin is None else origin.get("rpy"), 3, f"sensor {name!r} rpy", source
        )
        sensors.append(
            {
                "name": name,
                "joint": parent.get("joint"),
                "frame": frame.strip(),
                "direction": direction.strip(),
                "R": _rotation(rpy),
                "p": xyz,
            }
        )
    return {"name": robot.name, "links": links, "joints": joints, "sensors": sensors}


def _limit(limit) -> dict[str, float]:
    """``<limit>`` as floats; absent attributes are -inf/inf (no limit)."""

    def get(name: str, default: float) -> float:
        v = None if limit is None else getattr(limit, name, None)
        return default if v is None else float(v)

    return {
        "lower": get("lower", -np.inf),
        "upper": get("upper", np.inf),
        "velocity": get("velocity", np.inf),
        "effort": get("effort", np.inf),
    }


def axis_rotation_terms(R0: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Terms of ``R0 @ Rot(axis, q) = R0 + sin(q) C1 + (1 - cos(q)) C2`` (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return R0 @ K, R0 @ K @ K
