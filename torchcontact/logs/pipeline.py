"""Estimate the contacts of every frame of a Parquet log, streamed in chunks.

:class:`LogEstimator` turns one chunk (a pyarrow table in the log format of
:mod:`torchcontact.logs.format`) into output rows; it is shared by the local engine
(:func:`estimate_file`) and the Ray engine (:mod:`torchcontact.logs.ray_engine`).

Crash safety: the output is written to ``OUT.tmp`` and renamed to ``OUT`` when every chunk is
done, so an interrupted run never leaves a file named ``OUT``. Each estimated chunk ``k`` is also
journalled to ``OUT.partial/part-<k>.arrow`` (Arrow IPC, temporary name and atomic rename) and
``OUT.progress.json`` records the progress. ``resume=True`` writes the journalled chunks into a
fresh ``OUT.tmp`` and processes the rest with the same chunking, so no frame is missing or
duplicated. An output that is, or contains, an input is
refused before anything is written.

Status: every output row has ``status_code`` (the bits of :data:`torchcontact.STATUS`), ``status``
(its text) and ``status_detail`` (what the pipeline found: a malformed vector, an unknown link, a
joint beyond its velocity limit, ...). Frames with a non-zero code have NaN outputs; the rest of
the log is processed.

Friction cones (:class:`LogConstraints`, ``estimate --constraints``): every pushing contact's force
is kept inside the friction cone of its ``normal`` (contact field) and friction coefficient
(``friction`` or ``cone_angle`` field, else the run's default); the output adds per sensor
``converged.<sensor>`` and ``iterations.<sensor>`` and per contact ``cone_active``. Frames are
warm-started from their predecessor's estimate (:class:`~torchcontact.PreviousFrame`), across
chunks too: a chunk's first frame starts from the previous chunk's last estimates, matched by
link, kind and order. Non-convergence is not a status bit (status bits mean NaN outputs; a frame
that did not converge keeps its last interior-point iterate, inside the cones): it is
``converged.<sensor> = false``.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact.constrained import FrictionCones, PreviousFrame
from torchcontact.contacts import KINDS, ContactRecords, Contacts
from torchcontact.errors import InputError, LogError
from torchcontact.estimation import ContactEstimator
from torchcontact.logs.derive import DEFAULT_HALF_WINDOW, savgol_derivatives
from torchcontact.logs.format import (
    BASE_COLUMNS,
    META_DERIVED,
    META_RESIDUAL,
    META_SENSORS,
    META_URDF_SHA256,
    META_VERSION,
    LogWriter,
    check_outputs,
    fixed_list,
    ft_column,
    iter_chunks,
    joint_names_of,
    joint_permutation,
    open_log,
    output_schema,
    read_contacts,
    read_journal,
    struct_list,
    vectors,
    write_journal,
)
from torchcontact.model import RobotModel
from torchcontact.status import status_messages

__all__ = [
    "DEFAULT_VELOCITY_MARGIN",
    "LogConstraints",
    "LogError",
    "LogEstimator",
    "estimate_file",
    "estimate_files",
    "expand_inputs",
    "load_robot",
]

#: Default ``velocity_margin``: a joint faster than twice its URDF velocity limit is implausible.
DEFAULT_VELOCITY_MARGIN = 2.0

# The plausibility bit (64) and the non-finite-output bit (32) are set by the estimator
# (ContactEstimator(..., velocity_margin=..., ft_range=...)), one meaning in Python and logs.


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``; ``cuda`` must be available.

    Raises:
        InputError: an unknown device, or ``cuda`` without a usable CUDA device.
    """
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError(f"--device {device}: expected auto, cpu or cuda")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(
            f"--device {device}: CUDA is not available (torch {torch.__version__}"
            f"{' has no CUDA support' if torch.version.cuda is None else ' sees no GPU'});"
            " use --device cpu or auto"
        )
    return device


def load_robot(
    robot: str | Path | RobotModel,
    dtype: torch.dtype = torch.float64,
    device: str = "cpu",
) -> RobotModel:
    """The robot model of a robot argument (or a model, moved to ``device`` and ``dtype``).

    ``robot`` is ``tcarm``, ``icub``, a URDF path or a :class:`~torchcontact.robots.RobotSpec`
    (with declared F/T sensors): :func:`torchcontact.robots.load_robot_model`.

    Raises:
        InputError: no such URDF file, not a URDF, or an unusable device.
        URDFError: a URDF torchcontact cannot model (the message names the element).
    """
    from torchcontact.robots import load_robot_model

    device = resolve_device(device)
    if isinstance(robot, RobotModel):
        if robot.dtype == dtype and str(robot.device) == device:
            return robot
        return robot.to(device, dtype)
    return load_robot_model(robot, dtype=dtype, device=device)


def _check_positive(**values: int) -> None:
    for name, value in values.items():
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise InputError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")


def ft_ranges(ft_range: Mapping[str, Any] | None, sensors: Sequence[str]) -> dict[str, np.ndarray]:
    """``{sensor: (6,) or scalar}`` -> ``{sensor: (6,)}`` limits [N; N m], for sensors in use.

    Raises:
        InputError: a sensor not in use, a limit that is not 1 or 6 positive numbers.
    """
    out: dict[str, np.ndarray] = {}
    for s, v in (ft_range or {}).items():
        if s not in sensors:
            raise InputError(f"--ft-range {s}: not a sensor in use ({list(sensors)})")
        arr = np.broadcast_to(np.asarray(v, np.float64).reshape(-1), (6,)).copy()
        if np.asarray(v).size not in (1, 6) or not (arr > 0).all():
            raise InputError(f"--ft-range {s}: give 1 or 6 positive numbers [N; N m], got {v}")
        out[s] = arr
    return out


@dataclass(frozen=True)
class LogConstraints:
    """Friction-cone constrained estimation of a log (``estimate --constraints``).

    Attributes:
        cones: the solver's settings (iteration budget, ``eps``, ``tol``).
        friction: friction coefficient of the contacts whose records give neither ``friction``
            nor ``cone_angle`` (None: such a contact is an invalid record, status bit 4).
        warm_start: start each frame from its predecessor's estimate (else from the
            pseudo-inverse solution).
        wave: frames per batched call of the warm-started waves
            (:class:`~torchcontact.PreviousFrame`).

    Raises:
        InputError: a friction coefficient that is not a finite number > 0, a wave < 1.

    Example:
        >>> LogConstraints(friction=0.5).cones.iterations
        25
    """

    cones: FrictionCones = field(default_factory=FrictionCones)
    friction: float | None = None
    warm_start: bool = True
    wave: int = 1024

    def __post_init__(self) -> None:
        if self.friction is not None and not (0 < float(self.friction) < np.inf):
            raise InputError(f"--friction must be a finite number > 0, got {self.friction}")
        if not (isinstance(self.wave, int) and self.wave >= 1):
            raise InputError(f"the warm-start wave must be an integer >= 1, got {self.wave!r}")


class _Issues:
    """Per-frame problems found by the pipeline: status bits and details, in priority order."""

    def __init__(self, n: int) -> None:
        self.code = np.zeros(n, np.int64)
        self.items: list[tuple[np.ndarray, str]] = []

    def add(self, rows: np.ndarray, bit: int, detail: str) -> None:
        if rows.any():
            self.code[rows] |= bit
            self.items.append((rows, detail))

    def details(self) -> np.ndarray:
        out = np.full(len(self.code), None, dtype=object)
        for rows, text in self.items:
            idx = np.flatnonzero(rows)
            out[idx] = [text if c is None else f"{c}; {text}" for c in out[idx]]
        return out


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
        velocity_margin: frames with a joint velocity beyond ``margin`` times its URDF limit get
            status bit 64 (None: no check).
        ft_range: ``{sensor: (6,) or scalar}`` [N; N m]: frames with a reading beyond it get
            status bit 64.
        constraints: friction-cone constrained estimation (:class:`LogConstraints`), or None.

    Raises:
        LogError: joints missing from or extra to the model (mimic joints are not coordinates),
            an unknown sensor, or a residual for a sensor or joints not in use.
        InputError: a bad ``ft_range``.
    """

    model: RobotModel
    input_joint_names: Sequence[str]
    sensors: Sequence[str]
    contact_fields: Sequence[tuple[str, Any]] = ()
    source: str = ""
    derived: Sequence[str] = ()
    residual: Any = None
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN
    ft_range: Mapping[str, Any] | None = None
    constraints: LogConstraints | None = None
    estimator: ContactEstimator = field(init=False)
    perm: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.perm = joint_permutation(
            self.input_joint_names, self.model.joint_names, self.model.name, self.source
        )
        if self.velocity_margin is not None and not self.velocity_margin > 0:
            raise InputError(f"--velocity-margin must be > 0, got {self.velocity_margin}")
        self._ft_range = ft_ranges(self.ft_range, self.sensors)
        guards = {"velocity_margin": self.velocity_margin, "ft_range": self._ft_range}
        try:
            self.estimator = ContactEstimator(self.model, list(self.sensors), **guards)
        except ValueError as exc:
            raise LogError(f"{self.source}: {exc}") from None
        # contact links the estimator can use: known frames inside some sensor's region
        self._link_ok: dict[str | None, str | None] = {}
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
    def output_schema(self) -> Any:
        """Schema of the output rows, with joint names, robot hash and version in the metadata."""
        from torchcontact import __version__

        derived = {
            "columns": list(self.derived),
            "method": f"Savitzky-Golay order 2 over t_ns, {2 * DEFAULT_HALF_WINDOW + 1} frames"
            if self.derived
            else "",
        }
        meta = {
            META_URDF_SHA256: self.model.urdf_sha256,
            META_VERSION: __version__,
            META_SENSORS: json.dumps(list(self.sensors)),
            META_DERIVED: json.dumps(derived),
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
        return output_schema(
            self.model.joint_names,
            self.sensors,
            self.contact_fields,
            meta,
            constraints=self.constraints is not None,
        )

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
            self._link_ok[link] = msg
        return self._link_ok[link]

    def _vectors(self, table: Any, name: str, n: int, bit: int, issues: _Issues) -> np.ndarray:
        vals, bad = vectors(table.column(name), n)
        issues.add(bad, bit, f"{name} is not {n} floats")
        return vals

    def _check_contacts(
        self, records: ContactRecords, malformed: dict[str, np.ndarray], n: int, issues: _Issues
    ) -> np.ndarray:
        """Per-record problems -> frame issues (bit 128 or 4); returns the bad-record mask."""
        M = len(records)
        bit = np.zeros(M, np.int64)
        # per distinct link and kind (few), mapped back to the records
        ln, lc, kn, kc = records.name_codes()
        link_msg = [self._link_problem(None if n is None else str(n)) for n in ln]
        kind_msg = [None if k in KINDS else f"unknown contact kind {k!r}" for k in kn]
        reason = np.array(link_msg, dtype=object)[lc]
        reason = np.where(np.equal(reason, None), np.array(kind_msg, dtype=object)[kc], reason)
        bit[~np.equal(reason, None)] = 128
        # a vector field is required only by the kind that uses it
        kinds = records.kinds
        for need, col, width, kind in (
            (np.ones(M, bool), "position", 3, None),
            (kinds == "force_dir", "direction", 3, "force_dir"),
            (kinds == "known", "wrench", 6, "known"),
        ):
            bad = need & malformed[col] & (reason == None)  # noqa: E711 - object array
            reason[bad] = (
                "contact position is not 3 floats"
                if kind is None
                else f"{kind} contact without a {width}-float {col}"
            )
            bit[bad] = 4
        if self.constraints is not None:
            self._check_cones(records, malformed, reason, bit)
        bad_record = reason != None  # noqa: E711
        for msg in dict.fromkeys(reason[bad_record]):
            rows = np.zeros(n, bool)
            sel = reason == msg
            rows[records.frame[sel]] = True
            issues.add(rows, int(bit[sel][0]), msg)
        return bad_record

    def _check_cones(
        self,
        records: ContactRecords,
        malformed: dict[str, np.ndarray],
        reason: np.ndarray,
        bit: np.ndarray,
    ) -> None:
        """The friction-cone fields of pushing force and wrench records (bits 4 and 8)."""
        M = len(records)
        kinds = records.kinds
        push = (kinds != "known") if records.pushing is None else np.where(
            np.isnan(records.pushing), kinds != "known", records.pushing > 0.5
        )  # fmt: skip
        cone = push & ((kinds == "force") | (kinds == "wrench")) & np.equal(reason, None)
        nrm = np.full((M, 3), np.nan) if records.normals is None else records.normals
        no_normal = malformed.get("normal", np.ones(M, bool)) | ~np.isfinite(nrm).all(-1)
        nan = np.full(M, np.nan)
        mu = nan if records.friction is None else records.friction
        angle = nan if records.cone_angle is None else records.cone_angle
        default = self.constraints.friction
        checks = (
            (no_normal, 4, "pushing contact without a finite 3-float normal (--constraints)"),
            (~no_normal & ~(np.abs(nrm) > 0).any(-1), 8, "zero-length contact normal"),
            (~np.isnan(mu) & ~np.isnan(angle), 4, "contact gives both friction and cone_angle"),
            (~np.isnan(mu) & ~((mu > 0) & (mu < np.inf)), 4,
             "contact friction is not a finite number > 0"),
            (~np.isnan(angle) & ~((angle > 0) & (angle < np.pi / 2)), 4,
             "contact cone_angle is not in (0, pi/2) rad"),
            (np.isnan(mu) & np.isnan(angle) & (default is None), 4,
             "contact without friction or cone_angle (give --friction or --cone-angle)"),
        )  # fmt: skip
        for mask, b, msg in checks:
            bad = cone & mask & np.equal(reason, None)
            reason[bad] = msg
            bit[bad] = b

    # ------------------------------------------------------------------ one chunk
    def process(
        self,
        table: Any,
        qd: np.ndarray | None = None,
        qdd: np.ndarray | None = None,
        previous: Any = None,
    ) -> Any:
        """Estimate every frame of a chunk.

        Args:
            table: pyarrow table or record batch in the log format.
            qd: ``(N, nv)`` velocities in the model's joint order when derived (else read).
            qdd: ``(N, nv)`` accelerations likewise.
            previous: the output of the chunk before (with constraints and warm starts, its last
                frame's estimates start this chunk's first frame), or None.

        Returns:
            A pyarrow table with :meth:`output_schema`.
        """
        import pyarrow as pa

        if isinstance(table, pa.RecordBatch):
            table = pa.Table.from_batches([table])
        model, est, perm = self.model, self.estimator, self.perm
        N, nv = table.num_rows, len(self.input_joint_names)  # the log's joints (perm: the model's)
        issues = _Issues(N)
        q = self._vectors(table, "q", nv, 2, issues)[:, perm]
        if qd is None:
            qd = self._vectors(table, "qd", nv, 2, issues)[:, perm]
        if qdd is None:
            qdd = self._vectors(table, "qdd", nv, 2, issues)[:, perm]
        ft = {s: self._vectors(table, ft_column(s), 6, 1, issues) for s in self.sensors}
        if self.residual is not None:
            ft[self.residual.sensor] = self._corrected(table, ft[self.residual.sensor], q, qd, qdd)
        tau = None
        if "tau_measured" in table.column_names:
            tau = self._vectors(table, "tau_measured", nv, 16, issues)[:, perm]
        base = {}
        for col, key in BASE_COLUMNS.items():
            if col in table.column_names:
                base[key] = self._vectors(table, col, 3, 2, issues)
        if base and len(base) != 3:
            raise LogError(f"{self.source}: need all of {list(BASE_COLUMNS)} or none")

        # ---- contacts: records -> validated -> slots (one layout per chunk)
        if self.contact_fields:
            records, fields, malformed = read_contacts(table.column("contacts"))
            bad_record = self._check_contacts(records, malformed, N, issues)
        else:
            records, fields, bad_record = ContactRecords.empty(), {}, np.zeros(0, bool)
        good = np.flatnonzero(~bad_record)
        cons = self.constraints
        contacts, slot_good = Contacts.from_records(
            records.select(good), N, dtype=model.dtype, device=model.device,
            friction=None if cons is None else cons.friction,
        )  # fmt: skip
        slot = np.full(len(records), -1, np.int64)
        slot[good] = slot_good

        # ---- estimate (Del Prete et al. 2012, Sec. 2) on the model's device and dtype
        def t(x: np.ndarray) -> torch.Tensor:
            return torch.tensor(x, dtype=model.dtype, device=model.device)  # copy: arrow is r/o

        cone_args: dict[str, Any] = {}
        if cons is not None:
            before = _last_estimates(previous, contacts.links, contacts.kinds)
            cone_args["constraints"] = cons.cones
            if cons.warm_start:
                cone_args["warm_start"] = PreviousFrame(
                    None if before is None else tuple(t(v) for v in before), cons.wave
                )
        res = est.estimate(
            t(q),
            t(qd),
            t(qdd),
            {s: t(v) for s, v in ft.items()},
            contacts,
            base=None if not base else _base_motion(base, t),
            tau_measured=None if tau is None else t(tau),
            **cone_args,
        )
        force = res.force.detach().cpu().numpy()
        moment = res.moment.detach().cpu().numpy()
        jt = res.joint_torques.detach().cpu().numpy()
        resid = {s: res.residual[s].detach().cpu().numpy().astype(np.float64) for s in self.sensors}
        code = res.status.cpu().numpy().astype(np.int64) | issues.code
        self._explain(code, qd, ft, issues)
        # ---- outputs of frames with a non-zero status are NaN (the estimator's own rows are)
        bad = code != 0
        jt = np.where(bad[:, None], np.nan, jt)
        for s in self.sensors:
            resid[s] = np.where(bad, np.nan, resid[s])

        # ---- output rows: input contacts with force and moment added, in record order
        M = len(records)
        cf = np.full((M, 3), np.nan)
        cm = np.full((M, 3), np.nan)
        ok_c = (slot >= 0) & ~bad[records.frame] if M else np.zeros(0, bool)
        if ok_c.any():
            cf[ok_c] = force[records.frame[ok_c], slot[ok_c]]
            cm[ok_c] = moment[records.frame[ok_c], slot[ok_c]]
        schema = self.output_schema()
        ctype = schema.field("contacts").type.value_type
        children = {n: fields[n] for n, _ in self.contact_fields}
        children["force"], children["moment"] = fixed_list(cf), fixed_list(cm)
        if cons is not None:  # the cone binds; null where the contact was not estimated
            act = res.cones.active.cpu().numpy()
            ca = np.zeros(M, bool)
            ca[ok_c] = act[records.frame[ok_c], slot[ok_c]]
            children["cone_active"] = pa.array(ca, mask=~ok_c)
        out: dict[str, Any] = {"t_ns": table.column("t_ns").combine_chunks().cast(pa.int64())}
        out["contacts"] = struct_list(children, records.frame, N, ctype)
        out["joint_torques"] = fixed_list(jt)
        for s in self.sensors:
            rank = res.rank[s].cpu().numpy().astype(np.int64)
            unknowns = res.unknowns[s].cpu().numpy().astype(np.int64)
            out[f"rank.{s}"], out[f"unknowns.{s}"] = pa.array(rank), pa.array(unknowns)
            out[f"nullity.{s}"] = pa.array(unknowns - rank)
            out[f"residual.{s}"] = pa.array(resid[s])
            if cons is not None:  # the solver's status; null on frames with a non-zero status
                conv = res.cones.converged[s].cpu().numpy()
                its = res.cones.iterations[s].cpu().numpy().astype(np.int64)
                out[f"converged.{s}"] = pa.array(conv, mask=bad)
                out[f"iterations.{s}"] = pa.array(its, mask=bad)
        out["status_code"] = pa.array(code)
        text = np.full(N, "ok", dtype=object)
        for c in np.unique(code[bad]):
            text[code == c] = status_messages(int(c))
        out["status"] = pa.array(text.tolist(), pa.string())
        out["status_detail"] = pa.array(issues.details().tolist(), pa.string())
        return pa.table(out, schema=schema)

    def _explain(
        self, code: np.ndarray, qd: np.ndarray, ft: dict[str, np.ndarray], issues: _Issues
    ) -> None:
        """Details of the estimator's bits 64 (which value is implausible) and 32 (overflow)."""
        flagged = (code & 64) != 0
        if flagged.any():
            if self.velocity_margin is not None:
                limit = np.asarray(
                    self.model.joint_limits.get("velocity", np.full(self.model.nv, np.inf))
                )
                over = (np.abs(qd) > self.velocity_margin * limit) & flagged[:, None]
                for j in np.flatnonzero(over.any(0)):
                    issues.add(
                        over[:, j],
                        0,
                        f"qd of {self.model.joint_names[j]!r} beyond {self.velocity_margin:g} x"
                        f" its URDF velocity limit {limit[j]:g}",
                    )
            for s, lim in self._ft_range.items():
                beyond = (np.abs(ft[s]) > lim).any(1) & flagged
                issues.add(beyond, 0, f"{ft_column(s)} beyond its range {lim.tolist()}")
        issues.add((code & 32) != 0, 0, "non-finite output from finite inputs")

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


def _last_estimates(
    previous: Any, links: Sequence[str], kinds: Sequence[str]
) -> tuple[np.ndarray, np.ndarray] | None:
    """The last frame's estimates of an output table, matched to slots: ``(force, moment)``.

    A slot takes the estimate of the previous frame's contact with its link and kind and the same
    rank among them (the slot assignment's rule); ``(K, 3)`` each, NaN where none matches (that
    slot starts cold). None without a previous table or contacts.
    """
    if previous is None or previous.num_rows == 0 or not len(links):
        return None
    last = previous.column("contacts")[previous.num_rows - 1].as_py() or []
    seen: dict[tuple[str, str], int] = {}
    found: dict[tuple[str, str, int], tuple] = {}
    for c in last:
        key = (c.get("link"), c.get("kind"))
        r = seen.get(key, 0)
        seen[key] = r + 1
        if c.get("force") is not None and c.get("moment") is not None:
            found[(*key, r)] = (c["force"], c["moment"])
    force = np.full((len(links), 3), np.nan)
    moment = np.full((len(links), 3), np.nan)
    rank: dict[tuple[str, str], int] = {}
    for k, key in enumerate(zip(links, kinds, strict=True)):
        r = rank.get(key, 0)
        rank[key] = r + 1
        if (*key, r) in found:
            force[k], moment[k] = found[(*key, r)]
    return force, moment


def _base_motion(base: dict, t: Any) -> Any:
    from torchcontact.dynamics import BaseMotion

    return BaseMotion(t(base["omega"]), t(base["domega"]), t(base["proper_acc"]))


# ---------------------------------------------------------------------- streaming
def times_and_positions(
    chunk: Any, perm: np.ndarray, width: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``t_ns (N,)`` int64 and ``q (N, nv)`` in the model's joint order of a chunk.

    ``width`` is the number of joints of the log (default ``len(perm)``; more when the log has
    joints the robot lacks).
    """
    q, _ = vectors(chunk.column("q"), len(perm) if width is None else width)
    return chunk.column("t_ns").to_numpy().astype(np.int64), q[:, perm]


def chunks_with_derivatives(
    chunks: Iterator[Any],
    perm: np.ndarray,
    derive: bool,
    h: int,
    before: tuple[np.ndarray, np.ndarray] | None = None,
    after: tuple[np.ndarray, np.ndarray] | None = None,
    width: int | None = None,
) -> Iterator[tuple[Any, np.ndarray | None, np.ndarray | None]]:
    """Yield ``(chunk, qd, qdd)``; derivatives from ``q`` with ``h`` frames of context each side.

    Args:
        chunks: consecutive tables of a log.
        perm: the log's joint columns -> the model's order.
        derive: compute ``qd``/``qdd`` (else None).
        h: half window of :func:`~torchcontact.logs.derive.savgol_derivatives`.
        before: ``(t_ns, q)`` of the up to ``h`` frames preceding the first chunk (model order).
        after: ``(t_ns, q)`` of the up to ``h`` frames following the last chunk.
        width: the number of joints of the log (:func:`times_and_positions`).
    """
    if not derive:
        for c in chunks:
            yield c, None, None
        return
    nv = len(perm)
    empty = (np.zeros(0, np.int64), np.zeros((0, nv)))
    prev_t, prev_q = before if before is not None else empty
    cur = next(chunks, None)
    while cur is not None:
        nxt = next(chunks, None)
        t_c, q_c = times_and_positions(cur, perm, width)
        if nxt is not None:
            t_n, q_n = times_and_positions(nxt.slice(0, h), perm, width)
        else:
            t_n, q_n = after if after is not None else empty
        t_all = np.concatenate([prev_t, t_c, t_n[:h]])
        q_all = np.concatenate([prev_q, q_c, q_n[:h]])
        lo = len(prev_t)
        qd, qdd = savgol_derivatives(t_all, q_all, h, lo, lo + len(t_c))
        yield cur, qd, qdd
        prev_t = np.concatenate([prev_t, t_c])[-h:]
        prev_q = np.concatenate([prev_q, q_c])[-h:]
        cur = nxt


def estimate_chunks(
    le: LogEstimator,
    chunks: Iterator[tuple[Any, np.ndarray | None, np.ndarray | None]],
    previous: Any = None,
) -> Iterator[Any]:
    """Output tables of :func:`chunks_with_derivatives`' chunks.

    Derived columns only replace the missing ones; logged ``qd``/``qdd`` are kept. Each chunk
    gets the output of the one before (``previous`` for the first: e.g. the last part of an
    interrupted run), whose last frame warm-starts a constrained estimate.
    """
    for chunk, qd, qdd in chunks:
        previous = le.process(
            chunk,
            qd if "qd" in le.derived else None,
            qdd if "qdd" in le.derived else None,
            previous=previous,
        )
        yield previous


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
        checkpoint: directory written by ``torchcontact train fit`` or
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
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: LogConstraints | None = None,
) -> tuple[Any, LogEstimator, list[str]]:
    """Open a log and build its :class:`LogEstimator`.

    A log without a ``contacts`` column is estimated as contact-free, with one warning.

    Args:
        path: the log.
        model: the robot.
        sensors: sensors to use (default: those with a column).
        residual: a loaded :class:`~torchcontact.residual.ResidualCorrection` or None.
        velocity_margin: see :class:`LogEstimator`.
        ft_range: see :class:`LogEstimator`.
        constraints: see :class:`LogEstimator`.

    Returns:
        ``(ParquetFile, LogEstimator, columns to read)``.

    Raises:
        LogError: not Parquet, no joint names, mismatched joints, no sensor column, no ``q``, a
            residual whose sensor is not in use or whose feature columns the log lacks.
        InputError: ``constraints`` on a log whose contacts have no ``normal`` field, or no
            ``friction``/``cone_angle`` field and no default friction.
    """
    import pyarrow as pa

    src = str(path)
    pf = open_log(path)
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
    else:
        warnings.warn(
            f"{src}: no 'contacts' column: every frame is estimated as contact-free (any contact"
            " load shows in residual.<sensor>)",
            UserWarning,
            stacklevel=2,
        )
    if constraints is not None and contact_fields:
        names = [n for n, _ in contact_fields]
        if "normal" not in names:
            raise InputError(
                f"--constraints: the contacts of {src} have no 'normal' field (outward surface"
                f" normal, link frame); found {names}"
            )
        if constraints.friction is None and not {"friction", "cone_angle"} & set(names):
            raise InputError(
                f"--constraints: the contacts of {src} have no friction or cone_angle field;"
                " give a default with --friction or --cone-angle"
            )
    le = LogEstimator(
        model,
        joint_names,
        used,
        contact_fields,
        src,
        derived,
        residual,
        velocity_margin=velocity_margin,
        ft_range=ft_range,
        constraints=constraints,
    )
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


@dataclass
class RunState:
    """The files of one output while it is being written, and the progress already made.

    Attributes:
        out: the final output file.
        partial: ``OUT.partial/``, the journal: one part per chunk (or Ray unit).
        sidecar: ``OUT.progress.json``.
        ident: what the run is (input, robot, options); a resume must match it.
        done: parts already written by an interrupted run.
    """

    out: Path
    partial: Path
    sidecar: Path
    ident: dict
    done: set[int] = field(default_factory=set)

    @classmethod
    def side_paths(cls, out: Path) -> list[Path]:
        """Every path an estimate writes besides ``out`` itself."""
        return [out.with_name(out.name + s) for s in (".partial", ".progress.json", ".tmp")]

    def part(self, k: int) -> Path:
        """Path of part ``k``."""
        return self.partial / f"part-{k:08d}.arrow"

    def start(self, resume: bool, recurrent: bool = False) -> None:
        """Create the folder, or take over an interrupted run's parts (``resume``).

        Raises:
            LogError: parts of an interrupted run without ``resume``, a run for other inputs or
                options, or a recurrent residual (which cannot resume).
        """
        if self.partial.exists() or self.sidecar.exists():
            if recurrent:
                # the GRU state after the parts already written is not saved: refuse, not guess
                raise LogError(
                    f"{self.out}: an interrupted run left {self.partial.name}; a recurrent (GRU)"
                    " residual needs every frame in order and cannot resume: delete it and rerun"
                )
            if not resume:
                raise LogError(
                    f"{self.out}: an interrupted run left {self.partial.name}; pass --resume"
                    " (resume=True) to finish it or delete it"
                )
            try:
                rec = json.loads(self.sidecar.read_text())
            except (OSError, ValueError):
                rec = None
            if not isinstance(rec, dict) or any(rec.get(k) != v for k, v in self.ident.items()):
                raise LogError(
                    f"{self.out}: the interrupted run was for other inputs or options (engine,"
                    f" batch size, sensors, ...); delete {self.partial} and"
                    f" {self.sidecar.name} to start afresh"
                )
            for tmp in self.partial.glob("*.tmp"):
                tmp.unlink()
            self.done = {
                int(p.stem.removeprefix("part-")) for p in self.partial.glob("part-*.arrow")
            }
        else:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.partial.mkdir()
        self.record()

    def record(self) -> None:
        """Write the sidecar (atomically)."""
        _atomic_json(self.sidecar, {**self.ident, "parts_done": len(self.done)})

    def clean(self) -> None:
        """Remove the journal and the sidecar (the output is complete)."""
        shutil.rmtree(self.partial)
        self.sidecar.unlink()


def write_part(path: Path, tables: Iterator[Any] | Sequence[Any]) -> tuple[int, int]:
    """Journal output tables as one part; returns ``(rows, rows with status 0)``."""
    import pyarrow.compute as pc

    counts = [0, 0]

    def counted() -> Iterator[Any]:
        for tab in tables:
            counts[0] += tab.num_rows
            counts[1] += int(pc.sum(pc.equal(tab.column("status_code"), 0)).as_py() or 0)
            yield tab

    write_journal(counted(), path)
    return counts[0], counts[1]


def run_ident(path: str | Path, model: RobotModel, le: LogEstimator, **options: Any) -> dict:
    """What a run is: input file identity, robot, sensors and options (a resume must match)."""
    st = os.stat(path)
    ident = {
        "input": str(Path(path).resolve()),
        "input_size": st.st_size,
        "input_mtime_ns": st.st_mtime_ns,
        "urdf_sha256": model.urdf_sha256,
        "sensors": list(le.sensors),
        "velocity_margin": le.velocity_margin,
        "ft_range": {s: v.tolist() for s, v in le._ft_range.items()},
        **options,
    }
    if le.residual is not None:
        ident["residual_weights_sha256"] = le.residual.meta.get("weights_sha256")
    if le.constraints is not None:  # a resume must estimate with the same cones
        ident["constraints"] = repr(le.constraints)
    return ident


def summary(
    path: str | Path, out: Path, rows: int, counts: dict, t0: float, le: LogEstimator, **more: Any
) -> dict:
    """The summary dict both engines return (and ``--json`` prints)."""
    seconds = time.perf_counter() - t0
    now = counts["ok"] + counts["bad"]
    return {
        "input": str(path),
        "output": str(out),
        "frames": rows,
        "processed_now": now,
        "ok_now": counts["ok"],
        "bad_now": counts["bad"],
        "seconds": round(seconds, 3),
        "frames_per_s": round(now / max(seconds, 1e-9), 1),
        "sensors": list(le.sensors),
        "derived": list(le.derived),
        **more,
    }


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
    velocity_margin: float | None = DEFAULT_VELOCITY_MARGIN,
    ft_range: Mapping[str, Any] | None = None,
    constraints: LogConstraints | None = None,
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
        velocity_margin: frames with ``|qd|`` beyond this times the URDF velocity limit get
            status bit 64 (None: no check).
        ft_range: ``{sensor: (6,) or scalar}`` [N; N m]; readings beyond it get status bit 64.
        constraints: friction-cone constrained estimation (:class:`LogConstraints`), or None.

    Returns:
        A summary dict: input, output, frames, processed_now, ok_now, bad_now, seconds,
        frames_per_s, sensors, derived, resumed_chunks, chunks, engine (with constraints also
        ``cones``: ``converged`` share, ``iterations_mean`` and ``iterations_max`` over the frames
        estimated now).

    Raises:
        InputError: ``batch_size`` or ``half_window`` < 1, an unusable device, an output that is
            or contains an input, a missing URDF.
        LogError: the input cannot be processed at all (message names the file), or is
            corrupted (the chunks before the damage stay in ``out.partial`` for a resume); an
            existing ``out.partial`` without ``resume``; a ``resume`` whose input or options
            changed; a residual checkpoint for another robot, an unused sensor or with a column
            the log lacks; ``resume`` with a recurrent residual.
        URDFError: an unusable URDF.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    _check_positive(batch_size=batch_size, half_window=half_window)
    out = Path(out)
    robot_file = None if isinstance(robot, RobotModel) else robot
    check_outputs([out, *RunState.side_paths(out)], [path, robot_file, _path_or_none(residual)])
    model = load_robot(robot, dtype, device)
    if residual is not None and not hasattr(residual, "correct"):
        residual = load_residual(residual, model)
    if residual is not None:
        residual.reset()  # a GRU's state starts afresh with each log
    if residual is not None and residual.recurrent and resume:
        raise LogError(
            f"{path}: --resume (resume=True) is not supported with a recurrent (GRU) residual:"
            " its state depends on every earlier frame; rerun from the start"
        )
    pf, le, columns = prepare(
        path, model, sensors, residual, velocity_margin, ft_range, constraints
    )
    run = RunState(
        out,
        *RunState.side_paths(out)[:2],
        run_ident(path, model, le, engine="local", dtype=str(dtype), half_window=half_window),
    )
    # an interrupted run keeps its chunk size: read it before the ident is compared
    if resume and run.sidecar.exists():
        try:
            batch_size = int(json.loads(run.sidecar.read_text())["batch_size"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        if batch_size < 1:
            raise LogError(
                f"{run.sidecar}: batch_size {batch_size} is invalid; delete it and rerun"
            )
    run.ident["batch_size"] = batch_size
    run.start(resume, recurrent=residual is not None and residual.recurrent)
    done = len(run.done)
    if run.done != set(range(done)):
        raise LogError(f"{out}: parts of {run.partial} are not consecutive; delete it and rerun")
    total = pf.metadata.num_rows
    n_chunks = (total + batch_size - 1) // batch_size
    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=total, unit="frames", disable=not show, desc=Path(path).name)
    bar.update(min(done * batch_size, total))
    schema = le.output_schema()
    counts = {"ok": 0, "bad": 0}
    chunks = iter_chunks(pf, columns, batch_size, path)
    derive = bool(le.derived)
    if not derive:  # nothing to carry between chunks but the last estimates: skip the done ones
        chunks = (c for k, c in enumerate(chunks) if k >= done)
        previous = read_journal(run.part(done - 1)) if done and constraints else None
        stream = enumerate(
            estimate_chunks(
                le, chunks_with_derivatives(chunks, le.perm, False, half_window), previous
            ),
            done,
        )
    else:
        stream = enumerate(
            estimate_chunks(
                le,
                chunks_with_derivatives(
                    chunks, le.perm, True, half_window, width=len(le.input_joint_names)
                ),
            )
        )
    writer = LogWriter(out, schema)  # the output itself, renamed into place when complete
    try:
        for k in range(done):  # chunks of the interrupted run, from its journal
            writer.write(read_journal(run.part(k)))
        cones = _ConeTally(le)
        for k, res in stream:
            if k < done:
                continue
            writer.write(res)
            cones.add(res)
            rows, ok = write_part(run.part(k), [res])
            counts["ok"] += ok
            counts["bad"] += rows - ok
            run.done.add(k)
            run.record()
            bar.update(rows)
        if len(run.done) != n_chunks:
            missing = n_chunks - len(run.done)
            raise LogError(f"{out}: {missing} chunks missing; delete {run.partial} and rerun")
        rows = writer.rows
        writer.close()
    except LogError as exc:
        writer.abort()
        raise LogError(
            f"{exc}; {len(run.done)} of {n_chunks} chunks are estimated in {run.partial}"
        ) from None
    except BaseException:
        writer.abort()
        raise
    finally:
        bar.close()
    run.clean()
    return summary(
        path, out, rows, counts, t0, le, resumed_chunks=done, chunks=n_chunks, engine="local",
        **cones.summary(),
    )  # fmt: skip


class _ConeTally:
    """Convergence and iterations of the constrained solver over the output tables seen."""

    def __init__(self, le: LogEstimator) -> None:
        self.sensors = list(le.sensors) if le.constraints is not None else []
        self.n = self.converged = self.it_sum = self.it_max = 0

    def add(self, table: Any) -> None:
        for s in self.sensors:
            conv = table.column(f"converged.{s}").to_numpy(zero_copy_only=False)
            its = table.column(f"iterations.{s}").to_numpy(zero_copy_only=False)
            ran = ~np.isnan(its.astype(float)) & (its.astype(float) > 0)
            self.n += int(ran.sum())
            self.converged += int(np.sum(conv[ran] == True))  # noqa: E712 - object array
            if ran.any():
                self.it_sum += int(its[ran].astype(np.int64).sum())
                self.it_max = max(self.it_max, int(its[ran].astype(np.int64).max()))

    def summary(self) -> dict:
        if not self.sensors:
            return {}
        n = max(self.n, 1)
        return {"cones": {"solved": self.n, "converged": round(self.converged / n, 4),
                          "iterations_mean": round(self.it_sum / n, 2),
                          "iterations_max": self.it_max}}  # fmt: skip


def _path_or_none(x: Any) -> str | Path | None:
    return x if isinstance(x, (str, Path)) else None


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
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: several inputs need a folder, and {out} is a file")
    names = [p.name for p in inputs]
    if len(set(names)) != len(names):
        raise LogError(f"inputs share file names {names}; give them distinct names")
    return [out / n for n in names]


def estimate_files(
    inputs: Sequence[str | Path], robot: str | Path, out: str | Path, **kwargs: Any
) -> list[dict]:
    """:func:`estimate_file` over files, folders or globs (``out`` a folder for several).

    Every output is checked against every input before the first file is processed.
    """
    files = expand_inputs(inputs)
    outs = output_paths(files, out)
    for o in outs:
        check_outputs([o, *RunState.side_paths(o)], [*files, robot, kwargs.get("residual")])
    model = load_robot(robot, kwargs.get("dtype", torch.float64), kwargs.pop("device", "cpu"))
    if kwargs.get("residual") is not None:  # load and verify once for all files
        kwargs["residual"] = load_residual(kwargs["residual"], model)
    return [
        estimate_file(f, model, o, device=str(model.device), **kwargs)
        for f, o in zip(files, outs, strict=True)
    ]
