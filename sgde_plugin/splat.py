"""Depth maps from 3-D points: rigid transforms, z-buffer splatting, depth warping, zero-ignoring min-pool.

The one implementation of "lift, transform, project, keep the nearest" and of "the nearest surface per
block": a torch core (batched where it matters, device-agnostic, float64 by default for geometry) with
thin NumPy wrappers. Depth is in the camera model's convention (z for pinholes, range for fisheyes);
0 means "no value"; a point lands on its nearest pixel (pixel centres at integer coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .cameras import Camera, CameraModel, pixel_grid


def _model(cam: Camera | CameraModel) -> CameraModel:
    return cam.intrinsics if isinstance(cam, Camera) else cam


def transform_points_torch(T: Tensor, points: Tensor) -> Tensor:
    """Apply 4x4 transform(s) T (..., 4, 4) to points (..., N, 3) (T broadcasts over the leading dims)."""
    T = T.to(points.dtype)
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


@dataclass(frozen=True)
class PixelHits:
    """Where points land in a camera: flat pixel index (row * W + col), depth, and whether they land at all."""

    index: Tensor  # (N,) int64, meaningful where `valid`
    depth: Tensor  # (N,) depth in the camera's convention
    valid: Tensor  # (N,) bool: in front, inside the model's field of view and the image


def project_to_pixels(points: Tensor, camera: Camera | CameraModel) -> PixelHits:
    """Project camera-frame points (N, 3) to their nearest pixels (see `PixelHits`)."""
    model = _model(camera)
    uv, ok = model.project_torch(points)
    depth = model.depth_torch(points)
    col, row = torch.round(uv[:, 0]), torch.round(uv[:, 1])
    finite = torch.isfinite(col) & torch.isfinite(row) & torch.isfinite(depth)
    ok = ok & finite & (depth > 0) & (col >= 0) & (col <= model.width - 1) & (row >= 0) & (row <= model.height - 1)
    index = torch.where(ok, row * model.width + col, torch.zeros_like(col)).long()
    return PixelHits(index, depth, ok)


def zbuffer(hits: PixelHits, height: int, width: int) -> Tensor:
    """Depth image (H, W) keeping the nearest depth per pixel among valid hits; 0 where none lands."""
    buf = torch.full((height * width,), torch.inf, dtype=hits.depth.dtype, device=hits.depth.device)
    buf.scatter_reduce_(0, hits.index[hits.valid], hits.depth[hits.valid], reduce="amin")
    buf = torch.where(torch.isinf(buf), torch.zeros_like(buf), buf)
    return buf.reshape(height, width)


def splat_depth_torch(points: Tensor, camera: Camera | CameraModel) -> Tensor:
    """Z-buffer splat of camera-frame points (N, 3) into the camera: depth (H, W), nearest point per pixel."""
    model = _model(camera)
    return zbuffer(project_to_pixels(points, model), model.height, model.width)


def splat_depth(points: np.ndarray, camera: Camera | CameraModel) -> np.ndarray:
    """NumPy wrapper of `splat_depth_torch`: float64 (H, W), 0 = none."""
    return splat_depth_torch(torch.as_tensor(np.asarray(points, dtype=np.float64)), camera).numpy()


def lift_depth_torch(depth: Tensor, camera: Camera | CameraModel) -> tuple[Tensor, Tensor]:
    """Camera-frame 3-D points (M, 3) of the pixels with a finite depth > 0 the model can lift, in row-major
    order, and the bool (H, W) map of those pixels."""
    model = _model(camera)
    if tuple(depth.shape) != (model.height, model.width):
        raise ValueError(f"depth {tuple(depth.shape)} does not match camera size {(model.height, model.width)}")
    pts, ok = model.points_from_depth_torch(pixel_grid(model.width, model.height, depth.dtype, depth.device), depth)
    ok = ok & (depth > 0) & torch.isfinite(depth)
    return pts[ok], ok


def warp_depth_torch(depth: Tensor, src: Camera | CameraModel, dst: Camera | CameraModel, src_to_dst: Tensor
                     ) -> Tensor:
    """Forward-warp camera `src`'s depth map into camera `dst` (4x4 `src_to_dst`): (H_dst, W_dst), z-buffered."""
    return splat_depth_torch(transform_points_torch(src_to_dst, lift_depth_torch(depth, src)[0]), dst)


def warp_depth(depth: np.ndarray, src: Camera | CameraModel, dst: Camera | CameraModel, src_to_dst: np.ndarray
               ) -> np.ndarray:
    """NumPy wrapper of `warp_depth_torch` (float64 geometry): (H_dst, W_dst), 0 = nothing landed."""
    d = torch.as_tensor(np.asarray(depth, dtype=np.float64))
    return warp_depth_torch(d, src, dst, torch.as_tensor(np.asarray(src_to_dst, dtype=np.float64))).numpy()


def min_pool_nonzero_torch(depth: Tensor, ky: int, kx: int | None = None, *, stride: int | None = None,
                           ceil: bool = False, return_indices: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """Minimum non-zero value per ky x kx block of `depth` [..., H, W]; blocks without a value are 0.

    The nearest surface per block (BEVDepth's ground-truth downsampling, with 0 = none). Blocks step by
    the block size, or by `stride` (1: a sliding window). With `ceil`, partial blocks at the right and
    bottom edges are pooled too; otherwise H and W are cut to whole blocks. `return_indices` also gives,
    per block, the flat index (row * W + col) of the chosen pixel. Exports to ONNX (max-pool of the
    negated map) and works in half precision.
    """
    kx = ky if kx is None else kx
    *lead, h, w = depth.shape
    flat = depth.reshape(-1, 1, h, w)
    if ky == kx == 1 and not return_indices:
        return depth
    step = (ky, kx) if stride is None else (stride, stride)
    far_value = float(torch.finfo(depth.dtype).max) if depth.is_floating_point() else float(2**31 - 1)
    far = torch.where(flat > 0, flat, torch.full_like(flat, far_value))
    pooled = F.max_pool2d(-far, kernel_size=(ky, kx), stride=step, ceil_mode=ceil, return_indices=return_indices)
    if return_indices:
        pooled, index = pooled
    pooled = -pooled
    pooled = torch.where(pooled >= far_value, torch.zeros_like(pooled), pooled)
    out = pooled.reshape(*lead, *pooled.shape[-2:])
    return (out, index.reshape(*lead, *index.shape[-2:])) if return_indices else out


def min_pool_nonzero(depth: np.ndarray, ky: int, kx: int | None = None, *extra: np.ndarray
                     ) -> tuple[np.ndarray, ...]:
    """NumPy wrapper: min-pool a depth map (H, W) (0 = none) over ky x kx blocks, partial edge blocks included;
    each `extra` map (H, W) follows the chosen pixel (0 where the block has no depth)."""
    pooled, index = min_pool_nonzero_torch(torch.as_tensor(np.ascontiguousarray(depth)), ky, kx, ceil=True,
                                           return_indices=True)
    out = pooled.numpy()
    idx = index.numpy()
    return (out, *(np.where(out > 0, e.reshape(-1)[idx], 0).astype(e.dtype) for e in extra))


__all__ = [
    "PixelHits",
    "lift_depth_torch",
    "min_pool_nonzero",
    "min_pool_nonzero_torch",
    "project_to_pixels",
    "splat_depth",
    "splat_depth_torch",
    "transform_points_torch",
    "warp_depth",
    "warp_depth_torch",
    "zbuffer",
]
