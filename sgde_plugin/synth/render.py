"""Ray-cast rendering of the synthetic world for any camera model, with exact depth.

One code path for every model: each pixel (or k x k sub-pixel) is unprojected with the camera
model, rotated camera -> ego -> world, and intersected with the analytic primitives; the nearest hit
wins. Rays are grouped in square image tiles; each tile's bounding cone is tested against each
primitive's bounding sphere so a primitive is only intersected with the rays that may hit it.
All positions are taken relative to the camera centre (in float64 before the cast to float32), so
float32 ray parameters keep the depth accurate to ~1e-6 relative.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera, CameraModel
from ..threads import torch_threads  # noqa: F401 - re-exported
from .ego_body import body_hits, reflect
from .shading import shade
from .world import World

TILE_PX = 16
MAX_DISTANCE_M = 400.0  # primitives farther than this are not drawn
MAX_DEPTH_M = 250.0  # ground truth beyond this is "no value" (depth PNGs stop at 255.99 m)
_CONE_MARGIN = 2e-3


@dataclass(frozen=True, eq=False)
class RayTiles:
    """A camera model's rays grouped in tiles: `dirs` (n_tiles, R, 3) camera-frame unit rays, float32."""

    dirs: Tensor
    valid: Tensor
    axis: Tensor
    half_angle: Tensor
    pixel_angle: Tensor
    tiles_y: int
    tiles_x: int
    tile: int
    k: int


def _subpixel_grid(width: int, height: int, tile: int, k: int) -> tuple[Tensor, Tensor]:
    """Sub-pixel positions in tile order, (n_tiles, tile*tile*k*k, 2), and 'inside the image' flags."""
    ty, tx = -(-height // tile), -(-width // tile)
    off = (torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5
    v = torch.arange(ty * tile, dtype=torch.float64)
    u = torch.arange(tx * tile, dtype=torch.float64)
    vv = (v[:, None] + off[None, :]).reshape(ty, tile, k)  # (ty, tile, k)
    uu = (u[:, None] + off[None, :]).reshape(tx, tile, k)
    V = vv[:, None, :, None, :, None].expand(ty, tx, tile, tile, k, k)
    U = uu[None, :, None, :, None, :].expand(ty, tx, tile, tile, k, k)
    inside = (V < height - 0.5) & (U < width - 0.5)
    uv = torch.stack([U, V], dim=-1).reshape(ty * tx, tile * tile * k * k, 2)
    return uv, inside.reshape(ty * tx, -1)


@functools.lru_cache(maxsize=24)
def ray_tiles(intrinsics: CameraModel, k: int = 1, tile: int = TILE_PX) -> RayTiles:
    """Rays of every (sub-)pixel of a camera model, grouped in tiles with their bounding cones (cached)."""
    uv, inside = _subpixel_grid(intrinsics.width, intrinsics.height, tile, k)
    rays, valid = intrinsics.unproject_torch(uv)
    valid = valid & inside & torch.isfinite(rays).all(-1)
    # angular size of one whole pixel (texture is pre-filtered at pixel scale; sub-rays only
    # anti-alias silhouettes), from the neighbouring positions
    ru, _ = intrinsics.unproject_torch(uv + torch.tensor([1.0, 0.0], dtype=uv.dtype))
    rv, _ = intrinsics.unproject_torch(uv + torch.tensor([0.0, 1.0], dtype=uv.dtype))
    ang_u = torch.acos((rays * ru).sum(-1).clamp(-1, 1))
    ang_v = torch.acos((rays * rv).sum(-1).clamp(-1, 1))
    pixel_angle = torch.nan_to_num(0.5 * (ang_u + ang_v), nan=1e-3)
    rays = torch.where(valid[..., None], rays, torch.tensor([0.0, 0.0, 1.0], dtype=rays.dtype))
    axis = (rays * valid[..., None]).sum(1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (rays * axis[:, None, :]).sum(-1).clamp(-1, 1)
    ang = torch.where(valid, torch.acos(cos), torch.zeros_like(cos))
    half = ang.max(dim=1).values + _CONE_MARGIN
    half = torch.where(valid.any(1), half, torch.full_like(half, -1.0))
    ty, tx = -(-intrinsics.height // tile), -(-intrinsics.width // tile)
    return RayTiles(rays.float(), valid, axis.float(), half.float(), pixel_angle.float(), ty, tx, tile, k)


@dataclass(frozen=True, eq=False)
class Hits:
    """Nearest hits of a tile set of rays: ray parameter `t` (inf = none) and primitive id (-1 sky, 0 ground)."""

    t: Tensor
    pid: Tensor
    dirs: Tensor


def _rotz(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((*np.shape(yaw), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def _cone_candidates(tiles: RayTiles, axes: Tensor, rel: np.ndarray, radius: np.ndarray) -> Tensor:
    """(n_tiles, n) bool: the tile's cone may meet the bounding sphere (centre rel, radius) of each primitive."""
    dist = np.linalg.norm(rel, axis=1)
    unit = torch.from_numpy(rel / np.maximum(dist, 1e-9)[:, None]).float()
    reach = torch.from_numpy(np.arcsin(np.clip(radius / np.maximum(dist, 1e-9), 0.0, 1.0))).float()
    inside = torch.from_numpy(dist <= radius)
    ang = torch.acos((axes @ unit.T).clamp(-1, 1))
    return ((ang <= tiles.half_angle[:, None] + reach[None, :]) & (tiles.half_angle[:, None] >= 0)) | inside[None]


def trace(world: World, tiles: RayTiles, cam_to_world: np.ndarray, time_s: float) -> Hits:
    """Nearest hit of every ray of `tiles` from a camera with pose `cam_to_world` (4x4) at `time_s`."""
    R = cam_to_world[:3, :3]
    origin = cam_to_world[:3, 3]
    Rt = torch.from_numpy(R.T.copy()).float()
    dirs = tiles.dirs @ Rt  # (n_tiles, R, 3) world directions
    axes = tiles.axis @ Rt
    t = torch.full(dirs.shape[:2], float("inf"))
    pid = torch.full(dirs.shape[:2], -1, dtype=torch.int32)

    # ground plane z = 0
    dz = dirs[..., 2]
    if origin[2] > 0:
        down = dz < -1e-7
        t = torch.where(down, float(-origin[2]) / torch.where(down, dz, torch.ones_like(dz)), t)
        pid = torch.where(down, torch.zeros_like(pid), pid)

    # boxes
    centers = world.box_centers(time_s)
    rel = centers - origin
    radius = np.linalg.norm(world.box_half, axis=1)
    near = np.nonzero(np.linalg.norm(rel, axis=1) - radius < MAX_DISTANCE_M)[0]
    if near.size:
        cand = _cone_candidates(tiles, axes, rel[near], radius[near])
        rot = _rotz(-world.box_yaw[near])  # world -> box
        o_local = np.einsum("nij,nj->ni", rot, -rel[near])
        for col in torch.nonzero(cand.any(0)).flatten().tolist():
            j = int(near[col])
            idx = torch.nonzero(cand[:, col]).flatten()
            d = dirs[idx] @ torch.from_numpy(rot[col].T.copy()).float()
            th = _box_hit(d, o_local[col], world.box_half[j])
            cur = t[idx]
            better = th < cur
            t[idx] = torch.where(better, th, cur)
            pid[idx] = torch.where(better, torch.full_like(pid[idx], 1 + j), pid[idx])

    # poles (vertical cylinders standing on the ground)
    if world.n_poles:
        prel = np.concatenate([world.pole_xy - origin[:2], (world.pole_height / 2 - origin[2])[:, None]], axis=1)
        pradius = np.hypot(world.pole_radius, world.pole_height / 2)
        pnear = np.nonzero(np.linalg.norm(prel, axis=1) - pradius < MAX_DISTANCE_M)[0]
        if pnear.size:
            cand = _cone_candidates(tiles, axes, prel[pnear], pradius[pnear])
            for col in torch.nonzero(cand.any(0)).flatten().tolist():
                m = int(pnear[col])
                idx = torch.nonzero(cand[:, col]).flatten()
                th = _cylinder_hit(dirs[idx], prel[m, :2], float(world.pole_radius[m]), float(-origin[2]),
                                   float(world.pole_height[m] - origin[2]))
                cur = t[idx]
                better = th < cur
                t[idx] = torch.where(better, th, cur)
                pid[idx] = torch.where(better, torch.full_like(pid[idx], 1 + world.n_boxes + m), pid[idx])

    invalid = ~tiles.valid
    t = t.masked_fill(invalid, float("inf"))
    pid = pid.masked_fill(invalid | ~torch.isfinite(t), -1)
    return Hits(t, pid, dirs)


def _box_hit(d: Tensor, o: np.ndarray, half: np.ndarray) -> Tensor:
    """Entry parameter of rays (origin o, directions d, box frame) into the box |x| <= half; inf if missed."""
    o_t = torch.from_numpy(o).float()
    h_t = torch.from_numpy(half).float()
    inv = 1.0 / d
    t1 = (-h_t - o_t) * inv
    t2 = (h_t - o_t) * inv
    t_near = torch.minimum(t1, t2).amax(-1)
    t_far = torch.maximum(t1, t2).amin(-1)
    hit = (t_near <= t_far) & (t_near > 1e-4)
    return torch.where(hit, t_near, torch.full_like(t_near, float("inf")))


def _cylinder_hit(d: Tensor, c_xy: np.ndarray, r: float, z0: float, z1: float) -> Tensor:
    """Entry parameter of rays from the origin into a vertical cylinder (axis at c_xy, z in [z0, z1]); inf if missed."""
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    cx, cy = float(c_xy[0]), float(c_xy[1])
    a = dx * dx + dy * dy
    b = -2.0 * (dx * cx + dy * cy)
    c = cx * cx + cy * cy - r * r
    disc = b * b - 4 * a * c
    ok = (disc >= 0) & (a > 1e-12)
    th = (-b - torch.sqrt(disc.clamp_min(0))) / (2 * a.clamp_min(1e-12))
    z = th * dz
    ok = ok & (th > 1e-4) & (z >= z0) & (z <= z1)
    return torch.where(ok, th, torch.full_like(th, float("inf")))


def _untile(x: Tensor, tiles: RayTiles, height: int, width: int) -> Tensor:
    """(n_tiles, R, ...) in tile order -> (H, W, k*k, ...) image order, cropped to the image."""
    T, k = tiles.tile, tiles.k
    rest = x.shape[2:]
    x = x.reshape(tiles.tiles_y, tiles.tiles_x, T, T, k, k, *rest)
    x = x.permute(0, 2, 1, 3, 4, 5, *range(6, 6 + len(rest)))
    x = x.reshape(tiles.tiles_y * T, tiles.tiles_x * T, k * k, *rest)
    return x[:height, :width]


def pixel_angle_at_centre(intrinsics: CameraModel) -> float:
    """Angle (radians) between the rays of the two pixels left and right of the principal area's centre."""
    cu, cv = (intrinsics.width - 1) / 2, (intrinsics.height - 1) / 2
    rays, _ = intrinsics.unproject(np.array([[cu - 0.5, cv], [cu + 0.5, cv]]))
    return float(np.arccos(np.clip(rays[0] @ rays[1], -1.0, 1.0)))


@dataclass(frozen=True)
class TextureLod:
    """Texture level of detail shared by a rig: pre-filter angle (radians) and origin (ego metres).

    Texture is pre-filtered by (distance from the origin x angle), so every camera of the rig sees
    exactly the same colour at a surface point whatever its resolution or position.
    """

    angle: float
    origin_ego: tuple[float, float, float]


def rig_lod(cameras: list[Camera]) -> TextureLod:
    """The LOD of a rig: the coarsest camera's central pixel angle, measured from the mean camera position."""
    angle = max(pixel_angle_at_centre(c.intrinsics) for c in cameras)
    centre = np.mean([c.sensor_to_ego[:3, 3] for c in cameras], axis=0)
    return TextureLod(angle, tuple(float(v) for v in centre))


def _cone_tiles(tiles: RayTiles, dirs: Tensor, valid: Tensor) -> RayTiles:
    """The same tiling with other ray directions (camera frame) and validity, bounding cones recomputed."""
    axis = (dirs * valid[..., None]).sum(1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos = (dirs * axis[:, None, :]).sum(-1).clamp(-1, 1)
    ang = torch.where(valid, torch.acos(cos), torch.zeros_like(cos))
    half = torch.where(valid.any(1), ang.max(dim=1).values + _CONE_MARGIN, torch.full_like(axis[:, 0], -1.0))
    return RayTiles(dirs, valid, axis, half, tiles.pixel_angle, tiles.tiles_y, tiles.tiles_x, tiles.tile, tiles.k)


def _with_ego_body(world: World, tiles: RayTiles, rgb: Tensor, camera: Camera, cam_to_world: np.ndarray,
                   time_s: float, angle: Tensor, lod_origin: np.ndarray | None) -> Tensor:
    """Linear RGB with the ego body's pixels replaced by its paint mixed with the mirrored world."""
    body = world.ego_body
    t, n, trim = body_hits(body, tiles.dirs, camera.sensor_to_ego)
    on = tiles.valid & torch.isfinite(t)
    if not bool(on.any()):
        return rgb
    mirrored = reflect(tiles.dirs, n.float(), camera.sensor_to_ego).float()
    mirrored = mirrored / mirrored.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    rt = _cone_tiles(tiles, torch.where(on[..., None], mirrored, tiles.dirs), on)
    hits = trace(world, rt, cam_to_world, time_s)
    seen = shade(world, hits.t, hits.pid, hits.dirs, angle, rt.valid, cam_to_world[:3, 3], time_s, lod_origin)
    paint = torch.tensor(body.paint, dtype=rgb.dtype) * (0.55 + 0.45 * n[..., 2:3].to(rgb.dtype))
    mixed = (1 - body.reflectivity) * paint + body.reflectivity * seen
    mixed = torch.where(trim[..., None], torch.full_like(mixed, 0.03), mixed)
    return torch.where(on[..., None], mixed, rgb)


def render(
    world: World, camera: Camera, ego_to_world: np.ndarray, time_s: float, supersample: int = 1, threads: int = 1,
    lod: TextureLod | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """RGB uint8 (H, W, 3) and depth float32 (H, W) in the camera's convention (z or range), 0 = no value.

    `threads` is torch's intra-op thread count during the call (1 is fastest on a shared machine;
    render several cameras concurrently for throughput, as `synth_sequence` does). `lod` sets the
    texture pre-filter; pass `rig_lod(cameras)` to render a rig consistently (default: this
    camera's own per-pixel footprint).
    """
    if supersample < 1:
        raise ValueError("supersample must be >= 1")
    intr = camera.intrinsics
    cam_to_world = np.asarray(ego_to_world, dtype=np.float64) @ np.asarray(camera.sensor_to_ego, dtype=np.float64)
    with torch.no_grad(), torch_threads(threads):
        tiles1 = ray_tiles(intr, 1)
        hits1 = trace(world, tiles1, cam_to_world, time_s)
        if intr.depth_is_range:
            depth_t = hits1.t
        else:
            depth_t = hits1.t * tiles1.dirs[..., 2]
        has_depth = (hits1.pid >= 0) & (hits1.t <= MAX_DEPTH_M)
        if world.ego_body is not None:
            tb, _, _ = body_hits(world.ego_body, tiles1.dirs, camera.sensor_to_ego)
            on = tiles1.valid & torch.isfinite(tb)
            depth_t = torch.where(on, tb.float() * (1.0 if intr.depth_is_range else tiles1.dirs[..., 2]), depth_t)
            has_depth = has_depth | on
        depth_t = torch.where(has_depth, depth_t, torch.zeros_like(depth_t))
        depth = _untile(depth_t, tiles1, intr.height, intr.width)[:, :, 0]

        if supersample == 1:
            tiles, hits = tiles1, hits1
        else:
            tiles = ray_tiles(intr, supersample)
            hits = trace(world, tiles, cam_to_world, time_s)
        if lod is None:
            angle, lod_origin = tiles.pixel_angle, None
        else:
            angle = torch.full_like(tiles.pixel_angle, float(lod.angle))
            lod_origin = (np.asarray(ego_to_world, np.float64) @ np.array([*lod.origin_ego, 1.0]))[:3]
        rgb = shade(world, hits.t, hits.pid, hits.dirs, angle, tiles.valid, cam_to_world[:3, 3], time_s, lod_origin)
        if world.ego_body is not None:
            rgb = _with_ego_body(world, tiles, rgb, camera, cam_to_world, time_s, angle, lod_origin)
        rgb = _untile(rgb, tiles, intr.height, intr.width).mean(dim=2)
        rgb8 = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
    return rgb8.numpy(), depth.numpy().astype(np.float32)
