"""The training losses of the networks built on the crop encoder (the AGM, the direct baseline), and the modules
that compute them in `forward`, so that DistributedDataParallel can wrap them while the networks keep their own
`forward` for inference."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from axispose_core.agm.denoiser import Encoding
from axispose_core.agm.guidance import axis_geometry, guided_eps
from axispose_core.agm.model import AxisGenerator
from axispose_core.baseline.direct import DirectRegressor, keypoints_to_normalised

Batch = dict[str, torch.Tensor]


def log_depth_target(K: torch.Tensor, t: torch.Tensor, scale: torch.Tensor, size: int) -> torch.Tensor:
    """The encoder's depth target log(z S / (f λ_O)) for crop intrinsics K (B,3,3), translations t (B,3) and object
    scales λ_O (B,): f is the crop's mean focal length in px, S its side (`agm/model.py`'s `depth_from_log`
    inverts it)."""
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    return torch.log(t[:, 2] * size / (f * scale)).float()


def dense_targets(points: torch.Tensor, mask: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Full-resolution surface points (B,3,S,S) and visible mask (B,1,S,S) at the encoder's dense map's side `size`:
    as they are at S; at S / 2, each 2 x 2 block's mean point over its visible pixels, visible where most of them
    are (the block mean lies at the block's centre only where all four are: the half-resolution head's boundary
    bias)."""
    stride = points.shape[-1] // size
    if stride == 1:
        return points, mask
    m = F.avg_pool2d(mask, stride) * stride**2
    return F.avg_pool2d(points * mask, stride) * stride**2 / m.clamp(min=1), (m >= stride**2 / 2).to(mask.dtype)


def encoder_losses(enc: Encoding, batch: Batch) -> dict[str, torch.Tensor]:
    """The encoder's dense and depth losses on the targets the batch has: "points" (L1 over the visible pixels, in
    object radii), "mask" (binary cross-entropy), both at the dense map's resolution (`dense_targets`), "depth"
    (L1 on log depth); and "unused", 0 times every head, so that a head without its target still enters the graph
    (DistributedDataParallel wants every parameter used)."""
    parts = {"unused": 0.0 * (enc.points.sum() + enc.mask.sum() + enc.log_depth.sum()).float()}
    if "points" in batch:
        target, m = dense_targets(batch["points"], batch["mask_visib"], enc.points.shape[-1])
        parts["points"] = (m * (enc.points.float() - target).abs()).sum() / (3 * m.sum() + 1)
        parts["mask"] = F.binary_cross_entropy_with_logits(enc.mask.float(), m)
    if "log_depth" in batch:
        parts["depth"] = (enc.log_depth.float() - batch["log_depth"]).abs().mean()
    return parts


def agm_losses(agm: AxisGenerator, batch: Batch, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """The AGM's training losses on a batch (crop, object, axes; points + mask_visib and log_depth where known):
    "diffusion" at random timesteps (with train_guidance, the guided estimate ε' is what it sees), the encoder's
    "points", "mask" and "depth", and their weighted "total"."""
    crops, x0 = batch["crop"], batch["axes"]
    cfg, sched = agm.config, agm.scheduler
    b = x0.shape[0]
    t = torch.randint(0, sched.config.num_train_timesteps, (b,), generator=generator).to(x0.device)
    noise = torch.randn(x0.shape, generator=generator).to(x0.device)
    x_t = sched.add_noise(x0, noise, t)
    enc = agm.encode(crops, batch["object"])
    out = agm.denoiser(x_t, t, enc)
    if cfg.train_guidance:
        abar = sched.alphas_cumprod.to(x0.device)[t].to(x0.dtype).view(-1, 1, 1, 1)
        eps, _ = sched.to_eps_x0(out, t, x_t, clip=False)
        eps_g = guided_eps(eps, x_t, abar, axis_geometry(x0), cfg.guidance_sigma, create_graph=True)
        # ε-prediction: the ε-loss sees ε' (the paper). Other parametrisations: ε' is mapped back with x̂0
        # clamped to the image range, as sampling does: unclamped, the 1/√ᾱ_t factors blow up at large t.
        out = sched.from_eps(eps_g, t, x_t, clip=sched.config.prediction_type != "epsilon")
    weight = 1 + cfg.line_weight * (x0 > -1).any(dim=1, keepdim=True).to(x0.dtype)
    parts = {"diffusion": (weight * (out.float() - sched.target(x0, noise, t)) ** 2).mean(), **encoder_losses(enc, batch)}
    parts["total"] = cfg.encoder_loss.total(parts, "diffusion")
    return parts


def direct_losses(model: DirectRegressor, batch: Batch) -> dict[str, torch.Tensor]:
    """The direct baseline's losses: "keypoints", smooth L1 to the true keypoints (normalised units;
    `batch["keypoints"]` in pixels), the encoder's where the batch has their targets, and their weighted "total"."""
    enc = model.encoder(batch["crop"], batch["object"])
    kp = model.head(enc.context).view(-1, 4, 2)
    target = keypoints_to_normalised(batch["keypoints"].to(kp.dtype), model.config.size)
    parts = {"keypoints": F.smooth_l1_loss(kp.float(), target.float(), beta=0.02), **encoder_losses(enc, batch)}
    parts["total"] = model.config.encoder_loss.total(parts, "keypoints")
    return parts


class AGMObjective(nn.Module):
    """`forward(batch, generator)`: the AGM's total training loss."""

    def __init__(self, agm: AxisGenerator) -> None:
        super().__init__()
        self.agm = agm

    def forward(self, batch: Batch, generator: torch.Generator | None = None) -> torch.Tensor:
        return agm_losses(self.agm, batch, generator)["total"]


class DirectObjective(nn.Module):
    """`forward(batch, generator)`: the direct baseline's total training loss (the generator is unused)."""

    def __init__(self, model: DirectRegressor) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch, generator: torch.Generator | None = None) -> torch.Tensor:
        return direct_losses(self.model, batch)["total"]
