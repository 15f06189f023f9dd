"""Training data of a surround rig at network resolution: `RigSequence`, plus the two derived masks
the training loop needs (LiDAR-like supervision pixels, the true overlap of adjacent cameras)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Camera
from ..stereo.evaluate import true_overlap

LIDAR_POSITION = np.array([0.94, 0.0, 1.84])  # roof LiDAR of nuScenes, ego frame
LIDAR_BEAMS_DEG = np.linspace(-30.67, 10.67, 32)  # 32-beam spinning LiDAR
LIDAR_RANGE_M = 70.0


@dataclass
class RigSequence:
    """Frames of a surround rig at network resolution; arrays are [frames, cameras, H, W(, 3)].

    The optional fields serve self-supervised training: ``camera_to_world`` [F,N,4,4] is each camera's
    pose in the world at its own capture (`Rig.capture(...).camera_to_world`), ``context_images``
    [F,2,N,H,W,3] the images of the instants just before (index 0) and after (index 1) each frame,
    ``context_camera_to_world`` [F,2,N,4,4] their camera poses, and ``masks`` [N,H,W] bool the static
    per-camera masks (False = ego body, ignore).
    """

    cameras: list[Camera]
    pairs: list[tuple[str, str]]
    images: np.ndarray  # uint8 RGB
    depth: np.ndarray  # float32 dense ground truth (evaluation), 0 = none
    supervision: np.ndarray  # float32 LiDAR-like training depth, 0 = none
    prior: np.ndarray  # float32 metres, 0 = none
    valid: np.ndarray  # bool prior validity
    overlap: np.ndarray  # bool: pixel seen by an adjacent camera (true geometry)
    scene_source: str = ""
    prior_source: str = ""
    camera_to_world: np.ndarray | None = None
    context_images: np.ndarray | None = None
    context_camera_to_world: np.ndarray | None = None
    masks: np.ndarray | None = None


def lidar_pattern(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixels a 32-beam roof LiDAR would return for (LiDAR-like sparse supervision): bool [H,W]."""
    model = camera.intrinsics
    rays, ok = model.ray_grid()
    d = torch.as_tensor(depth.astype(np.float64))
    pts = rays * (d / rays[..., 2].clamp(min=1e-9))[..., None] if not model.depth_is_range else rays * d[..., None]
    T = torch.as_tensor(camera.sensor_to_ego)
    p = (pts.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]).numpy() - LIDAR_POSITION
    rng_m = np.linalg.norm(p, axis=1)
    elev = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    nearest = np.abs(elev[:, None] - LIDAR_BEAMS_DEG[None]).min(1)
    pixel_deg = math.degrees(1.0 / float(model.K[1, 1])) if hasattr(model, "K") else 0.5
    hit = (nearest <= 0.5 * pixel_deg * np.maximum(1.0, rng_m / np.maximum(depth.reshape(-1), 1e-6)))
    hit &= (depth.reshape(-1) > 0) & (rng_m <= LIDAR_RANGE_M) & ok.reshape(-1).numpy()
    return hit.reshape(depth.shape)


def overlap_masks(depth: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """True overlap per camera [N,H,W]: pixels an adjacent camera sees unoccluded (the prior
    evaluation's definition)."""
    n = len(cameras)
    out = np.zeros(depth.shape, bool)
    for i in range(n):
        for j in ((i - 1) % n, (i + 1) % n):
            out[i] |= true_overlap(cameras[i], depth[i], cameras[j], depth[j])
    return out
