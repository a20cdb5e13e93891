"""What the benchmarks that pose frames as the node does share: their common arguments and the estimator loaded to run
as the node runs it (float32, the given threads). The scripts run as `python bench/NAME.py`, so this folder is on
sys.path and they `from node_estimator import ...`."""

from __future__ import annotations

import argparse

import torch

from axispose_core.estimator import Estimator


def add_common_arguments(ap: argparse.ArgumentParser, models_help: str) -> None:
    """--checkpoint, --models, --min-visib, --threads, --json."""
    ap.add_argument("--checkpoint", required=True, help="estimator checkpoint with a localiser")
    ap.add_argument("--models", default="../shared/data/lmo/models_eval", help=models_help)
    ap.add_argument("--min-visib", type=float, default=0.1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None)


def node_estimator(args: argparse.Namespace) -> Estimator:
    """The checkpoint's estimator in float32 on `args.threads` threads."""
    torch.set_num_threads(args.threads)
    est = Estimator.load(args.checkpoint)
    est.set_precision("float32")
    return est
