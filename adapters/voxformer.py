"""VoxFormer-style stage 1: rig depth (fused with the SGDE prior) -> occupancy -> query proposals.

What VoxFormer does (NVlabs/VoxFormer, SemanticKITTI): a stereo depth map becomes a pseudo point
cloud in the LiDAR frame (``depth2lidar.py``), accumulated over 10 sweeps with the LiDAR poses, and
is voxelised into a 256 x 256 x 32 occupancy at 0.2 m over [0, 51.2] x [-25.6, 25.6] x [-2, 4.4] m
(``lidar2voxel.py``, saved packed as ``.pseudo``). A trained query-proposal network (LMSCNet) turns
that occupancy into 128 x 128 x 16 query proposals (saved as ``.query*``) for the stage-2 head.

``DepthToVoxelProposals`` computes, for a whole rig in batched torch and for any
``sgde_plugin.cameras`` model:

- ``occupancy``: VoxFormer's stage-1 voxels, a drop-in for ``.pseudo`` (identical to VoxFormer's
  own on a constructed KITTI scene, ``tests/test_adapters_voxformer.py``), from one sweep or, with
  ``past_points`` from ``accumulate_sweeps``, from several;
- ``coarse_occupancy``: the occupancy max-pooled to the query resolution. A geometric stand-in,
  NOT VoxFormer's query proposals: stage-2 weights trained on LMSCNet's proposals would get
  another query set;
- ``proposals``: only when a query-proposal network is given (``query_net``, e.g. an LMSCNet
  checkpoint loaded with ``load_query_net``): its arg-max, as VoxFormer's stage 1 writes them.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sgde_plugin.cameras import CameraModel, pixel_grid
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import invert_transform
from sgde_plugin.nn import PriorL1Loss
from sgde_plugin.nn.inputs import require_tensor
from sgde_plugin.torchfiles import ExportedModule, load_exported_program, load_torchscript

from .voxel_grids import (
    GRID_PRESETS,
    OCC3D_NUSCENES_GRID,
    VOXFORMER_GRID,
    VoxelGrid,
    check_frames,
    voxelize,
)

__all__ = [
    "GRID_PRESETS", "OCC3D_NUSCENES_GRID", "VOXFORMER_GRID", "VoxelGrid", "DepthToVoxelProposals",
    "RigDepthToVoxelProposals", "accumulate_sweeps", "fuse_depth_with_prior", "load_query_net",
    "poses_in_frame", "proposal_depth_loss", "proposal_indices", "query_proposals",
]


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


def poses_in_frame(sensor_to_ego: np.ndarray, frame_to_ego: np.ndarray) -> np.ndarray:
    """Camera poses [..., 4, 4] re-expressed in another frame (e.g. the LiDAR's): inv(frame_to_ego) @ sensor_to_ego."""
    return invert_transform(np.asarray(frame_to_ego, dtype=np.float64)) @ np.asarray(sensor_to_ego, dtype=np.float64)


def accumulate_sweeps(
    points: Sequence[Tensor], valid: Sequence[Tensor], frame_to_world: Tensor
) -> tuple[Tensor, Tensor]:
    """Points of several sweeps in the frame of sweep 0, as VoxFormer's multi-sweep ``lidar2voxel.py``.

    ``points[s]``: [B, P_s, 3] in sweep s's own frame (LiDAR or ego), ``valid[s]``: [B, P_s];
    ``frame_to_world``: [S, 4, 4] or [B, S, 4, 4] poses of that frame per sweep (for KITTI the LiDAR
    poses of ``sgde_plugin.readers.kitti.read_kitti_poses``). Returns [B, sum P_s, 3] and [B, sum P_s].
    """
    if frame_to_world.dim() == 3:
        frame_to_world = frame_to_world.unsqueeze(0)
    world_to_current = torch.linalg.inv(frame_to_world[:, 0].to(torch.float64))
    out_p, out_v = [], []
    for s, (p, v) in enumerate(zip(points, valid)):
        rel = (world_to_current @ frame_to_world[:, s].to(torch.float64)).to(p.dtype)  # [B or 1, 4, 4]
        out_p.append(p @ rel[:, :3, :3].transpose(-1, -2) + rel[:, None, :3, 3])
        out_v.append(v)
    return torch.cat(out_p, dim=1), torch.cat(out_v, dim=1)


def query_proposals(occupancy: Tensor, query_net: nn.Module) -> Tensor:
    """Occupancy [B, X, Y, Z] -> {0, 1} proposals [B, X/2, Y/2, Z/2] from an LMSCNet-style network.

    VoxFormer's LMSCNet takes the occupancy as [B, Z, X, Y] (height as channels) and returns class
    logits [B, C, X/2, Y/2, Z/2]; a voxel is proposed where the arg-max class is not 0 (empty).
    """
    logits = query_net(occupancy.permute(0, 3, 1, 2))
    b, x, y, z = occupancy.shape
    if logits.dim() != 5 or tuple(logits.shape[2:]) != (x // 2, y // 2, z // 2):
        raise ValueError(f"the query-proposal network returned {tuple(logits.shape)}, expected "
                         f"[B, C, {x // 2}, {y // 2}, {z // 2}] class logits")
    return (logits.argmax(dim=1) > 0).to(occupancy.dtype)


def load_query_net(path: str | Path, module: nn.Module | None = None) -> nn.Module:
    """A query-proposal network from a local file: a torch.export archive (.pt2), TorchScript, or a state dict into
    ``module``.

    A state dict may sit under a ``"state_dict"`` key (mmcv checkpoints). Nothing is downloaded.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "no such checkpoint file")
    if module is None and path.suffix.lower() == ".pt2":
        return ExportedModule(load_exported_program(path))
    try:
        if module is None:
            net = load_torchscript(path)
        else:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
            module.load_state_dict(state.get("state_dict", state) if isinstance(state, dict) else state)
            net = module
    except (RuntimeError, ValueError, KeyError, pickle.UnpicklingError) as exc:
        raise InputError(path, None, f"not a usable query-proposal checkpoint: {str(exc).splitlines()[0]}") from None
    return net.eval()


def _check_inputs(depth: object, sensor_to_ego: object, **maps: object) -> None:
    """One clear error for inputs of the wrong kind (TypeError) or shape (ValueError): depth [B, N, H, W], each map
    in ``maps`` None or of the depth's shape, ``sensor_to_ego`` [B, N, 4, 4] or [N, 4, 4]."""
    depth, sensor_to_ego = require_tensor("depth", depth), require_tensor("sensor_to_ego", sensor_to_ego)
    maps = {name: None if value is None else require_tensor(name, value) for name, value in maps.items()}
    if depth.dim() != 4:
        raise ValueError(f"depth must be [B, N, H, W] metres, got shape {list(depth.shape)}")
    for name, value in maps.items():
        if value is not None and value.shape != depth.shape:
            raise ValueError(f"{name} must have the depth's shape {list(depth.shape)}, got {list(value.shape)}")
    b, n = depth.shape[:2]
    if list(sensor_to_ego.shape) not in ([b, n, 4, 4], [n, 4, 4]):
        raise ValueError(f"sensor_to_ego must be [{b}, {n}, 4, 4] or [{n}, 4, 4], got {list(sensor_to_ego.shape)}")


class DepthToVoxelProposals(nn.Module):
    """Rig depth [B, N, H, W] -> pseudo points, ``occupancy`` [B, X, Y, Z], coarse occupancy or proposals.

    Args:
        grid: the voxel grid (``VOXFORMER_GRID``, LiDAR frame, by default; or ``OCC3D_NUSCENES_GRID``).
        proposal_stride: query resolution reduction (VoxFormer: 2).
        confidence_threshold: prior pixels with a lower confidence keep the predicted depth.
        max_depth: depths beyond this (in each camera's convention) are dropped; None keeps all.
        rig_frame: the frame the ``sensor_to_ego`` poses given to ``forward`` map into: ``"ego"`` (the
            project's convention, the default) or ``"lidar"``; a grid in another frame is refused, so
            ``VOXFORMER_GRID`` needs poses re-expressed in the LiDAR frame (``poses_in_frame``, or
            ``sgde_plugin.readers.kitti.kitti_camera``) and ``rig_frame="lidar"``.
        query_net: an LMSCNet-style query-proposal network; without one there is no ``proposals``.
    """

    def __init__(
        self,
        grid: VoxelGrid = VOXFORMER_GRID,
        proposal_stride: int = 2,
        confidence_threshold: float = 0.5,
        max_depth: float | None = None,
        rig_frame: str = "ego",
        query_net: nn.Module | None = None,
    ) -> None:
        super().__init__()
        grid.coarsened(proposal_stride)  # raises when the shape is not divisible
        check_frames(grid, rig_frame)
        self.grid = grid
        self.proposal_stride = int(proposal_stride)
        self.confidence_threshold = float(confidence_threshold)
        self.max_depth = max_depth
        self.query_net = query_net

    def points(
        self, depth: Tensor, cameras: Sequence[CameraModel], sensor_to_ego: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Depth [B, N, H, W] -> points [B, N, H, W, 3] in the grid's frame and validity [B, N, H, W]."""
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
        pose = sensor_to_ego.to(device=depth.device, dtype=depth.dtype)
        rot, trans = pose[:, :, None, None, :3, :3], pose[:, :, None, None, :3, 3]
        ego = (rot @ cam_pts.unsqueeze(-1)).squeeze(-1) + trans
        return ego, ok

    def voxelize(self, points: Tensor, valid: Tensor) -> Tensor:
        """Points [B, P, 3] in the grid's frame + validity [B, P] -> point counts per voxel [B, X, Y, Z]."""
        return voxelize(points, valid, self.grid)

    def forward(
        self,
        depth: Tensor,
        cameras: Sequence[CameraModel],
        sensor_to_ego: Tensor,
        prior: Tensor | None = None,
        confidence: Tensor | None = None,
        past_points: tuple[Tensor, Tensor] | None = None,
    ) -> dict[str, Tensor]:
        """Depth (+ prior, confidence) [B, N, H, W] and the rig -> dict of tensors.

        ``cameras``: one model per camera (resized to the depth map when sizes differ);
        ``sensor_to_ego``: [B, N, 4, 4] or [N, 4, 4] into the grid's frame; ``past_points``: (points
        [B, P, 3], valid [B, P]) of earlier sweeps already in this frame (``accumulate_sweeps``).
        Returns ``depth`` (fused), ``points`` [B, N*H*W, 3], ``valid`` [B, N*H*W], ``occupancy``
        [B, X, Y, Z] in {0, 1}, ``coarse_occupancy`` [B, X/s, Y/s, Z/s] (a coarse voxel holding any
        occupied one) and, with a ``query_net``, ``proposals`` [B, X/2, Y/2, Z/2].
        """
        _check_inputs(depth, sensor_to_ego, prior=prior, confidence=confidence)
        fused = fuse_depth_with_prior(depth, prior, confidence, self.confidence_threshold)
        ego, ok = self.points(fused, cameras, sensor_to_ego)
        b = depth.shape[0]
        points, valid = ego.reshape(b, -1, 3), ok.reshape(b, -1)
        all_points, all_valid = points, valid
        if past_points is not None:
            all_points = torch.cat([points, past_points[0].to(points.dtype)], dim=1)
            all_valid = torch.cat([valid, past_points[1]], dim=1)
        occupancy = (self.voxelize(all_points, all_valid) > 0).to(depth.dtype)
        s = self.proposal_stride
        coarse = F.max_pool3d(occupancy.unsqueeze(1), kernel_size=s, stride=s).squeeze(1)
        out = {"depth": fused, "points": points, "valid": valid, "occupancy": occupancy, "coarse_occupancy": coarse}
        if self.query_net is not None:
            out["proposals"] = query_proposals(occupancy, self.query_net)
        return out


def proposal_indices(proposals: Tensor) -> list[Tensor]:
    """Proposal mask [B, X, Y, Z] -> per sample the [K, 3] (long) indices of the proposed voxels."""
    return [torch.nonzero(p > 0) for p in proposals]


def proposal_depth_loss(
    pred_depth: Tensor,
    gt_depth: Tensor,
    prior: Tensor | None = None,
    prior_loss: nn.Module | None = None,
) -> Tensor:
    """Depth loss of the stage-1 depth branch: mean L1 to ground truth + the SGDE prior loss.

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

    ``forward(depth, sensor_to_ego, prior, confidence)`` -> (occupancy, coarse): ``coarse`` is the
    query-proposal network's ``proposals`` when the module has one, else ``coarse_occupancy``.
    """

    def __init__(self, proposals: DepthToVoxelProposals, cameras: Sequence[CameraModel]) -> None:
        super().__init__()
        self.proposals = proposals
        self.cameras = list(cameras)

    def forward(self, depth: Tensor, sensor_to_ego: Tensor, prior: Tensor, confidence: Tensor) -> tuple[Tensor, Tensor]:
        """[B, N, H, W] maps and [B, N, 4, 4] poses -> occupancy [B, X, Y, Z], coarse [B, X/s, Y/s, Z/s]."""
        out = self.proposals(depth, self.cameras, sensor_to_ego, prior, confidence)
        return out["occupancy"], out.get("proposals", out["coarse_occupancy"])
