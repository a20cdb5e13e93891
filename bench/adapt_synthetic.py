"""A rendered recording whose objects wear colours other than their meshes' (`data/recolour.py`): the camera circles
a still scene; the first half of its frames is what `axispose adapt` adapts on, the second half (the scene from
the other side) judges, with ground truth the adaptation never reads.

    python bench/adapt_synthetic.py --out DIR [--frames 120] [--seed 77]

writes DIR/models (recoloured), DIR/render (the recording, BOP), DIR/first/000000 and DIR/second/000000 (its halves,
truth included for scoring), and prints the commands that adapt on the first half and validate on the second.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from axispose_core.data.recolour import recoloured_models
from axispose_core.data.synth.config import CameraPathConfig, SceneConfig, SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.lmo import SHARED_LMO


def split(scene: Path, out: Path, keep: set[int]) -> Path:
    """The frames `keep` of a BOP scene folder as another (images linked)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "rgb").mkdir(exist_ok=True)
    for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
        data = json.loads((scene / name).read_text())
        (out / name).write_text(json.dumps({k: v for k, v in data.items() if int(k) in keep}))
    for image in (scene / "rgb").iterdir():
        if int(image.stem) in keep and not (out / "rgb" / image.name).exists():
            os.symlink(image.resolve(), out / "rgb" / image.name)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--frames", type=int, default=160)
    parser.add_argument("--seed", type=int, default=77)
    parser.add_argument("--orbit", type=float, default=2.25, help="degrees the camera turns per frame")
    parser.add_argument("--objects", type=int, default=8, help="objects in the scene")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    out = Path(args.out)
    models = recoloured_models(SHARED_LMO / "models", out / "models", args.seed)
    scene = SceneConfig(objects_per_image=(args.objects, args.objects))
    cfg = SynthConfig(
        seed=args.seed, scenes=1, images_per_scene=args.frames, scene=scene, camera_path=CameraPathConfig(orbit_deg=args.orbit)
    )
    generate(cfg, models, out / "render", workers=args.workers)
    scene = out / "render" / "000000"
    half = args.frames // 2
    first = split(scene, out / "first" / "000000", set(range(half)))
    second = split(scene, out / "second" / "000000", set(range(half, args.frames)))
    print(f"recording {scene}: first half {first}, second half {second}")
    print(f"adapt:    axispose adapt {first} --out {out / 'adapt'} --models {models}")
    print(f"judge:    axispose validate --data {second.parent} [--checkpoint {out / 'adapt' / 'adapted.safetensors'}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
