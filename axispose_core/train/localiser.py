"""`axispose train-localiser`: the CenterNet localiser on synthetic BOP frames, with the AGM trainer's conventions
(AdamW, warm-up + cosine, clipping, EMA weights in the checkpoint, seeded, resumable from OUT.state.pt, CSV log
with periodic validation recall, `--max-minutes`).

Boxes are bbox_obj (the whole object, occluded parts included: the square the AGM's crops are cut around) of
instances with visib_fract >= `min_visib`; each instance's centre counts 1 + `occluded_weight` * (1 - visib_fract)
in the loss, so partly hidden instances (few, and the ones the localiser misses) can count more. Frames are zoomed
and shifted at random (boxes follow) and colour-jittered on top of the data's own randomisation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from axispose_core.checkpoint import save_checkpoint
from axispose_core.data.bop_scene import BopScene, bop_frames
from axispose_core.data.synth.appearance import photometric, surface
from axispose_core.data.synth.config import PhotometricConfig, SurfaceConfig
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.localiser.decode import draw_targets, focal_loss
from axispose_core.localiser.model import STRIDE, Localiser, LocaliserConfig, build_localiser
from axispose_core.localiser.scoring import detection_scores, frame_instances
from axispose_core.localiser.weights import KIND, warm_start
from axispose_core.train.loop import (
    DEFAULT_RUN,
    OptimConfig,
    RunOptions,
    TrainJob,
    Validation,
    epochs,
    fit,
    start_pretrained,
    training_device,
    training_record,
)
from axispose_core.trunks.style_mix import StyleMixConfig


@dataclass(frozen=True)
class LocaliserTrainConfig:
    localiser: LocaliserConfig = field(default_factory=LocaliserConfig)
    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(steps=4000, batch=16, lr=2e-3, warmup=100, grad_clip=5.0, ema_decay=0.99)
    )
    min_visib: float = 0.1
    occluded_weight: float = 0.0
    size_weight: float = 0.1
    offset_weight: float = 1.0
    val_frames: int = 40
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    """The appearance chain on each training frame, over the data's own randomisation (off by default)."""
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    """Each object's own look (fine detail, colour response) varied on its visible pixels, one draw per instance, where
    the frames have BOP `mask_visib` files (off by default)."""
    style_mix: StyleMixConfig = field(default_factory=StyleMixConfig)
    """Feature statistics mixed between the frames of a batch after the trunk's middle stages (off by default)."""
    frozen_parts: tuple[str, ...] = ()
    """Parts after the trunk kept as loaded (`localiser.model.PARTS`; the trunk's stages: `optim.freeze_trunk`), e.g.
    `[fuse32, fuse, heat]` to train the box heads of a localiser whose detections should stay as they are."""


class LocaliserDataset(Dataset):
    """Training frames, resized, zoomed, shifted and recoloured at random, with heatmap/size/offset targets;
    randomness depends on (seed, epoch, index)."""

    def __init__(
        self,
        roots: list[str | Path],
        config: LocaliserConfig,
        min_visib: float,
        seed: int = 0,
        occluded_weight: float = 0.0,
        models_dir: str | Path | None = None,
        photometric: PhotometricConfig | None = None,
        surface: SurfaceConfig | None = None,
    ) -> None:
        self.config, self.seed, self.epoch = config, seed, 0
        self.photometric = photometric or PhotometricConfig()
        self.surface = surface or SurfaceConfig()
        self.occluded_weight = occluded_weight
        self.classes = {o: k for k, o in enumerate(config.obj_ids)}
        self.frames = bop_frames(roots, gt_info_from_models(models_dir))
        self.min_visib = min_visib

    def __len__(self) -> int:
        return len(self.frames)

    def boxes(self, i: int) -> list[tuple[int, tuple[float, float, float, float], float]]:
        """(class index, bbox_obj, loss weight) of the frame's instances the localiser should find."""
        scene, im_id = self.frames[i]
        return [
            (self.classes[obj_id], tuple(float(v) for v in box), 1 + self.occluded_weight * (1 - visib))
            for obj_id, box, visib in frame_instances(scene, im_id, tuple(self.classes))
            if visib >= self.min_visib
        ]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        scene, im_id = self.frames[i]
        rng = np.random.default_rng([self.seed, self.epoch, i])
        rgb = scene.rgb(im_id)
        w, h = self.config.input_size
        sx, sy = w / rgb.shape[1], h / rgb.shape[0]
        A = np.array([[sx, 0, 0], [0, sy, 0]], np.float64)
        # zoom about the centre and shift; boxes follow the same affine map
        z = rng.uniform(0.8, 1.25)
        tx, ty = rng.uniform(-0.1, 0.1) * w, rng.uniform(-0.1, 0.1) * h
        A = np.array([[z, 0, (1 - z) * w / 2 + tx], [0, z, (1 - z) * h / 2 + ty]]) @ np.vstack([A, [0, 0, 1]])
        if self.surface.detail_prob > 0 or self.surface.response_prob > 0:
            rgb = np.round(255 * self._surfaces(rng, scene, im_id, rgb.astype(np.float32) / 255)).astype(np.uint8)
        image = cv2.warpAffine(rgb, A, (w, h), flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REFLECT101).astype(np.float32) / 255
        image = np.clip(image * rng.uniform(0.7, 1.3, 3) + rng.uniform(-0.1, 0.1), 0, 1)
        image, _ = photometric(rng, self.photometric, image, scale=A[0, 0])
        instances = self.boxes(i)
        boxes = [(c, (A[0, 0] * x + A[0, 2], A[1, 1] * y + A[1, 2], A[0, 0] * bw, A[1, 1] * bh)) for c, (x, y, bw, bh), _ in instances]
        weights = [wt for _, _, wt in instances]
        heat, log_size, offset, mask = draw_targets(boxes, len(self.classes), (h // STRIDE, w // STRIDE), STRIDE, weights)
        return {
            "image": torch.from_numpy(np.round(image * 255).astype(np.uint8)).permute(2, 0, 1),
            "heat": torch.from_numpy(heat),
            "log_size": torch.from_numpy(log_size),
            "offset": torch.from_numpy(offset),
            "mask": torch.from_numpy(mask),
            "known": torch.from_numpy(self.known(i)),
        }

    def known(self, i: int) -> np.ndarray:
        """Per class, 1 where the frame's labels say where the object is, and so where it is not: every class of
        an annotated frame (`focal_loss`'s `known`)."""
        return np.ones(len(self.classes), np.float32)

    def _surfaces(self, rng: np.random.Generator, scene: BopScene, im_id: int, image: np.ndarray) -> np.ndarray:
        """`appearance.surface` on each known instance's visible pixels (its mask's box only: the cost follows the
        object's size); instances without a mask file keep their look."""
        for k, (gt, _) in enumerate(scene.instances(im_id)):
            path = scene.root / "mask_visib" / f"{im_id:06d}_{k:06d}.png"
            if gt.obj_id not in self.classes or not path.exists():
                continue
            mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
            ys, xs = np.nonzero(mask)
            if len(ys):
                box = np.s_[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
                image[box] = surface(rng, self.surface, image[box], mask[box])
        return image


def localiser_loss(model: Localiser, batch: dict[str, torch.Tensor], cfg: LocaliserTrainConfig) -> torch.Tensor:
    heat, log_size, offset = model(batch["image"])
    mask = batch["mask"][:, None]
    n = mask.sum().clamp(min=1)
    size_loss = (F.l1_loss(log_size, batch["log_size"], reduction="none") * mask).sum() / n
    off_loss = (F.l1_loss(offset, batch["offset"], reduction="none") * mask).sum() / n
    return focal_loss(heat, batch["heat"], mask, known=batch.get("known")) + cfg.size_weight * size_loss + cfg.offset_weight * off_loss


def train_localiser(
    cfg: LocaliserTrainConfig,
    data: list[str | Path],
    out: str | Path,
    val_data: list[str | Path] | None = None,
    run: RunOptions = DEFAULT_RUN,
    init: str | Path | None = None,
) -> int:
    """Train (or continue) the localiser; OUT holds the EMA weights with their config. Returns the step reached.
    `init`: a trained checkpoint to start from (`warm_start`); a resumed run restores its own weights instead (and
    keeps recording the checkpoint its first call started from)."""
    dev = training_device(run.device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.optim.seed)
    train_set = LocaliserDataset(
        data,
        cfg.localiser,
        cfg.min_visib,
        seed=cfg.optim.seed,
        occluded_weight=cfg.occluded_weight,
        photometric=cfg.photometric,
        surface=cfg.surface,
    )
    if not len(train_set):
        raise ValueError(f"no frames in {data}")

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        provenance = training_record(data, step, cfg.optim.batch, seconds, dev, started_from)
        save_checkpoint(out, KIND, cfg.localiser, {"localiser": ema}, extra={"training": provenance})

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        scores = detection_scores(ema, val_data, limit=cfg.val_frames)
        return {"val_recall": scores["recall"], "val_precision": scores["precision"]}

    model = build_localiser(cfg.localiser)
    model.trunk.mix_styles(cfg.style_mix)
    if not run.resume:
        start_pretrained(model)
    if init and not run.resume:
        fresh = warm_start(model, init)
        shown = (": " + ", ".join(fresh[:6]) + (" ..." if len(fresh) > 6 else "")) if fresh else ""
        print(f"started from {init}; {len(fresh)} of {len(model.state_dict())} tensors start fresh{shown}")
    model.freeze_parts(cfg.frozen_parts)
    job = TrainJob(
        cfg, model, epochs(train_set, cfg.optim), lambda net, batch, _: localiser_loss(net, batch, cfg), out, save,
        validation=Validation(("val_recall", "val_precision"), validate if val_data else None), device=dev,
        desc="train localiser", init=str(init) if init else None,
    )  # fmt: skip
    return fit(job, run)
