"""The `axispose` command line."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from axispose_core.lmo import REAL_SLICE, SHARED_LMO

C = TypeVar("C")
TARGETS_FILE = "test_targets_bop19.json"


def _demo(args: argparse.Namespace) -> int:
    from axispose_core.demo import format_rows, run_demo

    rows = run_demo(args.out, seed=args.seed)
    print(format_rows(rows))
    print(f"\ncontact sheet: {Path(args.out) / 'geometry_demo.png'}")
    return 0 if all(r.ok for r in rows) else 1


def _train_reader(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.train.reader import ReaderTrainConfig, train_reader

    torch.set_num_threads(args.threads)
    cfg = _config(ReaderTrainConfig, args.config)
    step = train_reader(cfg, args.out, _run_options(args))
    print(f"stopped at step {step} of {cfg.optim.steps}; keypoint reader {args.out}")
    return 0


def _yaml_mapping(text: str) -> dict:
    """A YAML mapping given inline or as the path of a file holding one."""
    import yaml

    path = Path(text)
    try:
        data = yaml.safe_load(path.read_text() if path.is_file() else text)
    except yaml.YAMLError as err:
        raise ValueError(f"not YAML: {err}".replace("\n", " ")) from err
    if not isinstance(data, dict):
        raise ValueError(f"expected a YAML mapping, got {text!r}")
    return data


def _camera_path(text: str | None, config: type) -> object | None:
    """`--camera-path`: the orbit in degrees per image, or a mapping of CameraPathConfig's fields."""
    if text is None:
        return None
    try:
        return config(orbit_deg=float(text))
    except ValueError:
        from axispose_core.config import config_from_dict

        return config_from_dict(config, _yaml_mapping(text), "--camera-path")


def _synth(args: argparse.Namespace) -> int:
    from axispose_core.config import ConfigError, config_from_dict
    from axispose_core.data.bop import BopFormatError, load_camera
    from axispose_core.data.synth.config import CameraPathConfig, RandomizationConfig, SceneConfig, SynthConfig, recipe
    from axispose_core.data.synth.generate import generate

    K = SynthConfig().K
    try:
        scene, randomization = recipe(args.recipe)
        if args.randomization:
            randomization = config_from_dict(RandomizationConfig, _yaml_mapping(args.randomization), "--randomization", randomization)
        if args.scene:
            scene = config_from_dict(SceneConfig, _yaml_mapping(args.scene), "--scene", scene)
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
    from axispose_core.data.bop import BopFormatError, scene_dirs
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


def _config(cls: type[C], path: str | None) -> C:
    """A training config dataclass from a YAML of its fields, or its defaults without one."""
    if not path:
        return cls()
    import yaml

    from axispose_core.config import ConfigError, config_from_dict

    try:
        return config_from_dict(cls, yaml.safe_load(Path(path).read_text()) or {}, path)
    except (OSError, yaml.YAMLError, ConfigError) as err:
        print(f"axispose: {path}: not a readable {cls.__name__} ({err})", file=sys.stderr)
        raise SystemExit(2) from err


def _train(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.train.agm import TrainConfig, train_agm

    torch.set_num_threads(args.threads)
    if args.recipe:
        return _train_recipe(args)
    cfg = _config(TrainConfig, args.config)
    step = train_agm(cfg, _crop_sources(args), args.out, _run_options(args), init=args.init)
    print(f"stopped at step {step} of {cfg.optim.steps}; checkpoint {args.out}")
    return 0


def _train_recipe(args: argparse.Namespace) -> int:
    """`axispose train --recipe FILE --out DIR`: every stage the recipe's checkpoint needs, then the checkpoint."""
    from axispose_core.checkpoint import CheckpointError
    from axispose_core.train.recipe import RecipeError, RecipeRunner, load_recipe

    if args.config or args.init or args.resume or args.data or args.stop_at is not None:
        print("axispose train: --recipe runs the recipe's own configs, data and schedule; drop --config, --init, --resume, "
              "--data, --stop-at", file=sys.stderr)  # fmt: skip
        return 2
    adopt = dict(a.split("=", 1) for a in args.adopt if "=" in a)
    try:
        if len(adopt) != len(args.adopt):
            raise RecipeError(f"--adopt takes STAGE=CHECKPOINT, got {' '.join(args.adopt)}")
        recipe = load_recipe(args.recipe)
        runner = RecipeRunner(recipe, args.out, _run_options(args), adopt, render_workers=args.threads, name=Path(args.recipe).stem)
        path = runner.run_all()
    except (RecipeError, CheckpointError) as err:
        print(f"axispose train: {err}", file=sys.stderr)
        return 2
    print(f"checkpoint {path} (recipe {recipe.sha256[:12]})" if path else "stopped at the time cap; run the same command to go on")
    return 0


def _train_direct(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.train.direct import DirectTrainConfig, train_direct

    torch.set_num_threads(args.threads)
    cfg = _config(DirectTrainConfig, args.config)
    step = train_direct(cfg, _crop_sources(args), args.out, _run_options(args))
    print(f"stopped at step {step} of {cfg.optim.steps}; direct-regression baseline {args.out}")
    return 0


def _score_and_attach(args: argparse.Namespace) -> int:
    """After `train-localiser`: the localiser in OUT scored on --val, then given to --attach."""
    from axispose_core.checkpoint import stored_half
    from axispose_core.estimator import Estimator
    from axispose_core.localiser.scoring import detection_scores
    from axispose_core.localiser.weights import load_localiser

    localiser = load_localiser(args.out)
    if args.val:
        scores = detection_scores(localiser, args.val, progress=True)
        print(f"held-out recall {scores['recall']:.3f}, precision {scores['precision']:.3f} at IoU 0.5 (visib >= 0.3), "
              f"{scores['ms_per_frame']['median']:.1f} ms per frame")  # fmt: skip
    if args.attach:  # rewritten in the precision it is stored in (the shipped file: float16)
        Estimator.load(args.attach).with_localiser(localiser).save(args.attach, half=stored_half(args.attach))
        print(f"attached to {args.attach}")
    return 0


def _fit_verifier(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.checkpoint import CheckpointError, stored_half
    from axispose_core.data.bop import BopFormatError
    from axispose_core.estimator import Estimator
    from axispose_core.train.verifier import VerifierFitConfig, fit_verifier

    torch.set_num_threads(args.threads)
    if missing := [d for d in args.data if not Path(d).is_dir()]:
        print(f"axispose fit-verifier: no BOP scenes at {', '.join(missing)}", file=sys.stderr)
        return 2
    try:
        est = Estimator.load(args.checkpoint)
        config = VerifierFitConfig(min_score=args.min_score, steps=args.steps)
        verifier, record = fit_verifier(est, args.data, config, progress=True)
    except (CheckpointError, BopFormatError, ValueError) as err:
        print(f"axispose fit-verifier: {err}", file=sys.stderr)
        return 2
    est.with_verifier(verifier, record).save(args.out, half=stored_half(args.checkpoint))
    print(f"{record['detections']} detections ({record['hits']} hits, {record['false_alarms']} false alarms) in "
          f"{record['seconds']:.0f} s; weights {', '.join(f'{w:.3f}' for w in verifier.weights)}; wrote {args.out}")  # fmt: skip
    return 0


def _train_localiser(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.objects import dataset_objects
    from axispose_core.train.localiser import LocaliserTrainConfig, train_localiser

    torch.set_num_threads(args.threads)
    cfg = _config(LocaliserTrainConfig, args.config)
    if not cfg.localiser.obj_ids:  # default: the objects the data shows
        ids = tuple(o.obj_id for o in dataset_objects(args.data))
        cfg = dataclasses.replace(cfg, localiser=dataclasses.replace(cfg.localiser, obj_ids=ids))
    step = train_localiser(cfg, args.data, args.out, args.val, _run_options(args), init=args.init)
    print(f"stopped at step {step} of {cfg.optim.steps}; localiser {args.out}")
    return _score_and_attach(args)


def _eval(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.baseline.direct import KIND as DIRECT_KIND
    from axispose_core.baseline.direct import DirectEstimator
    from axispose_core.checkpoint import read_metadata
    from axispose_core.data.bop import BopFormatError
    from axispose_core.estimator import EstimateOptions, Estimator
    from axispose_core.evaluate import EvalOptions, Prediction, estimator_runs, evaluate
    from axispose_core.stress import PERTURBATIONS

    torch.set_num_threads(args.threads)
    perturb = PERTURBATIONS[args.perturb] if args.perturb else None
    try:
        targets, targets_path = _bop_targets(args)
    except BopFormatError as err:
        print(f"axispose eval: {err}", file=sys.stderr)
        return 2
    if read_metadata(args.checkpoint, None)["kind"] == DIRECT_KIND:  # the direct-regression baseline
        if args.crops == "detect":
            print("axispose eval: the direct-regression baseline has no localiser; use --crops gt", file=sys.stderr)
            return 2
        direct = DirectEstimator.load(args.checkpoint)
        objects = [o for o in direct.model.config.objects if not args.objects or o.obj_id in args.objects]
        eval_options = EvalOptions(limit=args.limit, visib=tuple(args.visib), perturb=perturb, targets=targets, bop=True)
        run = evaluate(lambda image, K, boxes: [Prediction(p.R, p.t, p.ok) for p in direct.estimate(image, K, boxes)],
                       args.data, args.models, objects, eval_options)  # fmt: skip
        records, notes, bop = run.records, run.notes, run.bop
        config = {"checkpoint": str(args.checkpoint), "data": str(args.data), "model": DIRECT_KIND, "crops": args.crops,
                  "visib": list(args.visib), "perturb": args.perturb, "targets": targets_path, **notes}  # fmt: skip
        return _report(args, records, objects, config, None, bop)
    est = Estimator.load(args.checkpoint)
    precision = est.set_precision(args.precision)
    objects = [o for o in est.config.objects if not args.objects or o.obj_id in args.objects]

    options = EstimateOptions(steps=args.steps, guidance_scale=args.guidance, hypotheses=args.hypotheses, mode_sample=args.mode_sample,
                              refine=args.refine == "on")  # fmt: skip
    predict, detector = estimator_runs(est, options)
    if args.crops == "detect" and est.localiser is None:
        print(f"axispose eval: {args.checkpoint} has no localiser (attach one with `axispose train-localiser --attach`)", file=sys.stderr)
        return 2
    eval_options = EvalOptions(limit=args.limit, detector=detector if args.crops == "detect" else None, visib=tuple(args.visib),
                               perturb=perturb, targets=targets, bop=True)  # fmt: skip
    run = evaluate(predict, args.data, args.models, objects, eval_options)
    records, notes, counts, bop = run.records, run.notes, run.detection_counts, run.bop
    config = {"checkpoint": str(args.checkpoint), "data": str(args.data), "steps": args.steps or est.config.ddim_steps,
              "guidance": est.config.guidance_scale if args.guidance is None else args.guidance, "crops": args.crops,
              "hypotheses": args.hypotheses, "precision": precision, "visib": list(args.visib), "perturb": args.perturb,
              "mode_sample": est.config.mode_sample if args.mode_sample is None else args.mode_sample, "targets": targets_path,
              "refine": args.refine == "on" and est.refiner is not None, **notes}  # fmt: skip
    return _report(args, records, objects, config, counts, bop)


def _validate(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.checkpoint import CheckpointError
    from axispose_core.estimator import SHIPPED_ESTIMATOR
    from axispose_core.evaluate import write_report
    from axispose_core.validation import ValidationSettings, format_validation, validate

    torch.set_num_threads(args.threads)
    if not Path(args.data).is_dir():
        print(f"axispose validate: no BOP scenes at {args.data}", file=sys.stderr)
        return 2
    given = {k: getattr(args, k) for k in ("steps", "hypotheses", "precision", "score_threshold") if getattr(args, k) is not None}
    given["refine"] = args.refine == "on"
    settings = ValidationSettings(**given)
    try:
        report = validate(args.checkpoint or SHIPPED_ESTIMATOR, args.data, args.models, settings, plots=Path(args.out) / "plots")
    except CheckpointError as err:
        print(f"axispose validate: {err}", file=sys.stderr)
        return 2
    write_report(report, Path(args.out) / "validation.json")
    print(format_validation(report))
    print(f"report: {Path(args.out) / 'validation.json'}")
    return 0


def _bop_targets(args: argparse.Namespace) -> tuple[dict | None, str | None]:
    """The BOP targets to evaluate: --targets, else a test_targets_bop19.json in --data or the folder above it
    (where BOP keeps it beside the split), else none; with the file's path."""
    from axispose_core.data.bop import load_test_targets

    if args.targets:
        path = Path(args.targets)
    else:
        data = Path(args.data)
        path = next((d / TARGETS_FILE for d in (data, data.parent) if (d / TARGETS_FILE).exists()), None)
    return (load_test_targets(path), str(path)) if path is not None else (None, None)


def _report(args: argparse.Namespace, records, objects, config: dict, counts: dict | None, bop: list) -> int:
    """Write, print and plot an eval's results."""
    from axispose_core.data.bop import write_bop_results
    from axispose_core.evaluate import (
        CHI2_3,
        UNCERTAINTY,
        format_average_recall,
        format_table,
        plot_cdfs,
        plot_grid,
        plot_uncertainty,
        summarize,
        write_report,
    )

    report = summarize(records, objects, config, counts, bop)
    write_report(report, args.report)
    print(format_table(report))
    print(format_average_recall(report["bop19"]))
    if config.get("targets"):
        print(f"BOP targets: {config['targets']}")
    if args.bop_results:
        write_bop_results(args.bop_results, [e for image in bop for e in image.estimates])
        print(f"BOP results: {args.bop_results}")
    if config.get("visibility_estimated_scenes"):
        print(
            f"visibility estimated from the models (no scene_gt_info.json) in scene(s) {', '.join(config['visibility_estimated_scenes'])}"
        )
    if config.get("gt_rotations_projected"):
        print(f"{config['gt_rotations_projected']} GT rotations were not orthonormal and were projected to the nearest rotation")
    for name in (n for n in UNCERTAINTY if n in report):
        q = report[name]
        print(f"{name} vs rotation error: Spearman {q['spearman_vs_rot_err']:.2f}; Reproj@15px {q['reproj_15px_all_posed']:.3f} "
              f"for all posed, {q['reproj_15px_least_half']:.3f} for the least uncertain half")  # fmt: skip
    if "calibration" in report:
        q = report["calibration"]
        print(f"covariance calibration ({q['n']} posed, symmetric objects left out; a right one gives {CHI2_3['median']:.2f}, 0.68, 0.95): "
              + "; ".join(f"{part} median d² {q[f'{part}_median_d2']:.2f}, within 68 / 95 % {q[f'{part}_within_68']:.2f} / "
                          f"{q[f'{part}_within_95']:.2f}" for part in ("translation", "rotation")))  # fmt: skip
    if args.plots:
        plots = [plot_cdfs(records, objects, args.plots), plot_grid(records, objects, args.models, args.plots)]
        plots += [plot_uncertainty(records, args.plots, key) for key in UNCERTAINTY.values()]
        print("plots: " + ", ".join(str(p) for p in plots if p))
    print(f"report: {args.report}")
    return 0


def _training_args(
    parser: argparse.ArgumentParser,
    what: str,
    config_cls: str,
    example: str,
    data_help: str | None = None,
    data: bool = True,
    stream: bool = False,
) -> None:
    """The options every trainer shares (data, output, config, resume, device, time cap, threads); `data_help`
    makes --data optional, `data` False leaves out --data and --val, `stream` adds the crop stream's --models."""
    if data:
        parser.add_argument(
            "--data", nargs="+", required=data_help is None, help=data_help or "BOP dataset folders written by `axispose synth`"
        )
        parser.add_argument("--val", nargs="*", default=None, help="held-out BOP folders for periodic validation")
    parser.add_argument("--out", required=True, help=f"{what} to write (.safetensors); OUT.state.pt holds the resume state")
    parser.add_argument("--config", help=f"YAML with {config_cls} fields (e.g. {example})")
    parser.add_argument("--resume", help="OUT.state.pt of an earlier run with the same config "
                        "(optim.steps, save_every, val_every may differ: a longer run extends it)")  # fmt: skip
    parser.add_argument("--device", default="auto", choices=["cpu", "cuda", "auto"])
    parser.add_argument("--max-minutes", type=float, default=None, help="stop (and save) after this much wall time")
    parser.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                        help="stop (and save) at this step, the schedule unchanged: equal-compute comparisons")  # fmt: skip
    parser.add_argument("--threads", type=int, default=2)
    if stream:
        help = "BOP models folder the crop stream renders (default: ../shared/data/lmo/models beside the clone)"
        parser.add_argument("--models", default=str(SHARED_LMO / "models"), help=help)


def _crop_sources(args: argparse.Namespace):
    """A crop trainer's --data, --val and --models."""
    from axispose_core.train.sources import CropSources

    return CropSources(tuple(args.data or ()), tuple(args.val or ()), args.models)


def _run_options(args: argparse.Namespace):
    """How this call of a trainer runs, from the options `_training_args` declares."""
    from axispose_core.train.loop import RunOptions

    return RunOptions(resume=args.resume, device=args.device, max_minutes=args.max_minutes, stop_at=args.stop_at)


def object_ids(text: str) -> list[int]:
    """The argparse type of `--objects`: comma-separated object ids (the ROS commands' too)."""
    return [int(v) for v in text.split(",") if v.strip()]


AddParser = Callable[..., argparse.ArgumentParser]
"""`add_parser` of the subcommands: what `build_parser`'s `commands` gets to add commands with."""


def build_parser(commands: Callable[[AddParser], None] | None = None) -> argparse.ArgumentParser:
    """The core's commands, then those `commands` adds (the ROS ones, `axispose_ros.cli`) with the same parser."""
    parser = argparse.ArgumentParser(prog="axispose", description="AxisPose: 6D object pose from one RGB image by axis generation.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="geometry demo on embedded defaults: axis image -> keypoints -> pose")
    demo.add_argument("--out", default="out/demo", help="folder for the contact sheet")
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(func=_demo)

    tr = sub.add_parser("train-reader", help="train the TBM keypoint reader on rendered, degraded axis images")
    _training_args(tr, "keypoint reader", "ReaderTrainConfig", "reader: {size: 64}", data=False)
    tr.set_defaults(func=_train_reader)

    sy = sub.add_parser("synth", help="render randomised BOP-format training scenes of the objects in --models")
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

    tn = sub.add_parser("train", help="train the AGM (axis generation) on the crop stream, or on BOP folders")
    _training_args(tn, "estimator checkpoint", "TrainConfig", "config/train_agm.yaml",
                   data_help="BOP folders to train on instead of the crop stream (e.g. a user's own frames)", stream=True)  # fmt: skip
    tn.add_argument("--init", help="estimator checkpoint to start from (its weights; a fresh optimiser and schedule), e.g. the "
                    "shipped model: the same AGM network, one whose encoder has more blocks per stage "
                    "(they start as the identity), or one on another trunk (the rest that fits is taken)")  # fmt: skip
    tn.add_argument("--recipe", help="a recipe (e.g. config/recipes/axispose_lmo.yaml): run all its stages into the folder "
                    "--out (resuming where a call stopped) and assemble its estimator checkpoint there")  # fmt: skip
    tn.add_argument("--adopt", nargs="*", default=[], metavar="STAGE=CHECKPOINT",
                    help="with --recipe: an existing checkpoint stands in for a stage (recorded as adopted)")  # fmt: skip
    tn.set_defaults(func=_train)

    td = sub.add_parser("train-localiser", help="train the 2D localiser (CenterNet) on synthetic BOP frames")
    _training_args(td, "localiser checkpoint", "LocaliserTrainConfig", "config/train_localiser.yaml")
    td.add_argument("--attach", help="estimator checkpoint to add the trained localiser to (rewritten in place)")
    td.add_argument("--init", help="trained localiser or estimator checkpoint to start from: weights whose names and shapes "
                    "match are copied (a wider/deeper localiser or other objects keep the rest fresh)")  # fmt: skip
    td.set_defaults(func=_train_localiser)

    tr = sub.add_parser("train-direct", help="train the direct-regression baseline (keypoints from the crop, no diffusion)")
    _training_args(tr, "regressor checkpoint", "DirectTrainConfig", "config/train_direct.yaml",
                   data_help="BOP folders to train on instead of the crop stream", stream=True)  # fmt: skip
    tr.set_defaults(func=_train_direct)

    fv = sub.add_parser("fit-verifier", help="fit the detection verifier (rescoring by the pose's variances) on synthetic frames")
    fv.add_argument("--checkpoint", required=True, help="estimator checkpoint with a localiser")
    fv.add_argument("--data", nargs="+", required=True, help="synthetic BOP folders (never the real validation frames)")
    fv.add_argument("--out", required=True, help="the checkpoint with the verifier (may be --checkpoint)")
    fv.add_argument("--min-score", type=float, default=0.2, help="least localiser score of a detection posed and rescored")
    fv.add_argument("--steps", type=int, default=3, help="DDIM steps per pose (the node's default)")
    fv.add_argument("--threads", type=int, default=2)
    fv.set_defaults(func=_fit_verifier)

    ev = sub.add_parser("eval", help="pose metrics of a checkpoint on BOP scenes (JSON report, plots)")
    ev.add_argument("--checkpoint", required=True)
    ev.add_argument("--data", required=True, help="a BOP split folder of scenes, or one scene folder")
    ev.add_argument("--models", required=True, help="models for the metrics (BOP models_eval folder)")
    ev.add_argument("--objects", type=object_ids, default=[], help="comma-separated object ids (default: all the checkpoint knows)")
    ev.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the checkpoint's)")
    ev.add_argument("--guidance", type=float, default=None, help="run-time guidance scale (0: off)")
    ev.add_argument(
        "--crops",
        choices=["gt", "detect"],
        default="gt",
        help="gt: square around the GT box (the paper's protocol); detect: the localiser's",
    )
    ev.add_argument("--hypotheses", type=int, default=1, help="AGM samples per instance; >= 2: consensus pose and spread")
    ev.add_argument("--mode-sample", action=argparse.BooleanOptionalAction, default=None,
                    help="start hypothesis 0 from the prior's mode, x_T = 0 (default: the checkpoint's setting)")  # fmt: skip
    ev.add_argument("--visib", type=float, nargs=2, default=[0.1, 1.0], metavar=("LO", "HI"),
                    help="visibility band of the instances scored (heavy occlusion: 0.1 0.5)")  # fmt: skip
    ev.add_argument("--perturb", choices=["low_light", "motion_blur"], default=None, help="degrade every frame (stress test)")
    ev.add_argument("--limit", type=int, default=None, help="stop after this many instances")
    ev.add_argument("--report", required=True, help="JSON to write")
    ev.add_argument("--plots", default=None, help="folder for error CDFs")
    ev.add_argument("--bop-results", default=None, metavar="CSV", help="also write the poses as a BOP19 results file "
                    "(name it METHOD_DATASET-SPLIT.csv, e.g. axispose_lmo-test.csv, for bop_toolkit's scripts)")  # fmt: skip
    ev.add_argument("--targets", default=None, help=f"BOP targets file (default: {TARGETS_FILE} in --data or the folder above, if any)")
    ev.add_argument("--refine", choices=["on", "off"], default="on", help="contour refinement where the checkpoint carries a "
                    "refiner (the report also scores the poses before it)")  # fmt: skip
    ev.add_argument("--threads", type=int, default=2)
    ev.add_argument("--precision", choices=["auto", "float32", "bfloat16"], default="float32",
                    help="the AGM's arithmetic (auto: bfloat16 where the device has it natively, as the node does)")  # fmt: skip
    ev.set_defaults(func=_eval)

    va = sub.add_parser("validate", help="a checkpoint on real frames: GT crops and the localiser's, per object (default: "
                        "the real validation slice)")  # fmt: skip
    va.add_argument("--checkpoint", help="estimator checkpoint (default: the shipped one)")
    va.add_argument("--data", default=str(REAL_SLICE), help="BOP split folder (default: ../shared/data/lmo_real_val/test)")
    va.add_argument("--models", default=str(SHARED_LMO / "models_eval"), help="models for the metrics and visibility")
    va.add_argument("--out", default="out/validate", help="folder for validation.json and plots/")
    # Unset options take ValidationSettings' defaults: the node's.
    va.add_argument("--steps", type=int, help="DDIM steps (default: the node's, 3)")
    va.add_argument("--hypotheses", type=int, help="AGM samples per instance (default: the node's, 1)")
    va.add_argument("--score-threshold", type=float, help="least localiser score (default: the node's, 0.3)")
    va.add_argument("--precision", choices=["float32", "bfloat16", "auto"], help="the AGM's arithmetic (default: float32)")
    va.add_argument("--refine", choices=["on", "off"], default="on", help="contour refinement where the checkpoint carries a "
                    "refiner (the report also gives the poses before it)")  # fmt: skip
    va.add_argument("--threads", type=int, default=2)
    va.set_defaults(func=_validate)

    gi = sub.add_parser("gt-info", help="write scene_gt_info.json (boxes, visible fractions) of BOP scenes that lack it, from the models")
    gi.add_argument("scenes", nargs="+", help="BOP scene folders, or folders of scenes")
    gi.add_argument("--models", required=True, help="the objects' BOP models folder")
    gi.add_argument("--overwrite", action="store_true", help="also replace existing scene_gt_info.json files")
    gi.set_defaults(func=_gt_info)

    sp = sub.add_parser("synth-preview", help="contact sheet of synthetic frames with their GT axes")
    sp.add_argument("data", help="dataset folder written by `axispose synth`")
    sp.add_argument("--out", required=True, help="PNG to write")
    sp.add_argument("--count", type=int, default=16)
    sp.add_argument("--tile-width", type=int, default=320, help="width of each frame in the sheet (px)")
    sp.set_defaults(func=_synth_preview)

    st = sub.add_parser("stream-preview", help="contact sheet of crop-stream samples (AGM training crops) with their GT axes")
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
    if commands is not None:
        commands(sub.add_parser)
    return parser


def main(argv: Sequence[str] | None = None, parser: argparse.ArgumentParser | None = None) -> int:
    """Run the command `argv` names with `parser`'s commands (default: the core's)."""
    args = (parser or build_parser()).parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
