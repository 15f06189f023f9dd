"""Vectorised rotation helpers for the adjustment (many rotation vectors at once)."""

from __future__ import annotations

import numpy as np


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues, exact near 0)."""
    w = np.asarray(w, dtype=np.float64)
    theta2 = np.sum(w * w, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / (safe * safe))
    K = skew(w)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), angles below pi."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin = np.sin(theta)
    small = sin < 1e-8
    scale = np.where(small, 0.5, theta / (2.0 * np.where(small, 1.0, sin)))
    return v * scale[..., None]


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


def tangent_basis(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each unit ray (N, 3) and to each other: (N, 3), (N, 3)."""
    rays = np.asarray(rays, dtype=np.float64)
    helper = np.where(np.abs(rays[:, 1:2]) < 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(helper, rays)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(rays, e1)
    return e1, e2


def angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle(s) in degrees of rotation matrices (..., 3, 3)."""
    return np.degrees(np.linalg.norm(log_so3(R), axis=-1))
