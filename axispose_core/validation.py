"""Scoring a checkpoint on real camera frames: GT crops and the node's path, side by side, per object.

Renders cannot show how a design transfers to a camera, so every design is also scored on the real validation
slice (`../shared/data/lmo_real_val`: 40 real LM-O frames, validation only). One call runs `evaluate` twice on
the same scenes: with the square around each GT box (the AGM and the TBM alone) and through the checkpoint's
localiser at the node's defaults (what a robot gets): the node's own poser in a `mode` (`stills`: each frame on its
own; the video modes follow each scene's frames in order: `evaluation/node_path.py`). Visibility comes from the
models (the slice ships no `scene_gt_info.json`). The report holds both, with the depth's spread and bias, BOP19
average recall and the covariance's calibration, and `format_validation` prints them as one table.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.evaluation.node_path import NodePath
from axispose_core.evaluation.records import Record
from axispose_core.evaluation.report import plot_cdfs
from axispose_core.evaluation.run import MIN_VISIB, EvalOptions, estimator_runs, evaluate
from axispose_core.evaluation.summary import summarize
from axispose_core.tracking.mode import Mode
from axispose_core.tracking.poser import PoserSettings

CROPS = ("gt", "detect")


@dataclass(frozen=True)
class ValidationSettings:
    """How the estimator runs: the node's defaults (config/axispose.yaml) in float32, a robot's CPU arithmetic."""

    steps: int = 3
    hypotheses: int = 1
    precision: str = "float32"
    score_threshold: float = 0.3
    """Least published score: the verifier's probability where the checkpoint carries one, else the localiser's."""
    visib: tuple[float, float] = (MIN_VISIB, 1.0)
    refine: bool = True
    """Contour refinement where the checkpoint carries a refiner (the report gives the poses before it too)."""
    mode: str = Mode.STILLS.value
    """How the localiser's pass treats the frames (`tracking/mode.py`); GT crops are posed each on its own."""

    def __post_init__(self) -> None:
        Mode.parse(self.mode)

    def poser(self) -> PoserSettings:
        """The node's poser at these settings and the node's others, but with the checkpoint's guidance and each
        frame's boxes in one AGM batch, as `axispose eval` poses them."""
        return PoserSettings(mode=self.mode, ddim_steps=self.steps, hypotheses=self.hypotheses, guidance_scale=None,
                             batch_boxes=None, refine=self.refine, score_threshold=self.score_threshold)  # fmt: skip


def run_crops(
    est: Estimator, crops: str, data: Path, models: Path, settings: ValidationSettings, progress: bool
) -> tuple[list[Record], dict]:
    """One pass over `data` with GT crops or the localiser's (through the node's poser: `NodePath`, what it
    counted under "poser"); the records and the summary report."""
    objects = list(est.config.objects)

    options = EstimateOptions(steps=settings.steps, hypotheses=settings.hypotheses, refine=settings.refine)
    predict, _ = estimator_runs(est, options)
    path = NodePath(est, settings.poser()) if crops == "detect" else None
    try:
        run = evaluate(predict, data, models, objects, EvalOptions(progress=progress, detector=path, visib=settings.visib, bop=True))
    finally:
        if path is not None:
            path.stop()
    report = summarize(run.records, objects, {"crops": crops, **run.notes}, run.detection_counts, run.bop)
    return run.records, report | ({"poser": path.counts} if path is not None else {})


def validate(
    checkpoint: str | Path,
    data: str | Path,
    models: str | Path,
    settings: ValidationSettings,
    plots: str | Path | None = None,
    progress: bool = True,
) -> dict:
    """The checkpoint's report on `data` with GT crops and, where it carries a localiser, the localiser's."""
    est = Estimator.load(checkpoint)
    precision = est.set_precision(settings.precision)
    verifier = None if est.config.verifier is None else asdict(est.config.verifier)
    report: dict = {"config": {"checkpoint": str(checkpoint), "data": str(data), **asdict(settings), "precision": precision,
                               "verifier": verifier}}  # fmt: skip
    for crops in CROPS:
        if crops == "detect" and est.localiser is None:
            continue
        records, report[crops] = run_crops(est, crops, Path(data), Path(models), settings, progress)
        if plots is not None:
            plot_cdfs(records, list(est.config.objects), Path(plots) / crops)
    return report


def format_cell(value: float | None, fmt: str) -> str:
    """A table cell: `value` in `fmt`, "-" where it is missing or NaN."""
    return "-" if value is None or np.isnan(value) else format(value, fmt)


def report_value(report: dict, crops: str, field: str, obj: str = "mean") -> float | None:
    """`field` of one pass (`crops`) of a validation report, for object key `obj` or the mean; None where absent. A
    field "a/b/c" is a nested one (the refinement's "refine/unrefined/add_0.1d")."""
    part = report.get(crops)
    entry = None if part is None else (part["mean"] if obj == "mean" else part["objects"].get(obj))
    for key in field.split("/"):
        entry = entry.get(key) if isinstance(entry, dict) else None
    return entry


COLUMNS = (
    ("det R", "detect", "det_recall", ".2f"),
    ("det P", "detect", "det_precision", ".2f"),
    ("node ADD", "detect", "add_0.1d", ".3f"),
    ("unrefined", "detect", "refine/unrefined/add_0.1d", ".3f"),
    ("node Rp15", "detect", "reproj_15px", ".3f"),
    ("ADD.1d", "gt", "add_0.1d", ".3f"),
    ("unrefined", "gt", "refine/unrefined/add_0.1d", ".3f"),
    ("Rp15", "gt", "reproj_15px", ".3f"),
    ("rot med", "gt", "rot_err_median_deg", ".1f"),
    ("z|log|%", "gt", "depth_log_abs_mean", ".2%"),
    ("z ratio", "gt", "depth_ratio_median", ".3f"),
)
"""The table's columns: header, which pass, report key, format. `node` is the localiser's path; the rest GT crops;
`unrefined`: the ADD(-S) of the same poses before contour refinement (where the checkpoint has a refiner)."""


def _value(report: dict, crops: str, field: str, obj: str) -> float | None:
    """A column's value; an object the refiner never saw (none of it posed) reads as it is in the `unrefined` ones."""
    value = report_value(report, crops, field, obj)
    if value is None and field.startswith("refine/unrefined/") and crops in report and report[crops]["mean"].get("refine"):
        value = report_value(report, crops, field.rsplit("/", 1)[1], obj)
    return value


def _before(pool: dict | None) -> str:
    return "" if pool is None else f"; before refinement {pool['rot_err_median_deg']:.1f}°, {pool['depth_log_abs_mean']:.2%}"


def format_validation(report: dict) -> str:
    """Per object and mean: the localiser, the node's path and the GT-crop pose errors; AR and calibration below."""
    gt = report["gt"]
    names = {k: e["name"] for k, e in gt["objects"].items()}
    head = f"{'object':<12} {'n':>4} " + " ".join(f"{c[0]:>9}" for c in COLUMNS) + f" {'AR gt':>6}"
    lines = [head]
    for key, name in [*names.items(), ("mean", "mean")]:
        cells = [f"{format_cell(_value(report, crops, field, key), fmt):>9}" for _, crops, field, fmt in COLUMNS]
        ar = gt["bop19"]["ar"] if key == "mean" else gt["bop19"]["objects"].get(key, {}).get("ar")
        n = "" if key == "mean" else str(gt["objects"][key]["n"])
        lines.append(f"{name:<12} {n:>4} " + " ".join(cells) + f" {format_cell(ar, '.3f'):>6}")
    for crops in CROPS:
        if crops not in report:
            continue
        ar = report[crops]["bop19"]
        line = f"{crops} crops: AR {ar['ar']:.3f} (MSSD {ar.get('ar_mssd', float('nan')):.3f}, MSPD {ar.get('ar_mspd', float('nan')):.3f})"
        if (cal := report[crops].get("calibration")) is not None:
            line += (f"; covariance median d² translation {cal['translation_median_d2']:.1f}, rotation "
                     f"{cal['rotation_median_d2']:.1f} (right: 2.37)")  # fmt: skip
        lines.append(line)
        pool = report[crops].get("instances", {})
        if pool:
            lines.append(f"{crops} crops, all instances: rotation median {pool['rot_err_median_deg']:.1f}°, depth mean |log| "
                         f"{pool['depth_log_abs_mean']:.2%} (posed ones)" + _before(pool.get("unrefined")))  # fmt: skip
        if (refine := report[crops]["mean"].get("refine")) is not None:
            before = refine["unrefined"]
            kept = ", ".join(f"{k} {v}" for k, v in sorted(refine["kept"].items())) or "none"
            lines.append(f"{crops} crops, contour refinement: {refine['refined']} refined, kept: {kept}; means over objects before "
                         f"it: ADD(-S)@0.1d {before['add_0.1d']:.3f}, Reproj@15px {before['reproj_15px']:.3f}")  # fmt: skip
    c = report["config"]
    scored = " (the verifier's)" if c.get("verifier") else ""
    lines.append(f"{c['steps']} DDIM steps, {c['hypotheses']} hypothesis/es, {c['precision']}, score threshold {c['score_threshold']}"
                 f"{scored}, visib {c['visib'][0]}-{c['visib'][1]}, localiser's pass in mode {c.get('mode', 'stills')}; "
                 "n: GT instances")  # fmt: skip
    return "\n".join(lines)
