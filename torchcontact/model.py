"""Robot model built once from a URDF into plain tensors.

The model is a frozen value: :meth:`RobotModel.to` returns a copy, algorithms are functions of
``(model, q, qd, qdd, ...)``. The URDF is read with the standard library's XML parser
(kinematic tree, inertials, limits, mimic tags, and the F/T sensor extension that iDynTree and
Gazebo read, ``<sensor type="force_torque">`` as a child of ``<robot>``, which URDF libraries drop).

Bodies. Links joined by fixed joints are rigidly attached and are merged into one *body* (their
inertias combined), except across fixed joints that carry an F/T sensor or that the caller names in
``keep_fixed``: those stay body boundaries, because a sensor splits the tree there. Bodies are
numbered breadth-first (parents before children; the bodies of one tree depth form a contiguous
range, ``levels``).

Joints. ``joint_names`` lists the independent joint coordinates (revolute, continuous, prismatic),
depth-first in URDF order like pinocchio, and fixes the order of every joint-space vector
(``q``, ``qd``, ``qdd``, ``tau``). A ``<mimic>`` joint is not an independent coordinate: its
position is ``multiplier * q_leader + offset``, its velocity and acceleration follow with the same
multiplier, and its torque is added to the leader's times the multiplier (virtual work). A
continuous joint is a revolute joint without limits, one coordinate in rad.
"""

from __future__ import annotations

import hashlib
import io
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchcontact.errors import InputError, URDFError
from torchcontact.identity import RobotIdentity, entry
from torchcontact.spatial import combine_inertias

__all__ = ["FTSensor", "Frame", "RobotModel", "URDFError"]

_MOVING = ("revolute", "continuous", "prismatic")
_KNOWN_TYPES = (*_MOVING, "fixed", "floating", "planar")


@dataclass(frozen=True)
class Frame:
    """A named frame rigidly attached to a body.

    Attributes:
        name: URDF link name, joint name, or sensor name.
        body: index of the body (into ``RobotModel.body_names``) the frame is attached to.
        R_body_frame: ``(3, 3)`` rotation of the frame in the body frame (numpy float64).
        p_body_frame: ``(3,)`` origin of the frame in the body frame, m (numpy float64).
    """

    name: str
    body: int
    R_body_frame: np.ndarray
    p_body_frame: np.ndarray


@dataclass(frozen=True)
class FTSensor:
    """A 6-axis force/torque sensor on a fixed joint, as declared in the URDF.

    The reading convention is iDynTree's: the sensor measures the wrench that the ``parent`` side
    exerts on the ``child`` side of its joint (``measure_direction`` ``parent_to_child``), or its
    opposite (``child_to_parent``), expressed in the sensor frame, moment about its origin.

    Attributes:
        name: sensor name (``<sensor name=...>``).
        joint: the fixed joint the sensor sits on.
        parent_body: body index on the parent side of the joint.
        child_body: body index on the child side; the subtree rooted there is the sensor's subtree.
        frame: ``"child"``, ``"parent"`` or ``"sensor"`` (the ``<frame>`` element).
        measure_direction: ``"parent_to_child"`` or ``"child_to_parent"``.
        R_child_sensor: ``(3, 3)`` rotation of the frame the reading is expressed in, relative to
            the child body frame (numpy float64): identity for ``child``, the inverse of the joint's
            rest rotation for ``parent``, the ``<origin>`` for ``sensor`` (iDynTree's rules).
        p_child_sensor: ``(3,)`` origin of that frame in the child body frame, m.
    """

    name: str
    joint: str
    parent_body: int
    child_body: int
    frame: Literal["child", "parent", "sensor"]
    measure_direction: Literal["parent_to_child", "child_to_parent"]
    R_child_sensor: np.ndarray
    p_child_sensor: np.ndarray


_TENSOR_FIELDS = (
    "q_to_body",
    "q_offset",
    "C0",
    "p0",
    "axis",
    "is_revolute",
    "is_prismatic",
    "mass",
    "com",
    "inertia_com",
    "gravity",
)


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A rigid-body tree with its inertial parameters, as plain tensors.

    Build it with :meth:`from_urdf`. Tensor attributes are on one device with one floating dtype;
    :meth:`to` returns a converted copy. ``nb`` counts bodies including the root body 0.

    Attributes:
        name: robot name from the URDF.
        joint_names: ``(nv,)`` independent joint coordinates; the order of ``q``, ``qd``, ``qdd``,
            ``tau``.
        joint_types: ``(nv,)`` ``"revolute"``, ``"continuous"`` or ``"prismatic"``.
        body_names: ``(nb,)`` the URDF link each body is named after (its first link).
        body_parent: ``(nb,)`` parent body index, -1 for the root.
        body_joint: ``(nb,)`` name of the joint that connects each body to its parent ('' for root).
        levels: ``(start, end)`` body ranges per tree depth (level 0 is the root alone).
        level_parent: per level >= 1, a long tensor with the parent of each body as an index into
            the previous level's range.
        frames: every URDF link and every joint (its child link's frame), by name. Sensors have
            their own namespace, ``ft_sensors`` (iCub names sensors like links).
        ft_sensors: F/T sensors declared in the URDF (or added with :meth:`with_ft_sensor`).
        q_to_body: ``(nv, nb)`` maps joint coordinates to each body's joint coordinate (mimic
            included).
        q_offset: ``(nb,)`` mimic offsets added to body joint positions, rad or m.
        C0: ``(nb, 3, 3)`` rotation of the joint frame in the parent body frame at q = 0.
        p0: ``(nb, 3)`` joint origin in the parent body frame at q = 0, m.
        axis: ``(nb, 3)`` unit joint axis in the body frame (0 for the root and fixed joints).
        is_revolute: ``(nb,)`` 1.0 where the body's joint is revolute or continuous.
        is_prismatic: ``(nb,)`` 1.0 where the body's joint is prismatic.
        mass: ``(nb,)`` kg.
        com: ``(nb, 3)`` centre of mass in the body frame, m.
        inertia_com: ``(nb, 3, 3)`` rotational inertia about the centre of mass, body axes, kg m^2.
        gravity: ``(3,)`` gravity acceleration in the root frame, m/s^2 (default ``(0, 0, -9.81)``;
            :meth:`with_gravity` changes it). Used by every algorithm on a fixed base; a moving base
            measured by an IMU brings its own proper acceleration instead.
        urdf_sha256: hash of the URDF text the model was built from (what checkpoints and
            graphs of earlier versions recorded; :attr:`identity` is what they record now).
        identity: the robot's :class:`~torchcontact.identity.RobotIdentity`, a canonical
            description of the parsed model (``identity.sha256`` keys checkpoints and graphs);
            set by :meth:`from_urdf` and kept up to date by the ``with_*`` methods.
        joint_parent_link: joint name -> its URDF parent link.
        joint_limits: ``"lower"``, ``"upper"`` (rad or m), ``"velocity"`` (rad/s or m/s),
            ``"effort"`` (N m or N) -> ``(nv,)`` numpy float64 in ``joint_names`` order, from the
            URDF ``<limit>`` (-inf/inf where absent; a continuous joint has no position limit).
    """

    name: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    body_names: tuple[str, ...]
    body_parent: tuple[int, ...]
    body_joint: tuple[str, ...]
    levels: tuple[tuple[int, int], ...]
    level_parent: tuple[Tensor, ...]
    frames: dict[str, Frame]
    ft_sensors: dict[str, FTSensor]
    q_to_body: Tensor
    q_offset: Tensor
    C0: Tensor
    p0: Tensor
    axis: Tensor
    is_revolute: Tensor
    is_prismatic: Tensor
    mass: Tensor
    com: Tensor
    inertia_com: Tensor
    gravity: Tensor
    urdf_sha256: str = ""
    identity: RobotIdentity = field(default_factory=lambda: RobotIdentity(()))
    joint_parent_link: dict[str, str] = field(default_factory=dict)
    joint_limits: dict[str, np.ndarray] = field(default_factory=dict)

    # ------------------------------------------------------------------ basic properties
    @property
    def nv(self) -> int:
        """Number of independent joint coordinates."""
        return len(self.joint_names)

    @property
    def nb(self) -> int:
        """Number of bodies, the root included."""
        return len(self.body_names)

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the model's tensors."""
        return self.C0.dtype

    @property
    def device(self) -> torch.device:
        """Device of the model's tensors."""
        return self.C0.device

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> RobotModel:
        """Return a copy with every tensor moved to ``device`` and/or cast to ``dtype``.

        Args:
            device: target device, or None to keep.
            dtype: target floating dtype, or None to keep.

        Returns:
            A new :class:`RobotModel`; ``self`` is unchanged.
        """
        if dtype is not None and not dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating dtype, got {dtype}")
        changes: dict[str, object] = {
            f: getattr(self, f).to(device=device, dtype=dtype) for f in _TENSOR_FIELDS
        }
        changes["level_parent"] = tuple(t.to(device=device) for t in self.level_parent)
        return replace(self, **changes)

    def with_gravity(self, gravity: Sequence[float] | Tensor) -> RobotModel:
        """Return a copy with another gravity vector.

        Args:
            gravity: ``(3,)`` gravity acceleration in the root frame, m/s^2.

        Returns:
            A new :class:`RobotModel`; ``self`` is unchanged.

        Example:
            >>> import torchcontact as tc
            >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path()).with_gravity((0, 0, -1.62))
            >>> m.gravity.tolist()
            [0.0, 0.0, -1.62]
        """
        g = torch.as_tensor(gravity, dtype=self.dtype).to(self.device).reshape(-1)
        if g.shape != (3,) or not bool(torch.isfinite(g).all()):
            raise InputError(f"gravity must be 3 finite numbers, got {gravity!r}")
        return replace(self, gravity=g)

    def with_point_mass(
        self, link: str, mass: float, com_link: Sequence[float] = (0.0, 0.0, 0.0)
    ) -> RobotModel:
        """Return a copy with a point mass rigidly added to the body of ``link`` (a payload).

        Args:
            link: a link or frame name.
            mass: kg (> 0).
            com_link: ``(3,)`` the point mass's position in ``link``'s frame, m.

        Returns:
            A new :class:`RobotModel` whose body carries the combined mass, centre of mass and
            inertia (parallel-axis theorem, :func:`torchcontact.spatial.combine_inertias`).

        Example:
            >>> import torchcontact as tc
            >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
            >>> b = m.frame("hand").body
            >>> float(m.with_point_mass("hand", 0.5).mass[b] - m.mass[b])
            0.5
        """
        if not mass > 0:
            raise InputError(f"point mass must be > 0 kg, got {mass!r}")
        fr = self.frame(link)
        b = fr.body
        c = fr.R_body_frame @ np.asarray(com_link, float) + fr.p_body_frame

        def np_(t: Tensor) -> np.ndarray:
            return t.detach().to("cpu", torch.float64).numpy()

        m1, c1, I1 = combine_inertias(
            [(float(self.mass[b]), np_(self.com[b]), np_(self.inertia_com[b])),
             (float(mass), c, np.zeros((3, 3)))]
        )  # fmt: skip
        mass_t, com_t, in_t = self.mass.clone(), self.com.clone(), self.inertia_com.clone()
        mass_t[b] = m1
        com_t[b] = torch.as_tensor(c1, dtype=self.dtype, device=self.device)
        in_t[b] = torch.as_tensor(I1, dtype=self.dtype, device=self.device)
        added = sum(1 for e in self.identity.entries if e[0] == f"link {link}" and
                    e[1].startswith("added mass"))  # fmt: skip
        ident = self.identity.replace(
            [entry(f"link {link}", f"added mass {added + 1}", [mass, *com_link], "kg, m")]
        )
        return replace(self, mass=mass_t, com=com_t, inertia_com=in_t, identity=ident)

    def body_of(self, name: str) -> int:
        """Index of the body a link or joint frame named ``name`` is attached to.

        Raises:
            KeyError: ``name`` is no frame of the model; the message lists close names.
        """
        return self.frame(name).body

    def frame(self, name: str) -> Frame:
        """The :class:`Frame` named ``name`` (a URDF link or a joint).

        Raises:
            KeyError: ``name`` is no frame of the model; the message lists close names.
        """
        try:
            return self.frames[name]
        except KeyError:
            import difflib

            close = difflib.get_close_matches(name, list(self.frames), n=5)
            hint = f"; did you mean {close}?" if close else ""
            raise KeyError(f"no link or joint frame named {name!r} in {self.name}{hint}") from None

    def subtree(self, body: int) -> list[int]:
        """Body indices of the subtree rooted at ``body`` (``body`` included), ascending."""
        inside = [False] * self.nb
        inside[body] = True
        for i in range(body + 1, self.nb):  # breadth-first order: parents precede children
            p = self.body_parent[i]
            inside[i] = p >= 0 and inside[p]
        return [i for i in range(self.nb) if inside[i]]

    def inverse_dynamics(self, q: Tensor, qd: Tensor, qdd: Tensor, **kwargs) -> Tensor:
        """Joint torques, ``(*B, nv)``; see :func:`torchcontact.inverse_dynamics` for arguments."""
        from torchcontact.dynamics import inverse_dynamics

        return inverse_dynamics(self, q, qd, qdd, **kwargs)

    def forward_pass(self, q: Tensor, qd: Tensor, qdd: Tensor, **kwargs):
        """Poses, twists, accelerations of all bodies; see :func:`torchcontact.forward_pass`."""
        from torchcontact.dynamics import forward_pass

        return forward_pass(self, q, qd, qdd, **kwargs)

    def frame_pose(self, fp, name: str) -> tuple[Tensor, Tensor]:
        """Pose of a named frame in the root frame from a forward pass.

        Args:
            fp: a :class:`torchcontact.ForwardPass` with ``(*B, nb, ...)`` fields.
            name: a URDF link or joint name.

        Returns:
            ``R_root_frame`` ``(*B, 3, 3)`` and ``p_root_frame`` ``(*B, 3)`` (m).
        """
        fr = self.frame(name)
        R_b, p_b = fp.R[..., fr.body, :, :], fp.p[..., fr.body, :]
        R_bf = torch.as_tensor(fr.R_body_frame, dtype=R_b.dtype, device=R_b.device)
        p_bf = torch.as_tensor(fr.p_body_frame, dtype=R_b.dtype, device=R_b.device)
        return R_b @ R_bf, (R_b @ p_bf.unsqueeze(-1)).squeeze(-1) + p_b

    def __repr__(self) -> str:
        return (
            f"RobotModel(name={self.name!r}, nv={self.nv}, nb={self.nb}, depth={len(self.levels)},"
            f" ft_sensors={list(self.ft_sensors)}, dtype={self.dtype}, device={self.device})"
        )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls,
        urdf: str | os.PathLike | io.IOBase,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
        keep_fixed: Iterable[str] = (),
        root: str | None = None,
    ) -> RobotModel:
        """Build a model from a URDF file.

        Args:
            urdf: path to a ``.urdf`` file, or an open file object with its XML text.
            dtype: floating dtype of the model's tensors (float64 recommended for estimation).
            device: device of the model's tensors.
            keep_fixed: names of fixed joints to keep as body boundaries (besides those carrying
                an F/T sensor), e.g. to declare a sensor on them later with
                :meth:`with_ft_sensor`.
            root: name of the root link; by default the single link that is no joint's child.

        Returns:
            The :class:`RobotModel`.

        Raises:
            URDFError: malformed XML, an unknown joint type, a joint naming a missing link, a
                cycle or several roots, a moving link without ``<inertial>``, or a malformed
                ``<sensor>``; the message names the element.
            FileNotFoundError: ``urdf`` is a path that does not exist.
        """
        from torchcontact import _urdf

        text, source = _urdf.read_text(urdf)
        parsed = _urdf.parse(text, source)
        return _build(parsed, dtype, device, set(keep_fixed), root, source, text)

    def with_ft_sensor(
        self,
        name: str,
        joint: str,
        frame: Literal["child", "parent", "sensor"] = "child",
        measure_direction: Literal["parent_to_child", "child_to_parent"] = "child_to_parent",
        R_child_sensor: np.ndarray | None = None,
        p_child_sensor: np.ndarray | None = None,
    ) -> RobotModel:
        """Return a copy with one more F/T sensor, on a fixed joint that is a body boundary.

        Args:
            name: sensor name (the key of its reading).
            joint: a fixed joint that splits two bodies (carries a URDF sensor, or was named in
                ``keep_fixed`` of :meth:`from_urdf`), or a moving joint's name is refused.
            frame: ``"child"`` (the joint's child link frame), ``"parent"`` (the joint's parent
                link frame) or ``"sensor"`` (the pose given by ``R_child_sensor``/``p_child_sensor``
                relative to the child link).
            measure_direction: ``"child_to_parent"`` or ``"parent_to_child"`` (iDynTree).
            R_child_sensor: ``(3, 3)`` sensor rotation in the child link frame (``"sensor"`` only).
            p_child_sensor: ``(3,)`` sensor origin in the child link frame, m (``"sensor"`` only).

        Raises:
            ValueError: the joint is unknown, moving, or merged into a body.
        """
        child = [b for b, j in enumerate(self.body_joint) if j == joint]
        if not child:
            known = joint in {f for f in self.frames}
            why = (
                "it is a fixed joint merged inside a body: pass keep_fixed=[...] to from_urdf"
                if known
                else "no such joint"
            )
            raise ValueError(f"cannot put F/T sensor {name!r} on joint {joint!r}: {why}")
        b = child[0]
        if self.is_revolute[b] or self.is_prismatic[b]:
            raise ValueError(f"cannot put F/T sensor {name!r} on moving joint {joint!r}")
        parent_link = self.frame(self.joint_parent_link[joint])
        # rest transform parent link -> child link (= child body frame) across the fixed joint
        R_pb_c, p_pb_c = self.C0[b].double().cpu().numpy(), self.p0[b].double().cpu().numpy()
        R_pc = parent_link.R_body_frame.T @ R_pb_c
        p_pc = parent_link.R_body_frame.T @ (p_pb_c - parent_link.p_body_frame)
        R_cs, p_cs = _reading_frame(
            frame, R_pc, p_pc,
            np.eye(3) if R_child_sensor is None else np.asarray(R_child_sensor, float),
            np.zeros(3) if p_child_sensor is None else np.asarray(p_child_sensor, float),
        )  # fmt: skip
        sensor = _make_sensor(
            name, joint, self.body_parent[b], b, frame, measure_direction, R_cs, p_cs
        )
        ident = self.identity.replace(_sensor_entries(sensor))
        return replace(self, ft_sensors={**self.ft_sensors, name: sensor}, identity=ident)


def _make_sensor(name, joint, parent_body, child_body, frame, direction, R_cs, p_cs) -> FTSensor:
    """An :class:`FTSensor`; ``(R_cs, p_cs)`` is the reading frame in the child body frame."""
    if frame not in ("child", "parent", "sensor"):
        raise URDFError(f"sensor {name!r}: <frame> must be child, parent or sensor, got {frame!r}")
    if direction not in ("parent_to_child", "child_to_parent"):
        raise URDFError(
            f"sensor {name!r}: <measure_direction> must be parent_to_child or child_to_parent,"
            f" got {direction!r}"
        )
    return FTSensor(name, joint, parent_body, child_body, frame, direction, R_cs, p_cs)


def _reading_frame(frame: str, R_pc, p_pc, R_origin, p_origin):
    """Pose in the child link frame of the frame a reading is expressed in (iDynTree's rules).

    ``(R_pc, p_pc)`` is the joint's rest transform parent link -> child link; ``(R_origin,
    p_origin)`` the sensor's ``<origin>``, relative to the child link.
    """
    if frame == "parent":
        return R_pc.T, -R_pc.T @ p_pc
    if frame == "sensor":
        return R_origin, p_origin
    return np.eye(3), np.zeros(3)


def _build(parsed, dtype, device, keep_fixed, root, source, text) -> RobotModel:
    links, joints, sensors = parsed["links"], parsed["joints"], parsed["sensors"]
    # Tree structure: every joint names existing links; each link has at most one parent.
    child_of: dict[str, dict] = {}
    children: dict[str, list[dict]] = {name: [] for name in links}
    for j in joints:
        for role in ("parent", "child"):
            if j[role] not in links:
                raise URDFError(
                    f"{source}: joint {j['name']!r} names missing {role} link {j[role]!r}"
                )
        if j["type"] not in _KNOWN_TYPES:
            raise URDFError(f"{source}: joint {j['name']!r} has unknown type {j['type']!r}")
        if j["type"] in ("floating", "planar"):
            raise URDFError(
                f"{source}: joint {j['name']!r} of type {j['type']!r} is not supported; model a"
                " moving base with the base-motion input of inverse_dynamics instead"
            )
        if j["child"] in child_of:
            raise URDFError(
                f"{source}: link {j['child']!r} is the child of two joints,"
                f" {child_of[j['child']]['name']!r} and {j['name']!r} (the URDF must be a tree)"
            )
        child_of[j["child"]] = j
        children[j["parent"]].append(j)
    roots = [name for name in links if name not in child_of]
    if root is None:
        if len(roots) != 1:
            cyc = "a cycle" if not roots else f"several roots {roots}"
            raise URDFError(f"{source}: the links do not form one tree ({cyc})")
        root = roots[0]
    elif root not in links:
        raise URDFError(f"{source}: root link {root!r} is not in the URDF")
    reached = {root}
    stack = [root]
    while stack:
        for j in children[stack.pop()]:
            reached.add(j["child"])
            stack.append(j["child"])
    if len(reached) != len(links):
        missing = sorted(set(links) - reached)[:5]
        raise URDFError(
            f"{source}: links {missing} are not reachable from root {root!r} (a cycle?)"
        )

    sensor_joints = {}
    joint_by_name = {j["name"]: j for j in joints}
    for s in sensors:
        if s["joint"] not in joint_by_name:
            raise URDFError(f"{source}: sensor {s['name']!r} names missing joint {s['joint']!r}")
        if joint_by_name[s["joint"]]["type"] != "fixed":
            raise URDFError(f"{source}: sensor {s['name']!r} sits on moving joint {s['joint']!r}")
        sensor_joints[s["joint"]] = s
    boundary = set(sensor_joints) | set(keep_fixed)
    unknown_keep = set(keep_fixed) - set(joint_by_name)
    if unknown_keep:
        raise URDFError(f"{source}: keep_fixed names unknown joints {sorted(unknown_keep)}")

    # Moving links need inertial parameters (a massless moving link is almost always a URDF bug).
    for j in joints:
        if j["type"] in _MOVING and links[j["child"]]["inertial"] is None:
            raise URDFError(
                f"{source}: link {j['child']!r} (child of {j['type']} joint {j['name']!r}) has no"
                " <inertial>"
            )

    # Depth-first joint order (pinocchio's): visit children in URDF document order.
    joint_order: list[str] = []
    mimics: dict[str, dict] = {}

    def dfs(link: str) -> None:
        for j in children[link]:
            if j["type"] in _MOVING:
                if j["mimic"] is None:
                    joint_order.append(j["name"])
                else:
                    mimics[j["name"]] = j
            dfs(j["child"])

    dfs(root)
    for name, j in mimics.items():
        lead = j["mimic"]["joint"]
        if lead not in joint_by_name or lead not in joint_order:
            raise URDFError(
                f"{source}: mimic joint {name!r} follows {lead!r}, which is not an independent"
                " moving joint"
            )

    # Bodies: a depth-first walk opens a body at every moving or boundary joint and merges the
    # child of any other fixed joint into its parent's body; link_in_body[link] = (body, R, p)
    # with (R, p) = T_body_link. Bodies are then sorted by depth (stably) so that each depth is a
    # contiguous range whose parents all lie in the previous one.
    body_names: list[str] = [root]
    body_parent: list[int] = [-1]
    body_joint: list[dict | None] = [None]
    depth: list[int] = [0]
    link_in_body: dict[str, tuple[int, np.ndarray, np.ndarray]] = {
        root: (0, np.eye(3), np.zeros(3))
    }
    stack = [root]
    while stack:
        link = stack.pop()
        b, R_bl, p_bl = link_in_body[link]
        for j in reversed(children[link]):
            if j["type"] == "fixed" and j["name"] not in boundary:
                link_in_body[j["child"]] = (b, R_bl @ j["R"], R_bl @ j["p"] + p_bl)
            else:
                body_names.append(j["child"])
                body_parent.append(b)
                body_joint.append(j)
                depth.append(depth[b] + 1)
                link_in_body[j["child"]] = (len(body_names) - 1, np.eye(3), np.zeros(3))
            stack.append(j["child"])
    order = sorted(range(len(body_names)), key=lambda i: depth[i])
    new_index = {old: new for new, old in enumerate(order)}
    body_names = [body_names[i] for i in order]
    body_parent = [-1 if body_parent[i] < 0 else new_index[body_parent[i]] for i in order]
    body_joint = [body_joint[i] for i in order]
    depth = [depth[i] for i in order]
    link_in_body = {k: (new_index[b], R, p) for k, (b, R, p) in link_in_body.items()}
    nb = len(body_names)

    # Levels and parent indices local to the previous level.
    levels: list[tuple[int, int]] = []
    for d in range(max(depth) + 1):
        idx = [i for i in range(nb) if depth[i] == d]
        levels.append((idx[0], idx[-1] + 1))
    level_parent = []
    for d in range(1, len(levels)):
        s, e = levels[d]
        ps = levels[d - 1][0]
        level_parent.append(torch.tensor([body_parent[i] - ps for i in range(s, e)], device=device))

    # Inertias merged per body, in the body frame.
    parts: list[list] = [[] for _ in range(nb)]
    for name, link in links.items():
        if link["inertial"] is None:
            continue
        b, R_bl, p_bl = link_in_body[name]
        m, R_li, p_li, I_i = link["inertial"]
        R_bi = R_bl @ R_li
        parts[b].append((m, R_bl @ p_li + p_bl, R_bi @ I_i @ R_bi.T))
    mass = np.zeros(nb)
    com = np.zeros((nb, 3))
    inertia = np.zeros((nb, 3, 3))
    for b in range(nb):
        mass[b], com[b], inertia[b] = combine_inertias(parts[b])

    # Joint placement and motion per body.
    nv = len(joint_order)
    jindex = {n: k for k, n in enumerate(joint_order)}
    q_to_body = np.zeros((nv, nb))
    q_offset = np.zeros(nb)
    C0 = np.tile(np.eye(3), (nb, 1, 1))
    p0 = np.zeros((nb, 3))
    axis = np.zeros((nb, 3))
    is_rev = np.zeros(nb)
    is_pri = np.zeros(nb)
    for b in range(1, nb):
        j = body_joint[b]
        _, R_pl, p_pl = link_in_body[j["parent"]]
        R0 = R_pl @ j["R"]
        C0[b] = R0
        p0[b] = R_pl @ j["p"] + p_pl
        if j["type"] == "fixed":
            continue
        a = j["axis"]
        axis[b] = a
        if j["mimic"] is None:
            lead, mult, off = j["name"], 1.0, 0.0
        else:
            lead, mult, off = j["mimic"]["joint"], j["mimic"]["multiplier"], j["mimic"]["offset"]
        q_to_body[jindex[lead], b] = mult
        q_offset[b] = off
        if j["type"] == "prismatic":
            is_pri[b] = 1.0
        else:
            is_rev[b] = 1.0

    frames: dict[str, Frame] = {}
    for name, (b, R, p) in link_in_body.items():
        frames[name] = Frame(name, b, R, p)
    for j in joints:  # a joint's frame is its child link's frame
        if j["name"] not in frames:
            frames[j["name"]] = Frame(j["name"], *link_in_body[j["child"]])
    ft: dict[str, FTSensor] = {}
    for s in sensors:
        j = joint_by_name[s["joint"]]
        cb = link_in_body[j["child"]][0]
        R_cs, p_cs = _reading_frame(s["frame"], j["R"], j["p"], s["R"], s["p"])
        sensor = _make_sensor(
            s["name"], j["name"], body_parent[cb], cb, s["frame"], s["direction"], R_cs, p_cs
        )
        if s["name"] in ft:
            raise URDFError(f"{source}: sensor {s['name']!r} is declared twice")
        ft[s["name"]] = sensor

    def t(x):  # float64 first: the identity is computed from float64 values
        return torch.as_tensor(np.asarray(x), dtype=torch.float64, device=device)

    model = RobotModel(
        name=parsed["name"],
        joint_names=tuple(joint_order),
        joint_types=tuple(joint_by_name[n]["type"] for n in joint_order),
        body_names=tuple(body_names),
        body_parent=tuple(body_parent),
        body_joint=tuple("" if j is None else j["name"] for j in body_joint),
        levels=tuple(levels),
        level_parent=tuple(level_parent),
        frames=frames,
        ft_sensors=ft,
        q_to_body=t(q_to_body),
        q_offset=t(q_offset),
        C0=t(C0),
        p0=t(p0),
        axis=t(axis),
        is_revolute=t(is_rev),
        is_prismatic=t(is_pri),
        mass=t(mass),
        com=t(com),
        inertia_com=t(inertia),
        gravity=t([0.0, 0.0, -9.81]),
        urdf_sha256=hashlib.sha256(text.encode()).hexdigest(),
        joint_parent_link={j["name"]: j["parent"] for j in joints},
        joint_limits={
            key: np.array(
                [
                    joint_by_name[n]["limit"][key]
                    if not (key in ("lower", "upper") and joint_by_name[n]["type"] == "continuous")
                    else (-np.inf if key == "lower" else np.inf)
                    for n in joint_order
                ]
            )
            for key in ("lower", "upper", "velocity", "effort")
        },
    )
    model = replace(model, identity=_describe(parsed, joint_order, ft))
    return model if dtype == torch.float64 else model.to(dtype=dtype)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


def _sensor_entries(s: FTSensor) -> list[tuple]:
    """Identity entries of an F/T sensor: joint, reading frame (child body frame), direction."""
    where = f"sensor {s.name}"
    return [
        entry(where, "joint", [s.joint, s.measure_direction]),
        entry(where, "frame", [*np.asarray(s.R_child_sensor).ravel(), *s.p_child_sensor], "m"),
    ]


def _describe(parsed: dict, joint_order: Sequence[str], sensors: dict) -> RobotIdentity:
    """The :class:`~torchcontact.identity.RobotIdentity` of a parsed URDF (see that module).

    Per link and joint as the URDF declares them, so that how the model is built from it (fixed
    joints merged or kept as body boundaries) does not change it.
    """
    out = [entry("robot", "joints", joint_order)]
    for name in sorted(parsed["links"]):
        inertial = parsed["links"][name]["inertial"]
        where = f"link {name}"
        if inertial is None:
            out.append(entry(where, "inertial", ["none"]))
            continue
        m, R, p, I = inertial  # noqa: E741 - the inertia tensor
        out += [
            entry(where, "mass", [m], "kg"),
            entry(where, "inertial origin", [*np.asarray(R).ravel(), *p], "m"),
            entry(where, "inertia", [I[0, 0], I[0, 1], I[0, 2], I[1, 1], I[1, 2], I[2, 2]],
                  "kg m^2"),
        ]  # fmt: skip
    for j in sorted(parsed["joints"], key=lambda j: j["name"]):
        where = f"joint {j['name']}"
        out.append(entry(where, "type", [j["type"], j["parent"], j["child"]]))
        out.append(entry(where, "origin", [*np.asarray(j["R"]).ravel(), *j["p"]], "m"))
        if j["type"] in _MOVING:
            out.append(entry(where, "axis", j["axis"]))
            out.append(entry(where, "velocity limit", [j["limit"]["velocity"]], "rad/s or m/s"))
            if j["mimic"] is not None:
                mm = j["mimic"]
                out.append(entry(where, "mimic", [mm["joint"], mm["multiplier"], mm["offset"]]))
    for s in sensors.values():
        out += _sensor_entries(s)
    return RobotIdentity(tuple(out))
