"""`axispose train-reader`: the TBM's keypoint reader on axis images rendered from random poses and crops
(`pose_sampling`) and degraded the way generated images fail (broken strokes, blur, noise, stray blobs, uneven
intensity). No dataset is needed: batch s is drawn from (seed, s), so a resumed run continues where it stopped."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from axispose_core.axis_image import axis_keypoints, render_axis_keypoints_torch
from axispose_core.checkpoint import save_checkpoint
from axispose_core.pose_sampling import sample_patch
from axispose_core.tbm.reader import KIND, KeypointReader, ReaderConfig
from axispose_core.train.loop import DEFAULT_RUN, OptimConfig, RunOptions, TrainJob, Validation, fit, training_device, training_record

VAL_SEED = 1_000_000


@dataclass(frozen=True)
class ReaderTrainConfig:
    """The defaults train the shipped reader (`tbm/reader.py`'s SHIPPED_READER)."""

    reader: ReaderConfig = field(default_factory=ReaderConfig)
    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(steps=3000, batch=32, lr=2e-3, warmup=150, ema_decay=0.99, workers=0, val_every=250)
    )
    degrade_prob: float = 0.7
    """Share of the training images degraded."""
    val_samples: int = 256


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
    cfg: ReaderTrainConfig,
    out: str | Path,
    run: RunOptions = DEFAULT_RUN,
) -> int:
    """Train (or continue) a reader; OUT holds the EMA weights with their config. Returns the step reached."""
    dev = training_device(run.device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    optim = cfg.optim
    torch.manual_seed(optim.seed)
    val_images, val_kp = synth_batch(
        np.random.default_rng(VAL_SEED), torch.Generator().manual_seed(VAL_SEED), cfg.reader, cfg.val_samples, cfg.degrade_prob
    )

    def batches(step: int) -> Iterator[dict[str, torch.Tensor]]:
        rng, gen = np.random.default_rng([optim.seed, step]), torch.Generator().manual_seed(optim.seed * 1000 + step)
        while True:
            images, kp = synth_batch(rng, gen, cfg.reader, optim.batch, cfg.degrade_prob)
            yield {"image": images, "keypoints": kp}

    def loss(net: torch.nn.Module, batch: dict[str, torch.Tensor], _: torch.Generator) -> torch.Tensor:
        return F.smooth_l1_loss(net(batch["image"]).float(), batch["keypoints"], beta=1.0)

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        with torch.inference_mode():
            kp = ema(val_images.to(dev)).float().cpu()
        return {"val_kp_err_px": float((kp - val_kp).norm(dim=-1).mean(dim=-1).median())}

    def save(ema: torch.nn.Module, step: int, seconds: float, init: str | None) -> None:
        record = training_record(["rendered axis images"], step, optim.batch, seconds, dev, init)
        save_checkpoint(out, KIND, cfg.reader, {"reader": ema}, extra={"training": record})

    validation = Validation(("val_kp_err_px",), validate)
    job = TrainJob(cfg, KeypointReader(cfg.reader), batches, loss, out, save, validation=validation, device=dev, desc="train reader")
    return fit(job, run)
