"""Estimate the contacts of every frame of a Parquet log, streamed in chunks.

:class:`LogEstimator` turns one chunk (a pyarrow table in the log format of
:mod:`torchcontact.logs.format`) into output rows; it is shared by the local engine
(:func:`estimate_file`) and the Ray engine (:mod:`torchcontact.logs.ray_engine`).

Crash safety of :func:`estimate_file`: chunk ``k`` is written to ``OUT.partial/part-<k>.parquet``
(through a temporary name and an atomic rename) and ``OUT.progress.json`` records the chunk
count. Only when every chunk is done are the parts merged into ``OUT.tmp`` and renamed to ``OUT``,
so an interrupted run never leaves a file named ``OUT``. ``resume=True`` keeps the parts already
written and processes the rest with the same chunk size, so no frame is missing or duplicated.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.contacts import KINDS, Contacts
from torchcontact.errors import LogError  # noqa: F401  (re-exported)
from torchcontact.estimation import ContactEstimator
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW, savgol_derivatives
from torchcontact.logs.format import (
    BASE_COLUMNS,
    META_DERIVED,
    META_JOINT_NAMES,
    META_RESIDUAL,
    META_SENSORS,
    META_URDF_SHA256,
    META_VERSION,
    fixed_list,
    ft_column,
    joint_names_of,
    vectors,
)
from torchcontact.model import RobotModel
from torchcontact.status import status_messages

__all__ = ["LogError", "LogEstimator", "estimate_file", "estimate_files", "expand_inputs"]


def open_parquet(path: str | Path) -> Any:
    """Open a Parquet file, raising :class:`LogError` naming the file when it is not one."""
    import pyarrow.parquet as pq

    try:
        return pq.ParquetFile(path)
    except Exception as exc:  # pyarrow raises ArrowInvalid, OSError, ...
        raise LogError(f"{path}: not a readable Parquet file ({exc})") from None


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


@dataclass
class LogEstimator:
    """Per-chunk estimation for one robot and one input schema.

    Args:
        model: the robot (its dtype and device are those of the computation).
        input_joint_names: joint order of the log's ``q`` columns.
        sensors: F/T sensors to use (each needs an ``ft.<sensor>`` column).
        contact_fields: ``(name, type)`` fields of the input contact struct (output adds
            ``force`` and ``moment``); empty when the log has no ``contacts`` column.
        source: file name used in error messages.
        derived: ``qd``/``qdd`` when derived from ``q`` (recorded in the output metadata).
        residual: learned F/T correction (:class:`~torchcontact.residual.ResidualCorrection`)
            subtracted from its sensor's reading before estimation, or None.

    Raises:
        LogError: joints missing from or extra to the model (mimic joints are not coordinates),
            an unknown sensor, or a residual for a sensor or joints not in use.
    """

    model: RobotModel
    input_joint_names: Sequence[str]
    sensors: Sequence[str]
    contact_fields: Sequence[tuple[str, Any]] = ()
    source: str = ""
    derived: Sequence[str] = ()
    residual: Any = None
    estimator: ContactEstimator = field(init=False)
    perm: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        names = list(self.input_joint_names)
        model_names = list(self.model.joint_names)
        missing = [n for n in model_names if n not in names]
        extra = [n for n in names if n not in model_names]
        if missing or extra:
            msg = f"{self.source}: joint names of the log do not match {self.model.name}:"
            if missing:
                msg += f" missing {missing}"
            if extra:
                msg += f" extra {extra} (mimic and fixed joints are not coordinates)"
            raise LogError(msg)
        if len(set(names)) != len(names):
            raise LogError(f"{self.source}: duplicate joint names {names}")
        self.perm = np.array([names.index(n) for n in model_names], dtype=np.int64)
        try:
            self.estimator = ContactEstimator(self.model, list(self.sensors))
        except ValueError as exc:
            raise LogError(f"{self.source}: {exc}") from None
        # contact links the estimator can use: known frames inside some sensor's region
        self._link_ok: dict[str, str | None] = {}
        if self.residual is not None and self.residual.sensor not in self.sensors:
            raise LogError(
                f"{self.source}: the residual checkpoint corrects sensor"
                f" {self.residual.sensor!r}, which is not among the sensors in use"
                f" {list(self.sensors)}"
            )

    def residual_columns(self) -> list[str]:
        """Log columns the residual model reads besides ``q``/``qd``/``qdd`` (e.g. temperature)."""
        return [] if self.residual is None else self.residual.extra_columns

    # ------------------------------------------------------------------ schema
    def output_schema(self, base_metadata: dict | None = None) -> Any:
        """Schema of the output rows, with joint names, robot hash and version in the metadata."""
        import pyarrow as pa

        from torchcontact import __version__

        nv = self.model.nv
        contact = pa.struct(
            [
                *[pa.field(n, t) for n, t in self.contact_fields],
                pa.field("force", pa.list_(pa.float64(), 3)),
                pa.field("moment", pa.list_(pa.float64(), 3)),
            ]
        )
        fields = [("t_ns", pa.int64()), ("contacts", pa.list_(contact))]
        fields.append(("joint_torques", pa.list_(pa.float64(), nv)))
        for s in self.sensors:
            fields += [(f"rank.{s}", pa.int64()), (f"unknowns.{s}", pa.int64())]
            fields.append((f"residual.{s}", pa.float64()))
        fields.append(("status", pa.string()))
        meta = {
            META_JOINT_NAMES: json.dumps(list(self.model.joint_names)),
            META_URDF_SHA256: self.model.urdf_sha256,
            META_VERSION: __version__,
            META_SENSORS: json.dumps(list(self.sensors)),
            META_DERIVED: json.dumps(
                {
                    "columns": list(self.derived),
                    "method": f"Savitzky-Golay order 2 over t_ns, {2 * DEFAULT_HALF_WINDOW + 1}"
                    " frames"
                    if self.derived
                    else "",
                }
            ),
        }
        if self.residual is not None:
            meta[META_RESIDUAL] = json.dumps(
                {
                    "checkpoint": self.residual.source,
                    "weights_sha256": self.residual.meta.get("weights_sha256"),
                    "sensor": self.residual.sensor,
                    "kind": "+".join(self.residual.layers),
                }
            )
        return pa.schema(fields, metadata=meta)

    # ------------------------------------------------------------------ helpers
    def _link_problem(self, link: str | None) -> str | None:
        if link not in self._link_ok:
            model, est = self.model, self.estimator
            if link is None:
                msg: str | None = "contact without a link"
            elif link not in model.frames:
                msg = f"unknown link {link!r}"
            elif est.region[model.frame(link).body] < 0:
                msg = f"link {link!r} is outside every F/T sensor's subtree"
            else:
                msg = None
            self._link_ok[link] = msg  # type: ignore[index]
        return self._link_ok[link]  # type: ignore[index]

    def _joint_vectors(self, table: Any, name: str, reasons: list) -> np.ndarray:
        vals, bad = vectors(table.column(name), len(self.perm))
        if bad.any():
            reasons.append((bad, f"{name} is not {len(self.perm)} floats"))
        return vals[:, self.perm]

    # ------------------------------------------------------------------ one chunk
    def process(
        self, table: Any, qd: np.ndarray | None = None, qdd: np.ndarray | None = None
    ) -> Any:
        """Estimate every frame of a chunk.

        Args:
            table: pyarrow table or record batch in the log format.
            qd: ``(N, nv)`` velocities in the model's joint order when derived (else read).
            qdd: ``(N, nv)`` accelerations likewise.

        Returns:
            A pyarrow table with :meth:`output_schema`.
        """
        import pyarrow as pa
        import pyarrow.compute as pc

        if isinstance(table, pa.RecordBatch):
            table = pa.Table.from_batches([table])
        model, est = self.model, self.estimator
        N, nv = table.num_rows, model.nv
        reasons: list[tuple[np.ndarray, str]] = []  # (frame mask, reason) in priority order
        q = self._joint_vectors(table, "q", reasons)
        qd = self._joint_vectors(table, "qd", reasons) if qd is None else qd
        qdd = self._joint_vectors(table, "qdd", reasons) if qdd is None else qdd
        ft = {}
        for s in self.sensors:
            vals, bad = vectors(table.column(ft_column(s)), 6)
            if bad.any():
                reasons.append((bad, f"{ft_column(s)} is not 6 floats"))
            ft[s] = vals
        if self.residual is not None:
            ft[self.residual.sensor] = self._corrected(table, ft[self.residual.sensor], q, qd, qdd)
        tau = None
        if "tau_measured" in table.column_names:
            tau_raw, bad = vectors(table.column("tau_measured"), nv)
            tau = tau_raw[:, self.perm]
            if bad.any():
                reasons.append((bad, f"tau_measured is not {nv} floats"))
                tau[bad] = np.nan
        base = {}
        for col, key in BASE_COLUMNS.items():
            if col in table.column_names:
                base[key], bad = vectors(table.column(col), 3)
                if bad.any():
                    reasons.append((bad, f"{col} is not 3 floats"))
        if base and len(base) != 3:
            raise LogError(f"{self.source}: need all of {list(BASE_COLUMNS)} or none")

        # ---- contacts: flatten the list<struct>, validate, assign slots per chunk
        has_contacts = "contacts" in table.column_names
        if has_contacts:
            lst = table.column("contacts").combine_chunks()
            lst = pc.if_else(lst.is_null(), pa.scalar([], lst.type), lst)
            structs = lst.flatten()
            parent = np.asarray(pc.list_parent_indices(lst).to_numpy(zero_copy_only=False))
            cols = dict(zip([f.name for f in structs.type], structs.flatten(), strict=True))
        else:
            lst, structs, parent, cols = None, None, np.zeros(0, np.int64), {}
        M = len(parent)
        bad_contact = np.zeros(M, bool)
        contact_reason = np.full(M, None, dtype=object)
        links = cols["link"].to_pylist() if M else []
        kinds = cols["kind"].to_pylist() if M else []
        for i, (link, kind) in enumerate(zip(links, kinds, strict=True)):
            msg = self._link_problem(link)
            if msg is None and kind not in KINDS:
                msg = f"unknown contact kind {kind!r}"
            if msg is not None:
                bad_contact[i], contact_reason[i] = True, msg
        pos, bad = vectors(cols["position"], 3) if M else (np.zeros((0, 3)), np.zeros(0, bool))
        for arr, msg in ((bad, "contact position is not 3 floats"),):
            contact_reason[arr & ~bad_contact] = msg
            bad_contact |= arr
        kinds_arr = np.array(kinds, dtype=object)
        vecs: dict[str, np.ndarray | None] = {"direction": None, "wrench": None}
        # a field is required only by the kind that uses it: force_dir needs a direction,
        # known needs a wrench
        for col, kind, width in (("direction", "force_dir", 3), ("wrench", "known", 6)):
            if not M:
                continue
            if col in cols:
                vecs[col], bad = vectors(cols[col], width)
                need = (kinds_arr == kind) & bad & ~bad_contact
                contact_reason[need] = f"{kind} contact without a {width}-float {col}"
            else:
                need = (kinds_arr == kind) & ~bad_contact
                contact_reason[need] = f"{kind} contact without a {col}"
            bad_contact |= need
        dirs, wr = vecs["direction"], vecs["wrench"]
        frame_contact_bad = np.zeros(N, bool)
        if bad_contact.any():
            for msg in dict.fromkeys(contact_reason[bad_contact]):
                rows = np.zeros(N, bool)
                rows[parent[bad_contact & (contact_reason == msg)]] = True
                reasons.append((rows, msg))
            frame_contact_bad[parent[bad_contact]] = True

        # slot layout: union over frames of (link, kind) with the max multiplicity per frame
        good = np.flatnonzero(~bad_contact)
        slot_of = np.full(M, -1, np.int64)
        slot_links: list[str] = []
        slot_kinds: list[str] = []
        if len(good):
            keys = [(links[i], kinds[i]) for i in good]
            uniq = sorted(set(keys))
            key_id = np.array([uniq.index(k) for k in keys]) if len(uniq) < 8 else None
            if key_id is None:
                lookup = {k: j for j, k in enumerate(uniq)}
                key_id = np.array([lookup[k] for k in keys])
            fr = parent[good]
            order = np.lexsort((np.arange(len(good)), key_id, fr))
            sk, sf = key_id[order], fr[order]
            new_group = np.r_[True, (sk[1:] != sk[:-1]) | (sf[1:] != sf[:-1])]
            group_start = np.maximum.accumulate(np.where(new_group, np.arange(len(order)), 0))
            rank = np.empty(len(order), np.int64)
            rank[order] = np.arange(len(order)) - group_start
            mult = np.zeros(len(uniq), np.int64)
            np.maximum.at(mult, key_id, rank + 1)
            offset = np.r_[0, np.cumsum(mult)[:-1]]
            slot_of[good] = offset[key_id] + rank
            for j, (link, kind) in enumerate(uniq):
                slot_links += [link] * int(mult[j])
                slot_kinds += [kind] * int(mult[j])
        K = len(slot_links)
        P = np.zeros((N, K, 3))
        D = np.zeros((N, K, 3))
        D[..., 2] = 1.0  # inactive force_dir slots: any nonzero direction
        Wk = np.zeros((N, K, 6))
        A = np.zeros((N, K), bool)
        if len(good):
            f, k = parent[good], slot_of[good]
            P[f, k] = pos[good]
            A[f, k] = True
            if dirs is not None:
                fd = good[kinds_arr[good] == "force_dir"]
                D[parent[fd], slot_of[fd]] = dirs[fd]
            if wr is not None:
                kn = good[kinds_arr[good] == "known"]
                Wk[parent[kn], slot_of[kn]] = wr[kn]
        A[frame_contact_bad] = False

        # ---- estimate (Del Prete et al. 2012, Sec. 2) on the model's device and dtype
        def t(x: np.ndarray) -> torch.Tensor:
            return torch.tensor(x, dtype=model.dtype, device=model.device)  # copy: arrow is r/o

        contacts = Contacts(
            tuple(slot_links),
            tuple(slot_kinds),
            t(P),
            directions=t(D) if "force_dir" in slot_kinds else None,
            wrenches=t(Wk) if "known" in slot_kinds else None,
            active=torch.as_tensor(A, device=model.device),
        )
        res = est.estimate(
            t(q),
            t(qd),
            t(qdd),
            {s: t(v) for s, v in ft.items()},
            contacts,
            base=None if not base else _base_motion(base, t),
            tau_measured=None if tau is None else t(tau),
        )
        code = res.status.cpu().numpy()
        status = np.full(N, "ok", dtype=object)
        for c in np.unique(code[code != 0]):
            status[code == c] = status_messages(int(c))
        # pipeline reasons take priority (they explain the NaNs the estimator saw)
        pipeline_bad = np.zeros(N, bool)
        for rows, msg in reversed(reasons):
            status[rows] = msg
            pipeline_bad |= rows
        force = res.force.detach().cpu().numpy()
        moment = res.moment.detach().cpu().numpy()
        jt = res.joint_torques.detach().cpu().numpy().copy()
        jt[pipeline_bad] = np.nan

        # ---- output rows: input contacts with force and moment added
        out: dict[str, Any] = {"t_ns": table.column("t_ns").combine_chunks().cast(pa.int64())}
        schema = self.output_schema()
        cf = np.full((M, 3), np.nan)
        cm = np.full((M, 3), np.nan)
        ok_c = (slot_of >= 0) & ~pipeline_bad[parent] if M else np.zeros(0, bool)
        if ok_c.any():
            cf[ok_c] = force[parent[ok_c], slot_of[ok_c]]
            cm[ok_c] = moment[parent[ok_c], slot_of[ok_c]]
        ctype = schema.field("contacts").type.value_type
        if has_contacts:
            children = [cols[n].cast(ctype.field(n).type) for n, _ in self.contact_fields]
        else:
            children = []
        children += [fixed_list(cf), fixed_list(cm)]
        struct = pa.StructArray.from_arrays(children, fields=list(ctype))
        offsets = np.r_[0, np.cumsum(np.bincount(parent, minlength=N))].astype(np.int32)
        out["contacts"] = pa.ListArray.from_arrays(pa.array(offsets), struct).cast(
            schema.field("contacts").type
        )
        out["joint_torques"] = fixed_list(jt)
        for s in self.sensors:
            rk = res.rank[s].cpu().numpy().astype(np.int64)
            un = res.unknowns[s].cpu().numpy().astype(np.int64)
            rs = res.residual[s].detach().cpu().numpy().astype(np.float64).copy()
            rs[pipeline_bad] = np.nan
            out[f"rank.{s}"] = pa.array(rk)
            out[f"unknowns.{s}"] = pa.array(un)
            out[f"residual.{s}"] = pa.array(rs)
        out["status"] = pa.array(status.tolist(), pa.string())
        return pa.table(out, schema=schema)

    def _corrected(
        self, table: Any, ft: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
    ) -> np.ndarray:
        """``ft (N, 6) - correction`` [N; N m]; joints ``(N, nv)`` in the model's order."""
        extra = {
            c: np.array(table.column(c).to_numpy(zero_copy_only=False), dtype=np.float64)
            for c in self.residual_columns()
        }
        joints = (torch.as_tensor(v) for v in (q, qd, qdd))
        return self.residual.correct(torch.tensor(ft), *joints, extra).cpu().numpy()


def _base_motion(base: dict, t: Any) -> Any:
    from torchcontact.dynamics import BaseMotion

    return BaseMotion(t(base["omega"]), t(base["domega"]), t(base["proper_acc"]))


# ---------------------------------------------------------------------- streaming
def _rebatch(pf: Any, columns: list[str], batch_size: int) -> Iterator[Any]:
    """Tables of exactly ``batch_size`` rows (the last one shorter), whatever the row groups."""
    import pyarrow as pa

    buf: list[Any] = []
    have = 0
    for rb in pf.iter_batches(batch_size=batch_size, columns=columns):
        buf.append(rb)
        have += rb.num_rows
        while have >= batch_size:
            tab = pa.Table.from_batches(buf).combine_chunks()
            yield tab.slice(0, batch_size)
            rest = tab.slice(batch_size)
            buf, have = rest.to_batches(), rest.num_rows
    if have:
        yield pa.Table.from_batches(buf).combine_chunks()


def _chunks_with_derivatives(
    chunks: Iterator[Any], perm: np.ndarray, derive: bool, h: int
) -> Iterator[tuple[Any, np.ndarray | None, np.ndarray | None]]:
    """Yield ``(chunk, qd, qdd)``; derivatives from ``q`` with ``h`` frames of context each side."""
    if not derive:
        for c in chunks:
            yield c, None, None
        return
    import pyarrow as pa

    def tq(c: Any) -> tuple[np.ndarray, np.ndarray]:
        q, _ = vectors(c.column("q"), len(perm))
        return c.column("t_ns").to_numpy().astype(np.int64), q[:, perm]

    prev_t = np.zeros(0, np.int64)
    prev_q = np.zeros((0, len(perm)))
    cur = next(chunks, None)
    while cur is not None:
        nxt = next(chunks, None)
        t_c, q_c = tq(cur)
        if nxt is not None:
            t_n, q_n = tq(nxt.slice(0, h) if isinstance(nxt, pa.Table) else nxt)
        else:
            t_n, q_n = np.zeros(0, np.int64), np.zeros((0, len(perm)))
        t_all = np.concatenate([prev_t, t_c, t_n[:h]])
        q_all = np.concatenate([prev_q, q_c, q_n[:h]])
        lo = len(prev_t)
        qd, qdd = savgol_derivatives(t_all, q_all, h, lo, lo + len(t_c))
        yield cur, qd, qdd
        prev_t = np.concatenate([prev_t, t_c])[-h:]
        prev_q = np.concatenate([prev_q, q_c])[-h:]
        cur = nxt


def _atomic_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def _sensors_of(schema: Any, model: RobotModel, sensors: Sequence[str] | None, src: str) -> list:
    cols = [n for n in schema.names if n.startswith("ft.")]
    if sensors:
        missing = [s for s in sensors if ft_column(s) not in cols]
        if missing:
            raise LogError(f"{src}: no column for sensors {missing} (found {cols})")
        return list(sensors)
    found = [c[3:] for c in cols if c[3:] in model.ft_sensors]
    if not found:
        raise LogError(
            f"{src}: no ft.<sensor> column for the robot's sensors {list(model.ft_sensors)}"
            f" (found {cols})"
        )
    return found


def load_residual(checkpoint: str | Path, model: RobotModel) -> Any:
    """Load a residual checkpoint for ``model`` (its robot hash must match).

    Args:
        checkpoint: directory written by ``python -m training`` or
            :meth:`~torchcontact.residual.ResidualCorrection.save`.
        model: the robot the log is estimated with.

    Returns:
        A :class:`~torchcontact.residual.ResidualCorrection`.

    Raises:
        LogError: unreadable, tampered or foreign checkpoint, or one trained for another robot.
    """
    from torchcontact.residual import CheckpointError, ResidualCorrection

    try:
        return ResidualCorrection.load(checkpoint, model)
    except CheckpointError as exc:
        raise LogError(f"--residual: {exc}") from None


def prepare(
    path: str | Path,
    model: RobotModel,
    sensors: Sequence[str] | None = None,
    residual: Any = None,
) -> tuple[Any, LogEstimator, list[str]]:
    """Open a log and build its :class:`LogEstimator`.

    Args:
        path: the log.
        model: the robot.
        sensors: sensors to use (default: those with a column).
        residual: a loaded :class:`~torchcontact.residual.ResidualCorrection` or None.

    Returns:
        ``(ParquetFile, LogEstimator, columns to read)``.

    Raises:
        LogError: not Parquet, no joint names, mismatched joints, no sensor column, no ``q``, a
            residual whose sensor is not in use or whose feature columns the log lacks.
    """
    import pyarrow as pa

    src = str(path)
    pf = open_parquet(path)
    schema = pf.schema_arrow
    for col in ("t_ns", "q"):
        if col not in schema.names:
            raise LogError(f"{src}: missing column {col!r} (found {schema.names})")
    joint_names = joint_names_of(schema, src)
    used = _sensors_of(schema, model, sensors, src)
    derived = [c for c in ("qd", "qdd") if c not in schema.names]
    contact_fields: list[tuple[str, Any]] = []
    if "contacts" in schema.names:
        ctype = schema.field("contacts").type
        if not (pa.types.is_list(ctype) or pa.types.is_large_list(ctype)) or not pa.types.is_struct(
            ctype.value_type
        ):
            raise LogError(f"{src}: contacts must be a list of structs, found {ctype}")
        contact_fields = [(f.name, f.type) for f in ctype.value_type]
        names = [n for n, _ in contact_fields]
        for need in ("link", "kind", "position"):
            if need not in names:
                raise LogError(f"{src}: contact struct lacks field {need!r} (has {names})")
    le = LogEstimator(model, joint_names, used, contact_fields, src, derived, residual)
    for col in le.residual_columns():
        if col not in schema.names:
            raise LogError(
                f"{src}: the residual checkpoint needs column {col!r}, which the log lacks"
                f" (found {schema.names})"
            )
    columns = ["t_ns", "q", *[c for c in ("qd", "qdd") if c in schema.names]]
    columns += [ft_column(s) for s in used]
    columns += [c for c in ("tau_measured", *BASE_COLUMNS, "contacts") if c in schema.names]
    columns += [c for c in le.residual_columns() if c not in columns]
    return pf, le, columns


def merge_parts(parts: Sequence[Path], out: Path, schema: Any) -> int:
    """Concatenate Parquet parts (in order) into ``out`` through ``out.tmp`` and a rename."""
    import pyarrow.parquet as pq

    tmp = out.with_name(out.name + ".tmp")
    rows = 0
    with pq.ParquetWriter(tmp, schema) as w:
        for p in parts:
            tab = pq.read_table(p).cast(schema)
            w.write_table(tab)
            rows += tab.num_rows
    os.replace(tmp, out)
    return rows


def estimate_file(
    path: str | Path,
    robot: str | Path | RobotModel,
    out: str | Path,
    *,
    sensors: Sequence[str] | None = None,
    batch_size: int = 8192,
    device: str = "cpu",
    dtype: torch.dtype = torch.float64,
    resume: bool = False,
    progress: bool | None = None,
    half_window: int = DEFAULT_HALF_WINDOW,
    residual: Any = None,
) -> dict:
    """Estimate every frame of a log and write the output log (local engine).

    Args:
        path: input Parquet log (format of :mod:`torchcontact.logs.format`).
        robot: URDF path or a :class:`RobotModel`.
        out: output Parquet file; ``out.partial/`` and ``out.progress.json`` exist while running.
        sensors: sensors to use (default: those with an ``ft.<sensor>`` column).
        batch_size: frames per chunk (memory is flat in the log length).
        device: ``auto``, ``cpu`` or ``cuda``.
        dtype: computation dtype (float64 recommended).
        resume: finish an interrupted run from its parts (same chunking as recorded).
        progress: show a progress bar (default: when stderr is a terminal).
        half_window: ``h`` of the Savitzky-Golay differentiator when ``qd``/``qdd`` are derived.
        residual: residual checkpoint directory (or a loaded
            :class:`~torchcontact.residual.ResidualCorrection`): its correction [N; N m] is
            subtracted from its sensor's reading before estimation and the output metadata
            ``torchcontact.residual`` names the checkpoint and its weights' sha256. A recurrent
            (GRU) residual sees the frames in time order across chunks; it cannot ``resume``.

    Returns:
        A summary dict: frames, ok, bad, seconds, frames_per_s, sensors, derived, resumed_chunks.

    Raises:
        LogError: the input cannot be processed at all (message names the file); an existing
            ``out.partial`` without ``resume``; a ``resume`` whose input changed; a residual
            checkpoint for another robot, an unused sensor or with a column the log lacks;
            ``resume`` with a recurrent residual.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    model = (
        robot
        if isinstance(robot, RobotModel)
        else RobotModel.from_urdf(robot, dtype=dtype, device=resolve_device(device))
    )
    if isinstance(robot, RobotModel) and (model.dtype != dtype or device != "cpu"):
        model = model.to(resolve_device(device), dtype)
    if residual is not None and not hasattr(residual, "correct"):
        residual = load_residual(residual, model)
    if residual is not None:
        residual.reset()  # a GRU's state starts afresh with each log
    if residual is not None and residual.recurrent and resume:
        raise LogError(
            f"{path}: --resume (resume=True) is not supported with a recurrent (GRU) residual:"
            " its state depends on every earlier frame; rerun from the start"
        )
    pf, le, columns = prepare(path, model, sensors, residual)
    out = Path(out)
    partial = out.with_name(out.name + ".partial")
    sidecar = out.with_name(out.name + ".progress.json")
    st = os.stat(path)
    ident = {
        "input": str(Path(path).resolve()),
        "input_size": st.st_size,
        "input_mtime_ns": st.st_mtime_ns,
        "urdf_sha256": model.urdf_sha256,
        "sensors": list(le.sensors),
        "dtype": str(dtype),
        "half_window": half_window,
    }
    if residual is not None:
        ident["residual_weights_sha256"] = residual.meta.get("weights_sha256")
    done = 0
    if partial.exists() or sidecar.exists():
        if residual is not None and residual.recurrent:
            # the GRU state after the parts already written is not saved: refuse, do not guess
            raise LogError(
                f"{out}: an interrupted run left {partial.name}; a recurrent (GRU) residual needs"
                " every frame in order and cannot resume: delete it and rerun"
            )
        if not resume:
            raise LogError(
                f"{out}: an interrupted run left {partial.name}; pass --resume (resume=True) to"
                " finish it or delete it"
            )
        rec = json.loads(sidecar.read_text()) if sidecar.exists() else None
        if rec is None or any(rec.get(k) != v for k, v in ident.items()):
            raise LogError(f"{out}: the interrupted run was for other inputs; delete {partial}")
        batch_size = int(rec["batch_size"])
        for tmp in partial.glob("*.tmp"):
            tmp.unlink()
        while (partial / f"part-{done:08d}.parquet").exists():
            done += 1
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        partial.mkdir()
    ident["batch_size"] = batch_size
    _atomic_json(sidecar, {**ident, "chunks_done": done})
    import pyarrow.parquet as pq

    total = pf.metadata.num_rows
    n_chunks = (total + batch_size - 1) // batch_size
    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=total, unit="frames", disable=not show, desc=Path(path).name)
    bar.update(min(done * batch_size, total))
    schema = le.output_schema()
    counts = {"ok": 0, "bad": 0}
    chunks = _rebatch(pf, columns, batch_size)
    if not le.derived:  # nothing to carry between chunks: skip the done ones cheaply
        chunks = (c for k, c in enumerate(chunks) if k >= done)
        stream = enumerate(_chunks_with_derivatives(chunks, le.perm, False, half_window), done)
    else:
        stream = enumerate(_chunks_with_derivatives(chunks, le.perm, True, half_window))
    for k, (chunk, qd, qdd) in stream:
        if k < done:
            continue
        # only the missing columns are replaced by derived values; logged ones are kept
        res = le.process(
            chunk, qd if "qd" in le.derived else None, qdd if "qdd" in le.derived else None
        )
        ok = int(np.sum(np.asarray(res.column("status").to_pylist(), dtype=object) == "ok"))
        counts["ok"] += ok
        counts["bad"] += res.num_rows - ok
        part = partial / f"part-{k:08d}.parquet"
        tmp = part.with_name(part.name + ".tmp")
        pq.write_table(res, tmp)
        os.replace(tmp, part)
        _atomic_json(sidecar, {**ident, "chunks_done": k + 1})
        bar.update(res.num_rows)
    bar.close()
    parts = [partial / f"part-{k:08d}.parquet" for k in range(n_chunks)]
    missing = [p.name for p in parts if not p.exists()]
    if missing:
        raise LogError(f"{out}: parts {missing[:3]} missing; delete {partial} and rerun")
    rows = merge_parts(parts, out, schema)
    shutil.rmtree(partial)
    sidecar.unlink()
    seconds = time.perf_counter() - t0
    return {
        "input": str(path),
        "output": str(out),
        "frames": rows,
        "processed_now": counts["ok"] + counts["bad"],
        "ok_now": counts["ok"],
        "bad_now": counts["bad"],
        "seconds": round(seconds, 3),
        "frames_per_s": round((counts["ok"] + counts["bad"]) / max(seconds, 1e-9), 1),
        "sensors": list(le.sensors),
        "derived": list(le.derived),
        "resumed_chunks": done,
        "engine": "local",
    }


def expand_inputs(inputs: Sequence[str | Path]) -> list[Path]:
    """Files, folders (their ``*.parquet``) and globs -> a sorted list of files.

    Raises:
        LogError: an input that matches nothing.
    """
    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(p.glob("*.parquet"))
        elif p.exists():
            found = [p]
        else:
            found = sorted(Path(m) for m in glob.glob(str(item)))
        if not found:
            raise LogError(f"{item}: no such file, folder or glob match")
        files += found
    return files


def output_paths(inputs: Sequence[Path], out: str | Path) -> list[Path]:
    """Output file per input: ``out`` itself for one file, ``out/<name>`` for several."""
    out = Path(out)
    if len(inputs) == 1 and not out.is_dir():
        return [out]
    names = [p.name for p in inputs]
    if len(set(names)) != len(names):
        raise LogError(f"inputs share file names {names}; give them distinct names")
    return [out / n for n in names]


def estimate_files(
    inputs: Sequence[str | Path], robot: str | Path, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file` over files, folders or globs (``out`` a folder for several)."""
    files = expand_inputs(inputs)
    outs = output_paths(files, out)
    model = RobotModel.from_urdf(
        robot,
        dtype=kwargs.get("dtype", torch.float64),
        device=resolve_device(kwargs.pop("device", "cpu")),
    )
    if kwargs.get("residual") is not None:  # load and verify once for all files
        kwargs["residual"] = load_residual(kwargs["residual"], model)
    return [estimate_file(f, model, o, **kwargs) for f, o in zip(files, outs, strict=True)]
