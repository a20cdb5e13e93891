"""An estimator checkpoint that is a base estimator (the shipped one) with another run's AGM weights: its
localiser, reader and inference settings (head_offaxis, dense fusion, covariance scale) kept, so that a
fine-tuning run is compared with the shipped model on everything but the AGM (`axispose validate` needs the
localiser that a trainer's own checkpoint lacks).

    python bench/swap_agm.py --agm /work/runs/RUN/agm.safetensors --out /work/runs/RUN/estimator.safetensors
"""

from __future__ import annotations

import argparse
import dataclasses

from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agm", required=True, help="a trained estimator checkpoint whose AGM to take")
    ap.add_argument("--base", default=str(SHIPPED_ESTIMATOR), help="the estimator whose other parts and settings to keep")
    ap.add_argument("--out", required=True)
    ap.add_argument(
        "--other-network",
        action="store_true",
        help="take an AGM of another network too (e.g. another trunk), under the base's inference settings",
    )
    args = ap.parse_args()
    base, run = Estimator.load(args.base), Estimator.load(args.agm)
    if run.config.agm != base.config.agm and not args.other_network:
        raise SystemExit(f"swap_agm: {args.agm}'s AGM config differs from {args.base}'s; assemble it with a recipe instead")
    config = dataclasses.replace(base.config, agm=run.config.agm, training=run.config.training)
    Estimator(config, run.agm, base.reader, "cpu", base.localiser).save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
