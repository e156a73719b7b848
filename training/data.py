"""Frames for fitting corrections: simulated logs and Parquet logs, and contiguous time blocks."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import LogError
from torchcontact.model import RobotModel


@dataclass
class ResidualDataset:
    """Frames of one or more logs of one F/T sensor, joints in the robot's order (numpy).

    Attributes:
        t_ns: ``(N,)`` int64 time stamps, ns.
        q: ``(N, nv)`` rad or m, ``joint_names`` order (the robot's); ``qd``, ``qdd`` likewise.
        qd: ``(N, nv)`` per s.
        qdd: ``(N, nv)`` per s^2.
        ft: ``(N, 6)`` measured reading ``[N; N m]``.
        contact_free: ``(N,)`` bool, frames with no contact (the only fitting targets).
        extra: column name -> ``(N,)`` float64 extra columns (temperature, currents, ...).
        file_id: ``(N,)`` int64, which file each frame comes from (blocks never cross files).
        joint_names: the robot's joint names.
        sensor: sensor name.
        usable: ``(N,)`` bool, frames whose joint state, reading and extra columns are finite
            (the others are counted in reports and never used).
        truth: ground truth of simulated logs (``contact_link``, ``contact_position``,
            ``contact_force``, ``links``, ``ft_effects``), empty for recorded logs.
        sources: one description per file (path, frames, derived columns).
    """

    t_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    ft: np.ndarray
    contact_free: np.ndarray
    extra: dict[str, np.ndarray]
    file_id: np.ndarray
    joint_names: tuple[str, ...]
    sensor: str
    usable: np.ndarray | None = None
    truth: dict = field(default_factory=dict)
    sources: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.usable is None:
            ok = np.isfinite(self.ft).all(1)
            for x in (self.q, self.qd, self.qdd, *[v[:, None] for v in self.extra.values()]):
                ok &= np.isfinite(x).all(1)
            self.usable = ok

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def targets(self) -> np.ndarray:
        """``(N,)`` bool: contact-free and usable frames, the ones a correction is fitted on."""
        return self.contact_free & self.usable

    @classmethod
    def from_simulated(cls, log: Any, extra: Sequence[str] = ()) -> ResidualDataset:
        """From a :class:`torchcontact.simulation.SimulatedLog` (joints already in model order).

        Args:
            log: the simulated log.
            extra: extra columns: ``temperature``, ``time`` (s since start), or keys of
                ``log.extra``.
        """
        n = len(log.t_ns)
        cols = {}
        for name in extra:
            if name == "temperature":
                cols[name] = np.asarray(log.temperature, float)
            elif name == "time":
                cols[name] = (log.t_ns - log.t_ns[0]) * 1e-9
            else:
                cols[name] = np.asarray(log.extra[name], float)
        truth = {
            "contact_link": np.asarray(log.contact_link),
            "contact_position": np.asarray(log.contact_position),
            "contact_force": np.asarray(log.contact_force),
            "links": tuple(log.links),
        }
        if log.ft_effects is not None:
            truth["ft_effects"] = np.asarray(log.ft_effects)
        return cls(
            t_ns=np.asarray(log.t_ns, np.int64),
            q=np.asarray(log.q, float),
            qd=np.asarray(log.qd, float),
            qdd=np.asarray(log.qdd, float),
            ft=np.asarray(log.ft, float),
            contact_free=(np.asarray(log.contact_link) < 0).all(1),
            extra=cols,
            file_id=np.zeros(n, np.int64),
            joint_names=tuple(log.joint_names),
            sensor=log.sensor,
            truth=truth,
            sources=[{"source": "simulated", "frames": n}],
        )

    def subset(self, frames: slice) -> ResidualDataset:
        """The frames of a contiguous range, as a dataset of their own."""
        truth = {k: v if k == "links" else v[frames] for k, v in self.truth.items()}
        return ResidualDataset(
            t_ns=self.t_ns[frames],
            q=self.q[frames],
            qd=self.qd[frames],
            qdd=self.qdd[frames],
            ft=self.ft[frames],
            contact_free=self.contact_free[frames],
            extra={k: v[frames] for k, v in self.extra.items()},
            file_id=self.file_id[frames],
            joint_names=self.joint_names,
            sensor=self.sensor,
            usable=None if self.usable is None else self.usable[frames],
            truth=truth,
            sources=self.sources,
        )

    def sha256(self) -> str:
        """Hash of the data used (arrays and names), recorded in checkpoints."""
        h = hashlib.sha256()
        h.update(json.dumps([self.joint_names, self.sensor, sorted(self.extra)]).encode())
        for a in (self.t_ns, self.q, self.qd, self.qdd, self.ft, self.contact_free, self.file_id):
            h.update(np.ascontiguousarray(a).tobytes())
        for k in sorted(self.extra):
            h.update(np.ascontiguousarray(self.extra[k]).tobytes())
        return h.hexdigest()


def read_log_columns(
    path: str | Path, model: RobotModel, sensor: str, extra: Sequence[str]
) -> dict[str, Any]:
    """Read one log in the documented format, joints mapped by name to ``model``'s order.

    The one place training reads the log format (columns by name, joints by the schema metadata
    ``torchcontact.joint_names``, as ``torchcontact estimate`` does); built on
    :mod:`torchcontact.logs.format`.

    Args:
        path: a Parquet log.
        model: the robot; the log must name exactly its joints, in any order.
        sensor: the ``ft.<sensor>`` column to read.
        extra: extra columns (``time`` is derived: s since the file's start).

    Returns:
        ``t_ns``, ``q``, ``qd``, ``qdd`` (model order; ``qd``/``qdd`` derived from ``q`` with the
        pipeline's Savitzky-Golay differentiator when absent), ``ft``, ``contact_free`` (an empty
        ``contacts`` list; all frames when the log has no ``contacts`` column), ``extra``,
        ``derived`` (names of derived columns), ``bad`` (frames with malformed or non-finite
        vectors: the format's reader gives wrong-length and null rows as NaN).

    Raises:
        LogError: not Parquet, no joint names, joints missing or not the robot's, no such
            sensor column, a missing extra column; the message names the file and what is wrong.
    """
    from torchcontact.logs.derive import savgol_derivatives
    from torchcontact.logs.format import (
        ft_column,
        joint_names_of,
        joint_permutation,
        open_log,
        read_log_columns,
    )

    # as torchcontact estimate: the log names exactly the robot's joints, in any order
    joint_permutation(joint_names_of(open_log(path).schema_arrow, path), model.joint_names,
                      model.name, path)  # fmt: skip
    schema_names = open_log(path).schema_arrow.names
    col = ft_column(sensor)
    derived = [c for c in ("qd", "qdd") if c not in schema_names]
    need = ["t_ns", "q", *(c for c in ("qd", "qdd") if c not in derived), col]
    need += [e for e in extra if e != "time"]
    has_contacts = "contacts" in schema_names
    if has_contacts:
        need.append("contacts")
    # the log format's one reader: page checksums verified, joints in the model's order
    cols = read_log_columns(path, need, joint_names=model.joint_names)
    t = cols["t_ns"]
    q = cols["q"]
    if derived:
        qd_d, qdd_d = savgol_derivatives(t, q)
    qd = qd_d if "qd" in derived else cols["qd"]
    qdd = qdd_d if "qdd" in derived else cols["qdd"]
    ft = cols[col]
    bad = ~(np.isfinite(q).all(1) & np.isfinite(qd).all(1) & np.isfinite(qdd).all(1))
    bad |= ~np.isfinite(ft).all(1)
    if has_contacts:
        free = np.bincount(cols["contacts"].frame, minlength=len(t)) == 0
    else:
        free = np.ones(len(t), bool)
    ex = {}
    for e in extra:
        if e == "time":
            ex[e] = (t - t[0]) * 1e-9 if len(t) else np.zeros(0)
        else:
            v = np.asarray(cols[e], float)
            if v.ndim != 1:
                raise LogError(f"{path}: column {e!r} is not a numeric column")
            ex[e] = v
    return {
        "t_ns": t,
        "q": q,
        "qd": qd,
        "qdd": qdd,
        "ft": ft,
        "contact_free": free,
        "extra": ex,
        "derived": derived,
        "bad": bad,
        "has_contacts": has_contacts,
    }


def load_parquet(
    paths: Sequence[str | Path],
    model: RobotModel,
    sensor: str,
    extra: Sequence[str] = (),
) -> ResidualDataset:
    """Load logs in the documented Parquet format (docs/format.md).

    Joints are matched by name to ``model``'s order (:func:`read_log_columns`); missing
    ``qd``/``qdd`` are derived; frames with malformed or non-finite values are kept but marked
    unusable (reports count them). A log without a ``contacts`` column counts as contact-free.

    Args:
        paths: one or more files; each becomes its own ``file_id``.
        model: the robot.
        sensor: which ``ft.<sensor>`` column to use; a sensor of ``model``.
        extra: extra columns to read (``time``: s since each file's start).

    Raises:
        LogError: no files, or a file that cannot be used (the message names it and why).
    """
    if sensor not in model.ft_sensors:
        raise LogError(f"{model.name} has no F/T sensor {sensor!r} ({list(model.ft_sensors)})")
    if not paths:
        raise LogError("no Parquet files given")
    parts = []
    sources = []
    for i, p in enumerate(paths):
        cols = read_log_columns(p, model, sensor, extra)
        cols["file_id"] = np.full(len(cols["t_ns"]), i, np.int64)
        parts.append(cols)
        sources.append(
            {
                "path": str(Path(p).resolve()),
                "frames": len(cols["t_ns"]),
                "derived": cols["derived"],
                "malformed_frames": int(cols["bad"].sum()),
                "contacts_column": cols["has_contacts"],
            }
        )
    keys = ("t_ns", "q", "qd", "qdd", "ft", "contact_free", "file_id")
    cat = {k: np.concatenate([d[k] for d in parts]) for k in keys}
    ex = {e: np.concatenate([d["extra"][e] for d in parts]) for e in extra}
    return ResidualDataset(
        **cat, extra=ex, joint_names=tuple(model.joint_names), sensor=sensor, sources=sources
    )


@dataclass(frozen=True)
class Split:
    """Frame indices of each split and the contiguous blocks ``(start, stop)`` they came from."""

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    blocks: dict[str, list[tuple[int, int]]]


def time_blocks(file_id: np.ndarray, block_frames: int) -> list[tuple[int, int]]:
    """Cut each file into blocks of ``block_frames`` consecutive frames (never across files).

    Raises:
        ValueError: the frames of a file are not consecutive, or ``block_frames < 1``.

    Example:
        >>> time_blocks(np.array([0, 0, 0, 1, 1]), 2)
        [(0, 2), (2, 3), (3, 5)]
    """
    if block_frames < 1:
        raise ValueError(f"block_frames must be >= 1, got {block_frames}")
    file_id = np.asarray(file_id)
    n = len(file_id)
    starts = np.flatnonzero(np.r_[True, file_id[1:] != file_id[:-1]]) if n else np.zeros(0, int)
    stops = np.r_[starts[1:], n]
    if len(np.unique(file_id)) != len(starts):
        raise ValueError("frames of each file must be consecutive")
    return [
        (int(s), int(min(s + block_frames, e)))
        for s0, e in zip(starts, stops, strict=True)
        for s in range(s0, e, block_frames)
    ]


def _indices(blocks: Sequence[tuple[int, int]]) -> np.ndarray:
    if not blocks:
        return np.zeros(0, np.int64)
    return np.concatenate([np.arange(s, e) for s, e in blocks])


def split_blocks(
    file_id: np.ndarray,
    block_frames: int,
    fractions: tuple[float, float, float] = (0.6, 0.2, 0.2),
    seed: int = 0,
) -> Split:
    """Split frames by contiguous time blocks, never by random frames.

    Blocks (:func:`time_blocks`) are shuffled with ``seed`` and dealt to train/validation/test
    in the given proportions (at least one block each when there are three or more blocks; a
    zero fraction gives none).

    Args:
        file_id: ``(N,)`` file of each frame; frames of a file must be consecutive.
        block_frames: frames per block.
        fractions: train, validation, test shares.
        seed: shuffle seed.

    Returns:
        :class:`Split` with sorted index arrays.

    Example:
        >>> s = split_blocks(np.zeros(100, int), 10)
        >>> len(s.train) + len(s.val) + len(s.test)
        100
    """
    blocks = time_blocks(file_id, block_frames)
    order = np.random.default_rng(seed).permutation(len(blocks))
    nb = len(blocks)

    def count(frac: float) -> int:
        return 0 if frac <= 0 or nb < 3 else max(1, round(frac * nb))

    n_test, n_val = count(fractions[2]), count(fractions[1])
    groups = {
        "test": order[:n_test],
        "val": order[n_test : n_test + n_val],
        "train": order[n_test + n_val :],
    }
    bl = {name: sorted(blocks[i] for i in ids) for name, ids in groups.items()}
    idx = {name: _indices(b) for name, b in bl.items()}
    return Split(idx["train"], idx["val"], idx["test"], bl)


def fold_splits(
    file_id: np.ndarray, block_frames: int, folds: int, val_fraction: float = 0.2, seed: int = 0
) -> list[Split]:
    """K-fold cross-validation over contiguous time blocks: every block is tested exactly once.

    Blocks are shuffled with ``seed`` and dealt round-robin to ``folds`` groups. Fold ``k``
    tests on group ``k``; of the other blocks, ``val_fraction`` (at least one) validate (early
    stopping, layer choice) and the rest train.

    Args:
        file_id: ``(N,)`` file of each frame.
        block_frames: frames per block.
        folds: number of folds (>= 2, at most the number of blocks).
        val_fraction: share of the non-test blocks used for validation.
        seed: shuffle seed.

    Returns:
        One :class:`Split` per fold; their ``test`` indices partition all frames.

    Raises:
        ValueError: fewer than ``folds + 1`` blocks (each fold needs a test, a validation and a
            training block).

    Example:
        >>> fs = fold_splits(np.zeros(100, int), 10, folds=5)
        >>> sorted(np.concatenate([f.test for f in fs]).tolist()) == list(range(100))
        True
    """
    blocks = time_blocks(file_id, block_frames)
    if folds < 2 or len(blocks) < folds + 2:
        raise ValueError(
            f"{len(blocks)} blocks of {block_frames} frames cannot make {folds} folds (each fold"
            " needs test, validation and training blocks): use shorter blocks or fewer folds"
        )
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(blocks))
    groups = [order[k::folds] for k in range(folds)]
    out = []
    for k in range(folds):
        rest = np.concatenate([g for j, g in enumerate(groups) if j != k])
        rest = rng.permutation(rest)
        n_val = max(1, round(val_fraction * len(rest)))
        bl = {
            "test": sorted(blocks[i] for i in groups[k]),
            "val": sorted(blocks[i] for i in rest[:n_val]),
            "train": sorted(blocks[i] for i in rest[n_val:]),
        }
        idx = {name: _indices(b) for name, b in bl.items()}
        out.append(Split(idx["train"], idx["val"], idx["test"], bl))
    return out
