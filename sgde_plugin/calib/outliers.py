"""Outlier removal per image pair: a loose epipolar gate from the initial poses, then OpenCV's
Graph-Cut RANSAC (USAC_ACCURATE) on the essential matrix.

Matches arrive as unit rays (any camera model). Each side is rotated so that the mean ray points
along +z and divided by z, which gives normalised coordinates valid for the identity intrinsic
matrix: the essential matrix of the rotated frames has the same inliers as the one of the cameras,
and fisheye rays beyond 90 degrees from the optical axis stay usable.
"""

from __future__ import annotations

import cv2
import numpy as np


def rotation_to_z(v: np.ndarray) -> np.ndarray:
    """A rotation matrix R with R @ v/|v| = (0, 0, 1)."""
    v = np.asarray(v, dtype=np.float64)
    v = v / np.linalg.norm(v)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(v, z)
    s, c = np.linalg.norm(axis), float(v @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def epipolar_angle_deg(rays_a: np.ndarray, rays_b: np.ndarray, R_ba: np.ndarray, t_ba: np.ndarray) -> np.ndarray:
    """Angle (deg) between each ray of B and the epipolar plane of its ray of A, for X_b = R_ba X_a + t_ba."""
    n = np.cross(np.asarray(t_ba, dtype=np.float64)[None, :], rays_a @ R_ba.T)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    s = np.abs(np.sum(n * rays_b, axis=1)) / np.where(ok, norm, 1.0)
    return np.where(ok, np.degrees(np.arcsin(np.clip(s, 0.0, 1.0))), 0.0)


def essential_inliers(
    rays_a: np.ndarray,
    rays_b: np.ndarray,
    threshold_px: float,
    focal_px: float,
    prob: float = 0.999,
    method: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Inlier mask of ray matches under one essential matrix (USAC_ACCURATE by default).

    `threshold_px` is the RANSAC threshold in pixels of a camera with `focal_px` pixels per radian.
    Returns all False when there are fewer than 8 usable matches or no model is found.
    """
    n = rays_a.shape[0]
    out = np.zeros(n, dtype=bool)
    if n < 8:
        return out
    Ra = rotation_to_z(rays_a.mean(axis=0))
    Rb = rotation_to_z(rays_b.mean(axis=0))
    va, vb = rays_a @ Ra.T, rays_b @ Rb.T
    usable = (va[:, 2] > 0.2) & (vb[:, 2] > 0.2)
    if usable.sum() < 8:
        return out
    pa = (va[usable, :2] / va[usable, 2:3]).astype(np.float64)
    pb = (vb[usable, :2] / vb[usable, 2:3]).astype(np.float64)
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(
        pa, pb, np.eye(3), method=cv2.USAC_ACCURATE if method is None else method, prob=prob,
        threshold=threshold_px / focal_px,
    )
    if E is None or mask is None:
        return out
    idx = np.flatnonzero(usable)
    out[idx] = mask.ravel().astype(bool)
    return out


def _epipolar_px(d: np.ndarray, R0: np.ndarray, t0: np.ndarray, rays_a: np.ndarray, rays_b: np.ndarray,
                 focal_px: float) -> np.ndarray:
    """Signed epipolar distances (px) of matches under rel = D(d)^-1 rel0 per match (R0 (N, 3, 3), t0 (N, 3)),
    D(d) a correction of camera b's mount: rotation vector d[:3], translation d[3:]."""
    from ..geometry import rodrigues

    RD = rodrigues(d[:3])
    R = np.einsum("ji,njk->nik", RD, R0)  # RD^T R0
    t = (t0 - d[3:]) @ RD  # RD^T (t0 - tau)
    n = np.cross(t, np.einsum("nij,nj->ni", R, rays_a))
    norm = np.maximum(np.linalg.norm(n, axis=1), 1e-12)
    return np.sum(n * rays_b, axis=1) / norm * focal_px


def mount_consensus(rel0: np.ndarray, rays_a: np.ndarray, rays_b: np.ndarray, focal_px: float,
                    scale_px: float = 1.0, sigma_rot_deg: float = 5.0, sigma_t_m: float = 0.1,
                    iterations: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """One mount correction of camera b that all matches of a camera pair agree with, whatever their frames.

    `rel0` (N, 4, 4): per match, the starting relative pose (camera a at its frame -> camera b at its frame,
    from the ego motion and the starting extrinsics). The two mounts are rigid, so one correction D of b's
    mount (3 rotation + 3 translation unknowns, weak priors of `sigma_rot_deg` / `sigma_t_m`) must explain
    every observation pair: robust Gauss-Newton (Cauchy, `scale_px`) on the epipolar distances. A free
    essential matrix per observation pair needs 5+ points and, in a narrow strip, fits wrong matches too;
    this model is shared by thousands. Returns the correction (6,) and each match's distance (px) under it.
    """
    d = np.zeros(6)
    R0, t0 = rel0[:, :3, :3], rel0[:, :3, 3]
    prior = np.r_[np.full(3, 1.0 / np.radians(sigma_rot_deg)), np.full(3, 1.0 / sigma_t_m)]
    for _ in range(iterations):
        e = _epipolar_px(d, R0, t0, rays_a, rays_b, focal_px)
        J = np.empty((e.size, 6))
        for k in range(6):
            step = np.zeros(6)
            step[k] = 1e-6
            J[:, k] = (_epipolar_px(d + step, R0, t0, rays_a, rays_b, focal_px) - e) / 1e-6
        w = 1.0 / (1.0 + (e / scale_px) ** 2)  # Cauchy IRLS weights
        H = J.T @ (J * w[:, None]) + np.diag(prior**2)
        g = J.T @ (w * e) + prior**2 * d
        delta = np.linalg.solve(H, -g)
        d = d + delta
        if np.linalg.norm(delta[:3]) < 1e-7 and np.linalg.norm(delta[3:]) < 1e-6:
            break
    return d, _epipolar_px(d, R0, t0, rays_a, rays_b, focal_px)
