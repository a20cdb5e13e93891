"""Every knob of the synthetic data generator, saved next to the data it made (synth_config.json)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from axispose_core.checkpoint import config_from_dict
from axispose_core.pose_sampling import LMO_K


@dataclass(frozen=True)
class SceneConfig:
    """What is in front of the camera."""

    objects_per_image: tuple[int, int] = (3, 6)
    distractors_per_image: tuple[int, int] = (1, 4)
    distance: tuple[float, float] = (0.35, 1.5)
    upright_prob: float = 0.5
    elevation_deg: tuple[float, float] = (-14.0, 89.0)
    camera_roll_deg: tuple[float, float] = (-30.0, 30.0)
    cluster_spread: float = 0.6
    """Lateral spread of objects around the scene centre, in object diameters (smaller: more occlusion)."""
    distractor_size: tuple[float, float] = (0.03, 0.15)


@dataclass(frozen=True)
class RandomizationConfig:
    """Domain randomisation of appearance."""

    photo_background_prob: float = 0.6
    light_intensity: tuple[float, float] = (0.6, 1.4)
    light_color_jitter: float = 0.15
    ambient: tuple[float, float] = (0.15, 0.6)
    object_brightness: tuple[float, float] = (0.75, 1.25)
    object_color_jitter: float = 0.08
    blur_prob: float = 0.3
    blur_sigma: tuple[float, float] = (0.3, 1.5)
    noise_std: tuple[float, float] = (0.0, 0.03)
    jpeg_quality: tuple[int, int] = (60, 95)
    cutout_prob: float = 0.3
    cutouts: tuple[int, int] = (1, 3)
    cutout_size: tuple[float, float] = (0.04, 0.15)
    """Side of a cut-out occluder as a fraction of the image width."""


@dataclass(frozen=True)
class SynthConfig:
    """A whole generation run: camera, scene and randomisation settings, and the recipe's identity."""

    width: int = 640
    height: int = 480
    K: tuple[float, ...] = tuple(LMO_K.ravel().tolist())
    objects: tuple[int, ...] = ()
    seed: int = 0
    scenes: int = 1
    images_per_scene: int = 1
    scene: SceneConfig = field(default_factory=SceneConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(dataclasses.asdict(self), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> SynthConfig:
        return config_from_dict(cls, json.loads(Path(path).read_text()), str(path))
