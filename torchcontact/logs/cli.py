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
from torchcontact.logs._alloc import imports_uncollected, keep_freed_memory
from torchcontact.robot_arg import (
    add_robot_argument,
    add_strict_joints_argument,
    check_log_joints,
    resolve_robot_argument,
)

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

    names = ("friction", "cone_angle", "cone_iterations", "cone_objective")
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
    its = {} if args.cone_iterations is None else {"iterations": args.cone_iterations}
    from torchcontact.constrained import FrictionCones
    from torchcontact.logs.pipeline import LogConstraints

    cones = FrictionCones(**its, objective=args.cone_objective)
    return LogConstraints(cones, friction, warm_start=not args.no_warm_start)


def _describe_cones(c: dict) -> str:
    """The summary's ``cones`` in one line."""
    return (
        f"{c['converged']:.2%} of {c['solved']} solves converged,"
        f" {c['iterations_mean']:.1f} iterations on average; {c['converged_frames']} frames"
        f" converged, {c['not_converged_frames']} not (status bit 256);"
        f" {c['cone_active_frames']} with an active cone; {c['outside_cone_frames']} of"
        f" {c['well_posed_frames']} well-posed frames with the unconstrained estimate outside"
        " a cone"
    )


def _describe_noise(noise: dict) -> str:
    """The summary's ``noise`` in one line: the source of each sensor's, or why none."""
    if not noise["weighted"]:
        return f"unweighted solve ({noise['reason']})"
    parts = []
    for name, n in noise["sensors"].items():
        std = n["std"]
        val = "" if std is None else f" (std {std[0]:.3g} N, {std[3]:.3g} N m)"
        parts.append(f"{name} from {n['source']}{val}")
    return "weighted solve: " + "; ".join(parts)


def _localize(args: argparse.Namespace) -> dict[str, Any] | None:
    """``--localize`` and its options -> the options of a run's LogLocalize, or None."""
    given = [n for n in ("localize_ft_std",) if getattr(args, n) is not None]
    given += ["localize_ambiguous"] if args.localize_ambiguous else []
    given += ["localize_temporal"] if args.localize_temporal else []
    given += ["localize_threshold"] if args.localize_threshold != 1.0 else []
    if args.localize is None:
        if given:
            names = ", ".join(f"--{n.replace('_', '-')}" for n in given)
            raise InputError(f"{names} apply with --localize only")
        return None
    links: Any = _names([args.localize])
    if not links:
        raise InputError("--localize: name the candidate links, or 'subtree'")
    if links == ["subtree"]:
        links = "subtree"
    elif "subtree" in links:
        raise InputError("--localize: give link names or 'subtree', not both")
    std = None
    if args.localize_ft_std is not None:
        try:
            std = [float(x) for x in args.localize_ft_std.split(",")]
        except ValueError:
            std = []
        if len(std) != 6:
            raise InputError(
                f"--localize-ft-std takes 6 numbers FX,FY,FZ,MX,MY,MZ, got {args.localize_ft_std!r}"
            )
    return {
        "links": links,
        "force_threshold": args.localize_threshold,
        "accept_ambiguous": args.localize_ambiguous,
        "ft_std": std,
        "temporal": args.localize_temporal,
    }


def _fraction(text: str) -> float:
    """``--max-bad``: a number in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1], got {text!r}")
    return value


def _log_bias(args: argparse.Namespace) -> Any:
    """``--track-bias`` and its options as a :class:`~torchcontact.logs.chunks.LogBias`."""
    from torchcontact.logs.chunks import LogBias

    std = None
    if args.ft_std:
        try:
            std = tuple(float(v) for v in args.ft_std.split(","))
        except ValueError:
            raise InputError(
                f"--ft-std takes 6 numbers separated by commas, got {args.ft_std!r}"
            ) from None
    return LogBias(args.bias_time_constant, std, smoother=not args.no_smoother)


def _ray_prestart(args: argparse.Namespace) -> None:
    """``--engine ray``: start Ray and its workers' imports before this process imports torch.

    :func:`torchcontact.logs._ray_boot.prestart`, unless the run is to be refused: an option the
    Ray engine refuses gets its error without Ray's start-up first (the inputs are resolved
    before this is called).
    """
    if (
        args.workers < 1
        or not 0 < args.worker_cpus < float("inf")
        or not 0 <= args.keep_workers < float("inf")
        or args.track_bias
        or args.derivatives != "centred"
    ):
        return
    from torchcontact.logs._ray_boot import prestart, prestart_pool, running_cluster

    if args.keep_workers > 0:
        if running_cluster():  # else the engine refuses it, with Ray not started here
            prestart_pool(args.workers, args.worker_cpus, args.device, args.keep_workers)
        return
    prestart(args.workers, args.worker_cpus, args.device)


def _nvidia_driver() -> bool:
    """True where an NVIDIA driver is loaded (``--device auto`` may then pick CUDA)."""
    return Path("/dev/nvidiactl").exists()


def _start_vm_build(args: argparse.Namespace, files: list[Path]) -> None:
    """Start the tape VM's build now, before torch is imported, when the run will need it.

    A CPU run of a log of at least ``AUTO_BUILD_MIN_FRAMES`` frames runs its programs on the VM
    until their kernels are built; on an empty cache the VM's own build (a second of the
    compiler, once per machine and dtype) would start once the log is opened, after torch's
    import (2-2.5 s on the 2-core machine), and the run would wait for it. Started here
    (:func:`torchcontact._lightkernels.start_vm_build`; the kernels package adopts the build), it
    compiles on a core that the import leaves idle. ``--device cuda``, or ``auto`` on a machine
    with an NVIDIA driver, skips it (the VM runs CPU programs only).
    """
    if args.device == "cuda" or (args.device == "auto" and _nvidia_driver()):
        return
    import pyarrow as pa  # the run's own import (the allocators are set: keep_freed_memory)
    import pyarrow.parquet as pq

    from torchcontact._lightkernels import AUTO_BUILD_MIN_FRAMES, start_vm_build

    try:
        rows = pq.read_metadata(files[0]).num_rows if files else 0
    except (OSError, pa.ArrowException):  # the run reports an unreadable log in its own words
        return
    if rows >= AUTO_BUILD_MIN_FRAMES:
        start_vm_build("double" if args.dtype == "float64" else "float")


def cmd_estimate(args: argparse.Namespace) -> int:
    """Estimate the contacts of every frame of one or more logs.

    Exit codes: 0 when every input has usable frames; 1 when an input has none, or more than
    ``--max-bad`` of its frames have a non-zero status (its output is written all the same),
    and for data errors; 2 for usage errors; 130 when interrupted.
    """
    from torchcontact.logs.format import expand_inputs

    files = expand_inputs(args.inputs)  # a missing input's error before Ray's start-up
    keep_freed_memory()
    with imports_uncollected():
        if args.engine == "ray":  # the driver imports no torch: its workers estimate
            _ray_prestart(args)
        else:
            _start_vm_build(args, files)
            import torchcontact.logs.pipeline  # noqa: F401 - torch and the pipeline

            _threads(args)
        import pyarrow.compute  # noqa: F401 - the run's own imports
        import pyarrow.parquet  # noqa: F401

        from torchcontact.errors import LogError
        from torchcontact.logs.noise import parse_ft_noise
        from torchcontact.logs.run import unusable
    robot = resolve_robot_argument(args, logs=files)  # never silently the bundled arm
    if args.strict_joints:
        check_log_joints(files, robot.load(), strict=True)
    kwargs: dict[str, Any] = dict(
        sensors=args.sensor or None,
        batch_size=args.batch_size,
        device=args.device,
        dtype=args.dtype if args.engine == "ray" else _dtype(args.dtype),
        resume=args.resume,
        progress=_progress(args),
        velocity_margin=args.velocity_margin or None,
        ft_range=_ft_range(args.ft_range),
        constraints=_constraints(args),
        ft_noise=parse_ft_noise(args.ft_noise),
        unweighted=args.unweighted,
        localize=_localize(args),
    )
    if args.ft_noise and args.unweighted:
        raise InputError("give --ft-noise or --unweighted, not both")
    if args.residual:
        kwargs["residual"] = args.residual
    if args.derivatives != "centred":
        kwargs.update(derivatives=args.derivatives, derivative_window=args.derivative_window,
                      derivative_order=args.derivative_order)  # fmt: skip
    if args.track_bias:
        kwargs["track_bias"] = _log_bias(args)
    elif args.ft_std or args.no_smoother or args.bias_time_constant != 0.5:
        raise InputError("--bias-time-constant, --ft-std and --no-smoother apply with --track-bias")
    if args.derivatives != "causal" and (args.derivative_window, args.derivative_order) != (15, 3):
        raise InputError(
            "--derivative-window and --derivative-order apply with --derivatives causal"
        )
    try:
        if args.engine == "ray":
            why = {
                "track_bias": "--track-bias applies to --engine local only (its first pass reads"
                " the whole log in one process)",
                "derivatives": "--derivatives causal applies to --engine local only (Ray units"
                " carry the centred filter's context)",
            }
            for opt, msg in why.items():
                if opt in kwargs:
                    raise InputError(msg)
            from torchcontact.logs.ray_engine import estimate_files_ray

            kwargs.update(workers=args.workers, threads=args.threads, worker_cpus=args.worker_cpus,
                          keep_workers=args.keep_workers)  # fmt: skip
            summaries = estimate_files_ray(files, robot, args.out, **kwargs)
        else:
            if args.workers != 1:
                raise InputError("--workers applies to --engine ray only")
            if args.worker_cpus != 1:
                raise InputError("--worker-cpus applies to --engine ray only")
            if args.keep_workers:
                raise InputError("--keep-workers applies to --engine ray only")
            from torchcontact.logs.pipeline import estimate_files

            summaries = estimate_files(files, robot, args.out, **kwargs)
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
                + "".join(
                    f"; {r}: {v['localized']} frames localized"
                    + "".join(f", {n} {k.lower()}" for k, n in v["status"].items() if n)
                    for r, v in s.get("localize", {}).items()
                )
            )
            if "cones" in s:
                print(f"  cones: {_describe_cones(s['cones'])}")
            if "noise" in s:
                print(f"  noise: {_describe_noise(s['noise'])}")
    failed = [m for m in (unusable(s, args.max_bad) for s in summaries) if m]
    if failed:
        raise LogError("; ".join(failed) + " (the outputs are written, with each frame's status)")
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
    robot = resolve_robot_argument(args)
    assert robot is not None  # simulate and demo default to tcarm
    check_outputs([out, out.with_name(out.name + ".tmp")], [robot])
    model = load_robot(robot)
    surface = _contact_surface(args, model, robot)
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
        skin=not getattr(args, "no_skin", False),
        surface=surface,
        robot=robot.robot,
        ft_sensors=[str(s) for s in robot.ft_sensors],
    )


def _contact_surface(args: argparse.Namespace, model: Any, robot: Any) -> Any:
    """The collision meshes of the contact links (``simulate --on-collision-mesh``), or None."""
    if not getattr(args, "on_collision_mesh", False):
        return None
    from torchcontact.meshes import load_meshes
    from torchcontact.simulation import contact_setup

    _, links = contact_setup(model, args.sensor, _names(args.contact_links))
    meshes = load_meshes(model, robot, "collision", links=links)
    bare = [n for n in links if n not in meshes.links]
    if bare:
        raise InputError(
            f"--on-collision-mesh: contact links {bare} have no collision mesh"
            " (name others with --contact-links)"
        )
    return meshes.links


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
    robot = resolve_robot_argument(args)
    summary = estimate_file(log, robot, est, progress=show)
    pngs = plot_log(est, robot, folder, input_log=log, progress=show)
    from torchcontact.view.logs import demo_recording

    rrd = demo_recording(folder, log, est, robot, progress=show)
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
    """PNGs of an estimated log (one writer per output folder: ``OUT.lock``)."""
    from torchcontact._lock import OutputLock
    from torchcontact.logs.plot import plot_log

    out = Path(args.out) if args.out else Path(args.log).with_suffix("")
    # without --robot: the robot recorded by the input log, else the estimate's URDF sha256
    robot = resolve_robot_argument(args, logs=[args.log, *([args.input] if args.input else [])])
    if args.strict_joints and args.input:
        check_log_joints([args.input], robot.load(), strict=True)
    with OutputLock(out, "plot"):
        pngs = plot_log(
            args.log,
            robot,
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

    robot = resolve_robot_argument(args)
    summary = convert(
        args.input,
        args.out,
        joint_states=args.joint_states,
        wrench_topics=args.wrench,
        contacts_topic=args.contacts_topic,
        contacts_file=args.contacts,
        robot=robot,
        joints=_names(args.joints),
        drop_joints=_names(args.drop_joints) or [],
        progress=_progress(args),
    )
    print(json.dumps(summary))
    return 0


def _add_sim_args(p: argparse.ArgumentParser) -> None:
    add_robot_argument(p, default="tcarm", what="the robot simulated")
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
    p.add_argument(
        "--offset",
        type=float,
        nargs="+",
        help="sensor offset, 1 or 6 numbers [N; N m] (default: 0)",
    )
    p.add_argument(
        "--drift", type=float, nargs="+", help="thermal drift, 1 or 6 numbers [N; N m] (default: 0)"
    )
    p.add_argument("--cable", type=float, default=0.0, help="cable force amplitude, N")
    p.add_argument("--cable-link", help="link the cable pulls on (default: tcarm's upper_arm)")
    p.add_argument("--payload", type=float, default=0.0, help="unmodelled payload, kg")
    p.add_argument("--payload-link", help="link carrying the payload (default: tcarm's hand)")
    p.add_argument(
        "--noise", type=float, nargs="+", help="noise std, 1 or 6 numbers [N; N m] (default: 0)"
    )
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads, 0: torch's default")
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
    add_robot_argument(
        est,
        default_help="the robot recorded in the logs' metadata by simulate or convert --robot;"
        " never silently the bundled arm",
    )
    add_strict_joints_argument(est)
    est.add_argument(
        "--out", required=True, help="output file (one input) or folder; never an input"
    )
    est.add_argument(
        "--sensor",
        action="append",
        help="F/T sensor to use (repeatable; default: every sensor of the robot the log has)",
    )
    est.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device"
    )
    est.add_argument("--dtype", default="float64", choices=list(DTYPES), help="computation dtype")
    est.add_argument("--batch-size", type=int, default=8192, help="frames per chunk")
    est.add_argument("--threads", type=int, default=1, help="torch CPU threads, 0: torch's default")
    est.add_argument("--resume", action="store_true", help="finish an interrupted run")
    est.add_argument(
        "--engine", default="local", choices=["local", "ray"], help="local process or Ray"
    )
    est.add_argument("--workers", type=int, default=1, help="Ray tasks at once (--engine ray)")
    est.add_argument(
        "--worker-cpus",
        type=float,
        default=1.0,
        metavar="N",
        help="CPUs Ray reserves per task (--engine ray); from 2 on a task decodes, estimates and"
        " encodes on overlapping threads, below 2 in turn (default: 1)",
    )
    est.add_argument(
        "--keep-workers",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="--engine ray on a running cluster (RAY_ADDRESS): the worker processes stay this"
        " long after their last unit, with the model built, for the next runs (a pool of"
        " detached actors, each holding its CPUs until it ends; 0: none stay)",
    )
    est.add_argument(
        "--residual",
        metavar="CHECKPOINT",
        help="residual checkpoint folder: subtract its learned F/T correction before estimating"
        " (default: none)",
    )
    est.add_argument(
        "--velocity-margin",
        type=float,
        default=2.0,
        help="status bit 64 when |qd| > margin x the URDF velocity limit, 0: no check",
    )
    est.add_argument(
        "--ft-range",
        action="append",
        metavar="SENSOR=LIMIT[,...]",
        help="status bit 64 when a reading exceeds the sensor's range: 1 or 6 limits [N; N m]"
        " (repeatable; default: no range check)",
    )
    est.add_argument(
        "--ft-noise",
        action="append",
        metavar="SENSOR=SIGMA_F,SIGMA_M",
        help="reading noise std of a sensor, N and N m (or 6 numbers FX,..,MZ, or a driver profile"
        " with datasheet noise, e.g. robotiq-ft300), weighing the solve (repeatable; default: the"
        " log's ft_cov.<sensor> column, else the profile in its metadata, else an estimate from"
        " its contact-free frames; docs/accuracy.md)",
    )
    est.add_argument(
        "--unweighted",
        action="store_true",
        help="the paper's unweighted pinv(A) b: ignore the reading noise (default: weighted)",
    )
    est.add_argument(
        "--constraints",
        action="store_true",
        help="friction-cone constrained estimate: pushing contacts stay inside the cone of their"
        " normal (contact field 'normal'; friction from 'friction'/'cone_angle' or the default)",
    )
    est.add_argument(
        "--friction",
        type=float,
        metavar="MU",
        help="friction coefficient of contacts whose record gives neither friction nor cone_angle"
        " (--constraints; default: none, every contact must give one)",
    )
    est.add_argument(
        "--cone-angle",
        type=float,
        metavar="RAD",
        help="cone half-angle of those contacts, instead of --friction (--constraints; default:"
        " none)",
    )
    est.add_argument(
        "--cone-iterations",
        type=int,
        metavar="N",
        help="interior-point iteration budget (--constraints; default 25)",
    )
    est.add_argument(
        "--cone-objective",
        choices=["map", "min_norm"],
        help="the estimate inside the cones: map (maximum a posteriori under a stated prior) or"
        " min_norm (--constraints; default: map in float64, min_norm in float32;"
        " docs/accuracy.md)",
    )
    est.add_argument(
        "--no-warm-start",
        action="store_true",
        help="start every frame from the pseudo-inverse, not its predecessor (--constraints)",
    )
    est.add_argument(
        "--track-bias",
        action="store_true",
        help="track each F/T sensor's offset over the log against the model on contact-free"
        " frames (two passes: the online tracker's filter and a forward-backward smoother) and"
        " subtract it; adds bias.<sensor>, bias_std.<sensor> columns and the summary's bias;"
        " with --residual the tracked offset replaces the checkpoint's offset layer",
    )
    est.add_argument(
        "--bias-time-constant",
        type=float,
        default=0.5,
        metavar="S",
        help="--track-bias: time constant of the offset tracker, s (default: 0.5)",
    )
    est.add_argument(
        "--ft-std",
        metavar="FX,FY,FZ,MX,MY,MZ",
        help="--track-bias: F/T noise standard deviations, N and N m: the offset's reported"
        " uncertainty (default: 0.05 N and 0.005 N m)",
    )
    est.add_argument(
        "--no-smoother",
        action="store_true",
        help="--track-bias: the causal filter alone (what the robot tracks online), no backward"
        " pass (default: forward-backward)",
    )
    est.add_argument(
        "--derivatives",
        choices=["centred", "causal"],
        default="centred",
        help="derived qd, qdd (logs without them): centred Savitzky-Golay, or the live loop's"
        " causal filter so that the estimate matches what the robot computes online"
        " (default: centred)",
    )
    est.add_argument(
        "--derivative-window",
        type=int,
        default=15,
        metavar="N",
        help="--derivatives causal: frames of the fit (default: 15)",
    )
    est.add_argument(
        "--derivative-order",
        type=int,
        default=3,
        metavar="P",
        help="--derivatives causal: polynomial degree, 3 for no low-frequency delay (default: 3)",
    )
    est.add_argument(
        "--localize",
        metavar="LINK[,LINK...]",
        help="in frames without a skin contact in a sensor's region, localize one contact from"
        " the F/T wrench and these candidate links' collision meshes, or every link with a"
        " collision mesh in a sensor's subtree with 'subtree', and estimate it as a force"
        " contact there (needs the meshes extra; default: none, no localization)",
    )
    est.add_argument(
        "--localize-threshold",
        type=float,
        default=1.0,
        metavar="N",
        help="no contact below this force, N (--localize)",
    )
    est.add_argument(
        "--localize-ambiguous",
        action="store_true",
        help="also estimate the first candidate where the line of action enters the links at"
        " several points (status bit 16; default: those frames are estimated contact-free)"
        " (--localize)",
    )
    est.add_argument(
        "--localize-temporal",
        action="store_true",
        help="resolve ambiguous frames by the contact of the nearest unambiguous frame of the"
        " same run of contact (consecutive frames above the threshold in one time segment;"
        " status bit 256) (--localize)",
    )
    est.add_argument(
        "--localize-ft-std",
        metavar="FX,FY,FZ,MX,MY,MZ",
        help="F/T noise standard deviations, N and N m, for the localized point's"
        " localize_position_std (--localize; default: none, the column is NaN)",
    )
    est.add_argument(
        "--max-bad",
        type=_fraction,
        default=1.0,
        metavar="FRACTION",
        help="exit 1 when more than this share of an input's frames has a non-zero status (1:"
        " only when no frame is usable)",
    )
    est.add_argument("--json", action="store_true", help="print a JSON summary at the end")
    est.add_argument("--quiet", action="store_true", help="no progress bar")
    est.set_defaults(func=cmd_estimate)

    sim = subparsers.add_parser("simulate", help="write a simulated log with known contacts")
    _add_sim_args(sim)
    sim.add_argument("--out", required=True, help="output Parquet file")
    sim.add_argument(
        "--no-skin",
        action="store_true",
        help="a log without skin: empty contacts (the truth in true_contacts), for estimate"
        " --localize",
    )
    sim.add_argument(
        "--on-collision-mesh",
        action="store_true",
        help="put the contacts on the contact links' collision meshes (needs the meshes extra)",
    )
    sim.set_defaults(func=cmd_simulate)

    demo = subparsers.add_parser("demo", help="simulate -> estimate -> plot into a folder")
    _add_sim_args(demo)
    demo.add_argument("--out", default="torchcontact-demo", help="output folder")
    demo.set_defaults(func=cmd_demo)

    plot = subparsers.add_parser("plot", help="PNG plots of an estimated log")
    plot.add_argument("log", help="output of torchcontact estimate")
    add_robot_argument(
        plot,
        default_help="the robot recorded in the --input log, else the known robot with the"
        " estimate's URDF sha256",
    )
    add_strict_joints_argument(plot)
    plot.add_argument(
        "--frame",
        type=int,
        help="row of the robot view and of the unobservable directions (default: a well-posed"
        " frame; for nullspace.png the frame with the most unobservable directions)",
    )
    plot.add_argument(
        "--input",
        help="the input log, for the joint positions of robot.png and nullspace.png (default:"
        " none, and those two are not drawn)",
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
        help="geometry_msgs/WrenchStamped topic, optionally =sensor name (repeatable; bags need"
        " one; default sensor name: the robot's sensor of the header's frame_id, else the"
        " frame_id)",
    )
    conv.add_argument(
        "--contacts-topic",
        help="geometry_msgs/PointStamped topic of contact points, frame_id = link (default: none)",
    )
    conv.add_argument("--contacts", help="contact-spec file, TOML or JSON (default: none)")
    add_robot_argument(
        conv,
        what="keep its joints (in its order), name F/T columns after its sensors and record it in"
        " the log for estimate",
        default_help="none: keep every joint",
    )
    conv.add_argument(
        "--joints",
        action="append",
        metavar="J[,J...]",
        help="keep these joints, in this order (default: the robot's, else every joint seen)",
    )
    conv.add_argument(
        "--drop-joints", action="append", metavar="J[,J...]", help="drop joints (default: none)"
    )
    conv.add_argument("--quiet", action="store_true", help="no progress bar")
    conv.set_defaults(func=cmd_convert)
