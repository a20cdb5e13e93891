"""What a tracker's output over a camera stream is judged by besides accuracy and jitter: whether it drifts (its
accuracy at the stream's end against its start) and how soon it finds an object again that left the view or was
hidden (frames from the object's return to its first right pose).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Seen:
    """One GT instance on one frame: how visible (`visibility`), and whether its pose passed."""

    frame: int
    obj_id: int
    visib: float
    add: float
    rp15: float


def visibility(visib_fract: float, K: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray, size: tuple[int, int]) -> float:
    """The share of an object the camera sees: BOP's `visib_fract` (visible pixels of its mask), which counts only
    the part inside the image, times the share of its model points (N x 3, m) that project inside the image of
    `size` (height, width), so that an object coming in at the border is not seen whole from its first pixel."""
    cam = points @ np.asarray(R, float).T + np.asarray(t, float).reshape(1, 3)
    front = cam[:, 2] > 1e-6
    uv = cam[front] @ np.asarray(K, float).T
    uv = uv[:, :2] / uv[:, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < size[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[0])
    return float(visib_fract) * float(inside.sum()) / max(len(points), 1)


def drift(rows: list[Seen], window: int = 100) -> dict[str, float]:
    """ADD(-S)@0.1d over the instances of the first and of the last `window` frames: a tracker that drifts loses
    along the stream what posing each frame afresh keeps."""
    if not rows:
        return {"add_first": float("nan"), "add_last": float("nan")}
    last = max(r.frame for r in rows)
    first = [r.add for r in rows if r.frame < window]
    end = [r.add for r in rows if r.frame > last - window]
    return {"add_first": float(np.mean(first)), "add_last": float(np.mean(end))}


def recovery(rows: list[Seen], gone: float = 0.1, back: float = 0.5, away: int = 5) -> dict[str, float | int]:
    """Frames from an object's return (visible at least `back` after at least `away` frames below `gone` or not
    annotated: it left the view or something passed in front of it) to its first pose within Reproj@15px: the
    median, the share within 5 frames, and how many returns (a return never posed right counts the frames left)."""
    by_obj: dict[int, list[Seen]] = {}
    for r in sorted(rows, key=lambda r: r.frame):
        by_obj.setdefault(r.obj_id, []).append(r)
    waits = []
    for seq in by_obj.values():
        hidden, previous = 0, seq[0].frame - 1
        for i, r in enumerate(seq):
            hidden, previous = hidden + r.frame - previous - 1, r.frame  # frames it was not annotated on: out of view
            if r.visib < gone:
                hidden += 1
                continue
            if r.visib >= back and hidden >= away:
                waits.append(next((s.frame - r.frame for s in seq[i:] if s.rp15), seq[-1].frame - r.frame + 1))
            hidden = 0 if r.visib >= back else hidden
    nan = float("nan")
    return {"returns": len(waits), "recovery_median": float(np.median(waits)) if waits else nan,
            "recovered_in_5": float(np.mean(np.array(waits) <= 5)) if waits else nan}  # fmt: skip
