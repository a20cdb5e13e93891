"""A constant-velocity Kalman filter on SE(3) for one tracked object, in the camera frame.

State: translation t and its velocity v, rotation R and its angular velocity ω (rad/s, camera frame:
R(τ+dt) = exp(ω dt) R(τ)). The filter runs on the error state δ = (δt, δv, δθ, δω) with R_true = exp(δθ) R,
which matches the pose covariance's convention (x, y, z, rx, ry, rz; a rotation about the camera's axes applied on
the left; m², rad²), so a measurement's covariance is its noise as it stands. A measurement whose innovation lies
beyond the gate (Mahalanobis d² of the 6-D pose innovation) is refused instead of followed: a symmetric flip or a
wrong detection moves the pose by far more than the state and the measurement's uncertainty allow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

_H = np.zeros((6, 12))
_H[0:3, 0:3] = np.eye(3)
_H[3:6, 6:9] = np.eye(3)


@dataclass(frozen=True)
class FilterConfig:
    """Process noise of the constant-velocity model and the gate."""

    accel_std: float = 0.5
    """Translational acceleration noise across the line of sight (m/s²): a camera that turns, hand-held or on an
    arm, moves what it sees sideways far more than in depth."""
    depth_accel_std: float | None = 0.02
    """Translational acceleration noise along the line of sight (m/s²); None: `accel_std`. Small, so the depth,
    a single image's weakest reading, is averaged over many frames."""
    angular_accel_std: float = 0.5
    """Angular acceleration noise (rad/s²)."""
    velocity_std: float = 0.2
    """Prior on a new track's speed (m/s)."""
    angular_velocity_std: float = 1.0
    """Prior on a new track's angular speed (rad/s)."""
    gate_d2: float = 22.46
    """Mahalanobis gate on the 6-D innovation: the chi-square 99.9 % point for 6 degrees of freedom."""


def _exp(rotvec: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rotvec).as_matrix()


def _log(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def _white_acceleration(dt: float, density: np.ndarray) -> np.ndarray:
    """Process noise of (position, velocity) over dt for white acceleration noise of (3, 3) spectral density."""
    block = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    return np.kron(block, density)


def _ray_density(t: np.ndarray, across_std: float, along_std: float) -> np.ndarray:
    """Acceleration density with `across_std` perpendicular to the line of sight through t and `along_std` on it."""
    ray = t / max(float(np.linalg.norm(t)), 1e-9)
    along = np.outer(ray, ray)
    return across_std**2 * (np.eye(3) - along) + along_std**2 * along


@dataclass
class PoseFilter:
    """One object's filtered pose. `predict(dt)` moves it along its velocities; `update` folds in a measured pose
    with its covariance (or refuses it at the gate)."""

    config: FilterConfig
    R: np.ndarray
    t: np.ndarray
    v: np.ndarray
    w: np.ndarray
    P: np.ndarray
    """(12, 12) error-state covariance: (δt, δv, δθ, δω)."""

    @classmethod
    def start(cls, config: FilterConfig, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> PoseFilter:
        """A filter at a measured pose, at rest, with the measurement's covariance and the velocity priors."""
        P = np.zeros((12, 12))
        P[0:3, 0:3] = covariance[0:3, 0:3]
        P[6:9, 6:9] = covariance[3:6, 3:6]
        P[0:3, 6:9] = covariance[0:3, 3:6]
        P[6:9, 0:3] = covariance[3:6, 0:3]
        P[3:6, 3:6] = np.eye(3) * config.velocity_std**2
        P[9:12, 9:12] = np.eye(3) * config.angular_velocity_std**2
        return cls(config, np.array(R, float), np.array(t, float), np.zeros(3), np.zeros(3), P)

    def predict(self, dt: float) -> None:
        """Move the state dt seconds ahead (dt ≤ 0: unchanged)."""
        if dt <= 0:
            return
        self.t = self.t + self.v * dt
        self.R = _exp(self.w * dt) @ self.R
        F = np.eye(12)
        F[0:3, 3:6] = np.eye(3) * dt
        F[6:9, 9:12] = np.eye(3) * dt
        Q = np.zeros((12, 12))
        c = self.config
        along = c.accel_std if c.depth_accel_std is None else c.depth_accel_std
        Q[0:6, 0:6] = _white_acceleration(dt, _ray_density(self.t, c.accel_std, along))
        Q[6:12, 6:12] = _white_acceleration(dt, np.eye(3) * c.angular_accel_std**2)
        self.P = F @ self.P @ F.T + Q

    def innovation(self, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The measured pose's difference from the state (δt, δθ), its covariance S and its Mahalanobis d²."""
        y = np.concatenate([t - self.t, _log(R @ self.R.T)])
        S = _H @ self.P @ _H.T + covariance
        return y, S, float(y @ np.linalg.solve(S, y))

    def update(self, R: np.ndarray, t: np.ndarray, covariance: np.ndarray) -> tuple[bool, float]:
        """Fold in a measured pose with its (6, 6) covariance; (False, d²) where it lies beyond the gate (the
        state unchanged), else (True, d²)."""
        y, S, d2 = self.innovation(R, t, covariance)
        if not np.isfinite(d2) or d2 > self.config.gate_d2:
            return False, d2
        K = self.P @ _H.T @ np.linalg.inv(S)
        delta = K @ y
        self.t = self.t + delta[0:3]
        self.v = self.v + delta[3:6]
        self.R = _exp(delta[6:9]) @ self.R
        self.w = self.w + delta[9:12]
        A = np.eye(12) - K @ _H
        self.P = A @ self.P @ A.T + K @ covariance @ K.T  # Joseph form: stays symmetric and positive
        self.P = 0.5 * (self.P + self.P.T)
        return True, d2

    def update_posterior(self, R: np.ndarray, t: np.ndarray, information: np.ndarray) -> tuple[bool, float]:
        """Fold in a pose that already is the posterior of some evidence (of (6, 6) `information`) given this
        filter's prediction as prior, e.g. a contour refined from it: as the one measurement z with covariance
        `information`⁻¹ that this update turns into that pose, z - x = (I + information⁻¹ P⁻¹)(pose - x)."""
        P = self.covariance
        L = np.asarray(information, float) + np.eye(6) * 1e-9
        delta = np.concatenate([t - self.t, _log(R @ self.R.T)])
        z = delta + np.linalg.solve(L, np.linalg.solve(P, delta))
        noise = np.linalg.inv(L)
        return self.update(_exp(z[3:]) @ self.R, self.t + z[:3], 0.5 * (noise + noise.T))

    @property
    def covariance(self) -> np.ndarray:
        """(6, 6) covariance of the pose (x, y, z, rx, ry, rz)."""
        return _H @ self.P @ _H.T
