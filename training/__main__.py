"""Command line: ``torchcontact train fit --config CFG --out DIR`` or ``... benchmark --out DIR``.

The same parser runs as ``python -m training`` from the repository root (``train`` is an alias of
``fit``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import torchcontact as tc
from torchcontact.cli import Parser, guarded
from torchcontact.errors import InputError

from .fit import TrainConfig
from .pipeline import (
    METHODS,
    DataConfig,
    asdict_cfg,
    load_config,
    make_dataset,
    plot,
    run_experiment,
    save_checkpoint,
    table_markdown,
    write_json,
)

OFFSET = (3.0, -2.0, 4.0, 0.3, -0.2, 0.25)
NOISE = (0.05, 0.05, 0.05, 0.005, 0.005, 0.005)

#: the three synthetic conditions of the benchmark (issue 5)
CONDITIONS = {
    "offset": {"offset": OFFSET, "noise_std": NOISE},
    "offset+payload": {"offset": OFFSET, "noise_std": NOISE, "payload_mass": 0.6},
    "offset+drift+cable": {
        "offset": OFFSET,
        "noise_std": NOISE,
        "drift": (4.0, -3.0, 2.0, 0.4, 0.3, -0.2),
        "drift_time_constant": 60.0,
        "cable_force": 6.0,
    },
}


def _seed(seed: int) -> None:
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)


def _config_path(config: str) -> Path:
    """A TOML file, or the name of a bundled config (``example``: ``configs/example.toml``)."""
    bundled = Path(__file__).resolve().parent / "configs" / f"{config}.toml"
    return bundled if not Path(config).exists() and bundled.is_file() else Path(config)


def cmd_train(args) -> int:
    """Train one residual model from a TOML config; write the checkpoint directory."""
    args.config = str(_config_path(args.config))
    try:
        data_cfg, train_cfg, raw = load_config(args.config)
    except (OSError, TypeError, ValueError) as exc:  # unreadable file, unknown key, bad value
        raise InputError(f"--config {args.config}: {exc}") from None
    _seed(train_cfg.seed)
    model = tc.RobotModel.from_urdf(args.urdf or tc.robots.tcarm_path())
    ds = make_dataset(model, data_cfg)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    key = "d_gru" if train_cfg.kind == "gru" else "d_mlp"
    methods = ("a", "b", "c", key)
    exp = run_experiment(
        model,
        ds,
        data_cfg,
        train_cfg,
        methods=methods,
        gru_cfg=train_cfg,
        device=args.device,
        label="train",
    )
    table = table_markdown({args.config: exp.metrics})
    print(table)
    save_checkpoint(
        out, exp.fits[key], ds, model, {**asdict_cfg(data_cfg, train_cfg), "toml": raw}, exp.metrics
    )
    (out / "metrics.md").write_text(table + "\n")
    plot(exp, ds, out, Path(args.config).stem)
    print(f"checkpoint: {out}")
    return 0


def cmd_benchmark(args) -> int:
    """Run (a)-(d) on the three synthetic conditions; print and save the table."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    train_cfg = TrainConfig(seed=args.seed)
    gru_cfg = TrainConfig(
        kind="gru",
        hidden=64,
        layers=1,
        epochs=args.gru_epochs,
        lr=3e-3,
        batch_size=256,
        patience=10,
        seq_len=200,
        seed=args.seed,
    )
    methods = ("a", "b", "c", "d_mlp", "d_mlp_c") + (("d_gru",) if args.gru else ())
    results, timing = {}, {}
    t0 = time.perf_counter()
    for i, (name, fx) in enumerate(CONDITIONS.items()):
        _seed(args.seed)
        data_cfg = DataConfig(frames=args.frames, seed=args.seed + i, effects=dict(fx))
        ds = make_dataset(model, data_cfg)
        exp = run_experiment(
            model,
            ds,
            data_cfg,
            train_cfg,
            methods=methods,
            gru_cfg=gru_cfg,
            device=args.device,
            label=name,
        )
        results[name], timing[name] = exp.metrics, exp.seconds
        d = out / name.replace("+", "_")
        d.mkdir(exist_ok=True)
        cfg = {**asdict_cfg(data_cfg, train_cfg), "gru": vars(gru_cfg)}
        save_checkpoint(d / "checkpoint", exp.fits["d_mlp"], ds, model, cfg, exp.metrics)
        if "d_gru" in exp.fits:
            save_checkpoint(d / "checkpoint_gru", exp.fits["d_gru"], ds, model, cfg, exp.metrics)
        plot(exp, ds, d, name)
        print(f"[{name}] {exp.seconds:.1f} s", file=sys.stderr)
    table = table_markdown(results)
    print(table)
    (out / "results.md").write_text(table + "\n")
    write_json(
        out / "results.json",
        {
            "methods": METHODS,
            "conditions": {
                k: {kk: list(vv) if isinstance(vv, tuple) else vv for kk, vv in v.items()}
                for k, v in CONDITIONS.items()
            },
            "frames": args.frames,
            "seed": args.seed,
            "results": results,
            "seconds": timing,
            "total_seconds": time.perf_counter() - t0,
            "torch_version": torch.__version__,
            "threads": torch.get_num_threads(),
        },
    )
    return 0


def main(argv=None, prog: str = "python -m training") -> int:
    """Entry point of ``torchcontact train`` and ``python -m training``; returns the exit code."""
    p = Parser(prog=prog, description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True, metavar="{fit,benchmark}")
    t = sub.add_parser("fit", aliases=["train"], help="train a residual model from a TOML config")
    t.add_argument(
        "--config",
        required=True,
        help="TOML config ([data], [model], [train]), or a bundled one by name: example",
    )
    t.add_argument("--out", required=True, help="checkpoint directory")
    t.add_argument("--urdf", default=None, help="robot URDF (default: the bundled tcarm)")
    t.add_argument("--device", default="cpu", help="torch device")
    b = sub.add_parser("benchmark", help="synthetic benchmark of corrections (a)-(d)")
    b.add_argument("--out", required=True, help="output folder")
    b.add_argument("--frames", type=int, default=24000, help="frames per condition")
    b.add_argument("--seed", type=int, default=0, help="random seed")
    b.add_argument("--gru", action=argparse.BooleanOptionalAction, default=True, help="train GRUs")
    b.add_argument("--gru-epochs", type=int, default=40, help="GRU epochs")
    b.add_argument("--device", default="cpu", help="torch device")
    for sp in (t, b):
        sp.add_argument(
            "--threads",
            type=int,
            default=1,
            help="torch CPU threads (1 is fastest for these small models)",
        )

    def run() -> int:
        args = p.parse_args(argv)
        torch.set_num_threads(args.threads)
        return cmd_benchmark(args) if args.cmd == "benchmark" else cmd_train(args)

    return guarded(run, debug="--debug" in (sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
