"""Shared fixtures: the LM-O data beside the clone (../shared/data/lmo), and deterministic torch threads."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from axispose_core.agm.denoiser import DenoiserConfig, EncoderConfig
from axispose_core.agm.model import AGMConfig
from axispose_core.trunks import ResidualGNConfig

REPO = Path(__file__).resolve().parents[1]
LMO_DIR = Path(os.environ.get("AXISPOSE_LMO_DIR", REPO.parent / "shared" / "data" / "lmo"))

torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture(scope="session")
def lmo_dir() -> Path:
    if not (LMO_DIR / "models" / "models_info.json").exists():
        pytest.fail(f"LM-O models not found at {LMO_DIR} (CI keeps ../shared beside the clone; set AXISPOSE_LMO_DIR)")
    return LMO_DIR


@pytest.fixture(scope="session")
def frames(tmp_path_factory, lmo_dir) -> Path:
    """Four rendered frames of objects 1 and 5 (one scene), for the localiser's tests."""
    from axispose_core.data.synth.config import SynthConfig
    from axispose_core.data.synth.generate import generate

    out = tmp_path_factory.mktemp("detdata")
    generate(SynthConfig(seed=33, scenes=1, images_per_scene=4, objects=(1, 5)), lmo_dir / "models", out, progress=False)
    return out


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


TINY_TRUNK = ResidualGNConfig(widths=(8, 8, 8, 8), blocks=(1, 1, 1, 1), groups=4)
TINY_ENCODER = EncoderConfig(trunk=TINY_TRUNK, embed=8, context=16, dense=8, groups=4)
TINY_AGM = AGMConfig(denoiser=DenoiserConfig(channels=8, multipliers=(1, 2), groups=4, encoder=TINY_ENCODER))
"""A small AGM for tests of plumbing, not of accuracy."""
TINY_AGM_YAML = {
    "denoiser": {"size": 64, "channels": 8, "multipliers": [1, 2], "groups": 4,
                 "encoder": {"trunk": {"kind": "residual_gn", "widths": [8, 8, 8, 8], "blocks": [1, 1, 1, 1], "groups": 4},
                             "embed": 8, "context": 16, "dense": 8, "groups": 4}}
}  # fmt: skip


def save_tiny_estimator(path: Path, refine_models: Path | None = None) -> Path:
    """An estimator checkpoint of TINY_AGM, the shipped reader and LM-O's ape (1) and can (5): the node's plumbing;
    with a contour refiner of their meshes from `refine_models` (a BOP models folder) where given."""
    from axispose_core.agm.model import AxisGenerator
    from axispose_core.data.meshes import refiner_meshes
    from axispose_core.estimator import Estimator
    from axispose_core.estimator_checkpoint import EstimatorConfig
    from axispose_core.objects import lmo_objects
    from axispose_core.tbm.reader import SHIPPED_READER, load_reader

    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=1)
    est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
    if refine_models is not None:
        est = est.with_refiner(refiner_meshes(refine_models, [1, 5]))
    est.save(path)
    return path


OFF_ORTHONORMAL = np.array([[0.005, 0.003, 0.0], [0.003, 0.004, 0.002], [0.0, 0.002, 0.005]])
"""R (I + S) with this symmetric S is as far from a rotation as the official LM-O GT: |RR^T - I| 0.0093, det 1.014."""


@pytest.fixture
def official_like():
    """Makes a copy of a BOP scene folder as real data comes: no scene_gt_info.json, no masks, and GT rotations as
    far off orthonormal as the official LM-O annotations."""

    def make(src: Path, dst: Path) -> Path:
        shutil.copytree(src, dst, ignore=shutil.ignore_patterns("mask", "mask_visib", "scene_gt_info.json"))
        gt = json.loads((dst / "scene_gt.json").read_text())
        for insts in gt.values():
            for e in insts:
                e["cam_R_m2c"] = (np.reshape(e["cam_R_m2c"], (3, 3)) @ (np.eye(3) + OFF_ORTHONORMAL)).ravel().tolist()
        (dst / "scene_gt.json").write_text(json.dumps(gt))
        return dst

    return make


def within_a_pixel(mask: np.ndarray) -> np.ndarray:
    """A mask grown by one pixel (3 x 3): the renderer's coverage is exact, so a model point on the silhouette's
    outline rounds to a pixel centre just outside it about half the time."""
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
