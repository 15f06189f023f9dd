"""Downstream effect on exact truth: stage-1 occupancy of a rig's predicted depth vs the true occupancy.

VoxFormer's stage 1 voxelises the pseudo points of a depth map (``sgde_plugin.adapters.voxformer``).
On the synthetic world the geometry is exact, so the true stage-1 occupancy of a frame is the
voxelisation of its exact depth on the same pixel grid: what a perfect depth network at that
resolution would give. IoU / precision / recall of the predicted occupancy against it, pooled over
frames and cameras, on two grids:

- ``occ3d``: Occ3D-nuScenes, 200 x 200 x 16 at 0.4 m over [-40, 40] x [-40, 40] x [-1, 5.4] m, ego frame;
- ``voxformer``: VoxFormer's 256 x 256 x 32 at 0.2 m over [0, 51.2] x [-25.6, 25.6] x [-2, 4.4] m in the
  frame of the roof LiDAR (``nn.sequence.LIDAR_POSITION``, axes as the ego's), as VoxFormer expects.

Every predicted pixel is voxelised (as VoxFormer does); truth pixels are those with a depth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ..adapters.voxel_grids import OCC3D_NUSCENES_GRID, VOXFORMER_GRID, VoxelGrid, voxelize
from ..adapters.voxformer import DepthToVoxelProposals, poses_in_frame
from ..cameras import Camera
from ..geometry import make_transform
from ..nn import DepthNet
from ..nn.sequence import LIDAR_POSITION, RigSequence
from ..nn.train import frame_tensors


def benchmark_grids(lidar_position: np.ndarray = LIDAR_POSITION) -> dict[str, tuple[VoxelGrid, np.ndarray]]:
    """The two grids of the benchmark, each with its frame's pose in the ego frame (frame_to_ego)."""
    return {"occ3d": (OCC3D_NUSCENES_GRID, np.eye(4)),
            "voxformer": (VOXFORMER_GRID, make_transform(np.eye(3), lidar_position))}


def _occupancies(depth: np.ndarray, cameras: Sequence[Camera], grid: VoxelGrid,
                 frame_to_ego: np.ndarray) -> torch.Tensor:
    """Depth [F, N, H, W] -> occupancy [F, X, Y, Z] (bool) in ``grid``."""
    module = DepthToVoxelProposals(grid, rig_frame=grid.frame)
    poses = torch.from_numpy(np.stack([poses_in_frame(c.sensor_to_ego, frame_to_ego) for c in cameras]))
    points, valid = module.points(torch.from_numpy(np.asarray(depth, dtype=np.float64)),
                                  [c.intrinsics for c in cameras], poses)
    f = depth.shape[0]
    return voxelize(points.reshape(f, -1, 3), valid.reshape(f, -1), grid) > 0


def rig_occupancy_scores(pred: np.ndarray, truth: np.ndarray, cameras: Sequence[Camera],
                         grids: dict[str, tuple[VoxelGrid, np.ndarray]] | None = None) -> dict[str, float]:
    """Occupancy IoU / precision / recall of predicted depth [F, N, H, W] vs true depth, pooled over frames.

    Keys ``occ_<grid>_iou``, ``occ_<grid>_precision``, ``occ_<grid>_recall`` for each grid of
    ``grids`` (default ``benchmark_grids()``); 0 in a depth map means no value.
    """
    grids = grids or benchmark_grids()
    out: dict[str, float] = {}
    for name, (grid, frame_to_ego) in grids.items():
        p = _occupancies(pred, cameras, grid, frame_to_ego)
        t = _occupancies(truth, cameras, grid, frame_to_ego)
        tp, n_p, n_t = int((p & t).sum()), int(p.sum()), int(t.sum())
        union = n_p + n_t - tp
        out[f"occ_{name}_iou"] = tp / union if union else math.nan
        out[f"occ_{name}_precision"] = tp / n_p if n_p else math.nan
        out[f"occ_{name}_recall"] = tp / n_t if n_t else math.nan
    return out


def predict_depth(net: DepthNet, seq: RigSequence, frames: list[int]) -> np.ndarray:
    """The network's depth [F, N, H, W] for ``frames`` of ``seq`` (with the prior when the net takes one)."""
    net.eval()
    preds = []
    with torch.no_grad():
        for k in frames:
            rgb, _, prior, valid = frame_tensors(seq, [k])
            pred = net.predict(rgb, prior if net.use_prior else None, valid if net.use_prior else None)
            preds.append(pred[:, 0].numpy())
    return np.stack(preds)


def occupancy_eval(net: DepthNet, seq: RigSequence, frames: list[int], paste_prior: bool = False) -> dict[str, float]:
    """``rig_occupancy_scores`` of a trained net's depth on ``frames`` against their exact depth.

    ``paste_prior``: the prior replaces the depth wherever it is valid first, as the VoxFormer
    adapter's ``fuse_depth_with_prior`` does.
    """
    pred = predict_depth(net, seq, frames)
    if paste_prior:
        pred = np.where(seq.valid[frames], seq.prior[frames], pred)
    return rig_occupancy_scores(pred, seq.depth[frames], seq.cameras)


def occupancy_table(arms: dict[str, dict]) -> str:
    """Markdown table of the occupancy scores of each arm (means over seeds)."""
    lines = ["| arm | Occ3D IoU | precision | recall | VoxFormer IoU | precision | recall |",
             "|---|---|---|---|---|---|---|"]
    for name, r in arms.items():
        for label, prefix in ((name, "occ"), (f"{name}, prior pasted", "pasted_occ")):
            if f"{prefix}_occ3d_iou" not in r:
                continue
            keys = [f"{prefix}_{g}_{m}" for g in ("occ3d", "voxformer") for m in ("iou", "precision", "recall")]
            cells = [f"{r[k]:.3f}" for k in keys]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
