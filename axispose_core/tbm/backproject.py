"""Triaxial back-projection: the pose of a cube corner (C2) from its projected origin and three leg endpoints.

With rays ``q_i = K⁻¹ x̃_i`` and the origin's depth fixed to 1, the corner's vertices are ``X_O = q_O`` and
``X_i = λ_i q_i``. Orthogonality of the legs ``l_i = λ_i q_i − q_O`` is the paper's system

    λ_A λ_B a_AB − λ_A a_AO − λ_B a_BO + a_OO = 0   (and cyclically for BC, CA),   a_ij = x_iᵀ μ x_j = q_i·q_j.

The first and third equations give λ_B and λ_C as rational functions of λ_A; substituting them in the second
leaves a quadratic in λ_A. Of its (at most two) roots, the physically valid one has every vertex in front of
the camera and a right-handed corner (the convex C2 the paper keeps); if two survive, the one whose leg lengths
best match the known ratios wins. The metric scale then comes from the known leg lengths λ_O (1, r_B, r_C):
the depth of the origin is the least-squares factor that maps the unit-depth legs onto them.

Noisy keypoints of a nearly orthographic view (a small crop far away) often give a complex pair of roots: its
real part, polished, is then the seed; if no root is valid, `refine` fits from the slopes' rotation and the 24
cube rotations instead. Every result must re-project onto the given keypoints within `MAX_RELATIVE_RESIDUAL`
of the longest leg, which refuses corners no object could form (a vertex behind the camera, wrong ratios).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from axispose_core.axis_image import axis_points
from axispose_core.camera import IntrinsicsError, project, transform, validate_intrinsics
from axispose_core.rotation import nearest_rotation

MIN_AXIS_PIXELS = 1e-3
"""Projected legs shorter than this (pixels) point at the camera: their depth cannot be recovered."""
MIN_SINE = 1e-6
"""Projected legs closer than this (sine of the angle) to one line are collinear: the corner is degenerate."""
MAX_RELATIVE_RESIDUAL = 0.2
"""A pose whose re-projected keypoints miss by more than this fraction of the longest projected leg is refused:
the keypoints do not come from a corner with the known leg ratios (e.g. a vertex behind the camera)."""
FALLBACK_FITS = 4
"""Seeds fitted when the corner system has no valid root (noisy keypoints): the best-reprojecting ones."""


class Backprojection(NamedTuple):
    """Result of a back-projection. On failure R is identity, t zero, ok False and reason says why."""

    R: np.ndarray
    t: np.ndarray
    ok: bool
    reason: str = ""


def _fail(reason: str) -> Backprojection:
    return Backprojection(np.eye(3), np.zeros(3), False, reason)


def _check_input(K: np.ndarray, uv_origin: np.ndarray, uv_axes: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Common validation; returns (K, 4x2 keypoints, reason) with a non-empty reason on bad input."""
    try:
        K = validate_intrinsics(K)
    except IntrinsicsError as err:
        return np.eye(3), np.zeros((4, 2)), f"invalid intrinsics: {err}"
    kp = np.vstack([np.reshape(uv_origin, (1, 2)), np.reshape(uv_axes, (3, 2))]).astype(np.float64)
    if not np.all(np.isfinite(kp)):
        return K, kp, "non-finite keypoints"
    legs = kp[1:] - kp[0]
    norms = np.linalg.norm(legs, axis=1)
    for name, n in zip("XYZ", norms, strict=True):
        if n < MIN_AXIS_PIXELS:
            return K, kp, f"axis {name} projects to a point (it points at the camera)"
    dirs = legs / norms[:, None]
    for i, j in ((0, 1), (1, 2), (2, 0)):
        if abs(dirs[i, 0] * dirs[j, 1] - dirs[i, 1] * dirs[j, 0]) < MIN_SINE:
            return K, kp, f"axes {'XYZ'[i]} and {'XYZ'[j]} project onto one line (collinear)"
    return K, kp, ""


def _rays(K: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """Back-projected rays with unit depth, one row per keypoint."""
    return np.column_stack([kp, np.ones(len(kp))]) @ np.linalg.inv(K).T


def _polish(a: np.ndarray, lam: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Newton steps on the three orthogonality equations: the quadratic's roots lose digits near a double root."""
    pairs = ((1, 2), (2, 3), (3, 1))
    for _ in range(iterations):
        full = np.concatenate([[1.0], lam])
        f = np.array([full[i] * full[j] * a[i, j] - full[i] * a[i, 0] - full[j] * a[j, 0] + a[0, 0] for i, j in pairs])
        J = np.zeros((3, 3))
        for row, (i, j) in enumerate(pairs):
            J[row, i - 1] = full[j] * a[i, j] - a[i, 0]
            J[row, j - 1] = full[i] * a[i, j] - a[j, 0]
        try:
            step = np.linalg.solve(J, f)
        except np.linalg.LinAlgError:
            return lam
        if not np.all(np.isfinite(step)):
            return lam
        lam = lam - step
    return lam


def _corner(K: np.ndarray, kp: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The analytic pose of the corner system's valid root (None if no root is valid)."""
    q = _rays(K, kp)  # (4,3): O, A, B, C
    a = q @ q.T
    O, A, B, C = 0, 1, 2, 3
    P = np.polynomial.polynomial
    n_poly = np.array([-a[O, O], a[A, O]])
    db = np.array([-a[B, O], a[A, B]])
    dc = np.array([-a[C, O], a[A, C]])
    quad = P.polysub(
        P.polyadd(P.polymul(a[B, C] * n_poly, n_poly), P.polymul(a[O, O] * db, dc)),
        P.polyadd(P.polymul(a[B, O] * n_poly, dc), P.polymul(a[C, O] * n_poly, db)),
    )
    roots = P.polyroots(np.trim_zeros(quad, "b")) if np.any(quad) else np.array([])
    candidates = []
    for root in np.atleast_1d(roots):
        # A complex pair means noisy keypoints no exact corner explains; its real part is the nearest
        # near-solution and still a good seed (the re-projection check decides whether to keep it).
        lam_a = root.real
        den_b, den_c = P.polyval(lam_a, db), P.polyval(lam_a, dc)
        if abs(den_b) < 1e-15 or abs(den_c) < 1e-15:
            continue
        num = P.polyval(lam_a, n_poly)
        lam = _polish(a, np.array([lam_a, num / den_b, num / den_c]))
        if np.any(lam <= 0):
            continue
        legs = lam[:, None] * q[1:] - q[0]
        if np.linalg.det(legs) <= 0:
            continue
        leg_len = np.linalg.norm(legs, axis=1)
        ratio_err = np.linalg.norm(leg_len / leg_len[0] - lengths / lengths[0])
        candidates.append((ratio_err, legs, leg_len))
    if not candidates:
        return None
    _, legs, leg_len = min(candidates, key=lambda c: c[0])
    scale = float(lengths @ leg_len / (leg_len @ leg_len))
    return nearest_rotation((legs / leg_len[:, None]).T), scale * q[0]


def _fallback_seeds(K: np.ndarray, kp: np.ndarray, lengths: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Noise pushed the corner system's roots out of the valid region: the axis directions' rotation and the 24
    cube rotations, each at the depth where the legs have their observed mean pixel length; the FALLBACK_FITS
    that re-project best (fitting all 25 took ~5 s per object)."""
    q = _rays(K, kp)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    t0 = q[0] * focal * lengths.mean() / np.linalg.norm(kp[1:] - kp[0], axis=1).mean()
    seeds = list(Rotation.create_group("O").as_matrix())
    slopes = rotation_from_slopes(K, kp[0], kp[1:] - kp[0])
    if slopes.ok:
        seeds.insert(0, slopes.R)
    seeds.sort(key=lambda R0: _reprojection_residual(K, kp, lengths, R0, t0))
    return [(R0, t0) for R0 in seeds[:FALLBACK_FITS]]


def backproject(K: np.ndarray, uv_origin: np.ndarray, uv_axes: np.ndarray, lengths: np.ndarray, refine: bool = False) -> Backprojection:
    """Pose (R, t) of a cube corner from its projected origin (2,), leg endpoints (3,2) and leg lengths (3,) in metres.

    R's columns are the model X, Y, Z axes in the camera frame; t is the model origin in metres. With `refine`,
    the analytic pose seeds a Levenberg-Marquardt fit of all four keypoints (what to use on noisy keypoints).
    """
    if np.size(uv_axes) != 6:
        return _fail(f"three axis endpoints needed, got {np.size(uv_axes) / 2:g}")
    keypoints = np.vstack([np.reshape(uv_origin, (1, 2)), np.reshape(uv_axes, (3, 2))])
    return backproject_many([K], [keypoints], [lengths], refine)[0]


def backproject_readings(K: np.ndarray, readings: list, lengths: np.ndarray, refine: bool = True) -> list[Backprojection | None]:
    """`backproject_many` of the readable ones of a reader's `AxisKeypoints` (K (N,3,3), lengths (N,3), one per
    reading), in one vectorised refinement; None where the reader could not read the image (its `reason` says why)."""
    read = [i for i, kp in enumerate(readings) if kp.ok]
    out: list[Backprojection | None] = [None] * len(readings)
    if read:
        solved = backproject_many(np.asarray(K)[read], np.stack([readings[i].array for i in read]), np.asarray(lengths)[read], refine)
        for i, res in zip(read, solved, strict=True):
            out[i] = res
    return out


def backproject_many(K: np.ndarray, keypoints: np.ndarray, lengths: np.ndarray, refine: bool = False) -> list[Backprojection]:
    """`backproject` of N corners at once: intrinsics (N,3,3), keypoints (N,4,2) (origin, then the endpoints) and
    leg lengths (N,3); the refinements of all of them are one vectorised Levenberg-Marquardt fit."""
    out: list[Backprojection | None] = []
    checked: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    jobs: list[tuple[int, np.ndarray, np.ndarray]] = []  # (item, R0, t0) to refine
    for i, (Ki, kpi, Li) in enumerate(zip(K, keypoints, lengths, strict=True)):
        Ki, kp, reason = _check_input(Ki, kpi[0], kpi[1:])
        Li = np.asarray(Li, dtype=np.float64)
        if not reason and (Li.shape != (3,) or not np.all(np.isfinite(Li)) or np.any(Li <= 0)):
            reason = f"leg lengths must be three positive numbers, got {Li}"
        checked.append((Ki, kp, Li))
        if reason:
            out.append(_fail(reason))
            continue
        pose = _corner(Ki, kp, Li)
        if pose is not None and refine and not np.isfinite(_reprojection_residual(Ki, kp, Li, *pose)):
            pose = None  # the scaled, orthonormalised corner puts a vertex behind the camera: a poor seed
        if pose is not None:
            out.append(Backprojection(*pose, True))
            if refine:
                jobs.append((i, *pose))
        elif refine:
            out.append(None)
            jobs.extend((i, R0, t0) for R0, t0 in _fallback_seeds(Ki, kp, Li))
        else:
            out.append(_fail("no right-handed solution with every vertex in front of the camera"))
    if jobs:
        idx = [j[0] for j in jobs]
        Rs, ts = refine_poses(
            np.stack([checked[i][0] for i in idx]), np.stack([checked[i][1] for i in idx]), np.stack([checked[i][2] for i in idx]),
            np.stack([j[1] for j in jobs]), np.stack([j[2] for j in jobs]),
        )  # fmt: skip
        best: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        for i, R, t in zip(idx, Rs, ts, strict=True):
            res = _reprojection_residual(*checked[i], R, t)
            if i not in best or res < best[i][0]:
                best[i] = (res, R, t)
        for i, (_, R, t) in best.items():
            out[i] = Backprojection(R, t, True)
    results = []
    for (Ki, kp, Li), res in zip(checked, out, strict=True):
        if not res.ok:
            results.append(res)
            continue
        if not (np.all(np.isfinite(res.R)) and np.all(np.isfinite(res.t)) and res.t[2] > 0):
            results.append(_fail("numerically unstable configuration"))
            continue
        residual = _reprojection_residual(Ki, kp, Li, res.R, res.t)
        longest = np.linalg.norm(kp[1:] - kp[0], axis=1).max()
        if residual > MAX_RELATIVE_RESIDUAL * longest:
            results.append(_fail(f"keypoints inconsistent with the known leg lengths "
                                 f"(re-projection misses by {residual:.1f} px of a {longest:.1f} px leg)"))  # fmt: skip
            continue
        results.append(res)
    return results


def _reprojection_residual(K: np.ndarray, kp: np.ndarray, lengths: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
    """Largest pixel distance between the given keypoints (4,2) and those of the pose."""
    cam = transform(R, t, axis_points(lengths))
    if np.any(cam[:, 2] <= 0):
        return float("inf")
    return float(np.linalg.norm(project(K, cam) - kp, axis=1).max())


def _project_many(K: np.ndarray, cam: np.ndarray) -> np.ndarray:
    """Camera-frame points (N,P,3) through intrinsics (N,3,3) to pixels (N,P,2); depths clamped to 1e-6."""
    z = np.maximum(cam[..., 2], 1e-6)
    u = (K[:, 0, 0, None] * cam[..., 0] + K[:, 0, 1, None] * cam[..., 1]) / z + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * cam[..., 1] / z + K[:, 1, 2, None]
    return np.stack([u, v], axis=-1)


def refine_poses(
    K: np.ndarray, keypoints: np.ndarray, lengths: np.ndarray, R0: np.ndarray, t0: np.ndarray, iterations: int = 30
) -> tuple[np.ndarray, np.ndarray]:
    """Minimise the reprojection error of origin and endpoints over N poses at once: K (N,3,3), keypoints (N,4,2),
    lengths (N,3), starting poses R0 (N,3,3), t0 (N,3) -> (R, t). Levenberg-Marquardt with the analytic Jacobian
    (rotation updates on the left, R <- exp([w]x) R), each pose with its own damping; a step is taken only where
    it lowers that pose's error, so no pose ends worse than it started."""
    K, kp = np.asarray(K, dtype=np.float64), np.asarray(keypoints, dtype=np.float64)
    R, t = np.array(R0, dtype=np.float64), np.array(t0, dtype=np.float64)
    n = len(kp)
    pts = np.zeros((n, 4, 3))
    pts[:, 1:] = np.asarray(lengths, dtype=np.float64)[:, :, None] * np.eye(3)

    def cost_of(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cam = np.einsum("nij,npj->npi", R, pts) + t[:, None, :]
        r = (_project_many(K, cam) - kp).reshape(n, 8)
        cost = (r * r).sum(axis=1)  # depths clamped as in _project_many: a path may cross them, the result is checked
        return r, cam, cost

    r, cam, cost = cost_of(R, t)
    damping = np.full(n, 1e-3)
    fx, skew, fy = K[:, 0, 0, None], K[:, 0, 1, None], K[:, 1, 1, None]
    for _ in range(iterations):
        z = np.maximum(cam[..., 2], 1e-6)
        d_proj = np.zeros((n, 4, 2, 3))
        d_proj[..., 0, 0], d_proj[..., 0, 1] = fx / z, skew / z
        d_proj[..., 0, 2] = -(fx * cam[..., 0] + skew * cam[..., 1]) / z**2
        d_proj[..., 1, 1], d_proj[..., 1, 2] = fy / z, -fy * cam[..., 1] / z**2
        a = cam - t[:, None, :]  # R p: d(exp([w]x) R p)/dw = -[R p]x
        d_cam = np.zeros((n, 4, 3, 6))
        d_cam[..., 0, 1], d_cam[..., 0, 2] = a[..., 2], -a[..., 1]
        d_cam[..., 1, 0], d_cam[..., 1, 2] = -a[..., 2], a[..., 0]
        d_cam[..., 2, 0], d_cam[..., 2, 1] = a[..., 1], -a[..., 0]
        d_cam[..., :, 3:] = np.eye(3)
        J = np.einsum("npij,npjk->npik", d_proj, d_cam).reshape(n, 8, 6)
        A = np.einsum("nri,nrj->nij", J, J)
        g = np.einsum("nri,nr->ni", J, r)
        diag = np.einsum("nii->ni", A)
        A_damped = A + (damping[:, None] * diag + 1e-12)[:, :, None] * np.eye(6)
        step = -np.linalg.solve(A_damped, g[..., None])[..., 0]
        if not np.isfinite(step).all():
            step = np.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
        R_new = Rotation.from_rotvec(step[:, :3]).as_matrix() @ R
        t_new = t + step[:, 3:]
        r_new, cam_new, cost_new = cost_of(R_new, t_new)
        better = cost_new < cost
        R[better], t[better], r[better], cam[better], cost[better] = (
            R_new[better],
            t_new[better],
            r_new[better],
            cam_new[better],
            cost_new[better],
        )
        # Converged: an accepted step too small to matter, or a damping so high that no step helps any more (a
        # rejected step is small only because of its damping, which says nothing about convergence).
        done = (better & (np.abs(step).max(axis=1) < 1e-9)) | (~better & (damping >= 1e6)) | (cost < 1e-24)
        damping = np.where(better, np.maximum(damping * 0.3, 1e-12), np.minimum(damping * 10.0, 1e12))
        if done.all():
            break
    return R, t


def _projected_direction(K: np.ndarray, uv_origin: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Image direction at the origin of a 3D direction v: d(π(X_O + s v))/ds up to a positive factor."""
    kv = K @ v
    return kv[:2] - kv[2] * uv_origin


def rotation_from_slopes(K: np.ndarray, uv_origin: np.ndarray, directions: np.ndarray) -> Backprojection:
    """Rotation from the projected origin and the three axes' image directions (3,2) (slope plus sense).

    Each axis lies in the plane through the camera centre and its image line (normal n_i), so
    R = [v1 v2 v3] with v_i ⊥ n_i. Writing v1 in its plane by an angle θ, v2 = ±v1×n2/‖·‖ and v3 = v1×v2,
    the remaining condition v3·n3 = 0 is one equation in θ, bracketed on a grid and solved with brentq.
    The solution whose axes project with the observed senses is kept. Without leg lengths the depth is
    unknown, so t is the unit-depth ray through the origin.
    """
    dirs = np.asarray(directions, dtype=np.float64).reshape(3, 2)
    norms = np.linalg.norm(dirs, axis=1)
    K, kp, reason = _check_input(K, uv_origin, np.asarray(uv_origin).reshape(1, 2) + dirs / np.maximum(norms, 1e-300)[:, None])
    if reason:
        return _fail(reason)
    dirs = kp[1:] - kp[0]
    q = _rays(K, kp)
    normals = np.cross(q[0], q[1:])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    e1 = q[0] / np.linalg.norm(q[0])
    e2 = np.cross(normals[0], e1)

    def frames(theta: np.ndarray, sign: float) -> np.ndarray:
        """Candidate rotations (N,3,3) for angles θ (N,)."""
        v1 = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
        v2 = np.cross(v1, normals[1])
        v2 = sign * v2 / np.maximum(np.linalg.norm(v2, axis=1, keepdims=True), 1e-300)
        return np.stack([v1, v2, np.cross(v1, v2)], axis=2)

    def condition(theta: float, sign: float) -> float:
        return float(frames(np.array([theta]), sign)[0, :, 2] @ normals[2])

    grid = np.linspace(0.0, 2.0 * np.pi, 721)
    best: tuple[float, np.ndarray] | None = None
    for sign in (1.0, -1.0):
        f = frames(grid, sign)[:, :, 2] @ normals[2]
        for i in np.nonzero(np.sign(f[:-1]) * np.sign(f[1:]) <= 0)[0]:
            theta = grid[i] if f[i] == f[i + 1] else brentq(condition, grid[i], grid[i + 1], args=(sign,), xtol=1e-15)
            R = frames(np.array([theta]), sign)[0]
            d = np.stack([_projected_direction(K, kp[0], R[:, k]) for k in range(3)])
            cosines = np.sum(d * dirs, axis=1) / np.maximum(np.linalg.norm(d, axis=1) * np.linalg.norm(dirs, axis=1), 1e-300)
            if best is None or cosines.min() > best[0]:
                best = (float(cosines.min()), R)
    if best is None or best[0] < 0.5:
        return _fail("no rotation explains the observed axis directions")
    return Backprojection(nearest_rotation(best[1]), q[0], True)
