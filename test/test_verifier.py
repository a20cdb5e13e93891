"""The detection verifier: a detection's pose signals, the logistic model fitted on them, the estimator's `find` that
rescores with it, its place in the checkpoint, and `axispose fit-verifier`."""

import dataclasses

import numpy as np
import pytest
from conftest import TINY_AGM
from scipy.special import expit

from axispose_core.agm.model import AxisGenerator
from axispose_core.cli import main
from axispose_core.data.bop_scene import bop_frames
from axispose_core.estimator import SHIPPED_ESTIMATOR, EstimateOptions, Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.lmo import LMO_K
from axispose_core.localiser.decode import Detection
from axispose_core.localiser.model import Localiser, LocaliserConfig
from axispose_core.localiser.verifier import FEATURES, WORST_VARIANCE, DetectionVerifier, fit, signals
from axispose_core.objects import lmo_objects
from axispose_core.pose_estimate import Found
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.trunks import ResidualBNConfig


def test_signals_read_the_covariance_blocks_and_count_no_pose_as_the_widest():
    cov = np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.02, 0.03])
    score, var_r, var_t = signals(0.7, cov)
    assert score == 0.7 and var_r == pytest.approx(0.06) and var_t == pytest.approx(6e-4)
    assert signals(0.7, None)[1:] == (WORST_VARIANCE, WORST_VARIANCE)
    assert signals(0.7, np.full((6, 6), np.nan))[1:] == (WORST_VARIANCE, WORST_VARIANCE)


def _detections(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Hits with higher scores and narrower rotation variance than false alarms, overlapping."""
    hits = rng.uniform(size=n) < 0.5
    score = np.clip(rng.normal(np.where(hits, 0.6, 0.4), 0.15), 0.01, 0.99)
    var_r = np.exp(rng.normal(np.where(hits, -5.0, -3.0), 1.0))
    var_t = np.exp(rng.normal(-7.0, 1.0, n))
    return np.stack([score, var_r, var_t], axis=1), hits.astype(int)


def test_fit_ranks_hits_above_false_alarms_better_than_the_score():
    rows, hits = _detections(np.random.default_rng(0), 2000)
    verifier = fit(rows, hits, min_score=0.25)
    assert len(verifier.weights) == len(FEATURES) + 1 and verifier.min_score == 0.25
    assert verifier.weights[0] > 0 and verifier.weights[1] > 0  # score, -log var_r
    test_rows, test_hits = _detections(np.random.default_rng(1), 2000)
    p = verifier.probability(test_rows)
    assert p.shape == (2000,) and np.all((p > 0) & (p < 1))

    def auc(x: np.ndarray) -> float:
        return float(np.mean(x[test_hits == 1][:, None] > x[test_hits == 0][None, :]))

    assert auc(p) > auc(test_rows[:, 0]) + 0.05
    assert fit(rows, hits, min_score=0.25) == verifier  # deterministic


def test_fit_needs_both_hits_and_false_alarms():
    rows, _ = _detections(np.random.default_rng(0), 10)
    with pytest.raises(ValueError, match="both hits and false alarms"):
        fit(rows, np.ones(10))


def test_a_verifier_is_plain_data_and_refuses_a_wrong_one():
    verifier = DetectionVerifier((0.5, 1.0, 0.0, -1.0), min_score=0.2)
    assert DetectionVerifier(**{"weights": tuple(verifier.weights), "min_score": 0.2}) == verifier
    expected = expit(0.5 * np.log(0.5 / 0.5) + np.log(1e3) - 1.0)
    assert verifier.probability(np.array([0.5, 1e-3, 1e-5]))[0] == pytest.approx(expected)
    assert verifier.rescore([0.5], [np.diag([1e-5 / 3] * 3 + [1e-3 / 3] * 3)])[0] == pytest.approx(expected)
    with pytest.raises(ValueError, match="4 finite weights"):
        DetectionVerifier((1.0, 2.0, 3.0, 4.0, 5.0))
    with pytest.raises(ValueError, match="min_score"):
        DetectionVerifier((0.0,) * 4, min_score=0.0)


@pytest.fixture(scope="module")
def localised():
    """The tiny AGM with an untrained localiser of ape (1) and can (5)."""
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(lmo_objects()[:2]), ddim_steps=1)
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    return Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(localiser)


DETECTIONS = [Detection(1, 0.25, (200.0, 200.0), (60.0, 70.0)), Detection(5, 0.5, (400.0, 250.0), (80.0, 90.0)),
              Detection(1, 0.9, (300.0, 300.0), (50.0, 60.0))]  # fmt: skip


def _detect(est: Estimator, monkeypatch) -> list[float]:
    """Make `est.detect` give DETECTIONS (those scoring at least its threshold) and record the thresholds asked for."""
    asked: list[float] = []

    def detect(image, threshold=None):
        asked.append(threshold)
        return [d for d in DETECTIONS if d.score >= threshold]

    monkeypatch.setattr(est, "detect", detect)
    return asked


def test_without_a_verifier_find_poses_the_localisers_detections_above_the_threshold(localised, monkeypatch):
    asked = _detect(localised, monkeypatch)
    image = np.zeros((480, 640, 3), np.uint8)
    found = localised.find(image, LMO_K, 0.3)
    assert asked == [0.3] and found.detections == DETECTIONS[1:] and found.dropped == 0
    assert [p.obj_id for p in found.poses] == [5, 1]
    assert [d.obj_id for d in localised.find(image, LMO_K, 0.3, objects={1}).detections] == [1]


def test_a_verifier_poses_down_to_its_min_score_and_publishes_its_probability(localised, monkeypatch):
    score_only = localised.with_verifier(DetectionVerifier((1.0, 0.0, 0.0, 0.0), min_score=0.2))  # P(hit) = the score
    asked = _detect(score_only, monkeypatch)
    image = np.zeros((480, 640, 3), np.uint8)
    found = score_only.find(image, LMO_K, 0.3)
    assert asked == [0.2] and found.dropped == 1
    assert [d.score for d in found.detections] == pytest.approx([0.5, 0.9]) and [p.obj_id for p in found.poses] == [5, 1]
    monkeypatch.setattr(score_only, "detect", lambda image, threshold=None: [])
    assert score_only.find(image, LMO_K, 0.3) == Found([], [], 0)  # nothing found: nothing posed, nothing dropped
    # The probability of each kept detection is the verifier's of its score and its pose's covariance.
    lifted = localised.with_verifier(DetectionVerifier((0.0, 1.0, 0.0, 0.0), min_score=0.2))
    _detect(lifted, monkeypatch)
    found = lifted.find(image, LMO_K, 0.0)
    assert found.dropped == 0 and len(found.detections) == 3
    for d, original, pose in zip(found.detections, DETECTIONS, found.poses, strict=True):
        expected = lifted.config.verifier.rescore([original.score], [pose.fit_covariance if pose.ok else None])[0]
        assert d.score == pytest.approx(expected) and d.box == original.box


def test_find_each_gives_finds_detections_one_at_a_time_likeliest_first(localised, monkeypatch):
    """`find_each` (the background search): the detections `find` poses, each on its own, the localiser's highest
    score first, kept with the verifier's probability or counted as dropped as `find` does."""
    score_only = localised.with_verifier(DetectionVerifier((1.0, 0.0, 0.0, 0.0), min_score=0.2))  # P(hit) = the score
    asked = _detect(score_only, monkeypatch)
    image = np.zeros((480, 640, 3), np.uint8)
    each = list(score_only.find_each(image, LMO_K, 0.3))
    assert asked == [0.2] and [len(f.detections) + f.dropped for f in each] == [1, 1, 1]
    assert [f.dropped for f in each] == [0, 0, 1]  # 0.9, 0.5 kept; 0.25 below 0.3 dropped
    assert [(d.obj_id, d.score) for f in each for d in f.detections] == [(1, pytest.approx(0.9)), (5, pytest.approx(0.5))]
    assert [p.obj_id for f in each for p in f.poses] == [1, 5]
    assert [d.obj_id for f in score_only.find_each(image, LMO_K, 0.3, objects={5}) for d in f.detections] == [5]


def test_verified_refuses_the_poses_its_verifier_scores_below_the_threshold(localised):
    """`Estimator.verified` (a tracker's new detections, posed on their own): a pose the verifier scores below the
    threshold is refused with its reason; without a verifier, and for a pose already refused, nothing changes."""
    score_only = localised.with_verifier(DetectionVerifier((1.0, 0.0, 0.0, 0.0), min_score=0.2))  # P(hit) = the score
    image = np.zeros((480, 640, 3), np.uint8)
    poses = [dataclasses.replace(p, ok=True) for p in score_only.estimate(image, LMO_K, [(d.obj_id, d.box) for d in DETECTIONS])]
    checked = score_only.verified([d.score for d in DETECTIONS], poses, 0.3)
    assert [p.ok for p in checked] == [False, True, True] and checked[0].reason == "verifier"
    assert localised.verified([0.01], poses[:1], 0.3) == poses[:1]
    refused = dataclasses.replace(poses[0], ok=False, reason="pose")
    assert score_only.verified([0.01], [refused], 0.3)[0].reason == "pose"


def test_the_verifier_reads_the_fusions_own_covariance_alike_at_any_number_of_samples(frames):
    """With one sample the unrefined pose's covariance is the dense fusion's; with several it adds their scatter, and
    refined it is the contour refiner's, both of which the verifier leaves out: the variances it was fitted on (one
    sample, the fusion's) keep their meaning."""
    est = Estimator.load(SHIPPED_ESTIMATOR)
    scene, im_id = bop_frames([frames])[0]
    boxes = [(g.obj_id, info.bbox_obj) for g, info in scene.instances(im_id) if info.visib_fract > 0.5]
    one = [p for p in est.estimate(scene.rgb(im_id), scene.cameras[im_id], boxes, EstimateOptions(steps=1, refine=False)) if p.ok]
    assert one and all(np.array_equal(p.covariance, p.fit_covariance) for p in one)
    refined = [p for p in est.estimate(scene.rgb(im_id), scene.cameras[im_id], boxes, EstimateOptions(steps=1)) if p.ok]
    assert any(p.refined for p in refined)
    assert all(np.array_equal(a.fit_covariance, b.fit_covariance) for a, b in zip(one, refined, strict=True))
    options = EstimateOptions(steps=1, hypotheses=3, refine=False)
    many = [p for p in est.estimate(scene.rgb(im_id), scene.cameras[im_id], boxes, options) if p.ok and p.samples_ok > 1]
    assert many and all(p.fit_covariance is not None for p in many)
    for p in many:  # the total covariance is the fusion's plus a positive semi-definite scatter
        assert np.linalg.eigvalsh(p.covariance - p.fit_covariance).min() > -1e-12


def test_the_verifier_travels_in_the_checkpoint_and_leaves_with_its_localiser(localised, tmp_path):
    verifier = DetectionVerifier((2.5, 1.5, -1.0, 3.4), min_score=0.2)
    path = tmp_path / "v.safetensors"
    localised.with_verifier(verifier).save(path)
    loaded = Estimator.load(path)
    assert loaded.config.verifier == verifier
    assert loaded.with_localiser(loaded.localiser).config.verifier is None  # fitted to that localiser's scores
    bare = EstimatorConfig(agm=TINY_AGM, reader=loaded.config.reader, objects=loaded.config.objects, verifier=verifier)
    with pytest.raises(ValueError, match="no localiser"):
        Estimator(bare, loaded.agm, loaded.reader)


def test_fit_verifier_labels_each_detection_by_the_protocol_and_writes_the_checkpoint(localised, frames, tmp_path, monkeypatch, capsys):
    """Detections at every visible instance's box (hits) and one off in a corner per frame (a false alarm): the fit
    counts them so and the written checkpoint carries a verifier that ranks the hits first."""
    by_image = {}
    for scene, im_id in bop_frames([frames]):
        insts = [(g.obj_id, info.bbox_obj) for g, info in scene.instances(im_id) if info.visib_fract >= 0.1]
        hits = [Detection(o, 0.6, (x + w / 2, y + h / 2), (w, h)) for o, (x, y, w, h) in insts]
        by_image[scene.rgb(im_id).tobytes()] = ([*hits, Detection(1, 0.3, (20.0, 20.0), (30.0, 30.0))], len(hits))
    n_hits = sum(n for _, n in by_image.values())

    def detect(self, image, threshold=None):
        return by_image[image.tobytes()][0]

    monkeypatch.setattr(Estimator, "detect", detect)
    checkpoint, out = tmp_path / "in.safetensors", tmp_path / "out.safetensors"
    localised.save(checkpoint)
    assert main(["fit-verifier", "--checkpoint", str(checkpoint), "--data", str(frames), "--out", str(out), "--steps", "1",
                 "--threads", "1"]) == 0  # fmt: skip
    est = Estimator.load(out)
    record = est.config.training["verifier"]
    assert (record["hits"], record["false_alarms"], record["min_score"]) == (n_hits, len(by_image), 0.2)
    assert est.config.verifier.weights[0] > 0  # the score tells hits (0.6) from the false alarms (0.3)
    assert "wrote" in capsys.readouterr().out


def test_fit_verifier_refuses_what_it_cannot_fit_in_one_line(tmp_path, capsys):
    from conftest import save_tiny_estimator

    bare = save_tiny_estimator(tmp_path / "bare.safetensors")
    assert main(["fit-verifier", "--checkpoint", str(bare), "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert main(["fit-verifier", "--checkpoint", str(bare), "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "no BOP scenes" in err[0] and "no localiser" in err[1]
