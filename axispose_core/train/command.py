"""The training commands: `train` (the AGM, or a whole recipe), `train-localiser`, `train-direct`, `train-reader`
and `fit-verifier`, with the options the trainers share."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from axispose_core.command_args import AddParser
from axispose_core.lmo import SHARED_LMO

if TYPE_CHECKING:
    from axispose_core.train.loop import RunOptions
    from axispose_core.train.sources import CropSources

C = TypeVar("C")


def training_config(cls: type[C], path: str | None) -> C:
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


def _crop_sources(args: argparse.Namespace) -> CropSources:
    """A crop trainer's --data, --val and --models."""
    from axispose_core.train.sources import CropSources

    return CropSources(tuple(args.data or ()), tuple(args.val or ()), args.models)


def _run_options(args: argparse.Namespace) -> RunOptions:
    """How this call of a trainer runs, from the options `_training_args` declares."""
    from axispose_core.train.loop import RunOptions

    return RunOptions(resume=args.resume, device=args.device, max_minutes=args.max_minutes, stop_at=args.stop_at)


def _train_reader(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.train.reader import ReaderTrainConfig, train_reader

    torch.set_num_threads(args.threads)
    cfg = training_config(ReaderTrainConfig, args.config)
    step = train_reader(cfg, args.out, _run_options(args))
    print(f"stopped at step {step} of {cfg.optim.steps}; keypoint reader {args.out}")
    return 0


def _train(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.train.agm import TrainConfig, train_agm

    torch.set_num_threads(args.threads)
    if args.recipe:
        return _train_recipe(args)
    cfg = training_config(TrainConfig, args.config)
    step = train_agm(cfg, _crop_sources(args), args.out, _run_options(args), init=args.init)
    print(f"stopped at step {step} of {cfg.optim.steps}; checkpoint {args.out}")
    return 0


def _train_recipe(args: argparse.Namespace) -> int:
    """`axispose train --recipe FILE --out DIR`: every stage the recipe's checkpoint needs, then the checkpoint."""
    from axispose_core.checkpoint import CheckpointError
    from axispose_core.train.recipe import RecipeError, load_recipe
    from axispose_core.train.recipe_runner import RecipeRunner

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
    cfg = training_config(DirectTrainConfig, args.config)
    step = train_direct(cfg, _crop_sources(args), args.out, _run_options(args))
    print(f"stopped at step {step} of {cfg.optim.steps}; direct-regression baseline {args.out}")
    return 0


def score_and_attach(args: argparse.Namespace) -> int:
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
    cfg = training_config(LocaliserTrainConfig, args.config)
    if not cfg.localiser.obj_ids:  # default: the objects the data shows
        ids = tuple(o.obj_id for o in dataset_objects(args.data))
        cfg = dataclasses.replace(cfg, localiser=dataclasses.replace(cfg.localiser, obj_ids=ids))
    step = train_localiser(cfg, args.data, args.out, args.val, _run_options(args), init=args.init)
    print(f"stopped at step {step} of {cfg.optim.steps}; localiser {args.out}")
    return score_and_attach(args)


def add_train_reader(add_parser: AddParser) -> None:
    """`axispose train-reader`."""
    tr = add_parser("train-reader", help="train the TBM keypoint reader on rendered, degraded axis images")
    _training_args(tr, "keypoint reader", "ReaderTrainConfig", "reader: {size: 64}", data=False)
    tr.set_defaults(func=_train_reader)


def add_train(add_parser: AddParser) -> None:
    """`axispose train`."""
    tn = add_parser("train", help="train the AGM (axis generation) on the crop stream, or on BOP folders")
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


def add_train_localiser(add_parser: AddParser) -> None:
    """`axispose train-localiser`."""
    td = add_parser("train-localiser", help="train the 2D localiser (CenterNet) on synthetic BOP frames")
    _training_args(td, "localiser checkpoint", "LocaliserTrainConfig", "config/train_localiser.yaml")
    td.add_argument("--attach", help="estimator checkpoint to add the trained localiser to (rewritten in place)")
    td.add_argument("--init", help="trained localiser or estimator checkpoint to start from: weights whose names and shapes "
                    "match are copied (a wider/deeper localiser or other objects keep the rest fresh)")  # fmt: skip
    td.set_defaults(func=_train_localiser)


def add_train_direct(add_parser: AddParser) -> None:
    """`axispose train-direct`."""
    tr = add_parser("train-direct", help="train the direct-regression baseline (keypoints from the crop, no diffusion)")
    _training_args(tr, "regressor checkpoint", "DirectTrainConfig", "config/train_direct.yaml",
                   data_help="BOP folders to train on instead of the crop stream", stream=True)  # fmt: skip
    tr.set_defaults(func=_train_direct)


def add_fit_verifier(add_parser: AddParser) -> None:
    """`axispose fit-verifier`."""
    fv = add_parser("fit-verifier", help="fit the detection verifier (rescoring by the pose's variances) on synthetic frames")
    fv.add_argument("--checkpoint", required=True, help="estimator checkpoint with a localiser")
    fv.add_argument("--data", nargs="+", required=True, help="synthetic BOP folders (never the real validation frames)")
    fv.add_argument("--out", required=True, help="the checkpoint with the verifier (may be --checkpoint)")
    fv.add_argument("--min-score", type=float, default=0.2, help="least localiser score of a detection posed and rescored")
    fv.add_argument("--steps", type=int, default=3, help="DDIM steps per pose (the node's default)")
    fv.add_argument("--threads", type=int, default=2)
    fv.set_defaults(func=_fit_verifier)
