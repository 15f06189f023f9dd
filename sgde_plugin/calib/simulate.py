"""Synthetic correspondences with known truth, for tests and benchmarks of the adjustment alone.

Points are sampled in the image of camera A at frame t with a random depth, projected into camera B
at frame t', and both pixels get Gaussian noise before they are turned back into unit rays.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..geometry import camera_mount, rodrigues
from ..rig import Frame, Rig, ring_pairs
from ..stereo.rectify import torch_threads
from .ba import Observations


def straight_drive(n_frames: int, step_m: float = 1.0, yaw_step_deg: float = 1.0) -> np.ndarray:
    """Ego poses (T, 4, 4) of a car moving forward `step_m` per frame while turning `yaw_step_deg`."""
    poses = np.zeros((n_frames, 4, 4))
    x = y = yaw = 0.0
    for t in range(n_frames):
        c, s = np.cos(yaw), np.sin(yaw)
        poses[t] = [[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1]]
        x += step_m * np.cos(yaw)
        y += step_m * np.sin(yaw)
        yaw += np.radians(yaw_step_deg)
    return poses


def perturb_extrinsics(
    sensor_to_ego: np.ndarray, rot_deg: float, trans_m: float, rng: np.random.Generator
) -> np.ndarray:
    """Each extrinsic rotated by `rot_deg` about a random axis and moved `trans_m` in a random direction."""
    out = np.array(sensor_to_ego, dtype=np.float64)
    for m in range(out.shape[0]):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        out[m, :3, :3] = rodrigues(axis * np.radians(rot_deg)) @ out[m, :3, :3]
        d = rng.normal(size=3)
        out[m, :3, 3] += d / np.linalg.norm(d) * trans_m
    return out


def _ego(ego_to_world: np.ndarray, t: int, m: int) -> np.ndarray:
    """Ego pose of frame t at camera m's capture ((T, 4, 4) synchronous, or (T, M, 4, 4))."""
    return ego_to_world[t] if ego_to_world.ndim == 3 else ego_to_world[t, m]


def simulate_observations(
    cameras: list[Camera],
    pairs: list[tuple[int, int]],
    ego_to_world: np.ndarray,
    per_view_pair: int = 30,
    noise_px: float = 0.5,
    depth_range_m: tuple[float, float] = (4.0, 40.0),
    rng: np.random.Generator | None = None,
    two_view: bool = False,
) -> tuple[Observations, np.ndarray, np.ndarray]:
    """Observations of random points in the overlaps of adjacent pairs, like merged match tracks.

    For every pair (a, b) and frame t, `per_view_pair * T` points are sampled in camera a's image at
    frame t (random depth) and kept when camera b sees them in some frame; each point is observed by
    cameras a and b in every frame that sees it (a track), or, with `two_view`, only by a at t and b
    at one frame. Pixels get Gaussian noise. Returns the observations, the true world points and the
    pair index of each point.
    """
    rng = rng or np.random.default_rng(0)
    T = ego_to_world.shape[0]
    cams, frames, points, rays, world_pts, pair_of = [], [], [], [], [], []
    n_pts = 0
    for p, (a, b) in enumerate(pairs):
        ca = cameras[a]
        for t in range(T):
            n_try = per_view_pair * T * 20
            uv = rng.uniform([0, 0], [ca.width - 1, ca.height - 1], size=(n_try, 2))
            depth = rng.uniform(*depth_range_m, size=n_try)
            pa, ok = ca.intrinsics.points_from_depth(uv, depth)
            A = _ego(ego_to_world, t, a) @ ca.sensor_to_ego
            world = pa @ A[:3, :3].T + A[:3, 3]
            seen = {}
            for m in (a, b):
                cm = cameras[m]
                for t2 in range(T):
                    V = _ego(ego_to_world, t2, m) @ cm.sensor_to_ego
                    uvv, okv = cm.intrinsics.project((world - V[:3, 3]) @ V[:3, :3])
                    seen[(m, t2)] = (uvv, okv & ok)
            in_b = np.any([seen[(b, t2)][1] for t2 in range(T)], axis=0)
            keep = np.flatnonzero(in_b & ok)[: per_view_pair * T]
            if keep.size == 0:
                continue
            ids = np.arange(n_pts, n_pts + keep.size)
            n_pts += keep.size
            world_pts.append(world[keep])
            pair_of.append(np.full(keep.size, p))
            if two_view:
                first_b = np.argmax(np.stack([seen[(b, t2)][1][keep] for t2 in range(T)]), axis=0)
                views = [(a, np.full(keep.size, t), np.ones(keep.size, bool))]
                views.append((b, first_b, np.ones(keep.size, bool)))
            else:
                views = [(m, np.full(keep.size, t2), seen[(m, t2)][1][keep]) for m in (a, b) for t2 in range(T)]
            for m, tt, vis in views:
                cm = cameras[m]
                uvv = np.stack([seen[(m, int(x))][0][k] for k, x in zip(keep, tt)]) if two_view else \
                    seen[(m, int(tt[0]))][0][keep]
                noisy = uvv + rng.normal(scale=noise_px, size=uvv.shape)
                r, okr = cm.intrinsics.unproject(noisy)
                sel = vis & okr
                cams.append(np.full(int(sel.sum()), m))
                frames.append(tt[sel])
                points.append(ids[sel])
                rays.append(r[sel])
    obs = Observations(
        camera=np.concatenate(cams).astype(np.int64),
        frame=np.concatenate(frames).astype(np.int64),
        point=np.concatenate(points).astype(np.int64),
        ray=np.concatenate(rays),
    )
    return obs, np.concatenate(world_pts), np.concatenate(pair_of)


def noise_texture(size: int = 1024, seed: int = 0) -> np.ndarray:
    """A grey uint8 texture of blurred noise over several scales (rich in SIFT blobs, not periodic)."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size), np.float32)
    for sigma, weight in ((1.5, 0.6), (3.0, 1.0), (6.0, 1.0), (12.0, 0.8)):
        layer = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
        tex += weight * layer / max(float(layer.std()), 1e-6)
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(128 + 45 * tex, 0, 255).astype(np.uint8)


def render_box_world(
    camera: Camera,
    ego_to_world: np.ndarray,
    textures: list[np.ndarray],
    half_width_m: float = 6.0,
    half_length_m: float = 60.0,
    height_m: float = 8.0,
    texels_per_m: float = 40.0,
) -> np.ndarray:
    """RGB image of a textured box (two side walls, two end walls, ground, ceiling) seen by a camera.

    A fast stand-in for the synthetic street for calibration tests: every ray hits a textured plane,
    each plane maps its own texture (from `textures`, cycled) by its two in-plane world coordinates.
    """
    with torch_threads(1):
        rays, valid = camera.intrinsics.ray_grid()
    rays, valid = rays.numpy(), valid.numpy()
    pose = ego_to_world @ camera.sensor_to_ego
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    # planes: (axis, value, in-plane axes)
    planes = [(1, half_width_m, (0, 2)), (1, -half_width_m, (0, 2)), (0, half_length_m, (1, 2)),
              (0, -half_length_m, (1, 2)), (2, 0.0, (0, 1)), (2, height_m, (0, 1))]
    best_t = np.full(d.shape[:2], np.inf)
    best_k = np.full(d.shape[:2], -1)
    for k, (ax, val, _) in enumerate(planes):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (val - o[ax]) / d[..., ax]
        hit = (t > 1e-6) & (t < best_t)
        best_t = np.where(hit, t, best_t)
        best_k = np.where(hit, k, best_k)
    pts = o + d * best_t[..., None]
    out = np.zeros(d.shape[:2], np.uint8)
    for k, (_, _, (i, j)) in enumerate(planes):
        m = best_k == k
        if not m.any():
            continue
        tex = textures[k % len(textures)]
        n = tex.shape[0]
        u = (pts[..., i] * texels_per_m) % n
        v = (pts[..., j] * texels_per_m) % n
        sample = cv2.remap(tex, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_WRAP)
        out[m] = sample[m]
    out[~valid] = 0
    return np.repeat(out[..., None], 3, axis=2)


def box_world_rig(
    n_cameras: int = 6,
    n_frames: int = 3,
    width: int = 320,
    height: int = 180,
    hfov_deg: float = 80.0,
    noise_deg: float = 1.0,
    noise_m: float = 0.05,
    step_m: float = 1.0,
    seed: int = 0,
) -> tuple[Rig, Rig, dict[str, dict[str, np.ndarray]]]:
    """A ring of pinholes driving through the textured box: (true rig, perturbed rig, images[frame][camera]).

    The perturbed rig tags itself like a synthetic preset (extra["synth"]), so beta is BETA_SYNTH.
    """
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    cams = []
    for m in range(n_cameras):
        yaw = -2 * np.pi * m / n_cameras
        pos = np.array([0.9 * np.cos(yaw) + 0.8, 0.7 * np.sin(yaw), 1.5])
        cams.append(Camera(f"C{m}", Pinhole(width, height, K), camera_mount(yaw, pos)))
    ego = straight_drive(n_frames, step_m, 1.0)
    frames = tuple(Frame(f"{t:06d}", t * 100_000, ego[t]) for t in range(n_frames))
    ring = tuple(c.name for c in cams)
    rig_true = Rig(tuple(cams), ring_pairs(ring), frames, ring, extra={"synth": {"preset": "box", "seed": seed}})
    noisy = perturb_extrinsics(np.stack([c.sensor_to_ego for c in cams]), noise_deg, noise_m,
                               np.random.default_rng(seed))
    rig = rig_true.with_extrinsics({c.name: noisy[i] for i, c in enumerate(cams)})
    textures = [noise_texture(1024, seed * 10 + k) for k in range(6)]
    images = {fr.id: {c.name: render_box_world(c, fr.ego_to_world, textures) for c in cams} for fr in frames}
    return rig_true, rig, images
