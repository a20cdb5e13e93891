"""Training on the real pixels: the AGM fine-tuned from an estimator checkpoint on the recording's crops at their
pseudo-poses, each batch mixed with the crop stream the checkpoint's AGM last trained on, so the synthetic skill
stays (Self6D++: a low learning rate, an EMA of the weights, strong photometric augmentation on the student's
input), and the checkpoint written a blend of the fine-tune's weights with the source's (`blend`). Resumable as
every trainer (`train/loop.py`): OUT.state.pt beside the checkpoint.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch

from axispose_core.adapt.crops import LabelledCrops, mixed_batches
from axispose_core.agm.model import AxisGenerator
from axispose_core.camera import CropJitter
from axispose_core.config import PRESET, config_from_dict
from axispose_core.data.bop_models import model_path
from axispose_core.data.meshes import load_ply
from axispose_core.data.synth.config import PhotometricConfig, StreamConfig
from axispose_core.data.synth.stream import CropStream
from axispose_core.estimator import Estimator
from axispose_core.evaluation.records import object_symmetries
from axispose_core.train.agm import VAL_COLUMNS, validate, with_depth_target
from axispose_core.train.loop import DEFAULT_RUN, OptimConfig, RunOptions, TrainJob, Validation, fit, training_device, training_record
from axispose_core.train.losses import AGMObjective

STRONG = PhotometricConfig(prob=0.8)
"""The photometric chain on the real crops: GDRNPP's LM-O strength, on four crops in five."""


@dataclass(frozen=True)
class AdaptTrainConfig:
    """How the AGM adapts: `real_per_batch` of each batch's crops are the recording's (at least `min_visib` visible
    by the models at their labels), the rest the crop stream's (`stream`: None, the one the checkpoint's AGM last
    trained on, as its training record says); the checkpoint written holds `blend` of the fine-tune's (EMA) weights
    and the rest of the source's."""

    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(600, 32, 1e-4, warmup=50, ema_decay=0.995, save_every=100, val_every=300, bf16=True),
        metadata=PRESET,
    )
    """A YAML's `optim` section changes these values; the keys it leaves out keep them."""
    real_per_batch: int = 16
    min_visib: float = 0.2
    augment: PhotometricConfig = STRONG
    jitter: CropJitter = field(default_factory=CropJitter)
    stream: StreamConfig | None = None
    val_samples: int = 64
    val_steps: int = 2
    val_seed: int = 1_000_000
    blend: float = 0.7
    """The fine-tune's share of the weights written, the source's the rest (WiSE-FT, Wortsman et al. 2022: the
    weights between the two keep most of the gain on the new domain at a fraction of the loss on the old; 1: the
    fine-tune as trained). docs/BENCHMARKS.md, *Adaptation*, measures 0.5, 0.7 and 1."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.blend <= 1.0:
            raise ValueError(f"blend must lie in [0, 1], got {self.blend}")
        if not 0 <= self.real_per_batch <= self.optim.batch:
            raise ValueError(f"real_per_batch must lie in 0..batch ({self.optim.batch}), got {self.real_per_batch}")


def checkpoint_stream(est: Estimator, models: str | Path) -> StreamConfig:
    """The crop stream the checkpoint's AGM last trained on, from its training record (the recipe's AGM stage), over
    `models`; the stream's defaults where the record does not say."""
    recipe = est.config.training.get("recipe", {})
    name = recipe.get("estimator", {}).get("agm")
    stage = next((s for s in recipe.get("stages", ()) if s.get("name") == name), None)
    base = config_from_dict(StreamConfig, stage["config"].get("stream", {}), f"{name}'s stream") if stage else StreamConfig()
    return dataclasses.replace(base, size=est.size, objects=tuple(o.obj_id for o in est.config.objects))


def adapt_agm(
    checkpoint: str | Path, labels: str | Path, models: str | Path, out: str | Path, cfg: AdaptTrainConfig, run: RunOptions = DEFAULT_RUN
) -> int:
    """Fine-tune `checkpoint`'s AGM on the labelled frames `labels` (a BOP folder, `labels.write_labels`) mixed with
    the stream over `models`; OUT is the whole estimator with the adapted AGM (its localiser, verifier and refiner
    as they were). Returns the step reached."""
    base = Estimator.load(checkpoint)
    objects = list(base.config.objects)
    stream_cfg = cfg.stream or checkpoint_stream(base, models)
    cfg = dataclasses.replace(cfg, stream=stream_cfg)
    dev = training_device(run.device)
    torch.manual_seed(cfg.optim.seed)
    model = AxisGenerator(base.config.agm)
    model.denoiser.load_state_dict(base.agm.denoiser.state_dict())
    real = LabelledCrops([labels], objects, base.size, models, cfg.augment, cfg.min_visib, cfg.jitter, cfg.optim.seed)
    if not len(real):
        raise ValueError(f"{labels}: no labelled crop at least {cfg.min_visib:.0%} visible to adapt on")
    stream = CropStream(stream_cfg, models)
    scales = torch.tensor([o.scale for o in objects], dtype=torch.float64)

    def batches(step: int):
        return mixed_batches(real, stream, cfg.optim.batch, cfg.real_per_batch, step, cfg.optim.seed, cfg.optim.workers)

    def loss(net: torch.nn.Module, batch: dict[str, torch.Tensor], gen: torch.Generator) -> torch.Tensor:
        return net(with_depth_target(batch, scales.to(batch["t"].device), base.size), gen)

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        record = training_record([str(labels), f"crop stream of {models}"], step, cfg.optim.batch, seconds, dev, started_from)
        training = {**base.config.training, "adapt": {"config": dataclasses.asdict(cfg), **record}}
        config = dataclasses.replace(base.config, training=training)
        Estimator(config, written(ema).cpu(), base.reader, "cpu", base.localiser, base.meshes).save(out)

    def written(ema: torch.nn.Module) -> torch.nn.Module:
        net = copy.deepcopy(ema)
        net.denoiser.load_state_dict(blend(base.agm.denoiser.state_dict(), net.denoiser.state_dict(), cfg.blend))
        return net

    held_out = Validation(VAL_COLUMNS, _held_out(cfg, stream_cfg, models, base, dev, written))
    job = TrainJob(
        cfg, model, batches, loss, Path(out), save, validation=held_out, device=dev, desc="adapt agm", init=str(checkpoint),
        objective=AGMObjective,
    )  # fmt: skip
    return fit(job, run)


def blend(source: Mapping[str, torch.Tensor], tuned: Mapping[str, torch.Tensor], weight: float) -> dict[str, torch.Tensor]:
    """`weight` of each tuned tensor and 1 - `weight` of the source's, in float64 before the tensors' own type;
    integer buffers (counters) are the tuned ones."""
    if source.keys() != tuned.keys():
        raise ValueError(f"the weights differ in their tensors: {sorted(source.keys() ^ tuned.keys())[:5]}")
    out = {}
    for k, a in tuned.items():
        if not a.is_floating_point():
            out[k] = a.clone()
            continue
        s = source[k].to(device=a.device, dtype=torch.float64)
        out[k] = ((1.0 - weight) * s + weight * a.to(torch.float64)).to(a.dtype)
    return out


def _held_out(cfg: AdaptTrainConfig, stream_cfg: StreamConfig, models: str | Path, base: Estimator, dev: torch.device,
              written: Callable[[torch.nn.Module], torch.nn.Module]):  # fmt: skip
    """The stream's held-out crops (seed `val_seed`) read by the weights a save would write: what adapting costs on
    renders, as the AGM's own trainer validates."""
    from axispose_core.data.synth.stream import CropStreamDataset

    crops = CropStreamDataset(CropStream(dataclasses.replace(stream_cfg, seed=cfg.val_seed), models))
    items = [crops[i] for i in range(cfg.val_samples)]
    objects = list(base.config.objects)
    scales = torch.tensor([o.scale for o in objects], dtype=torch.float64)
    batch = {k: torch.stack([it[k] for it in items]).to(dev) for k in items[0] if k != "keypoints"}
    batch = with_depth_target(batch, scales.to(dev), base.size)
    held = [objects[int(it["object"])] for it in items]
    points = {o.obj_id: load_ply(model_path(models, o.obj_id)).vertices for o in objects if o.symmetric}
    symmetries = object_symmetries(objects, points)
    lengths = torch.stack([torch.as_tensor(o.axes.lengths) for o in held]).numpy()
    syms = [symmetries.get(o.obj_id, []) for o in held]

    def metrics(ema: torch.nn.Module) -> dict[str, float]:
        return validate(written(ema), base.reader, batch, lengths, cfg.val_steps, syms)

    return metrics
