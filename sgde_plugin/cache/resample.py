"""Resizing and augmenting priors and images with one pixel-coordinate affine (3x3) per sample.

A matrix A maps a source pixel (u, v, 1) to an output pixel (contracts: the centre of the top-left
pixel is (0, 0)). Images are resampled bilinearly (after area pooling when shrinking by 2x or
more). Depth maps (priors, ground truth) are never interpolated: when shrinking, blocks are first
min-pooled over their valid values (the nearest surface wins, as for lidar depth targets), then
every output pixel takes the value of the nearest source pixel, so no depth is invented across an
edge or a hole.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..splat import min_pool_nonzero


def as_affine(matrix: np.ndarray) -> np.ndarray:
    """A 3x3 pixel affine from a 3x3 matrix or a BEVDepth-style 4x4 `ida_mat`."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 3):
        out = m.copy()
    elif m.shape == (4, 4):
        out = np.eye(3)
        out[:2, :2] = m[:2, :2]
        out[:2, 2] = m[:2, 3]
    elif m.shape == (2, 3):
        out = np.eye(3)
        out[:2] = m
    else:
        raise ValueError(f"an image augmentation matrix is 2x3, 3x3 or 4x4, not {m.shape}")
    if not np.allclose(out[2], [0, 0, 1]):
        raise ValueError("the augmentation matrix must be affine (last row [0, 0, 1])")
    return out


def resize_matrix(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> np.ndarray:
    """The affine of a plain resize from (H, W) to (h, w), pixel centres mapped onto pixel centres."""
    sy, sx = dst_hw[0] / src_hw[0], dst_hw[1] / src_hw[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def ida_matrix(
    resize: float | tuple[float, float],
    crop: tuple[int, int] = (0, 0),
    flip: bool = False,
    rotate_deg: float = 0.0,
    out_hw: tuple[int, int] | None = None,
) -> np.ndarray:
    """BEVDepth-style image augmentation (resize, crop at (x0, y0), horizontal flip, rotation about
    the output centre) as a 3x3 pixel affine in the pixel-centre convention."""
    rx, ry = (resize, resize) if np.isscalar(resize) else resize
    m = np.array([[rx, 0.0, 0.5 * rx - 0.5], [0.0, ry, 0.5 * ry - 0.5], [0.0, 0.0, 1.0]])
    m = np.array([[1.0, 0.0, -crop[0]], [0.0, 1.0, -crop[1]], [0.0, 0.0, 1.0]]) @ m
    if out_hw is None and (flip or rotate_deg):
        raise ValueError("flip and rotation need the output size out_hw")
    if flip:
        w = out_hw[1]
        m = np.array([[-1.0, 0.0, w - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ m
    if rotate_deg:
        cx, cy = (out_hw[1] - 1) / 2.0, (out_hw[0] - 1) / 2.0
        a = math.radians(rotate_deg)
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy], [0.0, 0.0, 1.0]])
        m = rot @ m
    return m


def _pool_factors(affine: np.ndarray) -> tuple[int, int]:
    """Integer block sizes (ky, kx) by which the source can be pooled before the warp."""
    sx = float(np.hypot(affine[0, 0], affine[1, 0]))
    sy = float(np.hypot(affine[0, 1], affine[1, 1]))
    kx = max(1, math.floor(1.0 / sx + 1e-9)) if sx > 0 else 1
    ky = max(1, math.floor(1.0 / sy + 1e-9)) if sy > 0 else 1
    return ky, kx


def _pool_matrix(ky: int, kx: int) -> np.ndarray:
    """Affine from pooled-pixel coordinates to source-pixel coordinates."""
    return np.array([[kx, 0.0, (kx - 1) / 2.0], [0.0, ky, (ky - 1) / 2.0], [0.0, 0.0, 1.0]])


def min_pool_depth(depth: np.ndarray, ky: int, kx: int, *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """Min-pool a depth map (0 = none) over ky x kx blocks among valid values; extra maps follow the
    chosen pixel. Edge blocks are padded with 'none' (`sgde_plugin.splat.min_pool_nonzero`)."""
    return min_pool_nonzero(np.asarray(depth, dtype=np.float32), ky, kx, *extra)


def _nearest_indices(affine: np.ndarray, src_hw: tuple[int, int], out_hw: tuple[int, int]):
    """For every output pixel, the nearest source pixel (rows, cols) and whether it is inside."""
    inv = np.linalg.inv(affine)
    h, w = out_hw
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    if inv[0, 1] == 0 and inv[1, 0] == 0:  # no rotation: rows and columns separate (the common resize)
        cols = np.floor(inv[0, 0] * u + inv[0, 2] + 0.5).astype(np.int64)
        rows = np.floor(inv[1, 1] * v + inv[1, 2] + 0.5).astype(np.int64)
    else:
        cols = np.floor(inv[0, 0] * u + inv[0, 1] * v + inv[0, 2] + 0.5).astype(np.int64)
        rows = np.floor(inv[1, 0] * u + inv[1, 1] * v + inv[1, 2] + 0.5).astype(np.int64)
    inside = (cols >= 0) & (cols < src_hw[1]) & (rows >= 0) & (rows < src_hw[0])
    rows = np.clip(rows, 0, src_hw[0] - 1)
    cols = np.clip(cols, 0, src_hw[1] - 1)
    return np.broadcast_to(rows, out_hw), np.broadcast_to(cols, out_hw), np.broadcast_to(inside, out_hw)


def warp_depth_affine(
    depth: np.ndarray, matrix: np.ndarray, out_hw: tuple[int, int], *extra: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Warp a depth map (0 = none) by a pixel affine to out_hw without inventing depths: min-pool of
    valid values when shrinking, then nearest sampling. Extra maps (e.g. confidence) follow the
    chosen pixels. Returns (depth, *extra)."""
    affine = as_affine(matrix)
    depth = np.asarray(depth, dtype=np.float32)
    ky, kx = _pool_factors(affine)
    maps = (depth, *extra)
    if ky > 1 or kx > 1:
        maps = min_pool_depth(depth, ky, kx, *extra)
        affine = affine @ _pool_matrix(ky, kx)
    rows, cols, inside = _nearest_indices(affine, maps[0].shape, out_hw)
    out = []
    for m in maps:
        o = m[rows, cols]
        o[~inside] = 0
        out.append(o)
    out[0] = np.where(np.isfinite(out[0]) & (out[0] > 0), out[0], 0).astype(np.float32)
    for i in range(1, len(out)):
        out[i] = np.where(out[0] > 0, out[i], 0).astype(maps[i].dtype)
    return tuple(out)


def warp_image(image: np.ndarray, matrix: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """Warp an image (H, W[, C]) by a pixel affine to out_hw: area pooling by integer factors when
    shrinking by 2x or more, then bilinear; outside the source is 0."""
    affine = as_affine(matrix)
    ky, kx = _pool_factors(affine)
    img = np.ascontiguousarray(image)
    if ky > 1 or kx > 1:
        h, w = img.shape[:2]
        hp, wp = -(-h // ky) * ky, -(-w // kx) * kx
        if (hp, wp) != (h, w):
            img = cv2.copyMakeBorder(img, 0, hp - h, 0, wp - w, cv2.BORDER_REPLICATE)
        img = cv2.resize(img, (wp // kx, hp // ky), interpolation=cv2.INTER_AREA)
        affine = affine @ _pool_matrix(ky, kx)
    return cv2.warpAffine(
        img, affine[:2], (out_hw[1], out_hw[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )


def resize_depth(depth: np.ndarray, out_hw: tuple[int, int], *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """Resize a depth map (0 = none) to out_hw without inventing depths (see `warp_depth_affine`)."""
    return warp_depth_affine(depth, resize_matrix(depth.shape[:2], out_hw), out_hw, *extra)


__all__ = [
    "as_affine",
    "ida_matrix",
    "min_pool_depth",
    "resize_depth",
    "resize_matrix",
    "warp_depth_affine",
    "warp_image",
]
