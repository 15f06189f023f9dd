"""Voxel grids that state their frame: VoxFormer's (LiDAR frame) and Occ3D-nuScenes' (ego frame).

A grid is axis-aligned in a named coordinate frame: ``"lidar"`` (VoxFormer / SemanticKITTI: the
Velodyne frame, x forward, y left, z up, origin at the sensor about 1.73 m above the road) or
``"ego"`` (this project's nuScenes ego frame: origin on the ground). Points are binned with
VoxFormer's rule (``preprocess/utils/lidar2voxel.py``): a point counts when it lies strictly inside
the grid's box, in voxel ``floor((p - origin) / voxel_size)``; arrays are indexed ``[x, y, z]``.

Also here: the stage-2 reference points in the order of VoxFormer's ``VoxFormerHead.get_ref_3d``,
what an unmodified VoxFormer head would make of a grid, and occupancy IoU / precision / recall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

FRAMES = ("lidar", "ego")


@dataclass(frozen=True)
class VoxelGrid:
    """An axis-aligned voxel grid: lower corner (m), voxel edge (m), shape (X, Y, Z), coordinate frame."""

    origin: tuple[float, float, float]
    voxel_size: float
    shape: tuple[int, int, int]
    frame: str = "ego"

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise ValueError(f"grid frame must be one of {FRAMES}, got {self.frame!r}")

    @property
    def upper(self) -> tuple[float, float, float]:
        """Upper corner of the grid, metres."""
        return tuple(o + self.voxel_size * n for o, n in zip(self.origin, self.shape))

    @property
    def point_cloud_range(self) -> tuple[float, ...]:
        """(x_min, y_min, z_min, x_max, y_max, z_max), the mmdet3d ``point_cloud_range`` of the grid."""
        return (*self.origin, *self.upper)

    @property
    def num_voxels(self) -> int:
        """X * Y * Z."""
        x, y, z = self.shape
        return x * y * z

    def coarsened(self, stride: int) -> VoxelGrid:
        """The same box with voxels ``stride`` times larger (VoxFormer's queries: stride 2)."""
        if any(n % stride for n in self.shape):
            raise ValueError(f"grid shape {self.shape} is not divisible by stride {stride}")
        return replace(self, voxel_size=self.voxel_size * stride, shape=tuple(n // stride for n in self.shape))

    def voxel_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Points [..., 3] in the grid's frame -> voxel indices [..., 3] (long) and inside flags [...].

        Inside means strictly between the lower and the upper corner on every axis (VoxFormer's filter).
        """
        origin = torch.as_tensor(self.origin, dtype=points.dtype, device=points.device)
        upper = torch.as_tensor(self.upper, dtype=points.dtype, device=points.device)
        idx = torch.floor((points - origin) / self.voxel_size).long()
        size = torch.as_tensor(self.shape, device=points.device)
        inside = ((points > origin) & (points < upper) & (idx >= 0) & (idx < size)).all(dim=-1)
        return idx, inside


VOXFORMER_GRID = VoxelGrid(origin=(0.0, -25.6, -2.0), voxel_size=0.2, shape=(256, 256, 32), frame="lidar")
OCC3D_NUSCENES_GRID = VoxelGrid(origin=(-40.0, -40.0, -1.0), voxel_size=0.4, shape=(200, 200, 16), frame="ego")
GRID_PRESETS = {"voxformer": VOXFORMER_GRID, "occ3d-nuscenes": OCC3D_NUSCENES_GRID}


def check_frames(grid: VoxelGrid, rig_frame: str) -> None:
    """Refuse (ValueError) a grid whose frame differs from the frame the rig's poses map into."""
    if rig_frame not in FRAMES:
        raise ValueError(f"rig frame must be one of {FRAMES}, got {rig_frame!r}")
    if grid.frame != rig_frame:
        raise ValueError(
            f"the grid is in the {grid.frame} frame but the rig's sensor_to_ego poses map into the {rig_frame} "
            f"frame: re-express the poses (sensor_to_grid = inv(grid_frame_to_ego) @ sensor_to_ego, e.g. "
            f"adapters.voxformer.poses_in_frame) and declare rig_frame={grid.frame!r}, or use a grid in the "
            f"{rig_frame} frame (a LiDAR-frame grid placed in the ego frame sits as high as the LiDAR is)")


def voxelize(points: Tensor, valid: Tensor, grid: VoxelGrid) -> Tensor:
    """Points [B, P, 3] in the grid's frame + validity [B, P] -> point counts per voxel [B, X, Y, Z]."""
    b = points.shape[0]
    x, y, z = grid.shape
    idx, inside = grid.voxel_index(points)
    keep = valid & inside
    flat = (idx[..., 0] * y + idx[..., 1]) * z + idx[..., 2]
    # points outside the grid go to one extra "dump" cell that is cut off afterwards
    flat = torch.where(keep, flat, torch.full_like(flat, grid.num_voxels))
    counts = torch.zeros(b, grid.num_voxels + 1, dtype=points.dtype, device=points.device)
    counts = counts.scatter_add(1, flat, keep.to(points.dtype))
    return counts[:, : grid.num_voxels].reshape(b, x, y, z)


# --- VoxFormer's stage-2 reference points --------------------------------------------------------

VOXFORMER_HEAD_REAL_M = 51.2  # VoxFormerHead.real_h = real_w
VOXFORMER_HEAD_SCENE_M = (51.2, 51.2, 6.4)  # get_ref_3d's scene_size
VOXFORMER_HEAD_ORIGIN = (0.0, -25.6, -2.0)  # get_ref_3d's vox_origin


def reference_points(query_grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray]:
    """Voxel coordinates [Q, 4] (i, j, k, flat index) and normalised centres [Q, 3] of ``query_grid``.

    The order is VoxFormer's ``get_ref_3d`` (meshgrid 'ij', flat index = (i * Y + j) * Z + k, i.e. a
    C-order flatten of a [X, Y, Z] query mask); centres are ((i + 0.5) / X, (j + 0.5) / Y, (k + 0.5) / Z).
    """
    shape = np.asarray(query_grid.shape)
    ijk = np.stack(np.indices(query_grid.shape), axis=-1).reshape(-1, 3)
    flat = np.arange(len(ijk))[:, None]
    return np.concatenate([ijk, flat], axis=1), (ijk + 0.5) / shape


def unmodified_head_coordinates(bev_h: int, bev_w: int, bev_z: int) -> np.ndarray:
    """Voxel coordinates [Q', 3] that an unmodified VoxFormerHead builds for (bev_h, bev_w, bev_z) queries.

    Its voxel edge is 51.2 m / bev_h over a hard-coded 51.2 x 51.2 x 6.4 m scene, so Q' equals
    bev_h * bev_w * bev_z only for grids of VoxFormer's proportions.
    """
    voxel = VOXFORMER_HEAD_REAL_M / bev_h
    dims = [int(math.ceil(s / voxel)) for s in VOXFORMER_HEAD_SCENE_M]
    return np.stack(np.indices(dims), axis=-1).reshape(-1, 3)


def voxformer_head_settings(query_grid: VoxelGrid) -> dict[str, object]:
    """What VoxFormer's stage-2 head must be given to consume queries on ``query_grid`` unchanged."""
    x, y, z = query_grid.shape
    s = query_grid.voxel_size
    return {
        "bev_h": x, "bev_w": y, "bev_z": z,
        "real_h": x * s, "real_w": y * s,  # VoxFormerHead.real_h / real_w (hard-coded 51.2)
        "scene_size": (x * s, y * s, z * s),  # get_ref_3d's scene_size (hard-coded 51.2, 51.2, 6.4)
        "vox_origin": tuple(query_grid.origin),  # get_ref_3d's vox_origin (hard-coded 0, -25.6, -2)
        "point_cloud_range": query_grid.point_cloud_range,
        "frame": query_grid.frame,
        "output_shape": (2 * x, 2 * y, 2 * z),  # the head's Header upsamples the queries by 2
    }


def voxformer_head_problems(query_grid: VoxelGrid) -> list[str]:
    """What an unmodified VoxFormer head gets wrong for queries on ``query_grid`` ([] if nothing)."""
    x, y, z = query_grid.shape
    problems = []
    n_head = len(unmodified_head_coordinates(x, y, z))
    if n_head != query_grid.num_voxels:
        problems.append(f"get_ref_3d builds {n_head} coordinates for {query_grid.num_voxels} queries "
                        "(scene size hard-coded to 51.2 x 51.2 x 6.4 m)")
    if not np.isclose(VOXFORMER_HEAD_REAL_M / x, query_grid.voxel_size):
        problems.append(f"the head's voxel edge is {VOXFORMER_HEAD_REAL_M / x:.4g} m, the queries' "
                        f"{query_grid.voxel_size:.4g} m (real_h hard-coded to 51.2 m)")
    if not np.allclose(query_grid.origin, VOXFORMER_HEAD_ORIGIN):
        problems.append(f"the head's grid origin is {VOXFORMER_HEAD_ORIGIN}, the queries' {tuple(query_grid.origin)}")
    if query_grid.frame != "lidar":
        problems.append("the head projects LiDAR-frame points (lidar2img), "
                        f"the queries are in the {query_grid.frame} frame")
    return problems


# --- evaluation ----------------------------------------------------------------------------------

def occupancy_scores(pred: Tensor | np.ndarray, truth: Tensor | np.ndarray) -> dict[str, float]:
    """IoU, precision and recall of an occupied-voxel mask against the true one (any shapes, equal)."""
    p = np.asarray(pred.detach().cpu() if isinstance(pred, Tensor) else pred) > 0
    t = np.asarray(truth.detach().cpu() if isinstance(truth, Tensor) else truth) > 0
    if p.shape != t.shape:
        raise ValueError(f"prediction {p.shape} and truth {t.shape} differ in shape")
    tp = int(np.count_nonzero(p & t))
    n_p, n_t = int(np.count_nonzero(p)), int(np.count_nonzero(t))
    union = n_p + n_t - tp
    return {
        "iou": tp / union if union else math.nan,
        "precision": tp / n_p if n_p else math.nan,
        "recall": tp / n_t if n_t else math.nan,
        "true_positives": tp, "predicted": n_p, "occupied": n_t,
    }
