"""One call from an image, K and object boxes to metric poses: crop -> AGM -> axis image -> reader -> TBM.

The boxes come from the caller (an external detector, ROIs, GT boxes) or from the localiser the checkpoint
may carry (`detect`).

The node, `axispose eval` and the demos all go through `Estimator`, so what is measured is what runs. Its
checkpoint (config and file) is `estimator_checkpoint.py`'s, the stages that run no network `estimator_stages.py`'s,
and what it returns `pose_estimate.py`'s.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from axispose_core.agm.denoiser import Encoding
from axispose_core.agm.guidance import AxisGeometry, self_consistency_target
from axispose_core.agm.model import AxisGenerator, depth_from_log
from axispose_core.agm.sampler import Guidance, sample
from axispose_core.axis_image import AxisSpec
from axispose_core.camera import off_axis, validate_intrinsics
from axispose_core.checkpoint import CheckpointError
from axispose_core.estimator_checkpoint import EstimatorConfig, read_estimator, write_estimator
from axispose_core.estimator_stages import CropBatch, crop_batch, fuse_samples, solve_samples
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.model import Localiser
from axispose_core.localiser.verifier import DetectionVerifier
from axispose_core.pose_estimate import Found, PoseEstimate
from axispose_core.precision import bf16_native
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.meshes import Meshes
from axispose_core.refine.refiner import ContourRefiner
from axispose_core.refine.refiner import Start as RefineStart
from axispose_core.tbm.reader import KeypointReader

SHIPPED_ESTIMATOR = Path(__file__).resolve().parent / "models" / "axispose_lmo.safetensors"
"""The shipped LM-O estimator: the node's and `axispose validate`'s default checkpoint."""
PRECISIONS = ("auto", "float32", "bfloat16")


@dataclass(frozen=True)
class EstimateOptions:
    """Per-call settings of `Estimator.estimate`, one value the node, eval and benches build; None takes the
    checkpoint's (`EstimatorConfig`)."""

    steps: int | None = None
    """DDIM steps (None or 0: `ddim_steps`)."""
    guidance_scale: float | None = None
    """Run-time guidance weight (0: off)."""
    seed: int = 0
    """Seed of the starting noise, so a call repeats exactly."""
    scales: Mapping[int, float] | None = None
    """λ_O (metres) per object id in place of the checkpoint's, e.g. the node's object_scale parameters."""
    hypotheses: int = 1
    """AGM samples per crop, drawn in the same batch; with two or more the pose is their consensus, with their spread
    and covariance."""
    mode_sample: bool | None = None
    """Whether each crop's first sample starts from the prior's mode."""
    max_boxes: int | None = None
    """Most boxes in one AGM batch (None: all at once); more are posed in successive batches of this many, so the
    memory a call takes and the batch shapes it runs stay within what a caller warmed up."""
    refine: bool = True
    """Refine the poses on the image's contours where the checkpoint carries a refiner (`EstimatorConfig.refine`)."""
    follow_passes: int = 0
    """Correspondence passes of `follow`: the last n of the refiner's `track_scales` (0: all): fewer make a frame
    cheaper and reach less far from the predicted pose."""

    def __post_init__(self) -> None:
        if self.hypotheses < 1:
            raise ValueError(f"hypotheses must be >= 1, got {self.hypotheses}")
        if self.max_boxes is not None and self.max_boxes < 1:
            raise ValueError(f"max_boxes must be >= 1 or None, got {self.max_boxes}")
        if self.follow_passes < 0:
            raise ValueError(f"follow_passes must be >= 0, got {self.follow_passes}")


class Estimator:
    """Holds the AGM and the keypoint reader; `estimate(image, K, boxes)` returns one pose per box."""

    def __init__(
        self,
        config: EstimatorConfig,
        agm: AxisGenerator,
        reader: KeypointReader,
        device: str = "cpu",
        localiser: Localiser | None = None,
        meshes: Meshes | None = None,
    ) -> None:
        if len(config.objects) > agm.config.denoiser.encoder.objects:
            raise ValueError(f"{len(config.objects)} objects, but the AGM's encoder embeds {agm.config.denoiser.encoder.objects}")
        if agm.config.denoiser.size != reader.config.size:
            raise ValueError(f"AGM draws {agm.config.denoiser.size}px axis images, the reader reads {reader.config.size}px")
        if (localiser is None) != (config.localiser is None) or (localiser is not None and localiser.config != config.localiser):
            raise ValueError("the localiser and config.localiser must be given together and agree")
        if config.verifier is not None and localiser is None:
            raise ValueError("a verifier rescores the localiser's detections: this estimator has no localiser")
        if localiser is not None and not set(localiser.config.obj_ids) <= {o.obj_id for o in config.objects}:
            raise ValueError(f"the localiser finds objects {localiser.config.obj_ids}, not all known to the estimator")
        if (meshes is None) != (config.refine is None):
            raise ValueError("the refiner's meshes and config.refine must be given together")
        if meshes is not None and set(meshes) != {o.obj_id for o in config.objects}:
            known = [o.obj_id for o in config.objects]
            raise ValueError(f"the refiner has meshes of objects {sorted(meshes)}, the estimator knows {known}")
        self.config = config
        self.device = torch.device(device)
        self.agm = agm.to(self.device).eval()
        self.reader = reader.to(self.device).eval()
        self.localiser = localiser.to(self.device).eval() if localiser is not None else None
        self._detector = self.localiser.fused() if self.localiser is not None else None
        self.objects = {o.obj_id: o for o in config.objects}
        self.index = {o.obj_id: k for k, o in enumerate(config.objects)}
        self.bf16 = False
        """Run the AGM (encoder and denoiser) under bfloat16 autocast; see `set_precision`."""
        self.sampler = sample
        """How axis images are drawn from an encoding (`agm/sampler.py`'s `sample`, with its signature)."""
        self.meshes = meshes
        self.refiner = ContourRefiner(config.refine, meshes) if meshes is not None and config.refine is not None else None
        """The contour refiner (`refine/`) where the checkpoint carries one."""

    def set_precision(self, precision: str) -> str:
        """Set the AGM's arithmetic: float32, bfloat16, or auto (bfloat16 where the device computes it natively:
        1.5x faster on this project's CPU at 4 samples per crop); returns the one used."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.bf16 = precision == "bfloat16" or (precision == "auto" and bf16_native(self.device))
        return "bfloat16" if self.bf16 else "float32"

    @property
    def size(self) -> int:
        return self.config.agm.denoiser.size

    def save(self, path: str | Path, half: bool = False) -> None:
        """Write the checkpoint; `half`: weights in float16, as the shipped one (runs in float32 after loading)."""
        write_estimator(path, self.config, self.agm, self.reader, self.localiser, self.meshes, half)

    def with_localiser(self, localiser: Localiser) -> Estimator:
        """This estimator carrying `localiser` (replacing any it had, and the verifier fitted to that one's scores), so
        one checkpoint serves the node."""
        config = replace(self.config, localiser=localiser.config, verifier=None)
        return Estimator(config, self.agm, self.reader, str(self.device), localiser, self.meshes)

    def with_verifier(self, verifier: DetectionVerifier | None, record: dict | None = None) -> Estimator:
        """This estimator with `verifier` (None: without one) rescoring what `find` finds; `record`, how it was fitted,
        joins the training record (`training["verifier"]`)."""
        training = self.config.training if record is None else {**self.config.training, "verifier": record}
        config = replace(self.config, verifier=verifier, training=training)
        return Estimator(config, self.agm, self.reader, str(self.device), self.localiser, self.meshes)

    def with_refiner(self, meshes: Meshes | None, config: RefineConfig | None = None) -> Estimator:
        """This estimator with a contour refiner of the objects' `meshes` (metres; `data.meshes.refiner_meshes`)
        and `config` (None: the defaults), or without one (meshes None)."""
        config = None if meshes is None else (config or RefineConfig())
        return Estimator(replace(self.config, refine=config), self.agm, self.reader, str(self.device), self.localiser, meshes)

    def detect(self, image_rgb: np.ndarray, threshold: float | None = None) -> list[Detection]:
        """Objects found in a full frame by the checkpoint's localiser (none found: an empty list)."""
        if self._detector is None:
            raise ValueError("this checkpoint has no localiser: pass boxes, or attach one with `axispose train-localiser --attach`")
        return self._detector.detect(image_rgb, threshold)

    def find(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        threshold: float | None = None,
        options: EstimateOptions | None = None,
        cancelled: Callable[[], bool] | None = None,
        objects: Container[int] | None = None,
    ) -> Found:
        """The localiser's objects (of `objects`, None: all) scoring at least `threshold` (None: the localiser's),
        posed. With a verifier the localiser's detections down to its `min_score` are posed and rescored with their
        poses' variances, and `threshold` applies to that probability; the others are counted as dropped."""
        return self._posed(image_rgb, K, self._found(image_rgb, threshold, objects), threshold, options, cancelled)

    def find_each(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        threshold: float | None = None,
        options: EstimateOptions | None = None,
        objects: Container[int] | None = None,
    ) -> Iterator[Found]:
        """`find`, one detection at a time, the localiser's highest score first: each one's `Found` (kept, or
        counted as dropped) as soon as it is posed, so that a caller uses the likeliest objects before the others
        are posed."""
        for d in sorted(self._found(image_rgb, threshold, objects), key=lambda d: -d.score):
            yield self._posed(image_rgb, K, [d], threshold, options, None)

    def _found(self, image_rgb: np.ndarray, threshold: float | None, objects: Container[int] | None) -> list[Detection]:
        """The localiser's detections of `objects` to pose: down to the verifier's `min_score` where there is one."""
        verifier = self.config.verifier
        floor = threshold if verifier is None else verifier.min_score
        return [d for d in self.detect(image_rgb, floor) if objects is None or d.obj_id in objects]

    def _posed(
        self, image_rgb: np.ndarray, K: np.ndarray, dets: list[Detection], threshold: float | None, options: EstimateOptions | None,
        cancelled: Callable[[], bool] | None,
    ) -> Found:  # fmt: skip
        """The detections posed, and rescored by the verifier where there is one (those below `threshold` dropped)."""
        poses = self.estimate(image_rgb, K, [(d.obj_id, d.box) for d in dets], options=options, cancelled=cancelled)
        if self.config.verifier is None:
            return Found(dets, poses)
        scores, least = self._rescored([d.score for d in dets], poses, threshold)
        keep = [k for k, s in enumerate(scores) if s >= least]
        return Found([replace(dets[k], score=float(scores[k])) for k in keep], [poses[k] for k in keep], len(dets) - len(keep))

    def verified(self, scores: Sequence[float], poses: list[PoseEstimate], threshold: float | None = None) -> list[PoseEstimate]:
        """Detections' poses (their localiser `scores`) with those the checkpoint's verifier scores below `threshold`
        (None: the localiser's) refused (`ok` False, reason "verifier"); all of them as they are without one."""
        if self.config.verifier is None or not poses:
            return poses
        probability, least = self._rescored(scores, poses, threshold)
        return [p if q >= least or not p.ok else replace(p, ok=False, reason="verifier") for p, q in zip(poses, probability, strict=True)]

    def _rescored(self, scores: Sequence[float], poses: list[PoseEstimate], threshold: float | None) -> tuple[np.ndarray, float]:
        """The verifier's probability of each posed detection (its localiser score and its pose's dense-fusion
        covariance), and the least one published (`threshold`, None: the localiser's)."""
        least = self.localiser.config.threshold if threshold is None else threshold
        return self.config.verifier.rescore(scores, [p.fit_covariance if p.ok else None for p in poses]), least

    def head_depth(self, log_depth: float, K_patch: np.ndarray, scale: float) -> float:
        """The encoder's depth (m) for a crop with intrinsics K_patch, its off-axis bias (`head_offaxis`) taken off."""
        c0, c1 = self.config.head_offaxis
        return depth_from_log(log_depth - c0 - c1 * off_axis(K_patch, self.size), K_patch, scale, self.size)

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> Estimator:
        config, agm, reader, localiser, meshes = read_estimator(path)
        try:
            return cls(config, agm, reader, device, localiser, meshes)
        except ValueError as err:
            raise CheckpointError(f"{path}: {err}") from err

    def estimate(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        boxes: list[tuple[int, tuple[float, float, float, float]]],
        options: EstimateOptions | None = None,
        cancelled: Callable[[], bool] | None = None,
    ) -> list[PoseEstimate]:
        """Poses for (obj_id, (x, y, w, h)) boxes in an RGB uint8 image; the crops go through the AGM as one batch
        (or batches of `options.max_boxes`).

        The data flow's stages, each one step: crop, sample (the AGM), read (the reader), solve (the TBM and the
        samples' consensus), fuse (the dense points), and over the whole frame's poses, refine (the contours).
        `options` holds the per-call settings (None: the checkpoint's defaults); `cancelled()` is asked between DDIM
        steps, and True raises `Cancelled`.
        """
        options = options or EstimateOptions()
        size = options.max_boxes or max(1, len(boxes))
        poses = []
        for i in range(0, max(1, len(boxes)), size):  # no boxes: one call all the same, which checks K
            poses += self._estimate_batch(image_rgb, K, boxes[i : i + size], options, cancelled)
        return self._refine(image_rgb, K, poses, options) if options.refine and self.refiner is not None else poses

    def _estimate_batch(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        boxes: list[tuple[int, tuple[float, float, float, float]]],
        options: EstimateOptions,
        cancelled: Callable[[], bool] | None,
    ) -> list[PoseEstimate]:
        """`estimate` on boxes that go through the AGM as one batch."""
        batch = self._crop(image_rgb, K, boxes, options)
        if batch is None:
            return []
        enc, images = self._sample(batch, options, cancelled)
        readings = self.reader.read(images)
        solved = solve_samples(batch, readings, enc, self.head_depth, self.config.head_depth_weight)
        return fuse_samples(batch, enc, images, solved, self.config.dense_fusion)

    def _crop(
        self, image_rgb: np.ndarray, K: np.ndarray, boxes: list[tuple[int, tuple[float, float, float, float]]], options: EstimateOptions
    ) -> CropBatch | None:
        """The boxes' crops and their objects' axis lengths (λ_O from `options.scales` where given); None without
        boxes, after K and the objects are checked, so a bad call fails alike with or without boxes."""
        cuts, pixels = crop_batch(image_rgb, K, boxes, self.objects, self.size, self.config.crop_pad)
        if not boxes:
            return None
        scales = options.scales or {}
        specs = [self.objects[obj_id] for obj_id, _ in boxes]
        lengths = np.stack([AxisSpec(scales.get(o.obj_id, o.scale), o.ratio_b, o.ratio_c).lengths for o in specs])
        objects = torch.tensor([self.index[obj_id] for obj_id, _ in boxes], device=self.device)
        k = options.hypotheses
        K_rows = np.repeat(np.stack([c.K_patch for c in cuts]), k, axis=0)
        return CropBatch(list(boxes), cuts, pixels, objects, lengths, k, K_rows, np.repeat(lengths, k, axis=0))

    def _sample(self, batch: CropBatch, options: EstimateOptions, cancelled: Callable[[], bool] | None) -> tuple[Encoding, torch.Tensor]:
        """Every crop's encoding and its `hypotheses` axis images (B·K,3,S,S) in [0,1], drawn as one batch. Guided
        sampling differentiates through the reader, so it runs outside inference mode."""
        scale = self.config.guidance_scale if options.guidance_scale is None else options.guidance_scale
        k = batch.hypotheses

        def target(x0: torch.Tensor) -> AxisGeometry:
            return self_consistency_target(x0, self.reader, batch.K_rows, batch.length_rows)

        gen = torch.Generator().manual_seed(options.seed)
        noise_scale = torch.ones(len(batch.cuts) * k)
        if self.config.mode_sample if options.mode_sample is None else options.mode_sample:
            noise_scale[::k] = 0.0  # each crop's first sample from the prior's mode
        guidance = Guidance(target, scale) if scale > 0 else None
        steps = options.steps or self.config.ddim_steps
        with torch.inference_mode(scale <= 0), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            enc = self.agm.encode(batch.pixels.to(self.device), batch.objects)
            rows = enc.repeat(k)
            axes = self.sampler(self.agm, rows, steps, generator=gen, guidance=guidance, cancelled=cancelled, noise_scale=noise_scale)
        return enc, ((axes.float() + 1) * 0.5).clamp(0, 1)

    def _size(self, obj_id: int, options: EstimateOptions) -> float:
        """The object's size against its mesh's: a run-time λ_O (`options.scales`) over the checkpoint's."""
        scale = self.objects[obj_id].scale
        return (options.scales or {}).get(obj_id, scale) / scale

    def _refine(self, image_rgb: np.ndarray, K: np.ndarray, poses: list[PoseEstimate], options: EstimateOptions) -> list[PoseEstimate]:
        """The frame's poses moved to the image's contours together (each masks the lines of those behind it); a
        pose the refiner keeps says why (`refine_kept`)."""
        posed = [k for k, p in enumerate(poses) if p.ok]
        starts = [RefineStart(poses[k].obj_id, poses[k].R, poses[k].t, poses[k].covariance, self._size(poses[k].obj_id, options))
                  for k in posed]  # fmt: skip
        out = list(poses)
        for k, r in zip(posed, self.refiner.refine(image_rgb, np.asarray(K, dtype=np.float64), starts), strict=True):
            out[k] = replace(poses[k], R=r.R, t=r.t, covariance=r.covariance, refined=r.refined, refine_kept=r.reason,
                             contour_lines=r.lines, contour_agreement=r.agreement, unrefined=(poses[k].R, poses[k].t),
                             colours=r.colours)  # fmt: skip
        return out

    def follow(self, image_rgb: np.ndarray, K: np.ndarray, last: Sequence[PoseEstimate], predicted: Sequence[tuple[np.ndarray, ...]],
               options: EstimateOptions | None = None) -> list[PoseEstimate]:  # fmt: skip
        """Tracked objects followed to this frame by their contours alone, no AGM: each from its `predicted` (R, t,
        covariance) with the colours its `last` pose learned (`colours`; without them the whole schedule). Each
        result is its last pose moved: `refined` where the contour took it, else `ok` False (the object is lost
        to the contour: `refine_kept` says why)."""
        if self.refiner is None:
            raise ValueError("this checkpoint has no contour refiner to follow objects with")
        K = validate_intrinsics(K)
        options = options or EstimateOptions()
        starts = [RefineStart(p.obj_id, R, t, cov, self._size(p.obj_id, options)) for p, (R, t, cov) in zip(last, predicted, strict=True)]
        out = []
        for p, r in zip(last, self.refiner.refine(image_rgb, K, starts, [p.colours for p in last], options.follow_passes), strict=True):
            out.append(replace(p, R=r.R, t=r.t, covariance=r.covariance, ok=r.refined, reason="" if r.refined else f"contour: {r.reason}",
                               refined=r.refined, refine_kept=r.reason, contour_lines=r.lines, contour_agreement=r.agreement,
                               unrefined=None, colours=r.colours or p.colours, contour_information=r.information))  # fmt: skip
        return out
