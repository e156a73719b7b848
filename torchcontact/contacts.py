"""Contacts: the one place a contact set is described, as slots or as records.

Two shapes of the same contacts, and the conversions between them:

- :class:`Contacts`: K *slots* with fixed links and kinds and per-frame tensors (``(*B, K, 3)``);
  what :class:`~torchcontact.ContactEstimator` and the exported ONNX graphs take.
- :class:`ContactRecords`: a variable number of *records* per frame (what a tactile skin reports,
  the ``contacts`` list of a log, the entries of a contact-spec file): flat numpy arrays with the
  frame of each record.

:class:`SlotLayout` assigns records to slots (the variable-count-to-slots assignment): the r-th
record of a ``(link, kind)`` pair in a frame goes to the r-th slot of that pair.
:meth:`Contacts.from_records` and :meth:`Contacts.to_records` convert between the two shapes, and
:func:`load_contact_spec` reads the TOML/JSON contact-spec files used by ``torchcontact convert
--contacts``, ``torchcontact run --contacts`` and ``torchcontact export estimator --contacts``.

Records and slots also carry what the friction-cone constrained estimate needs
(``estimate(..., constraints=...)``): each contact's outward surface normal, its friction
coefficient or cone half-angle, and whether it pushes.

torch is imported only by :meth:`Contacts.from_records`, so the records, layouts and specs serve
the live loop's onnxruntime path without torch.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from torchcontact.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import torch
    from torch import Tensor

__all__ = [
    "CONE_FIELDS",
    "KINDS",
    "ContactRecords",
    "ContactSpec",
    "Contacts",
    "SlotLayout",
    "load_contact_spec",
    "parse_contact_spec",
]

#: Contact kinds and their number of unknowns.
KINDS: dict[str, int] = {"wrench": 6, "force": 3, "force_dir": 1, "known": 0}
#: The friction-cone fields of a contact record (:class:`ContactRecords`).
CONE_FIELDS = ("normals", "friction", "cone_angle", "pushing")
#: Numeric fields of a record and their widths (None: one number per record).
_VECTOR_FIELDS: dict[str, int | None] = {
    "positions": 3, "directions": 3, "wrenches": 6, "normals": 3, "friction": None,
    "cone_angle": None, "pushing": None,
}  # fmt: skip


@dataclass(frozen=True)
class Contacts:
    """A batch of contact slots: K slots with fixed links and kinds, per-frame data.

    A tactile skin reporting a changing set of contacts is described by the union of the slots it
    may use, with ``active`` telling which are in contact in each frame
    (:meth:`from_records` builds it from per-frame records).

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
            raise InputError(
                f"contacts: {len(self.links)} links but {len(self.kinds)} kinds; one kind per slot"
            )
        for k in self.kinds:
            if k not in KINDS:
                raise InputError(f"contacts: unknown kind {k!r}; expected one of {list(KINDS)}")
        if self.friction is not None and self.cone_angle is not None:
            raise InputError("contacts: give friction or cone_angle, not both")
        for name in ("friction", "cone_angle"):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not _in_range(name, float(v)):
                raise InputError(f"contacts: {name} must be {_RANGE[name]}, got {v!r}")

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

    @classmethod
    def from_records(
        cls,
        records: ContactRecords,
        frames: int,
        layout: SlotLayout | None = None,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str = "cpu",
        friction: float | None = None,
        slot: np.ndarray | None = None,
    ) -> tuple[Contacts, np.ndarray]:
        """Slots from per-frame records: the variable-count-to-slots assignment.

        Args:
            records: M records of frames ``0 .. frames - 1``.
            frames: number of frames B.
            layout: the slots to fill (a fixed layout, e.g. an exported graph's); default
                :meth:`SlotLayout.covering` the records. Records that find no free slot of their
                ``(link, kind)`` in their frame are left out (their slot is -1).
            dtype: of the tensors (default float64).
            device: of the tensors.
            friction: friction coefficient of the records that give neither ``friction`` nor
                ``cone_angle`` (None: theirs stays NaN, which a constrained estimate refuses).
            slot: ``(M,)`` the records' slots from ``layout.assign(records)``, when the caller
                has them already (not computed again).

        Returns:
            ``(contacts, slot)``: :class:`Contacts` with ``(B, K, ...)`` tensors (``active`` marks
            the filled slots; inactive ``force_dir`` slots get the direction +z, other inactive
            data zeros), and ``slot`` ``(M,)`` int64, each record's slot (-1: none). When the
            records carry them (or ``friction`` is given), ``normals`` ``(B, K, 3)`` (NaN for a
            record without one), ``friction`` ``(B, K)`` (each record's ``mu``: its
            ``friction``, else ``tan(cone_angle)``, else ``friction``) and ``pushing``
            ``(B, K)`` (a record's own flag, else every kind but ``known``).

        Raises:
            InputError: a record's frame outside ``[0, frames)`` (see :meth:`SlotLayout.fill`).

        Example:
            >>> rec = ContactRecords(
            ...     frame=[0, 0, 1], links=["hand", "hand", "arm"], kinds=["force"] * 3,
            ...     positions=np.zeros((3, 3)))
            >>> c, slot = Contacts.from_records(rec, 2)
            >>> c.links, slot.tolist(), c.active.tolist()
            (('arm', 'hand', 'hand'), [1, 2, 0], [[False, True, True], [True, False, False]])
        """
        import torch

        dtype = torch.float64 if dtype is None else dtype
        layout = SlotLayout.covering(records) if layout is None else layout
        arrays, slot = layout.fill(records, frames, friction=friction, slot=slot)

        def t(x: np.ndarray | None) -> Tensor | None:
            # the arrays are fill's own: shared, not copied, when dtype and device allow
            return None if x is None else torch.as_tensor(x, dtype=dtype, device=device)

        pushing = arrays.get("pushing")
        contacts = cls(
            layout.links,
            layout.kinds,
            t(arrays["positions"]),  # type: ignore[arg-type]
            directions=t(arrays.get("directions")),
            wrenches=t(arrays.get("wrenches")),
            active=torch.as_tensor(arrays["active"], device=device),
            normals=t(arrays.get("normals")),
            friction=t(arrays.get("friction")),
            pushing=None if pushing is None else torch.as_tensor(pushing, device=device),
        )
        return contacts, slot

    def to_records(self) -> ContactRecords:
        """The active slots as records, frames numbered in the flattened batch order.

        Returns:
            :class:`ContactRecords` ordered by frame, then slot (the inverse of
            :meth:`from_records` up to the order of records within a frame).

        Example:
            >>> import torch
            >>> c = Contacts(["a", "b"], ["force", "force"], torch.zeros(2, 2, 3),
            ...              active=torch.tensor([[True, False], [True, True]]))
            >>> r = c.to_records()
            >>> r.frame.tolist(), r.links.tolist()
            ([0, 1, 1], ['a', 'a', 'b'])
        """
        K = self.K
        pos = self.positions.detach().reshape(-1, K, 3).cpu().double().numpy()
        n = pos.shape[0]
        if self.active is None:
            act = np.ones((n, K), bool)
        else:
            act = self.active.detach().reshape(n, K).cpu().numpy().astype(bool)
        f, k = np.nonzero(act)

        def per_record(x: Tensor | None, width: int) -> np.ndarray | None:
            if x is None:
                return None
            return x.detach().reshape(n, K, width).cpu().double().numpy()[f, k]

        def per_slot(x: Tensor | float | None) -> np.ndarray | None:
            if x is None:
                return None
            a = x.detach().cpu().double().numpy() if hasattr(x, "detach") else np.asarray(x, float)
            return np.broadcast_to(a, (*a.shape[:-1], K) if a.ndim else (K,)).reshape(-1, K)

        def slot_values(x: Tensor | float | None) -> np.ndarray | None:
            a = per_slot(x)
            return None if a is None else np.broadcast_to(a, (n, K))[f, k]

        push = slot_values(self.pushing)
        return ContactRecords(
            frame=f,
            links=np.asarray(self.links, dtype=object)[k],
            kinds=np.asarray(self.kinds, dtype=object)[k],
            positions=pos[f, k],
            directions=per_record(self.directions, 3),
            wrenches=per_record(self.wrenches, 6),
            normals=per_record(self.normals, 3),
            friction=slot_values(self.friction),
            cone_angle=slot_values(self.cone_angle),
            pushing=None if push is None else push.astype(np.float64),
        )


def _object_array(values: Any, M: int, name: str) -> np.ndarray:
    if isinstance(values, np.ndarray) and values.dtype == object and values.shape == (M,):
        return values
    out = np.empty(M, dtype=object)
    values = list(values)
    if len(values) != M:
        raise InputError(f"contact records: {name} has {len(values)} entries, expected {M}")
    out[:] = values
    return out


@dataclass(frozen=True)
class ContactRecords:
    """Contacts as a variable number of records per frame (numpy arrays, M records).

    Attributes:
        frame: ``(M,)`` int64, the frame of each record.
        links: ``(M,)`` object array of link (or frame) names; None marks a record without one.
        kinds: ``(M,)`` object array of :data:`KINDS` names (anything else marks a bad record).
        positions: ``(M, 3)`` float64 contact points in the link frame, m (NaN: missing).
        directions: ``(M, 3)`` float64 force directions of ``force_dir`` records, link frame (NaN:
            missing), or None when no record has one.
        wrenches: ``(M, 6)`` float64 ``[force (N); moment (N m)]`` of ``known`` records, link
            frame, or None.
        names: optional ``(link names, link codes, kind names, kind codes)`` with
            ``links == link_names[link_codes]`` (likewise kinds): the distinct names and each
            record's index among them, when the reader has them (Arrow dictionary encoding);
            :meth:`name_codes` computes them otherwise.
        normals: ``(M, 3)`` float64 outward surface normals, link frame (NaN: missing), or None.
        friction: ``(M,)`` float64 friction coefficients (NaN: not given), or None.
        cone_angle: ``(M,)`` float64 cone half-angles, rad (NaN: not given), or None; a record
            gives ``friction`` or ``cone_angle``.
        pushing: ``(M,)`` float64 1 (the contact pushes) or 0 (NaN: not given, which means
            every kind but ``known`` pushes), or None.

    Raises:
        InputError: arrays of inconsistent lengths or widths.
    """

    frame: np.ndarray
    links: np.ndarray
    kinds: np.ndarray
    positions: np.ndarray
    directions: np.ndarray | None = None
    wrenches: np.ndarray | None = None
    names: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = field(
        default=None, repr=False, compare=False
    )
    normals: np.ndarray | None = None
    friction: np.ndarray | None = None
    cone_angle: np.ndarray | None = None
    pushing: np.ndarray | None = None

    def __post_init__(self) -> None:
        frame = np.asarray(self.frame, dtype=np.int64).reshape(-1)
        M = len(frame)
        object.__setattr__(self, "frame", frame)
        object.__setattr__(self, "links", _object_array(self.links, M, "links"))
        object.__setattr__(self, "kinds", _object_array(self.kinds, M, "kinds"))
        for name, width in _VECTOR_FIELDS.items():
            value = getattr(self, name)
            if value is None:
                continue
            arr = np.asarray(value, dtype=np.float64)
            shape = (M,) if width is None else (M, width)
            if arr.shape != shape:
                raise InputError(
                    f"contact records: {name} must have shape {shape}, got {arr.shape}"
                )
            object.__setattr__(self, name, arr)

    @property
    def cone_fields(self) -> tuple[str, ...]:
        """The friction-cone fields these records carry (``normals``, ``friction``, ...)."""
        return tuple(n for n in CONE_FIELDS if getattr(self, n) is not None)

    def with_frame(self, frame: np.ndarray) -> ContactRecords:
        """The same records numbered with other frames."""
        return replace(self, frame=frame)

    @classmethod
    def concat(cls, parts: Sequence[ContactRecords]) -> ContactRecords:
        """Records of several parts, in order (a field missing from a part is NaN there)."""
        if not parts:
            return cls.empty()
        M = [len(p) for p in parts]

        def joined(name: str) -> np.ndarray | None:
            if all(getattr(p, name) is None for p in parts):
                return None
            w = _VECTOR_FIELDS[name]
            return np.concatenate(
                [np.full((m,) if w is None else (m, w), np.nan) if getattr(p, name) is None
                 else getattr(p, name) for p, m in zip(parts, M, strict=True)]
            )  # fmt: skip

        return cls(
            np.concatenate([p.frame for p in parts]),
            np.concatenate([p.links for p in parts]),
            np.concatenate([p.kinds for p in parts]),
            np.concatenate([p.positions for p in parts]),
            **{n: joined(n) for n in _VECTOR_FIELDS if n != "positions"},
        )

    def __len__(self) -> int:
        return len(self.frame)

    def name_codes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The records' names as codes: ``(link names, link codes, kind names, kind codes)``.

        Distinct names are object arrays (None included when a record has none); codes are each
        record's index among them. Computed once (or given by the reader).
        """
        if self.names is None:
            object.__setattr__(self, "names", (*_factorize(self.links), *_factorize(self.kinds)))
        return self.names  # type: ignore[return-value]

    @classmethod
    def empty(cls) -> ContactRecords:
        """No records."""
        return cls(np.zeros(0, np.int64), [], [], np.zeros((0, 3)))

    def select(self, index: np.ndarray) -> ContactRecords:
        """The records picked by a boolean mask or an index array, in that order."""

        def pick(x: np.ndarray | None) -> np.ndarray | None:
            return None if x is None else x[index]

        names = None
        if self.names is not None:
            ln, lc, kn, kc = self.names
            names = (ln, lc[index], kn, kc[index])
        return ContactRecords(
            self.frame[index],
            self.links[index],
            self.kinds[index],
            self.positions[index],
            pick(self.directions),
            pick(self.wrenches),
            names,
            **{n: pick(getattr(self, n)) for n in CONE_FIELDS},
        )


@dataclass(frozen=True)
class SlotLayout:
    """The links and kinds of K contact slots, and the assignment of records to them.

    Attributes:
        links: K link names.
        kinds: K kinds (:data:`KINDS`).
    """

    links: tuple[str, ...]
    kinds: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "links", tuple(self.links))
        object.__setattr__(self, "kinds", tuple(self.kinds))
        if len(self.links) != len(self.kinds):
            raise InputError(f"slot layout: {len(self.links)} links but {len(self.kinds)} kinds")

    @property
    def K(self) -> int:  # noqa: N802 - the slot count, as Contacts.K
        """Number of slots."""
        return len(self.links)

    @classmethod
    def covering(cls, records: ContactRecords) -> SlotLayout:
        """The smallest layout that holds every frame's records.

        For each ``(link, kind)`` pair (sorted), as many slots as the most records of that pair in
        one frame. Records without a link or with an unknown kind are ignored (filter them first
        to report them).

        Example:
            >>> rec = ContactRecords([0, 0, 1], ["b", "b", "a"], ["force"] * 3, np.zeros((3, 3)))
            >>> SlotLayout.covering(rec).links
            ('a', 'b', 'b')
        """
        keys, key_id = _pair_codes(records)
        rank = _rank_in_frame(records.frame, key_id)
        mult = np.zeros(len(keys), np.int64)
        ok = key_id >= 0
        np.maximum.at(mult, key_id[ok], rank[ok] + 1)
        links = [k[0] for k, m in zip(keys, mult, strict=True) for _ in range(int(m))]
        kinds = [k[1] for k, m in zip(keys, mult, strict=True) for _ in range(int(m))]
        return cls(tuple(links), tuple(kinds))

    def assign(self, records: ContactRecords) -> np.ndarray:
        """Each record's slot: the r-th record of a ``(link, kind)`` pair in a frame takes the r-th.

        Records keep their order within a frame.

        Returns:
            ``(M,)`` int64 slot index, -1 where the layout has no free slot of that pair.
        """
        first: dict[tuple[str, str], int] = {}
        count: dict[tuple[str, str], int] = {}
        for i, key in enumerate(zip(self.links, self.kinds, strict=True)):
            first.setdefault(key, i)
            count[key] = count.get(key, 0) + 1
        keys, key_id = _pair_codes(records)
        rank = _rank_in_frame(records.frame, key_id)
        # per distinct pair of the records (few): its first slot and slot count in the layout
        start = np.array([first.get(k, 0) for k in keys] + [0], np.int64)[key_id]
        mult = np.array([count.get(k, 0) for k in keys] + [0], np.int64)[key_id]
        return np.where((key_id >= 0) & (rank < mult), start + rank, -1)

    def fill(
        self,
        records: ContactRecords,
        frames: int,
        friction: float | None = None,
        slot: np.ndarray | None = None,
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Per-slot arrays of B frames from records (numpy; :meth:`Contacts.from_records` wraps it).

        Args:
            records: M records of frames ``0 .. frames - 1``.
            frames: number of frames B.
            friction: friction coefficient of records without ``friction`` or ``cone_angle``.
            slot: ``(M,)`` the records' slots from :meth:`assign`, when the caller has them.

        Returns:
            ``(arrays, slot)``: ``positions (B, K, 3)``, ``active (B, K)`` bool, and, when the
            layout has such slots, ``directions (B, K, 3)`` (inactive ``force_dir`` slots get +z)
            and ``wrenches (B, K, 6)``; when the records carry them, ``normals (B, K, 3)``
            (inactive slots: zeros), ``friction (B, K)`` (``friction``, else
            ``tan(cone_angle)``, else the default ``friction``; inactive slots: 1) and
            ``pushing (B, K)`` bool (a record's flag, else every kind but ``known``); ``slot
            (M,)`` from :meth:`assign` (-1: record left out). A ``force_dir`` or ``known`` record
            without its vector, a record without a normal or friction, gets NaN there.

        Raises:
            InputError: a record's frame outside ``[0, frames)``.
        """
        if len(records) and (records.frame.min() < 0 or records.frame.max() >= frames):
            raise InputError(f"contact records: frames must lie in [0, {frames})")
        slot = self.assign(records) if slot is None else slot
        K = self.K
        every = bool((slot >= 0).all())
        ok = np.arange(len(slot)) if every else np.flatnonzero(slot >= 0)
        f, k = records.frame[ok], slot[ok]
        flat = f * K + k  # (frame, slot) -> one index into the (B * K) rows
        out = {"positions": np.zeros((frames, K, 3)), "active": np.zeros((frames, K), bool)}
        pos = records.positions if every else records.positions[ok]
        out["positions"].reshape(-1, 3)[flat] = pos
        out["active"].reshape(-1)[flat] = True
        kinds = records.kinds[ok]
        if "force_dir" in self.kinds:
            D = out["directions"] = np.zeros((frames, K, 3))
            D[..., 2] = 1.0  # inactive force_dir slots: any nonzero direction
            sel = kinds == "force_dir"
            dirs = records.directions
            D[f[sel], k[sel]] = np.nan if dirs is None else dirs[ok[sel]]
        if "known" in self.kinds:
            W = out["wrenches"] = np.zeros((frames, K, 6))
            sel = kinds == "known"
            wr = records.wrenches
            W[f[sel], k[sel]] = np.nan if wr is None else wr[ok[sel]]
        if records.normals is not None:
            out["normals"] = np.zeros((frames, K, 3))
            out["normals"][f, k] = records.normals[ok]
        if records.friction is not None or records.cone_angle is not None or friction is not None:
            mu = np.full(len(ok), np.nan if friction is None else float(friction))
            if records.cone_angle is not None:
                angle = records.cone_angle[ok]
                mu = np.where(np.isnan(angle), mu, np.tan(angle))
            if records.friction is not None:
                mu = np.where(np.isnan(records.friction[ok]), mu, records.friction[ok])
            out["friction"] = np.ones((frames, K))
            out["friction"][f, k] = mu
        if records.pushing is not None:
            default = np.array([kd != "known" for kd in self.kinds], bool)
            out["pushing"] = np.repeat(default[None], frames, 0)
            given = records.pushing[ok]
            out["pushing"][f, k] = np.where(np.isnan(given), default[k], given > 0.5)
        return out, slot


def _factorize(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct values (object array; None last when present) and each value's index."""
    none = np.equal(values, None)
    uniq, codes = np.unique(np.where(none, "", values).astype(str), return_inverse=True)
    names, codes = uniq.astype(object), codes.reshape(-1)
    if none.any():
        names = np.append(names, None)
        codes = np.where(none, len(names) - 1, codes)
    return names, codes


def _pair_codes(records: ContactRecords) -> tuple[list[tuple[str, str]], np.ndarray]:
    """Sorted distinct valid ``(link, kind)`` pairs and each record's index among them.

    Returns:
        ``(pairs, code)``: ``code`` ``(M,)`` int64, -1 for a record without a link or with an
        unknown kind. Vectorized over records (a Python loop over the distinct names only).
    """
    M = len(records)
    code = np.full(M, -1, np.int64)
    if M == 0:
        return [], code
    ln, lc, kn, kc = records.name_codes()
    ok_link = np.array([isinstance(n, str) for n in ln], bool)
    ok_kind = np.array([k in KINDS for k in kn], bool)
    valid = ok_link[lc] & ok_kind[kc]
    uc, ci = np.unique(lc[valid] * len(kn) + kc[valid], return_inverse=True)
    pairs = [(str(ln[c // len(kn)]), str(kn[c % len(kn)])) for c in uc]
    order = sorted(range(len(pairs)), key=pairs.__getitem__)
    rank = np.empty(len(pairs), np.int64)
    rank[order] = np.arange(len(pairs))
    code[valid] = rank[ci.reshape(-1)]
    return [pairs[i] for i in order], code


def _rank_in_frame(frame: np.ndarray, key_id: np.ndarray) -> np.ndarray:
    """For each record, how many earlier records of its frame share its key (record order)."""
    M = len(frame)
    if M == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((np.arange(M), key_id, frame))
    sk, sf = key_id[order], frame[order]
    new_group = np.r_[True, (sk[1:] != sk[:-1]) | (sf[1:] != sf[:-1])]
    group_start = np.maximum.accumulate(np.where(new_group, np.arange(M), 0))
    rank = np.empty(M, np.int64)
    rank[order] = np.arange(M) - group_start
    return rank


# ---------------------------------------------------------------------- contact-spec files
_SPEC_KEYS = ("link", "kind", "position", "direction", "wrench", "normal", "friction",
              "cone_angle", "pushing", "start_ns", "end_ns")  # fmt: skip


@dataclass(frozen=True)
class ContactSpec:
    """Contacts read from a spec file: E entries, each a contact over an optional time range.

    Attributes:
        entries: the E entries as :class:`ContactRecords` (``frame`` = entry index).
        start_ns: ``(E,)`` int64, first time stamp each entry is in contact (inclusive), ns.
        end_ns: ``(E,)`` int64, last time stamp (inclusive), ns.
        source: where the spec came from (for messages).
    """

    entries: ContactRecords
    start_ns: np.ndarray
    end_ns: np.ndarray
    source: str = ""

    @property
    def timed(self) -> bool:
        """Whether any entry has a time range."""
        lo, hi = np.iinfo(np.int64).min, np.iinfo(np.int64).max
        return bool(((self.start_ns != lo) | (self.end_ns != hi)).any())

    def at(self, t_ns: np.ndarray) -> ContactRecords:
        """The records of frames stamped ``t_ns``: the entries whose range holds each stamp.

        Args:
            t_ns: ``(N,)`` int64 frame time stamps, ns.

        Returns:
            :class:`ContactRecords` ordered by frame, then entry.
        """
        t = np.asarray(t_ns, np.int64)[:, None]
        f, e = np.nonzero((t >= self.start_ns[None]) & (t <= self.end_ns[None]))
        return self.entries.select(e).with_frame(f)

    def static(self) -> ContactRecords:
        """Every entry in frame 0, for a fixed contact set (the live loop).

        Raises:
            InputError: an entry with a time range (only logs have time).
        """
        if self.timed:
            raise InputError(
                f"{self.source}: start_ns/end_ns apply to logs only; a live contact spec lists"
                " the contacts present all the time"
            )
        return self.entries.with_frame(np.zeros(len(self.entries), np.int64))


def _numbers(value: Any, n: int, where: str) -> list[float]:
    if (
        not isinstance(value, (list, tuple))
        or len(value) != n
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise InputError(f"{where} must be a list of {n} finite numbers, got {value!r}")
    return [float(v) for v in value]


def parse_contact_spec(data: Any, source: str = "contact spec") -> ContactSpec:
    """Validate a contact spec given as data (the parsed TOML/JSON of :func:`load_contact_spec`).

    Args:
        data: ``{"contact": [entry, ...]}`` or a list of entries; an entry is a mapping with
            ``link`` (str), ``position`` (3 numbers, m, link frame), optional ``kind`` (default
            ``"force"``), ``direction`` (3 numbers; ``force_dir`` only, required there),
            ``wrench`` (6 numbers ``[N; N m]``; ``known`` only, required there), ``normal`` (3
            numbers, outward surface normal in the link frame, nonzero), ``friction`` (> 0) or
            ``cone_angle`` (rad, in ``(0, pi/2)``), ``pushing`` (bool), ``start_ns`` and
            ``end_ns`` (int ns, inclusive range; default always).
        source: name used in messages.

    Returns:
        :class:`ContactSpec`.

    Raises:
        InputError: naming the entry and key: an unknown key, a missing link or position, an
            unknown kind, a vector of the wrong length or with non-finite values, a missing
            direction or wrench, a zero normal, a friction coefficient or cone angle out of
            range (or both given), a ``pushing`` that is not a boolean, or ``start_ns > end_ns``.

    Example:
        >>> spec = parse_contact_spec({"contact": [{"link": "hand", "position": [0, 0, 0.1]}]})
        >>> spec.entries.links.tolist(), spec.entries.kinds.tolist()
        (['hand'], ['force'])
    """
    items = data.get("contact", []) if isinstance(data, Mapping) else data
    if isinstance(data, Mapping) and set(data) - {"contact"}:
        raise InputError(
            f"{source}: unknown top-level keys {sorted(set(data) - {'contact'})}; write"
            ' [[contact]] tables (TOML) or {"contact": [...]} (JSON)'
        )
    if not isinstance(items, list):
        raise InputError(
            f"{source}: 'contact' must be a list of tables, got {type(items).__name__}"
        )
    links, kinds, pos, dirs, wrs, lo, hi = [], [], [], [], [], [], []
    cone: dict[str, list] = {n: [] for n in CONE_FIELDS}
    for i, c in enumerate(items):
        where = f"{source}: contact {i}"
        if not isinstance(c, Mapping):
            raise InputError(f"{where} must be a table with link and position")
        unknown = sorted(set(c) - set(_SPEC_KEYS))
        if unknown:
            raise InputError(f"{where}: unknown keys {unknown}; allowed {list(_SPEC_KEYS)}")
        for need in ("link", "position"):
            if need not in c:
                raise InputError(f"{where} needs {need!r}")
        if not isinstance(c["link"], str) or not c["link"]:
            raise InputError(f"{where}: link must be a name, got {c['link']!r}")
        kind = c.get("kind", "force")
        if kind not in KINDS:
            raise InputError(f"{where}: unknown kind {kind!r}; expected one of {list(KINDS)}")
        links.append(c["link"])
        kinds.append(kind)
        pos.append(_numbers(c["position"], 3, f"{where}: position"))
        for key, width, needed_by, out in (
            ("direction", 3, "force_dir", dirs),
            ("wrench", 6, "known", wrs),
        ):
            if c.get(key) is not None:
                out.append(_numbers(c[key], width, f"{where}: {key}"))
            elif kind == needed_by:
                raise InputError(f"{where}: a {needed_by} contact needs a {key}")
            else:
                out.append([math.nan] * width)
        _cone_entry(c, where, cone)
        for key, default, out in (
            ("start_ns", np.iinfo(np.int64).min, lo),
            ("end_ns", np.iinfo(np.int64).max, hi),
        ):
            v = c.get(key, default)
            if not isinstance(v, int) or isinstance(v, bool):
                raise InputError(f"{where}: {key} must be an integer (ns), got {v!r}")
            out.append(v)
        if lo[-1] > hi[-1]:
            raise InputError(f"{where}: start_ns {lo[-1]} is after end_ns {hi[-1]}")
    E = len(links)
    given = {n: v for n, v in cone.items() if any(not math.isnan(x) for x in np.ravel(v))}
    entries = ContactRecords(
        np.arange(E),
        links,
        kinds,
        np.asarray(pos, np.float64).reshape(E, 3),
        np.asarray(dirs, np.float64).reshape(E, 3) if "force_dir" in kinds else None,
        np.asarray(wrs, np.float64).reshape(E, 6) if "known" in kinds else None,
        **{n: np.asarray(v, np.float64).reshape(E, 3) if n == "normals" else
           np.asarray(v, np.float64) for n, v in given.items()},
    )  # fmt: skip
    return ContactSpec(entries, np.asarray(lo, np.int64), np.asarray(hi, np.int64), source)


def _cone_entry(c: Mapping[str, Any], where: str, out: dict[str, list]) -> None:
    """Validate an entry's friction-cone keys; append its values (NaN when absent) to ``out``."""
    normal = [math.nan] * 3
    if c.get("normal") is not None:
        normal = _numbers(c["normal"], 3, f"{where}: normal")
        if not any(normal):
            raise InputError(f"{where}: normal is zero; give the outward surface normal")
    out["normals"].append(normal)
    if c.get("friction") is not None and c.get("cone_angle") is not None:
        raise InputError(f"{where}: give friction or cone_angle, not both")
    for key in ("friction", "cone_angle"):
        v = c.get(key)
        if v is not None and not (
            isinstance(v, (int, float)) and not isinstance(v, bool) and _in_range(key, float(v))
        ):
            raise InputError(f"{where}: {key} must be {_RANGE[key]}, got {v!r}")
        out[key].append(math.nan if v is None else float(v))
    push = c.get("pushing")
    if push is not None and not isinstance(push, bool):
        raise InputError(f"{where}: pushing must be true or false, got {push!r}")
    out["pushing"].append(math.nan if push is None else float(push))


def load_contact_spec(path: str | Path) -> ContactSpec:
    """Read a contact-spec file: TOML (``.toml``) or JSON (any other suffix).

    TOML::

        [[contact]]
        link = "forearm_skin"
        kind = "force"               # wrench | force | force_dir | known (default force)
        position = [0.0, 0.0, 0.0]   # m, link frame
        direction = [0, 0, -1]       # force_dir only
        wrench = [0, 0, 0, 0, 0, 0]  # known only, [N; N m]
        normal = [0, 0, 1]           # optional: outward surface normal, link frame
        cone_angle = 0.5             # optional: rad (or friction = mu)
        pushing = true               # optional (default: every kind but known)
        start_ns = 0                 # optional time range (inclusive), logs only
        end_ns = 5_000_000_000

    JSON: ``{"contact": [{"link": "forearm_skin", "position": [0, 0, 0]}, ...]}``.

    Args:
        path: the file.

    Returns:
        :class:`ContactSpec` (see :func:`parse_contact_spec`).

    Raises:
        InputError: a missing or unreadable file, malformed TOML/JSON, or an invalid entry.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the contact spec ({exc.strerror or exc})") from None
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except ValueError as exc:
        kind = "TOML" if path.suffix.lower() == ".toml" else "JSON"
        raise InputError(f"{path}: not a valid {kind} contact spec ({exc})") from None
    return parse_contact_spec(data, str(path))


_RANGE = {"friction": "a finite number > 0", "cone_angle": "in (0, pi/2) rad"}


def _in_range(name: str, v: float) -> bool:
    if name == "friction":
        return 0 < v < math.inf
    return 0 < v < math.pi / 2
