"""`axispose eval` (pose metrics of a checkpoint on BOP scenes: report, tables, plots) and `axispose validate`
(a checkpoint on real frames, GT crops and the localiser's side by side)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from axispose_core.command_args import AddParser, object_ids
from axispose_core.lmo import REAL_SLICE, SHARED_LMO
from axispose_core.tracking.mode import Mode

if TYPE_CHECKING:
    from axispose_core.bop19 import ImageErrors
    from axispose_core.evaluation.records import Record
    from axispose_core.objects import ObjectSpec

TARGETS_FILE = "test_targets_bop19.json"


def _eval(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.baseline.direct import KIND as DIRECT_KIND
    from axispose_core.baseline.direct import DirectEstimator
    from axispose_core.checkpoint import read_metadata
    from axispose_core.data.bop import BopFormatError
    from axispose_core.estimator import EstimateOptions, Estimator
    from axispose_core.evaluation.records import Prediction
    from axispose_core.evaluation.run import EvalOptions, estimator_runs, evaluate
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
    from axispose_core.evaluation.report import write_report
    from axispose_core.validation import ValidationSettings, format_validation, validate

    torch.set_num_threads(args.threads)
    if not Path(args.data).is_dir():
        print(f"axispose validate: no BOP scenes at {args.data}", file=sys.stderr)
        return 2
    given = {k: getattr(args, k) for k in ("steps", "hypotheses", "precision", "score_threshold", "mode") if getattr(args, k) is not None}
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


def _report(
    args: argparse.Namespace,
    records: list[Record],
    objects: list[ObjectSpec],
    config: dict,
    counts: dict | None,
    bop: list[ImageErrors],
) -> int:
    """Write, print and plot an eval's results."""
    from axispose_core.data.bop_results import write_bop_results
    from axispose_core.evaluation.report import format_average_recall, format_table, plot_cdfs, plot_grid, plot_uncertainty, write_report
    from axispose_core.evaluation.summary import CHI2_3, UNCERTAINTY, summarize

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


def add_eval(add_parser: AddParser) -> None:
    """`axispose eval`."""
    ev = add_parser("eval", help="pose metrics of a checkpoint on BOP scenes (JSON report, plots)")
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


def add_validate(add_parser: AddParser) -> None:
    """`axispose validate`."""
    va = add_parser("validate", help="a checkpoint on real frames: GT crops and the localiser's, per object (default: "
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
    va.add_argument("--mode", choices=[m.value for m in Mode], help="how the localiser's pass treats each scene's frames, "
                    "as the node's mode parameter (default: stills, each frame on its own; GT crops: always so)")  # fmt: skip
    va.add_argument("--threads", type=int, default=2)
    va.set_defaults(func=_validate)
