"""Camera rigs of the synthetic world: nuScenes-like, DDAD-like and a Synthetic-Urban-like fisheye rig.

Mounting positions of `nuscenes` follow the data set's calibrated sensors (ego = rear-axle centre,
cameras about 1.5 m above the ground); focal lengths follow its camera intrinsics (the back camera
is the wide one). Yaws are the nominal ring directions; the rigs are level (no pitch or roll).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..cameras import Camera, Ocam, Pinhole
from ..geometry import camera_mount
from .ego_body import ego_body_for
from .random_rig import random_rig
from .world import World, build_world, with_companions

PRESETS = ("nuscenes", "ddad", "urban-fisheye", "random")

# name, yaw (deg, left +), position (ego metres), focal length at 1600x900
_NUSCENES = (
    ("CAM_FRONT", 0.0, (1.70, 0.016, 1.51), 1266.4),
    ("CAM_FRONT_RIGHT", -55.0, (1.55, -0.493, 1.50), 1260.8),
    ("CAM_BACK_RIGHT", -110.0, (1.01, -0.481, 1.56), 1259.5),
    ("CAM_BACK", 180.0, (0.03, 0.003, 1.58), 809.2),
    ("CAM_BACK_LEFT", 110.0, (1.04, 0.485, 1.59), 1256.7),
    ("CAM_FRONT_LEFT", 55.0, (1.52, 0.495, 1.51), 1272.6),
)

# DDAD ring: front, front-right, rear-right, rear, rear-left, front-left (about 60 degrees apart)
_DDAD = (
    ("CAMERA_01", 0.0, (1.60, 0.00, 1.55)),
    ("CAMERA_06", -60.0, (1.20, -0.75, 1.55)),
    ("CAMERA_08", -120.0, (0.50, -0.75, 1.55)),
    ("CAMERA_09", 180.0, (-0.60, 0.00, 1.55)),
    ("CAMERA_07", 120.0, (0.50, 0.75, 1.55)),
    ("CAMERA_05", 60.0, (1.20, 0.75, 1.55)),
)
_DDAD_SIZE = (1936, 1216)
_DDAD_HFOV_DEG = 68.0

# four 220-degree fisheyes on the sides of a roof rig, facing front, right, back, left
_URBAN = (
    ("F", 0.0, (0.55, 0.00, 1.60)),
    ("R", -90.0, (0.00, -0.55, 1.60)),
    ("B", 180.0, (-0.55, 0.00, 1.60)),
    ("L", 90.0, (0.00, 0.55, 1.60)),
)
_URBAN_SIZE = (800, 768)
_URBAN_FOV_DEG = 220.0


def preset_ring(preset: str, seed: int = 0) -> list[str]:
    """Camera names of a preset in ring order (last adjacent to first); `random` depends on the seed."""
    if preset == "random":
        return random_rig(seed, 0.05).ring
    table = {"nuscenes": _NUSCENES, "ddad": _DDAD, "urban-fisheye": _URBAN}
    if preset not in table:
        raise ValueError(f"unknown preset {preset!r} (expected one of {', '.join(PRESETS)})")
    return [row[0] for row in table[preset]]


def _scaled_size(width: int, height: int, scale: float) -> tuple[int, int]:
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    return max(8, int(round(width * scale))), max(8, int(round(height * scale)))


def _pinhole(width: int, height: int, focal: float) -> Pinhole:
    K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Pinhole(width, height, K)


def equidistant_ocam(width: int, height: int, fov_deg: float, margin_px: float = 4.0, degree: int = 8) -> Ocam:
    """An ocam model with an (almost) equidistant mapping whose image circle fits the shorter side.

    The forward polynomial `poly` (rho -> OCam z) is a least-squares fit of rho * cot(rho / f) (the
    equidistant mapping rho = f * theta); `inv_poly` (elevation angle -> rho) is fitted to the
    same curve, so project and unproject agree before the model's Newton refinement.
    """
    theta_max = math.radians(fov_deg) / 2
    rho_max = min(width, height) / 2 - margin_px
    f = rho_max / theta_max
    rho = np.linspace(0.0, rho_max * 1.04, 400)
    x = rho / f
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(x > 1e-9, -rho * np.cos(x) / np.sin(x), -f)
    # fit in normalised rho for conditioning, then rescale the coefficients
    coeffs = np.polynomial.polynomial.polyfit(rho / rho_max, z, degree)
    poly = coeffs / rho_max ** np.arange(degree + 1)
    z_fit = np.polynomial.polynomial.polyval(rho, poly)
    theta = np.arctan2(rho, -z_fit)
    elevation = theta - math.pi / 2  # the model's inverse-polynomial argument atan(z / rho)
    inv = np.polynomial.polynomial.polyfit(elevation, rho, 12)
    center = np.array([(height - 1) / 2, (width - 1) / 2])
    return Ocam(width, height, poly=poly, inv_poly=inv, center=center, affine=np.array([1.0, 0.0, 0.0]),
                fov_deg=fov_deg)


def preset_cameras(preset: str, scale: float = 1.0, seed: int = 0) -> list[Camera]:
    """Cameras of a preset with their true extrinsics, in ring order; image sizes multiplied by `scale`.

    The `random` preset draws its rig from `seed` (`synth.random_rig`); the others ignore it.
    """
    if preset == "random":
        _scaled_size(1, 1, scale)  # checks the scale
        return list(random_rig(seed, scale).cameras)
    if preset == "nuscenes":
        w, h = _scaled_size(1600, 900, scale)
        sx = w / 1600
        return [
            Camera(name, _pinhole(w, h, focal * sx), camera_mount(math.radians(yaw), np.array(pos)))
            for name, yaw, pos, focal in _NUSCENES
        ]
    if preset == "ddad":
        w, h = _scaled_size(*_DDAD_SIZE, scale)
        focal = (w / 2) / math.tan(math.radians(_DDAD_HFOV_DEG) / 2)
        return [Camera(name, _pinhole(w, h, focal), camera_mount(math.radians(yaw), np.array(pos)))
                for name, yaw, pos in _DDAD]
    if preset == "urban-fisheye":
        w, h = _scaled_size(*_URBAN_SIZE, scale)
        model = equidistant_ocam(w, h, _URBAN_FOV_DEG, margin_px=max(1.0, 4.0 * scale))
        return [Camera(name, model, camera_mount(math.radians(yaw), np.array(pos))) for name, yaw, pos in _URBAN]
    raise ValueError(f"unknown preset {preset!r} (expected one of {', '.join(PRESETS)})")


def preset_world(preset: str, seed: int, ego_body: bool = False) -> World:
    """The street of a seed, plus the near objects of the `random` preset's rig and, optionally, the ego body."""
    world = build_world(seed)
    if preset == "random":
        near = random_rig(seed).near_objects
        world = with_companions(world, [(o.center, o.half, o.yaw, o.color) for o in near])
    if ego_body:
        world = replace(world, ego_body=ego_body_for(preset_cameras(preset, 1.0, seed)))
    return world
