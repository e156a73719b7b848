r"""``python -m export``: write deployment artefacts with :mod:`torchcontact.export`.

Example::

    python -m export estimator --robot tcarm --slot forearm_skin:force --slot hand_skin:force \\
        --out tcarm.onnx
    python -m export estimator --urdf iCubGenova04.urdf --sensor l_arm_ft \\
        --slot l_hand:wrench --dtype float32 --out icub_larm.onnx
    python -m export residual runs/correction --urdf arm.urdf --out correction.onnx
"""

from __future__ import annotations

import argparse
import json
import sys


def _estimator(args: argparse.Namespace) -> int:
    import torch

    import torchcontact as tc
    from torchcontact.export import DEFAULT_OPSET, export_estimator

    if (args.robot is None) == (args.urdf is None):
        print("give exactly one of --robot tcarm or --urdf PATH", file=sys.stderr)
        return 2
    path = tc.robots.tcarm_path() if args.robot == "tcarm" else args.urdf
    model = tc.RobotModel.from_urdf(path)
    slots = [s.rsplit(":", 1) for s in args.slot]
    if any(len(s) != 2 for s in slots):
        print("--slot takes LINK:KIND, e.g. hand_skin:force", file=sys.stderr)
        return 2
    links, kinds = [s[0] for s in slots], [s[1] for s in slots]
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    opset = args.opset or DEFAULT_OPSET
    try:
        meta = export_estimator(
            model, args.sensor or None, links, kinds, args.out, dtype=dtype, opset=opset,
            rank_rtol=args.rank_rtol, sweeps=args.sweeps,
        )  # fmt: skip
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"path": str(args.out), **meta}, indent=1))
    return 0


def _residual(args: argparse.Namespace) -> int:
    import torchcontact as tc
    from torchcontact.export import DEFAULT_OPSET, export_residual_checkpoint
    from torchcontact.residual import CheckpointError

    robot = tc.robots.tcarm_path() if args.robot == "tcarm" else args.urdf
    try:
        meta = export_residual_checkpoint(
            args.checkpoint,
            args.out,
            robot,
            opset=args.opset or DEFAULT_OPSET,
            check=not args.no_check,
        )
    except (CheckpointError, AssertionError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"path": str(args.out), **meta}, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m export``."""
    p = argparse.ArgumentParser(prog="python -m export", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("estimator", help="the whole contact estimator as one ONNX graph")
    e.add_argument("--robot", choices=["tcarm"], help="a bundled robot")
    e.add_argument("--urdf", help="URDF file of the robot")
    e.add_argument("--sensor", action="append", help="F/T sensor to use (repeat; default all)")
    e.add_argument("--slot", action="append", required=True, help="contact slot LINK:KIND")
    e.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    e.add_argument("--opset", type=int, default=None)
    e.add_argument("--rank-rtol", type=float, default=None)
    e.add_argument("--sweeps", type=int, default=None, help="Jacobi sweeps (default: per dtype)")
    e.add_argument("--out", required=True, help="output .onnx path")
    r = sub.add_parser("residual", help="a learned F/T residual checkpoint (MLP or GRU)")
    r.add_argument("checkpoint", help="checkpoint folder written by python -m training")
    r.add_argument("--robot", choices=["tcarm"], help="a bundled robot")
    r.add_argument("--urdf", help="URDF of the robot (default: the one recorded at training)")
    r.add_argument("--out", required=True, help="output .onnx path")
    r.add_argument("--opset", type=int, default=None)
    r.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check")
    args = p.parse_args(argv)
    return _residual(args) if args.cmd == "residual" else _estimator(args)


if __name__ == "__main__":
    sys.exit(main())
