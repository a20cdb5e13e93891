"""Static-scene consistency: the objects of a recording stand still while the camera moves, so one pose per object
in a fixed frame explains every frame (CosyPose's multi-view stage, after Labbé et al. 2020).

From the poses each frame accepted on its own evidence (`pseudo.AcceptConfig`): each frame's camera is placed where
at least `min_register` of its objects agree with the scene (or taken from odometry), each object's scene pose is
the robust mean of its views (rotations up to its symmetries, positions fused by their information: a view sees
depth poorly, across its line of sight well), and per frame every object of the scene is predicted where the scene
puts it. A frame's own pose that disagrees with its object's scene pose (a flip, a quarter turn, a wrong place) is
rejected; an object the scene predicts in a frame where none of its poses was accepted is filled there. An object
whose views split into places never seen together has moved: it falls back to each frame's own evidence.

Pure geometry: the frames' pixels enter only where `fill` refines the predictions on them (`labels.py`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from axispose_core.adapt.geometry import ObjectGeometry, aligned, fuse, inverse, pose_matrix, rotation_gap_deg, variants
from axispose_core.adapt.pseudo import AcceptConfig, Candidate


@dataclass(frozen=True)
class ConsistencyConfig:
    """When poses of one object agree: their positions apart by at most `depth_gate` of the camera's distance along
    its line of sight and `lateral_gate` of it across, their rotations by at most `rotation_gate_deg` (up to the
    object's symmetries)."""

    depth_gate: float = 0.12
    lateral_gate: float = 0.05
    rotation_gate_deg: float = 25.0
    min_register: int = 2
    """Objects of a frame that must agree with the scene for its camera to be placed without odometry."""
    min_views: int = 3
    """Frames an object's scene pose needs (its views that agree) before it fills or rejects anything."""
    window: int = 0
    """Frames either side of a frame (in recording order) that are one scene with it: 0, the whole recording (the
    objects stand still throughout); k, each frame is checked and filled by the scene of the 2k + 1 frames around
    it, for recordings whose objects are moved now and then."""
    depth_sigma: float = 0.05
    """Standard deviation of a single view's depth along its line of sight (a fraction of the depth)..."""
    lateral_sigma: float = 0.005
    """...and across it: the anisotropy the scene's positions are fused with."""

    def __post_init__(self) -> None:
        if not (self.depth_gate > 0 and self.lateral_gate > 0 and 0 < self.rotation_gate_deg <= 180):
            raise ValueError(f"consistency gates must be positive (rotation at most 180 degrees), got {self}")
        if self.min_register < 1 or self.min_views < 1 or self.window < 0 or not 0 < self.lateral_sigma <= self.depth_sigma:
            raise ValueError(f"min_register and min_views must be >= 1 and 0 < lateral_sigma <= depth_sigma, got {self}")


@dataclass
class Instance:
    """One object at rest in the fixed frame: its pose (4x4, model to fixed), the candidates that agree with it
    (frame id -> candidate) and those at its place whose rotation does not (flips)."""

    obj_id: int
    pose: np.ndarray
    members: dict[int, Candidate] = field(default_factory=dict)
    turned: list[Candidate] = field(default_factory=list)

    @property
    def views(self) -> int:
        return len(self.members)


@dataclass(frozen=True)
class Prediction:
    """Where the scene puts an instance in a frame (camera frame), and the frame's own accepted pose of it (None:
    the frame accepted none: a fill)."""

    im_id: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    own: Candidate | None


@dataclass
class SceneResult:
    """The consistency stage's answer, per frame: its camera (4x4 camera to the fixed frame of its scene; frames
    left out could not be placed), its scene's instances and the objects found to have moved there, and the
    predictions of the static instances with enough views (`static`); in all, the candidates rejected (with why)
    and the frames' own accepted poses that stand on per-frame evidence alone (unplaced frames, moved or thinly seen
    objects)."""

    cameras: dict[int, np.ndarray]
    instances: dict[int, list[Instance]]
    moved: dict[int, set[int]]
    predictions: dict[int, list[Prediction]]
    rejected: list[tuple[Candidate, str]]
    alone: list[Candidate]
    odometry: bool
    static: dict[int, list[Instance]] = field(default_factory=dict)

    @property
    def moved_objects(self) -> set[int]:
        """The objects found to have moved in any frame's scene."""
        return set().union(*self.moved.values())


def same_place(cfg: ConsistencyConfig, a: np.ndarray, b: np.ndarray, ray: np.ndarray) -> bool:
    """Whether two positions of one object seen along `ray` (from the camera to it, its length the distance) are
    within the gates: apart along the ray by at most `depth_gate` of the distance, across it by `lateral_gate`."""
    depth = float(np.linalg.norm(ray))
    d = np.asarray(a) - np.asarray(b)
    along = float(d @ ray) / max(depth, 1e-9)
    across = float(np.linalg.norm(d - along * ray / max(depth, 1e-9)))
    return abs(along) <= cfg.depth_gate * depth and across <= cfg.lateral_gate * depth


def agree(cfg: ConsistencyConfig, a: np.ndarray, b: np.ndarray, geometry: ObjectGeometry) -> bool:
    """Whether two camera-frame 4x4 poses of one object agree: the same place (seen along b's ray) and rotation."""
    return same_place(cfg, a[:3, 3], b[:3, 3], b[:3, 3]) and rotation_gap_deg(a[:3, :3], b[:3, :3], geometry) <= cfg.rotation_gate_deg


def _candidate_pose(c: Candidate) -> np.ndarray:
    return pose_matrix(c.R, c.t)


def _depth(c: Candidate) -> float:
    return float(np.linalg.norm(c.t))


# --------------------------------------------------------------------------------------------- the fixed frame


def information(camera: np.ndarray, c: Candidate, cfg: ConsistencyConfig) -> np.ndarray:
    """A view's position information in the fixed frame: weak along its line of sight, strong across it."""
    d = _depth(c)
    ray = c.t / max(d, 1e-9)
    cov = (cfg.lateral_sigma * d) ** 2 * np.eye(3) + ((cfg.depth_sigma * d) ** 2 - (cfg.lateral_sigma * d) ** 2) * np.outer(ray, ray)
    R_wc = camera[:3, :3]
    return R_wc @ np.linalg.inv(cov) @ R_wc.T


@dataclass
class _Place:
    """Views of one object gathered at one place while the instances are built, with their fused position."""

    obj_id: int
    views: list[tuple[np.ndarray, Candidate]]
    information: np.ndarray
    weighted: np.ndarray

    def centre(self) -> np.ndarray:
        return np.linalg.solve(self.information, self.weighted)

    def holds(self, cfg: ConsistencyConfig, T: np.ndarray, c: Candidate) -> bool:
        """Whether a view (T in the fixed frame, from candidate c) lies at this place, seen along its own ray."""
        return c.obj_id == self.obj_id and same_place(cfg, self.centre(), T[:3, 3], T[:3, :3] @ c.R.T @ c.t)

    def add(self, T: np.ndarray, c: Candidate, information: np.ndarray) -> None:
        self.views.append((T, c))
        self.information = self.information + information
        self.weighted = self.weighted + information @ T[:3, 3]


def build_instances(
    seeds: Mapping[int, Sequence[Candidate]], cameras: Mapping[int, np.ndarray], geometry: Mapping[int, ObjectGeometry],
    cfg: ConsistencyConfig,
) -> list[Instance]:  # fmt: skip
    """The placed frames' accepted poses grouped into objects at rest: per object id, greedily by evidence, each view
    joins the place whose fused position it shares (else starts one), and places that come to share a position
    merge; within an instance, the rotation most views agree on wins, and the views turned from it are kept apart."""
    views = [(cameras[f] @ _candidate_pose(c), c) for f in sorted(cameras) for c in seeds.get(f, ())]
    views.sort(key=lambda v: -(v[1].score + v[1].agreement))
    places: list[_Place] = []
    for T, c in views:
        info = information(cameras[c.im_id], c, cfg)
        home = next((p for p in places if p.holds(cfg, T, c)), None)
        if home is None:
            places.append(_Place(c.obj_id, [(T, c)], info, info @ T[:3, 3]))
        else:
            home.add(T, c, info)
    merged = True
    while merged:
        merged = False
        for a, b in ((a, b) for a in places for b in places if a is not b and a.obj_id == b.obj_id):
            ray = b.centre() - cameras[b.views[0][1].im_id][:3, 3]  # b's place, seen from the camera of its best view
            if same_place(cfg, a.centre(), b.centre(), ray):
                for T, c in b.views:
                    a.add(T, c, information(cameras[c.im_id], c, cfg))
                places.remove(b)
                merged = True
                break
    return [_instance(p.obj_id, sorted(p.views, key=lambda v: -(v[1].score + v[1].agreement)), cameras, geometry[p.obj_id], cfg)
            for p in places]  # fmt: skip


def _instance(
    obj_id: int, members: list[tuple[np.ndarray, Candidate]], cameras: Mapping[int, np.ndarray], geometry: ObjectGeometry,
    cfg: ConsistencyConfig,
) -> Instance:  # fmt: skip
    """The instance of views at one place (in order of evidence): the rotation most of them share (a medoid) and
    their fused pose, one view per frame (its best); views turned from that rotation are kept apart."""
    Rs = [T[:3, :3] for T, _ in members]
    support = [sum(rotation_gap_deg(Ra, Rb, geometry) <= cfg.rotation_gate_deg for Rb in Rs) for Ra in Rs]
    medoid = members[int(np.argmax(support))]
    kept: dict[int, tuple[np.ndarray, Candidate]] = {medoid[1].im_id: medoid}
    turned = []
    for T, c in members:
        if rotation_gap_deg(T[:3, :3], medoid[0][:3, :3], geometry) > cfg.rotation_gate_deg:
            turned.append(c)
        else:
            kept.setdefault(c.im_id, (T, c))
    views = list(kept.values())
    pose = fuse([T for T, _ in views], [information(cameras[c.im_id], c, cfg) for _, c in views], geometry)
    return Instance(obj_id, pose, {c.im_id: c for _, c in views}, turned)


# --------------------------------------------------------------------------------------------- cameras


def locate(
    cands: Sequence[Candidate], instances: Sequence[Instance], geometry: Mapping[int, ObjectGeometry], cfg: ConsistencyConfig
) -> tuple[np.ndarray | None, list[tuple[Candidate, Instance]]]:
    """A frame's camera (4x4 camera to fixed) from its poses and the scene's instances: every pose of an object the
    scene holds proposes one (each of its symmetric equivalents), the proposal most of the frame's objects agree
    with wins and is refined on them; (None, []) where none is proposed."""
    best: tuple[int, float, np.ndarray, list] | None = None
    for c in cands:
        for inst in (i for i in instances if i.obj_id == c.obj_id):
            for V in variants(c.R, c.t, geometry[c.obj_id]):
                camera = inst.pose @ inverse(V)
                inliers = _inliers(camera, cands, instances, geometry, cfg)
                key = (len({c.obj_id for c, _ in inliers}), sum(c.score + c.agreement for c, _ in inliers))
                if best is None or key > best[:2]:
                    best = (*key, camera, inliers)
    if best is None:
        return None, []
    camera = _refined_camera(best[2], best[3], geometry, cfg)
    return camera, _inliers(camera, cands, instances, geometry, cfg)


def _inliers(
    camera: np.ndarray, cands: Sequence[Candidate], instances: Sequence[Instance], geometry: Mapping[int, ObjectGeometry],
    cfg: ConsistencyConfig,
) -> list[tuple[Candidate, Instance]]:  # fmt: skip
    """The frame's poses that agree (place and rotation) with an instance seen from `camera`; one per instance."""
    to_camera = inverse(camera)
    out, used = [], set()
    for c in cands:
        for k, inst in enumerate(instances):
            if k in used or inst.obj_id != c.obj_id:
                continue
            if agree(cfg, to_camera @ inst.pose, _candidate_pose(c), geometry[c.obj_id]):
                out.append((c, inst))
                used.add(k)
                break
    return out


def _refined_camera(
    camera: np.ndarray, inliers: list[tuple[Candidate, Instance]], geometry: Mapping[int, ObjectGeometry], cfg: ConsistencyConfig
) -> np.ndarray:
    """The camera all the inliers agree on: its rotation the weighted chordal mean of what each object's rotation
    says (the symmetric equivalent nearest `camera`'s), its position the information-weighted least-squares one
    (each view's position known across its line of sight far better than along it)."""
    Rs, infos, targets, weights = [], [], [], []
    for c, inst in inliers:
        V = aligned(_candidate_pose(c), inverse(camera) @ inst.pose, geometry[c.obj_id])
        Rs.append(inst.pose[:3, :3] @ V[:3, :3].T)
        weights.append(c.score + c.agreement)
    R = Rotation.from_matrix(np.array(Rs)).mean(weights=np.array(weights)).as_matrix()
    for c, inst in inliers:
        V = aligned(_candidate_pose(c), inverse(camera) @ inst.pose, geometry[c.obj_id])
        infos.append(information(pose_matrix(R, np.zeros(3)), c, cfg))
        targets.append(inst.pose[:3, 3] - R @ V[:3, 3])
    t = np.linalg.solve(np.sum(infos, axis=0), np.einsum("nij,nj->i", np.array(infos), np.array(targets)))
    return pose_matrix(R, t)


def register(
    seeds: Mapping[int, Sequence[Candidate]], geometry: Mapping[int, ObjectGeometry], cfg: ConsistencyConfig, sweeps: int = 2
) -> dict[int, np.ndarray]:
    """The frames' cameras without odometry, in the frame of the camera that accepted the most objects: frames are
    placed one at a time, the one most of whose objects agree with the scene so far first; then every frame is
    placed again on the scene of all of them (`sweeps` times), so an early placement on a thin scene is checked."""
    order = sorted(seeds, key=lambda f: (-len({c.obj_id for c in seeds[f]}), f))
    if not order or not seeds[order[0]]:
        return {}
    cameras = {order[0]: np.eye(4)}
    pending = set(order[1:])
    while pending:
        instances = build_instances(seeds, cameras, geometry, cfg)
        placed = [(f, *locate(seeds[f], instances, geometry, cfg)) for f in sorted(pending)]
        placed = [(f, cam, inl) for f, cam, inl in placed if cam is not None and len({c.obj_id for c, _ in inl}) >= cfg.min_register]
        if not placed:
            break
        f, camera, _ = max(placed, key=lambda p: (len({c.obj_id for c, _ in p[2]}), -p[0]))
        cameras[f] = camera
        pending.discard(f)
    for _ in range(sweeps):
        instances = build_instances(seeds, cameras, geometry, cfg)
        again = {}
        for f in seeds:
            camera, inliers = locate(seeds[f], instances, geometry, cfg)
            if camera is not None and len({c.obj_id for c, _ in inliers}) >= cfg.min_register:
                again[f] = camera
        if not again:
            break
        cameras = _anchored(again, order[0])
    return cameras


def _anchored(cameras: dict[int, np.ndarray], anchor: int) -> dict[int, np.ndarray]:
    """The cameras re-expressed so that `anchor`'s (where placed) is the identity: the fixed frame stays put."""
    if anchor not in cameras:
        return cameras
    to_anchor = inverse(cameras[anchor])
    return {f: to_anchor @ T for f, T in cameras.items()}


# --------------------------------------------------------------------------------------------- the whole stage


def _moved(instances: Sequence[Instance], cfg: ConsistencyConfig) -> set[int]:
    """Objects with two or more well-seen places one after the other in the recording: seen in one place, then in
    another (two instances of it would be seen side by side, and one place's views split by errors interleave with
    the other's)."""
    out = set()
    by_object: dict[int, list[Instance]] = {}
    for inst in instances:
        if inst.views >= cfg.min_views:
            by_object.setdefault(inst.obj_id, []).append(inst)
    for obj_id, places in by_object.items():
        spans = sorted((min(p.members), max(p.members)) for p in places)
        if any(a[1] < b[0] for a, b in itertools.pairwise(spans)):
            out.add(obj_id)
    return out


def consistent(
    candidates: Mapping[int, Sequence[Candidate]],
    geometry: Mapping[int, ObjectGeometry],
    accept: AcceptConfig,
    cfg: ConsistencyConfig,
    odometry: Mapping[int, np.ndarray] | None = None,
    in_view: Callable[[int, int, np.ndarray, np.ndarray], bool] | None = None,
) -> SceneResult:
    """The consistency stage over a recording's candidates (frame id -> poses, ids in recording order; `geometry`
    per object id): per frame, the scene of its window (`cfg.window`) with cameras from `odometry` (frame id -> 4x4
    camera to fixed, every frame) or from the accepted poses; the frame's camera and the predictions of its scene's
    well-seen static instances (those `in_view(im_id, obj_id, R, t)` says the frame can show, where given); each
    of its accepted poses checked by the scene, rejected by it, or standing alone where the scene cannot check it."""
    order = sorted(candidates)
    seeds = {f: [c for c in candidates[f] if c.obj_id in geometry and accept.accepts(c)] for f in order}
    out = SceneResult({}, {}, {}, {}, [], [], odometry is not None)
    scenes: dict[tuple[int, ...], _Scene] = {}
    for k, f in enumerate(order):
        window = tuple(order) if cfg.window == 0 else tuple(order[max(0, k - cfg.window) : k + cfg.window + 1])
        if window not in scenes:
            scenes[window] = _static_scene({g: seeds[g] for g in window}, geometry, cfg, odometry)
        scene = scenes[window]
        out.instances[f], out.moved[f], out.static[f] = scene.instances, scene.moved, scene.static
        if f in scene.cameras:
            out.cameras[f] = scene.cameras[f]
        for c in seeds[f]:
            verdict = scene.verdict(c, geometry, cfg)
            if verdict == "alone":
                out.alone.append(c)
            elif verdict != "checked":
                out.rejected.append((c, verdict))
        out.predictions[f] = scene.predictions(f, in_view) if f in scene.cameras else []
    return out


@dataclass
class _Scene:
    """One static scene: its frames' cameras, its instances, the objects that moved in it, and those instances with
    enough views to check and fill (`static`)."""

    cameras: dict[int, np.ndarray]
    instances: list[Instance]
    moved: set[int]
    static: list[Instance]

    def verdict(self, c: Candidate, geometry: Mapping[int, ObjectGeometry], cfg: ConsistencyConfig) -> str:
        """What the scene says of an accepted pose: "checked" (one of a static instance's views), "turned" (at its
        place, another rotation), "misplaced" (in a placed frame, away from every static instance of its object),
        "duplicate" (a second pose of an instance in one frame), or "alone" (the scene cannot check it)."""
        if any(i.members.get(c.im_id) is c for i in self.static):
            return "checked"
        if any(c is t for i in self.static for t in i.turned):
            return "turned"
        if c.im_id not in self.cameras:
            return "alone"
        if _disowned(c, self.static, self.cameras[c.im_id], geometry, cfg):
            return "misplaced"
        if any(i.obj_id == c.obj_id and c.im_id in i.members for i in self.static):
            return "duplicate"
        return "alone"

    def predictions(self, f: int, in_view: Callable[[int, int, np.ndarray, np.ndarray], bool] | None) -> list[Prediction]:
        """Where the static instances lie in frame f (`predict`)."""
        return predict(f, self.cameras[f], self.static, in_view)


def predict(f: int, camera: np.ndarray, instances: Sequence[Instance],
            in_view: Callable[[int, int, np.ndarray, np.ndarray], bool] | None = None) -> list[Prediction]:  # fmt: skip
    """Where the instances lie in frame f seen from `camera` (4x4 camera to fixed): those in front of it and, where
    given, `in_view`; each with the frame's own accepted pose of it, if any."""
    to_camera = inverse(camera)
    out = []
    for inst in instances:
        T = to_camera @ inst.pose
        if T[2, 3] <= 0 or (in_view is not None and not in_view(f, inst.obj_id, T[:3, :3], T[:3, 3])):
            continue
        out.append(Prediction(f, inst.obj_id, T[:3, :3], T[:3, 3], inst.members.get(f)))
    return out


def _static_scene(
    seeds: Mapping[int, Sequence[Candidate]], geometry: Mapping[int, ObjectGeometry], cfg: ConsistencyConfig,
    odometry: Mapping[int, np.ndarray] | None,
) -> _Scene:  # fmt: skip
    """The scene of frames taken to show objects at rest: cameras (odometry's, or placed by the accepted poses), the
    instances of those poses, the objects that moved, and the static instances with `min_views` views."""
    cameras = {f: np.asarray(odometry[f], float) for f in seeds} if odometry is not None else register(seeds, geometry, cfg)
    instances = build_instances(seeds, cameras, geometry, cfg)
    moved = _moved(instances, cfg)
    return _Scene(cameras, instances, moved, [i for i in instances if i.views >= cfg.min_views and i.obj_id not in moved])


def _disowned(c: Candidate, static: Sequence[Instance], camera: np.ndarray, geometry: Mapping[int, ObjectGeometry],
              cfg: ConsistencyConfig) -> bool:  # fmt: skip
    """A pose in a placed frame of an object the scene holds well-seen, away from (or turned from) every one of its
    instances: the scene says it is wrong."""
    mine = [i for i in static if i.obj_id == c.obj_id]
    if not mine:
        return False
    to_camera = inverse(camera)
    return not any(agree(cfg, to_camera @ i.pose, _candidate_pose(c), geometry[c.obj_id]) for i in mine)
