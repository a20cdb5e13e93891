"""`axispose fit-verifier`: the detection verifier (`localiser/verifier.py`) fitted on synthetic BOP frames. Every
detection of the checkpoint's localiser down to `min_score` is posed as the node poses it (float32, its DDIM steps,
one sample); the detection protocol (`scoring.detection_outcomes`) says which found an instance, and a logistic
model of hit against false alarm is fitted on them. Rendered frames only: the real frames validate it.
"""

from __future__ import annotations

import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from axispose_core.data.bop_scene import bop_frames
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.scoring import detection_outcomes, frame_instances
from axispose_core.localiser.verifier import FEATURES, DetectionVerifier, fit, signals


@dataclass(frozen=True)
class VerifierFitConfig:
    min_score: float = 0.2
    """Detections down to this localiser score are posed, in fitting and at run time."""
    steps: int = 3
    """DDIM steps per pose: the node's default (config/axispose.yaml)."""
    min_visib: float = 0.1
    """A detection of an instance at least this visible is a hit (the protocol of `axispose validate`)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.min_score < 1.0 or self.steps < 1:
            raise ValueError(f"min_score must lie in (0, 1) and steps be >= 1, got {self.min_score} and {self.steps}")


def verifier_rows(
    est: Estimator, data: list[str | Path], config: VerifierFitConfig, progress: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """One row of `FEATURES` per detection of the frames in `data`, and its outcome (1 hit, 0 false alarm, -1
    neither)."""
    ids = tuple(o.obj_id for o in est.config.objects)
    rows: list[np.ndarray] = [np.zeros((0, len(FEATURES)))]
    outcomes: list[int] = []
    for scene, im_id in tqdm(bop_frames(data), desc="verifier", disable=not progress):
        rgb, K = scene.rgb(im_id), scene.cameras[im_id]
        dets = est.detect(rgb, config.min_score)
        rows.append(pose_signals(est, rgb, K, dets, config.steps))
        outcomes += detection_outcomes(dets, frame_instances(scene, im_id, ids), config.min_visib)
    return np.concatenate(rows), np.array(outcomes, int)


def pose_signals(est: Estimator, rgb: np.ndarray, K: np.ndarray, dets: list[Detection], steps: int) -> np.ndarray:
    """(n, len(FEATURES)) rows of a frame's detections, each posed as the node poses it (one sample, `steps`)."""
    poses = est.estimate(rgb, K, [(d.obj_id, d.box) for d in dets], EstimateOptions(steps=steps))
    rows = [signals(d.score, p.fit_covariance if p.ok else None) for d, p in zip(dets, poses, strict=True)]
    return np.array(rows, float).reshape(-1, len(FEATURES))


def fit_verifier(
    est: Estimator, data: list[str | Path], config: VerifierFitConfig = VerifierFitConfig(), progress: bool = False
) -> tuple[DetectionVerifier, dict]:
    """The verifier of `est`'s localiser fitted on `data`, and the record of the fit (data, counts, time, host)."""
    if est.localiser is None:
        raise ValueError("the verifier rescores the localiser's detections: this checkpoint has no localiser")
    if est.config.dense_fusion.points <= 0:
        raise ValueError("the verifier reads the dense fusion's pose covariance: this checkpoint has dense_fusion.points 0")
    before = "bfloat16" if est.bf16 else "float32"
    est.set_precision("float32")  # the robot's arithmetic, as `axispose validate`
    start = time.perf_counter()
    try:
        rows, outcomes = verifier_rows(est, data, config, progress)
    finally:
        est.set_precision(before)
    counted = outcomes >= 0
    verifier = fit(rows[counted], outcomes[counted], config.min_score)
    record = {"data": [str(d) for d in data], **asdict(config), "detections": int(counted.sum()), "hits": int((outcomes == 1).sum()),
              "false_alarms": int((outcomes == 0).sum()), "seconds": time.perf_counter() - start,
              "host": platform.processor() or platform.machine()}  # fmt: skip
    return verifier, record
