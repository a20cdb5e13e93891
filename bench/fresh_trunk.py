"""An estimator checkpoint that is the shipped one with its AGM's trunk back at its initial (random) weights, and
with it the layers that read the trunk's widths (the ones a transplant onto another trunk leaves fresh: object
FiLM, context input, laterals, the denoiser's injections): the from-scratch arm of a trunk comparison under the
shipped denoiser, against `axispose train --init SHIPPED` onto a pretrained trunk.

    python bench/fresh_trunk.py --out /work/runs/trunk/scratch_start.safetensors
    axispose train --config C --init /work/runs/trunk/scratch_start.safetensors --out ...
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from axispose_core.agm.model import AxisGenerator, transplant
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator
from axispose_core.trunks import EfficientNetLiteConfig

TRUNK = "denoiser.encoder.trunk."


def reset_trunk(est: Estimator) -> list[str]:
    """Set `est`'s trunk and the layers that read it to a new network's initial weights (torch's random state);
    returns their names."""
    agm = est.config.agm
    # The layers that read the trunk are those a transplant onto another trunk leaves fresh: asked, not listed here.
    encoder = dataclasses.replace(agm.denoiser.encoder, trunk=EfficientNetLiteConfig(weights="none"))
    other = AxisGenerator(dataclasses.replace(agm, denoiser=dataclasses.replace(agm.denoiser, encoder=encoder)))
    reading = {name.rsplit(".", 1)[0] for name in transplant(other, est.agm)}
    initial, state = AxisGenerator(agm).state_dict(), est.agm.state_dict()
    reset = [k for k in state if k.startswith(TRUNK) or k.rsplit(".", 1)[0] in reading]
    est.agm.load_state_dict(state | {k: initial[k] for k in reset})
    return reset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    est = Estimator.load(args.checkpoint)
    reset = reset_trunk(est)
    est.save(args.out)
    outside = sum(not k.startswith(TRUNK) for k in reset)
    print(f"wrote {args.out}: {len(reset)} tensors at their initial weights, {outside} outside the trunk")


if __name__ == "__main__":
    main()
