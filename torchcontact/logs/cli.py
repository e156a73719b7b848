"""Command-line jobs on logs: ``estimate``, ``simulate``, ``demo``, ``plot`` and ``convert``.

Registered by :func:`add_parser` from ``torchcontact/cli.py``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

DTYPES = {"float64": "float64", "float32": "float32"}


def _dtype(name: str) -> Any:
    import torch

    return {"float64": torch.float64, "float32": torch.float32}[name]


def _threads(args: argparse.Namespace) -> None:
    # Small batched kernels (index_add over a few bodies) run far slower with several intra-op
    # threads on small CPUs (measured ~2000x on 2 cores); one thread per process is the default.
    import torch

    if getattr(args, "threads", 0):
        torch.set_num_threads(args.threads)


def _robot(path: str | None) -> str:
    from torchcontact.robots import tcarm_path

    return str(path) if path else str(tcarm_path())


def cmd_estimate(args: argparse.Namespace) -> int:
    """Estimate the contacts of every frame of one or more logs."""
    from torchcontact.logs.pipeline import LogError, estimate_files

    _threads(args)
    kwargs: dict[str, Any] = dict(
        sensors=args.sensor or None,
        batch_size=args.batch_size,
        device=args.device,
        dtype=_dtype(args.dtype),
        resume=args.resume,
    )
    if args.residual:
        kwargs["residual"] = args.residual
    if args.quiet:
        kwargs["progress"] = False
    try:
        if args.engine == "ray":
            from torchcontact.logs.ray_engine import estimate_files_ray

            kwargs.pop("resume")
            kwargs.pop("progress", None)
            summaries = estimate_files_ray(args.inputs, _robot(args.robot), args.out, **kwargs)
        else:
            summaries = estimate_files(args.inputs, _robot(args.robot), args.out, **kwargs)
    except (LogError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted: run again with --resume to finish", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(summaries if len(summaries) > 1 else summaries[0]))
    else:
        for s in summaries:
            print(
                f"{s['input']} -> {s['output']}: {s['frames']} frames"
                f" ({s['frames_per_s']:.0f} frames/s)"
                + (f", derived {'/'.join(s['derived'])} from q" if s["derived"] else "")
            )
    return 0


def _effects(args: argparse.Namespace) -> Any:
    from torchcontact.simulation import UnmodeledEffects

    def six(v: list[float] | None, name: str) -> tuple[float, ...]:
        if v is None:
            return (0.0,) * 6
        if len(v) == 1:
            return (v[0],) * 6
        if len(v) != 6:
            raise SystemExit(f"--{name} takes 1 or 6 numbers [N; N m]")
        return tuple(v)

    fx = UnmodeledEffects(
        offset=six(args.offset, "offset"),
        drift=six(args.drift, "drift"),
        cable_force=args.cable,
        payload_mass=args.payload,
        noise_std=six(args.noise, "noise"),
    )
    return None if fx == UnmodeledEffects() else fx


def _simulate(args: argparse.Namespace, out: Path) -> Path:
    import torchcontact as tc
    from torchcontact.logs.simlog import write_simulated_log

    _threads(args)
    model = tc.RobotModel.from_urdf(_robot(args.robot))
    return write_simulated_log(
        model,
        args.frames,
        out,
        seed=args.seed,
        effects=_effects(args),
        derivatives=not args.no_derivatives,
        temperature=args.temperature,
        max_contacts=args.max_contacts,
    )


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a simulated log with known contacts."""
    out = _simulate(args, Path(args.out))
    print(f"wrote {args.frames} frames to {out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate -> estimate -> plot into one folder."""
    from torchcontact.logs.pipeline import estimate_file
    from torchcontact.logs.plot import plot_log

    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    log = _simulate(args, folder / "log.parquet")
    est = folder / "estimate.parquet"
    for leftover in (est, folder / "estimate.parquet.partial"):
        if leftover.is_dir():
            import shutil

            shutil.rmtree(leftover)
        elif leftover.exists():
            leftover.unlink()
    (folder / "estimate.parquet.progress.json").unlink(missing_ok=True)
    summary = estimate_file(log, _robot(args.robot), est, progress=False)
    pngs = plot_log(est, _robot(args.robot), folder, input_log=log)
    print(f"simulated log:  {log}")
    print(f"estimates:      {est} ({summary['frames']} frames, {summary['frames_per_s']:.0f}/s)")
    for p in pngs:
        print(f"plot:           {p}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """PNGs of an estimated log."""
    from torchcontact.logs.plot import plot_log

    out = Path(args.out) if args.out else Path(args.log).with_suffix("")
    for p in plot_log(args.log, _robot(args.robot), out, frame=args.frame, input_log=args.input):
        print(p)
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    """ROS 1/2 bags or CSV -> log format."""
    from torchcontact.logs.convert import ConvertError, convert

    try:
        summary = convert(
            args.input,
            args.out,
            joint_states=args.joint_states,
            wrench_topics=args.wrench,
            contacts_topic=args.contacts_topic,
            contacts_file=args.contacts,
        )
    except ConvertError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(summary))
    return 0


def _add_sim_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", help="URDF (default: the bundled tcarm)")
    p.add_argument("--frames", type=int, default=2000, help="number of frames (100 Hz)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-contacts", type=int, default=2, help="most simultaneous contacts")
    p.add_argument("--offset", type=float, nargs="+", help="sensor offset, 1 or 6 numbers")
    p.add_argument("--drift", type=float, nargs="+", help="thermal drift, 1 or 6 numbers")
    p.add_argument("--cable", type=float, default=0.0, help="cable force amplitude, N")
    p.add_argument("--payload", type=float, default=0.0, help="unmodelled payload on hand, kg")
    p.add_argument("--noise", type=float, nargs="+", help="noise std, 1 or 6 numbers")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: torch default)")
    p.add_argument("--no-derivatives", action="store_true", help="omit qd/qdd (derive them)")
    p.add_argument(
        "--temperature",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="keep the temperature column",
    )


def add_parser(subparsers: Any) -> None:
    """Register ``estimate``, ``simulate``, ``demo``, ``plot`` and ``convert``."""
    est = subparsers.add_parser("estimate", help="estimate contacts of every frame of logs")
    est.add_argument("inputs", nargs="+", metavar="INPUT", help="Parquet files, folders or globs")
    est.add_argument("--robot", help="URDF (default: the bundled tcarm)")
    est.add_argument("--out", required=True, help="output file (one input) or folder")
    est.add_argument("--sensor", action="append", help="F/T sensor to use (repeatable)")
    est.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    est.add_argument("--dtype", default="float64", choices=list(DTYPES))
    est.add_argument("--batch-size", type=int, default=8192, help="frames per chunk")
    est.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: default)")
    est.add_argument("--resume", action="store_true", help="finish an interrupted run")
    est.add_argument("--engine", default="local", choices=["local", "ray"])
    est.add_argument(
        "--residual",
        metavar="CHECKPOINT",
        help="residual checkpoint folder: subtract its learned F/T correction before estimating",
    )
    est.add_argument("--json", action="store_true", help="print a JSON summary at the end")
    est.add_argument("--quiet", action="store_true", help="no progress bar")
    est.set_defaults(func=cmd_estimate)

    sim = subparsers.add_parser("simulate", help="write a simulated log with known contacts")
    _add_sim_args(sim)
    sim.add_argument("--out", required=True, help="output Parquet file")
    sim.set_defaults(func=cmd_simulate)

    demo = subparsers.add_parser("demo", help="simulate -> estimate -> plot into a folder")
    _add_sim_args(demo)
    demo.add_argument("--out", default="torchcontact-demo", help="output folder")
    demo.set_defaults(func=cmd_demo)

    plot = subparsers.add_parser("plot", help="PNG plots of an estimated log")
    plot.add_argument("log", help="output of torchcontact estimate")
    plot.add_argument("--robot", help="URDF (default: the bundled tcarm)")
    plot.add_argument("--frame", type=int, help="row of the 3D view (default: largest force)")
    plot.add_argument("--input", help="the input log (joint positions for the 3D view)")
    plot.add_argument("--out", help="folder of the PNGs (default: next to the log)")
    plot.set_defaults(func=cmd_plot)

    conv = subparsers.add_parser("convert", help="ROS 1/2 bag (sqlite3, MCAP) or CSV -> log")
    conv.add_argument("input", help="bag file/folder or .csv")
    conv.add_argument("--out", required=True, help="output Parquet file")
    conv.add_argument("--joint-states", default="/joint_states", help="sensor_msgs/JointState")
    conv.add_argument(
        "--wrench",
        action="append",
        metavar="TOPIC[=SENSOR]",
        help="geometry_msgs/WrenchStamped topic, optionally =sensor name (repeatable)",
    )
    conv.add_argument("--contacts-topic", help="geometry_msgs/PointStamped (frame_id = link)")
    conv.add_argument("--contacts", help="TOML contact-spec file")
    conv.set_defaults(func=cmd_convert)
