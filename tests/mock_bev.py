"""Mock BEV heads for adapter tests: pure-torch LSS pooling with a heatmap head, and an occupancy head.

Small and differentiable, no custom ops: enough to train a depth branch end to end through a
bird's-eye-view task and to consume VoxFormer-style proposals.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def frustum_points(
    K: Tensor, sensor_to_ego: Tensor, feat_hw: tuple[int, int], stride: int, d_bound: tuple[float, float, float]
) -> Tensor:
    """Ego points of every (depth bin centre, feature cell centre): [B, N, D, h, w, 3] for pinholes.

    ``K`` [B, N, 3, 3] at the image size, ``sensor_to_ego`` [B, N, 4, 4].
    """
    h, w = feat_hw
    start, stop, step = d_bound
    depths = torch.arange(start, stop - 1e-9, step, dtype=K.dtype) + step / 2
    v = (torch.arange(h, dtype=K.dtype) + 0.5) * stride - 0.5
    u = (torch.arange(w, dtype=K.dtype) + 0.5) * stride - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    pix = torch.stack([uu, vv, torch.ones_like(uu)], dim=-1)  # [h, w, 3]
    rays = torch.einsum("bnij,hwj->bnhwi", torch.linalg.inv(K), pix)  # z = 1
    cam = rays[:, :, None] * depths[None, None, :, None, None, None]  # [B, N, D, h, w, 3]
    rot, trans = sensor_to_ego[..., :3, :3], sensor_to_ego[..., :3, 3]
    return torch.einsum("bnij,bndhwj->bndhwi", rot, cam) + trans[:, :, None, None, None, :]


def lss_pool(
    depth_probs: Tensor, context: Tensor, points: Tensor, origin: tuple[float, float], cell: float,
    bev_hw: tuple[int, int],
) -> Tensor:
    """Lift-splat: depth-weighted context scattered (summed) into BEV cells -> [B, C, X, Y].

    ``depth_probs`` [B*N, D, h, w], ``context`` [B*N, C, h, w], ``points`` [B, N, D, h, w, 3].
    """
    b, n = points.shape[:2]
    c = context.shape[1]
    nx, ny = bev_hw
    feats = depth_probs.unsqueeze(1) * context.unsqueeze(2)  # [B*N, C, D, h, w]
    feats = feats.reshape(b, n, c, -1).permute(0, 1, 3, 2).reshape(b, -1, c)  # [B, N*D*h*w, C]
    ix = torch.floor((points[..., 0] - origin[0]) / cell).long().reshape(b, -1)
    iy = torch.floor((points[..., 1] - origin[1]) / cell).long().reshape(b, -1)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    flat = torch.where(inside, ix * ny + iy, torch.full_like(ix, nx * ny))
    bev = torch.zeros(b, nx * ny + 1, c, dtype=feats.dtype)
    bev = bev.scatter_add(1, flat.unsqueeze(-1).expand(-1, -1, c), feats)
    return bev[:, : nx * ny].reshape(b, nx, ny, c).permute(0, 3, 1, 2)


class HeatmapHead(nn.Module):
    """BEV features -> one-class centre heatmap logits [B, 1, X, Y]."""

    def __init__(self, channels: int, hidden: int = 16) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(),
                                 nn.Conv2d(hidden, 1, 1))

    def forward(self, bev: Tensor) -> Tensor:
        """[B, C, X, Y] -> [B, 1, X, Y] logits."""
        return self.net(bev)

    @staticmethod
    def loss(logits: Tensor, target: Tensor) -> Tensor:
        """Binary cross-entropy against a {0, 1} target heatmap."""
        return F.binary_cross_entropy_with_logits(logits, target)


class OccupancyHead(nn.Module):
    """Query proposals [B, X, Y, Z] -> occupancy logits at the same resolution (a tiny 3-D CNN)."""

    def __init__(self, hidden: int = 8) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv3d(1, hidden, 3, padding=1), nn.ReLU(), nn.Conv3d(hidden, 1, 1))

    def forward(self, proposals: Tensor) -> Tensor:
        """[B, X, Y, Z] in {0, 1} -> [B, X, Y, Z] logits."""
        return self.net(proposals.unsqueeze(1)).squeeze(1)

    @staticmethod
    def loss(logits: Tensor, target: Tensor) -> Tensor:
        """Binary cross-entropy against a {0, 1} occupancy target."""
        return F.binary_cross_entropy_with_logits(logits, target)
