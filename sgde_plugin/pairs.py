"""Geometry of adjacent camera pairs: which is left, baseline, shared angular sector, image fractions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import Camera
from .geometry import invert_transform, rotation_angle_deg
from .rig import Rig

# Rays within this elevation band (ego frame) define a camera's horizontal azimuth interval.
_HORIZON_BAND_DEG = 5.0


@dataclass(frozen=True)
class PairGeometry:
    """Overlap geometry of one adjacent pair; `left` / `right` are decided from the baseline."""

    left: str
    right: str
    baseline_m: float
    axis_angle_deg: float
    sector_deg: float
    left_fraction: float
    right_fraction: float


def _sample_pixels(cam: Camera, n: int = 160) -> np.ndarray:
    """Grid of pixel positions covering the image edge to edge, (n*n', 2)."""
    nx = n
    ny = max(8, int(round(n * cam.height / cam.width)))
    u = np.linspace(-0.5, cam.width - 0.5, nx)
    v = np.linspace(-0.5, cam.height - 0.5, ny)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], axis=-1)


def _ego_rays(cam: Camera, n: int = 160) -> np.ndarray:
    rays, valid = cam.intrinsics.unproject(_sample_pixels(cam, n))
    return rays[valid] @ cam.sensor_to_ego[:3, :3].T


def optical_axis(cam: Camera) -> np.ndarray:
    """The camera's viewing direction (camera +z) in ego coordinates."""
    return cam.sensor_to_ego[:3, 2].copy()


def left_right(cam_a: Camera, cam_b: Camera) -> tuple[Camera, Camera]:
    """Order a pair as (left, right): left has the smaller coordinate along the mean view's right axis.

    The baseline decides, because stereo disparity is measured along it; for (nearly) co-located
    cameras the optical axes decide instead.
    """
    axis = optical_axis(cam_a) + optical_axis(cam_b)
    up = -(cam_a.sensor_to_ego[:3, 1] + cam_b.sensor_to_ego[:3, 1])  # camera y is down
    right = np.cross(axis, up)
    right /= np.linalg.norm(right)
    b = cam_b.sensor_to_ego[:3, 3] - cam_a.sensor_to_ego[:3, 3]
    s = float(b @ right)
    if abs(s) < 1e-3:
        s = float((optical_axis(cam_b) - optical_axis(cam_a)) @ right)
    return (cam_a, cam_b) if s >= 0 else (cam_b, cam_a)


def _azimuth_interval(rays: np.ndarray, ref_az: float) -> tuple[float, float] | None:
    horiz = np.linalg.norm(rays[:, :2], axis=1)
    elev = np.degrees(np.arctan2(rays[:, 2], horiz))
    band = rays[np.abs(elev) < _HORIZON_BAND_DEG]
    if band.shape[0] == 0:
        return None
    az = np.degrees(np.arctan2(band[:, 1], band[:, 0])) - ref_az
    az = (az + 180.0) % 360.0 - 180.0
    return float(az.min()), float(az.max())


def _fraction_seen_by(src: Camera, dst: Camera, n: int) -> float:
    """Share of src's valid image whose rays (points at infinity) fall inside dst's valid image."""
    rays = _ego_rays(src, n)
    if rays.shape[0] == 0:
        return 0.0
    in_dst = rays @ dst.sensor_to_ego[:3, :3]
    _, valid = dst.intrinsics.project(in_dst)
    return float(valid.mean())


def pair_geometry(cam_a: Camera, cam_b: Camera, samples: int = 160) -> PairGeometry:
    """Overlap geometry of two cameras (order-independent); overlap taken at infinity."""
    left, right = left_right(cam_a, cam_b)
    mean_axis = optical_axis(left) + optical_axis(right)
    ref_az = float(np.degrees(np.arctan2(mean_axis[1], mean_axis[0])))
    ia = _azimuth_interval(_ego_rays(left, samples), ref_az)
    ib = _azimuth_interval(_ego_rays(right, samples), ref_az)
    sector = 0.0 if ia is None or ib is None else max(0.0, min(ia[1], ib[1]) - max(ia[0], ib[0]))
    cos = np.clip(optical_axis(left) @ optical_axis(right), -1.0, 1.0)
    return PairGeometry(
        left=left.name,
        right=right.name,
        baseline_m=float(np.linalg.norm(right.sensor_to_ego[:3, 3] - left.sensor_to_ego[:3, 3])),
        axis_angle_deg=float(np.degrees(np.arccos(cos))),
        sector_deg=sector,
        left_fraction=_fraction_seen_by(left, right, samples),
        right_fraction=_fraction_seen_by(right, left, samples),
    )


def rig_pair_geometry(rig: Rig, samples: int = 160) -> list[PairGeometry]:
    """Pair geometry of every adjacent pair of a rig, in the rig's pair order."""
    return [pair_geometry(rig.camera(a), rig.camera(b), samples) for a, b in rig.pairs]


def relative_pose_errors(rig: Rig, reference: Rig) -> list[dict]:
    """Per adjacent pair: rotation (deg) and translation (m) error of the pair's relative pose vs `reference`."""
    rows = []
    for a, b in rig.pairs:
        rel = invert_transform(rig.camera(a).sensor_to_ego) @ rig.camera(b).sensor_to_ego
        ref = invert_transform(reference.camera(a).sensor_to_ego) @ reference.camera(b).sensor_to_ego
        delta = invert_transform(ref) @ rel
        rows.append({"pair": f"{a}-{b}", "rotation_deg": rotation_angle_deg(delta[:3, :3]),
                     "translation_m": float(np.linalg.norm(rel[:3, 3] - ref[:3, 3]))})
    return rows
