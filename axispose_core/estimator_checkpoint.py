"""The estimator's checkpoint: its config (`EstimatorConfig`: networks, objects, inference defaults) and the
reading and writing of its networks, localiser and refiner meshes in one safetensors file (`checkpoint.py`)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from axispose_core.agm.model import VERSION, AGMConfig, AxisGenerator
from axispose_core.checkpoint import ESTIMATOR, CheckpointError, load_state, read_checkpoint, read_metadata, save_checkpoint
from axispose_core.localiser.model import Localiser, LocaliserConfig, build_localiser
from axispose_core.localiser.verifier import DetectionVerifier
from axispose_core.objects import ObjectSpec
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.meshes import Meshes, ObjectMeshes
from axispose_core.tbm.dense import DenseFusion
from axispose_core.tbm.reader import KeypointReader, ReaderConfig

KIND = ESTIMATOR


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


def read_estimator(path: str | Path) -> tuple[EstimatorConfig, AxisGenerator, KeypointReader, Localiser | None, Meshes | None]:
    """An estimator checkpoint's config, AGM, reader, and localiser and refiner meshes where it carries them;
    a file of an earlier AGM version, or with weights its config does not describe, is a CheckpointError."""
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
    return config, agm, reader, localiser, meshes


def write_estimator(path: str | Path, config: EstimatorConfig, agm: AxisGenerator, reader: KeypointReader, localiser: Localiser | None,
                    meshes: Meshes | None, half: bool = False) -> None:  # fmt: skip
    """Write the checkpoint; `half`: weights in float16, as the shipped one (runs in float32 after loading)."""
    modules = {"agm": agm.denoiser, "reader": reader} | ({"localiser": localiser} if localiser else {})
    modules |= {"refine": ObjectMeshes(meshes)} if meshes is not None else {}
    save_checkpoint(path, KIND, config, modules, half=half)
