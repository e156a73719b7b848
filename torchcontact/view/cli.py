"""``torchcontact view``: registered by :func:`add_parser`; imports nothing heavy until run."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from torchcontact.errors import InputError
from torchcontact.robot_arg import add_robot_argument


def cmd_view(args: argparse.Namespace) -> int:
    """Write a rerun recording of a log (and its estimate), or open the viewer."""
    from pathlib import Path

    from torchcontact.robot_arg import resolve_robot_argument
    from torchcontact.view.logs import view_log

    # without --robot: the robot the log (or its estimate) records, never silently the arm
    robot = resolve_robot_argument(
        args, logs=[args.log, *([args.estimate] if args.estimate else [])]
    )
    if args.spawn and args.out:
        raise InputError("give --out FILE.rrd or --spawn, not both")
    out = args.out
    if not args.spawn and out is None:
        out = str(Path(args.estimate or args.log).with_suffix(".rrd"))
    summary = view_log(
        args.log,
        args.estimate,
        robot,
        out,
        spawn=args.spawn,
        every=args.every,
        start=args.start,
        end=args.end,
        scale=args.scale,
        nullspace=args.nullspace,
        require_meshes=args.require_meshes,
        batch_size=args.batch_size,
        progress=not args.quiet and sys.stderr.isatty(),
    )
    if args.json:
        print(json.dumps(summary))
        return 0
    r0, r1 = summary["rows"]
    where = f"to {summary['out']}" if summary["out"] else "to the viewer"
    print(
        f"drew {summary['frames']} frames (rows {r0}-{r1}, every {summary['every']}) {where};"
        f" arrows: {summary['scale']:g} N per m"
    )
    if summary["out"]:
        print(f"open it with: rerun {summary['out']}")
    return 0


def add_parser(subparsers: Any) -> None:
    """Register ``view``."""
    p = subparsers.add_parser(
        "view",
        help="interactive 3D timeline of a log and its estimate (rerun .rrd, extra 'view')",
        description="Draw a log and its estimate into a rerun recording: the robot's meshes"
        " posed by q, contacts with force arrows (one colour per slot, truth lighter), each F/T"
        " sensor's reading and residual A x - b, and time series of force norms, ranks,"
        " unknowns, null-space dimensions, residuals, status bits and friction cones; frames"
        " where rank < unknowns are marked. Time is the log's t_ns. Needs the extra 'view'"
        " (rerun-sdk).",
    )
    p.add_argument("log", help="the input log (joint positions, readings, contacts)")
    p.add_argument(
        "estimate", nargs="?", help="its output of torchcontact estimate (same rows; optional)"
    )
    add_robot_argument(p, default_help="the robot the log records", what="the robot of the log")
    p.add_argument(
        "--out", help="the .rrd to write (default: ESTIMATE or LOG with the suffix .rrd)"
    )
    p.add_argument("--spawn", action="store_true", help="open the rerun viewer instead of a file")
    p.add_argument("--every", type=int, default=1, metavar="N", help="draw every N-th frame")
    p.add_argument(
        "--start",
        type=float,
        metavar="S",
        help="from S seconds after the first t_ns (default: the first frame)",
    )
    p.add_argument(
        "--end",
        type=float,
        metavar="S",
        help="up to S seconds after the first t_ns (default: the last frame)",
    )
    p.add_argument(
        "--scale",
        type=float,
        metavar="N_PER_M",
        help="force arrows: N per m of arrow (default: the 95th percentile force drawn a quarter"
        " of the robot's size, rounded to 1, 2 or 5 x 10^k)",
    )
    p.add_argument(
        "--nullspace",
        action="store_true",
        help="draw the null-space directions of the frames where rank < unknowns",
    )
    p.add_argument(
        "--require-meshes",
        action="store_true",
        help="stop with an error when a visual mesh of the URDF cannot be loaded (default: draw"
        " those links' frames and say which meshes are missing)",
    )
    p.add_argument("--batch-size", type=int, default=2000, help="frames read and drawn at a time")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_view)
