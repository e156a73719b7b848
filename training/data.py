"""In-memory residual datasets, loaders (simulated logs, Parquet) and time-block splits."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchcontact.residual import feature_names


@dataclass
class ResidualDataset:
    """Frames of one or more logs of one F/T sensor, as numpy arrays (one row per frame).

    Attributes:
        t_ns: ``(N,)`` int64 time stamps, ns.
        q: ``(N, nv)`` rad; ``qd``, ``qdd`` likewise.
        qd: ``(N, nv)`` rad/s.
        qdd: ``(N, nv)`` rad/s^2.
        ft: ``(N, 6)`` measured reading ``[N; N m]``.
        contact_free: ``(N,)`` bool, frames with no contact (training targets).
        extra: column name -> ``(N,)`` float64 extra features (temperature, currents, ...).
        file_id: ``(N,)`` int64, which file/log each frame comes from (blocks never cross files).
        joint_names: order of the joint columns.
        sensor: sensor name.
        truth: optional ground truth of simulated logs (``contact_link``, ``contact_position``,
            ``contact_force``, ``links``).
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
    truth: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t_ns)

    @classmethod
    def from_simulated(cls, log, extra: Sequence[str] = ()) -> ResidualDataset:
        """From a :class:`torchcontact.simulation.SimulatedLog`.

        Args:
            log: the simulated log.
            extra: extra feature columns: ``temperature``, ``time`` (s since start), or keys
                of ``log.extra``.
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
            truth={
                "contact_link": np.asarray(log.contact_link),
                "contact_position": np.asarray(log.contact_position),
                "contact_force": np.asarray(log.contact_force),
                "links": tuple(log.links),
            },
        )

    def feature_names(self) -> list[str]:
        """``q.<joint>``, ``qd.<joint>``, ``qdd.<joint>``, then the extra columns."""
        return feature_names(self.joint_names, list(self.extra))

    def features(self, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """``(n, F)`` float64 features of the selected frames, in :meth:`feature_names` order."""
        parts = [self.q[idx], self.qd[idx], self.qdd[idx]]
        parts += [self.extra[k][idx][:, None] for k in self.extra]
        return np.concatenate(parts, 1)

    def sha256(self) -> str:
        """Hash of the data used (arrays and names), recorded in checkpoints."""
        h = hashlib.sha256()
        h.update(json.dumps([self.joint_names, self.sensor, sorted(self.extra)]).encode())
        for a in (self.t_ns, self.q, self.qd, self.qdd, self.ft, self.contact_free, self.file_id):
            h.update(np.ascontiguousarray(a).tobytes())
        for k in sorted(self.extra):
            h.update(np.ascontiguousarray(self.extra[k]).tobytes())
        return h.hexdigest()


def load_parquet(
    paths: Sequence[str | Path],
    sensor: str,
    extra: Sequence[str] = (),
    contact_free_mask: Sequence[np.ndarray] | None = None,
) -> ResidualDataset:
    """Load logs in the torchcontact Parquet format.

    Columns: ``t_ns`` int64, ``q``/``qd``/``qdd`` fixed-size lists (nv), ``ft.<sensor>`` 6 floats,
    ``contacts`` a list of structs per frame (empty list = contact-free), extra columns (e.g.
    ``temperature``); joint names in the schema metadata ``torchcontact.joint_names`` (JSON).

    Args:
        paths: one or more files; each becomes its own ``file_id``.
        sensor: which ``ft.<sensor>`` column to use.
        extra: extra feature columns to read (``time`` is derived: s since each file's start).
        contact_free_mask: per file, a user ``(N,)`` bool mask overriding ``contacts``.

    Raises:
        ValueError: missing columns, or files with different joint names.
    """
    from torchcontact.logs.format import ft_column, joint_names_of, open_log, read_log_columns

    parts: list[dict] = []
    joint_names = None
    for i, p in enumerate(paths):
        # the log format's reader: page checksums verified, joint columns matched by name
        names = tuple(joint_names_of(open_log(p).schema_arrow, p))
        if joint_names is not None and names != joint_names:
            raise ValueError(f"{p}: joint names {names} differ from the first file's")
        joint_names = names
        col = ft_column(sensor)
        need = ["t_ns", "q", "qd", "qdd", col] + [e for e in extra if e != "time"]
        if contact_free_mask is None:
            need.append("contacts")
        cols = read_log_columns(p, need, joint_names=names)
        t = cols["t_ns"]
        if contact_free_mask is None:
            free = np.bincount(cols["contacts"].frame, minlength=len(t)) == 0
        else:
            free = np.asarray(contact_free_mask[i], bool)
        ex = {e: (t - t[0]) * 1e-9 if e == "time" else cols[e] for e in extra}
        parts.append(
            {
                "t_ns": t,
                "q": cols["q"],
                "qd": cols["qd"],
                "qdd": cols["qdd"],
                "ft": cols[col],
                "contact_free": free,
                "extra": ex,
                "file_id": np.full(len(t), i, np.int64),
            }
        )
    if not parts:
        raise ValueError("no Parquet files given")
    cat = {k: np.concatenate([d[k] for d in parts]) for k in parts[0] if k != "extra"}
    ex = {e: np.concatenate([d["extra"][e] for d in parts]) for e in extra}
    return ResidualDataset(**cat, extra=ex, joint_names=joint_names, sensor=sensor)


@dataclass(frozen=True)
class Split:
    """Frame indices of each split and the contiguous blocks ``(start, stop)`` they came from."""

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    blocks: dict[str, list[tuple[int, int]]]


def split_blocks(
    file_id: np.ndarray,
    block_frames: int,
    fractions: tuple[float, float, float] = (0.6, 0.2, 0.2),
    seed: int = 0,
) -> Split:
    """Split frames by contiguous time blocks, never by random frames.

    Each file is cut into blocks of ``block_frames`` consecutive frames (a block never crosses
    files); blocks are shuffled with ``seed`` and dealt to train/val/test in the given
    proportions (at least one block each when there are three or more blocks).

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
    file_id = np.asarray(file_id)
    n = len(file_id)
    starts = np.flatnonzero(np.r_[True, file_id[1:] != file_id[:-1]])
    stops = np.r_[starts[1:], n]
    if len(np.unique(file_id)) != len(starts):
        raise ValueError("frames of each file must be consecutive")
    blocks = [
        (s, min(s + block_frames, e))
        for s0, e in zip(starts, stops, strict=True)
        for s in range(s0, e, block_frames)
    ]
    order = np.random.default_rng(seed).permutation(len(blocks))
    nb = len(blocks)
    n_test = max(1, round(fractions[2] * nb)) if nb >= 3 else 0
    n_val = max(1, round(fractions[1] * nb)) if nb >= 3 else 0
    groups = {
        "test": order[:n_test],
        "val": order[n_test : n_test + n_val],
        "train": order[n_test + n_val :],
    }
    out, bl = {}, {}
    for name, ids in groups.items():
        chosen = sorted(blocks[i] for i in ids)
        bl[name] = chosen
        out[name] = (
            np.concatenate([np.arange(s, e) for s, e in chosen]) if chosen else np.zeros(0, int)
        )
    return Split(out["train"], out["val"], out["test"], bl)
