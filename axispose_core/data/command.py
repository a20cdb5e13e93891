"""The commands on datasets: `synth` (rendered BOP scenes), `gt-info` (visibility of BOP scenes from their
models), `synth-preview` and `stream-preview` (contact sheets of synthetic frames and of crop-stream samples)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from axispose_core.command_args import AddParser, object_ids
from axispose_core.lmo import SHARED_LMO


def _camera_path(text: str | None, config: type) -> object | None:
    """`--camera-path`: the orbit in degrees per image, or a mapping of CameraPathConfig's fields."""
    if text is None:
        return None
    try:
        return config(orbit_deg=float(text))
    except ValueError:
        from axispose_core.config import config_from_dict, yaml_mapping

        return config_from_dict(config, yaml_mapping(text), "--camera-path")


def _synth(args: argparse.Namespace) -> int:
    from axispose_core.config import ConfigError, config_from_dict, yaml_mapping
    from axispose_core.data.bop import BopFormatError, load_camera
    from axispose_core.data.synth.config import CameraPathConfig, RandomizationConfig, SceneConfig, SynthConfig, recipe
    from axispose_core.data.synth.generate import generate

    K = SynthConfig().K
    try:
        scene, randomization = recipe(args.recipe)
        if args.randomization:
            randomization = config_from_dict(RandomizationConfig, yaml_mapping(args.randomization), "--randomization", randomization)
        if args.scene:
            scene = config_from_dict(SceneConfig, yaml_mapping(args.scene), "--scene", scene)
        path = _camera_path(args.camera_path, CameraPathConfig)
    except (ConfigError, TypeError, ValueError) as err:
        print(f"axispose synth: {err}", file=sys.stderr)
        return 2
    width, height = args.width, args.height
    if args.camera:
        try:
            cam_K, cam_width, cam_height = load_camera(args.camera)
        except BopFormatError as err:
            raise SystemExit(str(err)) from err
        K, width, height = tuple(cam_K.ravel().tolist()), cam_width or width, cam_height or height
    cfg = SynthConfig(
        width=width,
        height=height,
        K=K,
        objects=tuple(args.objects),
        seed=args.seed,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
        scene=scene,
        randomization=randomization,
        depth=args.depth,
        camera_path=path,
    )
    models = Path(args.models[0])
    if len(args.models) > 1 or not models.is_dir():
        from axispose_core.data.mesh_import import import_meshes

        models = Path(args.out) / "models"
        try:
            symmetries = dict(spec.split("=", 1) for spec in args.symmetry if "=" in spec)
            if len(symmetries) != len(args.symmetry):
                raise BopFormatError(f"--symmetry takes NAME=SPEC, got {' '.join(args.symmetry)}")
            ids = import_meshes(args.models, models, units=args.mesh_units, symmetries=symmetries)
        except BopFormatError as err:
            print(f"axispose synth: {err}", file=sys.stderr)
            return 2
        print("imported " + ", ".join(f"{p} as object {i}" for i, p in ids.items()) + f" into {models}")
    n = generate(cfg, models, args.out, workers=args.workers)
    print(f"wrote {n} images into {args.out}")
    return 0


def _gt_info(args: argparse.Namespace) -> int:
    """`axispose gt-info`: scene_gt_info.json (boxes, visibility) for BOP scenes that lack it, from the models."""
    from axispose_core.data.bop import BopFormatError
    from axispose_core.data.bop_scene import scene_dirs
    from axispose_core.data.visibility import write_gt_info

    try:
        scenes = [sd for root in args.scenes for sd in scene_dirs(root)]
        written = [sd for sd in scenes if write_gt_info(sd, args.models, overwrite=args.overwrite)]
    except BopFormatError as err:
        print(f"axispose gt-info: {err}", file=sys.stderr)
        return 2
    print(f"wrote scene_gt_info.json in {len(written)} of {len(scenes)} scene(s)" + ("" if args.overwrite else " (the rest had one)"))
    return 0


def _synth_preview(args: argparse.Namespace) -> int:
    from axispose_core.data.synth.preview import contact_sheet

    print(f"wrote {contact_sheet(args.data, args.out, count=args.count, tile_width=args.tile_width)}")
    return 0


def _stream_preview(args: argparse.Namespace) -> int:
    from axispose_core.data.bop import BopFormatError
    from axispose_core.data.synth.config import StreamConfig
    from axispose_core.data.synth.preview import stream_sheet
    from axispose_core.data.synth.stream import CropStream

    try:
        stream = CropStream(StreamConfig(size=args.size, objects=tuple(args.objects), seed=args.seed), args.models)
        print(f"wrote {stream_sheet(stream, args.out, start=args.start, count=args.count)}")
    except (ValueError, BopFormatError) as err:
        print(f"axispose stream-preview: {err}", file=sys.stderr)
        return 2
    return 0


def add_synth(add_parser: AddParser) -> None:
    """`axispose synth`."""
    sy = add_parser("synth", help="render randomised BOP-format training scenes of the objects in --models")
    sy.add_argument(
        "--models",
        required=True,
        nargs="+",
        help="a BOP models folder (obj_XXXXXX.ply + models_info.json), or PLY/OBJ files (ids 1, 2, ... in order)",
    )
    sy.add_argument("--mesh-units", type=float, default=0.001, help="metres per unit of PLY/OBJ files given to --models (BOP: mm)")
    sy.add_argument("--symmetry", nargs="*", default=[], metavar="NAME=SPEC",
                    help="an imported mesh's symmetry about an axis of its own frame through its origin: continuous-z "
                    "(a body of revolution), N-x (looks the same turned by 360/N degrees), ...")  # fmt: skip
    sy.add_argument("--out", required=True, help="dataset folder (reruns resume it)")
    sy.add_argument("--scenes", type=int, required=True)
    sy.add_argument("--images-per-scene", type=int, default=25)
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--recipe", default="desk", help="scenes and looks: desk (default: on a table among everyday "
                    "meshes, shadows, a camera's lens and sensor), plain (objects in front of a photograph: the data of "
                    "earlier models), desk-held-out (the desk's held-out meshes and photographs: stress sets)")  # fmt: skip
    sy.add_argument("--randomization", metavar="YAML", help="the recipe's look changed where this YAML mapping (or file of "
                    "one) says, e.g. '{light: {ambient: [0.15, 1.0]}}': a partial RandomizationConfig (data/synth/config.py)")  # fmt: skip
    sy.add_argument("--scene", metavar="YAML", help="the recipe's scenes changed where this YAML mapping (or file of one) "
                    "says, e.g. '{lookalike_prob: 0.5}': a partial SceneConfig (data/synth/config.py)")  # fmt: skip
    sy.add_argument("--objects", type=object_ids, default=[], help="comma-separated object ids (default: all in models_info.json)")
    sy.add_argument("--width", type=int, default=640)
    sy.add_argument("--height", type=int, default=480)
    sy.add_argument("--camera", help="BOP camera.json (fx, fy, cx, cy, width, height); default: the LM-O camera")
    sy.add_argument("--workers", type=int, default=1, help="worker processes")
    sy.add_argument("--depth", action="store_true", help="also write depth images (BOP depth/, for the VSD error of `axispose eval`)")
    sy.add_argument("--camera-path", default=None, metavar="DEG|MAPPING", help="film each scene along a camera path: one "
                    "world, the camera orbiting it by DEG per image and shaking as a hand-held one (tracking's video); or a "
                    "mapping of CameraPathConfig's fields, e.g. '{orbit_deg: 1.5, sweep_deg: 25, shutter: 0.5, passers: 2}'")  # fmt: skip
    sy.set_defaults(func=_synth)


def add_gt_info(add_parser: AddParser) -> None:
    """`axispose gt-info`."""
    gi = add_parser("gt-info", help="write scene_gt_info.json (boxes, visible fractions) of BOP scenes that lack it, from the models")
    gi.add_argument("scenes", nargs="+", help="BOP scene folders, or folders of scenes")
    gi.add_argument("--models", required=True, help="the objects' BOP models folder")
    gi.add_argument("--overwrite", action="store_true", help="also replace existing scene_gt_info.json files")
    gi.set_defaults(func=_gt_info)


def add_synth_preview(add_parser: AddParser) -> None:
    """`axispose synth-preview`."""
    sp = add_parser("synth-preview", help="contact sheet of synthetic frames with their GT axes")
    sp.add_argument("data", help="dataset folder written by `axispose synth`")
    sp.add_argument("--out", required=True, help="PNG to write")
    sp.add_argument("--count", type=int, default=16)
    sp.add_argument("--tile-width", type=int, default=320, help="width of each frame in the sheet (px)")
    sp.set_defaults(func=_synth_preview)


def add_stream_preview(add_parser: AddParser) -> None:
    """`axispose stream-preview`."""
    st = add_parser("stream-preview", help="contact sheet of crop-stream samples (AGM training crops) with their GT axes")
    st.add_argument("--out", required=True, help="PNG to write")
    st.add_argument(
        "--models", default=str(SHARED_LMO / "models"), help="BOP models folder (default: ../shared/data/lmo/models beside the clone)"
    )
    st.add_argument("--objects", type=object_ids, default=[], help="comma-separated object ids (default: all in models_info.json)")
    st.add_argument("--seed", type=int, default=0)
    st.add_argument("--start", type=int, default=0, help="first sample index")
    st.add_argument("--count", type=int, default=32)
    st.add_argument("--size", type=int, default=64, help="crop size in pixels")
    st.set_defaults(func=_stream_preview)
