"""What the TBM reads off an axis image: the projected origin and the three axis endpoints, in patch pixels."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class AxisKeypoints(NamedTuple):
    """Origin (2,) and endpoints of X, Y, Z (3,2) in pixels; ok False (with a reason) when the image is unreadable."""

    origin: np.ndarray
    endpoints: np.ndarray
    ok: bool = True
    reason: str = ""

    @property
    def array(self) -> np.ndarray:
        """(4,2): origin then the X, Y, Z endpoints, the layout `axis_keypoints` returns."""
        return np.vstack([self.origin[None], self.endpoints])


def unreadable(reason: str) -> AxisKeypoints:
    return AxisKeypoints(np.full(2, np.nan), np.full((3, 2), np.nan), False, reason)
