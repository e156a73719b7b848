r"""``torchcontact export``: write deployment artefacts with :mod:`torchcontact.export`.

The same parser runs as ``python -m export`` from the repository root. Example::

    torchcontact export estimator --robot tcarm --slot forearm_skin:force \\
        --slot hand_skin:force --out tcarm.onnx
    torchcontact export estimator --urdf iCubGenova04.urdf --sensor l_arm_ft \\
        --contacts slots.toml --dtype float32 --joints sensed --out icub_larm.onnx
    torchcontact export residual runs/correction --urdf arm.urdf --out correction.onnx
    torchcontact export estimator --robot tcarm --slot hand_skin:force \\
        --residual correction.onnx --out tcarm_corrected.onnx
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Iterator

from torchcontact.cli import Parser, guarded
from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.logs.format import check_outputs
from torchcontact.robot_arg import add_robot_argument, resolve_robot_argument


def _slots(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """Slot links and kinds from ``--slot LINK:KIND`` or a contact-spec file (``--contacts``)."""
    from torchcontact.contacts import SlotLayout, load_contact_spec

    if bool(args.slot) == bool(args.contacts):
        raise InputError("give the contact slots with --slot LINK:KIND (repeat) or --contacts SPEC")
    if args.contacts:
        layout = SlotLayout.covering(load_contact_spec(args.contacts).static())
        return list(layout.links), list(layout.kinds)
    slots = [s.rsplit(":", 1) for s in args.slot]
    if any(len(s) != 2 for s in slots):
        raise InputError("--slot takes LINK:KIND, e.g. hand_skin:force")
    return [s[0] for s in slots], [s[1] for s in slots]


def _estimator(args: argparse.Namespace) -> int:
    import torch

    import torchcontact as tc
    from torchcontact.errors import TorchContactError
    from torchcontact.export import DEFAULT_OPSET, export_estimator, step_graph_path

    localize_options = args.localize_threshold != 1.0 or args.localize_max_faces is not None
    if args.localize is None and localize_options:
        raise InputError("--localize-threshold and --localize-max-faces go with --localize")
    if args.format == "c":
        if args.localize is not None:
            raise InputError("--localize: the localization is in the ONNX step graph only")
        return _estimator_c(args)
    if args.payload_link and not args.online:
        raise InputError("--payload-link goes with --online (or --format c)")
    robot = resolve_robot_argument(args)
    check_outputs([args.out], [robot, args.contacts])
    from torchcontact.logs.pipeline import load_robot

    model = load_robot(robot)
    links, kinds = _slots(args)
    meshes = None
    if args.localize is not None:
        from torchcontact.meshes import load_meshes

        if args.localize in model.frames:  # else export_estimator names the unknown link
            meshes = load_meshes(model, robot, "collision",
                                 links=[args.localize])  # fmt: skip
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype or "float32"]
    opset = args.opset or DEFAULT_OPSET
    joints = args.joints
    if joints and joints not in ("all", "sensed"):
        joints = joints.split(",")
    print(
        f"export: building the estimator graphs of {model.name} ({len(links)} slots) ...",
        file=sys.stderr,
    )
    try:
        with _stage(f"estimator graphs of {model.name}, {len(links)} slots"):
            cones = None
            if args.constraints or args.cone_iterations is not None:
                cones = tc.FrictionCones(args.cone_iterations or tc.FrictionCones().iterations)
            meta = export_estimator(
                model,
                args.sensor or None,
                links,
                kinds,
                args.out,
                dtype=dtype,
                opset=opset,
                rank_rtol=args.rank_rtol,
                moving_base=args.moving_base,
                torque_rows=args.torque_rows,
                covariance=args.covariance,
                residual=args.residual or None,
                joints=None if joints in (None, "all") else joints,
                velocity_margin=args.velocity_margin,
                constraints=cones,
                online=_payload_links(args) or bool(args.online),
                ft_noise=args.ft_noise,
                localize=args.localize,
                meshes=meshes,
                localize_threshold=args.localize_threshold,
                localize_max_faces=args.localize_max_faces,
            )
    except TorchContactError:
        raise
    except ValueError as e:
        raise InputError(str(e)) from None
    step = str(step_graph_path(args.out))
    if args.json:
        print(json.dumps({"path": str(args.out), "step_path": step, **meta}, indent=1))
    else:
        print(estimator_summary(args.out, step, meta))
    return 0


def estimator_summary(path: str, step: str, meta: dict[str, str]) -> str:
    """A few lines on exported estimator graphs (``--json`` prints all of ``meta``).

    ``meta``: the batched graph's ``metadata_props`` (strings, JSON values encoded); the robot
    identity and the input/output layouts in it run to kilobytes, which a terminal does not need.
    """
    import os

    from torchcontact.onnx.format import decode

    m = decode(meta)
    sensors = ", ".join(s["name"] if isinstance(s, dict) else str(s) for s in m["sensors"])
    slots = ", ".join(f"{lk}:{kd}" for lk, kd in zip(m["slot_links"], m["slot_kinds"], strict=True))
    shapes = m.get("input_shapes") or {}
    ins = [f"{i} {'x'.join(map(str, shapes[i]))}" if i in shapes else i for i in m["inputs"]]
    options = [k.replace("_", " ") for k in ("moving_base", "torque_rows", "covariance")
               if m.get(k) in (True, "true")]  # fmt: skip
    if m.get("constraints") not in (None, "null", False):
        options.append("friction cones")
    if m.get("ft_noise") not in (None, "null"):
        options.append("noise-weighted (--ft-noise)")
    if m.get("residuals"):
        options.append(f"corrections {m['residuals']}")
    kb = [f"{os.path.getsize(x) / 1e3:.1f} kB" if os.path.isfile(x) else "?" for x in (path, step)]
    lines = [
        f"wrote {path} ({kb[0]}, frames batched) and {step} ({kb[1]}, one frame per call)",
        f"  robot {m['robot']}, sensors {sensors}; slots {slots}",
        f"  inputs {'; '.join(ins)}",
        f"  outputs {', '.join(m['outputs'])}",
        f"  {m['dtype']}, opset {m['opset']}"
        + (f"; {', '.join(options)}" if options else ""),
        *(
            [
                f"  step graph localizes {loc['link']} (slot {loc['slot']}, above"
                f" {loc['force_threshold']:g} N) on its {loc['mesh']}; step outputs"
                " localize_status, localize_position"
            ]
            if isinstance(loc := m.get("localize"), dict)
            else []
        ),
        "  all metadata: --json",
    ]  # fmt: skip
    return "\n".join(lines)


def _payload_links(args: argparse.Namespace) -> dict[str, str]:
    """``--payload-link SENSOR=LINK`` (repeat) as a dict."""
    out = {}
    for item in args.payload_link or []:
        sensor, sep, link = item.partition("=")
        if not sep or not sensor or not link:
            raise InputError(f"--payload-link takes SENSOR=LINK, got {item!r}")
        out[sensor] = link
    return out


def _estimator_c(args: argparse.Namespace) -> int:
    """``export estimator --format c``: the single-frame estimator as a C library."""
    import torch

    from torchcontact.logs.pipeline import load_robot
    from torchcontact.online.cstep import export_c_step

    if args.constraints or args.cone_iterations is not None:
        raise InputError("--format c: the friction-cone estimator is exported as ONNX only")
    if not args.out.endswith(".so"):
        raise InputError(f"--format c writes a shared library: --out NAME.so, got {args.out!r}")
    robot = resolve_robot_argument(args)
    stem = args.out.removesuffix(".so")
    outs = [args.out] + [f"{stem}{x}" for x in (".h", ".cpp", ".json")]
    check_outputs(outs, [robot, args.contacts])
    model = load_robot(robot)
    links, kinds = _slots(args)
    joints = args.joints
    if joints and joints not in ("all", "sensed"):
        joints = joints.split(",")
    payload_links = _payload_links(args)
    print(f"export: building the C step of {model.name} ({len(links)} slots) ...", file=sys.stderr)
    with _stage(f"C step of {model.name}, {len(links)} slots"):
        meta = export_c_step(
            model,
            args.sensor or None,
            links,
            kinds,
            args.out,
            dtype={"float32": torch.float32, "float64": torch.float64}[args.dtype or "float64"],
            correction=args.residual or None,
            payload_links=payload_links,
            joints=None if joints in (None, "all") else joints,
            moving_base=args.moving_base,
            torque_rows=args.torque_rows,
            covariance=args.covariance,
            velocity_margin=args.velocity_margin,
            rank_rtol=args.rank_rtol,
            prefix=args.prefix,
            march=args.march,
            build=not args.no_build,
            ft_noise=args.ft_noise,
        )
    for sensor, c in meta["correction"].items():
        left = [k for k in c["layers"] if k not in c["in_library"]]
        if left:
            print(
                f"warning: the {'+'.join(left)} layer of {sensor}'s correction is not in the C"
                " library: run its graph beside it (torchcontact export residual)",
                file=sys.stderr,
            )
    files = {"path": args.out, "header": f"{stem}.h", "source": f"{stem}.cpp"}
    print(json.dumps({**files, "metadata": f"{stem}.json", "in_size": meta["in_size"],
                      "out_size": meta["out_size"], "inputs": meta["inputs"],
                      "outputs": meta["outputs"],
                      **({"ft_noise": meta["ft_noise"]} if "ft_noise" in meta else {})},
                     indent=1))  # fmt: skip
    return 0


def _residual(args: argparse.Namespace) -> int:
    from torchcontact.export import DEFAULT_OPSET, export_residual_checkpoint

    check_outputs([args.out], [args.checkpoint])
    spec = resolve_robot_argument(args)
    robot = None if spec is None else spec.load()  # None: the URDF recorded at training
    try:
        with _stage("residual graph" + ("" if args.no_check else " and parity check")):
            meta = export_residual_checkpoint(
                args.checkpoint,
                args.out,
                robot,
                opset=args.opset or DEFAULT_OPSET,
                check=not args.no_check,
            )
    except AssertionError as e:
        raise ModelMismatchError(f"{args.checkpoint}: ONNX parity check failed: {e}") from None
    if args.json:
        print(json.dumps({"path": str(args.out), **meta}, indent=1))
    else:
        print(residual_summary(args.out, meta, checked=not args.no_check))
    return 0


def residual_summary(path: str, meta: dict[str, str], checked: bool) -> str:
    """A few lines on an exported correction graph (``--json`` prints all of ``meta``).

    ``meta``: the graph's ``metadata_props`` (strings, JSON values encoded).

    The metadata holds the learned layer again as a base64 ONNX model (``learned_graph``, tens of
    kB, for the estimator's step graph): a terminal gets its size only.
    """
    import os

    from torchcontact.onnx.format import Key, decode

    meta = decode(meta)  # the metadata_props strings
    ins = [f"{i} {'x'.join(map(str, meta['input_shapes'][i]))}" for i in meta["inputs"]]
    extra = meta.get("extra_columns") or []
    if extra:
        ins = [f"{x} ({', '.join(extra)})" if x.startswith("extra") else x for x in ins]
    learned = meta.get(Key.LEARNED_GRAPH)
    parts = ", ".join(meta.get("layers") or []) or "none"
    lines = [
        f"wrote {path} ({os.path.getsize(path) / 1e3:.1f} kB): the correction of sensor"
        f" {meta['sensor']} of {meta['robot']}, layers {parts}"
        + (", recurrent" if meta.get("recurrent") in (True, "true") else ""),
        f"  inputs {'; '.join(ins)}; output correction Nx6 [N; N m] in the sensor frame,"
        " subtracted from the reading",
        f"  {meta['dtype']}, opset {meta['opset']}, "
        + ("checked against torch with onnxruntime" if checked else "not checked (--no-check)")
        + ("" if learned is None else f"; learned layer also inside ({len(learned) / 1e3:.1f} kB"
           " base64, for the estimator's step graph)"),
        "  all metadata: --json",
    ]  # fmt: skip
    return "\n".join(lines)


@contextlib.contextmanager
def _stage(what: str) -> Iterator[None]:
    """A progress line on stderr, when it is a terminal: the stage, then its duration."""
    from tqdm import tqdm

    with tqdm(
        total=1,
        desc=f"export {what}",
        file=sys.stderr,
        bar_format="{desc}: {elapsed}",
        disable=not sys.stderr.isatty(),  # a log file or a pipe gets no progress
    ) as bar:
        yield
        bar.update(1)


def main(argv: list[str] | None = None, prog: str = "python -m export") -> int:
    """Entry point of ``torchcontact export`` and ``python -m export``; returns the exit code."""
    p = Parser(
        prog=prog,
        description="write deployment artefacts: the contact estimator or a learned residual as"
        " ONNX graphs",
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("estimator", help="the whole contact estimator as one ONNX graph")
    add_robot_argument(e, aliases=("--urdf",), required=True)
    e.add_argument("--sensor", action="append", help="F/T sensor to use (repeat; default all)")
    e.add_argument(
        "--slot",
        action="append",
        help="contact slot LINK:KIND (repeatable; default: none, give --slot or --contacts)",
    )
    e.add_argument(
        "--contacts",
        help="contact-spec file (TOML/JSON): one slot per contact, instead of --slot (default:"
        " none)",
    )
    e.add_argument(
        "--format",
        choices=["onnx", "c"],
        default="onnx",
        help="onnx graphs, or c: a C-ABI shared library NAME.so with NAME.h (no torch/onnxruntime)",
    )
    e.add_argument(
        "--dtype",
        choices=["float32", "float64"],
        default=None,
        help="graph dtype (default: float32; float64 for --format c)",
    )
    e.add_argument("--opset", type=int, default=None, help="ONNX opset (default: the library's)")
    e.add_argument("--rank-rtol", type=float, default=None, help="rank tolerance (default: dtype)")
    e.add_argument(
        "--moving-base",
        action="store_true",
        help="inputs omega, domega, proper_acc (IMU on the root body)",
    )
    e.add_argument(
        "--torque-rows",
        action="store_true",
        help="inputs tau_measured, tau_mask (joint torque sensors)",
    )
    e.add_argument("--covariance", action="store_true", help="input ft_cov, output covariance")
    e.add_argument(
        "--ft-noise",
        action="append",
        metavar="SENSOR=SIGMA_F,SIGMA_M",
        help="reading noise std of a sensor, N and N m (or 6 numbers FX,..,MZ, or a driver profile"
        " with datasheet noise, e.g. robotiq-ft300): the solve weighted by it, constants of the"
        " graph or library (give every sensor; repeatable; default: none, the unweighted"
        " pinv(A) b; docs/deployment.md)",
    )
    e.add_argument(
        "--joints",
        default=None,
        help="joint torques to output: all (default), sensed, or NAME,NAME,...",
    )
    e.add_argument(
        "--residual",
        action="append",
        help="correction graph to chain, from torchcontact export residual (repeatable;"
        " default: none); --format c: a correction checkpoint folder (its offset and inertial"
        " layers go into the library)",
    )
    e.add_argument(
        "--velocity-margin",
        type=float,
        default=None,
        help="status bit 64 beyond this multiple of the URDF velocity limits (default: no check)",
    )
    e.add_argument(
        "--constraints",
        action="store_true",
        help="the friction-cone constrained estimator (inputs normals, friction, pushing)",
    )
    e.add_argument(
        "--cone-iterations", type=int, default=None, help="its iteration budget (default 25)"
    )
    e.add_argument("--march", default="native", help="--format c: the compiler's -march")
    e.add_argument("--prefix", default="tc_estimator", help="--format c: C symbol prefix")
    e.add_argument(
        "--no-build", action="store_true", help="--format c: write the source and header only"
    )
    e.add_argument(
        "--online",
        action="store_true",
        help="step graph inputs bias, theta.<sensor> and outputs ft_model, regressor.<sensor>:"
        " bias tracking, tare and payloads in the runtime (always in --format c)",
    )
    e.add_argument(
        "--payload-link",
        action="append",
        help="with --online or --format c: SENSOR=LINK where payloads attach (repeat; default:"
        " the deepest link of the sensor's subtree)",
    )
    e.add_argument(
        "--localize",
        metavar="LINK",
        default=None,
        help="the step graph localizes a contact on LINK (which needs a --slot LINK:force) from"
        " its sensor's wrench and LINK's collision mesh, and uses it as that slot's contact in"
        " steps with no active slot in the sensor's region (outputs localize_status,"
        " localize_position; default: none; docs/localize.md)",
    )
    e.add_argument(
        "--localize-threshold",
        type=float,
        default=1.0,
        help="with --localize: below this force (N) a step has no contact (default 1)",
    )
    e.add_argument(
        "--localize-max-faces",
        type=int,
        default=None,
        help="with --localize: above this many faces the graph carries the collision mesh's"
        " convex hull (default 1000; the graph's cost grows with the faces)",
    )
    e.add_argument(
        "--out",
        required=True,
        help="output .onnx path (and <stem>.step.onnx); --format c: NAME.so (and .h, .cpp, .json)",
    )
    e.add_argument(
        "--json",
        action="store_true",
        help="print the graphs' whole metadata as JSON (robot identity, layouts) instead of a"
        " summary",
    )
    r = sub.add_parser("residual", help="a learned F/T residual checkpoint (MLP or GRU)")
    r.add_argument("checkpoint", help="checkpoint folder written by torchcontact train")
    add_robot_argument(r, aliases=("--urdf",), default_help="the URDF recorded at training")
    r.add_argument("--out", required=True, help="output .onnx path")
    r.add_argument("--opset", type=int, default=None, help="ONNX opset (default: the library's)")
    r.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check")
    r.add_argument(
        "--json",
        action="store_true",
        help="print the graph's whole metadata as JSON (with the learned layer as base64)"
        " instead of a summary",
    )

    def run() -> int:
        args = p.parse_args(argv)
        return _residual(args) if args.cmd == "residual" else _estimator(args)

    return guarded(run, debug="--debug" in (sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
