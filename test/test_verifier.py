"""The detection verifier: a detection's pose signals, and a logistic model fitted on them that ranks hits first."""

import numpy as np
import pytest

from axispose_core.localiser.verifier import FEATURES, WORST_VARIANCE, DetectionVerifier, fit, signals


def test_signals_read_the_covariance_blocks_and_count_no_pose_as_the_widest():
    cov = np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.02, 0.03])
    score, var_r, var_t, box_iou = signals(0.7, cov, 0.8)
    assert (score, box_iou) == (0.7, 0.8)
    assert var_r == pytest.approx(0.06) and var_t == pytest.approx(6e-4)
    assert signals(0.7, None, 0.0)[1:3] == (WORST_VARIANCE, WORST_VARIANCE)
    assert signals(0.7, np.full((6, 6), np.nan), 0.0)[1:3] == (WORST_VARIANCE, WORST_VARIANCE)


def _detections(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Hits with higher scores, narrower rotation variance and better boxes than false alarms, overlapping."""
    hits = rng.uniform(size=n) < 0.5
    score = np.clip(rng.normal(np.where(hits, 0.6, 0.4), 0.15), 0.01, 0.99)
    var_r = np.exp(rng.normal(np.where(hits, -5.0, -3.0), 1.0))
    var_t = np.exp(rng.normal(-7.0, 1.0, n))
    box_iou = np.clip(rng.normal(np.where(hits, 0.8, 0.5), 0.15), 0, 1)
    return np.stack([score, var_r, var_t, box_iou], axis=1), hits.astype(int)


def test_fit_ranks_hits_above_false_alarms_better_than_the_score():
    rows, hits = _detections(np.random.default_rng(0), 2000)
    verifier = fit(rows, hits)
    assert len(verifier.weights) == len(FEATURES) + 1
    assert verifier.weights[0] > 0 and verifier.weights[1] > 0 and verifier.weights[3] > 0  # score, -log var_r, IoU
    test_rows, test_hits = _detections(np.random.default_rng(1), 2000)
    p = verifier.probability(test_rows)
    assert p.shape == (2000,) and np.all((p > 0) & (p < 1))

    def auc(x: np.ndarray) -> float:
        return float(np.mean(x[test_hits == 1][:, None] > x[test_hits == 0][None, :]))

    assert auc(p) > auc(test_rows[:, 0]) + 0.05
    assert fit(rows, hits) == verifier  # deterministic


def test_fit_needs_both_hits_and_false_alarms():
    rows, _ = _detections(np.random.default_rng(0), 10)
    with pytest.raises(ValueError, match="both hits and false alarms"):
        fit(rows, np.ones(10))


def test_a_verifier_is_plain_data():
    verifier = DetectionVerifier((1.0, 0.5, 0.0, 2.0, -1.0))
    assert DetectionVerifier(**{"weights": tuple(verifier.weights)}) == verifier
    assert verifier.probability(np.array([0.5, 1e-3, 1e-5, 0.5]))[0] == pytest.approx(1 / (1 + np.exp(-(0.5 * np.log(1e3) + 1.0 - 1.0))))
