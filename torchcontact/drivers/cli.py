"""Command-line jobs of the drivers: ``sensor simulate``, ``sensor read`` and ``run``.

Registered by :func:`add_parser` from ``torchcontact/cli.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from torchcontact.drivers.profiles import available_profiles
from torchcontact.errors import InputError, TorchContactError
from torchcontact.robot_arg import add_robot_argument, resolve_robot_argument


def _is_loopback(host: str) -> bool:
    return host == "localhost" or host.startswith("127.")


def _make_source(args: argparse.Namespace) -> Any:
    from torchcontact.drivers.modbus import ModbusFTSensor, parse_hostport, quiet_pymodbus
    from torchcontact.drivers.profiles import load_profile
    from torchcontact.drivers.robotiq import RobotiqFT300

    quiet_pymodbus()
    profile = load_profile(args.profile)
    name = args.sensor or profile.name.replace("-", "_")
    if args.tcp:
        if args.stream:
            raise InputError("--stream needs a serial port (--port): stream mode is RS-485 only")
        host, port = parse_hostport(args.tcp)
        return ModbusFTSensor(profile, host=host, tcp_port=port, timeout=args.timeout, name=name)
    if profile.stream is not None or profile.name.startswith("robotiq"):
        return RobotiqFT300(
            args.port, stream=args.stream, profile=profile, timeout=args.timeout, name=name
        )
    if args.stream:
        raise InputError(f"profile {profile.name!r} has no stream mode")
    return ModbusFTSensor(profile, port=args.port, timeout=args.timeout, name=name)


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    """ValueErrors of the driver and estimator set-up are user errors (bad port, spec, module)."""
    try:
        yield
    except TorchContactError:
        raise
    except ValueError as exc:
        raise InputError(str(exc)) from exc


def _add_source_args(p: argparse.ArgumentParser, log: bool = False) -> None:
    p.add_argument("--profile", default="robotiq-ft300", help=f"one of {available_profiles()}")
    where = p.add_mutually_exclusive_group(required=True)
    other = "--tcp or --log" if log else "--tcp"
    where.add_argument(
        "--port", help=f"serial port (Modbus RTU), e.g. /dev/ttyUSB0 (default: none; or {other})"
    )
    where.add_argument(
        "--tcp",
        metavar="HOST:PORT",
        help=f"Modbus TCP server (default: none; or {other.replace('--tcp', '--port')})",
    )
    if log:
        where.add_argument(
            "--log",
            metavar="LOG.parquet",
            help="replay a recorded log (torchcontact log format) through --onnx or --c-step"
            " instead of reading sensors: its F/T readings, joint states (qd/qdd derived as"
            " estimate does when absent) and contact records, frame by frame (default: none)",
        )
    p.add_argument("--stream", action="store_true", help="FT 300 stream mode (100 Hz)")
    p.add_argument(
        "--sensor",
        help="sensor name for the log column ft.<sensor> (default: the profile's name; with"
        " --onnx, the graph's first sensor)",
    )
    p.add_argument("--timeout", type=float, default=0.05, help="response timeout, s")
    p.add_argument(
        "--duration", type=float, default=None, help="stop after S seconds (default: never)"
    )
    p.add_argument("--out", help="Parquet log of the frames, t_ns and ft.<sensor> (default: none)")
    p.add_argument(
        "--tare",
        type=int,
        nargs="?",
        const=100,
        default=0,
        metavar="N",
        help="zero over N frames (100 when N is left out): the sensor's software zero; run with"
        " a step with online inputs (--c-step, --onnx exported with --online): from the model,"
        " the reading less its prediction, once N frames in a row are contact-free (default: 0,"
        " no zero)",
    )


def cmd_simulate(args: argparse.Namespace) -> int:
    """Run a simulated sensor until interrupted or ``--duration`` elapsed."""
    from torchcontact.drivers.modbus import parse_hostport
    from torchcontact.drivers.simulator import (
        Faults,
        RtuSimulator,
        TcpSimulator,
        parquet_signal,
        sine_signal,
    )

    faults = Faults(
        drop=args.drop,
        corrupt=args.corrupt,
        split=args.split,
        delay_s=args.delay,
        disconnect_every_s=args.disconnect_every,
        disconnect_s=args.disconnect_for,
        streaming_at_start=args.streaming_at_start,
        seed=args.seed,
    )
    sig = parquet_signal(args.replay, args.replay_sensor) if args.replay else sine_signal()
    if args.tcp:
        host, port = parse_hostport(args.tcp, allow_zero=True)
        if not _is_loopback(host) and not args.allow_remote:
            raise InputError(f"refusing to serve on {host}: loopback only (--allow-remote)")
        sim: Any = TcpSimulator(args.profile, sig, faults, host=host, port=port).start()
        print(f"serving {args.profile} on tcp {sim.host}:{sim.port}", flush=True)
    else:
        sim = RtuSimulator(args.profile, sig, faults, link=args.link).start()
        print(f"serving {args.profile} on pty {sim.port}", flush=True)
    stop = {"flag": False}

    def _on_term(*_: object) -> None:
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _on_term)
    end = time.monotonic() + args.duration if args.duration else float("inf")
    try:
        while not stop["flag"] and time.monotonic() < end:
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    print(json.dumps({"simulator": sim.stats.as_dict()}), flush=True)
    return 0


def cmd_read(args: argparse.Namespace) -> int:
    """Read a sensor, print live values and statistics, optionally log to Parquet."""
    from torchcontact.drivers.log import FTLogWriter

    with _user_errors():
        src = _make_source(args)
        log = FTLogWriter(args.out, src.name, profile=args.profile) if args.out else None
        src.open()
    if getattr(src, "identity", None):
        ident = {k: v for k, v in src.identity.items() if k != "raw"}
        print(f"identity: {json.dumps(ident)}", flush=True)
    end = time.monotonic() + args.duration if args.duration else float("inf")
    t_start = time.monotonic()
    next_print = t_start
    try:
        if args.tare:
            print(f"tare: {src.tare(args.tare).round(4).tolist()}", flush=True)
        while time.monotonic() < end:
            s = src.read(min(0.1, max(0.001, end - time.monotonic())))
            if s is None:
                continue
            if log is not None:
                log.append(s.t_ns, s.wrench)
            now = time.monotonic()
            if now >= next_print:
                rate = src.stats.frames / max(now - t_start, 1e-9)
                values = " ".join(f"{v:+9.3f}" for v in s.wrench)
                print(f"seq {s.seq:7d}  [{values}]  {rate:6.1f} Hz  {src.stats.as_dict()}")
                sys.stdout.flush()
                next_print = now + 0.5
    except KeyboardInterrupt:
        pass
    finally:
        src.close()
        if log is not None:
            log.close()
    summary = {
        "stats": src.stats.as_dict(),
        "rate_hz": src.stats.frames / (time.monotonic() - t_start),
    }
    if log is not None:
        summary["log"] = {"path": str(args.out), "rows": log.rows}
    print(json.dumps(summary), flush=True)
    return 0


def _floats(text: str, option: str, n: tuple[int, ...]) -> list[float]:
    """``A,B,C`` as floats (``n``: the counts allowed)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"{option} takes numbers separated by commas, got {text!r}") from None
    if len(vals) not in n:
        raise InputError(f"{option} takes {' or '.join(map(str, n))} numbers, got {text!r}")
    return vals


def _online_options(args: argparse.Namespace) -> dict[str, Any]:
    """The runtime estimator's online options from ``run``'s arguments."""
    opts: dict[str, Any] = {"track_bias": bool(args.track_bias)}
    tracker: dict[str, Any] = {"time_constant": args.bias_time_constant}
    if not args.bias_time_constant > 0:
        raise InputError(f"--bias-time-constant must be > 0 s, got {args.bias_time_constant}")
    if args.ft_std:
        tracker["ft_std"] = _floats(args.ft_std, "--ft-std", (6,))
    if args.bias_gate is not None:
        tracker["gate"] = args.bias_gate
    opts["tracker_options"] = tracker
    payloads = []
    for item in args.payload or []:
        parts = item.split(",")
        if len(parts) not in (4, 5):
            raise InputError(f"--payload takes MASS,CX,CY,CZ[,LINK], got {item!r}")
        mass, *com = _floats(",".join(parts[:4]), "--payload", (4,))
        payloads.append((mass, com, parts[4] if len(parts) == 5 else None))
    opts["payloads"] = payloads
    opts["identify"] = args.identify_payload
    opts["tare"] = args.tare
    return opts


def _runtime_estimator(args: argparse.Namespace) -> tuple[Any, Any]:
    """``run --onnx`` / ``--c-step``: the exported estimator and its F/T source.

    ``--contacts SPEC`` (the contact-spec file) fills the file's slots; without it every slot is
    inactive. The sensor given by ``--port``/``--tcp`` is ``--sensor`` (default: the file's
    first); ``--source NAME=ADDRESS`` adds the others (``tcp://HOST:PORT`` or a serial port, same
    profile). ``--extra NAME=VALUE`` gives constant extra inputs of the residual corrections.
    ``--track-bias``, ``--tare``, ``--payload``, ``--identify-payload``: the online state.
    """
    from torchcontact.contacts import SlotLayout, load_contact_spec
    from torchcontact.drivers.live import RuntimeEstimator, SensorGroup

    path = args.onnx or args.c_step
    extra = {}
    for item in args.extra or []:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise InputError(f"--extra takes NAME=VALUE, got {item!r}")
        try:
            extra[name] = float(value)
        except ValueError:
            raise InputError(f"--extra takes NAME=VALUE (a number), got {item!r}") from None
    robot: Any = resolve_robot_argument(args)
    if robot is not None:  # identified by its URDF's hash (no torch), its model with --ft-sensor
        robot = robot.load() if robot.ft_sensors else os.fspath(robot)
    est = RuntimeEstimator(
        path,
        None,
        robot=robot,
        residual=args.residual or None,
        backend="c" if args.c_step else "onnx",
        **_online_options(args),
    )
    rt = est.runtime
    spec: dict[str, Any] = {"positions": np.zeros((rt.K, 3)), "active": np.zeros(rt.K)}
    if args.contacts:
        records = load_contact_spec(args.contacts).static()
        layout = SlotLayout(rt.slot_links, rt.slot_kinds)
        arrays, slot = layout.fill(records, 1)
        if (slot < 0).any():
            left = [f"{records.links[i]}:{records.kinds[i]}" for i in np.flatnonzero(slot < 0)]
            slots = [f"{a}:{b}" for a, b in zip(layout.links, layout.kinds, strict=True)]
            raise InputError(
                f"--contacts {args.contacts}: {left} find no free slot in {path}, whose"
                f" slots are {slots}"
            )
        spec = {k: v[0] for k, v in arrays.items()}
    if extra:
        spec["extra"] = extra
    est.set_inputs(spec)
    primary = args.sensor or rt.sensor_names[0]
    if primary not in rt.sensor_names:
        raise InputError(f"--sensor {primary!r} is not one of the file's {list(rt.sensor_names)}")
    addresses = {primary: None}
    for item in args.source or []:
        name, sep, address = item.partition("=")
        if not sep or name not in rt.sensor_names:
            raise InputError(
                f"--source takes SENSOR=ADDRESS with SENSOR one of"
                f" {list(rt.sensor_names)}, got {item!r}"
            )
        addresses[name] = address
    missing = [s for s in rt.sensor_names if s not in addresses]
    if missing:
        raise InputError(
            f"{path} reads sensors {list(rt.sensor_names)}; give the others with --source"
            f" NAME=tcp://HOST:PORT (or a serial port): missing {missing}"
        )
    sources = []
    for name in rt.sensor_names:
        sub = argparse.Namespace(**vars(args))
        sub.sensor = name
        if addresses[name] is not None:
            a = addresses[name]
            sub.tcp, sub.port = (
                (a.removeprefix("tcp://"), None) if a.startswith("tcp://") else (None, a)
            )
        sources.append(_make_source(sub))
    return est, sources[0] if len(sources) == 1 else SensorGroup(sources)


def cmd_run(args: argparse.Namespace) -> int:
    """Run the live loop: sensor + joint states -> estimator -> JSON lines."""
    from torchcontact.drivers.live import (
        CausalJointSource,
        JsonLinesPublisher,
        LiveLoop,
        UdpJointSource,
        UdpPublisher,
        json_line,
        load_estimator,
    )
    from torchcontact.drivers.log import FTLogWriter
    from torchcontact.drivers.modbus import parse_hostport
    from torchcontact.errors import ModelMismatchError

    if args.log:
        with _user_errors():
            return _cmd_replay(args)
    with _user_errors():
        exported = args.onnx or args.c_step
        if args.derivatives == "causal":
            from torchcontact.online.derivatives import CausalDerivatives

            if not args.joints:
                raise InputError("--derivatives causal needs joint states (--joints)")
            CausalDerivatives(1, args.derivative_window, args.derivative_order)  # checks them
        if args.contacts and not exported:
            raise InputError("--contacts applies to --onnx or --c-step (the exported estimator)")
        if exported:
            estimator, src = _runtime_estimator(args)
        else:
            given = {"--source": args.source, "--residual": args.residual, "--robot": args.robot,
                     "--ft-sensor": args.ft_sensor, "--extra": args.extra,
                     "--track-bias": args.track_bias, "--payload": args.payload,
                     "--identify-payload": args.identify_payload is not None}  # fmt: skip
            bad = [k for k, v in given.items() if v]
            if bad:
                raise InputError(f"{', '.join(bad)}: only with --onnx or --c-step")
            estimator = load_estimator(args.estimator)
            src = None
        joints_at = parse_hostport(args.joints.removeprefix("udp://")) if args.joints else None
        publish_at = None
        if args.publish != "stdout":
            publish_at = parse_hostport(args.publish.removeprefix("udp://"))
        publishers: list[Any] = []
        if publish_at is None:
            publishers.append(JsonLinesPublisher(sys.stdout))
        else:
            publishers.append(UdpPublisher(*publish_at, allow_remote=args.allow_remote))
        if src is None:
            src = _make_source(args)
        view = None
        if args.view:
            if not args.onnx:
                raise InputError("--view goes with --onnx (the exported estimator) and --robot")
            from torchcontact.view.scene import LiveView

            view = LiveView.for_estimator(estimator, args.robot, args.view)
        src.open()
        if args.tare and not exported:  # the sensor's software zero (no model to zero from)
            print(f"tare: {src.tare(args.tare).round(4).tolist()}", file=sys.stderr, flush=True)
    joints: Any = None
    if joints_at is not None:
        udp = UdpJointSource(*joints_at)
        print(f"joint states on udp {udp.address[0]}:{udp.address[1]}", file=sys.stderr)
        joints = udp
    if args.derivatives == "causal":
        joints = CausalJointSource(joints, args.derivative_window, args.derivative_order)
        print(json_line({"derivatives": joints.describe()}), file=sys.stderr, flush=True)
    log = None
    if args.out:
        runtime = getattr(estimator, "runtime", None)
        sensors = list(runtime.sensor_names) if exported else [src.name]
        online = runtime is not None and runtime.online is not None
        log = FTLogWriter(args.out, sensors, bias=online, profile=getattr(args, "profile", None))
    loop = LiveLoop(src, joints, estimator, publishers, log=log, require_joints=args.require_joints,
                    on_frame=view)  # fmt: skip
    try:
        summary = loop.run(duration=args.duration)
    except ModelMismatchError as exc:  # the joint states come from another robot: stop
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        src.close()
        if log is not None:
            log.close()
        if joints is not None:
            joints.close()
        if view is not None:
            view.close()
    if hasattr(estimator, "summary"):
        summary["online"] = estimator.summary()
    if isinstance(joints, CausalJointSource):
        summary["derivatives"] = joints.describe()
    print(json_line({"summary": summary}), file=sys.stderr, flush=True)
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    """``run --onnx GRAPH --log LOG``: the log's frames through the exported estimator."""
    from torchcontact.drivers.live import (
        JsonLinesPublisher,
        RuntimeEstimator,
        UdpPublisher,
        json_line,
    )
    from torchcontact.drivers.log import FTLogWriter
    from torchcontact.drivers.modbus import parse_hostport
    from torchcontact.drivers.replay import replay_log

    path = args.onnx or args.c_step
    if not path:
        raise InputError("--log replays a log through an exported estimator: give --onnx or"
                         " --c-step")  # fmt: skip
    given = {"--joints": args.joints, "--source": args.source, "--contacts": args.contacts,
             "--view": args.view, "--stream": args.stream, "--extra": args.extra,
             "--derivatives causal": args.derivatives == "causal",
             "--duration": args.duration is not None}  # fmt: skip
    bad = [k for k, v in given.items() if v]
    if bad:
        raise InputError(
            f"{', '.join(bad)}: not with --log (the log gives the readings, joint states,"
            " contacts and extra columns)"
        )
    spec = resolve_robot_argument(args, logs=[args.log])
    model = spec.load()
    est = RuntimeEstimator(
        path,
        None,
        robot=model,
        residual=args.residual or None,
        backend="c" if args.c_step else "onnx",
        **_online_options(args),
    )
    rt = est.runtime
    if args.publish == "stdout":
        publishers: list[Any] = [JsonLinesPublisher(sys.stdout)]
    else:
        at = parse_hostport(args.publish.removeprefix("udp://"))
        publishers = [UdpPublisher(*at, allow_remote=args.allow_remote)]
    log = None
    if args.out:
        log = FTLogWriter(args.out, list(rt.sensor_names), bias=rt.online is not None)
    try:
        summary = replay_log(args.log, est, model, publishers, log=log)
    finally:
        if log is not None:
            log.close()
    summary["online"] = est.summary()
    print(json_line({"summary": summary}), file=sys.stderr, flush=True)
    if summary["frames"] and summary["log_errors"] == summary["frames"]:
        print(f"error: {args.log}: no frame had a usable joint state and reading", file=sys.stderr)
        return 1
    return 0


def add_parser(subparsers: Any) -> None:
    """Register ``sensor simulate``, ``sensor read`` and ``run`` on the top-level subparsers."""
    sensor = subparsers.add_parser("sensor", help="F/T sensor drivers and simulator")
    sensor_sub = sensor.add_subparsers(dest="sensor_command", metavar="SENSOR_COMMAND")
    sensor.set_defaults(func=lambda _args: (sensor.print_help(), 2)[1])

    sim = sensor_sub.add_parser("simulate", help="serve a simulated sensor (pty or Modbus TCP)")
    sim.add_argument("--profile", default="robotiq-ft300", help=f"one of {available_profiles()}")
    where = sim.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="Modbus RTU on a pseudo-terminal")
    where.add_argument(
        "--tcp",
        metavar="HOST:PORT",
        help="Modbus TCP, e.g. 127.0.0.1:1502 (default: none; or --pty)",
    )
    sim.add_argument(
        "--link", help="stable path for the pty, a symlink (default: a temporary path)"
    )
    sim.add_argument("--allow-remote", action="store_true", help="allow a non-loopback address")
    sim.add_argument(
        "--replay", help="Parquet log to replay, column ft.<sensor> (default: a sinusoid)"
    )
    sim.add_argument(
        "--replay-sensor",
        help="sensor name of the replayed column (default: the log's first ft.* column)",
    )
    sim.add_argument(
        "--duration", type=float, default=None, help="stop after S seconds (default: never)"
    )
    sim.add_argument("--drop", type=float, default=0.0, help="probability a frame is dropped")
    sim.add_argument("--corrupt", type=float, default=0.0, help="probability of a bad CRC")
    sim.add_argument("--split", type=float, default=0.0, help="probability a write is split")
    sim.add_argument("--delay", type=float, default=0.0, help="extra response delay, s")
    sim.add_argument("--disconnect-every", type=float, default=0.0, help="unplug every S s")
    sim.add_argument("--disconnect-for", type=float, default=0.3, help="unplugged for S s")
    sim.add_argument("--streaming-at-start", action="store_true", help="start in stream mode")
    sim.add_argument("--seed", type=int, default=0, help="seed of the fault injection")
    sim.set_defaults(func=cmd_simulate)

    read = sensor_sub.add_parser("read", help="read a sensor, show values, log to Parquet")
    _add_source_args(read)
    read.set_defaults(func=cmd_read)

    run = subparsers.add_parser("run", help="live loop: sensor + joints -> estimator -> JSON")
    _add_source_args(run, log=True)
    which = run.add_mutually_exclusive_group()
    which.add_argument(
        "--estimator",
        default="torchcontact.drivers.live:passthrough_estimator",
        help="module:function called as f(q, qd, qdd, ft) -> dict",
    )
    which.add_argument(
        "--onnx",
        metavar="FILE.onnx",
        help="exported contact estimator (torchcontact export estimator), run with onnxruntime"
        " (default: none, --estimator runs)",
    )
    which.add_argument(
        "--c-step",
        metavar="LIB.so",
        help="exported C step library (export estimator --format c) via ctypes: no onnxruntime"
        " (default: none)",
    )
    add_robot_argument(
        run,
        what="with --onnx or --c-step, the robot the graph or library was exported for (one"
        " exported for another robot is refused)",
        default_help="none: the graph is not checked against a robot",
    )
    run.add_argument(
        "--source",
        action="append",
        metavar="SENSOR=ADDRESS",
        help="with --onnx: another sensor of the graph, tcp://HOST:PORT or a serial port"
        " (repeatable; default: none, the graph reads one sensor)",
    )
    run.add_argument(
        "--residual",
        action="append",
        metavar="FILE.onnx",
        help="with --onnx: a residual-correction graph to chain (repeatable; default: none)",
    )
    run.add_argument(
        "--extra",
        action="append",
        metavar="NAME=VALUE",
        help="with --onnx: a constant extra input of the corrections (repeatable; default: none)",
    )
    run.add_argument(
        "--contacts",
        metavar="SPEC",
        help='with --onnx: contact-spec file (TOML [[contact]] tables or JSON {"contact": [...]},'
        " each with link, kind, position), placed in the graph's slots; default no contact",
    )
    run.add_argument(
        "--track-bias",
        action="store_true",
        help="with --c-step or --onnx (exported with --online): track each sensor's offset"
        " against the model while no contact is active (no active slot in its region, no"
        " contact flag in the joint state); every record and --out row carry the bias state",
    )
    run.add_argument(
        "--bias-time-constant",
        type=float,
        default=0.5,
        metavar="S",
        help="time constant of the offset tracker, s (default: 0.5)",
    )
    run.add_argument(
        "--ft-std",
        metavar="FX,FY,FZ,MX,MY,MZ",
        help="F/T noise standard deviations, N and N m: the offset's reported uncertainty"
        " (default: 0.05 N and 0.005 N m)",
    )
    run.add_argument(
        "--bias-gate",
        type=float,
        default=None,
        metavar="CHI2",
        help="also skip contact-free frames whose residual exceeds this chi-square (6 degrees of"
        " freedom, e.g. 22.46 for 99.9 percent) (default: no gate)",
    )
    run.add_argument(
        "--payload",
        action="append",
        metavar="MASS,CX,CY,CZ[,LINK]",
        help="with --c-step or --onnx --online: a payload from the start, kg, its centre of mass"
        " in LINK's frame, m (a point mass; default link: the sensor's payload link; repeat)",
    )
    run.add_argument(
        "--identify-payload",
        nargs="?",
        const="",
        default=None,
        metavar="SENSOR",
        help="with --c-step or --onnx --online: identify the payload from the start while the"
        " robot moves without contact; the first record whose data identify it carries"
        " payload_identified, and it is applied (default sensor: the only one)",
    )
    run.add_argument(
        "--derivatives",
        choices=["sender", "causal"],
        default="sender",
        help="qd, qdd from the joint-state sender, or causal Savitzky-Golay derivatives of its q"
        " (for a sender without them; the delay is printed on stderr) (default sender)",
    )
    run.add_argument(
        "--derivative-window",
        type=int,
        default=15,
        metavar="N",
        help="--derivatives causal: frames of the fit (default: 15)",
    )
    run.add_argument(
        "--derivative-order",
        type=int,
        default=3,
        metavar="P",
        help="--derivatives causal: polynomial degree, 3 for no low-frequency delay (default: 3)",
    )
    run.add_argument(
        "--joints",
        metavar="udp://HOST:PORT",
        help="joint-state UDP packets (flag bit 0: the sender reports a contact) (default: none;"
        " frames carry no joint state)",
    )
    run.add_argument("--require-joints", action="store_true", help="skip frames without joints")
    run.add_argument("--publish", default="stdout", help="stdout or udp://127.0.0.1:PORT")
    run.add_argument("--allow-remote", action="store_true", help="allow a non-loopback target")
    run.add_argument(
        "--view",
        nargs="?",
        const="spawn",
        metavar="FILE.rrd",
        help="with --onnx and --robot: draw the frames in a rerun viewer (or into FILE.rrd;"
        " extra 'view') (default: no drawing)",
    )
    run.set_defaults(func=cmd_run)
