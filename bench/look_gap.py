"""How far the real look moves an AGM's encoder: the same GT crops cut from the real frames and from their twins
(`bench/real_twins.py`: the annotated objects re-rendered at their poses over the same frames), encoded by each
checkpoint, and the two encodings compared where the network computes them (every trunk stage) and where the
denoiser reads them (each level's injected map and the context vector).

The gap of a feature is the mean squared difference between a real crop's and its twin's, over the feature's
variance across all the crops: 0 when the real look changes nothing, about 2 when real and twin are as far apart
as two unrelated crops. A trunk whose features move less under the real look leaves less for the denoiser to
misread; the twin check's accuracy says what each checkpoint makes of it.

    python bench/real_twins.py --out out/twins      # writes out/twins/twins once
    python bench/look_gap.py --twins out/twins/twins --checkpoint A.safetensors B.safetensors
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from axispose_core.data.bop import bop_frames
from axispose_core.data.visibility import gt_info_from_models
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator, crop_batch
from axispose_core.lmo import REAL_SLICE, SHARED_LMO


def gt_crops(est: Estimator, data: str | Path, models: str | Path, visib: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """The estimator's crops (B,3,S,S) of every annotated instance in `data` within the visibility band, and the
    rows of their objects, frame by frame in file order (a split and its twins give the same instances)."""
    crops, objects = [], []
    for scene, im_id in bop_frames([data], gt_info_from_models(models)):
        boxes = [(g.obj_id, info.bbox_obj) for g, info in scene.instances(im_id)
                 if g.obj_id in est.index and visib[0] <= info.visib_fract <= visib[1]]  # fmt: skip
        if boxes:
            crops.append(crop_batch(scene.rgb(im_id), scene.cameras[im_id], boxes, est.objects, est.size, est.config.crop_pad)[1])
            objects += [est.index[o] for o, _ in boxes]
    return torch.cat(crops), torch.tensor(objects)


def features(est: Estimator, crops: torch.Tensor, objects: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each trunk stage's output and what the denoiser reads (each level's injected map, the context), per crop,
    flattened."""
    agm, out = est.agm.eval(), {}
    hooks = [stage.register_forward_hook(lambda _m, _i, o, k=k: out.__setitem__(f"stage {k + 1}", o))
             for k, stage in enumerate(agm.denoiser.encoder.trunk.stages)]  # fmt: skip
    try:
        with torch.no_grad():
            enc = agm.encode(crops, objects)
            inject = agm.denoiser.inject
            for k, (layer, m) in enumerate(zip(inject, enc.maps[: len(inject)], strict=True)):
                out[f"level {k + 1}"] = layer(m)
            out["context"] = enc.context
    finally:
        for hook in hooks:
            hook.remove()
    return {k: v.flatten(1).float() for k, v in out.items()}


def gap(real: torch.Tensor, twin: torch.Tensor) -> float:
    """Mean squared real-twin difference over the feature's variance across both sets."""
    return float(((real - twin) ** 2).mean() / torch.cat([real, twin]).var(dim=0).mean().clamp(min=1e-12))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", nargs="+", default=[str(SHIPPED_ESTIMATOR)], help="estimator checkpoints to compare")
    ap.add_argument("--data", default=str(REAL_SLICE), help="the real frames (default: the real validation slice)")
    ap.add_argument("--twins", required=True, help="their twins (bench/real_twins.py's OUT/twins)")
    ap.add_argument("--models", default=str(SHARED_LMO / "models_eval"), help="models for the instances' visibility")
    ap.add_argument("--visib", type=float, nargs=2, default=(0.1, 1.0))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", help="write the gaps as JSON here too")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gaps = {}
    for path in args.checkpoint:
        est = Estimator.load(path)
        real, objects = gt_crops(est, args.data, args.models, tuple(args.visib))
        twin, twin_objects = gt_crops(est, args.twins, args.models, tuple(args.visib))
        if not torch.equal(objects, twin_objects):
            raise SystemExit(f"look_gap: {args.twins} does not hold the twins of {args.data}'s instances")
        fr, ft = features(est, real, objects), features(est, twin, objects)
        gaps[path] = {k: gap(fr[k], ft[k]) for k in fr}
        print(f"{Path(path).name} ({len(objects)} crops, trunk {est.config.agm.denoiser.encoder.trunk.kind}):")
        print("  " + ", ".join(f"{k} {v:.3f}" for k, v in gaps[path].items()))
    if args.out:
        Path(args.out).write_text(json.dumps(gaps, indent=2))


if __name__ == "__main__":
    main()
