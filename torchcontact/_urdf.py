"""URDF reading (private): the robot tree and iDynTree's F/T ``<sensor>`` extension.

Returns plain numpy/float data; :mod:`torchcontact.model` turns it into tensors, and
:mod:`torchcontact.meshes` loads the ``<visual>``/``<collision>`` geometry :func:`geometry` lists.
Imports neither torch nor the model (the model imports this module, not the reverse).
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from torchcontact.errors import URDFError


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
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` of URDF roll-pitch-yaw angles (fixed axes x, y, z)."""
    cr, cp, cy = np.cos(rpy)
    sr, sp, sy = np.sin(rpy)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


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


def _origin(el, what: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R, p)`` of an element's ``<origin xyz rpy>`` (identity when absent)."""
    o = el.find("origin")
    xyz = _floats(None if o is None else o.get("xyz"), 3, f"{what} <origin xyz>", source)
    rpy = _floats(None if o is None else o.get("rpy"), 3, f"{what} <origin rpy>", source)
    return _rotation(rpy), xyz


def _number(el, attr: str, what: str, source: str, default: float | None = None) -> float:
    v = None if el is None else el.get(attr)
    if v is None:
        if default is None:
            raise URDFError(f"{source}: {what} needs the attribute {attr!r}")
        return default
    try:
        return float(v)
    except ValueError:
        raise URDFError(f"{source}: {what} {attr}={v!r} is not a number") from None


def _name_of(el, child: str, what: str, source: str) -> str:
    sub = el.find(child)
    if sub is None or not sub.get("link"):
        raise URDFError(f"{source}: {what} needs <{child} link=...>")
    return sub.get("link")


def parse(text: str, source: str) -> dict:
    """Parse URDF text into ``{"name", "links", "joints", "sensors"}`` with numpy data.

    The standard library's XML parser reads the URDF elements torchcontact uses (links with their
    ``<inertial>``, joints with origin, axis, limit and mimic, and iDynTree's ``<sensor
    type="force_torque">`` extension); visual and collision geometry is ignored.

    Raises:
        URDFError: the XML or its robot description is malformed; the message names the element.
    """
    from xml.etree import ElementTree

    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as e:
        raise URDFError(f"{source}: malformed XML: {e}") from None
    if root.tag != "robot":
        raise URDFError(f"{source}: root element is <{root.tag}>, expected <robot>")

    links: dict[str, dict] = {}
    for le in root.findall("link"):
        name = le.get("name")
        if not name:
            raise URDFError(f"{source}: a <link> has no name")
        if name in links:
            raise URDFError(f"{source}: link {name!r} is defined twice")
        inertial = None
        ie = le.find("inertial")
        if ie is not None:
            what = f"link {name!r} <inertial>"
            R, p = _origin(ie, what, source)
            m = _number(ie.find("mass"), "value", f"{what} <mass>", source, 0.0)
            te = ie.find("inertia")
            c = {k: _number(te, k, f"{what} <inertia>", source, 0.0)
                 for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}  # fmt: skip
            inertia = np.array(
                [
                    [c["ixx"], c["ixy"], c["ixz"]],
                    [c["ixy"], c["iyy"], c["iyz"]],
                    [c["ixz"], c["iyz"], c["izz"]],
                ]
            )
            if m < 0 or not np.isfinite(m) or not np.all(np.isfinite(inertia)):
                raise URDFError(f"{source}: link {name!r} has an invalid <inertial>")
            inertial = (m, R, p, inertia)
        links[name] = {"name": name, "inertial": inertial}

    joints: list[dict] = []
    names = set()
    for je in root.findall("joint"):
        name = je.get("name")
        jtype = je.get("type")
        if not name:
            raise URDFError(f"{source}: a <joint> has no name")
        if jtype not in ("revolute", "continuous", "prismatic", "fixed", "floating", "planar"):
            raise URDFError(f"{source}: joint {name!r} has unknown type {jtype!r}")
        if name in names:
            raise URDFError(f"{source}: joint {name!r} is defined twice")
        names.add(name)
        what = f"joint {name!r}"
        R, p = _origin(je, what, source)
        ae = je.find("axis")
        axis = _floats(ae.get("xyz") if ae is not None else "1 0 0", 3, f"{what} <axis>", source)
        norm = float(np.linalg.norm(axis))
        if jtype != "fixed" and not (norm > 0 and np.isfinite(norm)):
            raise URDFError(f"{source}: joint {name!r} has a zero or invalid <axis>")
        mimic = None
        me = je.find("mimic")
        if me is not None:
            if not me.get("joint"):
                raise URDFError(f"{source}: {what} <mimic> needs joint=...")
            mimic = {
                "joint": me.get("joint"),
                "multiplier": _number(me, "multiplier", f"{what} <mimic>", source, 1.0),
                "offset": _number(me, "offset", f"{what} <mimic>", source, 0.0),
            }
        lim = je.find("limit")
        joints.append(
            {
                "name": name,
                "type": jtype,
                "parent": _name_of(je, "parent", what, source),
                "child": _name_of(je, "child", what, source),
                "R": R,
                "p": p,
                "axis": axis / norm if norm > 0 else axis,
                "mimic": mimic,
                "limit": {
                    k: _number(lim, k, f"{what} <limit>", source, d)
                    for k, d in (
                        ("lower", -np.inf),
                        ("upper", np.inf),
                        ("velocity", np.inf),
                        ("effort", np.inf),
                    )  # fmt: skip
                },
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
    return {"name": root.get("name", ""), "links": links, "joints": joints, "sensors": sensors}


_SHAPES = ("mesh", "box", "cylinder", "sphere")


def geometry(text: str, source: str, kind: str) -> list[dict]:
    """The ``<visual>`` or ``<collision>`` elements of every link, in document order.

    Args:
        text: URDF XML text.
        source: a name for messages (the file path).
        kind: ``"visual"`` or ``"collision"``.

    Returns:
        One dict per element: ``link``, ``R``/``p`` (the element's ``<origin>`` in the link frame,
        numpy ``(3, 3)``/``(3,)``, m), ``type`` (``"mesh"``, ``"box"``, ``"cylinder"``,
        ``"sphere"``), ``filename`` and ``scale`` ``(3,)`` for meshes, ``size`` for primitives
        (box ``(3,)`` edge lengths, cylinder ``(radius, length)``, sphere ``(radius,)``, m), and
        ``rgba`` ``(4,)`` or ``None`` (a visual's material colour, inline or named at robot level).

    Raises:
        URDFError: malformed XML, or an element without a known shape or with malformed numbers.
    """
    from xml.etree import ElementTree

    if kind not in ("visual", "collision"):
        raise ValueError(f"kind must be 'visual' or 'collision', got {kind!r}")
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as e:
        raise URDFError(f"{source}: malformed XML: {e}") from None
    colours = {}
    for me in root.findall("material"):
        ce = me.find("color")
        if me.get("name") and ce is not None:
            colours[me.get("name")] = _floats(ce.get("rgba"), 4, "material rgba", source)
    out = []
    for le in root.findall("link"):
        link = le.get("name", "")
        for ge in le.findall(kind):
            what = f"link {link!r} <{kind}>"
            R, p = _origin(ge, what, source)
            shape = ge.find("geometry")
            el = None if shape is None else next(iter(shape), None)
            if el is None or el.tag not in _SHAPES:
                raise URDFError(f"{source}: {what} needs <geometry> with one of {_SHAPES}")
            item = {"link": link, "R": R, "p": p, "type": el.tag, "filename": None,
                    "scale": np.ones(3), "size": None, "rgba": None}  # fmt: skip
            if el.tag == "mesh":
                if not el.get("filename"):
                    raise URDFError(f"{source}: {what} <mesh> needs filename=...")
                item["filename"] = el.get("filename")
                if el.get("scale") is not None:
                    item["scale"] = _floats(el.get("scale"), 3, f"{what} <mesh scale>", source)
            elif el.tag == "box":
                item["size"] = _floats(el.get("size"), 3, f"{what} <box size>", source)
            elif el.tag == "cylinder":
                item["size"] = np.array(
                    [_number(el, k, f"{what} <cylinder>", source) for k in ("radius", "length")]
                )
            else:
                item["size"] = np.array([_number(el, "radius", f"{what} <sphere>", source)])
            me = ge.find("material")
            if me is not None:
                ce = me.find("color")
                if ce is not None:
                    item["rgba"] = _floats(ce.get("rgba"), 4, f"{what} <material rgba>", source)
                else:
                    item["rgba"] = colours.get(me.get("name", ""))
            out.append(item)
    return out
