"""Rigid-body helpers in NumPy: rotations, quaternions, 4x4 transforms (float64 throughout)."""

from __future__ import annotations

import numpy as np

ORTHONORMAL_TOL = 1e-6


def rotation_error(R: np.ndarray) -> float:
    """How far a 3x3 matrix is from a proper rotation: max |R^T R - I| (inf for det <= 0 or non-finite)."""
    R = np.asarray(R, dtype=np.float64)
    # entries beyond 2 cannot belong to a rotation, and their products may overflow
    if R.shape != (3, 3) or not np.all(np.isfinite(R)) or np.abs(R).max() > 2.0 or np.linalg.det(R) <= 0:
        return float("inf")
    return float(np.abs(R.T @ R - np.eye(3)).max())


def vector_norm(v: np.ndarray) -> float:
    """Euclidean norm of a finite vector, scaled first so that huge entries (1e308) do not overflow."""
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    big = float(np.abs(v).max(initial=0.0))
    return float(np.linalg.norm(v / big)) * big if big > 0 else 0.0


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homogeneous transform(s) (..., 4, 4) from rotation(s) (..., 3, 3) and translation(s) (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = np.asarray(t, dtype=np.float64).reshape(*R.shape[:-2], 3)
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) (..., 4, 4)."""
    R = np.swapaxes(np.asarray(T, dtype=np.float64)[..., :3, :3], -1, -2)
    return make_transform(R, -np.einsum("...ij,...j->...i", R, T[..., :3, 3]))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    w = np.asarray(w, dtype=np.float64)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], axis=-1),
            np.stack([w[..., 2], z, -w[..., 0]], axis=-1),
            np.stack([-w[..., 1], w[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (axis * angle, radians; exact near 0)."""
    w = np.asarray(rvec, dtype=np.float64)
    theta2 = np.sum(w * w, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / (safe * safe))
    K = skew(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (axis * angle) of rotation matrices (..., 3, 3), angles up to pi."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sin(theta)
    small = sin < 1e-8
    out = v * np.where(small, 0.5, theta / (2.0 * np.where(small, 1.0, sin)))[..., None]
    near_pi = np.pi - theta < 1e-6
    if np.any(near_pi):
        # v vanishes at pi: the axis is the largest column of (R + I) / 2
        flat_R, flat_out = R.reshape(-1, 3, 3), out.reshape(-1, 3)
        for k in np.flatnonzero(near_pi.reshape(-1)):
            B = (flat_R[k] + np.eye(3)) / 2
            i = int(np.argmax(np.diag(B)))
            axis = B[:, i] / np.sqrt(B[i, i])
            flat_out[k] = axis / np.linalg.norm(axis) * theta.reshape(-1)[k]
        out = flat_out.reshape(out.shape)
    return out


def rotation_angle_deg(R: np.ndarray) -> float | np.ndarray:
    """Angle in degrees of a rotation matrix (a float), or of each of (..., 3, 3) (an array)."""
    angle = np.degrees(np.linalg.norm(rotation_vector(R), axis=-1))
    return float(angle) if np.ndim(angle) == 0 else angle


def mean_transform(transforms: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Mean of rigid transforms (K, 4, 4), weighted by `weights` (K,) when given: the rotation nearest (Frobenius)
    to the mean rotation matrix, the mean translation (the chordal L2 mean; for rotations a few hundredths of a
    degree apart it is their centroid)."""
    T = np.asarray(transforms, dtype=np.float64)
    w = np.full(len(T), 1.0 / len(T)) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    U, _, Vt = np.linalg.svd(np.einsum("k,kij->ij", w, T[:, :3, :3]))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return make_transform(R, w @ T[:, :3, 3])


def quaternion_to_rotation(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion given as (w, x, y, z), or (..., 3, 3) of (..., 4); normalised first."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) with w >= 0 of a rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


# Camera frame (x right, y down, z forward) -> a body frame (x forward, y left, z up) when the
# camera looks straight along the body's x axis.
CAMERA_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def yaw_pitch_roll_to_rotation(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Body rotation (ego x forward, y left, z up) from yaw about z, pitch about y, roll about x, radians."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def camera_mount(yaw: float, position: np.ndarray, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """sensor_to_ego of a camera at `position` (ego metres) looking along azimuth `yaw` (radians, left +)."""
    R = yaw_pitch_roll_to_rotation(yaw, pitch, roll) @ CAMERA_TO_BODY
    return make_transform(R, position)
