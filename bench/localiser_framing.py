"""How the localiser frames the objects it finds: its crops' centre and scale errors against the GT box's crop.

For every instance the localiser finds (IoU >= 0.5 with its amodal GT box, the detection protocol of
`frame_outcome`) on held-out BOP frames, both boxes become the square crop the estimator cuts
(`square_around_box` with the estimator's `crop_pad`); the centre error is expressed in units of the GT crop's
side and the scale error as log(side_det / side_gt). These are the numbers the crop stream's framing
(`data/stream.py: Framing`) is set from: prints quantiles and the robust fit it uses, writes JSON.

    python bench/localiser_framing.py --checkpoint axispose_core/models/axispose_lmo.safetensors --data data/lmo_val
"""

from __future__ import annotations

import argparse
import datetime
import platform

import numpy as np
from tqdm import tqdm
from write_results import write_results

from axispose_core.camera import square_around_box
from axispose_core.data.bop_scene import bop_frames
from axispose_core.estimator import Estimator
from axispose_core.localiser.decode import match
from axispose_core.localiser.scoring import frame_instances, frame_outcome


def framing_errors(est: Estimator, data: list[str], min_visib: float) -> np.ndarray:
    """(N, 4): centre error x, y (GT crop sides), log side ratio, visib_fract of every found instance."""
    rows = []
    ids = tuple(o.obj_id for o in est.config.objects)
    for scene, im_id in tqdm(bop_frames(data), desc="frames"):
        dets = est.detect(scene.rgb(im_id))
        insts = frame_instances(scene, im_id, ids)
        hits = match(dets, [(o, b) for o, b, _ in insts])
        found, _ = frame_outcome(dets, insts, min_visib)
        for g, k in enumerate(hits):
            if k is None or g not in found:
                continue
            (gx, gy), gs = square_around_box(insts[g][1], est.config.crop_pad)
            (dx, dy), ds = square_around_box(dets[k].box, est.config.crop_pad)
            rows.append(((dx - gx) / gs, (dy - gy) / gs, np.log(ds / gs), insts[g][2]))
    return np.asarray(rows)


def _robust_std(v: np.ndarray) -> float:
    """1.4826 x the median absolute deviation: the standard deviation of a Gaussian core, blind to the tails."""
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="axispose_core/models/axispose_lmo.safetensors")
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--min-visib", type=float, default=0.1)
    ap.add_argument("--json", default="bench/results/localiser_framing.json")
    args = ap.parse_args()
    est = Estimator.load(args.checkpoint)
    err = framing_errors(est, args.data, args.min_visib)
    q = (0.05, 0.25, 0.5, 0.75, 0.95)
    table = {}
    print(f"{len(err)} found instances; crop pad {est.config.crop_pad}")
    print(f"{'':14s}" + "".join(f"{f'q{int(100 * p)}':>9s}" for p in q) + f"{'std':>9s}{'1.4826·MAD':>12s}")
    for j, name in enumerate(("centre_x", "centre_y", "log_scale")):
        v = err[:, j]
        mad = _robust_std(v)
        table[name] = {"quantiles": dict(zip(map(str, q), np.quantile(v, q).round(4).tolist(), strict=True)),
                       "median": float(np.median(v)), "std": float(v.std()), "robust_std": mad}  # fmt: skip
        print(f"{name:14s}" + "".join(f"{x:9.4f}" for x in np.quantile(v, q)) + f"{v.std():9.4f}{mad:12.4f}")
    by_visib = {}
    for lo, hi in ((0.1, 0.5), (0.5, 0.8), (0.8, 1.01)):
        sel = (err[:, 3] >= lo) & (err[:, 3] < hi)
        if sel.any():
            c = np.hypot(err[sel, 0], err[sel, 1])
            xy, ls = err[sel, :2].ravel(), err[sel, 2]
            band = {"n": int(sel.sum()), "centre_err_median": float(np.median(c)), "centre_robust_std": _robust_std(xy),
                    "log_scale_median": float(np.median(ls)), "log_scale_robust_std": _robust_std(ls)}  # fmt: skip
            by_visib[f"{lo}-{min(hi, 1.0)}"] = band
            print(f"visib {lo}-{min(hi, 1.0)}: n={band['n']}, centre error median {band['centre_err_median']:.4f} "
                  f"(per axis robust std {band['centre_robust_std']:.4f}), log scale median {band['log_scale_median']:+.4f} "
                  f"(robust std {band['log_scale_robust_std']:.4f})")  # fmt: skip
    out = {"checkpoint": args.checkpoint, "data": args.data, "n": len(err), "crop_pad": est.config.crop_pad, **table,
           "by_visib": by_visib, "machine": platform.processor() or platform.machine(),
           "date": datetime.date.today().isoformat()}  # fmt: skip
    write_results(args.json, out)


if __name__ == "__main__":
    main()
