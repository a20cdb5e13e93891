"""One call from an image, K and object boxes to metric poses: crop -> AGM -> axis image -> reader -> TBM.

The boxes come from the caller (an external detector, ROIs, GT boxes) or from the localiser the checkpoint
may carry (`detect`).

The node, `axispose eval` and the demos all go through `Estimator`, so what is measured is what runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from axispose_core.agm.guidance import self_consistency_target
from axispose_core.agm.model import AGMConfig, AxisGenerator
from axispose_core.axis_image import AxisSpec
from axispose_core.camera import validate_intrinsics
from axispose_core.checkpoint import CheckpointError, load_state, read_checkpoint, save_checkpoint
from axispose_core.data.crops import instance_crop
from axispose_core.data.objects import ObjectSpec
from axispose_core.detect.decode import Detection
from axispose_core.detect.model import Localiser, LocaliserConfig
from axispose_core.tbm.backproject import backproject
from axispose_core.tbm.reader import KeypointReader, ReaderConfig

KIND = "estimator"


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything a checkpoint needs to run: networks, the objects it knows, and default inference settings."""

    agm: AGMConfig = field(default_factory=AGMConfig)
    reader: ReaderConfig = field(default_factory=ReaderConfig)
    objects: tuple[ObjectSpec, ...] = ()
    crop_pad: float = 1.25
    ddim_steps: int = 4
    guidance_scale: float = 0.0
    training: dict = field(default_factory=dict)
    """Provenance: data recipe, steps, wall time, hardware."""
    localiser: LocaliserConfig | None = None
    """The 2D localiser's config when the checkpoint carries one."""


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


class Estimator:
    """Holds the AGM and the keypoint reader; `estimate(image, K, boxes)` returns one pose per box."""

    def __init__(
        self, config: EstimatorConfig, agm: AxisGenerator, reader: KeypointReader, device: str = "cpu", localiser: Localiser | None = None
    ) -> None:
        if agm.config.denoiser.size != reader.config.size:
            raise ValueError(f"AGM draws {agm.config.denoiser.size}px axis images, the reader reads {reader.config.size}px")
        if (localiser is None) != (config.localiser is None) or (localiser is not None and localiser.config != config.localiser):
            raise ValueError("the localiser and config.localiser must be given together and agree")
        if localiser is not None and not set(localiser.config.obj_ids) <= {o.obj_id for o in config.objects}:
            raise ValueError(f"the localiser finds objects {localiser.config.obj_ids}, not all known to the estimator")
        self.config = config
        self.device = torch.device(device)
        self.agm = agm.to(self.device).eval()
        self.reader = reader.to(self.device).eval()
        self.localiser = localiser.to(self.device).eval() if localiser is not None else None
        self.objects = {o.obj_id: o for o in config.objects}

    @property
    def size(self) -> int:
        return self.config.agm.denoiser.size

    def save(self, path: str | Path) -> None:
        modules = {"agm": self.agm.denoiser, "reader": self.reader} | ({"localiser": self.localiser} if self.localiser else {})
        save_checkpoint(path, KIND, self.config, modules)

    def with_localiser(self, localiser: Localiser) -> Estimator:
        """This estimator carrying `localiser` (replacing any it had), so one checkpoint serves the node."""
        return Estimator(replace(self.config, localiser=localiser.config), self.agm, self.reader, str(self.device), localiser)

    def detect(self, image_rgb: np.ndarray, threshold: float | None = None) -> list[Detection]:
        """Objects found in a full frame by the checkpoint's localiser (none found: an empty list)."""
        if self.localiser is None:
            raise ValueError("this checkpoint has no localiser: pass boxes, or attach one with `axispose train-detector --attach`")
        return self.localiser.detect(image_rgb, threshold)

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> Estimator:
        config, states, _ = read_checkpoint(path, KIND, EstimatorConfig)
        agm = AxisGenerator(config.agm)
        load_state(agm.denoiser, states.get("agm", {}), f"{path} (agm)")
        reader = KeypointReader(config.reader)
        load_state(reader, states.get("reader", {}), f"{path} (reader)")
        localiser = None
        if config.localiser is not None:
            localiser = Localiser(config.localiser)
            load_state(localiser, states.get("localiser", {}), f"{path} (localiser)")
        elif "localiser" in states:
            raise CheckpointError(f"{path}: holds localiser weights but no localiser config")
        return cls(config, agm, reader, device, localiser)

    def estimate(
        self,
        image_rgb: np.ndarray,
        K: np.ndarray,
        boxes: list[tuple[int, tuple[float, float, float, float]]],
        steps: int | None = None,
        guidance_scale: float | None = None,
        seed: int = 0,
        scales: dict[int, float] | None = None,
    ) -> list[PoseEstimate]:
        """Poses for (obj_id, (x, y, w, h)) boxes in an RGB uint8 image; all crops go through the AGM as one batch.

        `scales` overrides λ_O per object id (metres), e.g. from the node's object_scale parameters.
        """
        K = validate_intrinsics(K)
        unknown = [o for o, _ in boxes if o not in self.objects]
        if unknown:
            raise ValueError(f"objects {unknown} are not in this checkpoint (it knows {sorted(self.objects)})")
        if not boxes:
            return []
        steps = steps or self.config.ddim_steps
        scale = self.config.guidance_scale if guidance_scale is None else guidance_scale
        S = self.size
        cuts = [instance_crop(image_rgb, K, box, S, pad=self.config.crop_pad) for _, box in boxes]
        Kp = [c.K_patch for c in cuts]
        lengths = []
        for obj_id, _ in boxes:
            spec = self.objects[obj_id]
            lengths.append(AxisSpec((scales or {}).get(obj_id, spec.scale), spec.ratio_b, spec.ratio_c).lengths)
        x = torch.from_numpy(np.stack([c.patch for c in cuts]).astype(np.float32) / 127.5 - 1).permute(0, 3, 1, 2).to(self.device)

        def guidance(x0: torch.Tensor):
            return self_consistency_target(x0, self.reader, np.stack(Kp), np.stack(lengths))

        gen = torch.Generator().manual_seed(seed)
        with torch.inference_mode(scale <= 0):
            axes = self.agm.sample(x, steps, generator=gen, guidance=guidance if scale > 0 else None, guidance_scale=scale)
        images = ((axes + 1) * 0.5).clamp(0, 1)
        readings = self.reader.read(images)
        out = []
        for (obj_id, _), kp, cut, L, img in zip(boxes, readings, cuts, lengths, images, strict=True):
            axis_image = img.permute(1, 2, 0).cpu().numpy()
            if not kp.ok:
                out.append(PoseEstimate(obj_id, np.eye(3), np.zeros(3), False, kp.reason, axis_image, cut.K_patch, cut.center, cut.side))
                continue
            res = backproject(cut.K_patch, kp.origin, kp.endpoints, L, refine=True)
            out.append(PoseEstimate(obj_id, res.R, res.t, res.ok, res.reason, axis_image, cut.K_patch, cut.center, cut.side))
        return out
