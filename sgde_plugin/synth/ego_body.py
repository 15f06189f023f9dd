"""An optional glossy ego body for the synthetic world (`sgde synth --ego-body`): hood, roof edges, side panels.

The body is the top of the car: a flat panel at `top_z` (ego frame) over a superellipse footprint
that reaches `margin_m` beyond the outermost cameras, so each camera sees a band of it at the bottom
of its image. Its depth is exact (the panel's plane); its colour mixes a dark paint with a mirror
image of the world: the shading normal bulges outwards towards the edges (like a rounded body), so
the middle reflects the sky and facades and the edges reflect the street. The reflection is traced
from the camera centre along the mirrored ray (an environment-map approximation; the body is within
about a metre), so it moves over the body as the car drives, while the body itself stays put.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera

SUPERELLIPSE_POWER = 4.0


@dataclass(frozen=True)
class EgoBody:
    """Body panel in ego coordinates: footprint centre and half sizes (m), height, paint, reflectivity."""

    center_xy: tuple[float, float]
    half_xy: tuple[float, float]
    top_z: float
    paint: tuple[float, float, float] = (0.30, 0.04, 0.03)
    reflectivity: float = 0.4
    bulge: float = 0.3
    trim: float = 0.06  # a matt black moulding along the outline, share of the footprint radius


def ego_body_for(cameras: list[Camera], margin_m: float = 0.7, drop_m: float = 0.15) -> EgoBody:
    """A body whose top is `drop_m` below the lowest camera and reaches `margin_m` beyond the cameras."""
    pos = np.array([c.sensor_to_ego[:3, 3] for c in cameras])
    cx = float((pos[:, 0].max() + pos[:, 0].min()) / 2)
    cy = float((pos[:, 1].max() + pos[:, 1].min()) / 2)
    a = float(np.abs(pos[:, 0] - cx).max()) + margin_m
    b = float(np.abs(pos[:, 1] - cy).max()) + margin_m
    return EgoBody((cx, cy), (a, b), float(pos[:, 2].min()) - drop_m)


def body_hits(body: EgoBody, dirs_cam: Tensor, sensor_to_ego: np.ndarray) -> tuple[Tensor, Tensor, Tensor]:
    """Ray parameter of each camera ray's hit on the body (inf = none), the shading normal (ego frame)
    and whether the hit is on the matt trim along the outline."""
    R = torch.from_numpy(np.asarray(sensor_to_ego[:3, :3], np.float64)).to(dirs_cam.dtype)
    o = np.asarray(sensor_to_ego[:3, 3], np.float64)
    d = dirs_cam @ R.T
    dz = d[..., 2]
    down = dz < -1e-6
    t = torch.where(down, (body.top_z - o[2]) / torch.where(down, dz, torch.full_like(dz, -1.0)),
                    torch.full_like(dz, float("inf")))
    u = (o[0] + t * d[..., 0] - body.center_xy[0]) / body.half_xy[0]
    v = (o[1] + t * d[..., 1] - body.center_xy[1]) / body.half_xy[1]
    u, v = torch.nan_to_num(u, nan=9.0, posinf=9.0, neginf=-9.0), torch.nan_to_num(v, nan=9.0, posinf=9.0, neginf=-9.0)
    p = SUPERELLIPSE_POWER
    radius = u.abs() ** p + v.abs() ** p
    inside = down & (radius <= 1.0) & (t > 0)
    on_trim = inside & (radius >= (1.0 - body.trim) ** p)
    t = torch.where(inside, t, torch.full_like(t, float("inf")))
    gx = body.bulge * p * torch.sign(u) * u.abs().clamp(max=1.0) ** (p - 1) / body.half_xy[0]
    gy = body.bulge * p * torch.sign(v) * v.abs().clamp(max=1.0) ** (p - 1) / body.half_xy[1]
    n = torch.stack([gx, gy, torch.ones_like(gx)], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    return t, n, on_trim


def reflect(dirs_cam: Tensor, normal_ego: Tensor, sensor_to_ego: np.ndarray) -> Tensor:
    """Camera-frame rays mirrored on the body normals (given in the ego frame)."""
    R = torch.from_numpy(np.asarray(sensor_to_ego[:3, :3], np.float64)).to(dirs_cam.dtype)
    d = dirs_cam @ R.T
    r = d - 2 * (d * normal_ego).sum(-1, keepdim=True) * normal_ego
    return r @ R


def body_mask(body: EgoBody, camera: Camera) -> np.ndarray:
    """Bool (H, W): pixels of `camera` whose centre ray hits the body (the true static mask, True = body)."""
    rays, ok = camera.intrinsics.ray_grid(torch.float64)
    t, _, _ = body_hits(body, rays, camera.sensor_to_ego)
    return (ok & torch.isfinite(t)).numpy()
