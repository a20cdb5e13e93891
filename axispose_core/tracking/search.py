"""The search: when the localiser runs over a tracked stream, and what its detections do to the tracks.

A tracked object's crop comes from its predicted pose (`tracks`), so the localiser runs only every
`redetect_period` frames, while nothing is tracked, or after a track missed a frame or ended (but not when the
localiser itself stopped finding it); its detections then refresh the tracks' boxes (matched by object and
nearness) and start tracks for new objects. With following, a detection of a followed track is that track's, and
the AGM poses it only to check a track whose contour agrees less than `check_below` (`follow.Following.check`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from axispose_core.tracking.config import TrackingConfig
from axispose_core.tracking.follow import agreement
from axispose_core.tracking.tracks import Box, Crop, Detected, Measurement, Sighting, Track, Tracks


def detection_due(book: Tracks, following: bool = False) -> bool:
    """The localiser's turn: every period, with no tracks, after a track ended, while a track misses (without
    following, where it is posed in its predicted box anyway) or where a contour was lost (following)."""
    period = max(1, book.config.redetect_period)
    missing = any(tr.lost for tr in book.tracks) if following else any(tr.misses > 0 for tr in book.tracks)
    due = book.look or not book.tracks or book.frame % period == 0 or missing
    book.look = False
    return due


def with_detections(book: Tracks, crops: list[Crop], detections: Sequence[Detected], followed: list[Track], K: np.ndarray) -> list[Crop]:
    """A detection near a track its contour followed on this frame is that track's (posed only to check it:
    `_check_crops`); each other refreshes the box of the nearest track of its object (`match_iou`,
    `match_distance`) or becomes a new crop; a track no detection found is unseen once more (`max_unseen`)."""
    config = book.config
    detections, found = list(detections), []
    for tr in followed:
        box = book.predicted_box(tr, K)
        near = [(d, j) for j, det in enumerate(detections) if det.obj_id == tr.obj_id and (d := _match(config, box, det.box)) is not None]
        tr.unseen = 0 if near else tr.unseen + 1
        if near:
            found.append((tr, detections.pop(min(near)[1])))
    checks = _check_crops(book, found)
    crops = list(crops)
    pairs = sorted((d, i, j) for i, c in enumerate(crops) for j, det in enumerate(detections)
                   if c.obj_id == det.obj_id and (d := _match(config, c.box, det.box)) is not None)  # fmt: skip
    taken_c, taken_d = set(), set()
    for _, i, j in pairs:
        if i in taken_c or j in taken_d:
            continue
        taken_c.add(i)
        taken_d.add(j)
        d = detections[j]
        crops[i] = Crop(d.obj_id, tuple(d.box), d.score, crops[i].track, _posed(d), detected=True)
    for i, c in enumerate(crops):
        tr = book.track(c.track)
        tr.unseen = 0 if i in taken_c else tr.unseen + 1
    new = [d for j, d in enumerate(detections) if j not in taken_d]
    return crops + [Crop(d.obj_id, tuple(d.box), d.score, measurement=_posed(d), detected=True) for d in new] + checks


def _check_crops(book: Tracks, found: list[tuple[Track, Detected]]) -> list[Crop]:
    """Of the followed tracks the localiser found, with their detections, the one checked longest ago among
    those whose contour agrees less than `check_below`: its detection's crop, to be posed by the AGM
    (`Following.check`)."""
    doubtful = [(tr, d) for tr, d in found if agreement(tr.last, -np.inf) < book.config.check_below]
    if not doubtful:
        return []
    tr, d = min(doubtful, key=lambda f: (f[0].checked, f[0].id))
    tr.checked = book.frame
    return [Crop(d.obj_id, tuple(d.box), d.score, detected=True, checks=tr.id)]


def unfound_dropped(book: Tracks, crops: list[Crop]) -> list[Crop]:
    """The crops but those of tracks whose contour was lost and that no detection found: where the contour
    lost its object its predicted box is no place to pose it, and the track ends (the localiser's period finds
    the object again when it is back)."""
    unfound = {c.track for c in crops if (tr := book.track(c.track)) is not None and tr.lost and not c.detected}
    book.end("unfound", lambda tr: tr.id in unfound, look=False)
    return [c for c in crops if c.track not in unfound]


def _match(config: TrackingConfig, a: Box, b: Box) -> float | None:
    """How far detection box `b` is from track box `a` (centre distance over the larger diagonal); None when
    they do not match."""
    diag = max(np.hypot(a[2], a[3]), np.hypot(b[2], b[3]), 1e-9)
    dist = float(np.hypot(a[0] + a[2] / 2 - b[0] - b[2] / 2, a[1] + a[3] / 2 - b[1] - b[3] / 2)) / diag
    return dist if dist <= config.match_distance or _iou(a, b) >= config.match_iou else None


def _iou(a: Box, b: Box) -> float:
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def _posed(d: Detected) -> Measurement | None:
    """The pose a `Sighting` brings (None: the detection is to be posed)."""
    return d.measurement if isinstance(d, Sighting) else None
