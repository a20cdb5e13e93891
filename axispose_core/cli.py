"""The `axispose` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def _demo(args: argparse.Namespace) -> int:
    from axispose_core.demo import format_rows, run_demo

    rows = run_demo(args.out, seed=args.seed)
    print(format_rows(rows))
    print(f"\ncontact sheet: {Path(args.out) / 'geometry_demo.png'}")
    return 0 if all(r.ok for r in rows) else 1


def _train_reader(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.tbm.reader import ReaderConfig, train_reader

    torch.set_num_threads(args.threads)
    config = ReaderConfig(size=args.size, steps=args.steps, batch=args.batch, seed=args.seed)
    train_reader(config, out=args.out, log_csv=args.log)
    print(f"saved {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="axispose", description="AxisPose: 6D object pose from one RGB image by axis generation.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="geometry demo on embedded defaults: axis image -> keypoints -> pose")
    demo.add_argument("--out", default="out/demo", help="folder for the contact sheet")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)

    tr = sub.add_parser("train-reader", help="train the TBM keypoint reader on rendered, degraded axis images")
    tr.add_argument("--out", required=True, help="checkpoint to write (.safetensors)")
    tr.add_argument("--size", type=int, default=64, help="axis image size S (the AGM's output size)")
    tr.add_argument("--steps", type=int, default=3000)
    tr.add_argument("--batch", type=int, default=32)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--threads", type=int, default=2)
    tr.add_argument("--log", default=None, help="CSV of the training loss")
    tr.set_defaults(func=_train_reader)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
