"""Pseudo-poses: what the estimator itself finds on each frame of a recording (localiser, AGM, contour refinement,
verifier), every detection kept with its evidence, and which of them that evidence accepts on its own.

Nothing here knows a label: a pose is accepted by its verifier score and its contour's agreement with the image,
thresholds chosen on rendered recordings (`AcceptConfig`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from axispose_core.adapt.recording import Frame
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.rotation import nearest_rotation


@dataclass(frozen=True)
class Candidate:
    """One pose the estimator gave on a frame, with its evidence: the published score (the verifier's probability),
    whether the contour refiner moved it, the share of its contour lines usable and their agreement with the image
    (NaN unrefined); `box` the localiser's (x, y, w, h)."""

    im_id: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    score: float
    refined: bool
    lines: float
    agreement: float
    box: tuple[float, float, float, float]

    def to_json(self) -> dict:
        d = asdict(self)
        d.update(R=self.R.ravel().tolist(), t=self.t.tolist(), box=list(self.box))
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    @classmethod
    def from_json(cls, d: dict) -> Candidate:
        nan = float("nan")
        return cls(int(d["im_id"]), int(d["obj_id"]), nearest_rotation(np.asarray(d["R"], float).reshape(3, 3)),
                   np.asarray(d["t"], float), float(d["score"]), bool(d["refined"]),
                   nan if d["lines"] is None else float(d["lines"]), nan if d["agreement"] is None else float(d["agreement"]),
                   tuple(float(v) for v in d["box"]))  # fmt: skip


@dataclass(frozen=True)
class AcceptConfig:
    """The evidence a pose needs to be taken on its own (without another frame agreeing): refined by the contours,
    its verifier score, its contour's agreement and the share of its lines usable at least these."""

    min_score: float = 0.5
    min_agreement: float = 0.75
    min_lines: float = 0.0

    def accepts(self, c: Candidate) -> bool:
        return c.refined and c.score >= self.min_score and c.agreement >= self.min_agreement and c.lines >= self.min_lines


@dataclass(frozen=True)
class PoseSettings:
    """How the recording's frames are posed: the localiser's detections down to `threshold` (the verifier's
    probability), with `steps` DDIM steps and `hypotheses` samples per detection, contours refined."""

    threshold: float = 0.2
    steps: int = 3
    hypotheses: int = 1

    def options(self) -> EstimateOptions:
        return EstimateOptions(steps=self.steps, hypotheses=self.hypotheses, refine=True)


def pose_frame(est: Estimator, frame: Frame, settings: PoseSettings) -> list[Candidate]:
    """Every detection of the frame at `settings.threshold`, posed, as candidates (poses that failed left out)."""
    found = est.find(frame.rgb(), frame.K, threshold=settings.threshold, options=settings.options())
    return [Candidate(frame.im_id, d.obj_id, p.R, p.t, float(d.score), bool(p.refined), float(p.contour_lines),
                      float(p.contour_agreement), tuple(float(v) for v in d.box))
            for d, p in zip(found.detections, found.poses, strict=True) if p.ok]  # fmt: skip


def pose_frames(
    est: Estimator, frames: Iterable[Frame], settings: PoseSettings, log: Path, progress: Callable[[int, int], None] | None = None
) -> dict[int, list[Candidate]]:
    """Every frame's candidates; each frame's are appended to `log` (JSON lines) as it is posed, and the frames
    `log` already holds are read from it, not posed again: an interrupted run goes on where it stopped."""
    done = read_candidates(log)
    if log.exists():  # rewritten whole: a line an interruption cut off is not continued by the next
        log.write_text("".join(json.dumps(_entry(i, cs)) + "\n" for i, cs in done.items()))
    frames = list(frames)
    with open(log, "a") as out:
        for k, frame in enumerate(frames):
            if frame.im_id not in done:
                done[frame.im_id] = pose_frame(est, frame, settings)
                out.write(json.dumps(_entry(frame.im_id, done[frame.im_id])) + "\n")
                out.flush()
            if progress is not None:
                progress(k + 1, len(frames))
    return {f.im_id: done[f.im_id] for f in frames}


def _entry(im_id: int, candidates: list[Candidate]) -> dict:
    return {"im_id": im_id, "candidates": [c.to_json() for c in candidates]}


def read_candidates(log: Path) -> dict[int, list[Candidate]]:
    """The frames' candidates a `pose_frames` log holds; a last line cut off by an interruption is ignored."""
    out: dict[int, list[Candidate]] = {}
    if not log.exists():
        return out
    for line in log.read_text().splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        out[int(entry["im_id"])] = [Candidate.from_json(c) for c in entry["candidates"]]
    return out
