"""Fit a correction stack, choose its layers on validation blocks, report, save one checkpoint.

One split (:func:`fit_split`): on the training blocks' contact-free frames fit the constant
offset, the offset plus re-identified inertial parameters (:mod:`training.baselines`), and the
learned layer on what each physics layer leaves; each candidate stack is a
:class:`~torchcontact.residual.ResidualCorrection`, evaluated by the same code that
``torchcontact estimate --residual`` runs; the stack with the lowest error on the validation
blocks is chosen (``layers = "auto"``) unless the configuration names the layers.

Reports (:func:`cross_validate`): K-fold cross-validation over contiguous time blocks, so every
block is held out exactly once and every contact-free frame is scored out of sample: per axis
F/T residual of each candidate and baseline, and on simulated logs the contact-force errors. The
checkpoint itself is fitted on all blocks (:func:`train`).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

import torchcontact as tc
from torchcontact.errors import LogError
from torchcontact.residual import FeatureSpec, ResidualCorrection, sensor_joints
from torchcontact.simulation import UnmodeledEffects, simulate

from .baselines import RegressorBlocks, fit_inertial, fit_offset, predict_free
from .data import ResidualDataset, Split, fold_splits, load_parquet, split_blocks, time_blocks
from .evaluate import AXES, contact_metrics, residual_rmse
from .fit import FitResult, TrainConfig, fit_residual, predict_residual

#: Report labels of the methods (a stack is named by its layers joined with "+").
METHODS = {
    "none": "no correction",
    "offset": "constant offset",
    "offset+inertial": "offset + inertial LS",
    "offset+mlp": "offset + MLP",
    "offset+inertial+mlp": "offset + inertial + MLP",
    "offset+gru": "offset + GRU",
    "offset+inertial+gru": "offset + inertial + GRU",
    "mlp": "MLP alone",
    "gru": "GRU alone",
    "stack": "chosen stack",
    "oracle": "oracle (true effects removed)",
}
CLASSICAL = ("offset", "offset+inertial")


# ---------------------------------------------------------------------- configuration
@dataclass
class DataConfig:
    """The ``[data]`` table: where frames come from and how they are cut into blocks.

    Attributes:
        source: ``"parquet"`` (``paths``, logs in the documented format) or ``"simulate"``.
        paths: Parquet logs.
        robot: ``"tcarm"`` (bundled), ``"icub"`` (iCubGenova04 of icub-models) or a URDF path.
        sensor: the F/T sensor (default: the robot's first).
        extra: extra logged columns used as features (e.g. ``temperature``).
        frames: simulated frames.
        seed: simulation and split seed.
        rate_hz: simulated frame rate, Hz.
        force_max: simulated peak contact force, N.
        block_seconds: length of the contiguous time blocks of every split, s.
        folds: cross-validation folds of the report (0: no report).
        val_fraction: share of the non-test blocks that validate (early stopping, layer choice).
        effects: simulated unmodeled effects (:class:`~torchcontact.simulation.UnmodeledEffects`).
        bias_time_constant: s; > 0 smooths each log's F/T offset drift out of the residuals
            before any layer is fitted (:func:`smooth_drift`: the tracker and smoother of
            ``estimate --track-bias``), so the stack does not learn a session's drift; 0: off.
    """

    source: str = "simulate"
    paths: list[str] = field(default_factory=list)
    robot: str = "tcarm"
    sensor: str = ""
    extra: list[str] = field(default_factory=lambda: ["temperature"])
    frames: int = 24000
    seed: int = 0
    rate_hz: float = 100.0
    force_max: float = 20.0
    block_seconds: float = 10.0
    folds: int = 5
    val_fraction: float = 0.2
    effects: dict[str, Any] = field(default_factory=dict)
    bias_time_constant: float = 0.0


@dataclass
class FeatureConfig:
    """The ``[features]`` table: inputs of the learned layer (:class:`FeatureSpec`).

    Attributes:
        joints: ``"sensor"`` (the joints that can move the sensor or its load,
            :func:`~torchcontact.residual.sensor_joints`), ``"all"``, or a list of names.
        angles: ``"sincos"`` or ``"raw"``.
        velocities: joint velocities.
        accelerations: joint accelerations.
        nominal: the nominal contact-free wrench of the model.
    """

    joints: Any = "sensor"
    angles: str = "sincos"
    velocities: bool = True
    accelerations: bool = False
    nominal: bool = True

    def spec(self, model: tc.RobotModel, sensor: str, extra: list[str]) -> FeatureSpec:
        """The :class:`FeatureSpec` for a robot and sensor."""
        if self.joints == "sensor":
            joints = sensor_joints(model, sensor)
        elif self.joints == "all":
            joints = list(model.joint_names)
        elif isinstance(self.joints, list):
            joints = list(self.joints)
        else:
            raise ValueError(
                f"features.joints must be 'sensor', 'all' or a list, got {self.joints!r}"
            )
        return FeatureSpec(
            tuple(joints),
            angles=self.angles,
            velocities=self.velocities,
            accelerations=self.accelerations,
            nominal=self.nominal,
            extra=tuple(extra),
        )


@dataclass
class StackConfig:
    """The ``[stack]`` table: which layers.

    Attributes:
        layers: ``"auto"`` (choose among offset, offset + inertial, each with and without the
            learned layer, on the validation blocks) or a list such as
            ``["offset", "inertial", "mlp"]``.
        rcond: singular-value threshold of the identifiable inertial directions.
        inertial_rank: fixed truncation rank (None: chosen on the validation blocks).
    """

    layers: Any = "auto"
    rcond: float = 1e-7
    inertial_rank: int | None = None

    def candidates(self, kind: str) -> list[str]:
        """Stacks to fit, by name (``"offset+inertial+mlp"``)."""
        if self.layers == "auto":
            return ["offset", "offset+inertial", f"offset+{kind}", f"offset+inertial+{kind}"]
        if not isinstance(self.layers, list) or not self.layers:
            raise ValueError(f"stack.layers must be 'auto' or a list, got {self.layers!r}")
        order = ("offset", "inertial", "mlp", "gru")
        bad = [x for x in self.layers if x not in order]
        if bad or ("mlp" in self.layers and "gru" in self.layers):
            raise ValueError(f"stack.layers {self.layers}: from {list(order)}, one learned layer")
        layers = [x for x in order if x in self.layers]
        if "inertial" in layers and "offset" not in layers:
            layers.insert(0, "offset")  # the inertial layer is fitted with its offset
        return ["+".join(layers)]


@dataclass
class Config:
    """A whole training configuration: the TOML tables and their defaults."""

    data: DataConfig = field(default_factory=DataConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    stack: StackConfig = field(default_factory=StackConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_json(self) -> dict:
        """JSON-ready dictionary."""
        return {
            "data": asdict(self.data),
            "features": asdict(self.features),
            "stack": asdict(self.stack),
            "train": asdict(self.train),
        }


def _toml_loads(text: str) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    return tomllib.loads(text)


def load_config(path: str | Path) -> tuple[Config, dict]:
    """Read a TOML config (``tomllib`` on Python 3.11+, ``tomli`` before).

    Tables: ``[data]`` (with ``[data.effects]``), ``[features]``, ``[stack]``, ``[model]``,
    ``[train]``.

    Raises:
        ValueError: an unknown table or key (the message names it).
    """
    raw = _toml_loads(Path(path).read_text())
    unknown = set(raw) - {"data", "features", "stack", "model", "train"}
    if unknown:
        raise ValueError(
            f"{path}: unknown tables {sorted(unknown)} (data, features, stack, model, train)"
        )
    try:
        cfg = Config(
            data=DataConfig(**raw.get("data", {})),
            features=FeatureConfig(**raw.get("features", {})),
            stack=StackConfig(**raw.get("stack", {})),
            train=TrainConfig(**raw.get("model", {}), **raw.get("train", {})),
        )
    except TypeError as e:
        raise ValueError(f"{path}: {e}") from None
    return cfg, raw


def make_dataset(model: tc.RobotModel, cfg: DataConfig, sensor: str) -> ResidualDataset:
    """Simulate (with ``cfg.effects``) or load Parquet files (joints mapped by name)."""
    if cfg.source == "simulate":
        log = simulate(
            model,
            cfg.frames,
            sensor=sensor,
            seed=cfg.seed,
            rate_hz=cfg.rate_hz,
            force_max=cfg.force_max,
            effects=UnmodeledEffects(**cfg.effects),
        )
        return ResidualDataset.from_simulated(log, cfg.extra)
    if cfg.source == "parquet":
        return load_parquet(cfg.paths, model, sensor, cfg.extra)
    raise ValueError(f"data.source must be 'simulate' or 'parquet', got {cfg.source!r}")


# ---------------------------------------------------------------------- fitting
@dataclass
class Prepared:
    """What every split of one dataset shares: residual, features, reduced regressor blocks."""

    model: tc.RobotModel
    ds: ResidualDataset
    residual: np.ndarray
    features: np.ndarray
    spec: FeatureSpec
    blocks: list[tuple[int, int]]
    regressor: RegressorBlocks | None
    scale: np.ndarray

    def block_ids(self, blocks: list[tuple[int, int]]) -> list[int]:
        """Indices into :attr:`blocks` of the given blocks."""
        pos = {b: i for i, b in enumerate(self.blocks)}
        return [pos[b] for b in blocks]


def block_frames(ds: ResidualDataset, seconds: float) -> int:
    """Frames per block of ``seconds`` at the dataset's median frame rate."""
    dt = np.diff(ds.t_ns)
    dt = dt[(np.diff(ds.file_id) == 0) & (dt > 0)]
    rate = 1e9 / float(np.median(dt)) if len(dt) else 100.0
    return max(1, int(round(seconds * rate)))


#: Fewest usable contact-free frames a fit accepts: a floor, not a sufficiency. Below it no
#: layer is determined well enough for the report to mean anything (each fold fits on about
#: half of them; the learned layer has thousands of parameters, the offset alone 6).
MIN_FIT_FRAMES = 100


def _data_of(ds: ResidualDataset) -> str:
    """The data's logs, for messages (``the data`` when simulated)."""
    names = [Path(s["path"]).name for s in ds.sources or () if s.get("path")]
    if not names:
        return "the data"
    return ", ".join(names) if len(names) <= 3 else f"{len(names)} logs"


def check_data(ds: ResidualDataset, cfg: Config) -> None:
    """Enough data for a fit (and its cross-validated report), before any work is done.

    A fit needs :data:`MIN_FIT_FRAMES` usable contact-free frames (finite joint state, reading
    and extra columns, no contact: the only fitting targets), and whole time blocks of
    ``block_seconds``: 3 for the final fit (training, validation and the rule that deals one
    block to each split), ``folds + 2`` for a ``folds``-fold report.

    Raises:
        LogError: naming the minimum and what the data has.
    """
    n, targets = len(ds), int(ds.targets.sum())
    free, usable = int(ds.contact_free.sum()), int(ds.usable.sum())
    data = _data_of(ds)
    if targets < MIN_FIT_FRAMES:
        raise LogError(
            f"train fit needs at least {MIN_FIT_FRAMES} usable contact-free frames (finite joint"
            f" state, reading and extra columns, and no contact): {data} has {targets} of {n}"
            f" frames ({free} contact-free, {usable} usable)"
        )
    folds = cfg.data.folds
    bf = block_frames(ds, cfg.data.block_seconds)
    blocks = len(time_blocks(ds.file_id, bf))
    need = folds + 2 if folds >= 2 else 3
    if blocks < need:
        why = (f"{folds}-fold cross-validation needs folds + 2" if folds >= 2
               else "a fit needs training and validation blocks")  # fmt: skip
        hint = "fewer --folds (0: no report), " if folds >= 2 else ""
        raise LogError(
            f"train fit needs at least {need} blocks of {cfg.data.block_seconds:g} s ({bf} frames"
            f" each, so at least {(need - 1) * bf + 1} frames; {why}): {data} has {n} frames"
            f" ({blocks} block{'s' if blocks != 1 else ''}), {targets} of them usable and"
            f" contact-free; give more data, {hint}or shorter blocks (data.block_seconds in the"
            " config)"
        )


def prepare(model: tc.RobotModel, ds: ResidualDataset, cfg: Config) -> Prepared:
    """Residual of the nominal model, learned-layer features and the regressor's block factors.

    Raises:
        ValueError: the dataset's joints are not the model's.
        LogError: fewer than :data:`MIN_FIT_FRAMES` usable contact-free frames.
    """
    if tuple(ds.joint_names) != tuple(model.joint_names):
        raise ValueError(f"dataset joints {ds.joint_names} != model joints {model.joint_names}")
    targets = int(ds.targets.sum())
    if targets < MIN_FIT_FRAMES:
        raise LogError(
            f"a fit needs at least {MIN_FIT_FRAMES} usable contact-free frames; {_data_of(ds)}"
            f" has {targets} of {len(ds)}"
        )
    blocks = time_blocks(ds.file_id, block_frames(ds, cfg.data.block_seconds))
    nominal = predict_free(model, ds.sensor, ds.q, ds.qd, ds.qdd, ds.usable)
    residual = ds.ft - nominal
    if cfg.data.bias_time_constant > 0:  # the sessions' drift out, before any layer is fitted
        residual = residual - smooth_drift(ds, residual, cfg.data.bias_time_constant)
    spec = cfg.features.spec(model, ds.sensor, list(ds.extra))
    features = feature_matrix(model, ds, spec)
    needs_inertial = any("inertial" in c for c in cfg.stack.candidates(cfg.train.kind))
    rb = RegressorBlocks.build(model, ds, residual, blocks) if needs_inertial else None
    scale = residual[ds.targets].std(0)
    scale[scale < 1e-9] = 1.0
    return Prepared(model, ds, residual, features, spec, blocks, rb, scale)


def smooth_drift(ds: ResidualDataset, residual: np.ndarray, time_constant: float) -> np.ndarray:
    """Each log's slow F/T offset drift, about its mean (``train fit`` bias smoothing).

    Per file, :func:`torchcontact.online.bias.smooth_bias` (the filter and RTS smoother of
    ``estimate --track-bias``, the same code) over its contact-free usable frames measures the
    offset of ``residual``; its mean over those frames is taken off, so the stack's offset
    layer still holds the mean and only the drift about it leaves the targets. The time
    constant should be long against the motion (tens of seconds): what changes faster, the
    pose-dependent effects the inertial and learned layers model, stays in the residual.

    Args:
        ds: the frames (``file_id``, ``t_ns``, ``targets``).
        residual: ``(N, 6)`` ``ft - nominal`` [N; N m].
        time_constant: s (> 0).

    Returns:
        ``(N, 6)`` the drift to subtract (zero for a file without contact-free frames).
    """
    from torchcontact.online.bias import smooth_bias

    drift = np.zeros_like(residual)
    free = ds.targets
    for f in np.unique(ds.file_id):
        rows = np.flatnonzero(ds.file_id == f)
        if not free[rows].any():
            continue
        # time stamps that go back (a log's glitch) are held: the filter needs them monotonic
        t = np.maximum.accumulate(ds.t_ns[rows].astype(np.int64)) * 1e-9
        track = smooth_bias(residual[rows], free[rows], t - t[0], time_constant=time_constant)
        off = track.offset[:, 0]
        drift[rows] = off - off[free[rows]].mean(0)
    return drift


def feature_matrix(
    model: tc.RobotModel, ds: ResidualDataset, spec: FeatureSpec, chunk: int = 16384
) -> np.ndarray:
    """``(N, F)`` learned-layer features of every frame, by the correction's own code.

    Frames that are not usable get NaN.
    """
    g = ResidualCorrection(model, ds.sensor, features=spec).graph
    out = np.full((len(ds), len(spec.names(model))), np.nan)
    idx = np.flatnonzero(ds.usable)
    for s in range(0, len(idx), chunk):
        sel = idx[s : s + chunk]
        t = [torch.as_tensor(x[sel], dtype=model.dtype) for x in (ds.q, ds.qd, ds.qdd)]
        ex = (
            torch.as_tensor(np.stack([ds.extra[c][sel] for c in spec.extra], -1), dtype=model.dtype)
            if spec.extra
            else None
        )
        with torch.no_grad():
            _, nominal = g.physics(*t)
            out[sel] = g.feature_matrix(*t, ex, nominal).numpy()
    return out


def predict(
    corr: ResidualCorrection, ds: ResidualDataset, blocks: list[tuple[int, int]]
) -> np.ndarray:
    """Correction ``(N, 6)`` on the frames of ``blocks`` (NaN elsewhere and on unusable frames).

    A GRU runs each block as one sequence from a zero state, as after a restart on the robot.
    """
    out = np.full((len(ds), 6), np.nan)
    m = corr.model
    for s, e in _merge(blocks) if not corr.recurrent else blocks:
        t = [torch.as_tensor(x[s:e], dtype=m.dtype) for x in (ds.q, ds.qd, ds.qdd)]
        corr.reset()
        extra = {c: ds.extra[c][s:e] for c in corr.extra_columns}
        out[s:e] = corr.correction(*t, extra).numpy()
    corr.reset()
    return out


def _merge(blocks: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Adjacent blocks merged (fewer calls for frame-wise corrections)."""
    out: list[tuple[int, int]] = []
    for s, e in sorted(blocks):
        if out and out[-1][1] == s:
            out[-1] = (out[-1][0], e)
        else:
            out.append((s, e))
    return out


@dataclass
class SplitResult:
    """The candidates of one split, their predictions, validation scores and the choice."""

    corrections: dict[str, ResidualCorrection]
    predictions: dict[str, np.ndarray]
    val_score: dict[str, float]
    chosen: str
    fits: dict[str, FitResult]
    inertial: dict[str, Any]
    seconds: float


def score(prep: Prepared, pred: np.ndarray, frames: np.ndarray) -> float:
    """Mean over axes of the squared residual left on ``frames``, each axis over its variance."""
    err = (prep.residual[frames] - pred[frames]) / prep.scale
    return float(np.mean(err**2)) if len(frames) else float("nan")


def _mask(n: int, blocks: list[tuple[int, int]]) -> np.ndarray:
    out = np.zeros(n, bool)
    for s, e in blocks:
        out[s:e] = True
    return out


def _frames(prep: Prepared, blocks: list[tuple[int, int]]) -> np.ndarray:
    idx = np.concatenate([np.arange(s, e) for s, e in blocks]) if blocks else np.zeros(0, int)
    return idx[prep.ds.targets[idx]]


def fit_split(
    prep: Prepared, split: Split, cfg: Config, device: str = "cpu", label: str = ""
) -> SplitResult:
    """Fit every candidate stack on ``split``'s training blocks; choose one on its validation.

    Returns:
        :class:`SplitResult`; predictions cover the validation and test blocks (physics layers:
        every frame).
    """
    t0 = time.perf_counter()
    model, ds = prep.model, prep.ds
    names = cfg.stack.candidates(cfg.train.kind)
    tr, va = _frames(prep, split.blocks["train"]), _frames(prep, split.blocks["val"])
    if not len(tr):
        raise LogError(
            f"{label.strip() or 'the fit'}: its training blocks hold no usable contact-free frame"
            f" ({int(prep.ds.targets.sum())} in the whole data, all in other blocks): give more"
            " data, fewer folds or shorter blocks"
        )
    everywhere = _merge(prep.blocks)
    held = split.blocks["val"] + split.blocks["test"]
    corr: dict[str, ResidualCorrection] = {}
    pred: dict[str, np.ndarray] = {}
    fits: dict[str, FitResult] = {}
    inertial: dict[str, Any] = {}
    # physics layers, fitted in closed form (also when only needed as baselines of the report)
    corr["offset"] = ResidualCorrection(
        model, ds.sensor, offset=torch.as_tensor(fit_offset(prep.residual, tr))
    )
    if prep.regressor is not None:
        fit = fit_inertial(
            prep.regressor,
            prep.block_ids(split.blocks["train"]),
            prep.block_ids(split.blocks["val"]),
            rcond=cfg.stack.rcond,
            rank=cfg.stack.inertial_rank,
        )
        corr["offset+inertial"] = ResidualCorrection(
            model,
            ds.sensor,
            offset=torch.as_tensor(fit.offset),
            inertial_bodies=tuple(model.body_names[b] for b in fit.bodies),
            delta=torch.as_tensor(fit.delta),
            meta={"inertial": fit.info()},
        )
        inertial = fit.info()
    for name in list(corr):
        pred[name] = predict(corr[name], ds, everywhere)
    # learned layers on what each physics layer leaves
    for name in names:
        if name in corr:
            continue
        layers = name.split("+")
        base = "+".join(x for x in layers if x in ("offset", "inertial"))
        phys = pred[base] if base else np.zeros_like(prep.residual)
        res = fit_residual(
            prep.features,
            prep.residual - phys,
            prep.ds.targets,
            split.blocks["train"],
            split.blocks["val"],
            cfg.train,
            device,
            desc=f"{label} {name}",
        )
        fits[name] = res
        b = corr.get(base)
        corr[name] = ResidualCorrection(
            model,
            ds.sensor,
            offset=None if b is None else b.offset,
            inertial_bodies=() if b is None else b.inertial_bodies,
            delta=None if b is None else b.delta,
            learned=res.module,
            features=prep.spec,
            meta={"inertial": inertial} if b is not None and b.delta is not None else {},
        )
        # the stack's correction on the held-out blocks: physics + network(features), the same
        # numbers as corr[name].correction (checked on the checkpoint in train), without
        # recomputing the regressor
        learned = predict_residual(res.module, prep.features, held)
        pred[name] = np.where(_mask(len(ds), held)[:, None], phys + learned, np.nan)
    val = {n: score(prep, pred[n], va) for n in corr}
    allowed = [n for n in names if n in corr]
    chosen = min(allowed, key=lambda n: val[n] if np.isfinite(val[n]) else np.inf)
    return SplitResult(corr, pred, val, chosen, fits, inertial, time.perf_counter() - t0)


# ---------------------------------------------------------------------- reports
@dataclass
class Report:
    """Out-of-sample predictions of every method over all folds, and their scores."""

    predictions: dict[str, np.ndarray]
    chosen: list[str]
    metrics: dict[str, dict[str, float]]
    folds: int
    seconds: float


def cross_validate(
    prep: Prepared, cfg: Config, device: str = "cpu", label: str = "", contacts: bool = True
) -> Report:
    """K-fold cross-validation over contiguous time blocks: every block is tested once.

    Every method is refitted in each fold; ``stack`` is the candidate chosen on that fold's
    validation blocks. Scores: per axis F/T residual on all contact-free frames (every one out of
    sample) and, with ground truth and ``contacts``, the contact-force errors of all contact frames.
    """
    t0 = time.perf_counter()
    ds = prep.ds
    bf = block_frames(ds, cfg.data.block_seconds)
    splits = fold_splits(ds.file_id, bf, cfg.data.folds, cfg.data.val_fraction, cfg.data.seed)
    preds: dict[str, np.ndarray] = {}
    chosen = []
    for k, sp in enumerate(splits):
        r = fit_split(prep, sp, cfg, device, label=f"{label} fold {k + 1}/{len(splits)}")
        chosen.append(r.chosen)
        te = np.concatenate([np.arange(s, e) for s, e in sp.blocks["test"]])
        for name, p in {**r.predictions, "stack": r.predictions[r.chosen]}.items():
            preds.setdefault(name, np.full((len(ds), 6), np.nan))[te] = p[te]
    preds["none"] = np.zeros((len(ds), 6))
    if "ft_effects" in ds.truth:
        preds["oracle"] = ds.truth["ft_effects"]
    metrics = score_methods(prep, preds, contacts=contacts)
    return Report(preds, chosen, metrics, len(splits), time.perf_counter() - t0)


def score_methods(
    prep: Prepared, preds: dict[str, np.ndarray], contacts: bool = True
) -> dict[str, dict[str, float]]:
    """Per method: residual RMS per axis on contact-free frames, contact errors with truth."""
    ds = prep.ds
    free = np.flatnonzero(ds.targets)
    contact = np.flatnonzero(~ds.contact_free & ds.usable)
    est = tc.ContactEstimator(prep.model, [ds.sensor]) if ds.truth and contacts else None
    out: dict[str, dict[str, float]] = {}
    for name in [m for m in METHODS if m in preds]:
        p = preds[name]
        row = residual_rmse(prep.residual[free] - p[free])
        if est is not None and len(contact):
            truth = {k: v[contact] for k, v in ds.truth.items() if k not in ("links",)}
            truth["links"] = ds.truth["links"]
            row.update(
                contact_metrics(
                    est,
                    ds.q[contact],
                    ds.qd[contact],
                    ds.qdd[contact],
                    ds.ft[contact] - p[contact],
                    truth,
                    ds.sensor,
                )
            )
        out[name] = row
    return out


def table_markdown(results: dict[str, dict[str, dict[str, float]]], contacts: bool = True) -> str:
    """Markdown table: one row per (condition, method)."""
    cols = []
    if contacts:
        cols += [
            ("force_rmse", "force RMSE 1c (N)"),
            ("force_rmse_2c", "force RMSE 2c (N)"),
            ("moment_rmse", "moment RMSE 1c (N m)"),
        ]
    cols += [(f"rms.{a}", f"free {a}") for a in AXES]
    cols += [
        ("residual_force_rms", "free \\|F\\| (N)"),
        ("residual_moment_rms", "free \\|M\\| (N m)"),
    ]
    lines = ["| condition | method | " + " | ".join(c[1] for c in cols) + " |"]
    lines.append("|---|---|" + "---:|" * len(cols))
    for cond, rows in results.items():
        for m, row in rows.items():
            vals = " | ".join(f"{row.get(k, float('nan')):.3f}" for k, _ in cols)
            lines.append(f"| {cond} | {METHODS.get(m, m)} | {vals} |")
    return "\n".join(lines)


# ---------------------------------------------------------------------- the train command
@dataclass
class Trained:
    """Result of :func:`train`: the checkpoint's correction, the final split, the report."""

    correction: ResidualCorrection
    final: SplitResult
    report: Report | None
    prep: Prepared
    seconds: float


def train(
    model: tc.RobotModel,
    ds: ResidualDataset,
    cfg: Config,
    out: str | Path | None = None,
    device: str = "cpu",
    label: str = "train",
    contacts: bool = True,
) -> Trained:
    """Cross-validated report, then the correction fitted on all blocks; optionally saved.

    The final stack is fitted with ``val_fraction`` of all blocks for validation (early
    stopping, layer and rank choice) and the rest for training; with ``layers = "auto"`` its
    layers are chosen there.

    Args:
        model: the robot.
        ds: the frames.
        cfg: the configuration.
        out: checkpoint directory to write (with ``report.md``, ``report.json`` and plots).
        device: where the learned layer trains.
        label: progress label.
        contacts: with ground truth, also estimate the contact forces in the report.

    Returns:
        :class:`Trained`.

    Raises:
        LogError: too little usable data (:func:`check_data`).
    """
    t0 = time.perf_counter()
    check_data(ds, cfg)
    prep = prepare(model, ds, cfg)
    report = (
        cross_validate(prep, cfg, device, label, contacts=contacts) if cfg.data.folds >= 2 else None
    )
    fractions = (1.0 - cfg.data.val_fraction, cfg.data.val_fraction, 0.0)
    split = split_blocks(
        ds.file_id, block_frames(ds, cfg.data.block_seconds), fractions, cfg.data.seed
    )
    final = fit_split(prep, split, cfg, device, label=f"{label} final")
    corr = final.corrections[final.chosen]
    _check_prediction(corr, ds, final.predictions[final.chosen], split.blocks["val"][:1])
    # the range of each feature the learned layer saw (estimate --residual flags frames beyond)
    sel = ds.targets
    corr.record_ranges(ds.q[sel], ds.qd[sel], ds.qdd[sel], {k: v[sel] for k, v in ds.extra.items()})
    seconds = time.perf_counter() - t0
    corr.meta.update(
        urdf=_urdf_of(model, cfg.data.robot),
        data_sha256=ds.sha256(),
        data=summary(ds),
        config=cfg.to_json(),
        validation={n: final.val_score[n] for n in final.corrections},
        chosen=final.chosen,
        report=None if report is None else report_json(report),
        torch_version=torch.__version__,
        seconds=seconds,
    )
    if final.chosen in final.fits:
        f = final.fits[final.chosen]
        corr.meta.update(train_loss=f.train_loss, val_loss=f.val_loss, best_epoch=f.best_epoch)
    trained = Trained(corr, final, report, prep, seconds)
    if out is not None:
        write_outputs(trained, Path(out))
    return trained


def _check_prediction(
    corr: ResidualCorrection, ds: ResidualDataset, pred: np.ndarray, blocks: list[tuple[int, int]]
) -> None:
    """The checkpoint's own correction reproduces the numbers the layers were chosen on."""
    got = predict(corr, ds, blocks)
    sel = _mask(len(ds), blocks) & ds.usable
    scale = max(1.0, float(np.abs(pred[sel]).max())) if sel.any() else 1.0
    err = float(np.abs(got[sel] - pred[sel]).max()) if sel.any() else 0.0
    if not err <= 1e-5 * scale:
        raise RuntimeError(f"the saved stack differs from its validated predictions by {err:.3g}")


def _urdf_of(model: tc.RobotModel, robot: str) -> str | None:
    """The resolved URDF path of ``robot`` when it is ``model``'s (same text hash), else None."""
    import hashlib

    from torchcontact.robots import robot_urdf

    try:
        path = robot_urdf(robot)
    except ValueError:
        return None
    digest = hashlib.sha256(path.read_text().encode()).hexdigest()
    return str(path.resolve()) if digest == model.urdf_sha256 else None


def summary(ds: ResidualDataset) -> dict:
    """Frame counts of a dataset (recorded with the checkpoint)."""
    return {
        "frames": len(ds),
        "contact_free": int(ds.contact_free.sum()),
        "unusable": int((~ds.usable).sum()),
        "targets": int(ds.targets.sum()),
        "sensor": ds.sensor,
        "extra": list(ds.extra),
        "files": ds.sources,
    }


def report_json(report: Report) -> dict:
    """JSON-ready report."""
    return {
        "folds": report.folds,
        "chosen_per_fold": report.chosen,
        "metrics": report.metrics,
        "seconds": report.seconds,
        "note": "every block held out once (K-fold over contiguous time blocks); free = residual"
        " left on contact-free frames, per axis (N, N m)",
    }


def report_markdown(trained: Trained) -> str:
    """The report as Markdown (``report.md``)."""
    corr, ds = trained.correction, trained.prep.ds
    s = summary(ds)
    lines = [
        f"# Correction of `{ds.sensor}` on {trained.prep.model.name}",
        "",
        f"Checkpoint stack: `{'+'.join(corr.layers)}` (chosen on the validation blocks among"
        f" {list(trained.final.val_score)}). Frames: {s['frames']}, contact-free"
        f" {s['contact_free']}, unusable (non-finite or malformed) {s['unusable']}.",
        "",
    ]
    if corr.delta is not None:
        info = trained.final.inertial
        lines += [
            f"Inertial layer: {info['rank']} of {info['identifiable']} identifiable directions"
            f" fitted ({info['unknowns']} unknowns: 6 offset + 10 per body of"
            f" {list(corr.inertial_bodies)}); the other directions keep the URDF values.",
            "",
        ]
    lines += workspace_markdown(corr, ds)
    if trained.report is not None:
        r = trained.report
        contacts = any("force_rmse" in row for row in r.metrics.values())
        lines += [
            f"Cross-validated ({r.folds} folds over {trained.prep.ds.sensor}'s contiguous time"
            " blocks, every block held out once; `stack` = the candidate chosen in each fold:"
            f" {r.chosen}). `free` columns: RMS of the residual each method leaves on the"
            " held-out contact-free frames, per axis.",
            "",
            table_markdown({"held out": r.metrics}, contacts=contacts),
        ]
    return "\n".join(lines) + "\n"


def workspace_markdown(corr: ResidualCorrection, ds: ResidualDataset) -> list[str]:
    """The report's training-range section: what the learned layer saw, how to cover the rest.

    Per joint of the learned layer's features the range of ``q`` over the contact-free frames
    it was trained on, against the URDF limits; frames beyond the recorded feature ranges get
    status bit ``OUTSIDE_TRAINING`` (1024) in ``estimate --residual``.
    """
    if corr.features is None or corr.meta.get("feature_ranges") is None:
        return []
    model = corr.model
    sel = ds.targets
    limits = model.joint_limits
    rows, coverage = [], []
    for j in corr.features.joints:
        i = list(model.joint_names).index(j)
        q = ds.q[sel, i]
        q = q[np.isfinite(q)]
        if not len(q):
            continue
        lo_l = float(limits["lower"][i]) if "lower" in limits else float("nan")
        hi_l = float(limits["upper"][i]) if "upper" in limits else float("nan")
        span = hi_l - lo_l
        cov = (q.max() - q.min()) / span if np.isfinite(span) and span > 0 else float("nan")
        coverage.append((cov, j, lo_l, hi_l))
        share = "-" if not np.isfinite(cov) else f"{100 * cov:.0f} %"
        rows.append(
            f"| {j} | {q.min():.3f} .. {q.max():.3f} | {lo_l:.3f} .. {hi_l:.3f} | {share} |"
        )
    lines = [
        "## Training range",
        "",
        "The learned layer saw these joint positions (contact-free training frames). Its checkpoint"
        " records the range of every feature (`feature_ranges` in `checkpoint.json`);"
        " `torchcontact estimate --residual` gives frames beyond them (with a 5 % margin) status"
        " bit 1024 (`outside_training`, outputs kept) and counts them in its summary"
        " (`outside_training`): there the network extrapolates.",
        "",
        "| joint | trained q (rad or m) | URDF limits | share of the limits |",
        "|---|---|---|---|",
        *rows,
        "",
    ]
    narrow = sorted(c for c in coverage if np.isfinite(c[0]) and c[0] < 0.8)
    if narrow:
        names = ", ".join(f"`{j}` ({100 * c:.0f} %)" for c, j, _, _ in narrow[:4])
        lines += [
            f"To cover the workspace: record contact-free motion that sweeps {names} over their"
            " limits (at the speeds and temperatures the robot meets), then fit again on all the"
            " logs together (`torchcontact train fit --log old.parquet new.parquet ...`, or list"
            " them in the config); `estimate --residual`'s"
            " `outside_training` count tells which logs still leave the range.",
            "",
        ]
    else:
        lines += [
            "The training frames span most of each joint's limits. Frames still flagged by"
            " `estimate --residual` differ in velocity, load or an extra column: record"
            " contact-free motion in those conditions and fit again on all the logs.",
            "",
        ]
    return lines


def write_outputs(trained: Trained, out: Path) -> None:
    """Checkpoint, ``report.md``, ``report.json`` and plots into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    trained.correction.save(out)
    (out / "report.md").write_text(report_markdown(trained))
    write_json(
        out / "report.json",
        {
            "stack": trained.correction.layers,
            "data": summary(trained.prep.ds),
            "validation": trained.final.val_score,
            "report": None if trained.report is None else report_json(trained.report),
            "seconds": trained.seconds,
        },
    )
    plot(trained, out)


def plot(trained: Trained, out: Path) -> None:
    """``loss.png`` (learned layers of the final fit) and ``residual.png`` (held out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if trained.final.fits:
        fig, ax = plt.subplots(figsize=(6, 4))
        for name, f in trained.final.fits.items():
            (line,) = ax.semilogy(f.train_loss, label=f"{METHODS.get(name, name)} train")
            ax.semilogy(f.val_loss, "--", color=line.get_color(), label=f"{name} val")
        ax.set_xlabel("epoch")
        ax.set_ylabel("normalised MSE")
        ax.set_title("learned layers: loss")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "loss.png", dpi=110)
        plt.close(fig)
    if trained.report is None:
        return
    ds, prep = trained.prep.ds, trained.prep
    t = (ds.t_ns - ds.t_ns[0]) * 1e-9
    free = np.flatnonzero(ds.targets)
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for name, p in trained.report.predictions.items():
        if name == "oracle":
            continue
        r = prep.residual[free] - p[free]
        label = METHODS.get(name, name)
        axes[0].plot(t[free], np.linalg.norm(r[:, :3], axis=1), ".", ms=1, label=label)
        axes[1].plot(t[free], np.linalg.norm(r[:, 3:], axis=1), ".", ms=1)
    axes[0].set_ylabel("|residual force| (N)")
    axes[1].set_ylabel("|residual moment| (N m)")
    axes[1].set_xlabel("time (s), contact-free frames, each predicted by the fold that held it out")
    axes[0].set_title(f"{ds.sensor}: residual after each correction")
    axes[0].legend(fontsize=7, markerscale=6)
    fig.tight_layout()
    fig.savefig(out / "residual.png", dpi=110)
    plt.close(fig)


def write_json(path: Path, obj: Any) -> None:
    """JSON with NaN written as null."""
    from torchcontact.residual import _json_clean

    path.write_text(json.dumps(_json_clean(obj), indent=2) + "\n")


def log(msg: str) -> None:
    """Progress line on stderr."""
    print(msg, file=sys.stderr, flush=True)
