"""An estimator checkpoint that is the shipped one with its AGM's trunk back at its initial (random) weights, and
with it the layers that read the trunk's widths (the ones a transplant onto another trunk leaves fresh: object
FiLM, context input, laterals, the denoiser's injections): the from-scratch arm of a trunk comparison under the
shipped denoiser, against `axispose train --init SHIPPED` onto a pretrained trunk.

    python bench/fresh_trunk.py --out /work/runs/trunk/scratch_start.safetensors
    axispose train --config C --init /work/runs/trunk/scratch_start.safetensors --out ...
"""

from __future__ import annotations

import argparse

import torch

from axispose_core.agm.model import TRUNK, fresh_trunk
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)  # before the load, which draws too: as a recipe's `fresh_trunk` stage starts
    est = Estimator.load(args.checkpoint)
    reset = fresh_trunk(est.agm)
    est.save(args.out)
    outside = sum(not k.startswith(TRUNK) for k in reset)
    print(f"wrote {args.out}: {len(reset)} tensors at their initial weights, {outside} outside the trunk")


if __name__ == "__main__":
    main()
