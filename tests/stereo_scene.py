"""Analytic scenes for the stereo tests: textured planes rendered by exact ray-plane intersection."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sgde_plugin.cameras import Camera, KannalaBrandt, Pinhole
from sgde_plugin.geometry import camera_mount
from sgde_plugin.stereo.rectify import torch_threads


@dataclass(frozen=True)
class Plane:
    """A plane through `point` with unit `normal`; texture coordinates along `axis_u`, `axis_v` (ego)."""

    point: np.ndarray
    normal: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    seed: int = 0
    extent: tuple[float, float] | None = None  # half sizes along axis_u, axis_v around `point`; None = unbounded


def wall(distance: float, azimuth_deg: float, height: float = 1.5, seed: int = 0) -> Plane:
    """A vertical wall facing the ego origin at `distance` along `azimuth_deg` (ego, left +)."""
    a = math.radians(azimuth_deg)
    n = np.array([math.cos(a), math.sin(a), 0.0])
    return Plane(n * distance + np.array([0, 0, height]), -n, np.array([-n[1], n[0], 0.0]), np.array([0, 0, 1.0]), seed)


def _texture(s: np.ndarray, t: np.ndarray, seed: int) -> np.ndarray:
    """Smooth random texture in [0, 1]: a sum of 40 sinusoids, wavelengths 0.15 to 2 m."""
    rng = np.random.default_rng(seed)
    out = np.zeros_like(s)
    for _ in range(40):
        lam = math.exp(rng.uniform(math.log(0.15), math.log(2.0)))
        ang = rng.uniform(0, math.pi)
        ph = rng.uniform(0, 2 * math.pi)
        out += np.cos(2 * math.pi / lam * (math.cos(ang) * s + math.sin(ang) * t) + ph)
    return 0.5 + 0.5 * np.tanh(out / 4)


def render(planes: list[Plane], camera: Camera, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """RGB uint8 and depth float32 (camera convention, 0 = nothing hit) of the planes seen by `camera`."""
    k = supersample
    big = camera.intrinsics.resized(camera.width * k, camera.height * k)
    with torch_threads(1):
        rays, valid = big.ray_grid()
    rays, valid = rays.numpy(), valid.numpy()
    R, c = camera.sensor_to_ego[:3, :3], camera.sensor_to_ego[:3, 3]
    d_ego = rays @ R.T
    best_t = np.full(valid.shape, np.inf)
    value = np.zeros(valid.shape)
    for pl in planes:
        den = d_ego @ pl.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((pl.point - c) @ pl.normal) / den
        hit = valid & (t > 0) & np.isfinite(t) & (t < best_t)
        if pl.extent is not None:  # a finite rectangle
            q = c + d_ego * np.where(hit, t, 0.0)[..., None] - pl.point
            hit &= (np.abs(q @ pl.axis_u) <= pl.extent[0]) & (np.abs(q @ pl.axis_v) <= pl.extent[1])
        p = c + d_ego[hit] * t[hit, None] - pl.point
        value[hit] = _texture(p @ pl.axis_u, p @ pl.axis_v, pl.seed)
        best_t[hit] = t[hit]
    hit = np.isfinite(best_t)
    depth = np.where(hit, best_t * (1.0 if big.depth_is_range else rays[..., 2]), 0.0)
    h, w = camera.height, camera.width
    img = value.reshape(h, k, w, k).mean(axis=(1, 3))
    # depth: take the centre sample's hit (supersampled depths would blend across edges)
    depth = depth.reshape(h, k, w, k)[:, k // 2, :, k // 2]
    rgb = np.repeat(np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return rgb, depth.astype(np.float32)


def nuscenes_pair(scale: float = 0.25) -> tuple[Camera, Camera]:
    """CAM_FRONT and CAM_FRONT_RIGHT of a nuScenes-like rig (1600x900 at scale 1)."""
    cams = []
    for name, yaw, pos in (("FRONT", 0.0, (1.70, 0.0, 1.51)), ("FRONT_RIGHT", -55.0, (1.55, -0.49, 1.50))):
        K = np.array([[1266.0, 0, 799.5], [0, 1266.0, 449.5], [0, 0, 1]])
        model = Pinhole(1600, 900, K, None).resized(round(1600 * scale), round(900 * scale))
        cams.append(Camera(name, model, camera_mount(math.radians(yaw), np.array(pos))))
    return cams[0], cams[1]


def fisheye_pair(size: int = 160) -> tuple[Camera, Camera]:
    """Two 220-degree equidistant fisheyes 90 degrees apart on a rig's front-left and front-right corners."""
    f = (size / 2) / math.radians(110)
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    model = KannalaBrandt(size, size, K, np.zeros(4), 220.0)
    front = Camera("F", model, camera_mount(0.0, np.array([1.0, 0.0, 1.6])))
    right = Camera("R", model, camera_mount(math.radians(-90), np.array([0.2, -0.6, 1.6])))
    return front, right
