"""Plane-sweep matching between the original views of an adjacent pair (`matcher: planesweep`; no rectification).

Each camera of a pair is resampled once into its own undistorted pinhole at the matching scale, the
"view": the camera's rotation and optical centre, its focal length times `scale` (a fisheye goes through
the virtual pinhole half that faces its neighbour). With one view as the reference, the depth hypotheses
are planes fronto-parallel to it, uniform in inverse depth over [min_depth, max_depth]; for each plane the
neighbour's view is warped onto the reference by the plane's homography and compared with the reference by
windowed ZNCC (gain and offset do not matter). For the true plane the two windows are compared under the
same foreshortening, which the rectified canvases of cameras 50-70 degrees apart do not give. Costs are
optionally aggregated semi-globally along image rows and columns, the best plane is refined by a parabola,
and the two references are checked against each other (the reference swap plays the left-right check).

The result is a "disparity" f B / z over the reference view (f its focal length, B the baseline, z the
view's depth), so the rectified path's back-projection (`backproject.backprojection`, the view standing
for the rectified camera) turns it into depth in the original camera, and fusion, cache and evaluation
take it unchanged. All geometry (views, warp maps, homographies, backward maps) is computed once per rig.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..pairs import left_right
from ..rig import Rig
from .backproject import BackProjection, backprojection, camera_rays
from .checks import match_box
from .config import PriorConfig
from .filters import (
    discontinuity_factor,
    grey_float,
    masked_median,
    normalize_image,
    remove_islands,
    window_scores,
)
from .planning import facing_half, ground_disparity, shared_warp_maps
from .rectify import WarpMaps, torch_threads

MIN_PLANES = 16
_INVALID = 2.0  # cost of a plane whose warped window leaves the neighbour's view (ZNCC -1 costs 2 as well)
_FLAT = 1.0  # cost where the neighbour's warped window has no texture (ZNCC undefined)
_MIN_STD = 2.0  # grey levels: windows flatter than this have no ZNCC


@dataclass(frozen=True, eq=False)
class SweepSide:
    """One camera of a swept pair: its view, and everything its reference sweep needs."""

    camera: str  # original camera name
    view: Camera  # undistorted pinhole at the matching scale, same optical centre as the camera
    warp: WarpMaps  # original image -> view
    back: BackProjection  # original camera -> view; "disparity" f B / z of the view
    crop: tuple[slice, slice]  # rows, columns of the view that can see the other view (plus a window)
    homographies: np.ndarray  # (N, 3, 3): crop pixel -> pixel of the other view, one per plane
    reach: np.ndarray  # bool crop: pixels that see the other view on some plane
    min_disparity: np.ndarray | None  # float32 crop: the ground rule's smallest f B / z; None = off

    def warp_image(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Original image -> view."""
        return self.warp.warp(image, interpolation)


@dataclass(frozen=True, eq=False)
class SweepPlan:
    """Everything precomputed for one adjacent pair matched by the plane sweep."""

    left: SweepSide
    right: SweepSide
    baseline_m: float
    inv_depths: np.ndarray  # (N,) float64, ascending: plane k is at depth 1 / inv_depths[k] in the reference view
    to_right: np.ndarray  # 4x4: left view coordinates -> right view coordinates

    @property
    def cost(self) -> float:
        """Work of one frame (crop pixels x planes), for scheduling."""
        area = sum((s.crop[0].stop - s.crop[0].start) * (s.crop[1].stop - s.crop[1].start) for s in (self.left,
                                                                                                      self.right))
        return float(area * len(self.inv_depths))

    @property
    def name(self) -> str:
        """`left|right`."""
        return f"{self.left.camera}|{self.right.camera}"

    @property
    def focal_baseline(self) -> float:
        """f B (px m) of the "disparities" f B / z: the two views' mean focal length times the baseline."""
        return float(0.5 * (self.left.view.intrinsics.K[0, 0] + self.right.view.intrinsics.K[0, 0]) * self.baseline_m)


def sweep_view(camera: Camera, other: Camera, scale: float) -> Camera:
    """The undistorted pinhole a camera is matched in: its own K (pinhole) or its half facing `other` (fisheye)."""
    if camera.intrinsics.depth_is_range:
        return facing_half(camera, other, scale)
    model = camera.intrinsics
    w, h = max(2, round(camera.width * scale)), max(2, round(camera.height * scale))
    K = model.resized(w, h).K
    return Camera(f"{camera.name}#sweep", Pinhole(w, h, K, None), camera.sensor_to_ego.copy())


def plane_homographies(own: Camera, other: Camera, inv_depths: np.ndarray, offset: tuple[int, int]) -> np.ndarray:
    """(N, 3, 3): pixel (x + offset) of `own` -> pixel of `other` through the plane z = 1 / inv_depth of `own`.

    With X_o = R X + t and the plane e3 . X = d: H = K_o (R + t e3^T / d) K^-1 (both pinholes)."""
    T = np.linalg.inv(other.sensor_to_ego) @ own.sensor_to_ego
    R, t = T[:3, :3], T[:3, 3]
    K_inv = np.linalg.inv(own.intrinsics.K)
    shift = np.array([[1.0, 0, offset[0]], [0, 1.0, offset[1]], [0, 0, 1.0]])
    Ko = other.intrinsics.K
    e3 = np.array([0.0, 0.0, 1.0])
    return np.stack([Ko @ (R + np.outer(t, e3) * q) @ K_inv @ shift for q in inv_depths])


def nearest_shared_inverse_depth(views: tuple[Camera, Camera], valid: tuple[np.ndarray, np.ndarray], q_far: float,
                                 q_near: float, samples: int = 64, stride: int = 8) -> float | None:
    """The largest inverse depth in [q_far, q_near] at which a plane of either view is still seen by the other
    (pixels sampled every `stride` px, `samples` planes; one sample step of margin), None if never.

    Nearer than that no point can be matched: the rectified path's search range is cut the same way."""
    qs = np.linspace(q_far, q_near, samples)
    seen = np.zeros(samples, bool)
    for k in (0, 1):
        own, other = views[k], views[1 - k]
        rows, cols = np.nonzero(valid[k][::stride, ::stride])
        if rows.size == 0:
            continue
        pts = np.stack([cols * stride, rows * stride, np.ones_like(rows)]).astype(np.float64)
        uvw = plane_homographies(own, other, qs, (0, 0)) @ pts  # (samples, 3, P)
        w = uvw[:, 2]
        front = w > 1e-9
        u = np.rint(uvw[:, 0] / np.where(front, w, 1.0))
        v = np.rint(uvw[:, 1] / np.where(front, w, 1.0))
        inside = front & (u >= 0) & (u < other.width) & (v >= 0) & (v < other.height)
        ui, vi = np.where(inside, u, 0).astype(np.intp), np.where(inside, v, 0).astype(np.intp)
        seen |= (inside & valid[1 - k][vi, ui]).any(axis=1)
    if not seen.any():
        return None
    last = int(np.flatnonzero(seen)[-1])
    return float(qs[min(last + 1, samples - 1)])


def sweep_inverse_depths(views: tuple[Camera, Camera], baseline_m: float, config: PriorConfig,
                         q_near: float | None = None) -> np.ndarray:
    """Plane inverse depths, uniform from 1/max_depth to `q_near` (default 1/min_depth): one plane per
    `step_px` of parallax (f B x the inverse-depth step, f the larger focal length), at most `planes`."""
    g = config.geometry
    q_far, q_near = 1.0 / g.max_depth, 1.0 / g.min_depth if q_near is None else q_near
    f = max(float(v.intrinsics.K[0, 0]) for v in views)
    parallax = f * baseline_m * (q_near - q_far)
    n = int(min(config.sweep.planes, max(MIN_PLANES, math.ceil(parallax / config.sweep.step_px) + 1)))
    return np.linspace(q_far, q_near, n)


def _reach(own: Camera, other: Camera, other_valid: np.ndarray, own_valid: np.ndarray,
           inv_depths: np.ndarray) -> np.ndarray:
    """Bool view mask: pixels of `own` whose ray lands in `other`'s view on some plane (8 planes sampled + ends)."""
    picks = np.unique(np.linspace(0, len(inv_depths) - 1, 9).round().astype(int))
    reach = np.zeros(own_valid.shape, np.uint8)
    src = other_valid.astype(np.uint8)
    for H in plane_homographies(own, other, inv_depths[picks], (0, 0)):
        reach |= cv2.warpPerspective(src, H, (own.width, own.height), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    # planes between the samples move the footprint by at most the sampling step: close the gaps
    reach = cv2.dilate(reach, np.ones((9, 9), np.uint8)) > 0
    return reach & own_valid


def plan_sweeps(rig: Rig, config: PriorConfig, shared: dict | None = None) -> list[SweepPlan]:
    """Views, warp maps, homographies and backward maps of every pair of `rig` that the sweep can match;
    `shared` as in `planning.plan_pairs` (the cameras' ray grids, kept for planning the moved rig again)."""
    with torch_threads(1):
        plans = []
        shared = {} if shared is None else shared
        for a, b in rig.pairs:
            plan = _plan_sweep(*left_right(rig.camera(a), rig.camera(b)), config, shared)
            if plan is not None:
                plans.append(plan)
        return plans


def _plan_sweep(left: Camera, right: Camera, config: PriorConfig, shared: dict) -> SweepPlan | None:
    """One pair's `SweepPlan` (None when the cameras share a centre or their views never meet)."""
    baseline = float(np.linalg.norm(right.sensor_to_ego[:3, 3] - left.sensor_to_ego[:3, 3]))
    if baseline < 1e-6:
        return None
    scale = config.geometry.scale
    views = (sweep_view(left, right, scale), sweep_view(right, left, scale))
    warps = tuple(shared_warp_maps(cam, view, shared) for cam, view in zip((left, right), views))
    g = config.geometry
    q_near = nearest_shared_inverse_depth(views, (warps[0].valid, warps[1].valid), 1 / g.max_depth, 1 / g.min_depth)
    if q_near is None:
        return None
    inv = sweep_inverse_depths(views, baseline, config, q_near)
    grow = config.sweep.window // 2 + 2
    ratio = config.filters.ground_depth_ratio
    sides = []
    for k, cam in enumerate((left, right)):
        own, other = views[k], views[1 - k]
        reach = _reach(own, other, warps[1 - k].valid, warps[k].valid, inv)
        box = match_box(reach, halo=grow)
        if box is None:
            return None
        back = backprojection(cam, own, baseline, (0, own.width), *camera_rays(cam, shared), possible=reach)
        floor = ground_disparity(own, baseline, (0, own.width), ratio) if ratio > 0 else None
        sides.append(SweepSide(
            camera=cam.name, view=own, warp=warps[k], back=back, crop=box,
            homographies=plane_homographies(own, other, inv, (box[1].start, box[0].start)),
            reach=reach[box], min_disparity=None if floor is None else floor[box],
        ))
    to_right = np.linalg.inv(views[1].sensor_to_ego) @ views[0].sensor_to_ego
    return SweepPlan(sides[0], sides[1], baseline, inv, to_right)


def _view_image(side: SweepSide, image: np.ndarray, mask: np.ndarray | None, config: PriorConfig
                ) -> tuple[np.ndarray, np.ndarray]:
    """(float32 grey view image centred on 0 and 0 where unseen, bool valid) of one side for one frame."""
    view = side.warp_image(image)
    valid = side.warp.valid
    if mask is not None:
        valid = valid & (side.warp_image(mask.astype(np.uint8), cv2.INTER_NEAREST) > 0)
    if config.images.normalize != "none":
        view = normalize_image(view, valid, config.images.normalize, config.images.normalize_sigma)
    grey = grey_float(view) - 128.0
    grey[~valid] = 0.0
    return grey, valid


def cost_volume(ref: np.ndarray, other: np.ndarray, other_valid: np.ndarray, side: SweepSide, window: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """(costs (N, h, w) float32 = 1 - ZNCC of the crop against the warped neighbour per plane, the crop's
    window variance). A window that leaves the neighbour's view costs 2, a flat neighbour window 1."""
    rows, cols = side.crop
    a = np.ascontiguousarray(ref[rows, cols])
    h, w = a.shape
    box = (window, window)
    ma = cv2.blur(a, box)
    va = cv2.blur(a * a, box) - ma * ma
    src = np.ascontiguousarray(np.dstack([other, other_valid.astype(np.float32)]))
    out = np.empty((len(side.homographies), h, w), np.float32)
    stack = np.empty((h, w, 4), np.float32)
    for k, H in enumerate(side.homographies):
        warped = cv2.warpPerspective(src, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        b = warped[..., 0]
        stack[..., 0] = b
        stack[..., 1] = b * b
        stack[..., 2] = a * b
        stack[..., 3] = warped[..., 1] > 0.999
        s = cv2.blur(stack, box)
        mb = s[..., 0]
        vb = s[..., 1] - mb * mb
        zncc = (s[..., 2] - ma * mb) / np.sqrt(np.maximum(va * vb, 1e-6))
        cost = out[k]
        np.subtract(1.0, zncc, out=cost)
        cost[vb < _MIN_STD**2] = _FLAT
        cost[s[..., 3] < 0.999] = _INVALID
    return out, va


def _scan(costs: np.ndarray, total: np.ndarray, axis: int, reverse: bool, p1: float, p2: float) -> None:
    """One semi-global path along image `axis` (1 rows' direction = down, 2 = right), added to `total`."""
    n = costs.shape[axis]
    prev = None
    for i in (range(n - 1, -1, -1) if reverse else range(n)):
        c = costs[:, i] if axis == 1 else costs[:, :, i]
        if prev is None:
            cur = c.copy()
        else:
            low = prev.min(axis=0)
            best = np.minimum(prev, low + p2)
            np.minimum(best[1:], prev[:-1] + p1, out=best[1:])
            np.minimum(best[:-1], prev[1:] + p1, out=best[:-1])
            cur = c + best - low
        if axis == 1:
            total[:, i] += cur
        else:
            total[:, :, i] += cur
        prev = cur


def aggregate(costs: np.ndarray, paths: int, p1: float, p2: float) -> np.ndarray:
    """Semi-global aggregation of (N, h, w) costs along `paths` directions (2: left/right, 4: and up/down);
    0 returns the costs themselves (the ZNCC window is the box aggregation)."""
    if paths == 0:
        return costs
    total = np.zeros_like(costs)
    for axis, reverse in ((2, False), (2, True), (1, False), (1, True))[:paths]:
        _scan(costs, total, axis, reverse, p1, p2)
    return total


def subplane(costs: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Offset in [-0.5, 0.5] of the minimum of the parabola through the costs at planes k - 1, k, k + 1
    (0 at the first and last plane, and where the costs do not curve upwards)."""
    n = costs.shape[0]
    c0 = np.take_along_axis(costs, k[None], 0)[0]
    cm = np.take_along_axis(costs, np.maximum(k - 1, 0)[None], 0)[0]
    cp = np.take_along_axis(costs, np.minimum(k + 1, n - 1)[None], 0)[0]
    denom = cm - 2 * c0 + cp
    inner = (k > 0) & (k < n - 1) & (denom > 1e-6)
    return np.where(inner, 0.5 * (cm - cp) / np.where(inner, denom, 1.0), 0.0).clip(-0.5, 0.5).astype(np.float32)


def winner(total: np.ndarray, uniqueness: float, in_place: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(best plane index, sub-plane offset from a parabola (`subplane`), unique) per pixel.

    Unique: the best cost outside the winner's neighbours is above (1 + uniqueness) x the winner's.
    `in_place`: `total` may be overwritten (saves a copy of the volume)."""
    n = total.shape[0]
    k = total.argmin(axis=0)
    c0 = np.take_along_axis(total, k[None], 0)[0]
    offset = subplane(total, k)
    others = total if in_place else total.copy()
    for d in (-1, 0, 1):
        np.put_along_axis(others, np.clip(k + d, 0, n - 1)[None], np.inf, 0)
    second = others.min(axis=0)
    unique = second > c0 * (1 + uniqueness) + 1e-6 if n > 3 else np.ones(k.shape, bool)
    return k, offset, unique


def depth_maps(plan: SweepPlan, k: int, inv_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (float32 x, y over reference `k`'s crop) of the other view's pixels that the points
    at `inv_depth` (per crop pixel, reference view) project to: H(q) x = A x + q (e3 . K^-1 x) K_o t."""
    own, other = (plan.left, plan.right)[k], (plan.left, plan.right)[1 - k]
    T = np.linalg.inv(other.view.sensor_to_ego) @ own.view.sensor_to_ego
    Ko, K_inv = other.view.intrinsics.K, np.linalg.inv(own.view.intrinsics.K)
    h, w = inv_depth.shape
    rows, cols = own.crop
    ys, xs = np.mgrid[rows.start : rows.start + h, cols.start : cols.start + w]
    rays = K_inv @ np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)])
    p = Ko @ T[:3, :3] @ rays + np.outer(Ko @ T[:3, 3], inv_depth.ravel() * rays[2])
    front = p[2] > 1e-9
    z = np.where(front, p[2], 1.0)
    u, v = np.where(front, p[0] / z, -1e4), np.where(front, p[1] / z, -1e4)  # behind: far outside the image
    return u.reshape(h, w).astype(np.float32), v.reshape(h, w).astype(np.float32)


def _photometric_confidence(plan: SweepPlan, k: int, views: list[tuple[np.ndarray, np.ndarray]],
                            inv_depth: np.ndarray, ok: np.ndarray, config: PriorConfig) -> np.ndarray:
    """The rectified path's photometric confidence (`checks._photometric`) at the refined depth, the other
    view warped pixel by pixel: windowed ZNCC above `min_zncc`, mean absolute difference (after the cameras'
    brightness offset) below `max_abs_diff`, x-texture above `min_texture`."""
    side = (plan.left, plan.right)[k]
    f, window = config.filters, config.sweep.window
    a = np.ascontiguousarray(views[k][0][side.crop])
    map_x, map_y = depth_maps(plan, k, inv_depth)
    warped = cv2.remap(views[1 - k][0], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # the brightness offset, from the matches that pass the ZNCC check (the rectified path takes it from its
    # checked matches; the unchecked pixels of a sweep are mostly wrong and bias it by tens of grey levels)
    ncc, _, _ = window_scores(a, warped, ok, window, _MIN_STD, offset=0.0)  # only the ZNCC is used here
    sure = ok & (ncc > f.min_zncc)
    offset = masked_median(a - warped, sure)
    ncc, mad, texture = window_scores(a, warped, ok, window, _MIN_STD, offset)
    conf = np.clip((ncc - f.min_zncc) / (1 - f.min_zncc), 0, 1) * np.clip(1 - mad / f.max_abs_diff, 0, 1)
    if f.min_texture > 0:  # rows without x-structure are ambiguous
        conf *= np.clip(texture / f.min_texture - 1, 0, 1)
    return conf


@dataclass
class _Reference:
    """One reference's sweep result over its crop: "disparity" f B / z and confidence."""

    disp: np.ndarray
    conf: np.ndarray


def _sweep_reference(plan: SweepPlan, k: int, views: list[tuple[np.ndarray, np.ndarray]], config: PriorConfig
                     ) -> _Reference:
    """Cost volume, aggregation, winner and the per-pixel confidence terms of reference side `k`."""
    side = (plan.left, plan.right)[k]
    sw = config.sweep
    (ref, ref_valid), (other, other_valid) = views[k], views[1 - k]
    costs, va = cost_volume(ref, other, other_valid, side, sw.window)
    total = aggregate(costs, sw.paths, sw.p1, sw.p2)
    k0 = total.argmin(axis=0)
    raw = np.take_along_axis(costs, k0[None], 0)[0]  # before `winner` may overwrite an unaggregated volume
    best, offset, unique = winner(total, sw.uniqueness, in_place=True)
    del costs, total
    inv = plan.inv_depths
    q = inv[0] + (best + offset) * (inv[1] - inv[0])
    disp = (side.view.intrinsics.K[0, 0] * plan.baseline_m * q).astype(np.float32)
    ok = side.reach & ref_valid[side.crop] & unique & (raw < _INVALID) & (best < len(inv) - 1)
    ok &= va >= _MIN_STD**2
    ok &= np.isfinite(disp) & (1.0 - raw > config.filters.min_zncc)  # the winner's own ZNCC passes the check
    conf = _photometric_confidence(plan, k, views, np.where(ok, q, 0.0), ok, config)
    conf *= disp / (disp + config.confidence.disparity_px)  # small disparities give uncertain depth
    if side.min_disparity is not None:
        ok &= disp >= side.min_disparity
    return _Reference(np.where(ok, disp, 0).astype(np.float32), np.where(ok, conf, 0).astype(np.float32))


def _full(side: SweepSide, crop: np.ndarray) -> np.ndarray:
    """A crop map placed in a zero map of the whole view."""
    out = np.zeros((side.view.height, side.view.width), np.float32)
    out[side.crop] = crop
    return out


def swap_check(plan: SweepPlan, k: int, refs: list[_Reference], max_diff: float) -> np.ndarray:
    """Confidence of reference `k` after the reference-swap check: its point, seen from the other view, must
    have the depth the other reference found there within `max_diff` px of disparity (f B / z of the other
    view); the confidence falls off as a Gaussian of the disagreement, as the rectified left-right check."""
    own, other = (plan.left, plan.right)[k], (plan.left, plan.right)[1 - k]
    ref = refs[k]
    T = plan.to_right if k == 0 else np.linalg.inv(plan.to_right)
    rr, cc = np.nonzero(ref.conf > 0)
    out = np.zeros_like(ref.conf)
    if rr.size == 0:
        return out
    fb_own = own.view.intrinsics.K[0, 0] * plan.baseline_m
    z = fb_own / ref.disp[rr, cc]
    pix = np.stack([cc + own.crop[1].start, rr + own.crop[0].start, np.ones_like(rr)]).astype(np.float64)
    X = (np.linalg.inv(own.view.intrinsics.K) @ pix) * z
    Xo = T[:3, :3] @ X + T[:3, 3:4]
    Ko = other.view.intrinsics.K
    front = Xo[2] > 1e-6
    zo = np.where(front, Xo[2], 1.0)
    u = np.rint(Ko[0, 0] * Xo[0] / zo + Ko[0, 2]).astype(np.intp)
    v = np.rint(Ko[1, 1] * Xo[1] / zo + Ko[1, 2]).astype(np.intp)
    disp_o, conf_o = _full(other, refs[1 - k].disp), _full(other, refs[1 - k].conf)
    inside = front & (u >= 0) & (u < other.view.width) & (v >= 0) & (v < other.view.height)
    u, v = np.where(inside, u, 0), np.where(inside, v, 0)
    predicted = Ko[0, 0] * plan.baseline_m / zo
    diff = np.abs(predicted - disp_o[v, u])
    ok = inside & (conf_o[v, u] > 0) & (diff <= max_diff)
    out[rr, cc] = np.where(ok, ref.conf[rr, cc] * np.exp(-0.5 * (diff / max_diff) ** 2), 0)
    return out


def sweep_pair(plan: SweepPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None],
               config: PriorConfig) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """Both references' (disparity f B / z, confidence) over their whole views, and the seconds spent
    warping and matching."""
    t0 = time.perf_counter()
    views = [_view_image(s, grey[s.camera], masks.get(s.camera), config) for s in (plan.left, plan.right)]
    t_warp = time.perf_counter() - t0
    refs = [_sweep_reference(plan, k, views, config) for k in (0, 1)]
    confs = [swap_check(plan, k, refs, config.filters.lr_max_diff) for k in (0, 1)]
    out = []
    for side, ref, conf in zip((plan.left, plan.right), refs, confs):
        if config.confidence.edge_jump_px > 0:
            conf *= discontinuity_factor(ref.disp, conf > 0, config.confidence.edge_jump_px)
        remove_islands(ref.disp, conf, config.filters.min_region_px)
        out.append((_full(side, ref.disp), _full(side, conf)))
    return out, {"warp": t_warp, "match": time.perf_counter() - t0 - t_warp}


def sweep_values(plan: SweepPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None],
                 config: PriorConfig) -> tuple[list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], dict[str, float]]:
    """One pair: sweep both references and back-project; (camera, flat index, depth, confidence) per side
    and the seconds per stage, as the rectified path's `PriorBuilder._pair_values` gives them."""
    maps, timings = sweep_pair(plan, grey, masks, config)
    t0 = time.perf_counter()
    g = config.geometry
    values = [(side.camera, *side.back.values(disp, conf, g.min_depth, g.max_depth))
              for side, (disp, conf) in zip((plan.left, plan.right), maps)]
    timings["backproject"] = time.perf_counter() - t0
    return values, timings


__all__ = ["SweepPlan", "SweepSide", "aggregate", "cost_volume", "depth_maps", "nearest_shared_inverse_depth",
           "plan_sweeps", "plane_homographies", "subplane", "swap_check", "sweep_inverse_depths", "sweep_pair",
           "sweep_values", "sweep_view", "winner"]
