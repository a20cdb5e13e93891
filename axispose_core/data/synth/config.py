"""Every knob of the synthetic data generator, saved next to the data it made (synth_config.json)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from axispose_core.config import PRESET, config_from_dict
from axispose_core.lmo import LMO_K

PHOTOS = (
    "astronaut.png", "brick.png", "camera.png", "chelsea.png", "coffee.png", "coins.png", "color.png", "grass.png",
    "gravel.png", "hubble_deep_field.jpg", "ihc.png", "moon.png", "motorcycle_left.png", "motorcycle_right.png",
    "retina.jpg", "rocket.jpg", "text.png",
)  # fmt: skip
"""scikit-image's bundled photographs (not page.png: its ICC profile makes libpng warn on every read)."""
ALL_PHOTOS = (*PHOTOS, "cell.png", "clock_motion.png", "matplotlib:mpl-data/sample_data/grace_hopper.jpg")
"""Every usable photograph of the installed packages: PHOTOS, two more of scikit-image's, matplotlib's portrait
(logo.png is a drawing on an alpha background; the rest of the packages' images are plots and icons)."""
TEXTURES = ("noise", "stripes", "checkers", "gradient")
"""The procedural backgrounds of the frame recipe; `ALL_TEXTURES` adds printed markers and clutter."""
ALL_TEXTURES = (*TEXTURES, "markers", "clutter")
SURFACES = ("wood", "cloth", "paper")
"""Procedural table-top materials (also drawable as backgrounds)."""


TABLE_TEXTURE = 512
"""Side (px) of a table top's texture."""
SPLITS = ("train", "held_out", "all")


def _check_split(split: str) -> None:
    """A distractor-mesh split (`clutter.library`) by name, or a clear error."""
    if split not in SPLITS:
        raise ValueError(f"distractor_split must be one of {SPLITS}, got {split!r}")


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
    distractor_meshes: float = 0.0
    """Share of the distractors that are pybullet_data meshes (`clutter.py`) rather than primitive shapes."""
    distractor_split: str = "train"
    """Which of those meshes: "train" (nine in ten), "held_out" (the tenth, for stress sets) or "all"."""
    lookalike_prob: float = 0.0
    """Share of the distractors coloured in one of the objects' own colours (`clutter.lookalike`): a real
    scene's clutter shares colours with the objects (a blue toy car beside the blue hole punch, a yellow box beside
    the duck), and a localiser that knows an object by its colour fires on them; these make shape tell them apart."""
    table_prob: float = 0.0
    """Share of frames whose objects rest on a textured table top (`table.py`) instead of floating in front of
    the background."""
    table_elevation_deg: tuple[float, float] = (15.0, 75.0)
    """The camera's elevation above the table top."""
    table_size: tuple[float, float] = (0.8, 2.5)
    """Side range (m) of the table top; beyond its edges, the background."""
    table_texel: tuple[float, float] = (0.0008, 0.004)
    """Metres per pixel of its texture (`TABLE_TEXTURE` px, repeated mirrored)."""

    def __post_init__(self) -> None:
        _check_split(self.distractor_split)
        if not 0.0 <= self.lookalike_prob <= 1.0:
            raise ValueError(f"lookalike_prob must lie in [0, 1], got {self.lookalike_prob}")


@dataclass(frozen=True)
class BackgroundConfig:
    """What is behind the objects."""

    photo_background_prob: float = 0.6
    photos: tuple[str, ...] = PHOTOS
    """Background photographs by file name (randomize.py: scikit-image's, or 'package:path')."""
    photo_scale: tuple[float, float] = (0.4, 1.0)
    """Side of the photograph's random crop, as a fraction of its height."""
    textures: tuple[str, ...] = TEXTURES
    """Procedural backgrounds to draw from: noise, stripes, checkers, gradient, markers, clutter, wood, cloth, paper."""


TABLE_TOP = BackgroundConfig(photo_background_prob=0.25, textures=(*SURFACES, "markers"))
"""Table tops: wood, cloth, paper, printed markers; a quarter of them a photograph."""


@dataclass(frozen=True)
class LightConfig:
    """The light and the objects' materials."""

    light_intensity: tuple[float, float] = (0.6, 1.4)
    light_color_jitter: float = 0.15
    ambient: tuple[float, float] = (0.15, 0.6)
    specular: tuple[float, float] = (0.0, 0.0)
    """Strength of the Blinn-Phong highlight (0, 0: matte, and no number drawn)."""
    shininess: tuple[float, float] = (5.0, 60.0)
    object_brightness: tuple[float, float] = (0.75, 1.25)
    object_color_jitter: float = 0.08
    texture_prob: float = 0.0
    """Share of objects drawn in a wrong surface (`randomize.wrong_texture`: their own colours shuffled over the
    vertices, smooth colour bands, or one flat colour) instead of their scanned one: a real surface never looks
    quite like its scan, and a network that reads the shape stays right when the surface misleads."""
    shadows: float = 0.0
    """Share of frames whose light casts shadows, on the objects and the table (`raster.ShadowMap`)."""


@dataclass(frozen=True)
class SensorConfig:
    """The camera between the scene and the pixels, in the order `randomize.camera_effects` applies it; a knob at
    0 draws no random number."""

    blur_prob: float = 0.3
    blur_sigma: tuple[float, float] = (0.3, 1.5)
    chromatic: float = 0.0
    """Largest lateral chromatic aberration: red and blue magnified by ±δ about the frame's centre, |δ| up to this
    (0.002 shifts them 0.8 px at a VGA frame's corners)."""
    vignetting: tuple[float, float] = (0.0, 0.0)
    """Range of the light lost at the frame's corners (falling off with the squared distance from its centre)."""
    motion_blur_prob: float = 0.0
    motion_blur_px: tuple[float, float] = (2.0, 8.0)
    white_balance: float = 0.0
    """Per-channel gain jitter (std) of the camera's white balance."""
    contrast: float = 0.0
    """Contrast and saturation jitter (std of the gains about 1)."""
    gamma: tuple[float, float] = (0.0, 0.0)
    """Exponent range of the camera's tone curve (0, 0: linear)."""
    dynamic_range: tuple[float, float] = (0.0, 0.0)
    """Range of the share of [0, 1] a low-dynamic-range sensor loses, split at random between crushed shadows and
    clipped highlights."""
    noise_std: tuple[float, float] = (0.0, 0.03)
    noise_shot: float = 0.0
    """Extra noise in the dark: std x (1 + noise_shot x (1 - brightness))."""
    jpeg_quality: tuple[int, int] = (60, 95)
    """Applied when the image is saved (frames) or encoded in memory (crops)."""


@dataclass(frozen=True)
class PhotometricConfig:
    """Photometric augmentation of a finished image (`appearance.photometric`), at the strength of the methods
    that train on renders alone and read real LM-O frames (GDRNPP's LM-O chain, imgaug's and PIL's semantics): with
    probability `prob` the ops below run in random order, each with its own probability; `prob` 0 (the default)
    draws no random number. Factors are PIL ImageEnhance's (1: unchanged); additive terms in 8-bit levels. Camera
    processing follows: a Bayer mosaic demosaiced back (colour fringes on edges) and an unsharp mask (a camera's
    sharpening halos)."""

    prob: float = 0.0
    dropout: tuple[float, float, float] = (0.5, 0.2, 0.05)
    """(probability, share of cells set to black, cell side as a fraction of the image side): coarse dropout."""
    blur: tuple[float, float, float] = (0.4, 0.0, 3.0)
    """(probability, sigma range in px of the image)."""
    sharpness: tuple[float, float, float] = (0.3, 0.0, 50.0)
    contrast: tuple[float, float, float] = (0.3, 0.2, 50.0)
    brightness: tuple[float, float, float] = (0.5, 0.1, 6.0)
    color: tuple[float, float, float] = (0.3, 0.0, 20.0)
    add: tuple[float, float, float] = (0.5, 25.0, 0.3)
    """(probability, largest offset in levels, share of draws with one offset per channel)."""
    invert: tuple[float, float] = (0.3, 0.2)
    """(probability, chance each channel is inverted)."""
    multiply_channels: tuple[float, float, float, float] = (0.5, 0.6, 1.4, 0.5)
    """(probability, gain range, share of draws with one gain per channel)."""
    multiply: tuple[float, float, float] = (0.5, 0.6, 1.4)
    noise: tuple[float, float] = (0.1, 10.0)
    """(probability, per-channel Gaussian noise std in levels)."""
    linear_contrast: tuple[float, float, float, float] = (0.5, 0.5, 2.2, 0.3)
    """(probability, gain range about 128 levels, share of draws per channel)."""
    grayscale: float = 0.5
    """Probability of blending toward grey by a uniform alpha."""
    demosaic: float = 0.0
    """Probability of a Bayer mosaic demosaiced back (after the chain, whether or not it ran)."""
    sharpen: tuple[float, float, float] = (0.0, 0.3, 1.5)
    """(probability, amount range) of an unsharp mask of sigma 1 px."""


@dataclass(frozen=True)
class SurfaceConfig:
    """The object's own look beyond its vertex colours (`appearance.surface`), on the target's pixels only: a real
    surface has fine detail (print, grain, dirt) and a camera's colour response bends its colours; 0 draws nothing."""

    detail_prob: float = 0.0
    detail_std: tuple[float, float] = (0.05, 0.25)
    """Range of the std of a multiplicative texture at 1-3 px scale."""
    response_prob: float = 0.0
    response_gamma: tuple[float, float] = (0.6, 1.6)
    """Per-channel exponent range of the colour response on the object."""


@dataclass(frozen=True)
class RandomizationConfig:
    """Domain randomisation of appearance, by what it varies."""

    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    table_top: BackgroundConfig = field(default_factory=lambda: TABLE_TOP, metadata=PRESET)
    """The texture of a table top (`SceneConfig.table_prob`)."""
    light: LightConfig = field(default_factory=LightConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    cutout_prob: float = 0.3
    """Share of frames with flat-coloured rectangles pasted over them (`randomize.cutouts`)."""
    cutouts: tuple[int, int] = (1, 3)
    cutout_size: tuple[float, float] = (0.04, 0.15)
    """Side of a cut-out occluder as a fraction of the image width."""
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)


@dataclass(frozen=True)
class CameraPathConfig:
    """A scene filmed as a sequence: the camera orbits the objects' centre (about the table's normal; without a
    table, about the camera's vertical), sweeps its view to and fro, and shakes as a hand-held one does, so
    consecutive images share one world, seen a little differently; objects leave the view and come back, occluders
    cross it. Lighting stays with the camera; the background photograph is far away."""

    orbit_deg: float = 1.0
    """Orbit per image (degrees)."""
    shake_deg: float = 0.3
    """Standard deviation per image of the random walk of the camera's orientation (degrees)."""
    shake_m: float = 0.002
    """Standard deviation per image of the random walk of the camera's position (m)."""
    sweep_deg: float = 0.0
    """Amplitude of a pan (and half as much tilt) of the camera about its own centre (degrees): objects leave the
    view and come back."""
    sweep_frames: float = 150.0
    """Images per sweep cycle (the tilt's is 1.6 times as long)."""
    shutter: float = 0.0
    """Fraction of the interval between images the shutter is open: each image is smeared along the motion of the
    objects' centre in it since the one before (0: no motion blur)."""
    gain_walk: float = 0.0
    """Standard deviation per image of the random walk of the exposure's log gain (held within ±0.4)."""
    passers: int = 0
    """Occluders that cross the view once each, between the camera and the objects, at a random time."""
    pass_frames: int = 60
    """Images an occluder takes to cross the view."""


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
    depth: bool = False
    """Also write BOP depth images of the objects (depth/, DEPTH_SCALE), for BOP's VSD error."""
    camera_path: CameraPathConfig | None = None
    """Each scene as one world filmed along a camera path (tracking's test video); None: every image its own world."""

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(dataclasses.asdict(self), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> SynthConfig:
        return config_from_dict(cls, json.loads(Path(path).read_text()), str(path))


STREAM_RANDOMIZATION = RandomizationConfig(
    background=BackgroundConfig(photo_background_prob=0.5, photos=ALL_PHOTOS, textures=ALL_TEXTURES),
    light=LightConfig(specular=(0.0, 0.5)),
    sensor=SensorConfig(
        blur_sigma=(0.3, 1.2),
        noise_std=(0.0, 0.04),
        noise_shot=1.0,
        motion_blur_prob=0.15,
        motion_blur_px=(2.0, 7.0),
        white_balance=0.06,
        gamma=(0.8, 1.25),
        contrast=0.12,
        jpeg_quality=(50, 95),
    ),
    cutout_prob=0.0,
)
"""The crop stream's appearance: every photograph and texture, highlights, and the whole camera model on."""


HELD_OUT_PHOTOS = tuple(p for p in ALL_PHOTOS if p not in PHOTOS)
"""The photographs the frame recipes leave out of training, for stress sets."""
RECIPES = ("plain", "desk", "desk-held-out")


def recipe(name: str) -> tuple[SceneConfig, RandomizationConfig]:
    """A named frame recipe's scene and randomisation. "plain": the defaults, objects floating in front of a
    photograph or pattern (the shipped localiser's data); "desk": objects on a table top among pybullet_data
    meshes, shadows, highlights and the whole camera model, lens and sensor; "desk-held-out": the desk with only
    the distractor meshes and photographs the desk leaves out, for stress sets."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; one of {RECIPES}")
    if name == "plain":
        return SceneConfig(), RandomizationConfig()
    held_out = name == "desk-held-out"
    photos = HELD_OUT_PHOTOS if held_out else PHOTOS
    split = "held_out" if held_out else "train"
    scene = SceneConfig(distractors_per_image=(2, 6), table_prob=0.8, distractor_meshes=0.7, distractor_split=split)
    sensor = dataclasses.replace(STREAM_RANDOMIZATION.sensor, chromatic=0.002, vignetting=(0.0, 0.4), dynamic_range=(0.0, 0.15))
    randomization = RandomizationConfig(
        background=BackgroundConfig(photos=photos, textures=ALL_TEXTURES),
        table_top=dataclasses.replace(TABLE_TOP, photos=photos),
        light=LightConfig(specular=(0.0, 0.5), shadows=0.8),
        sensor=sensor,
    )
    return scene, randomization


@dataclass(frozen=True)
class Framing:
    """Where the crop sits on the object: the estimator's square around the amodal box (`pad`), shifted and
    scaled as the shipped localiser's crops are, by visibility band (edges `visib_edges`). Measured on 600
    held-out frames (`bench/localiser_framing.py`, bench/results/localiser_framing.json): the centre error per
    axis in crop sides and the log side ratio are drawn as Student-t of `dof` degrees of freedom (the measured
    tails are about twice a Gaussian's) with the measured medians and robust (1.4826 MAD) spreads."""

    pad: float = 1.25
    visib_edges: tuple[float, ...] = (0.5, 0.8)
    centre_std: tuple[float, ...] = (0.0719, 0.0410, 0.0145)
    scale_median: tuple[float, ...] = (-0.0602, -0.0290, -0.0069)
    scale_std: tuple[float, ...] = (0.1281, 0.0958, 0.0514)
    dof: float = 3.0


@dataclass(frozen=True)
class StreamConfig:
    """The crop stream (`data/synth/stream.py`): object crops rendered at their own resolution, sample i from
    (seed, i). The frame the crops are cut from is `width` x `height` through `K`; poses cover the LM-O range."""

    size: int = 64
    objects: tuple[int, ...] = ()
    seed: int = 0
    width: int = 640
    height: int = 480
    K: tuple[float, ...] = tuple(LMO_K.ravel().tolist())
    distance: tuple[float, float] = (0.35, 1.5)
    margin: float = 0.05
    """The object origin projects inside the frame less this fraction of its size on each side."""
    upright_prob: float = 0.5
    elevation_deg: tuple[float, float] = (-14.0, 89.0)
    camera_roll_deg: tuple[float, float] = (-30.0, 30.0)
    visib: tuple[float, float] = (0.1, 1.0)
    """Range of the target's visible fraction (visible / silhouette pixels in the crop); every sample meets it."""
    occluded_prob: float = 0.7
    """Share of samples with an occluder over the target, visible fraction uniform in `visib` (the rest: 1)."""
    clutter_prob: float = 0.5
    """Share of the unoccluded samples with an object in front beside the target."""
    neighbours: tuple[int, int] = (0, 2)
    """Objects behind the target, partly in the crop."""
    object_prob: float = 0.6
    """An occluder or neighbour is another object of the set with this probability, else a primitive."""
    primitive_size: tuple[float, float] = (0.03, 0.15)
    """Diameter range (m) of the primitive neighbours."""
    distractor_meshes: float = 0.0
    """Share of the primitives that are pybullet_data meshes instead (`clutter.py`, as the frame recipes' distractors)."""
    distractor_split: str = "train"
    mesh_cell: float = 2.0
    """Meshes are decimated to about this many crop pixels per cell at each object's apparent size (three levels
    of detail, `stream.LODS`; 0: full meshes)."""
    framing: Framing = field(default_factory=Framing)
    randomization: RandomizationConfig = field(default_factory=lambda: STREAM_RANDOMIZATION, metadata=PRESET)

    def __post_init__(self) -> None:
        if not (isinstance(self.size, int) and self.size % 16 == 0 and 32 <= self.size <= 512):
            raise ValueError(f"crop size must be a multiple of 16 from 32 to 512 (the networks halve it four times), got {self.size}")
        _check_split(self.distractor_split)
        lo, hi = self.visib
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(f"visib range must satisfy 0 < lo <= hi <= 1, got {self.visib}")
        if len(self.framing.centre_std) != len(self.framing.visib_edges) + 1:
            raise ValueError("framing: one centre_std, scale_median and scale_std per visibility band")
