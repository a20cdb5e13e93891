"""Training the localiser on the real pixels: the checkpoint's localiser fine-tuned on the recording's frames with
the boxes of their pseudo-poses, each batch mixed with rendered frames so the objects the recording never
labelled stay found, and the checkpoint written a blend of the fine-tune's weights with the source's (as the AGM's
adaptation, `adapt.train`).

A pseudo-labelled frame names only the objects whose pose was accepted: the others may stand anywhere in it, so
the frame teaches where a labelled object is and, for that object alone, where it is not (`partial` frames,
`focal_loss`'s `known`). Resumable as every trainer (`train/loop.py`): OUT.state.pt beside the checkpoint.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from axispose_core.adapt.train import blend
from axispose_core.config import PRESET
from axispose_core.data.synth.config import SynthConfig, recipe
from axispose_core.data.synth.generate import generate
from axispose_core.estimator import Estimator
from axispose_core.localiser.model import build_localiser
from axispose_core.localiser.scoring import detection_scores
from axispose_core.train.localiser import LocaliserDataset, LocaliserTrainConfig, localiser_loss
from axispose_core.train.loop import (
    DEFAULT_RUN,
    OptimConfig,
    RunOptions,
    TrainJob,
    Validation,
    epochs,
    fit,
    training_device,
    training_record,
)


@dataclass(frozen=True)
class RenderedFrames:
    """The rendered frames mixed into the localiser's batches (`axispose synth` at the recording's camera, of the
    checkpoint's objects): `desk_scenes` of the desk recipe and `plain_scenes` of the plain one (the shipped
    localiser's last data), `images_per_scene` each."""

    desk_scenes: int = 40
    plain_scenes: int = 20
    images_per_scene: int = 25
    seed: int = 40000


@dataclass(frozen=True)
class AdaptLocaliserConfig:
    """How the localiser adapts: `real_share` of each batch's frames (on average) are the recording's, the rest
    rendered frames (`frames`); the checkpoint written holds `blend` of the fine-tune's (EMA) weights and the rest
    of the source's."""

    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(600, 16, 2e-4, warmup=50, grad_clip=5.0, ema_decay=0.99, save_every=100, val_every=300),
        metadata=PRESET,
    )
    """A YAML's `optim` section changes these values; the keys it leaves out keep them."""
    real_share: float = 0.5
    min_visib: float = 0.1
    blend: float = 0.7
    val_frames: int = 40
    frames: RenderedFrames = field(default_factory=RenderedFrames)

    @property
    def trains(self) -> bool:
        """Whether the localiser adapts at all (0 steps: it stays as the checkpoint has it)."""
        return self.optim.steps > 0

    def __post_init__(self) -> None:
        if not 0.0 < self.real_share < 1.0:
            raise ValueError(f"real_share must lie in (0, 1), got {self.real_share}")
        if not 0.0 <= self.blend <= 1.0:
            raise ValueError(f"blend must lie in [0, 1], got {self.blend}")


def render_frames(cfg: RenderedFrames, models: str | Path, objects: tuple[int, ...], K: np.ndarray, size: tuple[int, int],
                  out: str | Path, progress: bool = True) -> list[Path]:  # fmt: skip
    """The rendered frames (OUT/desk, OUT/plain) at the camera `K`, `size` (width, height); a call after an
    interrupted one finishes them, a call after a finished one renders nothing."""
    roots = []
    for k, (name, scenes) in enumerate((("desk", cfg.desk_scenes), ("plain", cfg.plain_scenes))):
        if scenes <= 0:
            continue
        scene, randomization = recipe(name)
        synth = SynthConfig(width=size[0], height=size[1], K=tuple(np.asarray(K, float).ravel().tolist()), objects=objects,
                            seed=cfg.seed + 10000 * k, scenes=scenes, images_per_scene=cfg.images_per_scene, scene=scene,
                            randomization=randomization)  # fmt: skip
        generate(synth, models, Path(out) / name, progress=progress)
        roots.append(Path(out) / name)
    return roots


class PartlyLabelled(LocaliserDataset):
    """Pseudo-labelled frames: their labels name only the objects whose pose was accepted, so a class is known (a
    negative away from its box) only in the frames that label it."""

    def known(self, i: int) -> np.ndarray:
        scene, im_id = self.frames[i]
        out = np.zeros(len(self.classes), np.float32)
        for g in scene.gt[im_id]:
            if g.obj_id in self.classes:
                out[self.classes[g.obj_id]] = 1
        return out


class MixedFrames(Dataset):
    """Rendered frames and the recording's, the recording's repeated so that they are `real_share` of an epoch."""

    def __init__(self, rendered: LocaliserDataset, real: LocaliserDataset, real_share: float) -> None:
        self.rendered, self.real = rendered, real
        self.repeats = max(1, round(real_share / (1 - real_share) * len(rendered) / len(real)))

    def __len__(self) -> int:
        return len(self.rendered) + self.repeats * len(self.real)

    @property
    def epoch(self) -> int:
        return self.rendered.epoch

    @epoch.setter
    def epoch(self, value: int) -> None:
        self.rendered.epoch = value
        self.real.epoch = value

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        if i < len(self.rendered):
            return self.rendered[i]
        return self.real[(i - len(self.rendered)) % len(self.real)]


def adapt_localiser(
    checkpoint: str | Path, labels: str | Path, frames: list[str | Path], models: str | Path, out: str | Path, cfg: AdaptLocaliserConfig,
    run: RunOptions = DEFAULT_RUN,
) -> int:  # fmt: skip
    """Fine-tune `checkpoint`'s localiser on the labelled frames `labels` (a BOP folder, `labels.write_labels`)
    mixed with the rendered BOP frames `frames`; OUT is the whole estimator with the adapted localiser (its AGM,
    verifier and refiner as they were). Validation: recall and precision on the first `val_frames` rendered
    frames (what adapting costs on renders). Returns the step reached."""
    base = Estimator.load(checkpoint)
    if base.localiser is None:
        raise ValueError(f"{checkpoint}: no localiser to adapt")
    config = base.localiser.config
    dev = training_device(run.device)
    torch.manual_seed(cfg.optim.seed)
    rendered = LocaliserDataset(frames, config, cfg.min_visib, seed=cfg.optim.seed, models_dir=models)
    real = PartlyLabelled([labels], config, cfg.min_visib, seed=cfg.optim.seed + 1, models_dir=models)
    if not len(real) or not len(rendered):
        raise ValueError(f"no frames to adapt the localiser on: {len(real)} labelled, {len(rendered)} rendered")
    model = build_localiser(config)
    model.load_state_dict(base.localiser.state_dict())
    source = {k: v.detach().clone() for k, v in model.state_dict().items()}
    loss_cfg = LocaliserTrainConfig(localiser=config)

    def written(ema: torch.nn.Module) -> torch.nn.Module:
        net = copy.deepcopy(ema).cpu().eval()
        net.load_state_dict(blend(source, net.state_dict(), cfg.blend))
        return net

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        record = training_record([str(labels), *map(str, frames)], step, cfg.optim.batch, seconds, dev, started_from)
        training = {**base.config.training, "adapt_localiser": {"config": dataclasses.asdict(cfg), **record}}
        est = Estimator(dataclasses.replace(base.config, training=training), base.agm, base.reader, "cpu", written(ema), base.meshes)
        est.save(out)

    def validate(ema: torch.nn.Module) -> dict[str, float]:
        scores = detection_scores(written(ema), frames, limit=cfg.val_frames)
        return {"val_recall": scores["recall"], "val_precision": scores["precision"]}

    job = TrainJob(
        cfg, model, epochs(MixedFrames(rendered, real, cfg.real_share), cfg.optim),
        lambda net, batch, _: localiser_loss(net, batch, loss_cfg), Path(out), save,
        validation=Validation(("val_recall", "val_precision"), validate), device=dev, desc="adapt localiser", init=str(checkpoint),
    )  # fmt: skip
    return fit(job, run)
