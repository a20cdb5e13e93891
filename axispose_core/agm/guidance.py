"""Geometric-consistency guidance: L_geo on x̂0(x_t), its gradient injected into the noise estimate.

The operator H reads, differentiably, what the TBM needs from an axis image x (B,3,S,S) in [-1, 1]:
- the origin C: centroid of where all three channels are lit (weights p_X p_Y p_Z, p = (x+1)/2);
- the unit axis directions A_i: from C towards the centroid of channel i (a segment's centroid is its middle,
  so this is the axis' direction with its sense).
Coordinates are normalised to [-1, 1] over the image.

    L_geo = Σ_i ‖A_gen,i − A_gt,i‖² + ‖C_gen − C_gt‖²                                   (paper, eq. 4)
    ε' = ε + (1/σ²) √(1 − ᾱ_t) ∇_{x_t} L_geo(x̂0(x_t))                                  (paper, eq. 11)

Exactly what is implemented (`inject`): ∇_{x_t} is taken through x̂0 = (x_t − √(1−ᾱ_t) ε)/√ᾱ_t with ε held
fixed (so ∇_{x_t} = ∇_{x̂0} / √ᾱ_t): the network's own Jacobian ∂ε/∂x_t is dropped, as in the paper's
p(g|x_t) ≈ p(g|x̂0) approximation. During training the gradient is built with create_graph, so the ε-loss on
ε' reaches the network through x̂0 (test_agm.py checks the injection against finite differences).

At run time the ground truth is unknown; `self_consistency_target` supplies the measurement g instead: the
axis image re-drawn from the pose the TBM reads off x̂0 (an axis image that one rigid pose explains), plus
optionally the crop centre as a prior on C.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from axispose_core.axis_image import axis_keypoints_torch, render_axis_keypoints_torch
from axispose_core.tbm.backproject import backproject_readings
from axispose_core.tbm.reader import KeypointReader


class AxisGeometry(NamedTuple):
    origin: torch.Tensor  # (B,2) in [-1, 1]
    directions: torch.Tensor  # (B,3,2), unit


def axis_geometry(x: torch.Tensor, eps: float = 1e-6) -> AxisGeometry:
    """H: origin and unit axis directions of axis images x (B,3,S,S) in [-1, 1]."""
    h, w = x.shape[-2:]
    p = ((x + 1) * 0.5).clamp(0, 1)
    ys = (torch.arange(h, device=x.device, dtype=x.dtype) + 0.5) / h * 2 - 1
    xs = (torch.arange(w, device=x.device, dtype=x.dtype) + 0.5) / w * 2 - 1

    def centroid(weights: torch.Tensor) -> torch.Tensor:  # (..., H, W) -> (..., 2)
        total = weights.sum(dim=(-2, -1)) + eps
        return torch.stack([(weights.sum(-2) * xs).sum(-1) / total, (weights.sum(-1) * ys).sum(-1) / total], dim=-1)

    # The product (not its cube root, whose derivatives blow up at 0 and poison double backward).
    origin = centroid(p[:, 0] * p[:, 1] * p[:, 2])
    axis_mid = centroid(p * p)
    d = axis_mid - origin[:, None, :]
    # sqrt(|d|² + ε²), not |d|: the norm's derivatives are undefined at d = 0 (a blank or uniform image).
    return AxisGeometry(origin, d / torch.sqrt((d * d).sum(dim=-1, keepdim=True) + 1e-8))


def geo_loss(gen: AxisGeometry, target: AxisGeometry) -> torch.Tensor:
    """L_geo per sample (B,)."""
    return ((gen.directions - target.directions) ** 2).sum(dim=(1, 2)) + ((gen.origin - target.origin) ** 2).sum(dim=1)


def inject(eps: torch.Tensor, grad_xt: torch.Tensor, abar_t: torch.Tensor, sigma: float) -> torch.Tensor:
    """ε' = ε + (1/σ²) √(1−ᾱ_t) ∇_{x_t} L_geo."""
    return eps + (1.0 / sigma**2) * (1 - abar_t).sqrt() * grad_xt


def guided_eps(
    eps: torch.Tensor, x_t: torch.Tensor, abar_t: torch.Tensor, target: AxisGeometry, sigma: float, create_graph: bool
) -> torch.Tensor:
    """ε' for noise estimate ε at x_t, with ∇_{x_t} through x̂0(x_t) at fixed ε (module docstring)."""
    with torch.enable_grad():
        xt = x_t.detach().requires_grad_(True)
        x0 = (xt - (1 - abar_t).sqrt() * eps) / abar_t.sqrt()
        loss = geo_loss(axis_geometry(x0.clamp(-1, 1)), target).sum()
        (grad,) = torch.autograd.grad(loss, xt, create_graph=create_graph)
    return inject(eps, grad, abar_t, sigma)


def self_consistency_target(
    x0: torch.Tensor,
    reader: KeypointReader,
    K_patch: np.ndarray,
    lengths: np.ndarray,
) -> AxisGeometry:
    """Measurement g for run-time guidance: H of the axis image one rigid pose draws, that pose being the TBM's
    reading of x̂0. Where the TBM cannot read x̂0, the sample's own H is used (no pull)."""
    size = x0.shape[-1]
    own = axis_geometry(x0.detach())
    with torch.no_grad():
        images = ((x0.detach() + 1) * 0.5).clamp(0, 1)
        readings = reader.read(images)
    origins, dirs = own.origin.clone(), own.directions.clone()
    for i, res in enumerate(backproject_readings(K_patch, readings, lengths)):
        if res is None or not res.ok:
            continue
        kps = axis_keypoints_torch(
            torch.as_tensor(K_patch[i])[None], torch.as_tensor(res.R)[None], torch.as_tensor(res.t)[None], torch.as_tensor(lengths[i])[None]
        ).to(x0.dtype)
        redrawn = render_axis_keypoints_torch(kps, size).to(x0.device) * 2 - 1
        g = axis_geometry(redrawn)
        origins[i], dirs[i] = g.origin[0], g.directions[0]
    return AxisGeometry(origins, dirs)
