"""Back-projection of rectified disparities into an original camera, by backward mapping, and fusion.

For every pixel of the original camera: its ray, the rectified pixel on that ray (same optical
centre, so no occlusion can arise from the re-projection itself), the disparity there, and the
depth in the camera's own convention (z for pinholes, range for fisheyes):
depth = k * f * B / disparity with k = (depth of the point) / (rectified z of the point), a
per-pixel constant precomputed once per rig. Disparities are interpolated bilinearly only where
the four neighbours are valid and agree; across depth edges the nearest one is taken, so no
depths are invented between foreground and background.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..cameras import Camera

_ROW = 1024  # sample positions are laid out in rows of this length for cv2.remap


@dataclass(frozen=True, eq=False)
class BackProjection:
    """Precomputed backward map from one original camera into one rectified camera."""

    shape: tuple[int, int]  # (H, W) of the original camera
    index: np.ndarray  # flat indices of the original pixels that land in the rectified canvas
    map_x: np.ndarray  # (rows, _ROW) float32 rectified x of those pixels (padded)
    map_y: np.ndarray
    kfb: np.ndarray  # (N,) float32: depth = kfb / disparity

    @property
    def count(self) -> int:
        """Number of original pixels covered."""
        return int(self.index.shape[0])

    def sample(
        self, disparity: np.ndarray, confidence: np.ndarray, edge_px: float = 0.5
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Disparity (N,), confidence (N,) and validity (N,) at the covered pixels, edge-aware."""
        n = self.count
        valid = (confidence > 0).astype(np.float32)
        filled = np.where(valid > 0, disparity, 0).astype(np.float32)
        stack = cv2.merge([filled, valid])
        lin = cv2.remap(stack, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        near = cv2.merge([filled, confidence.astype(np.float32)])
        nn = cv2.remap(near, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        d_lin = lin[..., 0].reshape(-1)[:n]
        v_lin = lin[..., 1].reshape(-1)[:n]
        d_nn = nn[..., 0].reshape(-1)[:n]
        c_nn = nn[..., 1].reshape(-1)[:n]
        smooth = (v_lin > 0.999) & (np.abs(d_lin - d_nn) <= edge_px)
        d = np.where(smooth, d_lin, d_nn)
        ok = (c_nn > 0) & (d > 0)
        return d, np.where(ok, c_nn, 0).astype(np.float32), ok

    def depth(
        self, disparity: np.ndarray, confidence: np.ndarray, min_depth: float, max_depth: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Full-size depth (camera convention) and confidence maps; 0 where there is no value."""
        d, c, ok = self.sample(disparity, confidence)
        z = np.where(ok, self.kfb / np.where(ok, d, 1), 0)
        ok &= (z >= min_depth) & (z <= max_depth)
        depth = np.zeros(self.shape[0] * self.shape[1], np.float32)
        conf = np.zeros_like(depth)
        depth[self.index[ok]] = z[ok]
        conf[self.index[ok]] = c[ok]
        return depth.reshape(self.shape), conf.reshape(self.shape)


def backprojection(camera: Camera, rect: Camera, baseline_m: float, rays: torch.Tensor | None = None,
                   ray_valid: torch.Tensor | None = None) -> BackProjection:
    """Backward map of `camera` into the rectified pinhole `rect` (same optical centre).

    `rays`/`ray_valid` may pass the camera's precomputed `ray_grid()` to share it between pairs.
    """
    if rays is None or ray_valid is None:
        rays, ray_valid = camera.intrinsics.ray_grid()
    R = torch.as_tensor(rect.sensor_to_ego[:3, :3].T @ camera.sensor_to_ego[:3, :3], dtype=rays.dtype)
    r = rays.reshape(-1, 3)
    q = r @ R.T  # rays in the rectified frame
    K = rect.intrinsics.K
    front = q[:, 2] > 1e-6
    zq = torch.where(front, q[:, 2], torch.ones_like(q[:, 2]))
    u = K[0, 0] * q[:, 0] / zq + K[0, 2]
    v = K[1, 1] * q[:, 1] / zq + K[1, 2]
    inside = front & ray_valid.reshape(-1) & (u >= 0) & (u <= rect.width - 1) & (v >= 0) & (v <= rect.height - 1)
    index = torch.nonzero(inside).reshape(-1)
    # point = ray * t with t * q_z = rectified z; depth = t (range) or t * r_z (pinhole z)
    k = 1.0 / zq[index]
    if not camera.intrinsics.depth_is_range:
        k = k * r[index, 2]
    n = int(index.shape[0])
    rows = max(1, -(-n // _ROW))
    map_x = np.full(rows * _ROW, -1.0, np.float32)
    map_y = np.full(rows * _ROW, -1.0, np.float32)
    map_x[:n] = u[index].numpy()
    map_y[:n] = v[index].numpy()
    return BackProjection(
        shape=(camera.height, camera.width),
        index=index.numpy().astype(np.int64),
        map_x=map_x.reshape(rows, _ROW),
        map_y=map_y.reshape(rows, _ROW),
        kfb=(k.numpy() * K[0, 0] * baseline_m).astype(np.float32),
    )


def fuse_priors(
    maps: Sequence[tuple[np.ndarray, np.ndarray]], agree_rel: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse several (depth, confidence) maps of one camera into one.

    Where several have a value and agree within `agree_rel`, the confidence-weighted mean is taken
    and the confidence becomes 1 - prod(1 - c); where they disagree the most confident one wins,
    with its confidence halved.
    """
    if not maps:
        raise ValueError("nothing to fuse")
    depth = maps[0][0].astype(np.float32).copy()
    conf = maps[0][1].astype(np.float32).copy()
    for d2, c2 in maps[1:]:
        has1, has2 = conf > 0, c2 > 0
        both = has1 & has2
        only2 = has2 & ~has1
        depth[only2], conf[only2] = d2[only2], c2[only2]
        if both.any():
            a, ca, b, cb = depth[both], conf[both], d2[both], c2[both]
            agree = np.abs(a - b) <= agree_rel * np.minimum(a, b)
            mean = (a * ca + b * cb) / (ca + cb)
            pick_b = cb > ca
            depth[both] = np.where(agree, mean, np.where(pick_b, b, a))
            conf[both] = np.where(agree, 1 - (1 - ca) * (1 - cb), 0.5 * np.maximum(ca, cb))
    return depth, conf
