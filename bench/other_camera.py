"""A BOP split seen through another camera: each image's white balance, gamma, sharpness, noise and compression
changed (the same change for every image, its noise seeded by the image), labels and cameras as they were. An
adapted model must keep on these what it gained on the frames as recorded.

    python bench/other_camera.py --data DIR/test --out DIR_OTHER/test
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np

GAINS_BGR = (0.85, 1.0, 1.18)
"""Per-channel gains (B, G, R): a warmer white balance."""
GAMMA = 0.8
BLUR_SIGMA = 1.0
NOISE_STD = 4.0
"""Gaussian noise, 8-bit levels."""
JPEG_QUALITY = 60


def other_camera(bgr: np.ndarray, seed: int) -> np.ndarray:
    """The image as the other camera gives it."""
    x = bgr.astype(np.float32) / 255 * np.asarray(GAINS_BGR, np.float32)
    x = np.clip(x, 0, 1) ** GAMMA
    x = cv2.GaussianBlur(x, (0, 0), BLUR_SIGMA) * 255 + np.random.default_rng(seed).normal(0, NOISE_STD, x.shape).astype(np.float32)
    _, jpg = cv2.imencode(".jpg", np.clip(x + 0.5, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return cv2.imdecode(jpg, cv2.IMREAD_COLOR)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a BOP split folder (scene folders inside)")
    parser.add_argument("--out", required=True, help="the split folder to write")
    args = parser.parse_args()
    count = 0
    for scene in sorted(p for p in Path(args.data).iterdir() if (p / "scene_camera.json").is_file()):
        dst = Path(args.out) / scene.name
        (dst / "rgb").mkdir(parents=True, exist_ok=True)
        for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
            if (scene / name).is_file():
                shutil.copyfile(scene / name, dst / name)
        for image in sorted((scene / "rgb").iterdir()):
            cv2.imwrite(str(dst / "rgb" / f"{image.stem}.png"), other_camera(cv2.imread(str(image)), int(image.stem)))
            count += 1
    print(f"wrote {count} images into {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
