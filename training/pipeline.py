"""Experiments: fit every correction on one dataset, evaluate, write checkpoint, table, plots."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

import torchcontact as tc
from torchcontact.residual import load_residual_model, save_residual_model
from torchcontact.simulation import UnmodeledEffects, simulate

from .baselines import InertialLeastSquares, inertial_regressor, predict_free
from .data import ResidualDataset, Split, load_parquet, split_blocks
from .evaluate import contact_metrics, residual_rmse
from .fit import FitResult, TrainConfig, fit_residual, predict_residual

METHODS = {
    "a": "(a) no correction",
    "b": "(b) constant offset",
    "c": "(c) offset + inertial LS",
    "d_mlp": "(d) MLP",
    "d_mlp_c": "(d) MLP on (c)",
    "d_gru": "(d) GRU",
}


@dataclass
class DataConfig:
    """The ``[data]`` table: where frames come from and how they are split."""

    source: str = "simulate"  # "simulate" or "parquet"
    paths: list[str] = field(default_factory=list)
    sensor: str = "base_ft"
    extra: list[str] = field(default_factory=lambda: ["temperature"])
    frames: int = 24000
    seed: int = 0
    block_seconds: float = 10.0
    rate_hz: float = 100.0
    fractions: tuple[float, float, float] = (0.6, 0.2, 0.2)
    effects: dict[str, Any] = field(default_factory=dict)


def load_config(path: str | Path) -> tuple[DataConfig, TrainConfig, dict]:
    """Read a TOML config with ``[data]``, ``[data.effects]``, ``[model]`` and ``[train]``."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]

    raw = tomllib.loads(Path(path).read_text())
    unknown = set(raw) - {"data", "model", "train"}
    if unknown:
        raise ValueError(f"{path}: unknown tables {sorted(unknown)} (data, model, train)")
    data = DataConfig(**raw.get("data", {}))
    train = TrainConfig(**raw.get("model", {}), **raw.get("train", {}))
    return data, train, raw


def make_dataset(model: tc.RobotModel, cfg: DataConfig) -> ResidualDataset:
    """Simulate (with ``cfg.effects``) or load Parquet files."""
    if cfg.source == "simulate":
        log = simulate(
            model,
            cfg.frames,
            sensor=cfg.sensor,
            seed=cfg.seed,
            rate_hz=cfg.rate_hz,
            effects=UnmodeledEffects(**cfg.effects),
        )
        return ResidualDataset.from_simulated(log, cfg.extra)
    if cfg.source == "parquet":
        return load_parquet(cfg.paths, cfg.sensor, cfg.extra)
    raise ValueError(f"data.source must be 'simulate' or 'parquet', got {cfg.source!r}")


@dataclass
class Experiment:
    """Everything one run computed (for the report)."""

    metrics: dict[str, dict[str, float]]
    fits: dict[str, FitResult]
    corrections: dict[str, np.ndarray]
    residual: np.ndarray
    split: Split
    seconds: float


def run_experiment(
    model: tc.RobotModel,
    ds: ResidualDataset,
    data_cfg: DataConfig,
    train_cfg: TrainConfig,
    *,
    methods: tuple[str, ...] = ("a", "b", "c", "d_mlp", "d_mlp_c"),
    gru_cfg: TrainConfig | None = None,
    device: str = "cpu",
    label: str = "",
) -> Experiment:
    """Fit corrections (a)-(d) on the training blocks' contact-free frames, evaluate on test blocks.

    Every method sees the same split; learned models early-stop on the validation blocks; test
    blocks are used only for the metrics (contact segments there were never seen).
    """
    t0 = time.perf_counter()
    sensor = ds.sensor
    if tuple(ds.joint_names) != tuple(model.joint_names):
        raise ValueError(f"dataset joints {ds.joint_names} != model joints {model.joint_names}")
    est = tc.ContactEstimator(model, [sensor])
    block = max(1, int(round(data_cfg.block_seconds * data_cfg.rate_hz)))
    split = split_blocks(ds.file_id, block, tuple(data_cfg.fractions), seed=data_cfg.seed)
    free = ds.contact_free
    residual = ds.ft - predict_free(est, ds.q, ds.qd, ds.qdd, sensor)
    tr_free = split.train[free[split.train]]
    X = ds.features()
    corr: dict[str, np.ndarray] = {"a": np.zeros_like(residual)}
    corr["b"] = np.broadcast_to(residual[tr_free].mean(0), residual.shape).copy()
    fits: dict[str, FitResult] = {}
    if "c" in methods or "d_mlp_c" in methods:
        Y = inertial_regressor(model, sensor, ds.q, ds.qd, ds.qdd)
        ls = InertialLeastSquares().fit(model, sensor, Y[tr_free], residual[tr_free])
        corr["c"] = ls.correction(Y)
        del Y
    if "d_mlp" in methods:
        fits["d_mlp"] = fit_residual(
            X,
            residual,
            free,
            split.blocks["train"],
            split.blocks["val"],
            train_cfg,
            device,
            desc=f"{label} MLP",
        )
        corr["d_mlp"] = predict_residual(fits["d_mlp"].module, X, [(0, len(X))])
    if "d_mlp_c" in methods:
        fits["d_mlp_c"] = fit_residual(
            X,
            residual - corr["c"],
            free,
            split.blocks["train"],
            split.blocks["val"],
            train_cfg,
            device,
            desc=f"{label} MLP on (c)",
        )
        corr["d_mlp_c"] = corr["c"] + predict_residual(fits["d_mlp_c"].module, X, [(0, len(X))])
    if "d_gru" in methods:
        cfg = gru_cfg or TrainConfig(kind="gru", hidden=64, layers=1, epochs=60, lr=3e-3)
        fits["d_gru"] = fit_residual(
            X,
            residual,
            free,
            split.blocks["train"],
            split.blocks["val"],
            cfg,
            device,
            desc=f"{label} GRU",
        )
        corr["d_gru"] = predict_residual(fits["d_gru"].module, X, split.blocks["test"])

    # metrics on the held-out test blocks
    te = split.test
    te_free = te[free[te]]
    te_contact = te[~free[te]]
    metrics: dict[str, dict[str, float]] = {}
    for name in [m for m in METHODS if m in corr]:
        row: dict[str, float] = {}
        if ds.truth and len(te_contact):
            truth = {k: v[te_contact] for k, v in ds.truth.items() if k != "links"}
            truth["links"] = ds.truth["links"]
            sl = te_contact
            row.update(
                contact_metrics(
                    est, ds.q[sl], ds.qd[sl], ds.qdd[sl], ds.ft[sl] - corr[name][sl], truth, sensor
                )
            )
        row.update(residual_rmse(residual[te_free] - corr[name][te_free]))
        metrics[name] = row
    return Experiment(metrics, fits, corr, residual, split, time.perf_counter() - t0)


def save_checkpoint(
    out: str | Path,
    fit: FitResult,
    ds: ResidualDataset,
    model: tc.RobotModel,
    config: dict,
    metrics: dict,
) -> Path:
    """Write a residual checkpoint (weights, JSON meta) into ``out``."""
    meta = {
        "features": ds.feature_names(),
        "joint_names": list(ds.joint_names),
        "sensor": ds.sensor,
        "robot_sha256": model.urdf_sha256,
        "data_sha256": ds.sha256(),
        "config": config,
        "metrics": metrics,
        "train_loss": fit.train_loss,
        "val_loss": fit.val_loss,
        "best_epoch": fit.best_epoch,
        "torch_version": torch.__version__,
    }
    return save_residual_model(out, fit.module, meta)


def load_checkpoint(directory: str | Path, **kwargs):
    """Load and verify a checkpoint: see :func:`torchcontact.residual.load_residual_model`."""
    return load_residual_model(directory, **kwargs)


def table_markdown(results: dict[str, dict[str, dict[str, float]]]) -> str:
    """Markdown table: one row per (condition, method)."""
    cols = [
        ("force_rmse", "force RMSE 1c (N)"),
        ("moment_rmse", "moment RMSE 1c (N m)"),
        ("force_rmse_2c", "force RMSE 2c (N)"),
        ("residual_force_rms", "free resid. F (N)"),
        ("residual_moment_rms", "free resid. M (N m)"),
    ]
    lines = ["| condition | method | " + " | ".join(c[1] for c in cols) + " |"]
    lines.append("|---|---|" + "---:|" * len(cols))
    for cond, rows in results.items():
        for m, row in rows.items():
            vals = " | ".join(f"{row.get(k, float('nan')):.3f}" for k, _ in cols)
            lines.append(f"| {cond} | {METHODS[m]} | {vals} |")
    return "\n".join(lines)


def plot(exp: Experiment, ds: ResidualDataset, out: Path, title: str) -> None:
    """Loss curves and residual before/after correction over time (test blocks, contact-free)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if exp.fits:
        fig, ax = plt.subplots(figsize=(6, 4))
        for name, f in exp.fits.items():
            (line,) = ax.semilogy(f.train_loss, label=f"{METHODS[name]} train")
            ax.semilogy(f.val_loss, "--", color=line.get_color(), label=f"{METHODS[name]} val")
        ax.set_xlabel("epoch")
        ax.set_ylabel("normalised MSE")
        ax.set_title(f"{title}: loss")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "loss.png", dpi=110)
        plt.close(fig)
    t = (ds.t_ns - ds.t_ns[0]) * 1e-9
    te = exp.split.test
    te = te[ds.contact_free[te]]
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for name, c in exp.corrections.items():
        r = exp.residual[te] - c[te]
        axes[0].plot(t[te], np.linalg.norm(r[:, :3], axis=1), ".", ms=1.5, label=METHODS[name])
        axes[1].plot(t[te], np.linalg.norm(r[:, 3:], axis=1), ".", ms=1.5)
    axes[0].set_ylabel("|residual force| (N)")
    axes[1].set_ylabel("|residual moment| (N m)")
    axes[1].set_xlabel("time (s), contact-free frames of the test blocks")
    axes[0].set_title(f"{title}: residual after each correction")
    axes[0].legend(fontsize=7, markerscale=6)
    fig.tight_layout()
    fig.savefig(out / "residual.png", dpi=110)
    plt.close(fig)


def asdict_cfg(data_cfg: DataConfig, train_cfg: TrainConfig) -> dict:
    """JSON-ready config."""
    d = asdict(data_cfg)
    d["fractions"] = list(d["fractions"])
    return {"data": d, "train": asdict(train_cfg)}


def write_json(path: Path, obj: Any) -> None:
    """JSON with NaN written as null."""

    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, float) and not np.isfinite(x):
            return None
        return x

    path.write_text(json.dumps(clean(obj), indent=2) + "\n")
