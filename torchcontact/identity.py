"""The identity of a robot: a canonical description of the parsed model, and its hash.

Checkpoints (:mod:`torchcontact.residual`) and exported graphs (:mod:`torchcontact.onnx`) are
made for one robot. They record its :class:`RobotIdentity`, computed by
:attr:`torchcontact.RobotModel.identity` from the parsed model, not from the URDF text: an XML
comment, a re-indentation or a reordering of elements leaves it unchanged, while every number the
estimator reads changes it (a 10 g mass change does). It lists, in a fixed order:

- the joint coordinates (the order of ``q``);
- per link, as the URDF declares it: its mass, inertial origin and rotational inertia (and the
  point masses :meth:`~torchcontact.RobotModel.with_point_mass` added);
- per joint: its type, parent and child links, origin, and for a moving joint its axis, velocity
  limit (the implausibility check reads it) and mimic coupling;
- each F/T sensor's joint, measure direction and reading frame.

It is per link and joint, so how a model is built from the URDF (fixed joints merged into
bodies or kept as boundaries) does not change it; position and effort limits, which the
estimator does not read, are not listed.

Numbers are rounded to 10 significant digits (and to 1e-12 absolutely), so that the same robot
parsed from text that writes a number differently, or merged in another order, has the same
identity. :meth:`RobotIdentity.difference` names the first entry that differs, e.g.
``link hand: mass 0.5 vs 0.51 kg``.

This module imports nothing heavy: the torch-free runtime reads identities from graphs.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

__all__ = ["RobotIdentity", "entry"]

#: Format tag hashed with the entries (a change of what is listed changes every hash).
VERSION = "torchcontact.robot/1"


def _number(x: float) -> float:
    """``x`` rounded to 10 significant digits (values below 1e-12 in magnitude are 0)."""
    x = float(x)
    if not math.isfinite(x):
        return x
    if abs(x) < 1e-12:
        return 0.0
    return float(f"{x:.10g}") + 0.0  # + 0.0: no negative zero


def entry(subject: str, quantity: str, values: Iterable, unit: str = "") -> tuple:
    """One entry of an identity: ``(subject, quantity, values, unit)`` with values canonical.

    Args:
        subject: what it is about, e.g. ``"link hand"``.
        quantity: e.g. ``"mass"``.
        values: numbers (rounded) or strings.
        unit: SI unit of the numbers ("" for none).
    """
    vals = tuple(v if isinstance(v, str) else _number(v) for v in values)
    return (subject, quantity, vals, unit)


def _show(values: Sequence) -> str:
    return " ".join(v if isinstance(v, str) else f"{v:.6g}" for v in values)


@dataclass(frozen=True)
class RobotIdentity:
    """A robot's canonical description (:func:`entry` tuples in a fixed order) and its hash.

    Attributes:
        entries: ``(subject, quantity, values, unit)`` per listed quantity.
    """

    entries: tuple[tuple, ...]

    @property
    def sha256(self) -> str:
        """Hex sha256 of the canonical JSON of :attr:`entries` (sorted: element order is moot)."""
        rows = sorted([e[0], e[1], list(e[2]), e[3]] for e in self.entries)
        text = json.dumps([VERSION, rows])
        return hashlib.sha256(text.encode()).hexdigest()

    def to_json(self) -> list:
        """JSON-ready list of the entries."""
        return [[s, q, list(v), u] for s, q, v, u in self.entries]

    @classmethod
    def from_json(cls, data: Sequence) -> RobotIdentity:
        """Inverse of :meth:`to_json`.

        Raises:
            ValueError: ``data`` is not a list of ``[subject, quantity, values, unit]``.
        """
        try:
            return cls(tuple((str(s), str(q), tuple(v), str(u)) for s, q, v, u in data))
        except (TypeError, ValueError) as e:
            raise ValueError(f"not a robot identity: {e}") from None

    def replace(self, entries: Iterable[tuple]) -> RobotIdentity:
        """A copy with ``entries`` replacing those of the same subject and quantity (or added)."""
        new = {(e[0], e[1]): e for e in entries}
        out = [new.pop((e[0], e[1]), e) for e in self.entries]
        return RobotIdentity((*out, *new.values()))

    def difference(self, other: RobotIdentity) -> str | None:
        """The first entry that differs, as ``"link hand: mass 0.5 vs 0.51 kg"`` (None: equal).

        ``self`` is the recorded robot, ``other`` the one at hand.

        Example:
            >>> a = RobotIdentity((entry("link hand", "mass", [0.5], "kg"),))
            >>> a.difference(RobotIdentity((entry("link hand", "mass", [0.51], "kg"),)))
            'link hand: mass 0.5 vs 0.51 kg'
        """
        mine = {(e[0], e[1]): e for e in other.entries}
        for s, q, v, u in self.entries:
            theirs = mine.pop((s, q), None)
            if theirs is None:
                return f"{s}: {q} {_show(v)} {u}".rstrip() + " vs absent"
            if theirs[2] != v or theirs[3] != u:
                return f"{s}: {q} {_show(v)} vs {_show(theirs[2])} {u}".rstrip()
        for s, q, v, u in mine.values():
            return f"{s}: {q} absent vs {_show(v)} {u}".rstrip()
        return None
