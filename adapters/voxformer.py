"""VoxFormer-style stage 1: per-camera depth (fused with the SGDE prior) -> occupancy -> query proposals.

VoxFormer lifts a depth map to a pseudo point cloud, voxelises it (256 x 256 x 32 at 0.2 m over
[0, 51.2] x [-25.6, 25.6] x [-2, 4.4] m) and keeps the occupied voxels at half resolution as the
queries of its second stage. ``DepthToVoxelProposals`` does this for a whole rig in batched torch,
for any ``sgde_plugin.cameras`` model (pinholes and the virtual views of fisheyes), after replacing
the predicted depth by the prior wherever the prior is confident.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sgde_plugin.cameras import CameraModel, pixel_grid
from sgde_plugin.nn import PriorL1Loss


@dataclass(frozen=True)
class VoxelGrid:
    """An axis-aligned voxel grid in the ego frame: lower corner (m), voxel edge (m), shape (X, Y, Z)."""

    origin: tuple[float, float, float]
    voxel_size: float
    shape: tuple[int, int, int]

    @property
    def upper(self) -> tuple[float, float, float]:
        """Upper corner of the grid, metres."""
        return tuple(o + self.voxel_size * n for o, n in zip(self.origin, self.shape))

    @property
    def num_voxels(self) -> int:
        """X * Y * Z."""
        x, y, z = self.shape
        return x * y * z

    def voxel_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Ego points [..., 3] -> integer voxel indices [..., 3] (long) and inside-grid flags [...]."""
        origin = torch.as_tensor(self.origin, dtype=points.dtype, device=points.device)
        idx = torch.floor((points - origin) / self.voxel_size).long()
        size = torch.as_tensor(self.shape, device=points.device)
        inside = ((idx >= 0) & (idx < size)).all(dim=-1)
        return idx, inside


VOXFORMER_GRID = VoxelGrid(origin=(0.0, -25.6, -2.0), voxel_size=0.2, shape=(256, 256, 32))
OCC3D_NUSCENES_GRID = VoxelGrid(origin=(-40.0, -40.0, -1.0), voxel_size=0.4, shape=(200, 200, 16))
GRID_PRESETS = {"voxformer": VOXFORMER_GRID, "occ3d-nuscenes": OCC3D_NUSCENES_GRID}


def fuse_depth_with_prior(
    depth: Tensor, prior: Tensor | None, confidence: Tensor | None = None, threshold: float = 0.5
) -> Tensor:
    """Replace ``depth`` by ``prior`` where the prior exists (> 0) and ``confidence`` >= threshold."""
    if prior is None:
        return depth
    use = prior > 0
    if confidence is not None:
        use = use & (confidence >= threshold)
    return torch.where(use, prior, depth)


class DepthToVoxelProposals(nn.Module):
    """Rig depth [B, N, H, W] -> pseudo points (ego), occupancy [B, X, Y, Z], proposals at 1/stride.

    Args:
        grid: the voxel grid (``VOXFORMER_GRID`` by default, or ``OCC3D_NUSCENES_GRID``).
        proposal_stride: resolution reduction of the proposals (VoxFormer: 2).
        confidence_threshold: prior pixels with a lower confidence keep the predicted depth.
        max_depth: depths beyond this (in each camera's convention) are dropped; None keeps all.
    """

    def __init__(
        self,
        grid: VoxelGrid = VOXFORMER_GRID,
        proposal_stride: int = 2,
        confidence_threshold: float = 0.5,
        max_depth: float | None = None,
    ) -> None:
        super().__init__()
        if any(n % proposal_stride for n in grid.shape):
            raise ValueError(f"grid shape {grid.shape} is not divisible by proposal_stride {proposal_stride}")
        self.grid = grid
        self.proposal_stride = int(proposal_stride)
        self.confidence_threshold = float(confidence_threshold)
        self.max_depth = max_depth

    def points(
        self, depth: Tensor, cameras: Sequence[CameraModel], sensor_to_ego: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Depth [B, N, H, W] -> ego points [B, N, H, W, 3] and validity [B, N, H, W]."""
        b, n, h, w = depth.shape
        if len(cameras) != n:
            raise ValueError(f"{len(cameras)} cameras for {n} depth maps")
        if sensor_to_ego.dim() == 3:
            sensor_to_ego = sensor_to_ego.unsqueeze(0).expand(b, -1, -1, -1)
        uv = pixel_grid(w, h, dtype=depth.dtype, device=depth.device)
        pts, valid = [], []
        for i, cam in enumerate(cameras):
            if (cam.width, cam.height) != (w, h):
                cam = cam.resized(w, h)
            p, ok = cam.points_from_depth_torch(uv, depth[:, i])  # [B, H, W, 3], [B, H, W]
            pts.append(p)
            valid.append(ok & (depth[:, i] > 0))
        cam_pts = torch.stack(pts, dim=1)
        ok = torch.stack(valid, dim=1)
        if self.max_depth is not None:
            ok = ok & (depth <= self.max_depth)
        rot = sensor_to_ego[:, :, None, None, :3, :3].to(depth.dtype)
        trans = sensor_to_ego[:, :, None, None, :3, 3].to(depth.dtype)
        ego = (rot @ cam_pts.unsqueeze(-1)).squeeze(-1) + trans
        return ego, ok

    def voxelize(self, points: Tensor, valid: Tensor) -> Tensor:
        """Ego points [B, P, 3] + validity [B, P] -> point counts per voxel [B, X, Y, Z]."""
        b = points.shape[0]
        x, y, z = self.grid.shape
        idx, inside = self.grid.voxel_index(points)
        keep = valid & inside
        flat = (idx[..., 0] * y + idx[..., 1]) * z + idx[..., 2]
        # points outside the grid go to one extra "dump" cell that is cut off afterwards
        flat = torch.where(keep, flat, torch.full_like(flat, self.grid.num_voxels))
        counts = torch.zeros(b, self.grid.num_voxels + 1, dtype=points.dtype, device=points.device)
        counts = counts.scatter_add(1, flat, keep.to(points.dtype))
        return counts[:, : self.grid.num_voxels].reshape(b, x, y, z)

    def forward(
        self,
        depth: Tensor,
        cameras: Sequence[CameraModel],
        sensor_to_ego: Tensor,
        prior: Tensor | None = None,
        confidence: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Depth (+ prior, confidence) [B, N, H, W] and the rig -> dict of tensors.

        ``cameras``: one model per camera (resized to the depth map when sizes differ);
        ``sensor_to_ego``: [B, N, 4, 4] or [N, 4, 4]. Returns ``depth`` (fused, [B, N, H, W]),
        ``points`` [B, N*H*W, 3] and ``valid`` [B, N*H*W], ``occupancy`` [B, X, Y, Z] in {0, 1}
        and ``proposals`` [B, X/s, Y/s, Z/s] in {0, 1} (a coarse voxel holding any occupied one).
        """
        fused = fuse_depth_with_prior(depth, prior, confidence, self.confidence_threshold)
        ego, ok = self.points(fused, cameras, sensor_to_ego)
        b = depth.shape[0]
        points, valid = ego.reshape(b, -1, 3), ok.reshape(b, -1)
        occupancy = (self.voxelize(points, valid) > 0).to(depth.dtype)
        s = self.proposal_stride
        proposals = F.max_pool3d(occupancy.unsqueeze(1), kernel_size=s, stride=s).squeeze(1)
        return {"depth": fused, "points": points, "valid": valid, "occupancy": occupancy, "proposals": proposals}


def proposal_indices(proposals: Tensor) -> list[Tensor]:
    """Proposal mask [B, X, Y, Z] -> per sample the [K, 3] (long) indices of the proposed voxels."""
    return [torch.nonzero(p > 0) for p in proposals]


def proposal_depth_loss(
    pred_depth: Tensor,
    gt_depth: Tensor,
    prior: Tensor | None = None,
    prior_loss: nn.Module | None = None,
) -> Tensor:
    """Depth loss of the proposal branch: mean L1 to ground truth + the SGDE prior loss.

    Maps are [B, N, H, W] metres, 0 = no value (pixels without a target contribute nothing).
    ``prior_loss`` is any ``sgde_plugin.nn`` prior loss (default ``PriorL1Loss``, lambda = 0.005).
    """
    gt_mask = gt_depth > 0
    loss = (pred_depth - gt_depth).abs()[gt_mask].sum() / gt_mask.sum().clamp_min(1)
    if prior is not None:
        if prior_loss is None:
            prior_loss = PriorL1Loss()
        loss = loss + prior_loss(pred_depth.flatten(0, 1).unsqueeze(1), prior.flatten(0, 1).unsqueeze(1))
    return loss


class RigDepthToVoxelProposals(nn.Module):
    """``DepthToVoxelProposals`` with the rig's camera models fixed: tensors in, tensors out (exportable).

    ``forward(depth, sensor_to_ego, prior, confidence)`` -> (occupancy, proposals).
    """

    def __init__(self, proposals: DepthToVoxelProposals, cameras: Sequence[CameraModel]) -> None:
        super().__init__()
        self.proposals = proposals
        self.cameras = list(cameras)

    def forward(self, depth: Tensor, sensor_to_ego: Tensor, prior: Tensor, confidence: Tensor) -> tuple[Tensor, Tensor]:
        """[B, N, H, W] maps and [B, N, 4, 4] poses -> occupancy [B, X, Y, Z], proposals [B, X/s, Y/s, Z/s]."""
        out = self.proposals(depth, self.cameras, sensor_to_ego, prior, confidence)
        return out["occupancy"], out["proposals"]
