"""Per-rig work of the stereo prior: which pairs rectify, and every map a frame then needs.

`plan_pairs(rig, config)` gives one `PairPlan` per adjacent pair that rectifies: the rectified
geometry, each side's warp maps (through a virtual pinhole for fisheyes when asked), the canvas
pixels each camera sees and the backward maps from the original cameras to the canvases.
"""

from __future__ import annotations

import math
from concurrent.futures import Executor
from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera
from ..geometry import rotation_vector
from ..pairs import left_right
from ..rig import Rig
from ..threads import torch_threads
from .backproject import BackProjection, Owner, backprojection, camera_rays
from .config import PriorConfig
from .rectify import (
    RectifiedPair,
    WarpMaps,
    default_rim_px,
    rectified_rotation,
    rectify_pair,
    rim_inner,
    tile_pair,
)
from .virtual import virtual_pinholes

TILE_OVERLAP_DEG = 5.0  # `fisheye: tiled`: neighbouring tiles share this much field beyond their seam (context)


@dataclass(frozen=True, eq=False)
class PairSide:
    """How one side's rectified image is made from an original camera's image."""

    camera: str  # original camera name
    pre: WarpMaps | None  # original fisheye -> virtual pinhole (fisheye="virtual" only)
    rect: WarpMaps  # (virtual or original) source -> rectified canvas
    valid: np.ndarray  # bool canvas: pixels the camera sees (through its virtual pinhole, if any)
    back: BackProjection  # original camera -> rectified canvas (backward map)
    inner: np.ndarray  # bool core columns: `valid` eroded by the border a match keeps (`inner_core`)
    min_disparity: np.ndarray | None = None  # float32 core columns: `ground_disparity`; None = no ground rule

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Original image -> rectified canvas."""
        if self.pre is not None:
            image = self.pre.warp(image, interpolation)
        return self.rect.warp(image, interpolation)

    def inner_for(self, valid: np.ndarray, border: int, core_x: tuple[int, int]) -> np.ndarray:
        """`inner_core` of a canvas mask from `canvas_valid`: precomputed when it is this side's own."""
        return self.inner if valid is self.valid else inner_core(valid, border, core_x)

    def canvas_valid(self, mask: np.ndarray | None) -> np.ndarray:
        """Bool canvas mask: the camera sees the pixel and the ego mask (if any) allows it."""
        if mask is None:
            return self.valid
        return self.valid & (self.warp(mask.astype(np.uint8), cv2.INTER_NEAREST) > 0)


@dataclass(frozen=True, eq=False)
class PairPlan:
    """Everything precomputed for one adjacent pair."""

    pair: RectifiedPair
    left: PairSide
    right: PairSide

    @property
    def cost(self) -> float:
        """Work of one frame (canvas area x search range; SGBM's cost), for scheduling."""
        return float(self.pair.size[0] * self.pair.size[1] * self.pair.max_disparity)

    @property
    def name(self) -> str:
        """`left|right`."""
        return self.pair.name

    @property
    def focal_baseline(self) -> float:
        """f B (px m) of the disparities matched: disparity = this / rectified depth."""
        return float(self.pair.focal_px * self.pair.baseline_m)


def inner_core(valid: np.ndarray, border: int, core_x: tuple[int, int] | None = None) -> np.ndarray:
    """Bool: pixels of a canvas mask whose (2 border + 1)^2 neighbourhood is all valid, in columns `core_x`."""
    k = np.ones((2 * border + 1, 2 * border + 1), np.uint8)
    inner = cv2.erode(valid.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return inner if core_x is None else inner[:, core_x[0] : core_x[1]]


def ground_disparity(rect: Camera, baseline_m: float, core_x: tuple[int, int], ratio: float) -> np.ndarray | None:
    """Float32 (H, columns `core_x`): the smallest disparity f B / z a match of `rect`'s pixel may have (ground).

    A ray that points down meets the ground (the plane ego z = 0) at rectified depth h / (-dir_z), with h
    the camera centre's height and dir the ray at rectified z = 1; nothing it sees lies farther. A match
    farther than `ratio` times that (disparity below f B (-dir_z) / (ratio h)) is an object nearer than the
    search range matched far (or the ground is not where the rig says). 0 for rays that do not point down.
    None when the camera is not above the ground (the rule cannot hold).
    """
    h = float(rect.sensor_to_ego[2, 3])
    if h <= 0:
        return None
    K, R = rect.intrinsics.K, rect.sensor_to_ego[:3, :3]
    x0, x1 = core_x
    u = (np.arange(x0, x1, dtype=np.float64) - K[0, 2]) / K[0, 0]
    v = (np.arange(rect.height, dtype=np.float64) - K[1, 2]) / K[1, 1]
    dir_z = R[2, 0] * u[None, :] + R[2, 1] * v[:, None] + R[2, 2]  # ego z of the ray (rectified z = 1)
    return np.maximum(K[0, 0] * baseline_m * -dir_z / (ratio * h), 0.0).astype(np.float32)


def same_pose(a: np.ndarray, b: np.ndarray, rot_tol: float = 1e-4, trans_tol: float = 1e-3) -> bool:
    """True if two rigid transforms differ by less than `rot_tol` radians and `trans_tol` metres."""
    angle = np.linalg.norm(rotation_vector(a[:3, :3].T @ b[:3, :3]))
    return bool(angle < rot_tol and np.linalg.norm(a[:3, 3] - b[:3, 3]) < trans_tol)


def facing_half(fisheye: Camera, other: Camera, scale: float = 1.0) -> Camera:
    """The virtual pinhole half of `fisheye` that faces `other` (focal length `scale` x the fisheye's resolution)."""
    halves = virtual_pinholes(fisheye, scale=scale)
    axis = other.sensor_to_ego[:3, 2]
    return max(halves, key=lambda h: float(h.sensor_to_ego[:3, 2] @ axis))


def plan_pairs(rig: Rig, config: PriorConfig, shared: dict | None = None, pool: Executor | None = None
               ) -> list[PairPlan]:
    """Rectified geometry, warp maps and backward maps of every pair of `rig` that rectifies.

    With `fisheye: tiled`, a pair with a fisheye whose shared field reaches beyond `max_elevation_deg` about
    the baseline gives one plan per tile (`baseline_tiles`), each back-projecting only the field it owns.
    `shared` keeps what depends on a camera's intrinsics alone (ray grids, rim masks, keyed by the intrinsics):
    pass the same dict to plan the rig again with its cameras moved. With a thread `pool` the pairs are planned
    in its threads (the same plans, in the same order)."""
    geo = config.geometry
    shared = {} if shared is None else shared
    jobs = []
    for a, b in rig.pairs:
        cam_a, cam_b = rig.camera(a), rig.camera(b)
        src_a, src_b = cam_a, cam_b
        if geo.fisheye == "virtual":
            if cam_a.intrinsics.depth_is_range:
                src_a = facing_half(cam_a, cam_b)
            if cam_b.intrinsics.depth_is_range:
                src_b = facing_half(cam_b, cam_a)
        for pair, own in _rectified(src_a, src_b, config):
            orig_l, orig_r = (cam_a, cam_b) if pair.left is src_a else (cam_b, cam_a)
            jobs.append((pair, orig_l, orig_r, own))
    if pool is None:
        return [_plan_pair(*job, config, shared) for job in jobs]
    for cam in {c.intrinsics: c for job in jobs for c in job[1:3]}.values():  # made first: no two threads make it
        camera_rays(cam, shared)
        _rim_mask(cam, shared)

    def planned(job: tuple) -> PairPlan:
        with torch_threads(1):  # torch's thread count is per thread: a pool thread starts with the default
            return _plan_pair(*job, config, shared)

    return list(pool.map(planned, jobs))


def _rim_mask(src: Camera, shared: dict) -> tuple[int, np.ndarray | None]:
    """(rim px, `rim_inner` mask or None) of a warp's source camera, made once per intrinsics in `shared`."""
    rim = default_rim_px(src)
    key = ("rim", src.intrinsics, rim)  # the source's rim mask, shared by all the warps from it
    if rim > 0 and key not in shared:
        shared[key] = rim_inner(src, rim)
    return rim, shared.get(key)


def shared_warp_maps(src: Camera, dst: Camera, shared: dict) -> WarpMaps:
    """`WarpMaps.between(src, dst)` with the fisheye rim left out, `src`'s rim mask made once in `shared`."""
    rim, inner = _rim_mask(src, shared)
    return WarpMaps.between(src, dst, rim, inner=inner)


def _rectified(
    src_a: Camera, src_b: Camera, config: PriorConfig
) -> list[tuple[RectifiedPair, tuple[float, float] | None]]:
    """The rectified pairs of two (source) cameras, each with the turns about the baseline it owns (None =
    all): one pair, or with `fisheye: tiled` one per tile of a fisheye pair's field (`baseline_tiles`)."""
    geo = config.geometry
    tiled = geo.fisheye == "tiled" and (src_a.intrinsics.depth_is_range or src_b.intrinsics.depth_is_range)
    tiles = baseline_tiles(src_a, src_b, geo.max_azimuth_deg, geo.max_elevation_deg) if tiled else None
    if not tiles:
        pair = rectify_pair(
            src_a, src_b, geo.scale, geo.min_depth, geo.margin_px, geo.max_azimuth_deg, geo.max_elevation_deg
        )
        return [] if pair is None else [(pair, None)]
    out = []
    for k, (centre, lo, hi, half) in enumerate(tiles):
        pair = tile_pair(src_a, src_b, centre, half, geo.scale, geo.min_depth, geo.margin_px, geo.max_azimuth_deg,
                         name=str(k))
        if pair is not None:
            out.append((pair, (lo, hi)))
    return out


def _plan_pair(
    pair: RectifiedPair, orig_l: Camera, orig_r: Camera, own: tuple[float, float] | None, config: PriorConfig,
    shared: dict,
) -> PairPlan:
    """Warp maps, canvas masks and backward maps of one rectified pair; `own`: the turns about the baseline
    whose original pixels it back-projects (None = all)."""
    border = config.sgbm.block_size // 2 + config.filters.border_px
    origs, pres, rects = (orig_l, orig_r), [], []

    for src, rect, orig in zip((pair.left, pair.right), (pair.rect_left, pair.rect_right), origs):
        pres.append(None if src is orig else shared_warp_maps(orig, src, shared))
        rects.append(shared_warp_maps(src, rect, shared))
    valid = [_side_valid(p, r) for p, r in zip(pres, rects)]
    inner = [inner_core(v, border) for v in valid]
    possible = _possible(pair, *inner)
    sides = []
    x0, x1 = pair.core_x
    for orig, pre, warp, seen, rect, can, core in zip(
        origs, pres, rects, valid, (pair.rect_left, pair.rect_right), possible, inner
    ):
        owner = None if own is None else Owner.of(orig, rectified_rotation(pair.left, pair.right), *own)
        back = backprojection(orig, rect, pair.baseline_m, pair.core_x, *camera_rays(orig, shared), possible=can,
                              owner=owner)
        ratio = config.filters.ground_depth_ratio
        floor = ground_disparity(rect, pair.baseline_m, pair.core_x, ratio) if ratio > 0 else None
        sides.append(PairSide(camera=orig.name, pre=pre, rect=warp, valid=seen, back=back, inner=core[:, x0:x1],
                              min_disparity=floor))
    return PairPlan(pair, sides[0], sides[1])


def shared_turns(left: Camera, right: Camera, max_azimuth_deg: float, step_deg: float = 1.0) -> np.ndarray:
    """Angles (radians, increasing) about the baseline at which both cameras see some direction at infinity.

    The angle is measured from the rectified viewing direction of `rectified_rotation` (positive: down),
    over directions within `max_azimuth_deg` of the plane normal to the baseline (the pair in either order)."""
    left, right = left_right(left, right)
    R = rectified_rotation(left, right)
    alpha = np.radians(np.linspace(-max_azimuth_deg, max_azimuth_deg, 61))
    psi = np.radians(np.arange(-180.0, 180.0, step_deg))
    aa, pp = np.meshgrid(alpha, psi)
    dirs = np.stack([np.sin(aa), np.cos(aa) * np.sin(pp), np.cos(aa) * np.cos(pp)], axis=-1) @ R.T
    both = np.ones(aa.shape, bool)
    for cam in (left, right):
        _, ok = cam.intrinsics.project(dirs @ cam.sensor_to_ego[:3, :3])
        both &= np.asarray(ok, bool)
    return psi[both.any(axis=1)]


def baseline_tiles(
    left: Camera, right: Camera, max_azimuth_deg: float, max_elevation_deg: float, overlap_deg: float = TILE_OVERLAP_DEG
) -> list[tuple[float, float, float, float]] | None:
    """Tiles of the field two cameras share, about their baseline: (centre, owned from, owned to, half-angle), radians.

    Turning a rectified frame about the baseline keeps its rows epipolar, so a field wider than one canvas
    (`max_elevation_deg` each side) is split into equal tiles, each a canvas centred on its own part: its
    rectified depth stays close to the distance from the baseline (the search range holds), and its sampling
    close to uniform. Each tile back-projects only what it owns (the outer tiles own everything beyond them);
    its canvas reaches `overlap_deg` further for matching context. None when one canvas holds the field, or
    when the pair cannot be rectified (shared centre, views along the baseline: `rectify_pair` says why not)."""
    try:
        turns = shared_turns(left, right, max_azimuth_deg)
    except ValueError:
        return None
    if turns.size == 0:
        return None
    step = math.radians(1.0)
    runs = np.split(turns, np.flatnonzero(np.diff(turns) > 1.5 * step) + 1)
    run = min(runs, key=lambda r: (0 if r[0] <= 0 <= r[-1] else 1, -r.size))  # the run through 0, else the longest
    lo, hi = float(run[0]) - step, float(run[-1]) + step
    limit, overlap = math.radians(max_elevation_deg), math.radians(overlap_deg)
    if -limit <= lo and hi <= limit:
        return None
    n = math.ceil((hi - lo) / (2 * max(limit - overlap, math.radians(1.0))))
    width = (hi - lo) / n
    tiles = []
    for k in range(n):
        own_lo = -math.inf if k == 0 else lo + k * width
        own_hi = math.inf if k == n - 1 else lo + (k + 1) * width
        tiles.append((lo + (k + 0.5) * width, own_lo, own_hi, min(limit, width / 2 + overlap)))
    return tiles


def _side_valid(pre: WarpMaps | None, rect: WarpMaps) -> np.ndarray:
    """Canvas pixels a side's camera sees (through its virtual pinhole, if any)."""
    valid = rect.valid.copy()
    if pre is not None:
        valid &= rect.warp(pre.valid.astype(np.uint8), cv2.INTER_NEAREST) > 0
    return valid


def _possible(pair: RectifiedPair, inner_l: np.ndarray, inner_r: np.ndarray) -> tuple[np.ndarray, ...]:
    """Core pixels that can ever hold a left- / right-referenced disparity: seen (away from the
    border: `inner_core`) by their own camera, with a seen pixel of the other within the search range."""
    D = pair.max_disparity
    x0, x1 = pair.core_x
    vl, vr = inner_l.view(np.uint8), inner_r.view(np.uint8)
    row = np.ones((1, D), np.uint8)
    # any right pixel in [x - D + 1, x] / any left pixel in [x, x + D - 1]
    right_reach = cv2.dilate(vr, row, anchor=(D - 1, 0), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    left_reach = cv2.dilate(vl, row, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return (vl & right_reach)[:, x0:x1] > 0, (vr & left_reach)[:, x0:x1] > 0


__all__ = ["PairPlan", "PairSide", "baseline_tiles", "facing_half", "ground_disparity", "inner_core",
           "plan_pairs", "same_pose", "shared_turns", "shared_warp_maps"]
