"""Adapters of the SGDE depth prior to BEVDepth-style and VoxFormer-style pipelines.

Names are loaded on first use, so ``import sgde_plugin.adapters`` is cheap; see ``registry`` for
the optional mmdet3d registration.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "PriorDepthNet": "bevdepth",
    "PriorInjector": "bevdepth",
    "inject_prior": "bevdepth",
    "PRIOR_KEY": "prior_path",
    "PriorFeed": "prior_path",
    "DepthToVoxelProposals": "voxformer",
    "RigDepthToVoxelProposals": "voxformer",
    "VoxelGrid": "voxel_grids",
    "VOXFORMER_GRID": "voxel_grids",
    "OCC3D_NUSCENES_GRID": "voxel_grids",
    "GRID_PRESETS": "voxel_grids",
    "occupancy_scores": "voxel_grids",
    "reference_points": "voxel_grids",
    "voxformer_head_problems": "voxel_grids",
    "voxformer_head_settings": "voxel_grids",
    "accumulate_sweeps": "voxformer",
    "fuse_depth_with_prior": "voxformer",
    "load_query_net": "voxformer",
    "poses_in_frame": "voxformer",
    "proposal_depth_loss": "voxformer",
    "proposal_indices": "voxformer",
    "query_proposals": "voxformer",
    "write_pseudo": "voxformer_io",
    "write_query": "voxformer_io",
    "read_packed": "voxformer_io",
    "PriorFeatureEncoder": "prior_features",
    "min_pool_nonzero": "prior_features",
    "camera_params": "camera_aware",
    "depth_bin_labels": "depth_bins",
    "depth_bce_loss": "depth_bins",
    "register_mmdet3d": "registry",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)


def _register_if_mmdet3d_loaded() -> None:
    import sys

    if "mmdet3d" in sys.modules and "mmengine" in sys.modules:
        importlib.import_module(f"{__name__}.registry").register_if_loaded()


_register_if_mmdet3d_loaded()
