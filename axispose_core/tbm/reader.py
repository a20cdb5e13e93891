"""The TBM's regression network: axis image -> origin and three endpoints, robust to what a diffusion model draws.

Four heatmaps (origin, end X, end Y, end Z) at half resolution are read by soft-argmax, which keeps the
prediction sub-pixel and translation-equivariant. Dilated residual blocks at quarter resolution see the whole
axis, which is what tells a segment's far end from its origin. Training needs no dataset: axis images are
rendered on the fly from random poses and crops (`pose_sampling`) and degraded the way generated images fail
(broken strokes, blur, noise, stray blobs, uneven intensity).
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from axispose_core.axis_image import DEFAULT_LINE_WIDTH, axis_keypoints, render_axis_keypoints_torch
from axispose_core.checkpoint import load_state, read_checkpoint, save_checkpoint
from axispose_core.pose_sampling import sample_patch
from axispose_core.tbm.keypoints import AxisKeypoints

KIND = "tbm_reader"
SHIPPED_READER = Path(__file__).resolve().parents[1] / "models" / "tbm_reader.safetensors"
"""The reader trained by `axispose train-reader --size 64 --steps 3000 --seed 0`, installed with the package."""


@dataclass(frozen=True)
class ReaderConfig:
    """Network and training settings of the keypoint reader; saved inside its checkpoint."""

    size: int = 64
    channels: int = 32
    blocks: tuple[int, ...] = (1, 2, 4, 8, 1)
    line_width: float = DEFAULT_LINE_WIDTH
    steps: int = 1500
    batch: int = 32
    lr: float = 2e-3
    degrade_prob: float = 0.7
    seed: int = 0


class _DilatedBlock(nn.Module):
    def __init__(self, ch: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=dilation, dilation=dilation)
        self.norm1 = nn.GroupNorm(8, ch)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)
        self.norm2 = nn.GroupNorm(8, ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = F.silu(self.norm1(self.conv1(x)))
        return F.silu(x + self.norm2(self.conv2(h)))


class KeypointReader(nn.Module):
    """(B,3,S,S) axis images in [0,1] -> (B,4,2) keypoints in patch pixels (origin, end X, end Y, end Z)."""

    def __init__(self, config: ReaderConfig) -> None:
        super().__init__()
        self.config = config
        ch = config.channels
        self.stem = nn.Sequential(
            nn.Conv2d(3, ch, 3, stride=2, padding=1),
            nn.GroupNorm(8, ch),
            nn.SiLU(),
            nn.Conv2d(ch, ch, 3, padding=1),
            nn.GroupNorm(8, ch),
            nn.SiLU(),
        )
        self.down = nn.Sequential(nn.Conv2d(ch, ch, 3, stride=2, padding=1), nn.GroupNorm(8, ch), nn.SiLU())
        self.context = nn.Sequential(*[_DilatedBlock(ch, d) for d in config.blocks])
        self.fuse = nn.Sequential(nn.Conv2d(2 * ch, ch, 3, padding=1), nn.GroupNorm(8, ch), nn.SiLU())
        self.head = nn.Conv2d(ch, 4, 1)

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (B,4,S/2,S/2)."""
        skip = self.stem(x)
        ctx = self.context(self.down(skip))
        up = F.interpolate(ctx, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(self.fuse(torch.cat([skip, up], dim=1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.heatmaps(x)
        b, k, h, w = logits.shape
        prob = logits.flatten(2).softmax(-1).view(b, k, h, w)
        scale = x.shape[-1] / w
        # Half-resolution cell i covers patch pixels [i*scale - 0.5, (i+1)*scale - 0.5]; its centre:
        gx = (torch.arange(w, device=x.device, dtype=x.dtype) + 0.5) * scale - 0.5
        gy = (torch.arange(h, device=x.device, dtype=x.dtype) + 0.5) * scale - 0.5
        u = (prob.sum(2) * gx).sum(-1)
        v = (prob.sum(3) * gy).sum(-1)
        return torch.stack([u, v], dim=-1)

    def read(self, images: np.ndarray | torch.Tensor) -> list[AxisKeypoints]:
        """Keypoints of HxWx3 (or BxHxWx3) NumPy axis images, or a (B,3,H,W) tensor."""
        x = torch.as_tensor(images, dtype=torch.float32)
        if x.ndim == 3:
            x = x[None]
        if x.shape[-1] == 3 and x.shape[1] != 3:
            x = x.permute(0, 3, 1, 2)
        if x.shape[-1] != self.config.size or x.shape[-2] != self.config.size:
            raise ValueError(f"reader expects {self.config.size}x{self.config.size} axis images, got {tuple(x.shape[-2:])}")
        with torch.inference_mode():
            kp = self(x.to(next(self.parameters()).device)).cpu().numpy().astype(np.float64)
        return [AxisKeypoints(k[0], k[1:]) for k in kp]


def degrade(images: torch.Tensor, gen: torch.Generator, prob: float) -> torch.Tensor:
    """Corrupt a batch of axis images (B,3,H,W) like an imperfect generator: each sample with probability `prob`."""
    b, _, h, w = images.shape
    dev = images.device

    def pick(p: float) -> torch.Tensor:
        return (torch.rand(b, 1, 1, 1, generator=gen) < p * prob).to(dev)

    x = images
    # Broken strokes: random blocks of every channel are wiped.
    holes = torch.ones_like(x)
    for _ in range(3):
        cx = torch.randint(0, w, (b,), generator=gen)
        cy = torch.randint(0, h, (b,), generator=gen)
        r = torch.randint(1, max(2, w // 12), (b,), generator=gen)
        ys = torch.arange(h).view(1, h, 1)
        xs = torch.arange(w).view(1, 1, w)
        box = ((xs - cx.view(b, 1, 1)).abs() <= r.view(b, 1, 1)) & ((ys - cy.view(b, 1, 1)).abs() <= r.view(b, 1, 1))
        ch = torch.rand(b, 3, 1, 1, generator=gen) < 0.5
        holes = holes * (1.0 - (box.unsqueeze(1) & ch).float().to(dev))
    x = torch.where(pick(0.5), x * holes, x)
    # Stray blobs: Gaussian spots added to random channels.
    ys = torch.arange(h, device=dev, dtype=x.dtype).view(1, 1, h, 1)
    xs = torch.arange(w, device=dev, dtype=x.dtype).view(1, 1, 1, w)
    blobs = torch.zeros_like(x)
    for _ in range(2):
        c = (torch.rand(b, 2, 1, 1, generator=gen) * torch.tensor([w, h]).view(1, 2, 1, 1)).to(dev)
        s = (1.0 + torch.rand(b, 1, 1, 1, generator=gen) * w / 16).to(dev)
        amp = (torch.rand(b, 3, 1, 1, generator=gen) < 0.4).float().to(dev) * (0.5 + 0.5 * torch.rand(b, 3, 1, 1, generator=gen).to(dev))
        blobs = blobs + amp * torch.exp(-((xs - c[:, :1]) ** 2 + (ys - c[:, 1:]) ** 2) / (2 * s**2))
    x = torch.where(pick(0.5), (x + blobs).clamp(0, 1), x)
    # Blur with a random Gaussian sigma (one kernel per batch keeps it cheap).
    sigma = 0.5 + 1.5 * torch.rand(1, generator=gen).item()
    k = torch.arange(-3, 4, dtype=x.dtype, device=dev)
    k = torch.exp(-(k**2) / (2 * sigma**2))
    k = k / k.sum()
    blurred = F.conv2d(F.pad(x, (3, 3, 0, 0), mode="replicate"), k.view(1, 1, 1, 7).repeat(3, 1, 1, 1), groups=3)
    blurred = F.conv2d(F.pad(blurred, (0, 0, 3, 3), mode="replicate"), k.view(1, 1, 7, 1).repeat(3, 1, 1, 1), groups=3)
    x = torch.where(pick(0.5), blurred, x)
    # Uneven intensity and sensor-like noise, as diffusion outputs are neither binary nor clean.
    gain = (0.6 + 0.6 * torch.rand(b, 3, 1, 1, generator=gen)).to(dev)
    x = torch.where(pick(0.5), (x * gain).clamp(0, 1), x)
    noise = torch.randn(x.shape, generator=gen).to(dev) * (0.15 * torch.rand(b, 1, 1, 1, generator=gen).to(dev))
    return torch.where(pick(0.7), (x + noise).clamp(0, 1), x)


def synth_batch(
    rng: np.random.Generator,
    gen: torch.Generator,
    config: ReaderConfig,
    batch: int,
    degrade_prob: float,
    return_samples: bool = False,
) -> tuple:
    """Rendered (and degraded) axis images (B,3,S,S) with their true keypoints (B,4,2).

    With `return_samples`, also the crops' PatchSamples and leg lengths, for scoring poses downstream.
    """
    S = config.size
    kps, samples, lens = [], [], []
    for _ in range(batch):
        lengths = np.array([1.0, rng.uniform(0.6, 1.4), rng.uniform(0.6, 1.4)]) * 0.05
        ps = sample_patch(rng, radius=float(lengths.max()), size=S)
        kps.append(axis_keypoints(ps.K_patch, ps.R, ps.t, lengths))
        samples.append(ps)
        lens.append(lengths)
    kp = torch.as_tensor(np.stack(kps), dtype=torch.float32)
    width = config.line_width * (0.7 + 0.6 * torch.rand(1, generator=gen).item())
    images = render_axis_keypoints_torch(kp, S, width)
    if degrade_prob > 0:
        images = degrade(images, gen, degrade_prob)
    if return_samples:
        return images, kp, samples, lens
    return images, kp


def train_reader(
    config: ReaderConfig, out: str | Path | None = None, log_csv: str | Path | None = None, progress: bool = True
) -> KeypointReader:
    """Train a reader from scratch on rendered axis images (CPU minutes); saves to `out` when given."""
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    model = KeypointReader(config)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=1e-4)
    warmup = max(1, config.steps // 20)

    def lr_at(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, config.steps - warmup)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    writer = None
    log_file = None
    if log_csv is not None:
        log_file = open(log_csv, "w", newline="")
        writer = csv.writer(log_file)
        writer.writerow(["step", "loss_px", "lr", "seconds"])
    start = time.time()
    model.train()
    try:
        for step in tqdm(range(config.steps), desc="train reader", disable=not progress):
            images, kp = synth_batch(rng, gen, config, config.batch, config.degrade_prob)
            loss = F.smooth_l1_loss(model(images), kp, beta=1.0)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            if writer is not None and (step % 10 == 0 or step == config.steps - 1):
                writer.writerow([step, f"{loss.item():.5f}", f"{sched.get_last_lr()[0]:.2e}", f"{time.time() - start:.1f}"])
    finally:
        if log_file is not None:
            log_file.close()
    model.eval()
    if out is not None:
        save_checkpoint(out, KIND, config, {"reader": model})
    return model


def load_reader(path: str | Path, device: str = "cpu") -> KeypointReader:
    """A trained reader from its checkpoint (config included), in eval mode."""
    config, states, _ = read_checkpoint(path, KIND, ReaderConfig)
    model = KeypointReader(config)
    load_state(model, states.get("reader", {}), str(path))
    return model.to(device).eval()
