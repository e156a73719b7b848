"""Command line: ``torchcontact train fit | benchmark | heldout | study``.

The same parser runs as ``python -m training`` from the repository root (``train`` is an alias of
``fit`` there).

``train`` fits a correction stack on logs in the documented format (or a simulated log) for any
URDF and sensor and writes one checkpoint directory with its report; ``benchmark`` runs the
synthetic conditions (offset; payload on the end effector; temperature drift plus a cable whose
tension depends on joint angles) on any robot and sensor with cross-validated scores;
``heldout`` trains on one simulated log and scores on another; ``study`` compares learned-layer
input sets on held-out logs.
"""

from __future__ import annotations

import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import torchcontact as tc
from torchcontact.cli import Parser, guarded
from torchcontact.errors import InputError
from torchcontact.robot_arg import (
    add_robot_argument,
    add_strict_joints_argument,
    check_log_joints,
    resolve_robot_argument,
)
from torchcontact.robots import RobotSpec

from .data import ResidualDataset
from .fit import TrainConfig
from .pipeline import (
    CLASSICAL,
    Config,
    DataConfig,
    FeatureConfig,
    StackConfig,
    load_config,
    log,
    make_dataset,
    predict,
    score_methods,
    table_markdown,
    train,
    write_json,
)

OFFSET = (3.0, -2.0, 4.0, 0.3, -0.2, 0.25)
NOISE = (0.05, 0.05, 0.05, 0.005, 0.005, 0.005)
DRIFT = (4.0, -3.0, 2.0, 0.4, 0.3, -0.2)

#: the synthetic conditions (issue 12's table): payload on the sensor subtree's end effector,
#: temperature drift (logged temperature follows it) plus a joint-angle dependent cable
CONDITIONS = {
    "offset": {"offset": OFFSET, "noise_std": NOISE},
    "payload": {"offset": OFFSET, "noise_std": NOISE, "payload_mass": 0.25},
    "drift+cable": {
        "offset": OFFSET,
        "noise_std": NOISE,
        "drift": DRIFT,
        "drift_time_constant": 60.0,
        "cable_force": 3.0,
    },
}


def _seed(seed: int) -> None:
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)


def _meta() -> dict:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
            check=False,
        ).stdout.strip()
    except OSError:
        commit = ""
    return {
        "commit": commit or "unknown",
        "torch_version": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "python": platform.python_version(),
    }


def _model_and_sensor(robot: str | RobotSpec, sensor: str | None) -> tuple[tc.RobotModel, str]:
    spec = robot if isinstance(robot, RobotSpec) else RobotSpec.of(robot)
    model = spec.load()
    sensor = sensor or next(iter(model.ft_sensors), "")
    if sensor not in model.ft_sensors:
        raise InputError(f"{model.name} has no F/T sensor {sensor!r} ({list(model.ft_sensors)})")
    return model, sensor


def _config_path(config: str) -> Path:
    """A TOML file, or the name of a bundled config (``example``: ``configs/example.toml``)."""
    bundled = Path(__file__).resolve().parent / "configs" / f"{config}.toml"
    return bundled if not Path(config).exists() and bundled.is_file() else Path(config)


def cmd_train(args) -> int:
    """Fit a correction stack; write the checkpoint directory with its report."""
    from torchcontact._lock import OutputLock

    with OutputLock(Path(args.out), "train fit"):  # one writer per checkpoint folder at a time
        return _train(args)


def _train(args) -> int:
    if args.config:
        path = _config_path(args.config)
        try:
            cfg, _ = load_config(path)
        except (OSError, TypeError, ValueError) as exc:  # unreadable file, unknown key, bad value
            raise InputError(f"--config {args.config}: {exc}") from None
    else:
        cfg = Config()
    data = cfg.data
    if args.log:
        data = replace(data, source="parquet", paths=list(args.log))
    if args.robot is None:
        args.robot = data.robot  # the config's robot (tcarm by default)
    spec = resolve_robot_argument(args)
    data = replace(data, robot=spec.robot)
    if args.sensor:
        data = replace(data, sensor=args.sensor)
    if args.extra is not None:
        data = replace(data, extra=list(args.extra))
    if args.folds is not None:
        data = replace(data, folds=args.folds)
    if args.bias_time_constant is not None:
        if not args.bias_time_constant >= 0:
            raise InputError(f"--bias-time-constant must be >= 0 s, got {args.bias_time_constant}")
        data = replace(data, bias_time_constant=args.bias_time_constant)
    cfg = replace(cfg, data=data)
    if args.layers:
        cfg = replace(cfg, stack=replace(cfg.stack, layers=args.layers.split(",")))
    model, sensor = _model_and_sensor(spec, data.sensor or None)
    if data.source == "parquet" and args.strict_joints:  # else extra joints: one warning each
        check_log_joints(data.paths, model, strict=True)
    _seed(cfg.train.seed)
    ds = make_dataset(model, data, sensor)
    t0 = time.perf_counter()
    trained = train(model, ds, cfg, out=args.out, device=args.device)
    from .pipeline import report_markdown

    print(report_markdown(trained))
    print(f"checkpoint: {args.out} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _conditions(args) -> dict[str, dict]:
    out = {}
    for n in args.conditions:
        if n not in CONDITIONS:
            raise ValueError(f"unknown condition {n!r}; expected {list(CONDITIONS)}")
        fx = dict(CONDITIONS[n])
        if args.cable is not None and "cable_force" in fx:
            fx["cable_force"] = args.cable
        fx["noise_std"] = tuple(args.noise_scale * x for x in fx["noise_std"])
        out[n] = fx
    return out


def _goals(metrics: dict[str, dict[str, dict[str, float]]], key: str) -> list[str]:
    """The targets checked on one metric (contact-force RMSE 1c or free force RMS)."""
    lines = []
    for cond, rows in metrics.items():
        stack = rows["stack"][key]
        best = min(rows[c][key] for c in CLASSICAL if c in rows)
        never = f"stack {stack:.3f} vs best classical {best:.3f}: " + (
            "ok" if stack <= best * 1.02 else "MISSED"
        )
        if cond == "payload" and "oracle" in rows:
            ratio = stack / rows["oracle"][key]
            ok = "ok" if ratio <= 1.5 else "MISSED"
            lines.append(f"{cond}: stack/oracle = {ratio:.2f} (goal <= 1.5: {ok}); {never}")
        elif cond == "drift+cable":
            gain = rows["offset"][key] / stack
            ok = "ok" if gain >= 4 else "MISSED"
            lines.append(f"{cond}: offset/stack = {gain:.2f} (goal >= 4: {ok}); {never}")
        else:
            lines.append(f"{cond}: {never}")
    return lines


def cmd_benchmark(args) -> int:
    """Cross-validated benchmark of the correction stack on synthetic conditions."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = resolve_robot_argument(args)
    model, sensor = _model_and_sensor(spec, args.sensor)
    conditions = _conditions(args)
    train_cfg = TrainConfig(kind=args.learned, seed=args.seed, epochs=args.epochs)
    results, timing, chosen = {}, {}, {}
    t0 = time.perf_counter()
    for i, (name, fx) in enumerate(conditions.items()):
        _seed(args.seed)
        data = DataConfig(
            robot=spec.robot,
            sensor=sensor,
            frames=args.frames,
            seed=args.seed + i,
            force_max=args.force_max,
            folds=args.folds,
            block_seconds=args.block_seconds,
            effects=dict(fx),
        )
        cfg = Config(data=data, train=train_cfg)
        ds = make_dataset(model, data, sensor)
        d = out / name.replace("+", "_")
        trained = train(model, ds, cfg, out=d, device=args.device, label=name)
        assert trained.report is not None
        results[name] = trained.report.metrics
        timing[name] = trained.seconds
        chosen[name] = {"folds": trained.report.chosen, "checkpoint": trained.final.chosen}
        log(f"[{name}] {trained.seconds:.1f} s, stack {trained.report.chosen}")
    meta = _meta()
    head = (
        f"robot {model.name}, sensor {sensor}, {args.frames} frames per condition, "
        f"{args.folds}-fold CV over {args.block_seconds:g} s blocks, commit {meta['commit']}, torch"
        f" {meta['torch_version']}, {meta['threads']} thread(s)"
    )
    table = table_markdown(results)
    goals = _goals(results, "force_rmse") + _goals(results, "residual_force_rms")
    text = "\n".join([head, "", table, "", "goals (force RMSE 1c, then free |F|):", *goals])
    print(text)
    (out / "results.md").write_text(text + "\n")
    write_json(
        out / "results.json",
        {
            "robot": model.name,
            "sensor": sensor,
            "conditions": conditions,
            "frames": args.frames,
            "seed": args.seed,
            "results": results,
            "chosen": chosen,
            "seconds": timing,
            "total_seconds": time.perf_counter() - t0,
            **meta,
        },
    )
    return 0


def heldout(
    model: tc.RobotModel,
    sensor: str,
    fx: dict,
    cfg: Config,
    train_frames: int,
    test_frames: int,
    seed: int,
    device: str = "cpu",
    label: str = "",
    new_session: bool = False,
) -> tuple[dict, object]:
    """Train on the first frames of a simulated session, score on the frames after them.

    The first ``train_frames`` train (with validation blocks inside them), the next
    ``test_frames`` are scored; with ``new_session`` the test frames are another session (a
    different seed, whose joint trajectory explores another region of the workspace).

    Returns:
        ``(metrics per method on the test frames, the Trained result)``.
    """
    from torchcontact.simulation import UnmodeledEffects, simulate

    from .pipeline import prepare

    frames = train_frames + (0 if new_session else test_frames)
    data = replace(cfg.data, frames=frames, seed=seed, effects=dict(fx), folds=0)
    cfg = replace(cfg, data=data)
    whole = make_dataset(model, data, sensor)
    ds = whole.subset(slice(0, train_frames))
    trained = train(model, ds, cfg, device=device, label=label)
    if new_session:
        test_log = simulate(
            model,
            test_frames,
            sensor=sensor,
            seed=seed + 1000,
            rate_hz=data.rate_hz,
            force_max=data.force_max,
            effects=UnmodeledEffects(**fx),
        )
        test = ResidualDataset.from_simulated(test_log, data.extra)
    else:
        test = whole.subset(slice(train_frames, frames))
    prep = prepare(model, test, replace(cfg, stack=StackConfig(layers=["offset"])))
    span = [(0, len(test))]
    preds = {n: predict(c, test, span) for n, c in trained.final.corrections.items()}
    preds["stack"] = preds[trained.final.chosen]
    preds["none"] = np.zeros((len(test), 6))
    preds["oracle"] = test.truth["ft_effects"]
    return score_methods(prep, preds), trained


def cmd_heldout(args) -> int:
    """Held-out scoring: train on one log, estimate contacts on another."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = resolve_robot_argument(args)
    model, sensor = _model_and_sensor(spec, args.sensor)
    cfg = Config(
        data=DataConfig(robot=spec.robot, sensor=sensor, force_max=args.force_max),
        train=TrainConfig(kind=args.learned, seed=args.seed, epochs=args.epochs),
    )
    results, timing, chosen = {}, {}, {}
    for name, fx in _conditions(args).items():
        _seed(args.seed)
        metrics, trained = heldout(
            model,
            sensor,
            fx,
            cfg,
            args.train_frames,
            args.test_frames,
            args.seed,
            args.device,
            name,
            new_session=args.new_session,
        )
        results[name], timing[name] = metrics, trained.seconds
        chosen[name] = trained.final.chosen
        log(f"[{name}] trained in {trained.seconds:.1f} s, stack {trained.final.chosen}")
    meta = _meta()
    head = (
        f"robot {model.name}, sensor {sensor}, train {args.train_frames} / test"
        f" {args.test_frames} frames ("
        + ("another session" if args.new_session else "the frames after the training ones")
        + f"), noise x{args.noise_scale:g}, contacts 1-2 pure forces of 0-"
        f"{args.force_max:g} N, commit {meta['commit']}, torch {meta['torch_version']}"
    )
    text = "\n".join([head, "", table_markdown(results), "", f"chosen: {chosen}"])
    print(text)
    (out / "heldout.md").write_text(text + "\n")
    write_json(
        out / "heldout.json",
        {"results": results, "chosen": chosen, "train_seconds": timing, **meta},
    )
    return 0


#: input sets of the learned layer compared by ``study`` (the first is the old default)
FEATURE_SETS = {
    "all joints: q, qd, qdd": FeatureConfig(
        joints="all", angles="raw", accelerations=True, nominal=False
    ),
    "sensor joints: q, qd, qdd": FeatureConfig(angles="raw", accelerations=True, nominal=False),
    "sensor joints: sin/cos, qd": FeatureConfig(nominal=False),
    "sensor joints: sin/cos, qd, nominal (default)": FeatureConfig(),
    "sensor joints: sin/cos, qd, qdd, nominal": FeatureConfig(accelerations=True),
    "all joints: sin/cos, qd, nominal": FeatureConfig(joints="all"),
}


def cmd_study(args) -> int:
    """Held-out contact-force error of the learned layer per input set (benchmarks/README.md)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for robot, sensor in [r.split(":") for r in args.robots]:
        model, sensor = _model_and_sensor(robot, sensor)
        for cond, fx in _conditions(args).items():
            for fname, fcfg in FEATURE_SETS.items():
                _seed(args.seed)
                cfg = Config(
                    data=DataConfig(robot=robot, sensor=sensor, force_max=args.force_max),
                    features=fcfg,
                    stack=StackConfig(layers=["offset", args.learned]),
                    train=TrainConfig(kind=args.learned, seed=args.seed, epochs=args.epochs),
                )
                metrics, trained = heldout(
                    model, sensor, fx, cfg, args.train_frames, args.test_frames, args.seed,
                    args.device, f"{robot} {cond} {fname}",
                )  # fmt: skip
                n_feat = len(trained.prep.spec.names(model))
                key = f"offset+{args.learned}"
                f = trained.final.fits[key]
                rows.append(
                    {
                        "robot": model.name,
                        "sensor": sensor,
                        "condition": cond,
                        "features": fname,
                        "n_features": n_feat,
                        "force_rmse_1c": metrics["stack"].get("force_rmse"),
                        "free_force_rms": metrics["stack"]["residual_force_rms"],
                        "free_moment_rms": metrics["stack"]["residual_moment_rms"],
                        "offset_force_rmse_1c": metrics["offset"].get("force_rmse"),
                        "train_loss": f.train_loss[f.best_epoch],
                        "val_loss": f.val_loss[f.best_epoch],
                    }
                )
                log(f"{rows[-1]}")
    lines = [
        "| robot / sensor | condition | learned-layer inputs | F | held-out force RMSE 1c (N)"
        " | held-out free \\|F\\| (N) | train / val loss |",
        "|---|---|---|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['robot']} `{r['sensor']}` | {r['condition']} | {r['features']} |"
            f" {r['n_features']} | {r['force_rmse_1c']:.3f} | {r['free_force_rms']:.3f} |"
            f" {r['train_loss']:.3f} / {r['val_loss']:.3f} |"
        )
    meta = _meta()
    text = "\n".join(lines) + f"\n\ncommit {meta['commit']}, torch {meta['torch_version']}"
    print(text)
    (out / "study.md").write_text(text + "\n")
    write_json(out / "study.json", {"rows": rows, **meta})
    return 0


def main(argv=None, prog: str = "python -m training") -> int:
    """Entry point of ``torchcontact train`` and ``python -m training``; returns the exit code."""
    p = Parser(
        prog=prog,
        description="learn an F/T residual correction (fit) and measure it (benchmark, heldout,"
        " study)",
    )
    sub = p.add_subparsers(dest="cmd", required=True, metavar="{fit,benchmark,heldout,study}")
    t = sub.add_parser(
        "fit", aliases=["train"], help="fit a correction stack on logs; write the checkpoint"
    )
    t.add_argument(
        "--config",
        default=None,
        help="TOML config (flags override it), or a bundled one by name: example (default: none,"
        " the built-in defaults: a simulated log of tcarm)",
    )
    t.add_argument(
        "--log",
        nargs="+",
        default=None,
        help="Parquet logs in the documented format (default: the config's; none: a simulated log)",
    )
    add_robot_argument(t, aliases=("--urdf",), default_help="the config's [data] robot, else tcarm")
    add_strict_joints_argument(t)
    t.add_argument("--sensor", default=None, help="F/T sensor (default: the robot's first)")
    t.add_argument(
        "--extra",
        nargs="*",
        default=None,
        help="extra feature columns (default: the config's, temperature)",
    )
    t.add_argument("--layers", default=None, help="e.g. offset,inertial,mlp (default: auto)")
    t.add_argument(
        "--folds",
        type=int,
        default=None,
        help="cross-validation folds, 0: none (default: the config's, 5)",
    )
    t.add_argument(
        "--bias-time-constant",
        type=float,
        default=None,
        metavar="S",
        help="smooth each log's F/T offset drift out of the residuals before fitting, with the"
        " tracker and smoother of estimate --track-bias at this time constant (tens of seconds:"
        " slower than the motion) (default: the config's data.bias_time_constant, 0: off)",
    )
    t.add_argument("--out", required=True, help="checkpoint directory")
    for name, fn in (("benchmark", cmd_benchmark), ("heldout", cmd_heldout)):
        b = sub.add_parser(name, help=fn.__doc__.splitlines()[0])
        add_robot_argument(b, default="tcarm")
        b.add_argument("--sensor", default=None, help="F/T sensor (default: the robot's first)")
        b.add_argument(
            "--conditions", nargs="+", default=list(CONDITIONS), help="synthetic conditions"
        )
        b.add_argument(
            "--cable",
            type=float,
            default=None,
            help="cable force amplitude, N (default: each condition's, 3 for drift+cable)",
        )
        b.add_argument(
            "--noise-scale", type=float, default=1.0, help="times the F/T noise of the conditions"
        )
        b.add_argument("--force-max", type=float, default=10.0, help="peak contact force, N")
        b.add_argument(
            "--learned", choices=["mlp", "gru"], default="mlp", help="kind of the learned layer"
        )
        b.add_argument(
            "--epochs", type=int, default=TrainConfig.epochs, help="epochs of the learned layer"
        )
        b.add_argument("--seed", type=int, default=0, help="random seed")
        b.add_argument("--out", required=True, help="output folder of the results")
    bench = sub.choices["benchmark"]
    bench.add_argument("--frames", type=int, default=36000, help="frames per condition")
    bench.add_argument("--folds", type=int, default=5, help="cross-validation folds")
    bench.add_argument(
        "--block-seconds", type=float, default=10.0, help="time blocks of the splits, s"
    )
    h = sub.choices["heldout"]
    h.add_argument("--train-frames", type=int, default=36000, help="training frames")
    h.add_argument("--test-frames", type=int, default=12000, help="scored frames")
    h.add_argument(
        "--new-session",
        action="store_true",
        help="test on another simulated session (another workspace region), not the next frames",
    )
    s = sub.add_parser("study", help=cmd_study.__doc__.splitlines()[0])
    s.add_argument(
        "--robots",
        nargs="+",
        default=["tcarm:base_ft", "icub:l_arm_ft"],
        help="ROBOT:SENSOR pairs (ROBOT as --robot)",
    )
    s.add_argument(
        "--conditions", nargs="+", default=["payload", "drift+cable"], help="synthetic conditions"
    )
    s.add_argument(
        "--cable",
        type=float,
        default=None,
        help="cable force amplitude, N (default: each condition's, 3 for drift+cable)",
    )
    s.add_argument(
        "--noise-scale", type=float, default=1.0, help="times the F/T noise of the conditions"
    )
    s.add_argument("--force-max", type=float, default=10.0, help="peak contact force, N")
    s.add_argument(
        "--learned", choices=["mlp", "gru"], default="mlp", help="kind of the learned layer"
    )
    s.add_argument(
        "--epochs", type=int, default=TrainConfig.epochs, help="epochs of the learned layer"
    )
    s.add_argument("--train-frames", type=int, default=36000, help="training frames")
    s.add_argument("--test-frames", type=int, default=12000, help="scored frames")
    s.add_argument("--seed", type=int, default=0, help="random seed")
    s.add_argument("--out", required=True, help="output folder of the results")
    for sp in {id(v): v for v in sub.choices.values()}.values():
        sp.add_argument("--device", default="cpu", help="torch device")
        sp.add_argument(
            "--threads", type=int, default=1, help="torch CPU threads (1 is fastest here)"
        )
    commands = {
        "fit": cmd_train,
        "train": cmd_train,
        "benchmark": cmd_benchmark,
        "heldout": cmd_heldout,
        "study": cmd_study,
    }

    def run() -> int:
        args = p.parse_args(argv)
        torch.set_num_threads(args.threads)
        return commands[args.cmd](args)

    return guarded(run, debug="--debug" in (sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
