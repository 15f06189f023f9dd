"""Virtual pinhole cameras for fisheyes (SGDE step 1): a left and a right half, each a pinhole.

Each half is a pinhole sharing the fisheye's optical centre, turned by +-yaw about the camera's
vertical axis, with a chosen field of view and a focal length matching the fisheye's angular
resolution at the half's centre. The image is resampled bilinearly from the fisheye in one remap;
pixels that come from the last few pixels of the fisheye's image circle (the rim) are discarded.
"""

from __future__ import annotations

import math

import numpy as np

from ..cameras import Camera, Pinhole
from .rectify import WarpMaps, angular_resolution, default_rim_px


def _yaw(angle: float) -> np.ndarray:
    """Rotation about the camera's y axis (down) by `angle`: +angle turns z towards +x (right)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def virtual_pinholes(
    camera: Camera,
    hfov_deg: float | None = None,
    vfov_deg: float = 90.0,
    yaw_deg: float | None = None,
    scale: float = 1.0,
) -> tuple[Camera, Camera]:
    """The (left, right) virtual pinhole halves of a fisheye `camera`.

    Defaults: each half looks `yaw_deg` = fov/4 away from the axis and spans `hfov_deg` = fov/2
    (capped at 120 degrees) horizontally, so the halves tile the fisheye's horizontal field;
    focal = `scale` x the fisheye's angular resolution (px/rad) at the half's centre.
    """
    fov = float(getattr(camera.intrinsics, "fov_deg", 180.0))
    yaw = math.radians(fov / 4 if yaw_deg is None else yaw_deg)
    hfov = math.radians(min(fov / 2, 120.0) if hfov_deg is None else hfov_deg)
    vfov = math.radians(vfov_deg)
    if not (0 < hfov < math.pi and 0 < vfov < math.pi):
        raise ValueError("virtual pinhole fields of view must be in (0, 180) degrees")
    halves = []
    for name, sign in (("L", -1.0), ("R", 1.0)):
        R = camera.sensor_to_ego[:3, :3] @ _yaw(sign * yaw)
        res = angular_resolution(camera, R[:, 2])
        if res is None:
            raise ValueError(f"camera {camera.name}: the {name} half's centre lies outside its field of view")
        f = scale * res
        w = max(2, int(round(2 * f * math.tan(hfov / 2))))
        h = max(2, int(round(2 * f * math.tan(vfov / 2))))
        K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
        T = camera.sensor_to_ego.copy()
        T[:3, :3] = R
        halves.append(Camera(f"{camera.name}.{name}", Pinhole(w, h, K, None), T))
    return halves[0], halves[1]


def virtual_pinhole_images(
    camera: Camera, image: np.ndarray, rim_px: int | None = None, **kwargs: float | None
) -> tuple[tuple[np.ndarray, Camera], tuple[np.ndarray, Camera]]:
    """((left image, left camera), (right image, right camera)) of a fisheye image; 0 = no data.

    Keyword arguments go to `virtual_pinholes`; `rim_px` fisheye rim pixels are discarded.
    """
    rim = default_rim_px(camera) if rim_px is None else rim_px
    out = []
    for half in virtual_pinholes(camera, **kwargs):
        out.append((WarpMaps.between(camera, half, rim).warp(image), half))
    return out[0], out[1]
