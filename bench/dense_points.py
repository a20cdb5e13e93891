"""What bounds the depth the encoder's dense surface points give: the grid, the points' noise, or their shape.

On held-out crops of the full stream (exact renders, occluders and neighbours; seed 1,000,000, the trainer's
validation stream) it solves t with the true rotation (`tbm/dense.py`'s `translation_from_points`) from
- the exact targets at the encoder's half-resolution cells, as training sees them (`train/losses.py`'s
  `dense_targets`): what the grid allows, per crop size in `--sizes`;
- those targets with independent Gaussian noise of `--noise` object radii: what per-point noise costs at each size;
- the checkpoint's own points at its size, with their median error, their per-crop similarity scale to the targets
  (least squares about both centroids: below 1 where the points are drawn toward the object's centre), that
  scale's correlation with the depth error, and the depth the points give once rescaled about their centroid by
  the scale that best maps them onto the targets (an oracle: what is left is their shape's error, not their
  extent's).

    python bench/dense_points.py --checkpoint axispose_core/models/axispose_lmo.safetensors \\
        --models ../shared/data/lmo/models --json bench/results/dense_points.json
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from tqdm import tqdm
from write_results import write_results

from axispose_core.data.synth.config import StreamConfig
from axispose_core.data.synth.stream import CropStream, CropStreamDataset
from axispose_core.estimator import Estimator
from axispose_core.tbm.dense import translation_from_points
from axispose_core.train.losses import dense_targets

STREAM = {"seed": 1_000_000, "occluded_prob": 0.4, "clutter_prob": 0.5, "neighbours": (0, 2)}
"""The full stream of the AGM's last stages (`config/train_agm_finetune.yaml`), at the validation seed."""


def cells(half: int) -> np.ndarray:
    """Crop pixels (N,2) of the centres of a half-resolution map's cells (pixel centres at integers)."""
    c = np.arange(half) * 2 + 0.5
    return np.stack(np.meshgrid(c, c), axis=-1).reshape(-1, 2)


def depth_error(K: np.ndarray, R: np.ndarray, t: np.ndarray, uv: np.ndarray, X: np.ndarray) -> float:
    """|relative depth error| of t solved from model points X (m) seen at uv with the true R; 1 when unsolved."""
    s = translation_from_points(K, R, uv, X, np.ones(len(uv)))
    return abs(s[2] / t[2] - 1) if s is not None else 1.0


def samples(models: str, size: int, n: int) -> tuple[dict[str, torch.Tensor], np.ndarray]:
    """n held-out stream crops of `size` px as one batch, with each crop's object radius (m)."""
    ds = CropStreamDataset(CropStream(StreamConfig(size=size, **STREAM), models))
    items = [ds[i] for i in tqdm(range(n), desc=f"{size} px crops")]
    batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}
    obj = {v: k for k, v in ds.stream.index.items()}
    radius = np.array([0.5 * ds.stream.models[obj[int(o)]].spec.diameter for o in batch["object"]])
    return batch, radius


def grid_and_noise(models: str, size: int, n: int, noise: list[float], seed: int = 0) -> dict[str, float]:
    """Median depth error from the exact targets at the cells, and with each level of independent noise."""
    b, radius = samples(models, size, n)
    target, m = dense_targets(b["points"], b["mask_visib"], size // 2)
    uv = cells(size // 2)
    rng = np.random.default_rng(seed)
    errs: dict[float, list[float]] = {s: [] for s in [0.0, *noise]}
    for i in range(n):
        keep = m[i, 0].numpy().reshape(-1) > 0
        if keep.sum() < 8:
            continue
        X = target[i].numpy().reshape(3, -1).T[keep]
        K, R, t = (b[k][i].numpy() for k in ("K", "R", "t"))
        for s in errs:
            errs[s].append(depth_error(K, R, t, uv[keep], (X + rng.normal(0, s, X.shape)) * radius[i]))
    return {f"noise_{s:g}": float(np.median(e)) for s, e in errs.items()}


def network(checkpoint: str, models: str, n: int) -> dict[str, float]:
    """The checkpoint's points on the held-out crops: error, similarity scale, depth error and their correlation."""
    est = Estimator.load(checkpoint)
    b, radius = samples(models, est.size, n)
    with torch.inference_mode():
        enc = est.agm.encode(b["crop"], b["object"])
    target, m = dense_targets(b["points"], b["mask_visib"], enc.points.shape[-1])
    uv = cells(enc.points.shape[-1])
    rows = []
    for i in range(n):
        keep = m[i, 0].numpy().reshape(-1) > 0
        if keep.sum() < 8:
            continue
        P = enc.points[i].float().numpy().reshape(3, -1).T[keep]
        T = target[i].numpy().reshape(3, -1).T[keep]
        Pc, Tc = P - P.mean(0), T - T.mean(0)
        scale = float((Pc * Tc).sum() / (Tc * Tc).sum())
        K, R, t = (b[k][i].numpy() for k in ("K", "R", "t"))
        ratios = []
        fit = float((Pc * Tc).sum() / (Pc * Pc).sum())  # the scale that best maps the points onto the targets
        for X in (P, P.mean(0) + fit * Pc):  # as predicted; rescaled about their centroid by that oracle scale
            s = translation_from_points(K, R, uv[keep], X * radius[i], np.ones(int(keep.sum())))
            ratios.append(s[2] / t[2] if s is not None else np.nan)
        rows.append((float(np.median(np.abs(P - T).mean(1))), scale, *ratios))
    a = np.array(rows)
    ok = np.isfinite(a[:, 2])
    return {
        "n": len(a),
        "point_error_radii": float(np.median(a[:, 0])),
        "scale_q25": float(np.quantile(a[:, 1], 0.25)),
        "scale_median": float(np.median(a[:, 1])),
        "scale_q75": float(np.quantile(a[:, 1], 0.75)),
        "depth_error": float(np.median(np.abs(a[ok, 2] - 1))),
        "depth_bias": float(np.median(a[ok, 2])),
        "corr_depth_error_scale": float(np.corrcoef(a[ok, 2] - 1, a[ok, 1])[0, 1]),
        "depth_error_rescaled": float(np.nanmedian(np.abs(a[:, 3] - 1))),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--models", required=True, help="BOP models folder the stream renders")
    p.add_argument("--samples", type=int, default=192)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 96, 128])
    p.add_argument("--noise", type=float, nargs="+", default=[0.02, 0.05, 0.1], help="object radii")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    out = {"grid": {str(s): grid_and_noise(args.models, s, args.samples, args.noise) for s in args.sizes}}
    out["network"] = network(args.checkpoint, args.models, args.samples)
    for size, row in out["grid"].items():
        print(f"{size} px, exact targets / + noise {args.noise} radii: " + " / ".join(f"{100 * v:.2f} %" for v in row.values()))
    net = out["network"]
    print(f"the network's points ({net['n']} crops): error {net['point_error_radii']:.3f} radii, similarity scale "
          f"{net['scale_q25']:.2f} / {net['scale_median']:.2f} / {net['scale_q75']:.2f}, depth {100 * net['depth_error']:.2f} % "
          f"(bias {net['depth_bias']:.3f}), correlation of depth error and scale {net['corr_depth_error_scale']:.2f}; "
          f"rescaled by the oracle {100 * net['depth_error_rescaled']:.2f} %")  # fmt: skip
    if args.json:
        write_results(args.json, {"command": vars(args)} | out)


if __name__ == "__main__":
    main()
