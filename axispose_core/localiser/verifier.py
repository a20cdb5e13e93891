"""A second opinion on a detection from the pose the estimator finds for it. On real frames the localiser takes clutter
in an object's colours for the object; the AGM's crop of such clutter does not fit the object's model, and the dense
fusion says so with a wide covariance (its own, without the samples' scatter: alike at any number of samples). A
logistic model of the localiser's score and the pose's variances (`FEATURES`), fitted on rendered frames only
(`axispose fit-verifier`), ranks detections better than the score alone (docs/BENCHMARKS.md, "The pose as a second
opinion"); the estimator publishes its probability as the score.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.special import expit

FEATURES = ("score", "rotation_variance", "translation_variance")
"""Per detection: the localiser's score and the traces of the pose covariance's rotation (rad²) and translation (m²)
blocks."""
WORST_VARIANCE = 1e3
"""The variance of a detection without a pose or a covariance: wider than any posed one."""


@dataclass(frozen=True)
class DetectionVerifier:
    """A fitted logistic model over `FEATURES` (`weights`: one per feature, then a constant), and the least localiser
    score of a detection it is asked about: lower than the published threshold, so that a good pose can lift a
    detection the score alone would drop, and high enough that the AGM poses few detections per frame."""

    weights: tuple[float, ...]
    min_score: float = 0.2

    def __post_init__(self) -> None:
        if len(self.weights) != len(FEATURES) + 1 or not all(math.isfinite(w) for w in self.weights):
            raise ValueError(f"a verifier has {len(FEATURES) + 1} finite weights ({', '.join(FEATURES)}, constant), got {self.weights}")
        if not 0.0 < self.min_score < 1.0:
            raise ValueError(f"min_score must lie in (0, 1), got {self.min_score}")

    def probability(self, rows: np.ndarray) -> np.ndarray:
        """P(hit) per row of `FEATURES`."""
        return expit(design(rows) @ np.asarray(self.weights))

    def rescore(self, scores: Sequence[float], covariances: Sequence[np.ndarray | None]) -> np.ndarray:
        """P(hit) of detections with these localiser scores and their poses' dense-fusion covariances
        (`PoseEstimate.fit_covariance`; None: no pose)."""
        return self.probability(np.array([signals(s, c) for s, c in zip(scores, covariances, strict=True)], float))


def _variance(block: np.ndarray) -> float:
    v = float(np.trace(block))
    return v if np.isfinite(v) and v > 0 else WORST_VARIANCE


def signals(score: float, covariance: np.ndarray | None) -> tuple[float, float, float]:
    """One detection's row of `FEATURES` from its (6, 6) pose covariance (x, y, z, rx, ry, rz); none (no pose) counts
    as the widest."""
    if covariance is None:
        return (score, WORST_VARIANCE, WORST_VARIANCE)
    return (score, _variance(covariance[3:, 3:]), _variance(covariance[:3, :3]))


def design(rows: np.ndarray) -> np.ndarray:
    """The model's inputs: the score's logit, the variances' negative logs and a constant: scales on which hits and
    false alarms differ about linearly."""
    rows = np.asarray(rows, float).reshape(-1, len(FEATURES))
    score = np.clip(rows[:, 0], 1e-4, 1 - 1e-4)
    columns = [np.log(score / (1 - score)), -np.log(rows[:, 1]), -np.log(rows[:, 2]), np.ones(len(rows))]
    return np.stack(columns, axis=1)


def fit(rows: np.ndarray, hits: np.ndarray, min_score: float = 0.2, ridge: float = 1e-3) -> DetectionVerifier:
    """The lightly regularised logistic regression of `hits` (1 hit, 0 false alarm) on `rows` of detections scored
    at least `min_score`."""
    X, y = design(rows), np.asarray(hits, float)
    if len(y) == 0 or y.min() == y.max():
        raise ValueError("fitting a verifier needs both hits and false alarms")

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = X @ w
        return float(np.sum(np.logaddexp(0, z) - y * z) + ridge * w @ w), X.T @ (expit(z) - y) + 2 * ridge * w

    weights = minimize(loss, np.zeros(X.shape[1]), jac=True, method="BFGS").x
    return DetectionVerifier(tuple(float(w) for w in weights), min_score)
