"""Per-rig work of the stereo prior: which pairs rectify, and every map a frame then needs.

`plan_pairs(rig, config)` gives one `PairPlan` per adjacent pair that rectifies: the rectified
geometry, each side's warp maps (through a virtual pinhole for fisheyes when asked), the canvas
pixels each camera sees and the backward maps from the original cameras to the canvases.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera
from ..geometry import rotation_vector
from ..rig import Rig
from .backproject import BackProjection, backprojection
from .config import PriorConfig
from .rectify import RectifiedPair, WarpMaps, default_rim_px, rectify_pair
from .virtual import virtual_pinholes


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


def plan_pairs(rig: Rig, config: PriorConfig) -> list[PairPlan]:
    """Rectified geometry, warp maps and backward maps of every pair of `rig` that rectifies."""
    geo = config.geometry
    border = config.sgbm.block_size // 2 + config.filters.border_px
    rays = {}
    plans = []
    for a, b in rig.pairs:
        cam_a, cam_b = rig.camera(a), rig.camera(b)
        src_a, src_b = cam_a, cam_b
        if geo.fisheye == "virtual":
            if cam_a.intrinsics.depth_is_range:
                src_a = facing_half(cam_a, cam_b)
            if cam_b.intrinsics.depth_is_range:
                src_b = facing_half(cam_b, cam_a)
        pair = rectify_pair(
            src_a, src_b, geo.scale, geo.min_depth, geo.margin_px, geo.max_azimuth_deg, geo.max_elevation_deg
        )
        if pair is None:
            continue
        origs, pres, rects = [], [], []
        for src, rect in ((pair.left, pair.rect_left), (pair.right, pair.rect_right)):
            orig = cam_a if src is src_a else cam_b
            origs.append(orig)
            pres.append(None if src is orig else WarpMaps.between(orig, src, default_rim_px(orig)))
            rects.append(WarpMaps.between(src, rect, default_rim_px(src)))
        valid = [_side_valid(p, r) for p, r in zip(pres, rects)]
        inner = [inner_core(v, border) for v in valid]
        possible = _possible(pair, *inner)
        sides = []
        x0, x1 = pair.core_x
        for orig, pre, warp, seen, rect, can, core in zip(
            origs, pres, rects, valid, (pair.rect_left, pair.rect_right), possible, inner
        ):
            if orig.name not in rays:
                rays[orig.name] = orig.intrinsics.ray_grid()
            back = backprojection(orig, rect, pair.baseline_m, pair.core_x, *rays[orig.name], possible=can)
            ratio = config.filters.ground_depth_ratio
            floor = ground_disparity(rect, pair.baseline_m, pair.core_x, ratio) if ratio > 0 else None
            sides.append(PairSide(camera=orig.name, pre=pre, rect=warp, valid=seen, back=back, inner=core[:, x0:x1],
                                  min_disparity=floor))
        plans.append(PairPlan(pair, sides[0], sides[1]))
    return plans


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


__all__ = ["PairPlan", "PairSide", "facing_half", "ground_disparity", "inner_core", "plan_pairs", "same_pose"]
