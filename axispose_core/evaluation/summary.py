"""The report of an evaluation's records: per object and over objects (`summarize`), pooled over instances,
what contour refinement changed, depth errors, and whether the reported uncertainties match the errors."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np

from axispose_core.bop19 import ImageErrors, average_recall
from axispose_core.evaluation.records import SUMMARY_KEYS, Record
from axispose_core.metrics import mahalanobis_sq
from axispose_core.objects import ObjectSpec


def summarize(
    records: list[Record],
    objects: list[ObjectSpec],
    config: dict,
    detection_counts: dict[int, dict[str, int]] | None = None,
    bop: list[ImageErrors] | None = None,
) -> dict:
    """The report JSON: per object, mean over objects, latency, config; detection precision/recall when given;
    BOP19 average recall (`bop19`: overall and per object) from `bop`'s image errors."""
    per: dict[str, dict[str, float]] = {}
    for o in objects:
        rs = [r for r in records if r.obj_id == o.obj_id]
        if not rs:
            continue
        entry = {"n": len(rs), "name": o.name}
        for k in SUMMARY_KEYS:
            entry[k] = float(np.mean([r.scores[k] for r in rs]))
        entry["rot_err_median_deg"] = float(np.median([r.scores["rot_err_deg"] for r in rs]))
        entry["trans_err_median_mm"] = float(np.median([r.scores["trans_err_mm"] for r in rs]))
        entry |= depth_errors(rs)
        if (refine := refinement_summary(rs)) is not None:
            entry["refine"] = refine
        if detection_counts is not None:
            c = detection_counts.get(o.obj_id, {"tp": 0, "fp": 0, "n": 0})
            entry["det_recall"] = c["tp"] / c["n"] if c["n"] else float("nan")
            entry["det_precision"] = c["tp"] / (c["tp"] + c["fp"]) if c["tp"] + c["fp"] else float("nan")
        per[str(o.obj_id)] = entry
    keys = [*SUMMARY_KEYS, "rot_err_median_deg", "trans_err_median_mm", *DEPTH_KEYS] + (
        ["det_recall", "det_precision"] if detection_counts is not None else []
    )
    mean = {k: _mean_of_defined([e[k] for e in per.values()]) for k in keys} if per else {}
    refined = [e["refine"] for e in per.values() if "refine" in e]
    if refined:  # an object the refiner never saw counts as it is
        before = [e["refine"]["unrefined"] if "refine" in e else e for e in per.values()]
        mean["refine"] = {"unrefined": {k: _mean_of_defined([b[k] for b in before]) for k in refined[0]["unrefined"]},
                          "refined": sum(r["refined"] for r in refined),
                          "kept": dict(sum((Counter(r["kept"]) for r in refined), Counter()))}  # fmt: skip
    ms = np.array([1000 * r.seconds for r in records]) if records else np.zeros(1)
    report = {
        "objects": per,
        "mean": mean,
        "instances": pooled(records) | ({"unrefined": pooled(unrefined_records(records))} if refined else {}),
        "ms_per_object": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90))},
        "config": config,
    }
    if bop is not None:
        ar = average_recall(bop)
        names = {o.obj_id: o.name for o in objects}
        ar["objects"] = {str(i): {"name": names.get(i, str(i))} | e for i, e in ar["objects"].items()}
        report["bop19"] = ar
    measures = {name: q for name, key in UNCERTAINTY.items() if (q := uncertainty_quality(records, key))}
    calibration = covariance_calibration(records, objects)
    return report | measures | ({"calibration": calibration} if calibration else {})


def _mean_of_defined(values: list[float]) -> float:
    """The mean over the objects where a measure is defined (an object never posed has no depth error), NaN if none."""
    defined = [v for v in values if not np.isnan(v)]
    return float(np.mean(defined)) if defined else float("nan")


REFINE_KEYS = ("add_0.1d", "reproj_15px")


def unrefined_records(records: list[Record]) -> list[Record]:
    """The records with each pose the refiner saw as it was before refinement."""
    return [dataclasses.replace(r, R=r.unrefined[0], t=r.unrefined[1], scores=r.unrefined_scores)
            if r.unrefined is not None and r.unrefined_scores is not None else r for r in records]  # fmt: skip


def pooled(records: list[Record]) -> dict[str, float]:
    """Over all instances at once rather than per object: the median rotation error and the mean |log| depth error
    of the posed ones (what one bad object's median hides), and ADD(-S)@0.1d and Reproj@15px."""
    return {"n": len(records), "rot_err_median_deg": float(np.median([r.scores["rot_err_deg"] for r in records])) if records else np.nan,
            "depth_log_abs_mean": depth_errors(records)["depth_log_abs_mean"],
            **{k: float(np.mean([r.scores[k] for r in records])) if records else float("nan") for k in REFINE_KEYS}}  # fmt: skip


def refinement_summary(records: list[Record]) -> dict | None:
    """What contour refinement changed in one object's records: how many poses it refined and kept (by reason), and
    the scores of all its records with each pose as it was before refinement (`unrefined`: ADD(-S)@0.1d,
    Reproj@15px, median rotation error, depth; the instances it did not see, unposed ones among them, as they are),
    to set beside the report's own. None where the refiner saw none of them."""
    seen = [r for r in records if r.unrefined is not None and r.unrefined_scores is not None]
    if not seen:
        return None
    before = unrefined_records(records)
    unrefined = {k: float(np.mean([r.scores[k] for r in before])) for k in REFINE_KEYS}
    unrefined["rot_err_median_deg"] = float(np.median([r.scores["rot_err_deg"] for r in before]))
    unrefined |= depth_errors(before)
    kept = Counter(r.refine_kept for r in seen if r.refine_kept)
    return {"n": len(seen), "refined": len(seen) - sum(kept.values()), "kept": dict(kept), "unrefined": unrefined}


DEPTH_KEYS = ("depth_log_abs_mean", "depth_ratio_median")


def depth_errors(records: list[Record]) -> dict[str, float]:
    """The posed instances' depth against the truth: the mean |log(z / z_gt)| (its spread, what ADD(-S) at small
    thresholds needs within about 1 %) and the median z / z_gt (its bias); NaN without a posed instance."""
    ratios = np.array([r.t[2] / r.t_gt[2] for r in records if r.ok and r.t[2] > 0 and r.t_gt[2] > 0])
    if not len(ratios):
        return dict.fromkeys(DEPTH_KEYS, float("nan"))
    return {"depth_log_abs_mean": float(np.mean(np.abs(np.log(ratios)))), "depth_ratio_median": float(np.median(ratios))}


CHI2_3 = {"median": 2.366, "68": 3.527, "95": 7.815}
"""Quantiles of χ²(3), the law of a right covariance's squared Mahalanobis lengths of 3D errors."""


def covariance_calibration(records: list[Record], objects: list[ObjectSpec]) -> dict | None:
    """Is the reported covariance the size of the errors? Per part (translation, rotation), the median squared
    Mahalanobis length of the posed instances' errors (`metrics.mahalanobis_sq`; χ²(3)'s median 2.37 if right,
    more where the covariance is too narrow) and the fractions within χ²(3)'s 68 and 95 % quantiles. Symmetric
    objects are left out: their rotation error has no one direction. None without covariances."""
    symmetric = {o.obj_id for o in objects if o.symmetric}
    d2 = np.array([mahalanobis_sq(r.R, r.t, r.R_gt, r.t_gt, r.covariance) for r in records
                   if r.ok and r.covariance is not None and r.obj_id not in symmetric])  # fmt: skip
    if len(d2) < 4:
        return None
    out: dict[str, float] = {"n": len(d2)}
    for k, part in enumerate(("translation", "rotation")):
        out[f"{part}_median_d2"] = float(np.median(d2[:, k]))
        for q in ("68", "95"):
            out[f"{part}_within_{q}"] = float(np.mean(d2[:, k] <= CHI2_3[q]))
    return out


UNCERTAINTY = {"spread": "spread_deg", "sigma": "sigma_deg"}
"""A report's uncertainty measures: the samples' spread and the covariance's rotation sigma, by Record field."""


def posed_with(records: list[Record], key: str) -> tuple[list[Record], np.ndarray]:
    """Records with a pose and a finite `key` (a Record field), and its values."""
    rs = [r for r in records if r.ok and np.isfinite(getattr(r, key))]
    return rs, np.array([getattr(r, key) for r in rs])


def uncertainty_quality(records: list[Record], key: str) -> dict | None:
    """Does an uncertainty (`key`: spread_deg or sigma_deg) predict the error? Its rank correlation with the rotation
    error, and the accuracy of all poses against that of the half with the least uncertainty (None without it)."""
    from scipy.stats import spearmanr

    rs, u = posed_with(records, key)
    if len(rs) < 4:
        return None
    rot = np.array([r.scores["rot_err_deg"] for r in rs])
    half = np.argsort(u, kind="stable")[: len(rs) // 2]
    out: dict[str, float] = {"n": len(rs), "spearman_vs_rot_err": float(spearmanr(u, rot).statistic)}
    for score_key in ("add_0.2d", "reproj_15px"):
        score = np.array([r.scores[score_key] for r in rs])
        out[f"{score_key}_all_posed"] = float(score.mean())
        out[f"{score_key}_least_half"] = float(score[half].mean())
    return out
