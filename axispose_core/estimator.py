"""One call from an image, K and object boxes to metric poses: crop -> AGM -> axis image -> reader -> TBM.

The boxes come from the caller (an external detector, ROIs, GT boxes) or from the localiser the checkpoint
may carry (`detect`).

The node, `axispose eval` and the demos all go through `Estimator`, so what is measured is what runs.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from axispose_core.agm.correspondences import dense_correspondences
from axispose_core.agm.denoiser import Encoding
from axispose_core.agm.guidance import AxisGeometry, self_consistency_target
from axispose_core.agm.model import VERSION, AGMConfig, AxisGenerator, depth_from_log
from axispose_core.agm.sampler import Guidance, Start, sample
from axispose_core.axis_image import AxisSpec, render_axis_image
from axispose_core.camera import InstanceCrop, instance_crop, off_axis, validate_intrinsics
from axispose_core.checkpoint import ESTIMATOR, CheckpointError, load_state, read_checkpoint, read_metadata, save_checkpoint
from axispose_core.consensus import Consensus, consensus
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.model import Localiser, LocaliserConfig, build_localiser
from axispose_core.localiser.verifier import DetectionVerifier
from axispose_core.objects import ObjectSpec
from axispose_core.precision import bf16_native
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.histograms import ColourHistograms
from axispose_core.refine.meshes import Meshes, ObjectMeshes
from axispose_core.refine.refiner import ContourRefiner
from axispose_core.refine.refiner import Start as RefineStart
from axispose_core.tbm.backproject import backproject_readings
from axispose_core.tbm.dense import DenseFusion, fuse_pose
from axispose_core.tbm.keypoints import AxisKeypoints
from axispose_core.tbm.reader import KeypointReader, ReaderConfig

KIND = ESTIMATOR
SHIPPED_ESTIMATOR = Path(__file__).resolve().parent / "models" / "axispose_lmo.safetensors"
"""The shipped LM-O estimator: the node's and `axispose validate`'s default checkpoint."""
PRECISIONS = ("auto", "float32", "bfloat16")


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything a checkpoint needs to run: networks, the objects it knows, and default inference settings."""

    agm: AGMConfig = field(default_factory=AGMConfig)
    reader: ReaderConfig = field(default_factory=ReaderConfig)
    objects: tuple[ObjectSpec, ...] = ()
    crop_pad: float = 1.25
    ddim_steps: int = 4
    guidance_scale: float = 0.0
    head_depth_weight: float = 0.9
    """Weight of the encoder's depth in the fused log depth (0: the TBM's from the drawn axis lengths alone, 1: the
    encoder's alone); the translation keeps the TBM's ray. The encoder's depth is the more precise of the two
    (bench/agm_error_sources.py measures the weights on held-out frames). This is the pose `dense_fusion` starts
    from."""
    head_offaxis: tuple[float, float] = (0.0, 0.0)
    """(c0, c1): the encoder's log depth's bias c0 + c1 (1 / cos θ - 1) against the crop centre's angle θ off the
    optical axis (`camera.off_axis`), measured on held-out stream crops (bench/head_offaxis.py), which the estimator
    takes off. The head sees the crop, not where in the frame it was cut: an object off the axis is drawn
    stretched, reads nearer than one on it at the same depth, and the head learns the stream's average; frames
    whose objects sit nearer the centre than the stream's would read too far."""
    dense_fusion: DenseFusion = field(default_factory=DenseFusion)
    """How the final pose is solved from the encoder's dense points with the TBM's rotation and origin and the
    encoder's depth as priors (`tbm/dense.py`'s `fuse_pose`; points 0: the consensus of the TBM's poses as it is)."""
    mode_sample: bool = True
    """Start each crop's first hypothesis from x_T = 0, the mode of the prior, and the others from N(0, I): one
    sample is then the network's most likely axis image instead of a random draw, and the others still give the
    consensus its spread."""
    training: dict = field(default_factory=dict)
    """Provenance: data recipe, steps, wall time, hardware."""
    localiser: LocaliserConfig | None = None
    """The 2D localiser's config when the checkpoint carries one."""
    verifier: DetectionVerifier | None = None
    """Where the checkpoint carries one (`axispose fit-verifier`), `find` rescores the localiser's detections with
    their poses' variances and publishes its probability as the score."""
    refine: RefineConfig | None = None
    """Where the checkpoint carries its objects' meshes, how the contour refiner (`refine/`) moves each pose to the
    image's own contour after the fusion."""

    def __post_init__(self) -> None:
        if len(self.head_offaxis) != 2 or not all(math.isfinite(c) for c in self.head_offaxis):
            raise ValueError(f"head_offaxis must be two finite numbers (c0, c1), got {self.head_offaxis}")


def crop_batch(
    image_rgb: np.ndarray, K: np.ndarray, boxes: list[tuple[int, tuple[float, float, float, float]]], known: dict, size: int, pad: float
) -> tuple[list[InstanceCrop], torch.Tensor]:
    """Check K and that every box's object is `known`, then cut the boxes' crops and their (B,3,S,S) uint8 batch
    (the network normalises it): one place, so the estimator and the direct baseline read an image the same way."""
    K = validate_intrinsics(K)
    unknown = [o for o, _ in boxes if o not in known]
    if unknown:
        raise ValueError(f"objects {unknown} are not in this checkpoint (it knows {sorted(known)})")
    cuts = [instance_crop(image_rgb, K, box, size, pad=pad) for _, box in boxes]
    if not cuts:
        return cuts, torch.zeros((0, 3, size, size), dtype=torch.uint8)
    return cuts, torch.from_numpy(np.stack([c.patch for c in cuts])).permute(0, 3, 1, 2)


def fuse_depth(t: np.ndarray, z_head: float, weight: float) -> np.ndarray:
    """The TBM's translation `t` moved along its ray to the fused depth: the geometric mean of its depth and the
    encoder's `z_head`, weighted `weight` (head_depth_weight) for the encoder's; both scale with λ_O, so the
    result does too."""
    if weight <= 0 or t[2] <= 0:
        return t
    return t * float(np.exp(weight * (np.log(z_head) - np.log(t[2]))))


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
    warm_steps: int = 1
    """DDIM steps for a box that comes with a prior pose (`estimate`'s `priors`: a tracked object)..."""
    warm_strength: float = 0.5
    """...which start from the prior's axis image noised to this fraction of the schedule (`agm.sampler.Start`)."""
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


@dataclass(frozen=True)
class _Batch:
    """The crop stage's output, which the later stages share: per box its crop, embedding row and axis lengths (B,3);
    per sample (each box's `hypotheses` in a row) the intrinsics and lengths its keypoints are solved with."""

    boxes: list[tuple[int, tuple[float, float, float, float]]]
    cuts: list[InstanceCrop]
    pixels: torch.Tensor
    """(B,3,S,S) uint8: the network normalises it."""
    objects: torch.Tensor
    lengths: np.ndarray
    hypotheses: int
    K_rows: np.ndarray
    length_rows: np.ndarray
    priors: list[tuple[np.ndarray, np.ndarray] | None] | None = None
    """Per box a pose to start its samples from (None: from noise)."""


@dataclass(frozen=True)
class _Solved:
    """One box after the solve stage: the encoder's depth, its samples' poses (sample row, R, t with the fused depth),
    why the others failed, and the poses' consensus (None: no sample gave one)."""

    head_depth: float
    poses: list[tuple[int, np.ndarray, np.ndarray]]
    reasons: list[str]
    consensus: Consensus | None


@dataclass
class PoseEstimate:
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    ok: bool
    reason: str
    axis_image: np.ndarray
    """The generated axis image (S,S,3) in [0,1], for debug overlays."""
    K_patch: np.ndarray
    center: tuple[float, float]
    side: float
    samples: int = 1
    """AGM samples drawn for this box (`hypotheses`)."""
    samples_ok: int = 1
    """Samples that gave a pose; with two or more, the spread is filled in."""
    spread_deg: float = float("nan")
    spread_m: float = float("nan")
    covariance: np.ndarray | None = None
    """(6, 6) pose covariance (x, y, z, rx, ry, rz; camera frame; m², rad²): the dense fusion's (`FusedPose`) plus
    the samples' scatter about their consensus (consensus.py); without the fusion the scatter alone, with a floor
    (None for a single sample)."""
    fit_covariance: np.ndarray | None = None
    """(6, 6) the dense fusion's own covariance, without the samples' scatter: how well the crop's dense points fit
    the object's model, alike at any number of samples (what the detection verifier reads; None without the
    fusion)."""
    head_depth: float = float("nan")
    """The encoder's depth for this crop (m, linear in λ_O); t already fuses it with the TBM's (head_depth_weight)
    and with the dense points (dense_fusion)."""
    refined: bool = False
    """The contour refiner moved this pose (R, t and covariance are its); False where it did not run or kept the
    pose (`refine_kept`)."""
    refine_kept: str = ""
    """Why the refiner kept the unrefined pose (`refine.refiner.KEPT_REASONS`); empty where it refined or did not
    run."""
    contour_lines: float = float("nan")
    """Fraction of the object's contour lines the refiner could use at the end (NaN where it did not run)."""
    contour_agreement: float = float("nan")
    """How well the refined contour separates the object's colours from its surroundings' (0.5: not at all, 1:
    fully; NaN where the refiner did not refine): evidence for a detection verifier."""
    unrefined: tuple[np.ndarray, np.ndarray] | None = None
    """(R, t) as the fusion gave it, where the refiner saw this pose: what `axispose eval` scores the refinement
    against."""
    colours: ColourHistograms | None = None
    """The object's and its surroundings' colours the refiner learned here: what a tracker carries to the next
    frame (`follow`)."""
    contour_information: np.ndarray | None = None
    """(6,6) what the contour alone says of a followed pose (`Refinement.information`): its tracker, whose
    prediction was the refiner's prior, folds the pose in as that evidence, not the prior twice."""


@dataclass(frozen=True)
class Found:
    """A frame's objects found by the localiser (`Estimator.find`), each with its pose: `detections` carry the
    published score (the verifier's probability where the checkpoint has one, else the localiser's); `dropped`
    counts the detections posed and then refused by the verifier."""

    detections: list[Detection]
    poses: list[PoseEstimate]
    dropped: int = 0


def _guess(K_patch: np.ndarray, prior: tuple[np.ndarray, np.ndarray], lengths: np.ndarray, size: int) -> np.ndarray | None:
    """The axis image of a prior pose in a crop; None where it cannot be drawn (an axis behind the camera)."""
    try:
        return render_axis_image(K_patch, *prior, lengths, size)
    except ValueError:
        return None


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
        modules = {"agm": self.agm.denoiser, "reader": self.reader} | ({"localiser": self.localiser} if self.localiser else {})
        modules |= {"refine": ObjectMeshes(self.meshes)} if self.meshes is not None else {}
        save_checkpoint(path, KIND, self.config, modules, half=half)

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
        try:
            agm = json.loads(read_metadata(path, KIND).get("config", "{}")).get("agm", {})
        except (json.JSONDecodeError, AttributeError):
            agm = {"version": VERSION}  # unreadable: read_checkpoint says so
        if isinstance(agm, dict) and agm.get("version") != VERSION:
            raise CheckpointError(
                f"{path}: made by an earlier AxisPose (AGM version {agm.get('version', 1)}, this one runs {VERSION}); "
                "retrain it with `axispose train`"
            )
        config, states, _ = read_checkpoint(path, KIND, EstimatorConfig)
        agm = AxisGenerator(config.agm)
        load_state(agm.denoiser, states.get("agm", {}), f"{path} (agm)")
        reader = KeypointReader(config.reader)
        load_state(reader, states.get("reader", {}), f"{path} (reader)")
        localiser = None
        if config.localiser is not None:
            localiser = build_localiser(config.localiser)
            load_state(localiser, states.get("localiser", {}), f"{path} (localiser)")
        elif "localiser" in states:
            raise CheckpointError(f"{path}: holds localiser weights but no localiser config")
        meshes = None
        if config.refine is not None:
            try:
                meshes = ObjectMeshes.from_state(states.get("refine", {})).meshes()
            except ValueError as err:
                raise CheckpointError(f"{path}: {err}") from err
        elif "refine" in states:
            raise CheckpointError(f"{path}: holds refiner meshes but no refine config")
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
        priors: list[tuple[np.ndarray, np.ndarray] | None] | None = None,
    ) -> list[PoseEstimate]:
        """Poses for (obj_id, (x, y, w, h)) boxes in an RGB uint8 image; the crops go through the AGM as one batch
        (or batches of `options.max_boxes`).

        The data flow's stages, each one method: crop, sample (the AGM), read (the reader), solve (the TBM and the
        samples' consensus), fuse (the dense points), and over the whole frame's poses, refine (the contours).
        `options` holds the per-call settings (None: the checkpoint's defaults); `cancelled()` is asked between DDIM
        steps, and True raises `Cancelled`. `priors` gives per box a pose (R, t) it is likely near (None: none), e.g. a
        track's prediction: its samples start from that pose's axis image, `warm_steps` steps from `warm_strength` of
        the schedule.
        """
        options = options or EstimateOptions()
        if priors is not None and len(priors) != len(boxes):
            raise ValueError(f"{len(priors)} priors for {len(boxes)} boxes")
        size = options.max_boxes or max(1, len(boxes))
        poses = []
        for i in range(0, max(1, len(boxes)), size):  # no boxes: one call all the same, which checks K
            part = None if priors is None else priors[i : i + size]
            poses += self._estimate_batch(image_rgb, K, boxes[i : i + size], options, cancelled, part)
        return self._refine(image_rgb, K, poses, options) if options.refine and self.refiner is not None else poses

    def _estimate_batch(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        boxes: list[tuple[int, tuple[float, float, float, float]]],
        options: EstimateOptions,
        cancelled: Callable[[], bool] | None,
        priors: list[tuple[np.ndarray, np.ndarray] | None] | None,
    ) -> list[PoseEstimate]:
        """`estimate` on boxes that go through the AGM as one batch."""
        batch = self._crop(image_rgb, K, boxes, options)
        if batch is None:
            return []
        if priors is not None and any(p is not None for p in priors):
            batch = replace(batch, priors=list(priors))
        enc, images = self._sample(batch, options, cancelled)
        readings = self.reader.read(images)
        solved = self._solve(batch, readings, enc)
        return self._fuse(batch, enc, images, solved)

    def _crop(
        self, image_rgb: np.ndarray, K: np.ndarray, boxes: list[tuple[int, tuple[float, float, float, float]]], options: EstimateOptions
    ) -> _Batch | None:
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
        return _Batch(list(boxes), cuts, pixels, objects, lengths, k, K_rows, np.repeat(lengths, k, axis=0))

    def _sample(self, batch: _Batch, options: EstimateOptions, cancelled: Callable[[], bool] | None) -> tuple[Encoding, torch.Tensor]:
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
            if batch.priors is None:
                axes = self.sampler(self.agm, rows, steps, generator=gen, guidance=guidance, cancelled=cancelled, start=Start(noise_scale))
            else:
                axes = self._sample_warm(batch, rows, (steps, noise_scale, gen), options, (guidance, cancelled))
        return enc, ((axes.float() + 1) * 0.5).clamp(0, 1)

    def _sample_warm(self, batch: _Batch, rows: Encoding, cold: tuple, options: EstimateOptions, run: tuple) -> torch.Tensor:
        """Boxes without a prior from noise (`cold`: steps, noise scale, generator), those with one from their
        prior's axis image; `run` is (guidance, cancelled)."""
        steps, noise_scale, gen = cold
        guidance, cancelled = run
        k = batch.hypotheses
        guesses = [None if p is None else _guess(c.K_patch, p, lengths, self.size) for c, p, lengths in zip(batch.cuts, batch.priors,
                   batch.lengths, strict=True)]  # fmt: skip
        warm = torch.tensor([g is not None for g in guesses for _ in range(k)])
        if not warm.any():
            return self.sampler(self.agm, rows, steps, generator=gen, guidance=guidance, cancelled=cancelled, start=Start(noise_scale))
        x0 = torch.from_numpy(np.stack([g for g in guesses if g is not None])).permute(0, 3, 1, 2).repeat_interleave(k, dim=0) * 2 - 1
        out = torch.empty((len(warm), 3, self.size, self.size))
        for pick, start, n in ((~warm, Start(noise_scale[~warm]), steps),
                               (warm, Start(noise_scale[warm], x0, options.warm_strength), options.warm_steps)):  # fmt: skip
            if pick.any():
                idx = torch.nonzero(pick)[:, 0]
                out[idx] = self.sampler(self.agm, rows.select(idx.to(rows.context.device)), n, generator=gen, guidance=guidance,
                                        cancelled=cancelled, start=start).float().cpu()  # fmt: skip
        return out

    def _solve(self, batch: _Batch, readings: list[AxisKeypoints], enc: Encoding) -> list[_Solved]:
        """The TBM's pose of every sample (all boxes' in one refinement), its depth fused with the encoder's
        (`head_depth_weight`), and per box the consensus of the samples that gave one."""
        log_depth = enc.log_depth.detach().float().cpu().numpy()  # guided sampling runs outside inference mode
        results = backproject_readings(batch.K_rows, readings, batch.length_rows)
        k, out = batch.hypotheses, []
        for i, (cut, L) in enumerate(zip(batch.cuts, batch.lengths, strict=True)):
            z_head = self.head_depth(float(log_depth[i]), cut.K_patch, float(L[0]))
            poses, reasons = [], []
            for row in range(i * k, (i + 1) * k):
                res = results[row]
                if res is not None and res.ok:
                    poses.append((row, res.R, fuse_depth(res.t, z_head, self.config.head_depth_weight)))
                else:
                    reasons.append(readings[row].reason if res is None else res.reason)
            agreed = consensus(np.stack([p[1] for p in poses]), np.stack([p[2] for p in poses]), float(L.max())) if poses else None
            out.append(_Solved(z_head, poses, reasons, agreed))
        return out

    def _fuse(self, batch: _Batch, enc: Encoding, images: torch.Tensor, solved: list[_Solved]) -> list[PoseEstimate]:
        """Each box's pose from the encoder's dense points with its consensus and depth as priors (`dense_fusion`;
        points 0: the consensus as it is) and its covariance; a box no sample posed says why."""
        dense = dense_correspondences(enc, batch.lengths[:, 0]) if self.config.dense_fusion.points > 0 else None
        out = []
        for i, ((obj_id, _), cut, s) in enumerate(zip(batch.boxes, batch.cuts, solved, strict=True)):
            pick = dict(obj_id=obj_id, K_patch=cut.K_patch, center=cut.center, side=cut.side, samples=batch.hypotheses,
                        samples_ok=len(s.poses), head_depth=s.head_depth)  # fmt: skip
            c = s.consensus
            if c is None:
                axis_image = images[i * batch.hypotheses].permute(1, 2, 0).cpu().numpy()
                out.append(PoseEstimate(R=np.eye(3), t=np.zeros(3), ok=False, reason=s.reasons[0], axis_image=axis_image, **pick))
                continue
            many = len(s.poses) > 1
            axis_image = images[s.poses[c.medoid][0]].permute(1, 2, 0).cpu().numpy()
            spread = dict(spread_deg=c.spread_deg, spread_m=c.spread_m) if many else {}
            R, t, cov, fit = c.R, c.t, (c.covariance if many else None), None
            if dense is not None and (fused := fuse_pose(cut.K_patch, R, t, dense[i], s.head_depth, self.config.dense_fusion)) is not None:
                # The law of total covariance: the fusion's own (given the consensus) plus the samples' scatter about it.
                R, t, cov, fit = fused.R, fused.t, fused.covariance + (c.scatter if many else 0.0), fused.covariance
            out.append(PoseEstimate(R=R, t=t, ok=True, reason="", axis_image=axis_image, covariance=cov, fit_covariance=fit, **pick,
                                    **spread))  # fmt: skip
        return out

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
