"""The `axispose` command line: a table of the core's commands, each added (options and body) by the module of
what it runs."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from axispose_core.command_args import AddParser, Command
from axispose_core.data.command import add_gt_info, add_stream_preview, add_synth, add_synth_preview
from axispose_core.evaluation.command import add_eval, add_validate
from axispose_core.train.command import add_fit_verifier, add_train, add_train_direct, add_train_localiser, add_train_reader


def _demo(args: argparse.Namespace) -> int:
    from axispose_core.demo import format_rows, run_demo

    rows = run_demo(args.out, seed=args.seed)
    print(format_rows(rows))
    print(f"\ncontact sheet: {Path(args.out) / 'geometry_demo.png'}")
    return 0 if all(r.ok for r in rows) else 1


def add_demo(add_parser: AddParser) -> None:
    """`axispose demo`: here rather than in demo.py, whose imports (torch, matplotlib) every command would pay for."""
    demo = add_parser("demo", help="geometry demo on embedded defaults: axis image -> keypoints -> pose")
    demo.add_argument("--out", default="out/demo", help="folder for the contact sheet")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)


COMMANDS: tuple[Command, ...] = (
    add_demo, add_train_reader, add_synth, add_train, add_train_localiser, add_train_direct, add_fit_verifier, add_eval, add_validate,
    add_gt_info, add_synth_preview, add_stream_preview,
)  # fmt: skip
"""The core's commands, in the order `axispose --help` lists them."""


def build_parser(commands: Command | None = None) -> argparse.ArgumentParser:
    """The core's commands, then those `commands` adds (the ROS ones, `axispose_ros.cli`) with the same parser."""
    parser = argparse.ArgumentParser(prog="axispose", description="AxisPose: 6D object pose from one RGB image by axis generation.")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (*COMMANDS, *([commands] if commands is not None else [])):
        add(sub.add_parser)
    return parser


def main(argv: Sequence[str] | None = None, parser: argparse.ArgumentParser | None = None) -> int:
    """Run the command `argv` names with `parser`'s commands (default: the core's)."""
    args = (parser or build_parser()).parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
