from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.axis_image import axis_keypoints
from axispose_core.lmo import LMO_K
from axispose_core.metrics import re, te
from axispose_core.pose_sampling import sample_pose
from axispose_core.tbm.backproject import backproject, backproject_many, nearest_rotation, refine_poses, rotation_from_slopes


def _random_corner(rng):
    R, t = sample_pose(rng)
    lengths = rng.uniform(0.02, 0.15) * np.array([1.0, rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0)])
    return R, t, lengths, axis_keypoints(LMO_K, R, t, lengths)


def test_exact_keypoints_give_exact_pose_over_1000_random_poses(rng):
    rot, trans = [], []
    for _ in range(1000):
        R, t, lengths, kp = _random_corner(rng)
        res = backproject(LMO_K, kp[0], kp[1:], lengths)
        assert res.ok, res.reason
        rot.append(re(res.R, R))
        trans.append(te(res.t, t))
    assert max(rot) < 1e-6, max(rot)
    assert max(trans) < 1e-6, max(trans)


def test_result_is_a_proper_rotation(rng):
    _, _, lengths, kp = _random_corner(rng)
    res = backproject(LMO_K, kp[0], kp[1:] + rng.normal(0, 1.0, (3, 2)), lengths)
    assert res.ok
    np.testing.assert_allclose(res.R @ res.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(res.R) == pytest.approx(1.0)


def test_rotation_from_slopes_is_exact(rng):
    for _ in range(200):
        R, t, _, kp = _random_corner(rng)
        res = rotation_from_slopes(LMO_K, kp[0], (kp[1:] - kp[0]) * rng.uniform(0.1, 3.0, (3, 1)))
        assert res.ok, res.reason
        assert re(res.R, R) < 1e-6
        np.testing.assert_allclose(res.t / res.t[2], t / t[2], atol=1e-9)  # the origin's ray


def test_noisy_keypoints_refinement_helps(rng):
    """1 px Gaussian keypoint noise: the numbers for docs/BENCHMARKS.md come from bench/solver_noise.py."""
    plain, refined = [], []
    for _ in range(200):
        R, _, lengths, kp = _random_corner(rng)
        noisy = kp + rng.normal(0, 1.0, kp.shape)
        a = backproject(LMO_K, noisy[0], noisy[1:], lengths)
        b = backproject(LMO_K, noisy[0], noisy[1:], lengths, refine=True)
        plain.append(re(a.R, R) if a.ok else 180.0)
        refined.append(re(b.R, R) if b.ok else 180.0)
    print(f"median rotation error at 1 px noise: analytic {np.median(plain):.2f} deg, refined {np.median(refined):.2f} deg")
    assert np.median(refined) < np.median(plain)
    assert np.median(refined) < 10.0


def test_refinement_from_a_perturbed_pose_converges_to_the_exact_one(rng):
    """The vectorised Levenberg-Marquardt fit: 50 exact corners, each started 10 degrees and 2 cm off."""
    from scipy.spatial.transform import Rotation

    corners = [_random_corner(rng) for _ in range(50)]
    R0 = np.stack([Rotation.from_rotvec(rng.normal(size=3) * np.radians(10) / np.sqrt(3)).as_matrix() @ c[0] for c in corners])
    t0 = np.stack([c[1] + rng.normal(0, 0.02 / np.sqrt(3), 3) for c in corners])
    K = np.repeat(LMO_K[None], 50, axis=0)
    R, t = refine_poses(K, np.stack([c[3] for c in corners]), np.stack([c[2] for c in corners]), R0, t0)
    assert max(re(Ri, c[0]) for Ri, c in zip(R, corners, strict=True)) < 1e-5
    assert max(te(ti, c[1]) for ti, c in zip(t, corners, strict=True)) < 1e-6


def test_many_at_once_equals_one_at_a_time(rng):
    """backproject_many (one vectorised refinement) gives what backproject gives each item, refusals included."""
    items = []
    for _ in range(30):
        _, _, lengths, kp = _random_corner(rng)
        items.append((kp + rng.normal(0, 2.0, kp.shape), lengths))
    items[7] = (np.array([[300.0, 200], [300, 200], [350, 210], [310, 260]]), items[7][1])  # an axis at the camera
    many = backproject_many(
        np.repeat(LMO_K[None], 30, axis=0), np.stack([i[0] for i in items]), np.stack([i[1] for i in items]), refine=True
    )
    for (kp, lengths), got in zip(items, many, strict=True):
        one = backproject(LMO_K, kp[0], kp[1:], lengths, refine=True)
        assert got.ok == one.ok and got.reason == one.reason
        if one.ok:
            assert re(got.R, one.R) < 1e-6 and te(got.t, one.t) < 1e-8
    assert not many[7].ok and "points at the camera" in many[7].reason


def test_readings_are_back_projected_where_readable(rng):
    from axispose_core.tbm.backproject import backproject_readings
    from axispose_core.tbm.keypoints import AxisKeypoints, unreadable

    _, _, lengths, kp = _random_corner(rng)
    readings = [AxisKeypoints(kp[0], kp[1:]), unreadable("blank image"), AxisKeypoints(kp[0], kp[1:])]
    out = backproject_readings(np.repeat(LMO_K[None], 3, axis=0), readings, np.repeat(lengths[None], 3, axis=0))
    assert out[1] is None and out[0].ok and out[2].ok
    assert backproject_readings(LMO_K[None], [unreadable("blank image")], lengths[None]) == [None]


def _assert_refused(res, reason):
    assert not res.ok
    assert reason in res.reason
    assert np.all(np.isfinite(res.R)) and np.all(np.isfinite(res.t))


def test_collinear_axes_are_refused():
    o = np.array([320.0, 240.0])
    axes = np.array([[360.0, 240.0], [280.0, 240.0], [320.0, 280.0]])
    _assert_refused(backproject(LMO_K, o, axes, np.full(3, 0.05)), "collinear")
    _assert_refused(rotation_from_slopes(LMO_K, o, axes - o), "collinear")


def test_axis_pointing_at_camera_is_refused():
    o = np.array([320.0, 240.0])
    axes = np.array([[360.0, 240.0], [320.0, 280.0], [320.0, 240.0]])
    _assert_refused(backproject(LMO_K, o, axes, np.full(3, 0.05)), "points at the camera")


def test_nan_keypoints_and_bad_intrinsics_are_refused():
    o = np.array([320.0, 240.0])
    axes = np.array([[360.0, 240.0], [320.0, 280.0], [300.0, 220.0]])
    _assert_refused(backproject(LMO_K, [np.nan, 1.0], axes, np.full(3, 0.05)), "non-finite")
    _assert_refused(backproject(np.zeros((3, 3)), o, axes, np.full(3, 0.05)), "invalid intrinsics")
    _assert_refused(backproject(LMO_K, o, axes, np.array([0.05, -1.0, 0.05])), "lengths")


def test_corner_with_a_vertex_behind_the_camera_is_refused():
    # An axis 0.5 m long reaching from 0.3 m in front of the camera to 0.2 m behind it: its endpoint's pixel
    # is the mirror image of the true direction, and no physical corner explains the four points.
    x = np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])
    y = np.cross(x, [0.0, 1.0, 0.0])
    y /= np.linalg.norm(y)
    R = np.column_stack([x, y, np.cross(x, y)])
    t = np.array([0.05, 0.02, 0.3])
    lengths = np.array([0.5, 0.05, 0.05])
    pts = np.diag(lengths)
    cam = pts @ R.T + t
    assert (cam[:, 2] < 0).any()
    uvw = np.vstack([t, cam]) @ LMO_K.T
    kp = uvw[:, :2] / uvw[:, 2:3]
    res = backproject(LMO_K, kp[0], kp[1:], lengths)
    if res.ok:  # a corner may exist that explains the pixels; it must then not be the impossible true one
        assert re(res.R, R) > 1.0
    else:
        assert "front of the camera" in res.reason or "real solution" in res.reason


def test_nearest_rotation_projects_onto_so3(rng):
    M = rng.normal(size=(3, 3))
    R = nearest_rotation(M)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def _exact_points(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A pose (R, t) 0.8 m away, 300 model points X in a 10 cm cube and their exact projections uv."""
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    t = np.array([0.05, -0.03, 0.8])
    X = rng.uniform(-0.05, 0.05, (300, 3))
    cam = X @ R.T + t
    return R, t, X, (cam @ LMO_K.T)[:, :2] / cam[:, 2:]


def test_translation_from_dense_points_is_exact_and_robust():
    """Model points seen at their exact projections give the true t; a fifth of them moved far off do not pull it
    (Huber IRLS); too few points, or none weighted, give None."""
    from axispose_core.tbm.dense import translation_from_points

    rng = np.random.default_rng(3)
    R, t, X, uv = _exact_points(rng)
    np.testing.assert_allclose(translation_from_points(LMO_K, R, uv, X, np.ones(300)), t, atol=1e-9)
    bad = uv.copy()
    bad[:60] += rng.uniform(20, 40, (60, 2))
    assert abs(translation_from_points(LMO_K, R, bad + rng.normal(0, 0.3, bad.shape), X, np.ones(300))[2] / t[2] - 1) < 0.005
    assert translation_from_points(LMO_K, R, uv[:5], X[:5], np.ones(5)) is None
    assert translation_from_points(LMO_K, R, uv, X, np.zeros(300)) is None


def test_the_dense_fusion_weighs_points_against_its_priors():
    """Exact points and priors at the truth give the true pose from a start 10 degrees and 5 % off; priors off the
    truth (rotation, depth, the origin's projection) give way to many points and hold against few; a fifth of the
    points moved far off do not pull it (IRLS); too few points, or a start behind the camera, give None."""
    from axispose_core.tbm.dense import DenseFusion, DensePoints, fuse_pose

    rng = np.random.default_rng(4)
    R, t, X, uv = _exact_points(rng)
    off = Rotation.from_rotvec(np.radians(10) * np.array([0.6, -0.8, 0.0])).as_matrix() @ R

    def angle(A: np.ndarray, B: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))

    fusion = DenseFusion(points=10, rotation_sigma=0.1, depth_sigma=0.02)
    R1, t1, _ = fuse_pose(LMO_K, R, 1.05 * t, DensePoints(uv, X, np.ones(300)), t[2], fusion)  # the start is off, the priors are not
    np.testing.assert_allclose(R1, R, atol=1e-8)
    np.testing.assert_allclose(t1, t, atol=1e-8)
    many = fuse_pose(LMO_K, off, 1.05 * t, DensePoints(uv, X, np.ones(300)), 1.05 * t[2], DenseFusion(points=1e6))
    few = fuse_pose(LMO_K, off, 1.05 * t, DensePoints(uv, X, np.ones(300)), 1.05 * t[2], DenseFusion(points=1e-4))
    assert angle(many[0], R) < 0.05 and abs(many[1][2] / t[2] - 1) < 1e-3
    assert angle(few[0], off) < 0.05 and abs(few[1][2] / t[2] - 1.05) < 1e-3
    # the origin's prior: a start 1 cm to the side stays there against few points and gives way to many
    side = t + np.array([0.01, 0.0, 0.0])
    few = fuse_pose(LMO_K, R, side, DensePoints(uv, X, np.ones(300)), t[2], DenseFusion(points=1e-4))
    many = fuse_pose(LMO_K, R, side, DensePoints(uv, X, np.ones(300)), t[2], DenseFusion(points=1e6))
    np.testing.assert_allclose(few[1][:2] / few[1][2], side[:2] / side[2], atol=1e-5)
    np.testing.assert_allclose(many[1], t, atol=1e-4)
    between = fuse_pose(LMO_K, off, 1.05 * t, DensePoints(uv, X, np.ones(300)), 1.05 * t[2], fusion)
    assert angle(between[0], R) < angle(off, R) and abs(between[1][2] / t[2] - 1) < 0.05
    bad = uv.copy()
    bad[:60] += rng.uniform(20, 40, (60, 2))
    R2, t2, _ = fuse_pose(LMO_K, R, 1.05 * t, DensePoints(bad + rng.normal(0, 0.3, bad.shape), X, np.ones(300)), t[2], fusion)
    assert abs(t2[2] / t[2] - 1) < 0.005 and angle(R2, R) < 0.5
    assert fuse_pose(LMO_K, R, t, DensePoints(uv[:5], X[:5], np.ones(5)), t[2], fusion) is None
    assert fuse_pose(LMO_K, R, -t, DensePoints(uv, X, np.ones(300)), t[2], fusion) is None


def test_the_dense_fusions_covariance_is_the_scatter_of_its_solutions():
    """Points with Gaussian pixel noise (1 px per coordinate), each an independent point (points = their number) and
    priors too wide to matter: over many noise draws the solutions scatter as the reported covariance says (its
    Laplace approximation), in geometry_msgs' order (x, y, z, rotation about X, Y, Z; the rotation error as the
    rotation vector of R_est R_trueᵀ); `covariance_scale` scales its translation and rotation blocks."""
    from axispose_core.metrics import mahalanobis_sq
    from axispose_core.tbm.dense import DenseFusion, DensePoints, fuse_pose

    rng = np.random.default_rng(11)
    R, t, X, uv = _exact_points(rng)
    n = 60
    X, uv = X[:n], uv[:n]
    wide = DenseFusion(points=n, rotation_sigma=10.0, depth_sigma=10.0, origin_sigma=1e4)
    errors, covs, d2 = [], [], []
    for _ in range(1000):
        f = fuse_pose(LMO_K, R, t, DensePoints(uv + rng.normal(0, 1.0, uv.shape), X, np.ones(n)), t[2], wide)
        errors.append(np.concatenate([f.t - t, Rotation.from_matrix(f.R @ R.T).as_rotvec()]))
        covs.append(f.covariance)
        d2.append(mahalanobis_sq(f.R, f.t, R, t, f.covariance))
    scatter, cov = np.cov(np.array(errors).T), np.mean(covs, axis=0)
    ratio = np.diag(cov) / np.diag(scatter)
    assert np.all((ratio > 0.85) & (ratio < 1.2)), ratio
    corr = scatter / np.sqrt(np.outer(np.diag(scatter), np.diag(scatter)))
    corr_cov = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.abs(corr - corr_cov).max() < 0.1  # the cross terms too: depth against tilt, x against rotation about y
    assert 1.5 < np.median(np.array(d2)[:, 0]) < 2.5 and 1.5 < np.median(np.array(d2)[:, 1]) < 2.5  # χ²(3): 2.37
    scaled = fuse_pose(LMO_K, R, t, DensePoints(uv + 0.5, X, np.ones(n)), t[2], replace(wide, covariance_scale=(2.0, 3.0)))
    plain = fuse_pose(LMO_K, R, t, DensePoints(uv + 0.5, X, np.ones(n)), t[2], wide)
    np.testing.assert_allclose(scaled.covariance, plain.covariance * np.outer(*2 * [np.sqrt([2, 2, 2, 3, 3, 3])]), rtol=1e-9)
    with pytest.raises(ValueError, match="covariance_scale"):
        DenseFusion(covariance_scale=(0.0, 1.0))
