import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from axispose_core.axis_image import (
    AxisSpec,
    axis_keypoints,
    axis_keypoints_torch,
    render_axis_image,
    render_axis_keypoints,
    render_axis_keypoints_torch,
)
from axispose_core.pose_sampling import sample_patch


def test_axis_spec_lengths_and_validation():
    spec = AxisSpec(0.05, 0.8, 1.2)
    np.testing.assert_allclose(spec.lengths, [0.05, 0.04, 0.06])
    assert AxisSpec.from_diameter(0.2).scale == pytest.approx(0.1)
    with pytest.raises(ValueError, match="positive"):
        AxisSpec(0.0)
    with pytest.raises(ValueError, match="ratios"):
        AxisSpec(0.05, -1.0)


def test_channels_hold_x_y_z_axes():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    # Identity rotation: X points right, Y down, Z away (it projects to the origin's point).
    img = render_axis_image(K, np.eye(3), np.array([0, 0, 1.0]), np.array([0.2, 0.2, 0.2]), 64)
    assert img.shape == (64, 64, 3) and img.dtype == np.float32
    assert img[31, 45, 0] > 0.9 and img[31, 45, 1] < 0.1  # right of centre: X only
    assert img[45, 31, 1] > 0.9 and img[45, 31, 0] < 0.1  # below centre: Y only
    assert img[31:33, 31:33, 2].max() > 0.5 and img[10, 31, 2] == 0  # Z is a dot at the origin


def test_behind_camera_is_refused():
    with pytest.raises(ValueError, match="behind"):
        axis_keypoints(np.eye(3), np.eye(3), np.array([0, 0, -1.0]), np.full(3, 0.1))


def test_numpy_and_torch_renderers_agree(rng):
    ious = []
    for _ in range(30):
        ps = sample_patch(rng, 0.05, 64)
        kp = axis_keypoints(ps.K_patch, ps.R, ps.t, np.full(3, 0.05))
        a = render_axis_keypoints(kp, 64) > 0.5
        b = render_axis_keypoints_torch(torch.as_tensor(kp[None]), 64)[0].permute(1, 2, 0).numpy() > 0.5
        for c in range(3):
            union = (a[..., c] | b[..., c]).sum()
            if union:
                ious.append((a[..., c] & b[..., c]).sum() / union)
    assert min(ious) >= 0.9


def test_torch_render_matches_numpy_values(rng):
    ps = sample_patch(rng, 0.05, 64)
    kp = axis_keypoints(ps.K_patch, ps.R, ps.t, np.full(3, 0.05))
    a = render_axis_keypoints(kp, 64)
    b = render_axis_keypoints_torch(torch.as_tensor(kp[None]), 64)[0].permute(1, 2, 0).numpy()
    assert np.abs(a - b).mean() < 0.02


def test_gradients_reach_rotation_and_translation(rng):
    ps = sample_patch(rng, 0.05, 64)
    rotvec = torch.tensor(Rotation.from_matrix(ps.R).as_rotvec(), dtype=torch.float64, requires_grad=True)
    t = torch.tensor(ps.t, dtype=torch.float64, requires_grad=True)
    target = torch.as_tensor(render_axis_keypoints(axis_keypoints(ps.K_patch, ps.R, ps.t + [0.003, 0, 0], np.full(3, 0.05)), 64))

    def rodrigues(v: torch.Tensor) -> torch.Tensor:
        theta = v.norm()
        k = v / theta
        Kx = torch.zeros(3, 3, dtype=v.dtype)
        Kx[0, 1], Kx[0, 2], Kx[1, 2] = -k[2], k[1], -k[0]
        Kx = Kx - Kx.T
        return torch.eye(3, dtype=v.dtype) + torch.sin(theta) * Kx + (1 - torch.cos(theta)) * Kx @ Kx

    R = rodrigues(rotvec)
    kp = axis_keypoints_torch(torch.as_tensor(ps.K_patch)[None], R[None], t[None], torch.full((1, 3), 0.05, dtype=torch.float64))
    img = render_axis_keypoints_torch(kp, 64)[0].permute(1, 2, 0)
    ((img - target) ** 2).sum().backward()
    assert rotvec.grad is not None and torch.all(torch.isfinite(rotvec.grad)) and rotvec.grad.abs().sum() > 0
    assert t.grad is not None and t.grad[0] < 0  # the target sits at larger x: the loss falls as t_x grows
