"""LiDAR depth ground truth: read a sweep, project it into a camera at the camera's own capture, z-buffer.

A point measured in the LiDAR frame at the sweep's time goes to the world with the LiDAR's pose then
(ego_to_world(t_lidar) @ lidar_to_ego), and from the world into the camera with the camera's pose at
its own capture (ego_to_world(t_camera) @ sensor_to_ego): ego-motion compensation as the nuScenes
devkit and BEVDepth do it. Points behind the camera, outside [min_depth_m, max_depth_m] (depth in the
camera's convention) or under the camera's ego mask are dropped; the nearest return per pixel is kept
(`sgde_plugin.splat`). The result follows the depth-PNG conventions: float32 metres, 0 = none.

Sparse truth is not dense truth: the LiDAR sits ~0.5-1.5 m from the cameras, so near depth edges it
sees background that the camera does not (parallax), and those returns land on foreground pixels.
`occlusion_window_px` > 0 drops a return when a return within that many pixels is nearer by more
than `occlusion_rel` (a background point among foreground ones); it is off by default, and its effect
on the DDAD sample is reported in the README.

File formats: nuScenes LIDAR_TOP `.pcd.bin` (float32 x, y, z, intensity, ring; 5 per point) and DGP
`point_cloud/LIDAR/*.npz` (key `data`, columns X, Y, Z, intensity...; 3 or more per point).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .cameras import Camera
from .errors import InputError
from .geometry import invert_transform
from .splat import min_pool_nonzero_torch, splat_depth_torch, transform_points_torch

NUSCENES_FLOATS = 5  # x, y, z, intensity, ring index


@dataclass(frozen=True, eq=False)
class LidarSweep:
    """One LiDAR sweep of a frame: its file, format, mounting, and the ego pose and time it was taken at."""

    path: Path
    fmt: str  # "nuscenes_bin" or "dgp_npz"
    sensor_to_ego: np.ndarray  # LiDAR frame -> ego frame
    ego_to_world: np.ndarray  # ego pose at the sweep's time
    timestamp_us: int

    @property
    def lidar_to_world(self) -> np.ndarray:
        """LiDAR frame -> world at the sweep's time."""
        return np.asarray(self.ego_to_world, np.float64) @ np.asarray(self.sensor_to_ego, np.float64)


@dataclass(frozen=True)
class LidarDepthConfig:
    """How LiDAR returns become a depth map."""

    min_depth_m: float = 1.0  # the nuScenes devkit's min_dist: closer returns (the car itself) are dropped
    max_depth_m: float = 250.0  # below the depth-PNG limit (255.99 m)
    occlusion_window_px: int = 0  # > 0: drop returns with a much nearer return this close (parallax)
    occlusion_rel: float = 0.3  # "much nearer": by more than this fraction


def read_points(sweep: LidarSweep) -> np.ndarray:
    """The sweep's points (N, 3) float64 in the LiDAR frame; InputError for a missing, truncated or bad file."""
    path = Path(sweep.path)
    if not path.is_file():
        raise InputError(path, None, "point cloud file not found")
    if sweep.fmt == "nuscenes_bin":
        raw = path.read_bytes()
        if len(raw) % (4 * NUSCENES_FLOATS):
            raise InputError(path, None, f"truncated or wrong shape: {len(raw)} bytes is not a whole number of "
                             f"{NUSCENES_FLOATS}-float32 points")
        pts = np.frombuffer(raw, dtype="<f4").reshape(-1, NUSCENES_FLOATS)[:, :3]
    elif sweep.fmt == "dgp_npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "data" not in z.files:
                    raise InputError(path, "data", f"missing (keys: {', '.join(z.files) or 'none'})")
                data = z["data"]
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise InputError(path, None, f"not a readable .npz (truncated?): {exc}") from None
        if data.ndim != 2 or data.shape[1] < 3 or not np.issubdtype(data.dtype, np.number):
            raise InputError(path, "data", f"expected an (N, >=3) numeric array, found {data.dtype} {data.shape}")
        pts = data[:, :3]
    else:
        raise InputError(path, None, f"unknown point cloud format {sweep.fmt!r}")
    pts = np.asarray(pts, dtype=np.float64)
    return pts[np.isfinite(pts).all(axis=1)]


def lidar_to_camera(sweep: LidarSweep, camera_to_world: np.ndarray) -> np.ndarray:
    """4x4 LiDAR frame (at the sweep's time) -> camera frame (at the camera's capture), through the world."""
    return invert_transform(np.asarray(camera_to_world, np.float64)) @ sweep.lidar_to_world


def lidar_depth(points: np.ndarray, to_camera: np.ndarray, camera: Camera, mask: np.ndarray | None = None,
                config: LidarDepthConfig = LidarDepthConfig()) -> np.ndarray:
    """Depth map float32 (H, W) of LiDAR points (N, 3) moved by `to_camera` (4x4), nearest return per pixel."""
    with torch.no_grad():
        pts = transform_points_torch(torch.as_tensor(to_camera), torch.as_tensor(np.asarray(points, np.float64)))
        d = camera.intrinsics.depth_torch(pts)
        pts = pts[(d >= config.min_depth_m) & (d <= config.max_depth_m)]
        depth = splat_depth_torch(pts, camera)
        if config.occlusion_window_px > 0:
            depth = drop_occluded(depth, config.occlusion_window_px, config.occlusion_rel)
    out = depth.numpy().astype(np.float32)
    if mask is not None:
        out[~np.asarray(mask, bool)] = 0.0
    return out


def drop_occluded(depth: torch.Tensor, window_px: int, rel: float) -> torch.Tensor:
    """Zero the returns that have a return within `window_px` pixels nearer than depth * (1 - rel)."""
    k = 2 * window_px + 1
    padded = torch.nn.functional.pad(depth[None, None], (window_px,) * 4)
    near = min_pool_nonzero_torch(padded, k, k, stride=1)[0, 0]
    keep = (depth > 0) & (near >= depth * (1.0 - rel))
    return torch.where(keep, depth, torch.zeros_like(depth))


def sweep_depth(sweep: LidarSweep, camera: Camera, camera_to_world: np.ndarray, mask: np.ndarray | None = None,
                config: LidarDepthConfig = LidarDepthConfig()) -> np.ndarray:
    """Read a sweep and project it into a camera at its capture pose (see `lidar_depth`)."""
    return lidar_depth(read_points(sweep), lidar_to_camera(sweep, camera_to_world), camera, mask, config)


__all__ = [
    "LidarDepthConfig",
    "LidarSweep",
    "drop_occluded",
    "lidar_depth",
    "lidar_to_camera",
    "read_points",
    "sweep_depth",
]
