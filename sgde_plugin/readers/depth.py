"""Ground-truth depth of any reader's rig, in the contract's convention (metres, 0 = none)."""

from __future__ import annotations

import numpy as np

from ..rig import Rig

TIFF_SUFFIXES = (".tif", ".tiff")


def load_depth(rig: Rig, frame_id: str, camera: str) -> np.ndarray | None:
    """Depth of one camera in one frame: depth PNGs via `Rig.load_depth`, OmniMVS inverse-depth
    panoramas (TIFF) splatted into the camera; None when the frame has no ground truth."""
    path = rig.frame(frame_id).depths.get(camera)
    if path is None:
        return None
    if path.suffix.lower() in TIFF_SUFFIXES:
        from .omnimvs import load_panorama_depth

        return load_panorama_depth(path, rig.camera(camera))
    return rig.load_depth(frame_id, camera)


__all__ = ["load_depth"]
