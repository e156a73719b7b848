"""The frozen estimation model: one robot, sensor set and slot layout, resolved once.

:class:`EstimationModel` holds what every stage of :mod:`torchcontact.estimation.stages` reads:
the regions the chosen F/T sensors cut the tree into, the contact slots with their constant
placements, and the solve's and the status checks' constants.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from torchcontact import dynamics as _dyn
from torchcontact import spatial as sp
from torchcontact.contacts import KINDS
from torchcontact.errors import InputError
from torchcontact.model import FTSensor, RobotModel
from torchcontact.solve import RANK_RTOL

__all__ = ["EstimationModel", "Region", "Slot"]


@dataclass(frozen=True)
class Slot:
    """One contact slot of a layout.

    Attributes:
        link: the link or frame name the contact lies on.
        kind: one of :data:`torchcontact.KINDS`.
        body: the body the link belongs to.
        region: index of the region (sensor) that measures it.
        R: rotation of the link frame in the body's internal frame (constant).
        p: origin of the link frame in the body's internal frame, m (constant).
    """

    link: str
    kind: str
    body: int
    region: int
    R: sp.M3
    p: sp.V3


@dataclass(frozen=True)
class Region:
    """The bodies one F/T sensor measures, with what borders them.

    Attributes:
        sensor: the sensor's name.
        child: the sensor joint's child body (the region's root).
        sign: +1 if the reading is the wrench the parent side exerts on the region, -1 if opposite.
        T_child_sensor: pose of the reading frame in the child body's internal frame (constant).
        slots: indices of the layout's slots in this region.
        torque_coords: joint coordinates with a torque row here: every body they drive lies in the
            region and at least one holds a slot in its subtree.
    """

    sensor: str
    child: int
    sign: float
    T_child_sensor: sp.Pose
    slots: tuple[int, ...]
    torque_coords: tuple[int, ...]


@dataclass(frozen=True, eq=False)
class EstimationModel:
    """The estimator of one robot, sensor set and slot layout, built once (a frozen value).

    Holds the regions, slots and constants every stage reads; :meth:`to` returns a copy on
    another device or dtype. Build it with :meth:`build` (or through :class:`ContactEstimator`).

    Attributes:
        model: the robot.
        tree: its physics constants (:func:`torchcontact.dynamics.tree_of`).
        sensors: the chosen F/T sensors.
        region_of_body: per body, the index of its region, -1 for the root region.
        regions: one :class:`Region` per sensor, in ``sensors`` order.
        slots: the layout's :class:`Slot` s.
        rank_rtol: the solve's rank tolerance (relative to the largest diagonal of ``G``).
        velocity_limit: per coordinate, the ``|qd|`` above which a frame is implausible (status
            bit 64; inf: unchecked), or None.
        ft_range: per sensor, 6 bounds on ``|reading|`` (bit 64), or None.
        key: hash of everything above (identifies generated kernels).
    """

    model: RobotModel
    tree: _dyn.Tree
    sensors: tuple[FTSensor, ...]
    region_of_body: tuple[int, ...]
    regions: tuple[Region, ...]
    slots: tuple[Slot, ...]
    rank_rtol: float
    velocity_limit: tuple[float, ...] | None
    ft_range: tuple[tuple[float, ...] | None, ...]
    key: str
    _programs: dict = field(default_factory=dict, repr=False)

    @property
    def sensor_names(self) -> tuple[str, ...]:
        """Names of the chosen sensors."""
        return tuple(s.name for s in self.sensors)

    @property
    def links(self) -> tuple[str, ...]:
        """Slot links."""
        return tuple(s.link for s in self.slots)

    @property
    def kinds(self) -> tuple[str, ...]:
        """Slot kinds."""
        return tuple(s.kind for s in self.slots)

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> EstimationModel:
        """A copy whose robot model lives on ``device`` with ``dtype``."""
        return replace(self, model=self.model.to(device, dtype), _programs={})

    # ------------------------------------------------------------------ tree queries
    def cut_matrix(self) -> np.ndarray:
        """``D[i, j] = 1`` where a wrench on body ``j`` reaches body ``i``'s joint.

        The path from ``j`` towards the root stops at the first sensor's child body (the sensor
        measures the wrench there; beyond it the reading stands in for the subtree).
        """
        bodies = self.tree.bodies
        sensor_child = {reg.child for reg in self.regions}
        D = np.zeros((len(bodies), len(bodies)))
        for j in range(len(bodies)):
            i = j
            D[i, j] = 1.0
            while i not in sensor_child and bodies[i].parent >= 0:
                i = bodies[i].parent
                D[i, j] = 1.0
        return D

    def region_bodies(self) -> set[int]:
        """Bodies the regions need: every region body and its ancestors."""
        need: set[int] = set()
        for b, r in enumerate(self.region_of_body):
            if r >= 0:
                while b >= 0 and b not in need:
                    need.add(b)
                    b = self.tree.bodies[b].parent
        return need

    def torque_joints(self, joints: Sequence[str] | str | None) -> tuple[int, ...]:
        """Coordinates whose torques are wanted: all (None), named ones, or ``"sensed"``.

        ``"sensed"``: the coordinates whose torque the chosen sensors determine, i.e. every body
        in their joint's subtree, cut at the sensors, is an ancestor of (or in) a sensor region:
        the joints inside the regions and those between a sensor and the next body outside.

        Raises:
            InputError: an unknown joint name.
        """
        tree, model = self.tree, self.model
        if joints is None:
            return tuple(range(tree.nv))
        if joints == "sensed":
            need = self.region_bodies()
            D = self.cut_matrix()
            out = []
            for c in range(tree.nv):
                drivers = [i for i, b in enumerate(tree.bodies) if b.coord == c]
                if drivers and all(set(np.flatnonzero(D[i])) <= need for i in drivers):
                    out.append(c)
            return tuple(out)
        names = list(model.joint_names)
        bad = [j for j in joints if j not in names]
        if bad:
            raise InputError(f"unknown joints {bad}; the model has {names}")
        return tuple(sorted(names.index(j) for j in joints))

    def kept_bodies(self, coords: Sequence[int]) -> list[int]:
        """Body indices :meth:`prune` keeps (ascending): the regions', the torques' cut subtrees."""
        bodies = self.tree.bodies
        need = self.region_bodies()
        D = self.cut_matrix()
        for i, b in enumerate(bodies):
            if b.coord in coords:
                for j in np.flatnonzero(D[i]):
                    j = int(j)
                    while j >= 0 and j not in need:
                        need.add(j)
                        j = bodies[j].parent
        return sorted(need)

    def prune(self, coords: Sequence[int]) -> EstimationModel:
        """The layout restricted to the bodies its regions and the torques of ``coords`` need.

        Kept: every region body and its ancestors, and every body in the cut subtree of a joint
        of ``coords``, with their ancestors. Body indices are renumbered (parents first, as
        before); ``model`` keeps the full robot (index it through :meth:`kept_bodies`).
        """
        tree = self.tree
        keep = self.kept_bodies(coords)
        if len(keep) == len(tree.bodies):
            return self
        new = {old: k for k, old in enumerate(keep)}
        bodies = tuple(
            replace(tree.bodies[o], parent=new[tree.bodies[o].parent] if o else -1) for o in keep
        )
        order = tuple(new[o] for o in tree.order if o in new)
        return replace(
            self,
            tree=replace(tree, bodies=bodies, order=order),
            slots=tuple(replace(sl, body=new[sl.body]) for sl in self.slots),
            regions=tuple(replace(r, child=new[r.child]) for r in self.regions),
            region_of_body=tuple(self.region_of_body[o] for o in keep),
            _programs={},
        )

    @classmethod
    def build(
        cls,
        model: RobotModel,
        sensors: Sequence[str],
        links: Sequence[str],
        kinds: Sequence[str],
        rank_rtol: float | None = None,
        velocity_margin: float | None = None,
        ft_range: Mapping[str, float | Sequence[float]] | None = None,
    ) -> EstimationModel:
        """Resolve the regions and the slot layout.

        Args:
            model: the robot.
            sensors: names of the F/T sensors to use.
            links: per slot, the link or frame the contact lies on.
            kinds: per slot, its kind (:data:`torchcontact.KINDS`).
            rank_rtol: rank tolerance (default :data:`torchcontact.solve.RANK_RTOL`).
            velocity_margin: ``|qd|`` beyond this multiple of the URDF velocity limit marks a
                frame implausible (status bit 64); None: unchecked.
            ft_range: sensor -> measuring range (a number or 6 numbers, N and N m) beyond which
                a reading marks its frame implausible.

        Raises:
            InputError: an unknown sensor, kind or link, or a link outside every sensor's subtree.
        """
        tree = _dyn.tree_of(model)
        unknown = [s for s in sensors if s not in model.ft_sensors]
        if unknown:
            raise InputError(
                f"unknown F/T sensors {unknown}; the model has {list(model.ft_sensors)}"
                " (add one with model.with_ft_sensor)"
            )
        if not sensors:
            raise InputError(f"{model.name} has no F/T sensor to estimate contacts from")
        fts = tuple(model.ft_sensors[s] for s in sensors)
        child_of_sensor = {s.child_body: i for i, s in enumerate(fts)}
        region = [-1] * model.nb
        for b in range(model.nb):  # breadth-first order: the parent's region is known
            if b in child_of_sensor:
                region[b] = child_of_sensor[b]
            elif model.body_parent[b] >= 0:
                region[b] = region[model.body_parent[b]]
        if len(links) != len(kinds):
            raise InputError(f"{len(links)} slot links but {len(kinds)} kinds")
        slots = []
        for link, kind in zip(links, kinds, strict=True):
            if kind not in KINDS:
                raise InputError(f"contacts: unknown kind {kind!r}; expected one of {list(KINDS)}")
            try:
                fr = model.frame(link)
            except KeyError as e:
                raise InputError(f"contact on unknown link: {e.args[0]}") from None
            r = region[fr.body]
            if r < 0:
                raise InputError(
                    f"contact on link {link!r} lies outside every F/T sensor's subtree"
                    f" (sensors {list(sensors)}): nothing measures it"
                )
            R, p = _dyn.internal_frame(tree, fr.body, fr.R_body_frame, fr.p_body_frame)
            slots.append(Slot(link, kind, fr.body, r, sp.const_mat(R), sp.const_vec(p)))
        subtree = [set(model.subtree(b)) for b in range(model.nb)]
        regions = []
        for i, s in enumerate(fts):
            own = tuple(k for k, sl in enumerate(slots) if sl.region == i)
            coords = []
            for c in range(model.nv):
                drivers = [b for b, body in enumerate(tree.bodies) if body.coord == c]
                if (
                    drivers
                    and all(region[b] == i for b in drivers)
                    and any(slots[k].body in subtree[b] for b in drivers for k in own)
                ):
                    coords.append(c)
            R, p = _dyn.internal_frame(tree, s.child_body, s.R_child_sensor, s.p_child_sensor)
            regions.append(
                Region(
                    sensor=s.name,
                    child=s.child_body,
                    sign=1.0 if s.measure_direction == "parent_to_child" else -1.0,
                    T_child_sensor=(sp.const_mat(R), sp.const_vec(p)),
                    slots=own,
                    torque_coords=tuple(coords),
                )
            )
        rtol = RANK_RTOL.get(model.dtype, 1e-10) if rank_rtol is None else float(rank_rtol)
        vlim = None
        if velocity_margin is not None:
            if not velocity_margin > 0:
                raise InputError(f"velocity_margin must be positive, got {velocity_margin!r}")
            vmax = model.joint_limits.get("velocity", np.full(model.nv, np.inf))
            vlim = tuple(float(v) * float(velocity_margin) for v in vmax)
        ranges: list[tuple[float, ...] | None] = [None] * len(fts)
        for s, r in (ft_range or {}).items():
            if s not in sensors:
                raise InputError(f"ft_range names {s!r}, not one of the sensors {list(sensors)}")
            arr = np.broadcast_to(np.asarray(r, dtype=float), (6,))
            if not np.all(arr > 0):
                raise InputError(f"ft_range[{s!r}] must be positive, got {r!r}")
            ranges[list(sensors).index(s)] = tuple(float(v) for v in arr)
        key = hashlib.sha256(
            repr((tree.key, fts, slots, regions, rtol, vlim, ranges)).encode()
        ).hexdigest()
        return cls(
            model, tree, fts, tuple(region), tuple(regions), tuple(slots), rtol, vlim,
            tuple(ranges), key[:24],
        )  # fmt: skip
