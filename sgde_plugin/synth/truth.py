"""Cross-view truth check: ground-truth points of one camera, seen by its neighbour, agree in depth and colour."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Camera
from ..geometry import invert_transform
from ..splat import lift_depth_torch, transform_points_torch
from .render import RayTiles, torch_threads, trace
from .world import World

_CHUNK = 64


def trace_rays(world: World, rays_cam: np.ndarray, cam_to_world: np.ndarray, time_s: float) -> np.ndarray:
    """Distance to the first hit along arbitrary camera-frame unit rays (n, 3); inf where nothing is hit."""
    n = rays_cam.shape[0]
    pad = (-n) % _CHUNK
    rays = torch.from_numpy(np.concatenate([rays_cam, np.tile([[0.0, 0.0, 1.0]], (pad, 1))])).double()
    rays = rays.reshape(-1, _CHUNK, 3)
    valid = torch.ones(rays.shape[:2], dtype=torch.bool)
    if pad:
        valid[-1, _CHUNK - pad:] = False
    axis = rays.mean(1)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    half = torch.acos((rays * axis[:, None]).sum(-1).clamp(-1, 1)).amax(1) + 2e-3
    tiles = RayTiles(rays.float(), valid, axis.float(), half.float(), torch.zeros(rays.shape[:2]), 0, 0, 0, 1)
    with torch.no_grad(), torch_threads(1):
        hits = trace(world, tiles, cam_to_world, time_s)
    return hits.t.reshape(-1)[:n].double().numpy()


def _bilinear(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of img (H, W[, C]) at uv (n, 2) and the four neighbours' values (4, n[, C])."""
    h, w = img.shape[:2]
    u = np.clip(uv[:, 0], 0, w - 1)
    v = np.clip(uv[:, 1], 0, h - 1)
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    a, b = u - u0, v - v0
    corners = np.stack([img[v0, u0], img[v0, u0 + 1], img[v0 + 1, u0], img[v0 + 1, u0 + 1]]).astype(np.float64)
    wts = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
    if img.ndim == 3:
        wts = wts[..., None]
    return (corners * wts).sum(0), corners


@dataclass(frozen=True)
class CrossViewResult:
    """Outcome of one directed pair A -> B."""

    overlap_px: int
    visible_px: int
    depth_ok: float
    colour_ok: float
    both_ok: float


@dataclass(frozen=True)
class CrossViewPixels:
    """Per checked pixel of A (those whose point falls inside B): position in A and the outcomes."""

    uv_a: np.ndarray
    visible: np.ndarray
    depth_ok: np.ndarray
    colour_ok: np.ndarray


def cross_view_pixels(world: World, cam_a: Camera, cam_b: Camera, ego_to_world: np.ndarray, time_s: float,
                      rgb_a: np.ndarray, depth_a: np.ndarray, rgb_b: np.ndarray, depth_b: np.ndarray,
                      depth_tol: float = 0.01, colour_tol: float = 8.0) -> CrossViewPixels:
    """Project A's ground-truth points into B; say per pixel whether B sees it and whether B's truth agrees.

    A pixel is checked when its point projects inside B with all four bilinear neighbours valid
    (inside B's image circle). Visibility is decided by ray-casting from B's centre. Depth agrees
    when B's bilinearly interpolated inverse depth (exact on planes for pinholes) or B's nearest
    pixel (right at silhouettes) is within `depth_tol` relative; colour likewise within
    `colour_tol` (0..255, max over channels).
    """
    with torch_threads(1):
        return _cross_view_pixels(world, cam_a, cam_b, ego_to_world, time_s, rgb_a, depth_a, rgb_b, depth_b,
                                  depth_tol, colour_tol)


def _cross_view_pixels(world: World, cam_a: Camera, cam_b: Camera, ego_to_world: np.ndarray, time_s: float,
                       rgb_a: np.ndarray, depth_a: np.ndarray, rgb_b: np.ndarray, depth_b: np.ndarray,
                       depth_tol: float, colour_tol: float) -> CrossViewPixels:
    a_to_b = torch.as_tensor(invert_transform(cam_b.sensor_to_ego) @ cam_a.sensor_to_ego)
    pts_a, lifted = lift_depth_torch(torch.as_tensor(np.asarray(depth_a, dtype=np.float64)), cam_a)
    vv, uu = np.nonzero(lifted.numpy())
    uv_a = np.stack([uu, vv], axis=1).astype(np.float64)
    pts_b = transform_points_torch(a_to_b, pts_a).numpy()
    uv_b, inside = cam_b.intrinsics.project(pts_b)
    h, w = depth_b.shape
    inside &= (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= w - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= h - 1)
    idx = np.nonzero(inside)[0]
    _, corners = _bilinear(cam_b.intrinsics.valid_mask().astype(np.float64), uv_b[idx])
    idx = idx[(corners > 0.5).all(0)]
    empty = np.zeros(0, dtype=bool)
    if idx.size == 0:
        return CrossViewPixels(np.zeros((0, 2)), empty, empty, empty)
    pts_b, uv_b = pts_b[idx], uv_b[idx]
    rng = np.linalg.norm(pts_b, axis=1)
    t_hit = trace_rays(world, pts_b / rng[:, None], ego_to_world @ cam_b.sensor_to_ego, time_s)
    visible = t_hit >= rng * (1 - 1e-4) - 1e-3
    expected = cam_b.intrinsics.depth(pts_b)
    inv_b = np.where(depth_b > 0, 1.0 / np.maximum(depth_b, 1e-9), 0.0)
    inv_s, inv_c = _bilinear(inv_b, uv_b)
    d_s = np.where((inv_c > 0).all(0), 1.0 / np.maximum(inv_s, 1e-12), 0.0)
    near_u = np.clip(np.round(uv_b[:, 0]).astype(int), 0, w - 1)
    near_v = np.clip(np.round(uv_b[:, 1]).astype(int), 0, h - 1)
    d_n = depth_b[near_v, near_u].astype(np.float64)
    depth_ok = (np.abs(d_s - expected) <= depth_tol * expected) | (np.abs(d_n - expected) <= depth_tol * expected)
    col_s, _ = _bilinear(rgb_b, uv_b)
    col_n = rgb_b[near_v, near_u].astype(np.float64)
    col_a = rgb_a[vv[idx], uu[idx]].astype(np.float64)
    colour_ok = (np.abs(col_s - col_a).max(1) <= colour_tol) | (np.abs(col_n - col_a).max(1) <= colour_tol)
    return CrossViewPixels(uv_a[idx], visible, depth_ok, colour_ok)


def cross_view_check(world: World, cam_a: Camera, cam_b: Camera, ego_to_world: np.ndarray, time_s: float,
                     rgb_a: np.ndarray, depth_a: np.ndarray, rgb_b: np.ndarray, depth_b: np.ndarray,
                     depth_tol: float = 0.01, colour_tol: float = 8.0) -> CrossViewResult:
    """Summary of `cross_view_pixels`: agreement rates over the pixels B really sees."""
    px = cross_view_pixels(world, cam_a, cam_b, ego_to_world, time_s, rgb_a, depth_a, rgb_b, depth_b,
                           depth_tol, colour_tol)
    n = int(px.visible.sum())
    if n == 0:
        return CrossViewResult(int(px.visible.size), 0, 0.0, 0.0, 0.0)
    v = px.visible
    return CrossViewResult(
        overlap_px=int(v.size),
        visible_px=n,
        depth_ok=float(px.depth_ok[v].mean()),
        colour_ok=float(px.colour_ok[v].mean()),
        both_ok=float((px.depth_ok & px.colour_ok)[v].mean()),
    )
