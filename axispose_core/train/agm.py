"""`axispose train`: the AGM on the crop stream (or on BOP folders) — AdamW, warm-up + cosine, clipping, EMA,
resumable.

By default every training sample is a crop-stream sample (`data/synth/stream.py`) never seen before: step s
uses samples s*batch ... (s+1)*batch - 1, so a resumed run continues where it stopped and no data is stored.
BOP folders (`data`) train on their annotated crops instead, e.g. to fine-tune on a user's own frames.
Validation reads a fixed held-out batch (`train/sources.py`): stream samples of seed `val_seed`, or crops of
held-out BOP folders.

A run writes OUT (the estimator checkpoint, EMA weights, config inside) and OUT.state.pt (model, EMA,
optimiser, step, RNG: what `--resume` needs), both atomically every `save_every` steps and at the end, and
OUT.csv (loss, learning rate, crops seen, wall time, periodic held-out metrics). `--max-minutes` stops cleanly,
so long runs are chains of short ones. Under `torchrun`, DistributedDataParallel (gloo on CPU, nccl on CUDA)
splits the batches (rank r takes every world-th stream sample from r); rank 0 writes.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from axispose_core.agm.correspondences import dense_correspondences
from axispose_core.agm.model import AGMConfig, AxisGenerator, depth_from_log, grow_into, transplant
from axispose_core.agm.sampler import sample
from axispose_core.axis_image import axis_keypoints
from axispose_core.data.meshes import refiner_meshes
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, stream_loader
from axispose_core.estimator import Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.metrics import Symmetry, nearest_truth, re
from axispose_core.objects import ObjectSpec
from axispose_core.tbm.backproject import backproject_readings
from axispose_core.tbm.dense import translation_from_points
from axispose_core.tbm.reader import SHIPPED_READER, KeypointReader, load_reader
from axispose_core.train.dataset import AxisCropDataset
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
    world,
)
from axispose_core.train.losses import AGMObjective, agm_losses, dense_targets, log_depth_target
from axispose_core.train.sources import CropSources


@dataclass(frozen=True)
class CurriculumStage:
    """The stream's occlusion and clutter until step `until` (exclusive); the rest of StreamConfig is the run's."""

    until: int
    visib: tuple[float, float] = (0.1, 1.0)
    occluded_prob: float = 0.0
    clutter_prob: float = 0.0
    neighbours: tuple[int, int] = (0, 0)

    def stream(self, base: StreamConfig) -> StreamConfig:
        return dataclasses.replace(
            base, visib=self.visib, occluded_prob=self.occluded_prob, clutter_prob=self.clutter_prob, neighbours=self.neighbours
        )


@dataclass(frozen=True)
class TrainConfig:
    """The defaults train the shipped AGM's first stage (config/train_agm.yaml; config/recipes/axispose_lmo.yaml)."""

    agm: AGMConfig = field(default_factory=AGMConfig)
    optim: OptimConfig = field(
        default_factory=lambda: OptimConfig(
            steps=200_000, batch=16, lr=1e-3, warmup=200, ema_decay=0.999, workers=1, val_every=250, bf16=True
        )
    )
    min_visib: float = 0.1
    """Least visible fraction of the BOP instances trained on (BOP folders only)."""
    val_samples: int = 64
    val_steps: int = 2
    stream: StreamConfig = field(default_factory=lambda: StreamConfig(occluded_prob=0.0, clutter_prob=0.0, neighbours=(0, 0)))
    """The crop stream trained on when no BOP folders are given; its crop size must be the denoiser's. One object
    per crop, nothing in front or behind: pose is learned about twice as fast per step on these."""
    val_seed: int = 1_000_000
    """Seed of the held-out stream samples: fixed, so that the curves of different runs read the same crops."""
    curriculum: tuple[CurriculumStage, ...] = ()
    """Easier streams first, in order of `until`; `stream` from the last stage's `until` on, and for validation.
    Measured: unoccluded crops teach the encoder pose about twice as fast per step, also on occluded ones. A
    resumed run may change its stream from its current step on (`--resume` with a stage appended that ends there)."""


def stream_at(cfg: dict, step: int) -> dict:
    """The stream a TrainConfig, as `dataclasses.asdict` gives it, trains on at `step` (its curriculum applied)."""
    for stage in cfg.get("curriculum", ()):
        if step < stage["until"]:
            return cfg["stream"] | {k: v for k, v in stage.items() if k != "until"}
    return cfg["stream"]


def same_stream_before(saved: dict, now: TrainConfig, step: int) -> bool:
    """Whether `now` trains on the same stream as the saved config at every step before `step`: the streams are
    piecewise constant, so comparing them where any stage of either begins suffices."""
    new = dataclasses.asdict(now)
    starts = {0} | {s["until"] for c in (saved, new) for s in c.get("curriculum", ()) if s["until"] < step}
    return all(stream_at(saved, s) == stream_at(new, s) for s in starts)


def validate(
    agm: AxisGenerator,
    reader: KeypointReader,
    batch: dict[str, torch.Tensor],
    lengths: np.ndarray,
    steps: int,
    syms: Sequence[Sequence[Symmetry]] = (),
) -> dict[str, float]:
    """On a fixed batch of held-out crops: the diffusion loss at fixed timesteps and noise (four draws); median
    rotation error and the share within 15° of the sample started from the prior's mode (the estimator's first
    hypothesis), a symmetric object's taken up to its symmetries `syms` (per crop; as eval takes it); the
    reader's median keypoint error (px, mean over origin and endpoints) on the generated axis images; the median
    relative depth error of the TBM (from the drawn axis lengths) and of the encoder's depth head; the encoder's
    median surface-point error (object radii), and the median relative depth error of t solved from its points
    with the true rotation (what its points know of depth)."""
    with torch.no_grad():
        loss = float(np.mean([agm_losses(agm, batch, torch.Generator().manual_seed(k))["diffusion"].item() for k in range(4)]))
        enc = agm.encode(batch["crop"], batch["object"])
        axes = sample(agm, enc, steps, generator=torch.Generator().manual_seed(0), noise_scale=torch.zeros(len(batch["crop"])))
    readings = reader.read(((axes + 1) * 0.5).clamp(0, 1).cpu())
    size = batch["crop"].shape[-1]
    errs, kp_errs, tbm_depth, head_depth = [], [], [], []
    K_all, R_all, t_all = (batch[k].cpu().numpy() for k in ("K", "R", "t"))
    solved = backproject_readings(K_all, readings, lengths)
    for i, kp in enumerate(readings):
        K, R, t = K_all[i], R_all[i], t_all[i]
        z = depth_from_log(float(enc.log_depth[i]), K, float(lengths[i][0]), size)
        head_depth.append(abs(z / t[2] - 1))
        res = solved[i]
        if res is not None and res.ok:
            errs.append(re(res.R, nearest_truth(res.R, R, t, syms[i] if syms else ())[0]))
            tbm_depth.append(abs(res.t[2] / t[2] - 1))
        else:
            errs.append(180.0)
        if kp.ok:
            kp_errs.append(float(np.linalg.norm(kp.array - axis_keypoints(K, R, t, lengths[i]), axis=1).mean()))
    point_err, points_depth = float("nan"), []
    if "points" in batch:  # crop-stream samples know their surface points
        target, m = dense_targets(batch["points"], batch["mask_visib"], enc.points.shape[-1])
        err = ((enc.points - target).abs().mean(dim=1, keepdim=True) * m).sum(dim=(1, 2, 3)) / m.sum(dim=(1, 2, 3)).clamp(min=1)
        point_err = float(err.median())
        # The points' depth with the true rotation: what the dense head alone says about the object's extent.
        for i, (uv, X, w) in enumerate(dense_correspondences(enc, lengths[:, 0])):
            t_pts = translation_from_points(K_all[i], R_all[i], uv, X, w)
            points_depth.append(abs(t_pts[2] / t_all[i][2] - 1) if t_pts is not None else 1.0)
    errs_a = np.array(errs)

    def median(v: list[float]) -> float:
        return float(np.median(v)) if v else float("nan")

    return {"val_loss": loss, "val_rot_median_deg": float(np.median(errs_a)), "val_rot_within_15deg": float(np.mean(errs_a < 15.0)),
            "val_kp_err_px": median(kp_errs), "val_depth_tbm": median(tbm_depth), "val_depth_head": median(head_depth),
            "val_points_err": point_err, "val_depth_points": median(points_depth)}  # fmt: skip


VAL_COLUMNS = (
    "val_loss",
    "val_rot_median_deg",
    "val_rot_within_15deg",
    "val_kp_err_px",
    "val_depth_tbm",
    "val_depth_head",
    "val_points_err",
    "val_depth_points",
)


def curriculum_batches(
    stages: list[tuple[int | None, CropStream]], batch: int, step: int, world: int = 1, rank: int = 0, workers: int = 0
) -> Iterator[dict[str, torch.Tensor]]:
    """Training batches of a staged stream from `step` on: stage (until, stream) gives steps up to `until` (None:
    endless), sample indices step * batch * world + rank, strided by world, of its own stream (so a resumed run,
    whatever its stage, continues where it stopped)."""
    for until, stream in stages:
        if until is not None and step >= until:
            continue
        stop = None if until is None else until * batch * world
        for item in stream_loader(stream, batch, start=step * batch * world + rank, stop=stop, stride=world, workers=workers):
            step += 1
            yield item
        if until is None:
            return


def _batch_of(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([it[k] for it in items]) for k in items[0] if k != "keypoints"}


def with_depth_target(batch: dict[str, torch.Tensor], scales: torch.Tensor, size: int) -> dict[str, torch.Tensor]:
    """The batch with the encoder's depth target (from K', t and the objects' λ_O) added."""
    return batch | {"log_depth": log_depth_target(batch["K"], batch["t"], scales[batch["object"]], size)}


def start_from(model: AxisGenerator, start: AxisGenerator, name: str | Path) -> None:
    """`model` from `start`'s weights: grown (the same trunk kind) or transplanted (another trunk)."""
    if type(model.config.denoiser.encoder.trunk) is type(start.config.denoiser.encoder.trunk):
        if grown := grow_into(model, start):  # the same network: a plain copy, nothing grown
            print(f"started from {name}, its encoder grown by {len(grown)} block(s), each starting as the identity")
        return
    fresh = transplant(model, start)
    print(f"started from {name} on a new trunk: {len(fresh)} tensors outside the trunk start fresh ({', '.join(fresh)})")


def held_out_validation(
    cfg: TrainConfig, sources: CropSources, objects: list[ObjectSpec], scales: torch.Tensor, reader: KeypointReader, dev: torch.device
) -> Callable[[torch.nn.Module], dict[str, float]] | None:
    """What the trainer validates its EMA weights with: a full sampling and back-projection of the held-out crops
    (`validate`), symmetric objects' rotations taken up to symmetry; None when there are none. `scales`: the
    objects' λ_O, as the training loss takes them."""
    crop = cfg.agm.denoiser.size
    items = sources.held_out(AxisCropDataset, objects, cfg.stream, cfg.val_seed, crop, cfg.val_samples, cfg.optim.seed)
    if not items:
        return None
    batch = {k: v.to(dev) for k, v in with_depth_target(_batch_of(items), scales, crop).items()}
    held = [objects[int(it["object"])] for it in items]
    symmetries = sources.symmetries(objects)
    lengths, syms = np.stack([o.axes.lengths for o in held]), [symmetries.get(o.obj_id, []) for o in held]

    def validate_ema(ema: torch.nn.Module) -> dict[str, float]:
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.optim.bf16):
            return validate(ema, reader, batch, lengths, cfg.val_steps, syms)

    return validate_ema


def train_agm(
    cfg: TrainConfig,
    sources: CropSources,
    out: str | Path,
    run: RunOptions = DEFAULT_RUN,
    reader_path: str | Path | None = None,
    init: str | Path | None = None,
) -> int:
    """Train (or continue) the AGM; returns the step reached.

    Without BOP folders in `sources` the samples come from the crop stream of `cfg.stream` over its models
    folder; with them, from their annotated crops. `init`: an estimator checkpoint whose (EMA) weights a new
    run starts from, with a fresh optimiser and schedule, e.g. to train the shipped model on: the same AGM network,
    one whose encoder the config gives more blocks per stage (`grow_into`: more capacity without starting over),
    or one on another trunk (`transplant`: the denoiser and heads kept under a new, e.g. pretrained, trunk);
    a resumed run restores its own weights and keeps recording the checkpoint its first call started from.
    """
    distributed = "RANK" in os.environ and "WORLD_SIZE" in os.environ
    if distributed and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() and run.device != "cpu" else "gloo")
    rank, size = world()
    dev = training_device(run.device)
    if dev.type == "cuda" and distributed:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    optim = cfg.optim
    torch.manual_seed(optim.seed + rank)
    crop = cfg.agm.denoiser.size
    reader = load_reader(reader_path or SHIPPED_READER)
    if reader.config.size != crop:
        raise ValueError(f"the keypoint reader reads {reader.config.size}px images; the AGM is configured for {crop}px")
    objects, train_set, stream = sources.training(AxisCropDataset, cfg.stream, crop, cfg.min_visib, optim.seed)
    if train_set is not None:
        batches = epochs(train_set, optim)
    else:
        untils = [stage.until for stage in cfg.curriculum]
        if untils != sorted(untils) or any(u < 1 for u in untils):
            raise ValueError(f"curriculum stages must end at increasing steps >= 1, got {untils}")
        stages = [(stage.until, CropStream(stage.stream(cfg.stream), sources.models)) for stage in cfg.curriculum] + [(None, stream)]

        def batches(step: int) -> Iterator[dict[str, torch.Tensor]]:
            return curriculum_batches(stages, optim.batch, step, size, rank, optim.workers)

    if len(objects) > (rows := cfg.agm.denoiser.encoder.objects):  # the config's rows are a minimum, not a limit
        encoder = dataclasses.replace(cfg.agm.denoiser.encoder, objects=len(objects))
        cfg = dataclasses.replace(cfg, agm=dataclasses.replace(cfg.agm, denoiser=dataclasses.replace(cfg.agm.denoiser, encoder=encoder)))
        print(f"{len(objects)} objects: the encoder's object embedding gets a row for each (the config has {rows})")
    model = AxisGenerator(cfg.agm)
    if not run.resume:
        start_pretrained(model)
    if init and not run.resume:
        start_from(model, Estimator.load(init).agm, init)
    scales = torch.tensor([o.scale for o in objects], dtype=torch.float64)
    folder = sources.models_folder()
    meshes = refiner_meshes(folder, [o.obj_id for o in objects]) if folder is not None and rank == 0 else None
    validate_ema = held_out_validation(cfg, sources, objects, scales, reader, dev) if rank == 0 else None

    def loss(net: torch.nn.Module, batch: dict[str, torch.Tensor], gen: torch.Generator) -> torch.Tensor:
        return net(with_depth_target(batch, scales.to(batch["t"].device), crop), gen)

    def save(ema: torch.nn.Module, step: int, seconds: float, started_from: str | None) -> None:
        record = training_record(sources.describe(), step, optim.batch * size, seconds, dev, started_from)
        est_cfg = EstimatorConfig(agm=cfg.agm, reader=reader.config, objects=tuple(objects), training=record)
        est = Estimator(est_cfg, ema, reader, "cpu" if dev.type == "cpu" else str(dev))
        (est.with_refiner(meshes) if meshes is not None else est).save(out)  # the contour refiner of the models' meshes

    job = TrainJob(
        cfg, model, batches, loss, out, save, validation=Validation(VAL_COLUMNS, validate_ema), device=dev, desc="train agm",
        init=str(init) if init else None, data_fields=("stream", "curriculum"),
        same_data=lambda saved, at: same_stream_before(saved, cfg, at), objective=AGMObjective,
    )  # fmt: skip
    return fit(job, run)
