"""Multi-hypothesis poses: the consensus of sampled poses, its spread and covariance, and the estimator's K samples."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import TINY_AGM
from scipy.spatial.transform import Rotation

from axispose_core.agm.denoiser import Encoding
from axispose_core.agm.model import AxisGenerator
from axispose_core.axis_image import render_axis_image
from axispose_core.camera import instance_crop, project
from axispose_core.consensus import ROT_FLOOR_RAD, TRANS_FLOOR_M, consensus
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.metrics import re
from axispose_core.objects import lmo_objects
from axispose_core.tbm.dense import DenseFusion
from axispose_core.tbm.reader import SHIPPED_READER, load_reader

FLOOR = np.diag([TRANS_FLOOR_M**2] * 3 + [ROT_FLOOR_RAD**2] * 3)


def _base():
    R = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    return R, np.array([0.05, -0.02, 0.6])


def test_identical_samples_give_themselves_and_the_floor():
    R, t = _base()
    c = consensus(np.stack([R] * 4), np.stack([t] * 4), 0.05)
    np.testing.assert_allclose(c.R, R, atol=1e-12)
    np.testing.assert_allclose(c.t, t, atol=1e-12)
    assert c.spread_deg == pytest.approx(0, abs=1e-6) and c.spread_m == pytest.approx(0, abs=1e-12)
    np.testing.assert_allclose(c.covariance, FLOOR, atol=1e-12)
    assert c.inliers.all()


def test_symmetric_scatter_about_a_camera_axis_has_the_analytic_covariance():
    R, t = _base()
    d = np.radians(4.0)
    Rs = np.stack([Rotation.from_rotvec([s * d, 0, 0]).as_matrix() @ R for s in (1, -1)])  # about the camera's X
    ts = np.stack([t + [0.0, 0.0, 0.01], t - [0.0, 0.0, 0.01]])
    c = consensus(Rs, ts, 0.05)
    assert re(c.R, R) < 1e-6
    np.testing.assert_allclose(c.t, t, atol=1e-12)
    assert c.spread_deg == pytest.approx(4.0, rel=1e-6) and c.spread_m == pytest.approx(0.01, rel=1e-9)
    expected = FLOOR.copy()
    expected[2, 2] += 0.01**2
    expected[3, 3] += d**2
    expected[2, 3] = expected[3, 2] = 0.01 * d  # z and rx move together in this scatter
    np.testing.assert_allclose(c.covariance, expected, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(c.covariance) > 0)


def test_an_outlier_does_not_move_the_consensus_but_widens_the_spread():
    R, t = _base()
    rng = np.random.default_rng(0)
    good = [Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ R for _ in range(5)]
    flipped = Rotation.from_euler("z", 150, degrees=True).as_matrix() @ R
    Rs, ts = np.stack([*good, flipped]), np.stack([t] * 6)
    c = consensus(Rs, ts, 0.05)
    assert c.inliers.tolist() == [True] * 5 + [False]
    np.testing.assert_allclose(c.R, Rotation.from_matrix(np.stack(good)).mean().as_matrix(), atol=1e-12)
    assert re(c.R, R) < 2.0
    clean = consensus(np.stack(good), np.stack([t] * 5), 0.05)
    assert c.spread_deg > 10 * clean.spread_deg
    assert c.medoid != 5


def test_consensus_rejects_malformed_input():
    R, t = _base()
    with pytest.raises(ValueError, match="K >= 1"):
        consensus(np.zeros((0, 3, 3)), np.zeros((0, 3)), 0.05)
    with pytest.raises(ValueError, match="K >= 1"):
        consensus(np.stack([R]), np.stack([t, t]), 0.05)
    with pytest.raises(ValueError, match="positive"):
        consensus(np.stack([R]), np.stack([t]), 0.0)


class _OracleSampler:
    """Draws the axis image of the true pose tilted by a per-sample random rotation of `sigma_deg`.

    A stand-in for sampling a trained AGM whose samples scatter around the truth, so the estimator's batching,
    consensus and covariance can be checked against known poses.
    """

    def __init__(self, K_patch, R, t, lengths, sigma_deg, size):
        self.K_patch, self.R, self.t, self.lengths, self.sigma = K_patch, R, t, lengths, np.radians(sigma_deg)
        self.size = size
        self.batches: list[int] = []

    def __call__(self, agm, enc, steps, eta=0.0, generator=None, guidance=None, cancelled=None, noise_scale=None):
        n = len(enc.context)
        scale = np.ones(n) if noise_scale is None else noise_scale.numpy()  # the prior's mode draws the exact axes
        self.batches.append(n)
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator))
        rng = np.random.default_rng(seed)
        S = self.size
        out = []
        for k in range(n):
            tilt = Rotation.from_rotvec(rng.normal(0, self.sigma, 3) * scale[k]).as_matrix()
            out.append(render_axis_image(self.K_patch, tilt @ self.R, self.t, self.lengths, S))
        return torch.from_numpy(np.stack(out)).permute(0, 3, 1, 2) * 2 - 1


@pytest.fixture(scope="module")
def oracle_setup():
    reader = load_reader(SHIPPED_READER)
    spec = lmo_objects()[0]
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1.0]])
    R, t = _base()
    uv = project(K, t[None])[0]
    r = 0.5 * spec.diameter * K[0, 0] / t[2]
    box = (uv[0] - r, uv[1] - r, 2 * r, 2 * r)
    image = np.zeros((480, 640, 3), np.uint8)
    S = reader.config.size
    K_patch = instance_crop(image, K, box, S, pad=1.25).K_patch
    agm = replace(TINY_AGM, denoiser=replace(TINY_AGM.denoiser, size=S))
    # The oracle draws exact axis images; the untrained encoder's depth and points would only move the TBM's pose.
    cfg = EstimatorConfig(
        agm=agm, reader=reader.config, objects=(spec,), ddim_steps=1, head_depth_weight=0.0, dense_fusion=DenseFusion(points=0)
    )

    def make(sigma_deg: float, drawn: np.ndarray | None = None) -> Estimator:
        """The oracle's estimator; its axis images drawn at rotation `drawn` (default: the true one)."""
        est = Estimator(cfg, AxisGenerator(cfg.agm), reader)
        est.sampler = _OracleSampler(K_patch, R if drawn is None else drawn, t, spec.axes.lengths, sigma_deg, cfg.agm.denoiser.size)
        return est

    return make, image, K, box, spec, R, t


def test_estimator_samples_every_box_k_times_in_one_batch(oracle_setup):
    make, image, K, box, spec, R, _ = oracle_setup
    est = make(3.0)
    (single,) = est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=1))
    assert single.ok and single.covariance is None and np.isnan(single.spread_deg)
    many = est.estimate(image, K, [(spec.obj_id, box), (spec.obj_id, box)], EstimateOptions(hypotheses=8, seed=3))
    assert est.sampler.batches == [1, 16]
    for e in many:
        assert e.ok and e.samples == 8 and e.samples_ok >= 6
        assert re(e.R, R) < 3.0
        assert 0.5 < e.spread_deg < 10.0
        assert e.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(e.covariance) > 0)
    again = est.estimate(image, K, [(spec.obj_id, box), (spec.obj_id, box)], EstimateOptions(hypotheses=8, seed=3))
    np.testing.assert_array_equal(again[0].R, many[0].R)  # deterministic under a seed


def test_first_hypothesis_starts_from_the_priors_mode(oracle_setup):
    make, image, K, box, spec, R, _ = oracle_setup
    est = make(5.0)
    mode = [est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(seed=s))[0] for s in (1, 2)]
    drawn = [est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(seed=s, mode_sample=False))[0] for s in (1, 2)]
    np.testing.assert_allclose(mode[0].R, mode[1].R, atol=1e-9)  # seed-free: the mode, not a draw
    assert re(mode[0].R, R) < 1.0 and min(re(d.R, R) for d in drawn) > 2.0  # the reader's own error is ~0.5 deg
    assert not np.allclose(drawn[0].R, drawn[1].R)
    many = est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=8, seed=1))[0]
    assert many.samples_ok >= 6 and many.spread_deg > 1.0  # the other hypotheses still scatter


def test_wider_sample_scatter_gives_a_wider_spread(oracle_setup):
    make, image, K, box, spec, *_ = oracle_setup
    tight = make(1.0).estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=8, seed=1))[0]
    wide = make(8.0).estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=8, seed=1))[0]
    assert wide.spread_deg > 2 * tight.spread_deg
    assert np.trace(wide.covariance[3:, 3:]) > np.trace(tight.covariance[3:, 3:])


def test_hypotheses_must_be_positive(oracle_setup):
    make, image, K, box, spec, *_ = oracle_setup
    with pytest.raises(ValueError, match="hypotheses"):
        make(1.0).estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=0))


def test_the_encoders_depth_is_reported_and_fused_along_the_tbms_ray(oracle_setup):
    make, image, K, box, spec, *_ = oracle_setup
    tbm = make(0.0)
    (alone,) = tbm.estimate(image, K, [(spec.obj_id, box)])
    assert alone.ok and np.isfinite(alone.head_depth) and alone.head_depth > 0
    encoder = Estimator(replace(tbm.config, head_depth_weight=1.0), tbm.agm, tbm.reader)
    encoder.sampler = tbm.sampler
    (fused,) = encoder.estimate(image, K, [(spec.obj_id, box)])
    assert fused.head_depth == pytest.approx(alone.head_depth)
    np.testing.assert_allclose(fused.t, alone.t * alone.head_depth / alone.t[2])  # the encoder's depth, the TBM's ray


def test_the_dense_fusion_corrects_the_tbms_rotation_and_depth_with_exact_points(oracle_setup):
    """An encoder that sees a flat square (side 1.2 λ_O in the model's z = 0 plane) exactly: its points, mask and
    depth are the truth, while the axis images are drawn 8 degrees off. The TBM's pose keeps the tilt; the dense
    fusion moves it to the truth (the points outweigh the TBM's rotation prior), and points 0 leaves it alone."""
    make, image, K, box, spec, R, t = oracle_setup
    tilted = Rotation.from_rotvec(np.radians(8) * np.array([0.6, 0.8, 0.0])).as_matrix() @ R
    est = make(0.0, drawn=tilted)
    S, lam = est.size, spec.scale
    cut = instance_crop(image, K, box, S, pad=est.config.crop_pad)

    def encode(crops: torch.Tensor, objects: torch.Tensor) -> Encoding:
        cells = np.arange(S // 2) * 2 + 0.5
        uv = np.stack(np.meshgrid(cells, cells), axis=-1).reshape(-1, 2)
        ray = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(cut.K_patch).T
        # the ray's point on the square's plane n . (x - t) = 0, n = R e_z, in model coordinates
        n = R[:, 2]
        X = ((ray * (n @ t / (ray @ n))[:, None]) - t) @ R
        inside = (np.abs(X[:, :2]) < 0.6 * lam).all(axis=1)
        points = torch.from_numpy(X.T.reshape(1, 3, S // 2, S // 2) / lam).float()
        mask = torch.from_numpy(np.where(inside, 10.0, -10.0).reshape(1, 1, S // 2, S // 2)).float()
        f = 0.5 * (cut.K_patch[0, 0] + cut.K_patch[1, 1])
        log_depth = torch.tensor([np.log(t[2] * S / (f * lam))], dtype=torch.float32)
        return Encoding([torch.zeros(1, 1, S // 2, S // 2)], torch.zeros(1, 1), points, mask, log_depth)

    est.agm.encode = encode
    (tbm,) = est.estimate(image, K, [(spec.obj_id, box)])
    assert tbm.ok and re(tbm.R, R) > 6.0
    assert tbm.head_depth == pytest.approx(t[2], rel=1e-5)
    assert tbm.covariance is None  # one sample, no fusion: nothing to say how wrong it is
    est.config = replace(est.config, dense_fusion=DenseFusion())
    (fused,) = est.estimate(image, K, [(spec.obj_id, box)])
    assert re(fused.R, R) < 1.0 and abs(fused.t[2] / t[2] - 1) < 0.002 and np.linalg.norm(fused.t - t) < 0.002
    # one sample has the fusion's covariance; samples that scatter add theirs (the law of total covariance)
    assert fused.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(fused.covariance) > 0)
    (same,) = est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=4))  # the oracle's samples agree
    np.testing.assert_allclose(same.covariance, fused.covariance, rtol=1e-5, atol=1e-15)  # float32 sums in another order
    est.sampler.sigma = np.radians(4.0)
    (scattered,) = est.estimate(image, K, [(spec.obj_id, box)], EstimateOptions(hypotheses=4, seed=2))
    assert scattered.spread_deg > 1.0
    assert np.trace(scattered.covariance[3:, 3:]) > np.trace(fused.covariance[3:, 3:]) + np.radians(1.0) ** 2
