"""Searching a static scene for the objects none of its frames accepted (the localiser never found them, or never
well enough): the AGM reads a grid of places on the scene's support plane in several frames at once. Where nothing
stands, each frame's crop shows other background from another side and the reads scatter; where a thing stands they
agree in the fixed frame (place and rotation, the consistency stage's gates), but any thing, not only the object.
So the places most frames agree on are then predicted in those frames and refined on their contours as a fill is
(`labels.label_frame`): the one most frames take is the object's, where enough of them do.

What it finds joins the scene as an instance no frame accepted: predicted in every placed frame and, like any
prediction, a label only where the frame's contours take it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from axispose_core.adapt.geometry import ObjectGeometry, fuse, inverse, pose_matrix
from axispose_core.adapt.labels import FillConfig, label_frame
from axispose_core.adapt.pseudo import Candidate
from axispose_core.adapt.recording import Frame
from axispose_core.adapt.scene import ConsistencyConfig, Instance, SceneResult, information, predict
from axispose_core.estimator import EstimateOptions, Estimator

PLANE_SPAN = 0.05
"""Points span a plane where their second principal spread (root mean square, m) is at least this."""
CLEARANCE = 0.3
"""Two objects' centres are at least this much of their diameters together apart (0.5: spheres touching)."""


@dataclass(frozen=True)
class SearchConfig:
    """How the scene is searched: `views` placed frames spread over the recording (0: no search) read a grid of
    `step` (m) on the plane through the found objects' centres (at each of `levels`, m along its normal), reaching
    `margin` (m) past them; each place's crop a square of `box_scale` of the object's diameter as seen there. A place
    is taken where the reads of at least `min_support` frames agree."""

    views: int = 12
    places: int = 5
    """Places per object (the best supported) checked against the views' contours."""
    min_share: float = 0.75
    """Share of the views whose contour must take the object at a place for it to be found there."""
    step: float = 0.03
    margin: float = 0.10
    levels: tuple[float, ...] = (0.0,)
    box_scale: float = 0.75
    min_support: int = 4
    steps: int = 3
    max_boxes: int = 64

    def __post_init__(self) -> None:
        if self.views < 0 or self.step <= 0 or self.margin < 0 or self.box_scale <= 0 or self.min_support < 2:
            raise ValueError(f"search: views >= 0, step > 0, margin >= 0, box_scale > 0 and min_support >= 2, got {self}")
        if self.places < 1 or not 0 < self.min_share <= 1:
            raise ValueError(f"search: places must be >= 1 and 0 < min_share <= 1, got {self}")


@dataclass(frozen=True)
class Discovery:
    """What the search made of one object: the best place's pose (4x4, model to fixed; None where no place was
    taken), the frames whose reads agree there (`support`) and those whose contours took it (`takes`), of the
    `views` read."""

    obj_id: int
    pose: np.ndarray | None
    support: int
    takes: int
    views: int

    def to_json(self) -> dict:
        return {"obj_id": self.obj_id, "pose": None if self.pose is None else self.pose.ravel().tolist(),
                "support": self.support, "takes": self.takes, "views": self.views}  # fmt: skip

    @classmethod
    def from_json(cls, d: dict) -> Discovery:
        pose = None if d["pose"] is None else np.asarray(d["pose"], float).reshape(4, 4)
        return cls(int(d["obj_id"]), pose, int(d["support"]), int(d["takes"]), int(d["views"]))


@dataclass
class Reads:
    """One object's reads, every view's crops: pose in the fixed frame, the line of sight (fixed frame, camera to
    the object, its length the distance) and the frame."""

    poses: np.ndarray
    rays: np.ndarray
    frames: np.ndarray
    candidates: list[Candidate]


def missing_objects(scene: SceneResult, objects: Sequence[int]) -> list[int]:
    """The objects the scene predicts in no frame and that did not move: what the search looks for."""
    predicted = {p.obj_id for ps in scene.predictions.values() for p in ps}
    return [o for o in objects if o not in predicted and o not in scene.moved_objects]


def support_plane(centres: np.ndarray, cameras: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The plane the found objects stand on, through their centres: (origin, 3x3 rows e1, e2, normal). Its normal
    is that of the centres' plane where three or more span one (things resting on one table), else of the plane the
    cameras move in (a camera carried around a table keeps about its height), else the cameras' mean up (image rows
    run down the table)."""
    origin = centres.mean(axis=0)
    up = -np.mean([C[:3, 1] for C in cameras], axis=0)
    normal = up / np.linalg.norm(up)
    for points in (centres, np.array([C[:3, 3] for C in cameras])):
        _, s, vt = np.linalg.svd(points - points.mean(axis=0))
        if len(points) >= 3 and s[1] > PLANE_SPAN * np.sqrt(len(points)):
            normal = vt[2] if vt[2] @ up >= 0 else -vt[2]
            break
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return origin, np.stack([e1, np.cross(normal, e1), normal])


def grid(centres: np.ndarray, cameras: Sequence[np.ndarray], cfg: SearchConfig) -> np.ndarray:
    """The places searched (M, 3, fixed frame): the plane's grid over the centres' extent and `margin` past it."""
    origin, axes = support_plane(centres, cameras)
    uv = (centres - origin) @ axes[:2].T
    lo, hi = uv.min(axis=0) - cfg.margin, uv.max(axis=0) + cfg.margin
    a, b = (np.arange(lo[k], hi[k] + 1e-9, cfg.step) for k in range(2))
    A, B = np.meshgrid(a, b, indexing="ij")
    plane = origin + A.reshape(-1, 1) * axes[0] + B.reshape(-1, 1) * axes[1]
    return np.concatenate([plane + level * axes[2] for level in cfg.levels])


def spread(frames: Sequence[int], n: int) -> list[int]:
    """Up to n of the frames (in order), evenly spread."""
    if len(frames) <= n:
        return list(frames)
    return [frames[int(k)] for k in np.linspace(0, len(frames) - 1, n).round().astype(int)]


def read_places(est: Estimator, frame: Frame, camera: np.ndarray, obj_id: int, places: np.ndarray, cfg: SearchConfig) -> list[Candidate]:
    """The AGM's poses (camera frame) of one object at each of the places that lie in front of the frame's camera
    with their centre in its image; each read's box the crop it was read from."""
    image = frame.rgb()
    h, w = image.shape[:2]
    to_camera = inverse(camera)
    local = places @ to_camera[:3, :3].T + to_camera[:3, 3]
    z = local[:, 2]
    front = z > 0.05
    uv = (local[front] @ frame.K.T)[:, :2] / z[front, None]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    diameter = est.objects[obj_id].diameter
    sides = cfg.box_scale * frame.K[0, 0] * diameter / z[front][inside]
    boxes = [(obj_id, (float(u - s / 2), float(v - s / 2), float(s), float(s))) for (u, v), s in zip(uv[inside], sides, strict=True)]
    options = EstimateOptions(steps=cfg.steps, refine=False, max_boxes=cfg.max_boxes)
    poses = est.estimate(image, frame.K, boxes, options=options) if boxes else []
    nan = float("nan")
    return [Candidate(frame.im_id, obj_id, p.R, p.t, 0.0, False, nan, nan, b) for (_, b), p in zip(boxes, poses, strict=True) if p.ok]


def gather(candidates: Sequence[Candidate], cameras: Mapping[int, np.ndarray]) -> Reads:
    """Reads of one object from several frames, in the fixed frame (ordered by frame)."""
    candidates = sorted(candidates, key=lambda c: c.im_id)
    poses = np.array([cameras[c.im_id] @ pose_matrix(c.R, c.t) for c in candidates]).reshape(-1, 4, 4)
    rays = np.array([cameras[c.im_id][:3, :3] @ c.t for c in candidates]).reshape(-1, 3)
    return Reads(poses, rays, np.array([c.im_id for c in candidates], int), list(candidates))


def agreement(reads: Reads, rows: np.ndarray, geometry: ObjectGeometry, cfg: ConsistencyConfig) -> np.ndarray:
    """(len(rows), N) whether read `rows[i]` agrees with read j: at j's place (seen along j's line of sight, within
    the consistency gates) and within the rotation gate up to the object's symmetries."""
    P, R = reads.poses[:, :3, 3], reads.poses[:, :3, :3]
    depth = np.linalg.norm(reads.rays, axis=1)
    sight = reads.rays / np.maximum(depth, 1e-9)[:, None]
    d = P[rows, None, :] - P[None, :, :]
    along = np.einsum("anj,nj->an", d, sight)
    across = np.linalg.norm(d - along[..., None] * sight[None], axis=2)
    place = (np.abs(along) <= cfg.depth_gate * depth) & (across <= cfg.lateral_gate * depth)
    least = 1.0 + 2.0 * np.cos(np.radians(cfg.rotation_gate_deg))
    turned = np.zeros(place.shape, bool)
    for S, _ in geometry.symmetries:
        turned |= np.einsum("aij,nij->an", R[rows] @ S, R) >= least
    return place & turned


def best_place(reads: Reads, geometry: ObjectGeometry, cfg: ConsistencyConfig, chunk: int = 256) -> int:
    """The read the most frames agree with (one of a frame's reads agreeing counts the frame)."""
    starts = np.flatnonzero(np.r_[True, reads.frames[1:] != reads.frames[:-1]])
    best, most = 0, -1
    for lo in range(0, len(reads.candidates), chunk):
        rows = np.arange(lo, min(lo + chunk, len(reads.candidates)))
        counts = np.logical_or.reduceat(agreement(reads, rows, geometry, cfg), starts, axis=1).sum(axis=1)
        k = int(np.argmax(counts))
        if counts[k] > most:
            best, most = int(rows[k]), int(counts[k])
    return best


def unoccupied(points: np.ndarray, diameter: float, found: Sequence[Instance], geometry: Mapping[int, ObjectGeometry]) -> np.ndarray:
    """Which of the points (N, 3) an object of `diameter` could stand at without going through a found object: its
    centre further from each found one's than `CLEARANCE` of their diameters together (a read there is of the found
    object, seen as the missing one, and agrees across views as a real thing does)."""
    free = np.ones(len(points), bool)
    for inst in found:
        reach = CLEARANCE * (diameter + geometry[inst.obj_id].diameter)
        free &= np.linalg.norm(points - inst.pose[:3, 3], axis=1) > reach
    return free


def subset(reads: Reads, keep: np.ndarray) -> Reads:
    """The reads `keep` (N,) bool selects."""
    return Reads(reads.poses[keep], reads.rays[keep], reads.frames[keep], [c for c, k in zip(reads.candidates, keep, strict=True) if k])


def fused_place(reads: Reads, k: int, cameras: Mapping[int, np.ndarray], geometry: ObjectGeometry,
                consistency: ConsistencyConfig) -> tuple[np.ndarray, int]:  # fmt: skip
    """Read k and the reads that agree with it (one per frame, the nearest in rotation) fused; and their frames."""
    agrees = agreement(reads, np.array([k]), geometry, consistency)[0]
    R = reads.poses[:, :3, :3]
    closeness = np.max([np.einsum("ij,nij->n", R[k] @ S, R) for S, _ in geometry.symmetries], axis=0)
    members: dict[int, int] = {}
    for j in np.flatnonzero(agrees):
        f = int(reads.frames[j])
        if f not in members or closeness[j] > closeness[members[f]]:
            members[f] = j
    order = [k] + [j for j in members.values() if j != k]
    infos = [information(cameras[reads.candidates[j].im_id], reads.candidates[j], consistency) for j in order]
    return fuse([reads.poses[j] for j in order], infos, geometry), len(members)


def places(reads: Reads, cameras: Mapping[int, np.ndarray], geometry: ObjectGeometry, consistency: ConsistencyConfig,
           cfg: SearchConfig) -> list[tuple[np.ndarray, int]]:  # fmt: skip
    """Up to `cfg.places` places (fused pose, frames agreeing) with `min_support` frames at least, the best
    supported first; each from the reads the places before left (those further than the object's diameter)."""
    out = []
    while reads.candidates and len(out) < cfg.places:
        k = best_place(reads, geometry, consistency)
        pose, support = fused_place(reads, k, cameras, geometry, consistency)
        if support < cfg.min_support:
            break
        out.append((pose, support))
        reads = subset(reads, np.linalg.norm(reads.poses[:, :3, 3] - pose[:3, 3], axis=1) > geometry.diameter)
    return out


@dataclass(frozen=True)
class Scene:
    """A recording's scene as the search reads it: the estimator that reads and refines, the frames, the consistency
    stage's result, the objects' geometry, and the scene's and the fills' settings."""

    est: Estimator
    frames: Mapping[int, Frame]
    result: SceneResult
    geometry: Mapping[int, ObjectGeometry]
    consistency: ConsistencyConfig
    fill: FillConfig


def takes(scene: Scene, views: Sequence[int], obj_id: int, pose: np.ndarray) -> int:
    """In how many of the views the object at `pose` becomes a label: its prediction refined on the frame's contours
    with the scene's others (each masking those behind it), as the label stage does."""
    n = 0
    for f in views:
        mine = predict(f, scene.result.cameras[f], [Instance(obj_id, pose)])
        if not mine:
            continue
        predictions = [*scene.result.predictions.get(f, []), *mine]
        frame = scene.frames[f]
        labels = label_frame(scene.est.refiner, frame.rgb(), frame.K, predictions, [], scene.geometry, scene.consistency, scene.fill)
        n += any(lab.obj_id == obj_id and lab.source == "filled" for lab in labels)
    return n


def search(scene: Scene, cfg: SearchConfig, progress: Callable[[int, int], None] | None = None,
           objects: Sequence[int] | None = None) -> list[Discovery]:  # fmt: skip
    """Every missing object (`missing_objects`; of `objects`, None: the checkpoint's) searched for over the scene's
    placed frames; nothing where the scene is not one still scene with cameras and found objects to stand the plane
    on. Of an object's best supported places, the one whose contour the most views take wins, where `min_share` of
    them do."""
    result, est = scene.result, scene.est
    objects = missing_objects(result, [o.obj_id for o in est.config.objects] if objects is None else objects)
    found = _static_instances(result)
    if not objects or cfg.views == 0 or scene.consistency.window != 0 or not found or len(result.cameras) < cfg.min_support:
        return []
    views = spread(sorted(result.cameras), cfg.views)
    grid_places = grid(np.array([i.pose[:3, 3] for i in found]), [result.cameras[f] for f in views], cfg)
    out = []
    for n, obj_id in enumerate(objects):
        diameter = scene.geometry[obj_id].diameter
        free = grid_places[unoccupied(grid_places, diameter, found, scene.geometry)]
        reads = []
        for m, f in enumerate(views):
            reads += read_places(est, scene.frames[f], result.cameras[f], obj_id, free, cfg)
            if progress is not None:
                progress(n * len(views) + m + 1, len(objects) * len(views))
        seen = gather(reads, result.cameras)
        seen = subset(seen, unoccupied(seen.poses[:, :3, 3], diameter, found, scene.geometry))
        candidates = places(seen, result.cameras, scene.geometry[obj_id], scene.consistency, cfg)
        scored = [(takes(scene, views, obj_id, pose), support, pose) for pose, support in candidates]
        best = max(scored, key=lambda x: x[:2], default=(0, 0, None))
        taken = best[0] >= cfg.min_share * len(views)
        out.append(Discovery(obj_id, best[2] if taken else None, best[1], best[0], len(views)))
    return out


def _static_instances(scene: SceneResult) -> list[Instance]:
    """The instances the scene predicts from (one scene: every frame's list is the same one)."""
    lists = {id(v): v for v in scene.static.values()}
    return [i for v in lists.values() for i in v]


def with_discoveries(scene: SceneResult, discoveries: Sequence[Discovery],
                     in_view: Callable[[int, int, np.ndarray, np.ndarray], bool] | None = None) -> SceneResult:  # fmt: skip
    """The scene with each found object an instance no frame accepted, predicted in every placed frame it lies in
    front of (and, where given, `in_view`)."""
    added = [Instance(d.obj_id, d.pose, {}, []) for d in discoveries if d.pose is not None]
    if not added:
        return scene
    predictions = {f: list(ps) for f, ps in scene.predictions.items()}
    for f, camera in scene.cameras.items():
        predictions.setdefault(f, []).extend(predict(f, camera, added, in_view))
    return dataclasses.replace(scene, instances={f: [*v, *added] for f, v in scene.instances.items()},
                               static={f: [*v, *added] for f, v in scene.static.items()}, predictions=predictions)  # fmt: skip


def write_discoveries(path: Path, discoveries: Sequence[Discovery]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps([d.to_json() for d in discoveries], indent=1))
    tmp.replace(path)


def read_discoveries(path: Path) -> list[Discovery] | None:
    """A round's search as written, or None where it has not run."""
    return [Discovery.from_json(d) for d in json.loads(path.read_text())] if path.is_file() else None
