"""Each object's measurements in a fixed frame (the camera's pose from odometry): what a moving camera's views of a
still object add up to.

One view sees an object's depth poorly and its position across the line of sight well; views from other directions
pin each other's depth. So a measured pose is published fused with its object's other views in the fixed frame
(positions weighted by their information, rotations by their chordal mean), and an object no track holds can be
looked for where its views put it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class View:
    """One measurement in the fixed frame: pose (R, t), its translation's information (inverse covariance), its depth
    from the camera that made it, the frame it was made on, and what a track recalled from it starts with (the
    measurement, with the colours it learned: kept for an object's latest view only; its box and score)."""

    R: np.ndarray
    t: np.ndarray
    information: np.ndarray
    depth: float
    frame: int
    measurement: object
    box: tuple[float, float, float, float]
    score: float


@dataclass(frozen=True)
class Remembered:
    """An object no track holds, as its latest views put it in the camera's frame (R, t, covariance)."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    latest: View


class ObjectViews:
    """Views per object id; `gate` (translation as a fraction of the depth, rotation in degrees): views further than
    this from a measurement are not the same object at rest (another instance, the object moved, a symmetric twin, a
    wrong pose) and are left out of its fusion. Window and gate are the caller's on each call (its settings may
    change between frames)."""

    def __init__(self) -> None:
        self._views: dict[int, list[View]] = {}

    def forget(self) -> None:
        self._views = {}

    def age(self, frame: int, window: int) -> None:
        """Forget the views made `window` frames or more before `frame`."""
        for obj_id, views in list(self._views.items()):
            kept = [v for v in views if v.frame > frame - window]
            if kept:
                self._views[obj_id] = kept
            else:
                del self._views[obj_id]

    def add(self, obj_id: int, view: View, gate: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, int]:
        """Add a view; its object's views within `gate` of it, fused: (R, t) in the fixed frame, and how many of
        the object's views the gate left out."""
        views = self._views.setdefault(obj_id, [])
        near = _near(views, view, gate) + [view]
        if views:
            views[-1] = replace(views[-1], measurement=None)  # its images and histograms: memory for the latest only
        views.append(view)
        return _mean_rotation(near), _fused_position(near), len(views) - len(near)

    def remembered(self, camera: np.ndarray, frame: int, tracked: set[int], gate: tuple[float, float]) -> list[Remembered]:
        """The objects not in `tracked` (ids) seen before `frame` and not on it, each where its latest view and those
        within `gate` of it put it, in the frame of `camera` (4x4, camera to fixed)."""
        R_wc = camera[:3, :3]
        out = []
        for obj_id, views in self._views.items():
            latest = views[-1]
            if obj_id in tracked or latest.frame >= frame:
                continue
            near = _near(views, latest, gate)
            R, t = in_camera(camera, _mean_rotation(near), _fused_position(near))
            if t[2] <= 0:
                continue
            information = np.sum([v.information for v in near], axis=0)
            covariance = np.zeros((6, 6))
            covariance[:3, :3] = R_wc.T @ np.linalg.pinv(information) @ R_wc
            covariance[3:, 3:] = np.eye(3) * np.deg2rad(gate[1]) ** 2
            out.append(Remembered(obj_id, R, t, covariance, latest))
        return out


def _within(gate: tuple[float, float], Rs: np.ndarray, ts: np.ndarray, R: np.ndarray, t: np.ndarray, depth: float) -> np.ndarray:
    """Which of the poses (Rs N x 3 x 3, ts N x 3) lie within `gate` of (R, t): translation as a fraction of `depth`,
    rotation in degrees."""
    cos = (np.einsum("nij,ij->n", Rs, R) - 1) / 2  # trace(R_n^T R)
    return (np.linalg.norm(ts - t, axis=1) <= gate[0] * depth) & (cos >= np.cos(np.radians(gate[1])))


def _near(views: list[View], here: View, gate: tuple[float, float]) -> list[View]:
    """The views within `gate` of `here`."""
    if not views:
        return []
    near = _within(gate, np.array([v.R for v in views]), np.array([v.t for v in views]), here.R, here.t, here.depth)
    return [v for v, ok in zip(views, near, strict=True) if ok]


def apart(gate: tuple[float, float], a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], depth: float) -> bool:
    """Two poses (R, t) further apart than `gate` (translation as a fraction of `depth`, rotation in degrees)."""
    return not _within(gate, a[0][None], np.asarray(a[1])[None], b[0], b[1], depth)[0]


def in_fixed_frame(camera: np.ndarray, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A camera-frame pose and its translation's covariance (3x3) in the fixed frame: (R, t, information)."""
    R_wc, t_wc = camera[:3, :3], camera[:3, 3]
    return R_wc @ R, R_wc @ t + t_wc, R_wc @ np.linalg.pinv(covariance) @ R_wc.T


def in_camera(camera: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed-frame pose in the frame of `camera` (4x4, camera to fixed)."""
    R_wc, t_wc = camera[:3, :3], camera[:3, 3]
    return R_wc.T @ R, R_wc.T @ (t - t_wc)


def _mean_rotation(views: list[View]) -> np.ndarray:
    return Rotation.from_matrix(np.array([v.R for v in views])).mean().as_matrix()


def _fused_position(views: list[View]) -> np.ndarray:
    """The views' positions weighted by their information (the least-squares point of their error ellipsoids)."""
    information = np.array([v.information for v in views])
    total = information.sum(axis=0)
    if not np.all(np.isfinite(total)) or np.linalg.matrix_rank(total) < 3:
        return np.mean([v.t for v in views], axis=0)
    return np.linalg.solve(total, np.einsum("nij,nj->i", information, np.array([v.t for v in views])))
