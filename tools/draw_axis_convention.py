"""Draw docs/axis_convention.png: one LM-O-like pose, its model axes in 3D and its axis image, channel by channel."""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

from axispose_core.axis_image import AxisSpec, axis_keypoints, render_axis_keypoints
from axispose_core.camera import crop_intrinsics
from axispose_core.pose_sampling import LMO_K, sphere_crop


def main(out: str) -> None:
    spec = AxisSpec(0.05, ratio_b=0.8, ratio_c=1.2)
    R = Rotation.from_euler("xyz", [-110, 15, 30], degrees=True).as_matrix()
    t = np.array([0.03, -0.02, 0.6])
    center, side = sphere_crop(LMO_K, t, spec.lengths.max(), pad=1.3)
    Kp = crop_intrinsics(LMO_K, center, side, 128)
    kp = axis_keypoints(Kp, R, t, spec.lengths)
    img = render_axis_keypoints(kp, 128)

    fig = plt.figure(figsize=(13, 3.6))
    ax3 = fig.add_subplot(1, 5, 1, projection="3d")
    for k, c in enumerate("rgb"):
        end = np.eye(3)[k] * spec.lengths[k]
        ax3.plot([0, end[0]], [0, end[1]], [0, end[2]], c, lw=3)
        ax3.text(*(end * 1.1), f"{'XYZ'[k]}: L={spec.lengths[k] * 1000:.0f} mm", color=c)
    ax3.set_title("model frame, L = λ_O (1, r_B, r_C)", fontsize=9)
    ax3.set_axis_off()
    ax = fig.add_subplot(1, 5, 2)
    ax.imshow(img)
    ax.plot(*kp[0], "wo", ms=4)
    ax.set_title("axis image (R/G/B = X/Y/Z)")
    for k in range(3):
        a = fig.add_subplot(1, 5, 3 + k)
        a.imshow(img[..., k], cmap="gray", vmin=0, vmax=1)
        a.plot(*kp[0], "c+", ms=8)
        a.plot(*kp[k + 1], "mx", ms=8)
        a.set_title(f"channel {k} = axis {'XYZ'[k]}")
    for a in fig.axes[1:]:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(out, dpi=90)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/axis_convention.png")
