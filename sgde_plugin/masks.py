"""Static (ego-body) masks estimated from a sequence: the parts of an image that do not move while the scene does.

The car's own body (hood, side panels, trunk, mirrors) sits still in a camera's image while the
street flows past. Its reflections move, so a per-pixel "did not change" test alone fails on a
glossy body; what stays put is its outline. Two estimators:

- With the rig's poses (`rig_ground_maps`: capture poses and extrinsics, the car moving), every textured
  patch of the first frame votes "still" (the later frames show it unmoved) or "ground" (they show it moved
  as the road plane, ego z = 0, would move it), and `body_below_outline` finds, column by column, the outline
  the body hangs below: still votes under it, no road motion just under it, running on static edges. Road
  strips between lane lines (static-looking when driving straight) get ground votes and stay scene.
- Images only: the regions the static structure cuts out (edges with the same orientation at the same
  pixel in every frame, closed over small gaps) that touch the border, lie mostly in the lower half (the sky
  is the other still region), have a mostly static outline and change clearly less than the scene.

Anything that rides with the car (a trailer, a vehicle driving at the ego's speed during the frames) is
static too and is masked with the first estimator.
The mask follows the rig convention: True / 255 = use the pixel, False / 0 = ignore (body).
Three frames suffice when the car moves between them; more frames make the votes and static edges cleaner.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera
from .errors import InputError
from .geometry import invert_transform, transform_points
from .rig import Rig, check_image_file

WORK_WIDTH = 384  # estimation runs at about this width; the mask is scaled back up


@dataclass(frozen=True)
class MaskSettings:
    """Thresholds of the static-mask estimator (grey levels of a 0-255 image, fractions of the image)."""

    min_cos: float = 0.95  # an edge is static when its direction agrees (cosine) between every two frames
    min_gradient: float = 4.0  # ... and it is this strong (grey levels per pixel) in every frame
    min_area: float = 0.005  # smallest body region, share of the image
    max_area: float = 0.5  # largest (a larger static region means the car did not move)
    min_outline: float = 0.5  # share of a region's inner boundary on static edges
    max_change_ratio: float = 0.8  # region's median change / the whole image's median change
    close_px: int = 5  # static edges are closed over gaps this wide (working pixels)
    grow_px: int = 2  # the final mask grows by this much (working pixels) over the body's edge
    vote_margin: float = 3.0  # grey levels by which one motion model must explain a patch better to vote
    min_contrast: float = 4.0  # patches flatter than this (mean absolute deviation, grey levels) do not vote
    still_ratio: float = 0.5  # "still" needs the frames' difference under this share of the patch's contrast
    max_ground_m: float = 40.0  # the ground model is used up to this distance from the camera
    edge_gain: float = 6.0  # outline search: reward (in votes) for running on a static edge
    step_cost: float = 3.0  # ... cost per row the outline moves between neighbouring columns
    pixel_cost: float = 0.05  # ... cost per body pixel, so that no votes means no body
    band_px: int = 4  # ... "ground" votes count against the body only this far below its outline


def work_size(width: int, height: int) -> tuple[int, int]:
    """(w, h) of the working images the estimator uses for a camera of this size."""
    scale = min(1.0, WORK_WIDTH / width)
    return max(8, round(width * scale)), max(8, round(height * scale))


def ground_map(camera: Camera, first_cam_to_world: np.ndarray, other_cam_to_world: np.ndarray,
               ground_to_world: np.ndarray, max_range_m: float) -> np.ndarray:
    """Float32 (h, w, 2) at work size: where each first-frame pixel's ground point (z = 0 of `ground_to_world`)
    appears in the other frame; NaN above the horizon, beyond `max_range_m`, or outside the other image."""
    small = camera.resized(*work_size(camera.width, camera.height))
    rays, ok = small.intrinsics.ray_grid()
    rays, ok = rays.numpy(), ok.numpy()
    to_ground = invert_transform(ground_to_world) @ first_cam_to_world
    d = rays @ to_ground[:3, :3].T
    o = to_ground[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[2] / d[..., 2]
    ok &= np.isfinite(s) & (s > 0) & (s < max_range_m)
    points = o + d * np.where(ok, s, 0.0)[..., None]
    to_other = invert_transform(other_cam_to_world) @ ground_to_world
    uv, seen = small.intrinsics.project(transform_points(to_other, points.reshape(-1, 3)).reshape(points.shape))
    w, h = small.width, small.height
    ok &= seen & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    return np.where(ok[..., None], uv, np.nan).astype(np.float32)


def motion_votes(greys: Sequence[np.ndarray], maps: Sequence[np.ndarray], margin: float,
                 min_contrast: float, still_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Bool (still, ground) over the first frame's textured 7x7 patches: "still" when the later frames show
    the patch unmoved (mean absolute difference under `still_ratio` of its contrast, and the ground motion
    worse by `margin` grey levels), "ground" when they show it moved as the ground plane would move it."""
    g0 = greys[0]
    box = (7, 7)
    e_still = np.zeros_like(g0)
    e_ground = np.zeros_like(g0)
    seen = np.zeros_like(g0)
    for g, m in zip(greys[1:], maps):
        valid = cv2.erode(np.isfinite(m[..., 0]).astype(np.uint8), np.ones(box, np.uint8)) > 0
        mx = np.where(np.isfinite(m[..., 0]), m[..., 0], -1).astype(np.float32)
        my = np.where(np.isfinite(m[..., 1]), m[..., 1], -1).astype(np.float32)
        warped = cv2.remap(g, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        e_still += np.where(valid, cv2.boxFilter(np.abs(g0 - g), -1, box), 0)
        e_ground += np.where(valid, cv2.boxFilter(np.abs(g0 - warped), -1, box), 0)
        seen += valid
    n = np.maximum(seen, 1)
    e_still /= n
    e_ground /= n
    contrast = cv2.boxFilter(np.abs(g0 - cv2.boxFilter(g0, -1, box)), -1, box)
    vote = (seen > 0) & (contrast > min_contrast)
    still = vote & (e_still < still_ratio * contrast) & (e_ground > e_still + margin)
    return still, vote & (e_still > e_ground + margin)


def _reach_with_steps(values: np.ndarray, cost: float) -> tuple[np.ndarray, np.ndarray]:
    """max over y' of values[y'] - cost * |y - y'| for every y, and the y' that gives it (1-D L1 transform)."""
    rows = np.arange(values.size)
    up = values + cost * rows  # from y' <= y
    run_up = np.maximum.accumulate(up)
    arg_up = np.maximum.accumulate(np.where(up >= run_up, rows, 0))
    down = values - cost * rows  # from y' >= y
    run_down = np.maximum.accumulate(down[::-1])[::-1]
    arg_down = np.minimum.accumulate(np.where(down >= run_down, rows, values.size)[::-1])[::-1]
    from_up = run_up - cost * rows >= run_down + cost * rows
    best = np.where(from_up, run_up - cost * rows, run_down + cost * rows)
    return best, np.where(from_up, arg_up, arg_down)


def body_below_outline(still: np.ndarray, ground: np.ndarray, edges: np.ndarray, edge_gain: float,
                       step_cost: float, pixel_cost: float, band: int) -> np.ndarray:
    """Bool body mask hanging from the bottom edge below one outline row per column (none: the image height).

    The outline maximises, over all columns, the "still" votes below it, minus twice the "ground" votes in
    the `band` rows just below it (the body's own reflections may move like the road further down), plus
    `edge_gain` where it runs on a static edge, minus `pixel_cost` per body pixel (no votes, no body; a
    static edge alone draws a body only within `edge_gain / pixel_cost` rows of the bottom), and
    `step_cost` per row it moves between neighbouring columns (dynamic programming over the columns).
    """
    h, w = still.shape
    still_below = np.cumsum(still[::-1].astype(np.float32), axis=0)[::-1]
    ground_below = np.vstack([np.cumsum(ground[::-1].astype(np.float32), axis=0)[::-1], np.zeros((band, w))])
    gain = np.zeros((h + 1, w), np.float32)
    gain[:h] = still_below - 2 * (ground_below[:h] - ground_below[band:band + h]) + edge_gain * edges
    gain[:h] -= pixel_cost * (h - np.arange(h))[:, None]
    total = gain[:, 0].astype(np.float64)
    back = np.zeros((h + 1, w), np.int64)
    for x in range(1, w):
        best, back[:, x] = _reach_with_steps(total, step_cost)
        total = best + gain[:, x]
    top = np.empty(w, np.int64)
    top[-1] = int(total.argmax())
    for x in range(w - 1, 0, -1):
        top[x - 1] = back[top[x], x]
    return np.arange(h)[:, None] >= top[None, :]


def _grey_small(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    small = cv2.resize(grey, work_size(grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(small.astype(np.float32), (0, 0), 1.0)


def static_structure(greys: Sequence[np.ndarray], min_cos: float, min_gradient: float) -> np.ndarray:
    """Bool: edges that are there, with the same orientation, at the same pixel in every frame.

    The body's outline keeps its place and direction while the scene's edges move on; a random
    texture rarely agrees in orientation at one pixel over several frames, flat areas never count.
    """
    grads = []
    for g in greys:
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0) / 4
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1) / 4
        grads.append((gx, gy, np.hypot(gx, gy)))
    out = np.ones(greys[0].shape, bool)
    for _, _, m in grads:
        out &= m > min_gradient
    for i in range(len(grads)):
        for j in range(i + 1, len(grads)):
            xi, yi, mi = grads[i]
            xj, yj, mj = grads[j]
            out &= (xi * xj + yi * yj) > min_cos * mi * mj
    return out


def temporal_change(greys: Sequence[np.ndarray]) -> np.ndarray:
    """Per-pixel median over frame pairs of the absolute grey difference."""
    diffs = [np.abs(greys[i] - greys[j]) for i in range(len(greys)) for j in range(i + 1, len(greys))]
    return np.median(np.stack(diffs), axis=0)


def _region_candidates(edges: np.ndarray, walls: np.ndarray, s: MaskSettings) -> list[np.ndarray]:
    """Regions the closed static structure cuts out that could be the body (border, lower half, size, outline)."""
    sh, sw = walls.shape
    n, labels, stats, centroids = cv2.connectedComponentsWithStats((~walls).astype(np.uint8), connectivity=4)
    border = np.zeros((sh, sw), bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    ring = np.ones((5, 5), np.uint8)
    candidates = []
    for i in range(1, n):
        if not s.min_area * sh * sw <= stats[i, cv2.CC_STAT_AREA] <= s.max_area * sh * sw:
            continue
        region = labels == i
        if not (region & border).any() or centroids[i][1] < sh / 2:  # the sky is the other still region
            continue
        outline = (cv2.dilate(region.astype(np.uint8), ring) > 0) & ~region & ~border
        if not outline.any():  # the region is the whole image: nothing is static
            continue
        if float((edges | walls)[outline].mean()) >= s.min_outline:
            candidates.append(region)
    return candidates


def _changed_little(region: np.ndarray, change: np.ndarray, scene_change: float, s: MaskSettings) -> bool:
    """A candidate region is body when it changed over time clearly less than the scene."""
    return float(np.median(change[region])) <= s.max_change_ratio * max(scene_change, 1e-3)


def estimate_static_mask(images: Sequence[np.ndarray], settings: MaskSettings | None = None,
                         ground_maps: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Bool (H, W) of the first image's size: True = scene (use), False = static body (ignore).

    `images`: two or more frames of one camera (uint8 RGB or grey), taken while the car moves.
    `ground_maps`: optional, one `ground_map` per later frame. With them textured patches vote between
    "did not move" and "moved as the road would": the votes decide the regions, and an outline found by
    `body_below_outline` adds the body parts no closed static structure cuts out.
    """
    s = settings or MaskSettings()
    if len(images) < 2:
        raise ValueError("a static mask needs at least two frames")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("all frames of a camera must have the same size")
    greys = [_grey_small(im) for im in images]
    edges = static_structure(greys, s.min_cos, s.min_gradient)
    change = temporal_change(greys)
    kc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * s.close_px + 1, 2 * s.close_px + 1))
    walls = cv2.morphologyEx(edges.astype(np.uint8), cv2.MORPH_CLOSE, kc) > 0
    body = np.zeros(walls.shape, bool)
    if ground_maps is not None:
        votes = motion_votes(greys, ground_maps, s.vote_margin, s.min_contrast, s.still_ratio)
        near_edge = cv2.dilate(edges.astype(np.uint8), np.ones((3, 1), np.uint8)) > 0
        body = body_below_outline(*votes, near_edge, s.edge_gain, s.step_cost, s.pixel_cost, s.band_px)
    else:
        scene_change = float(np.median(change[~walls])) if (~walls).any() else 0.0
        for region in _region_candidates(edges, walls, s):
            if _changed_little(region, change, scene_change, s):
                body |= region
    if body.any() and ground_maps is None:  # the outline (the static structure along it) belongs to the body
        reach = s.close_px + 2
        kr = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
        body |= (cv2.dilate(body.astype(np.uint8), kr) > 0) & walls
    if body.any():
        kg = np.ones((2 * s.grow_px + 1, 2 * s.grow_px + 1), np.uint8)
        body = cv2.dilate(body.astype(np.uint8), kg) > 0
    full = cv2.resize(body.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    return ~full


def rig_ground_maps(rig: Rig, camera: str, frame_ids: Sequence[str], max_range_m: float,
                    min_motion_m: float = 0.3) -> list[np.ndarray] | None:
    """`ground_map`s from the first listed frame to each later one for one camera of the rig, from its capture
    poses; None when the car moved less than `min_motion_m` over the frames (then the road stands still too)."""
    cam = rig.camera(camera)
    frames = {f.id: f for f in rig.frames}
    poses = [frames[i].capture_ego_to_world(camera) for i in frame_ids]
    if max(float(np.linalg.norm(p[:3, 3] - poses[0][:3, 3])) for p in poses) < min_motion_m:
        return None
    first = poses[0] @ cam.sensor_to_ego
    return [ground_map(cam, first, p @ cam.sensor_to_ego, poses[0], max_range_m) for p in poses[1:]]


def spread_frames(n_frames: int, count: int) -> list[int]:
    """Up to `count` frame indices spread evenly over a sequence of `n_frames` (first and last included)."""
    if n_frames <= count:
        return list(range(n_frames))
    return sorted({round(i * (n_frames - 1) / (count - 1)) for i in range(count)})


def attach_masks(rig: Rig, folder: str | Path) -> Rig:
    """The rig with `folder/<camera>.png` as static masks for every camera that has no mask of its own.

    Masks already on the rig (the user's, from the rig folder's masks/) take precedence.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, None, "mask folder not found")
    found = {c: folder / f"{c}.png" for c in rig.camera_names if (folder / f"{c}.png").is_file()}
    for camera, path in found.items():
        check_image_file(path, rig.camera(camera))  # a mask of another size would be read at the wrong pixels
    return replace(rig, masks={**found, **dict(rig.masks)})
