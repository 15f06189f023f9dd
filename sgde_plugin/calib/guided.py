"""Guided matching on narrow overlaps: find a keypoint of one view in the other along its predicted
epipolar segment by normalised cross-correlation, then refine to sub-pixel by Lucas-Kanade.

Descriptor matching needs the same keypoint to be detected in both images and its descriptor to survive
the ratio test. In an overlap strip of 20-50 px (random rigs with 5-10 degrees of overlap) neither holds:
of the keypoints of one view that the other sees, about a third are detected there, and the descriptors
of keypoints near the strip's edge see the blank beyond it. Both views are virtual pinholes aimed at
the overlap at one angular resolution (`views.overlap_view`), so the neighbourhood of a point looks the
same in both up to parallax: a patch of one view is searched in the other inside a band around the
epipolar segment that the starting rig predicts (depths from `min_depth_m` to infinity), the band as wide
as the starting rig's uncertainty. A peak must be strong (NCC) and unique along the band; the
observation pair's verification (`outliers`) then checks the guided matches like any other.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class GuidedConfig:
    """Settings of the guided search (pixels are the views' pixels)."""

    half_patch: int = 5
    band_deg: float = 2.5
    min_depth_m: float = 1.0
    min_ncc: float = 0.85
    unique_margin: float = 0.05
    unique_radius_px: float = 3.0
    lk_max_shift_px: float = 1.5


def epipolar_segment(uv_a: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, rel: np.ndarray,
                     min_depth_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For pixels (N, 2) of view a: where their points land in view b at infinity and at `min_depth_m`
    (ray depth), for X_b = rel[:3, :3] X_a + rel[:3, 3]; and which ends are in front of b (N,)."""
    h = np.c_[uv_a, np.ones(len(uv_a))]
    rays = h @ np.linalg.inv(K_a).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    R, t = rel[:3, :3], rel[:3, 3]
    far = rays @ R.T
    near = far * min_depth_m + t
    ok = (far[:, 2] > 1e-3) & (near[:, 2] > 1e-3)
    p_far = far @ K_b.T
    p_near = near @ K_b.T
    z_far, z_near = np.where(ok, p_far[:, 2], 1.0), np.where(ok, p_near[:, 2], 1.0)
    return p_far[:, :2] / z_far[:, None], p_near[:, :2] / z_near[:, None], ok


def _distance_to_segment(x: np.ndarray, y: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Distance of grid points (x, y) to the segment p0-p1."""
    d = p1 - p0
    L2 = float(d @ d)
    s = np.zeros_like(x) if L2 < 1e-12 else np.clip(((x - p0[0]) * d[0] + (y - p0[1]) * d[1]) / L2, 0.0, 1.0)
    return np.hypot(x - (p0[0] + s * d[0]), y - (p0[1] + s * d[1]))


def _clip_segment(p0: np.ndarray, p1: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The part of segment p0-p1 inside the box [lo, hi] (Liang-Barsky), or None."""
    d = p1 - p0
    s0, s1 = 0.0, 1.0
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if p0[k] < lo[k] or p0[k] > hi[k]:
                return None
            continue
        a, b = (lo[k] - p0[k]) / d[k], (hi[k] - p0[k]) / d[k]
        s0, s1 = max(s0, min(a, b)), min(s1, max(a, b))
    if s0 > s1:
        return None
    return p0 + s0 * d, p0 + s1 * d


def _search_one(gray_b: np.ndarray, fits_b: np.ndarray, patch: np.ndarray, p0: np.ndarray, p1: np.ndarray,
                band: float, cfg: GuidedConfig) -> tuple[float, float, float] | None:
    """Best NCC position (x, y, score) of `patch` in b within `band` px of segment p0-p1 where the patch
    fits on usable pixels (`fits_b`), or None when it is weak or not unique."""
    r = cfg.half_patch
    h, w = gray_b.shape
    seg = _clip_segment(p0, p1, np.array([r - band, r - band]), np.array([w - 1 - r + band, h - 1 - r + band]))
    if seg is None:
        return None
    p0, p1 = seg
    x0 = int(np.floor(max(0.0, min(p0[0], p1[0]) - band - r)))
    x1 = int(np.ceil(min(w - 1.0, max(p0[0], p1[0]) + band + r)))
    y0 = int(np.floor(max(0.0, min(p0[1], p1[1]) - band - r)))
    y1 = int(np.ceil(min(h - 1.0, max(p0[1], p1[1]) + band + r)))
    if x1 - x0 < 2 * r + 1 or y1 - y0 < 2 * r + 1:
        return None
    allowed = fits_b[y0 + r:y1 - r + 1, x0 + r:x1 - r + 1]
    if not allowed.any():
        return None
    ncc = cv2.matchTemplate(gray_b[y0:y1 + 1, x0:x1 + 1], patch, cv2.TM_CCOEFF_NORMED)
    cy, cx = np.nonzero(allowed)
    xs, ys = (cx + x0 + r).astype(np.float64), (cy + y0 + r).astype(np.float64)
    near = _distance_to_segment(xs, ys, p0, p1) <= band
    if not near.any():
        return None
    xs, ys, vals = xs[near], ys[near], ncc[cy[near], cx[near]]
    k = int(np.argmax(vals))
    best = float(vals[k])
    if not best >= cfg.min_ncc:
        return None
    far = np.hypot(xs - xs[k], ys - ys[k]) > cfg.unique_radius_px
    second = float(vals[far].max()) if far.any() else -1.0
    if second > best - cfg.unique_margin:
        return None
    return float(xs[k]), float(ys[k]), best


def _padded(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`img` padded with zeros at the bottom and right to `size` (rows, cols)."""
    out = np.zeros(size, dtype=img.dtype)
    out[:img.shape[0], :img.shape[1]] = img
    return out


def guided_search(gray_a: np.ndarray, valid_a: np.ndarray, gray_b: np.ndarray, valid_b: np.ndarray,
                  uv_a: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, rel: np.ndarray,
                  cfg: GuidedConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Positions in view b of the view-a pixels `uv_a` (N, 2): (indices into uv_a that were found, their
    sub-pixel positions in b (n, 2)). `rel` maps view a's frame to view b's (starting rig)."""
    cfg = cfg or GuidedConfig()
    none = (np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
    if len(uv_a) == 0:
        return none
    r = cfg.half_patch
    band = float(K_b[0, 0]) * np.radians(cfg.band_deg)
    p_far, p_near, ok = epipolar_segment(uv_a, K_a, K_b, rel, cfg.min_depth_m)
    h, w = gray_a.shape
    found, pos = [], []
    k = 2 * r + 1  # where a patch centred on a pixel of b lies wholly on usable pixels
    fits_b = cv2.erode(valid_b.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT,
                       borderValue=0) > 0
    for i in np.flatnonzero(ok):
        x, y = int(round(uv_a[i, 0])), int(round(uv_a[i, 1]))
        if x - r < 0 or y - r < 0 or x + r >= w or y + r >= h or not valid_a[y - r:y + r + 1, x - r:x + r + 1].all():
            continue
        patch = gray_a[y - r:y + r + 1, x - r:x + r + 1]
        if float(patch.std()) < 2.0:  # flat: no position to find
            continue
        frac = uv_a[i] - [x, y]  # the patch is centred on the integer pixel: its segment is shifted by -frac
        hit = _search_one(gray_b, fits_b, patch, p_far[i] - frac, p_near[i] - frac, band, cfg)
        if hit is not None:
            found.append(i)
            pos.append(np.asarray(hit[:2]) + frac)
    if not found:
        return none
    idx, guess = np.asarray(found, dtype=np.int64), np.asarray(pos, dtype=np.float64)
    # sub-pixel: Lucas-Kanade from the integer peak, kept when it converged close to it
    pts_a = uv_a[idx].astype(np.float32).reshape(-1, 1, 2)
    pts_b = guess.astype(np.float32).reshape(-1, 1, 2)
    win = (2 * r + 1, 2 * r + 1)
    size = (max(gray_a.shape[0], gray_b.shape[0]), max(gray_a.shape[1], gray_b.shape[1]))  # LK needs one size
    refined, status, _ = cv2.calcOpticalFlowPyrLK(
        _padded(gray_a, size), _padded(gray_b, size), pts_a, pts_b.copy(), winSize=win, maxLevel=0,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
    refined = refined.reshape(-1, 2).astype(np.float64)
    good = (status.ravel() == 1) & (np.linalg.norm(refined - guess, axis=1) <= cfg.lk_max_shift_px)
    return idx[good], refined[good]
