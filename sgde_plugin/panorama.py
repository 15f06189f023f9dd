"""Rig-centred equirectangular ground truth (OmniMVS inverse-depth TIFFs) splatted into one camera.

Below the readers: `Rig.load_depth` reads these panoramas without importing `readers.omnimvs`. The ray
convention is OmniMVS's `makeSphericalRays` (documented in `sgde_plugin.readers.omnimvs`).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera
from .errors import InputError
from .geometry import CAMERA_TO_BODY
from .splat import splat_depth

SKY_INV_DEPTH = 1e-3  # inverse depth below this (beyond 1 km) is sky, as in OmniMVS


def read_inverse_depth_tiff(path: str | Path) -> np.ndarray:
    """The float32 page of an OmniMVS ground-truth TIFF (inverse depth, 1/m), shape (H, W)."""
    ok, pages = cv2.imreadmulti(str(path), flags=cv2.IMREAD_UNCHANGED)
    if not ok:
        raise InputError(path, None, "cannot read TIFF")
    floats = [p for p in pages if p.dtype == np.float32 and p.ndim == 2]
    if len(floats) != 1:
        raise InputError(path, None, f"expected one single-channel float32 page, found {len(floats)}")
    return floats[0]


def panorama_rays(height: int, width: int, phi_deg: float | None = None) -> np.ndarray:
    """Unit rays (H, W, 3) in OUR ego frame of an OmniMVS equirectangular map (phi_max = 180 H / W by default)."""
    phi_max = math.radians(180.0 * height / width if phi_deg is None else phi_deg)
    theta = (np.arange(width) - width / 2) / (width / 2) * math.pi + math.pi / 2
    half = (height - 1) / 2
    phi = (np.arange(height) - half) / half * phi_max if height > 1 else np.zeros(1)
    phi, theta = np.meshgrid(phi, theta, indexing="ij")
    rig = np.stack([-np.cos(phi) * np.cos(theta), np.sin(phi), np.cos(phi) * np.sin(theta)], axis=-1)
    return rig @ CAMERA_TO_BODY.T


def panorama_depth_to_camera(inv_depth: np.ndarray, camera: Camera, phi_deg: float | None = None) -> np.ndarray:
    """Splat a rig-centred inverse-depth panorama into one camera: float32 (H, W) depth in the camera's
    convention (range for fisheyes), 0 where no panorama point lands; nearest point wins."""
    inv = np.asarray(inv_depth, dtype=np.float64)
    rays = panorama_rays(inv.shape[0], inv.shape[1], phi_deg)
    ok = np.isfinite(inv) & (inv > SKY_INV_DEPTH)
    pts_ego = rays[ok] / inv[ok][:, None]
    R, t = camera.sensor_to_ego[:3, :3], camera.sensor_to_ego[:3, 3]
    return splat_depth((pts_ego - t) @ R, camera).astype(np.float32)


def load_panorama_depth(path: str | Path, camera: Camera, phi_deg: float | None = None) -> np.ndarray:
    """Read an OmniMVS ground-truth TIFF and return the camera's depth map (see `panorama_depth_to_camera`)."""
    return panorama_depth_to_camera(read_inverse_depth_tiff(path), camera, phi_deg)


__all__ = ["SKY_INV_DEPTH", "load_panorama_depth", "panorama_depth_to_camera", "panorama_rays",
           "read_inverse_depth_tiff"]
