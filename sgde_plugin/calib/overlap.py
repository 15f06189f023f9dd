"""Where two views can see the same scene, predicted from the initial extrinsics and the ego motion.

For camera A in frame t and camera B in frame t', a pixel of A is in the overlap when its ray, at any
of a set of sampled depths, lands inside B's image enlarged by a margin. The answer is a coarse mask
per (t, t') frame pair, looked up at keypoint positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..cameras import Camera, CameraModel

DEFAULT_DEPTHS_M = (2.0, 4.0, 8.0, 16.0, 40.0, 1000.0)


def pixels_per_radian(model: CameraModel) -> float:
    """Pixels per radian of view angle at the image centre (the residual scale of the adjustment)."""
    cx, cy = (model.width - 1) / 2.0, (model.height - 1) / 2.0
    rays, valid = model.unproject(np.array([[cx - 2.0, cy], [cx + 2.0, cy]]))
    if not valid.all():
        raise ValueError("the image centre of this camera does not see the scene")
    angle = float(np.arccos(np.clip(rays[0] @ rays[1], -1.0, 1.0)))
    return 4.0 / max(angle, 1e-12)


def _half_fov(model: CameraModel) -> float:
    """Largest angle from the optical axis that the model sees (radians)."""
    fov = getattr(model, "fov_deg", None)
    if model.depth_is_range and fov is not None:
        return float(np.radians(fov) / 2)
    return float(np.radians(89.0))


@dataclass
class OverlapGrid:
    """Coarse overlap masks of camera A's pixels against camera B: mask[t, t2] over cells of `stride` px."""

    stride: int
    mask: np.ndarray  # (T, T, Hc, Wc) bool

    def lookup(self, t: int, t2: int, uv: np.ndarray) -> np.ndarray:
        """True for pixels (N, 2) of A at frame t that may be seen by B at frame t2."""
        if uv.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        hc, wc = self.mask.shape[2:]
        col = np.clip(np.round(uv[:, 0] / self.stride).astype(int), 0, wc - 1)
        row = np.clip(np.round(uv[:, 1] / self.stride).astype(int), 0, hc - 1)
        return self.mask[t, t2, row, col]

    def any_mask(self, width: int, height: int) -> np.ndarray:
        """Full-resolution uint8 mask (255 = maybe overlapping in some frame pair) for feature detection."""
        coarse = self.mask.any(axis=(0, 1)).astype(np.uint8) * 255
        return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_NEAREST)


def overlap_grid(
    cam_a: Camera,
    cam_b: Camera,
    ego_to_world: np.ndarray,
    margin_px: float = 24.0,
    stride: int = 16,
    depths_m: tuple[float, ...] = DEFAULT_DEPTHS_M,
    ego_to_world_b: np.ndarray | None = None,
) -> OverlapGrid:
    """Overlap masks of camera A against camera B for every (t, t') pair of the window's ego poses.

    `ego_to_world` are the ego poses at camera A's captures, `ego_to_world_b` at B's (default: the same)."""
    ma, mb = cam_a.intrinsics, cam_b.intrinsics
    wc = int(np.ceil(ma.width / stride)) + 1
    hc = int(np.ceil(ma.height / stride)) + 1
    u, v = np.meshgrid(np.arange(wc) * stride, np.arange(hc) * stride)
    uv = np.stack([np.minimum(u, ma.width - 1), np.minimum(v, ma.height - 1)], axis=-1).reshape(-1, 2)
    rays, valid_a = ma.unproject(uv.astype(np.float64))
    # the cell is kept when any pixel of the cell could be seen: the margin covers the cell size too
    margin = margin_px + stride
    T = ego_to_world.shape[0]
    A = np.einsum("tij,jk->tik", ego_to_world, cam_a.sensor_to_ego)  # cam a -> world per frame
    ego_b = ego_to_world if ego_to_world_b is None else ego_to_world_b
    B = np.einsum("tij,jk->tik", ego_b, cam_b.sensor_to_ego)
    Binv = np.linalg.inv(B)
    rel = np.einsum("sij,tjk->tsik", Binv, A)  # (t, t2): cam a at t -> cam b at t2
    D, P = len(depths_m), rays.shape[0]
    pts = (rays[None, :, :] * np.asarray(depths_m, dtype=np.float64)[:, None, None]).reshape(-1, 3)
    rel = rel.reshape(T * T, 4, 4)
    pb = np.swapaxes(rel[:, :3, :3] @ pts.T[None], 1, 2) + rel[:, None, :3, 3]  # (T*T, D*P, 3)
    with torch.no_grad():
        uvb = mb.project_torch(torch.from_numpy(pb))[0].numpy()
    cos_limit = np.cos(_half_fov(mb))
    front = pb[..., 2] >= cos_limit * np.linalg.norm(pb, axis=-1)
    seen = (
        front
        & (uvb[..., 0] >= -margin)
        & (uvb[..., 0] <= mb.width - 1 + margin)
        & (uvb[..., 1] >= -margin)
        & (uvb[..., 1] <= mb.height - 1 + margin)
    )
    mask = seen.reshape(T * T, D, P).any(axis=1) & valid_a[None, :]
    return OverlapGrid(stride, mask.reshape(T, T, hc, wc))
