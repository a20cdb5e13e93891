"""The encoder's depth bias against how far off the optical axis its crop was cut: the numbers for the estimator's
`head_offaxis`.

The depth head sees the crop, not where in the frame it was cut. An object off the optical axis is drawn stretched
along the radial direction (by up to 1 / cos θ), so at the same depth it reads nearer than one on the axis, and the
head learns the average over the stream's angles. On held-out crops of the training stream (the validation seed:
the full stream and the unoccluded one) this fits the head's log depth error as c0 + c1 (1 / cos θ - 1), θ the
angle of the ray through the crop's centre (`camera.off_axis`), by least absolute deviations, and prints the bias
per band of θ before and after taking the fit off. The frames' objects sit nearer the centre than the stream's
(whose origins are drawn anywhere in the frame), which is where the uncorrected head reads too far.

    python bench/head_offaxis.py --checkpoint axispose_core/models/axispose_lmo.safetensors \\
        --models ../shared/data/lmo/models --json bench/results/head_offaxis.json --plot docs/head_offaxis.png
"""

from __future__ import annotations

import argparse
import itertools

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from dense_points import STREAM
from tqdm import tqdm
from write_results import write_results

from axispose_core.camera import off_axis
from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, stream_loader
from axispose_core.estimator import Estimator
from axispose_core.train.losses import log_depth_target

STREAMS = {
    "full": STREAM,
    "unoccluded": {"seed": 1_000_001, "occluded_prob": 0.0, "clutter_prob": 0.0, "neighbours": (0, 0)},
}
"""Held-out crops of the AGM's last stages' stream and of its first stage's, at validation seeds."""
BANDS_DEG = (0, 5, 10, 15, 20, 25, 35)


def errors(est: Estimator, models: str, per_stream: int, batch: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """The head's log depth errors (N,) on held-out stream crops and their crops' 1 / cos θ - 1 (N,)."""
    scales = torch.tensor([o.scale for o in est.config.objects], dtype=torch.float32)
    err, x = [], []
    for name, cfg in STREAMS.items():
        stream = CropStream(StreamConfig(size=est.size, **cfg), models)
        for b in tqdm(stream_loader(stream, batch, stop=per_stream), total=-(-per_stream // batch), desc=f"{name} stream"):
            with torch.inference_mode():
                log_depth = est.agm.encode(b["crop"], b["object"]).log_depth.float()
            err.append((log_depth - log_depth_target(b["K"], b["t"].float(), scales[b["object"]], est.size)).numpy())
            x.append([off_axis(K, est.size) for K in b["K"].numpy()])
    return np.concatenate(err), np.concatenate(x)


def fit_lad(x: np.ndarray, y: np.ndarray, iters: int = 50) -> np.ndarray:
    """(c0, c1) minimising sum |y - c0 - c1 x| (iteratively reweighted least squares): the median line, as the
    estimator's depth errors are judged by their median."""
    A = np.column_stack([np.ones_like(x), x])
    w = np.ones_like(y)
    coef = np.zeros(2)
    for _ in range(iters):
        coef = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)[0]
        w = 1 / np.sqrt(np.maximum(np.abs(y - A @ coef), 1e-4))
    return coef


def degrees(x: np.ndarray) -> np.ndarray:
    """θ in degrees from 1 / cos θ - 1 (`camera.off_axis`)."""
    return np.degrees(np.arccos(1 / (1 + x)))


def bands(x: np.ndarray, e: np.ndarray) -> list[dict]:
    """Median ratio of estimated to true depth per band of θ."""
    theta = degrees(x)
    out = []
    for lo, hi in itertools.pairwise(BANDS_DEG):
        s = (theta >= lo) & (theta < hi)
        out.append({"deg": [lo, hi], "n": int(s.sum()), "bias": float(np.exp(np.median(e[s]))) if s.any() else None})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--models", required=True, help="BOP models folder the stream renders")
    p.add_argument("--crops", type=int, default=1024, help="held-out crops per stream")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default=None)
    p.add_argument("--plot", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    est = Estimator.load(args.checkpoint)
    e, x = errors(est, args.models, args.crops)
    c0, c1 = fit_lad(x, e)
    r = e - c0 - c1 * x
    before, after = bands(x, e), bands(x, r)
    med = {"before": float(np.median(np.abs(np.expm1(e)))), "after": float(np.median(np.abs(np.expm1(r))))}
    print(f"{len(e)} held-out stream crops: log depth error = {c0:.4f} + {c1:.4f} (1/cos θ - 1); median |error| "
          f"{100 * med['before']:.2f} % -> {100 * med['after']:.2f} % with it taken off")  # fmt: skip
    for b0, b1 in zip(before, after, strict=True):
        if b0["n"]:
            print(f"  θ {b0['deg'][0]:>2}-{b0['deg'][1]:<2} deg  n {b0['n']:>5}  bias {b0['bias']:.4f} -> {b1['bias']:.4f}")
    print(f"estimator config: head_offaxis: [{c0:.4f}, {c1:.4f}]")
    if args.plot:
        theta = degrees(x)
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.scatter(theta, 100 * np.expm1(e), s=3, alpha=0.25, label="head, per crop")
        grid = np.linspace(0, theta.max(), 100)
        ax.plot(grid, 100 * np.expm1(c0 + c1 * (1 / np.cos(np.radians(grid)) - 1)), "r", label="fit (taken off)")
        mid = [np.mean(b["deg"]) for b in before if b["n"]]
        ax.plot(mid, [100 * (b["bias"] - 1) for b in before if b["n"]], "ko-", label="median per band")
        ax.plot(mid, [100 * (b["bias"] - 1) for b in after if b["n"]], "go-", label="median per band, corrected")
        ax.set(xlabel="crop centre's angle off the optical axis (deg)", ylabel="depth error (%)", ylim=(-8, 8))
        ax.axhline(0, color="grey", lw=0.5)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
    if args.json:
        write_results(args.json, {"command": vars(args), "head_offaxis": [float(c0), float(c1)], "median_abs_error": med,
                                  "bias_by_angle": before, "bias_by_angle_corrected": after})  # fmt: skip


if __name__ == "__main__":
    main()
