"""The `axispose` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def _demo(args: argparse.Namespace) -> int:
    from axispose_core.demo import format_rows, run_demo

    rows = run_demo(args.out, seed=args.seed)
    print(format_rows(rows))
    print(f"\ncontact sheet: {Path(args.out) / 'geometry_demo.png'}")
    return 0 if all(r.ok for r in rows) else 1


def _train_reader(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.tbm.reader import ReaderConfig, train_reader

    torch.set_num_threads(args.threads)
    config = ReaderConfig(size=args.size, steps=args.steps, batch=args.batch, seed=args.seed)
    train_reader(config, out=args.out, log_csv=args.log)
    print(f"saved {args.out}")
    return 0


def _synth(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from axispose_core.camera import validate_intrinsics
    from axispose_core.data.synth.config import SynthConfig
    from axispose_core.data.synth.generate import generate

    K = SynthConfig().K
    width, height = args.width, args.height
    if args.camera:
        cam = json.loads(Path(args.camera).read_text())
        try:
            K = np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])
        except KeyError as err:
            raise SystemExit(f"{args.camera}: camera JSON needs fx, fy, cx, cy (BOP camera.json) - missing {err}") from err
        K = tuple(validate_intrinsics(K).ravel().tolist())
        width, height = cam.get("width", width), cam.get("height", height)
    cfg = SynthConfig(
        width=width,
        height=height,
        K=K,
        objects=tuple(args.objects),
        seed=args.seed,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
    )
    models = Path(args.models[0])
    if len(args.models) > 1 or not models.is_dir():
        from axispose_core.data.mesh_import import import_meshes

        models = Path(args.out) / "models"
        ids = import_meshes(args.models, models, units=args.mesh_units)
        print("imported " + ", ".join(f"{p} as object {i}" for i, p in ids.items()) + f" into {models}")
    n = generate(cfg, models, args.out, workers=args.workers)
    print(f"wrote {n} images into {args.out}")
    return 0


def _synth_preview(args: argparse.Namespace) -> int:
    from axispose_core.data.synth.preview import contact_sheet

    print(f"wrote {contact_sheet(args.data, args.out, count=args.count, tile_width=args.tile_width)}")
    return 0


def _ids(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="axispose", description="AxisPose: 6D object pose from one RGB image by axis generation.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="geometry demo on embedded defaults: axis image -> keypoints -> pose")
    demo.add_argument("--out", default="out/demo", help="folder for the contact sheet")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)

    tr = sub.add_parser("train-reader", help="train the TBM keypoint reader on rendered, degraded axis images")
    tr.add_argument("--out", required=True, help="checkpoint to write (.safetensors)")
    tr.add_argument("--size", type=int, default=64, help="axis image size S (the AGM's output size)")
    tr.add_argument("--steps", type=int, default=3000)
    tr.add_argument("--batch", type=int, default=32)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--threads", type=int, default=2)
    tr.add_argument("--log", default=None, help="CSV of the training loss")
    tr.set_defaults(func=_train_reader)

    sy = sub.add_parser("synth", help="render randomised BOP-format training scenes of the objects in --models")
    sy.add_argument(
        "--models",
        required=True,
        nargs="+",
        help="a BOP models folder (obj_XXXXXX.ply + models_info.json), or PLY/OBJ files (ids 1, 2, ... in order)",
    )
    sy.add_argument("--mesh-units", type=float, default=0.001, help="metres per unit of PLY/OBJ files given to --models (BOP: mm)")
    sy.add_argument("--out", required=True, help="dataset folder (reruns resume it)")
    sy.add_argument("--scenes", type=int, required=True)
    sy.add_argument("--images-per-scene", type=int, default=25)
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--objects", type=_ids, default=[], help="comma-separated object ids (default: all in models_info.json)")
    sy.add_argument("--width", type=int, default=640)
    sy.add_argument("--height", type=int, default=480)
    sy.add_argument("--camera", help="BOP camera.json (fx, fy, cx, cy, width, height); default: the LM-O camera")
    sy.add_argument("--workers", type=int, default=1, help="worker processes")
    sy.set_defaults(func=_synth)

    sp = sub.add_parser("synth-preview", help="contact sheet of synthetic frames with their GT axes")
    sp.add_argument("data", help="dataset folder written by `axispose synth`")
    sp.add_argument("--out", required=True, help="PNG to write")
    sp.add_argument("--count", type=int, default=16)
    sp.add_argument("--tile-width", type=int, default=320, help="width of each frame in the sheet (px)")
    sp.set_defaults(func=_synth_preview)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
