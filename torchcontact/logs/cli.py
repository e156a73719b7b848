"""Command-line jobs on logs: ``estimate``, ``simulate``, ``demo``, ``plot`` and ``convert``.

Registered by :func:`add_parser` from ``torchcontact/cli.py``. Errors are raised as
:class:`~torchcontact.errors.TorchContactError` subclasses; ``torchcontact.cli`` prints them as one
``error:`` line. Progress bars go to stderr when it is a terminal (``--quiet``: never).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from torchcontact.errors import InputError

DTYPES = ("float64", "float32")


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


def _progress(args: argparse.Namespace) -> bool:
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def _names(values: list[str] | None) -> list[str] | None:
    """``--opt a,b --opt c`` -> ``["a", "b", "c"]`` (None when not given)."""
    if values is None:
        return None
    return [n.strip() for v in values for n in v.split(",") if n.strip()]


def _ft_range(values: list[str] | None) -> dict[str, list[float]] | None:
    """``--ft-range SENSOR=LIMIT[,LIMIT x5]`` (repeatable) -> ``{sensor: limits}``."""
    if not values:
        return None
    out = {}
    for v in values:
        sensor, sep, nums = v.partition("=")
        try:
            limits = [float(x) for x in nums.split(",")]
        except ValueError:
            limits = []
        if not sep or not sensor or len(limits) not in (1, 6):
            raise InputError(
                f"--ft-range {v}: expected SENSOR=LIMIT or SENSOR=FX,FY,FZ,MX,MY,MZ (N, N m)"
            )
        out[sensor] = limits
    return out


def _constraints(args: argparse.Namespace) -> Any:
    """``--constraints`` and its options -> a :class:`~torchcontact.logs.LogConstraints` or None."""
    import math

    from torchcontact.constrained import FrictionCones
    from torchcontact.logs.pipeline import LogConstraints

    names = ("friction", "cone_angle", "cone_iterations")
    given = [f"--{n.replace('_', '-')}" for n in names if getattr(args, n) is not None]
    given += ["--no-warm-start"] if args.no_warm_start else []
    if not args.constraints:
        if given:
            raise InputError(f"{', '.join(given)} apply with --constraints only")
        return None
    if args.friction is not None and args.cone_angle is not None:
        raise InputError("give --friction or --cone-angle, not both")
    friction = args.friction
    if args.cone_angle is not None:
        if not 0 < args.cone_angle < math.pi / 2:
            raise InputError(f"--cone-angle must be in (0, pi/2) rad, got {args.cone_angle}")
        friction = math.tan(args.cone_angle)
    cones = FrictionCones() if args.cone_iterations is None else FrictionCones(args.cone_iterations)
    return LogConstraints(cones, friction, warm_start=not args.no_warm_start)


def cmd_estimate(args: argparse.Namespace) -> int:
    """Estimate the contacts of every frame of one or more logs."""
    from torchcontact.logs.pipeline import estimate_files

    _threads(args)
    kwargs: dict[str, Any] = dict(
        sensors=args.sensor or None,
        batch_size=args.batch_size,
        device=args.device,
        dtype=_dtype(args.dtype),
        resume=args.resume,
        progress=_progress(args),
        velocity_margin=args.velocity_margin or None,
        ft_range=_ft_range(args.ft_range),
        constraints=_constraints(args),
    )
    if args.residual:
        kwargs["residual"] = args.residual
    try:
        if args.engine == "ray":
            from torchcontact.logs.ray_engine import estimate_files_ray

            kwargs.update(workers=args.workers, threads=args.threads)
            summaries = estimate_files_ray(args.inputs, _robot(args.robot), args.out, **kwargs)
        else:
            if args.workers != 1:
                raise InputError("--workers applies to --engine ray only")
            summaries = estimate_files(args.inputs, _robot(args.robot), args.out, **kwargs)
    except KeyboardInterrupt:
        print("interrupted: run again with --resume to finish", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(summaries if len(summaries) > 1 else summaries[0]))
    else:
        for s in summaries:
            print(
                f"{s['input']} -> {s['output']}: {s['frames']} frames"
                f" ({s['frames_per_s']:.0f} frames/s, {s['bad_now']} with a non-zero status)"
                + (f", derived {'/'.join(s['derived'])} from q" if s["derived"] else "")
                + (
                    f"; cones: {s['cones']['converged']:.2%} of {s['cones']['solved']} solves"
                    f" converged, {s['cones']['iterations_mean']:.1f} iterations on average"
                    if "cones" in s
                    else ""
                )
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
            raise InputError(f"--{name} takes 1 or 6 numbers [N; N m], got {len(v)}")
        return tuple(v)

    links = {}
    if args.cable_link:
        links["cable_link"] = args.cable_link
    if args.payload_link:
        links["payload_link"] = args.payload_link
    fx = UnmodeledEffects(
        offset=six(args.offset, "offset"),
        drift=six(args.drift, "drift"),
        cable_force=args.cable,
        payload_mass=args.payload,
        noise_std=six(args.noise, "noise"),
        **links,
    )
    return None if fx == UnmodeledEffects(**links) else fx


def _simulate(args: argparse.Namespace, out: Path) -> Path:
    from torchcontact.logs.format import check_outputs
    from torchcontact.logs.pipeline import load_robot
    from torchcontact.logs.simlog import write_simulated_log

    _threads(args)
    if args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    if args.max_contacts < 1:
        raise InputError(f"--max-contacts must be >= 1, got {args.max_contacts}")
    robot = _robot(args.robot)
    check_outputs([out, out.with_name(out.name + ".tmp")], [robot])
    model = load_robot(robot)
    return write_simulated_log(
        model,
        args.frames,
        out,
        seed=args.seed,
        effects=_effects(args),
        derivatives=not args.no_derivatives,
        temperature=args.temperature,
        max_contacts=args.max_contacts,
        sensor=args.sensor,
        links=_names(args.contact_links),
        progress=_progress(args),
    )


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a simulated log with known contacts."""
    out = _simulate(args, Path(args.out))
    print(f"wrote {args.frames} frames to {out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate -> estimate -> plot into one folder."""
    import shutil

    from torchcontact.logs.pipeline import estimate_file
    from torchcontact.logs.plot import plot_log

    folder = Path(args.out)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out {folder}: a file, not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    est = folder / "estimate.parquet"
    for leftover in (est, folder / "estimate.parquet.partial"):  # the demo's own outputs
        if leftover.is_dir():
            shutil.rmtree(leftover)
        elif leftover.exists():
            leftover.unlink()
    (folder / "estimate.parquet.progress.json").unlink(missing_ok=True)
    show = _progress(args)
    log = _simulate(args, folder / "log.parquet")
    summary = estimate_file(log, _robot(args.robot), est, progress=show)
    pngs = plot_log(est, _robot(args.robot), folder, input_log=log, progress=show)
    from torchcontact.view.logs import demo_recording

    rrd = demo_recording(folder, log, est, _robot(args.robot), progress=show)
    print(f"simulated log:  {log}")
    print(f"estimates:      {est} ({summary['frames']} frames, {summary['frames_per_s']:.0f}/s)")
    for p in pngs:
        print(f"plot:           {p}")
    if rrd is not None:
        print(f"rerun view:     {rrd} (open it with: rerun {rrd})")
    else:
        print("rerun view:     pip install 'torchcontact[view]' to get demo.rrd too")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """PNGs of an estimated log."""
    from torchcontact.logs.plot import plot_log

    out = Path(args.out) if args.out else Path(args.log).with_suffix("")
    pngs = plot_log(
        args.log,
        _robot(args.robot),
        out,
        frame=args.frame,
        input_log=args.input,
        progress=_progress(args),
    )
    for p in pngs:
        print(p)
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    """ROS 1/2 bags or CSV -> log format."""
    from torchcontact.logs.convert import convert

    summary = convert(
        args.input,
        args.out,
        joint_states=args.joint_states,
        wrench_topics=args.wrench,
        contacts_topic=args.contacts_topic,
        contacts_file=args.contacts,
        robot=args.robot,
        joints=_names(args.joints),
        drop_joints=_names(args.drop_joints) or [],
        progress=_progress(args),
    )
    print(json.dumps(summary))
    return 0


def _add_sim_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", help="URDF (default: the bundled tcarm)")
    p.add_argument("--sensor", help="F/T sensor to simulate (default: the robot's first)")
    p.add_argument(
        "--contact-links",
        action="append",
        metavar="LINK[,LINK...]",
        help="links or frames touched (default: tcarm's skin frames, else every link of the"
        " sensor's subtree)",
    )
    p.add_argument("--frames", type=int, default=2000, help="number of frames (100 Hz)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--max-contacts", type=int, default=2, help="most simultaneous contacts")
    p.add_argument("--offset", type=float, nargs="+", help="sensor offset, 1 or 6 numbers")
    p.add_argument("--drift", type=float, nargs="+", help="thermal drift, 1 or 6 numbers")
    p.add_argument("--cable", type=float, default=0.0, help="cable force amplitude, N")
    p.add_argument("--cable-link", help="link the cable pulls on (default: tcarm's upper_arm)")
    p.add_argument("--payload", type=float, default=0.0, help="unmodelled payload, kg")
    p.add_argument("--payload-link", help="link carrying the payload (default: tcarm's hand)")
    p.add_argument("--noise", type=float, nargs="+", help="noise std, 1 or 6 numbers")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: torch default)")
    p.add_argument("--no-derivatives", action="store_true", help="omit qd/qdd (derive them)")
    p.add_argument(
        "--temperature",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="keep the temperature column",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_parser(subparsers: Any) -> None:
    """Register ``estimate``, ``simulate``, ``demo``, ``plot`` and ``convert``."""
    est = subparsers.add_parser("estimate", help="estimate contacts of every frame of logs")
    est.add_argument("inputs", nargs="+", metavar="INPUT", help="Parquet files, folders or globs")
    est.add_argument("--robot", help="URDF (default: the bundled tcarm)")
    est.add_argument(
        "--out", required=True, help="output file (one input) or folder; never an input"
    )
    est.add_argument("--sensor", action="append", help="F/T sensor to use (repeatable)")
    est.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device"
    )
    est.add_argument("--dtype", default="float64", choices=list(DTYPES), help="computation dtype")
    est.add_argument("--batch-size", type=int, default=8192, help="frames per chunk")
    est.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: default)")
    est.add_argument("--resume", action="store_true", help="finish an interrupted run")
    est.add_argument(
        "--engine", default="local", choices=["local", "ray"], help="local process or Ray"
    )
    est.add_argument("--workers", type=int, default=1, help="Ray tasks at once (--engine ray)")
    est.add_argument(
        "--residual",
        metavar="CHECKPOINT",
        help="residual checkpoint folder: subtract its learned F/T correction before estimating",
    )
    est.add_argument(
        "--velocity-margin",
        type=float,
        default=2.0,
        help="status bit 64 when |qd| > margin x the URDF velocity limit (0: no check)",
    )
    est.add_argument(
        "--ft-range",
        action="append",
        metavar="SENSOR=LIMIT[,...]",
        help="status bit 64 when a reading exceeds the sensor's range: 1 or 6 limits [N; N m]"
        " (repeatable)",
    )
    est.add_argument(
        "--constraints",
        action="store_true",
        help="friction-cone constrained estimate: pushing contacts stay inside the cone of their"
        " normal (contact field 'normal'; friction from 'friction'/'cone_angle' or the default)",
    )
    est.add_argument(
        "--friction", type=float, metavar="MU", help="default friction coefficient (--constraints)"
    )
    est.add_argument(
        "--cone-angle", type=float, metavar="RAD", help="default cone half-angle (--constraints)"
    )
    est.add_argument(
        "--cone-iterations",
        type=int,
        metavar="N",
        help="interior-point iteration budget (--constraints; default 25)",
    )
    est.add_argument(
        "--no-warm-start",
        action="store_true",
        help="start every frame from the pseudo-inverse, not its predecessor (--constraints)",
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
    plot.add_argument(
        "--frame",
        type=int,
        help="row of the robot view and of the unobservable directions (default: a well-posed"
        " frame; for nullspace.png the frame with the most unobservable directions)",
    )
    plot.add_argument(
        "--input", help="the input log (joint positions for robot.png and nullspace.png)"
    )
    plot.add_argument("--out", help="folder of the PNGs (default: the log's name without suffix)")
    plot.add_argument("--quiet", action="store_true", help="no progress bar")
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
    conv.add_argument("--contacts", help="contact-spec file (TOML or JSON)")
    conv.add_argument(
        "--robot", help="URDF: keep its joints, name F/T columns after its sensors' frames"
    )
    conv.add_argument(
        "--joints", action="append", metavar="J[,J...]", help="keep these joints, in this order"
    )
    conv.add_argument("--drop-joints", action="append", metavar="J[,J...]", help="drop joints")
    conv.add_argument("--quiet", action="store_true", help="no progress bar")
    conv.set_defaults(func=cmd_convert)
