import numpy as np
import pytest

from axispose_core.camera import (
    Camera,
    IntrinsicsError,
    crop_image,
    crop_intrinsics,
    crop_transform,
    jacobian_times,
    off_axis,
    project,
    project_model,
    projection_jacobian,
    square_around_box,
    times_jacobian,
    validate_intrinsics,
)
from axispose_core.lmo import LMO_K
from axispose_core.pose_sampling import sample_pose


def test_projection_jacobian_matches_finite_differences_and_its_products(rng):
    K = np.array([[572.4, 0.3, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
    p = rng.uniform([-0.2, -0.2, 0.5], [0.2, 0.2, 1.5], (50, 3))
    q = p @ K.T
    uv, z = q[:, :2] / q[:, 2:], q[:, 2]
    J = projection_jacobian(K, uv, z)
    h = 1e-6
    numeric = np.stack([(project(K, p + h * e) - project(K, p - h * e)) / (2 * h) for e in np.eye(3)], axis=2)
    np.testing.assert_allclose(J, numeric, rtol=1e-6, atol=1e-3)
    d, n = rng.normal(size=(50, 3)), rng.normal(size=(50, 2))
    np.testing.assert_allclose(jacobian_times(K, uv, z, d), np.einsum("nij,nj->ni", J, d), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(times_jacobian(K, uv, z, n), np.einsum("ni,nij->nj", n, J), rtol=1e-12, atol=1e-9)


def test_crop_intrinsics_match_projection_then_crop(rng):
    pts = rng.uniform(-0.1, 0.1, size=(200, 3))
    for _ in range(50):
        R, t = sample_pose(rng)
        center = tuple(rng.uniform(100, 500, size=2))
        side = rng.uniform(20, 400)
        size = int(rng.choice([64, 128, 256]))
        uv = project_model(LMO_K, R, t, pts)
        A = crop_transform(center, side, size)
        via_crop = np.column_stack([uv, np.ones(len(uv))]) @ A.T
        via_kp = project_model(crop_intrinsics(LMO_K, center, side, size), R, t, pts)
        np.testing.assert_allclose(via_kp, via_crop[:, :2], atol=1e-9)


def test_off_axis_is_the_crop_centres_angle_from_the_optical_axis():
    K = LMO_K
    assert off_axis(crop_intrinsics(K, (K[0, 2], K[1, 2]), 120.0, 64), 64) == pytest.approx(0.0, abs=1e-12)
    for deg in (5.0, 20.0, 35.0):
        ray = np.tan(np.radians(deg)) * np.array([np.cos(0.7), np.sin(0.7)])  # a ray `deg` off the axis, diagonally
        centre = (K[0, 2] + K[0, 0] * ray[0], K[1, 2] + K[1, 1] * ray[1])
        for side, size in ((80.0, 64), (300.0, 128)):
            assert off_axis(crop_intrinsics(K, centre, side, size), size) == pytest.approx(1 / np.cos(np.radians(deg)) - 1, rel=1e-9)


def test_crop_centre_maps_to_patch_centre():
    A = crop_transform((300.0, 200.0), 100.0, 64)
    np.testing.assert_allclose(A @ [300.0, 200.0, 1.0], [31.5, 31.5, 1.0])
    # The square's edge (centre - side/2) is the patch's outer edge, half a pixel left of pixel 0.
    np.testing.assert_allclose(A @ [250.0, 150.0, 1.0], [-0.5, -0.5, 1.0])


def test_crop_image_puts_a_pixel_where_the_patch_intrinsics_say():
    img = np.zeros((480, 640), np.float32)
    img[200, 300] = 1.0
    center, side, size = (309.5, 189.5), 64.0, 64  # unit scale, pixel centres on pixel centres
    patch = crop_image(img, center, side, size)
    x, y, _ = crop_transform(center, side, size) @ [300.0, 200.0, 1.0]
    assert patch[round(y), round(x)] == 1.0
    assert patch.sum() == 1.0


def test_square_around_box_covers_the_box():
    (cx, cy), side = square_around_box((10, 20, 30, 50), pad=1.0)
    assert (cx, cy) == (24.5, 44.5)
    assert side == 50


def test_scaled_camera_matches_resized_image():
    cam = Camera(LMO_K, 640, 480)
    half = cam.scaled(320, 240)
    pts = np.array([[0.01, 0.02, 0.8], [-0.05, 0.03, 0.5]])
    # cv2.resize by 1/2 averages pixel pairs: full-res centre u maps to (u + 0.5) / 2 - 0.5.
    np.testing.assert_allclose(project(half.K, pts), (project(cam.K, pts) + 0.5) / 2 - 0.5)


@pytest.mark.parametrize(
    "K, message",
    [
        (np.zeros((3, 3)), "focal"),
        (np.full((3, 3), np.nan), "non-finite"),
        (np.eye(2), "3x3"),
        (np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 2]]), "last row"),
    ],
)
def test_bad_intrinsics_are_refused(K, message):
    with pytest.raises(IntrinsicsError, match=message):
        validate_intrinsics(K)


def test_camera_refuses_bad_size():
    with pytest.raises(IntrinsicsError, match="size"):
        Camera(LMO_K, 0, 480)
