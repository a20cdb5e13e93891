"""The estimator's warm-up before the first frame: the first use of each batch shape sets its kernels up, about
50 ms per shape on a CPU, which the first frames with that many objects would otherwise pay."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from axispose_core.agm.sampler import Cancelled
from axispose_core.estimator import EstimateOptions, Estimator
from axispose_core.lmo import LMO_K

BLANK = (480, 640, 3)
"""Shape of the blank frame warmed up on (a VGA camera's)."""
BOX = (280.0, 200.0, 80.0, 90.0)
"""The box (x, y, w, h) of every warm-up instance."""


def warm_up(estimator: Estimator, ids: Sequence[int], count: int, hypotheses: int, cancelled: Callable[[], bool]) -> bool:
    """One pass over a blank frame per box count 1..`count` (1 DDIM step, `hypotheses` samples, objects `ids` in
    turn), and one of the localiser if there is one; the contour refiner's viewpoint models of `ids` built (or read
    from their cache) first, whatever `count`, so that no frame waits for them. False when no pass ran: `count` 0,
    or `cancelled`."""
    if estimator.refiner is not None:
        estimator.refiner.prepare(ids)
    if count == 0:
        return False
    rgb = np.full(BLANK, 127, np.uint8)
    try:
        if estimator.localiser is not None:
            estimator.detect(rgb)
        for k in range(1, count + 1):
            boxes = [(ids[i % len(ids)], BOX) for i in range(k)]
            estimator.estimate(rgb, LMO_K, boxes, options=EstimateOptions(steps=1, hypotheses=hypotheses), cancelled=cancelled)
    except Cancelled:
        return False
    return True
