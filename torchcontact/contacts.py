"""Contact slots: which links may be touched, how (the kind of unknown), and the per-frame data.

This is the one place a contact set is described. A tactile skin reporting a changing set of
contacts is described by the union of the slots it may use, with ``active`` telling which are in
contact in each frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

__all__ = ["KINDS", "Contacts"]

#: Contact kinds and their number of unknowns.
KINDS: dict[str, int] = {"wrench": 6, "force": 3, "force_dir": 1, "known": 0}


@dataclass(frozen=True)
class Contacts:
    """A batch of contact slots: K slots with fixed links and kinds, per-frame data.

    A tactile skin reporting a changing set of contacts is described by the union of the slots it
    may use, with ``active`` telling which are in contact in each frame.

    Attributes:
        links: K link (or joint/fixed frame) names the contacts lie on.
        kinds: K of ``"wrench"`` (6 unknowns), ``"force"`` (3; the moment about the contact point
            is zero), ``"force_dir"`` (1: the magnitude along a known direction), ``"known"`` (0: a
            given wrench, the paper's mu_eKnown).
        positions: ``(*B, K, 3)`` contact points in the link frame, m.
        directions: ``(*B, K, 3)`` force directions in the link frame (``force_dir`` slots; any
            length > 0, normalised internally), or None.
        wrenches: ``(*B, K, 6)`` ``[force (N); moment about the contact point (N m)]`` in the link
            frame for ``known`` slots, or None.
        active: ``(*B, K)`` bool, which slots are in contact in each frame; None means all.
        normals: ``(*B, K, 3)`` outward surface normals at the contacts, link frame (any length
            > 0; from the skin model or the log), or None. A force that pushes points into the
            surface, ``f . n < 0``. Used by friction-cone constrained estimation
            (``estimate(..., constraints=...)``).
        friction: friction coefficient ``mu > 0`` per slot, ``(*B, K)``, ``(K,)`` or a number:
            the force lies within ``atan(mu)`` of ``-n``; or None.
        cone_angle: the cone's half-angle instead of ``friction``, rad in ``(0, pi/2)``
            (``mu = tan(angle)``); give one of the two.
        pushing: which slots push (their force is confined to its friction cone), ``(*B, K)``
            or ``(K,)`` bool; None: every slot that is not ``known``. A ``force_dir`` slot
            pushes when its magnitude is >= 0 (no normal needed); a ``wrench`` slot's cone bounds
            its force part.
    """

    links: tuple[str, ...]
    kinds: tuple[str, ...]
    positions: Tensor
    directions: Tensor | None = None
    wrenches: Tensor | None = None
    active: Tensor | None = None
    normals: Tensor | None = None
    friction: Tensor | float | None = None
    cone_angle: Tensor | float | None = None
    pushing: Tensor | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "links", tuple(self.links))
        object.__setattr__(self, "kinds", tuple(self.kinds))
        if len(self.links) != len(self.kinds):
            raise ValueError(
                f"contacts: {len(self.links)} links but {len(self.kinds)} kinds; one kind per slot"
            )
        for k in self.kinds:
            if k not in KINDS:
                raise ValueError(f"contacts: unknown kind {k!r}; expected one of {list(KINDS)}")
        if self.friction is not None and self.cone_angle is not None:
            raise ValueError("contacts: give friction or cone_angle, not both")
        for name in ("friction", "cone_angle"):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not _in_range(name, float(v)):
                raise ValueError(f"contacts: {name} must be {_RANGE[name]}, got {v!r}")

    def friction_coefficient(self) -> Tensor | float | None:
        """``mu`` per slot: ``friction``, or ``tan(cone_angle)``, or None."""
        if self.cone_angle is None:
            return self.friction
        if isinstance(self.cone_angle, (int, float)):
            return math.tan(float(self.cone_angle))
        return self.cone_angle.tan()

    @property
    def K(self) -> int:  # noqa: N802 - the paper's and the API's name for the slot count
        """Number of contact slots."""
        return len(self.links)


_RANGE = {"friction": "a finite number > 0", "cone_angle": "in (0, pi/2) rad"}


def _in_range(name: str, v: float) -> bool:
    if name == "friction":
        return 0 < v < math.inf
    return 0 < v < math.pi / 2
