"""Depth prior of a whole rig frame (SGDE step 3): rectify every adjacent pair, match, back-project, fuse.

`PriorBuilder(rig, config)` does all per-rig work once (rectified geometry, remap maps, backward
maps); `.build(images, masks)` then turns one frame's images into one `PriorMap` per camera.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..rig import Rig
from .backproject import BackProjection, backprojection, fuse_into
from .filters import grey_float, lr_check, photometric_scores, refine_disparity, remove_islands
from .matchers import Matcher, SGBMMatcher, load_learned_matcher
from .rectify import RectifiedPair, WarpMaps, default_rim_px, rectify_pair, torch_threads
from .virtual import virtual_pinholes

PRIOR_ALGO_VERSION = "1"

MATCHERS = ("sgbm", "torch", "onnx")
FISHEYE_PATHS = ("direct", "virtual")


@dataclass(frozen=True)
class PriorConfig:
    """Everything that changes the prior: matcher, matching scale, depth range, filters, geometry."""

    matcher: str = "sgbm"  # "sgbm", or a learned matcher from matcher_path: "torch" / "onnx"
    matcher_path: str | None = None
    matcher_arch: str | None = None  # "pkg.module:factory" for a torch state dict
    matcher_input_scale: float = 1.0  # learned matchers: multiply [0, 255] pixels by this
    matcher_flow_output: bool = False  # learned matchers: output is a flow (disparity = -x)
    scale: float = 0.5  # matching resolution relative to the source cameras
    min_depth: float = 1.5
    max_depth: float = 80.0
    block_size: int = 3  # SGBM settings tuned on the synthetic world (all three presets)
    p1: int = 8
    p2: int = 32
    uniqueness: int = 15
    speckle_window: int = 100
    speckle_range: int = 2
    lr_max_diff: float = 1.0  # left-right consistency, rectified pixels
    border_px: int = 2  # matches this far (+ half a block) from an image border are dropped
    refine_iterations: int = 1  # sub-pixel Gauss-Newton steps after matching (0 = off)
    min_zncc: float = 0.5  # photometric check after the shift (7x7 windows): ZNCC above this,
    max_abs_diff: float = 8.0  # mean absolute difference (grey levels) below this,
    min_texture: float = 0.5  # RMS x-gradient (grey levels / px) above this (full confidence at 2x)
    min_region_px: int = 200  # final speckle filter: smallest region of similar disparity kept
    color: bool = False  # match RGB instead of grey
    margin_px: int = 8
    max_azimuth_deg: float = 60.0  # rectified canvas half-angles (matter for fisheyes only)
    max_elevation_deg: float = 50.0
    fisheye: str = "direct"  # "direct": remap straight from the fisheye; "virtual": via virtual pinholes

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise InputError(None, "matcher", f"unknown matcher {self.matcher!r} (expected {', '.join(MATCHERS)})")
        if self.matcher != "sgbm" and not self.matcher_path:
            raise InputError(None, "matcher_path", f"matcher {self.matcher!r} needs a model file")
        if self.fisheye not in FISHEYE_PATHS:
            raise InputError(None, "fisheye", f"expected one of {', '.join(FISHEYE_PATHS)}")
        if not 0 < self.scale <= 2:
            raise InputError(None, "scale", "must be in (0, 2]")
        if not 0 < self.min_depth < self.max_depth:
            raise InputError(None, "min_depth/max_depth", "need 0 < min_depth < max_depth")

    def to_dict(self) -> dict[str, Any]:
        """All settings plus the algorithm version and, for a learned matcher, the model file's hash."""
        d: dict[str, Any] = asdict(self)
        d["algo_version"] = PRIOR_ALGO_VERSION
        if self.matcher == "sgbm":
            for key in ("matcher_path", "matcher_arch", "matcher_input_scale", "matcher_flow_output"):
                d.pop(key)
        else:
            path = Path(self.matcher_path or "")
            d["matcher_sha256"] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
            for key in ("block_size", "p1", "p2", "uniqueness", "speckle_window", "speckle_range"):
                d.pop(key)
        return d

    def make_matcher(self) -> Matcher:
        """The configured matcher."""
        if self.matcher == "sgbm":
            return SGBMMatcher(
                block_size=self.block_size, p1=self.p1, p2=self.p2, uniqueness=self.uniqueness,
                speckle_window=self.speckle_window, speckle_range=self.speckle_range,
            )
        return load_learned_matcher(
            str(self.matcher_path), self.matcher_arch, self.matcher_input_scale, self.matcher_flow_output
        )


@dataclass
class PriorMap:
    """Depth prior of one camera: depth float32 (H, W) metres (0 = none), confidence float32 in [0, 1]."""

    depth: np.ndarray
    confidence: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """Bool (H, W): where the prior has a value."""
        return self.depth > 0

    @classmethod
    def empty(cls, height: int, width: int) -> PriorMap:
        """A map without any value."""
        return cls(np.zeros((height, width), np.float32), np.zeros((height, width), np.float32))


@dataclass(frozen=True, eq=False)
class _Side:
    """How one side's rectified image is made from an original camera's image."""

    camera: str  # original camera name
    pre: WarpMaps | None  # original fisheye -> virtual pinhole (fisheye="virtual" only)
    rect: WarpMaps  # (virtual or original) source -> rectified canvas
    valid: np.ndarray  # bool canvas: pixels the camera sees (through its virtual pinhole, if any)
    back: BackProjection  # original camera -> rectified canvas (backward map)

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Original image -> rectified canvas."""
        if self.pre is not None:
            image = self.pre.warp(image, interpolation)
        return self.rect.warp(image, interpolation)

    def canvas_valid(self, mask: np.ndarray | None) -> np.ndarray:
        """Bool canvas mask: the camera sees the pixel and the ego mask (if any) allows it."""
        if mask is None:
            return self.valid
        return self.valid & (self.warp(mask.astype(np.uint8), cv2.INTER_NEAREST) > 0)


@dataclass(frozen=True, eq=False)
class PairPlan:
    """Everything precomputed for one adjacent pair."""

    pair: RectifiedPair
    left: _Side
    right: _Side


def _facing_half(fisheye: Camera, other: Camera) -> Camera:
    """The virtual pinhole half of `fisheye` that faces `other`."""
    halves = virtual_pinholes(fisheye)
    axis = other.sensor_to_ego[:3, 2]
    return max(halves, key=lambda h: float(h.sensor_to_ego[:3, 2] @ axis))


class PriorBuilder:
    """Builds depth priors for every camera of one rig; all per-rig geometry is computed here once."""

    def __init__(self, rig: Rig, config: PriorConfig | None = None, threads: int | None = None):
        self.rig = rig
        self.config = config or PriorConfig()
        # pairs processed in parallel: OpenCV's thread count by default (1 in a single-threaded worker);
        # a learned matcher parallelises inside torch instead
        default = cv2.getNumThreads() if self.config.matcher == "sgbm" else 1
        self.threads = max(1, default if threads is None else int(threads))
        self.matcher: Matcher = self.config.make_matcher()
        self.last_timings: dict[str, float] = {}
        self.plans: list[PairPlan] = []
        self._static_masks = {c: rig.load_mask(c) for c in rig.camera_names} if rig.root is not None else {}
        with torch_threads(1):
            self._plan()

    def _plan(self) -> None:
        """Rectified geometry, warp maps and backward maps of every pair."""
        rig, cfg = self.rig, self.config
        rays = {}
        for a, b in rig.pairs:
            cam_a, cam_b = rig.camera(a), rig.camera(b)
            src_a, src_b = cam_a, cam_b
            if cfg.fisheye == "virtual":
                if cam_a.intrinsics.depth_is_range:
                    src_a = _facing_half(cam_a, cam_b)
                if cam_b.intrinsics.depth_is_range:
                    src_b = _facing_half(cam_b, cam_a)
            pair = rectify_pair(
                src_a, src_b, cfg.scale, cfg.min_depth, cfg.margin_px, cfg.max_azimuth_deg, cfg.max_elevation_deg
            )
            if pair is None:
                continue
            origs, pres, rects = [], [], []
            for src, rect in ((pair.left, pair.rect_left), (pair.right, pair.rect_right)):
                orig = cam_a if src is src_a else cam_b
                origs.append(orig)
                pres.append(None if src is orig else WarpMaps.between(orig, src, default_rim_px(orig)))
                rects.append(WarpMaps.between(src, rect, default_rim_px(src)))
            valid = [self._side_valid(p, r) for p, r in zip(pres, rects)]
            possible = self._possible(pair, *valid)
            sides = []
            for orig, pre, warp, seen, rect, can in zip(
                origs, pres, rects, valid, (pair.rect_left, pair.rect_right), possible
            ):
                if orig.name not in rays:
                    rays[orig.name] = orig.intrinsics.ray_grid()
                back = backprojection(orig, rect, pair.baseline_m, pair.core_x, *rays[orig.name], possible=can)
                sides.append(_Side(camera=orig.name, pre=pre, rect=warp, valid=seen, back=back))
            self.plans.append(PairPlan(pair, sides[0], sides[1]))

    @staticmethod
    def _side_valid(pre: WarpMaps | None, rect: WarpMaps) -> np.ndarray:
        """Canvas pixels a side's camera sees (through its virtual pinhole, if any)."""
        valid = rect.valid.copy()
        if pre is not None:
            valid &= rect.warp(pre.valid.astype(np.uint8), cv2.INTER_NEAREST) > 0
        return valid

    def _possible(self, pair: RectifiedPair, valid_l: np.ndarray, valid_r: np.ndarray) -> tuple[np.ndarray, ...]:
        """Core pixels that can ever hold a left- / right-referenced disparity: seen (away from the
        border) by their own camera, with a seen pixel of the other within the search range."""
        D = pair.max_disparity
        x0, x1 = pair.core_x
        r = self.config.block_size // 2 + self.config.border_px
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        vl = cv2.erode(valid_l.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        vr = cv2.erode(valid_r.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        row = np.ones((1, D), np.uint8)
        # any right pixel in [x - D + 1, x] / any left pixel in [x, x + D - 1]
        right_reach = cv2.dilate(vr, row, anchor=(D - 1, 0), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        left_reach = cv2.dilate(vl, row, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        return (vl & right_reach)[:, x0:x1] > 0, (vr & left_reach)[:, x0:x1] > 0

    def _prepare(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Check sizes and convert to the matching colour space (grey unless `color`)."""
        out = {}
        used = {s.camera for p in self.plans for s in (p.left, p.right)}
        for name in used:
            if name not in images:
                raise InputError(None, f"images[{name}]", "missing")
            img = np.asarray(images[name])
            cam = self.rig.camera(name)
            if img.shape[:2] != (cam.height, cam.width):
                raise InputError(
                    None, f"images[{name}]", f"is {img.shape[1]}x{img.shape[0]}, camera is {cam.width}x{cam.height}"
                )
            if img.dtype != np.uint8:
                raise InputError(None, f"images[{name}]", f"must be uint8, got {img.dtype}")
            if not self.config.color and img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            out[name] = img
        return out

    def match_pair(
        self, plan: PairPlan, left: np.ndarray, right: np.ndarray, valid_l: np.ndarray, valid_r: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Left- and right-referenced disparity and confidence over the core columns, and the matching seconds.

        The left reference is matched on canvas columns [0, x1) (the left padding gives every core
        pixel its full search range), the right reference on the mirrored columns [x0, W).
        """
        cfg = self.config
        D = plan.pair.max_disparity
        x0, x1 = plan.pair.core_x
        wc = x1 - x0
        t0 = time.perf_counter()
        dl, cl = self.matcher.match(left[:, :x1], right[:, :x1], D)
        dr_f, cr_f = self.matcher.match(
            np.ascontiguousarray(right[:, x0:][:, ::-1]), np.ascontiguousarray(left[:, x0:][:, ::-1]), D
        )
        t_match = time.perf_counter() - t0
        disp_l, conf_l = dl[:, x0:], cl[:, x0:].copy()
        disp_r, conf_r = np.ascontiguousarray(dr_f[:, ::-1][:, :wc]), cr_f[:, ::-1][:, :wc].copy()
        # a match must start on a pixel its camera sees, away from the black border
        r = cfg.block_size // 2 + cfg.border_px
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        for conf, valid in ((conf_l, valid_l), (conf_r, valid_r)):
            inner = cv2.erode(valid.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0)
            conf[inner[:, x0:x1] == 0] = 0
        lf, rf = grey_float(left), grey_float(right)
        lc, rc = lf[:, x0:x1], rf[:, x0:x1]
        if cfg.refine_iterations > 0:
            disp_l = refine_disparity(lc, rf, disp_l, conf_l > 0, -1, x0, cfg.refine_iterations)
            disp_r = refine_disparity(rc, lf, disp_r, conf_r > 0, +1, x0, cfg.refine_iterations)
        conf_l2 = lr_check(disp_l, conf_l, disp_r, conf_r, -1, cfg.lr_max_diff)
        conf_r2 = lr_check(disp_r, conf_r, disp_l, conf_l, +1, cfg.lr_max_diff)
        # photometric checks after the per-pixel shift catch consistent but wrong matches, e.g. of
        # points whose true match has left the other image
        t, m = cfg.min_zncc, cfg.max_abs_diff
        for conf, a, b, disp, sign in ((conf_l2, lc, rf, disp_l, -1), (conf_r2, rc, lf, disp_r, +1)):
            ncc, mad, texture = photometric_scores(a, b, disp, conf > 0, sign, x0)
            conf *= np.clip((ncc - t) / (1 - t), 0, 1) * np.clip(1 - mad / m, 0, 1)
            conf *= np.clip(texture / cfg.min_texture - 1, 0, 1)  # rows without x-structure are ambiguous
            conf *= disp / (disp + 2.0)  # small disparities (far points) give uncertain depth
            remove_islands(disp, conf, cfg.min_region_px)  # isolated islands are mostly wrong matches
        return disp_l, conf_l2, disp_r, conf_r2, t_match

    def _pair_values(
        self, plan: PairPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None]
    ) -> tuple[list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], dict[str, float]]:
        """One pair: warp, match, filter, back-project; (camera, flat index, depth, confidence) per side."""
        cfg = self.config
        t0 = time.perf_counter()
        left = plan.left.warp(grey[plan.left.camera])
        right = plan.right.warp(grey[plan.right.camera])
        valid_l = plan.left.canvas_valid(masks.get(plan.left.camera))
        valid_r = plan.right.canvas_valid(masks.get(plan.right.camera))
        t_warp = time.perf_counter() - t0
        disp_l, conf_l, disp_r, conf_r, t_match = self.match_pair(plan, left, right, valid_l, valid_r)
        t0 = time.perf_counter()
        values = [
            (side.camera, *side.back.values(disp, conf, cfg.min_depth, cfg.max_depth))
            for side, disp, conf in ((plan.left, disp_l, conf_l), (plan.right, disp_r, conf_r))
        ]
        return values, {"warp": t_warp, "match": t_match, "backproject": time.perf_counter() - t0}

    def build(
        self, images: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray] | None = None
    ) -> dict[str, PriorMap]:
        """Priors of all cameras for one frame; `masks` (True = use) default to the rig's static masks.

        Pairs run in `self.threads` threads (OpenCV and NumPy release the GIL); the fusion into each
        camera's map then happens in pair order, so the result does not depend on the thread count.
        """
        t_start = time.perf_counter()
        masks = dict(self._static_masks) if masks is None else dict(masks)
        masks = {k: None if m is None else np.asarray(m) > 0 for k, m in masks.items()}  # any dtype, True = use
        for name, m in masks.items():
            if m is not None and name in self.rig.camera_names:
                cam = self.rig.camera(name)
                if m.shape != (cam.height, cam.width):
                    raise InputError(None, f"masks[{name}]", f"is {m.shape[1]}x{m.shape[0]}, camera is "
                                     f"{cam.width}x{cam.height}")
        grey = self._prepare(images)
        if self.threads > 1 and len(self.plans) > 1:
            with ThreadPoolExecutor(self.threads) as pool:
                results = list(pool.map(lambda p: self._pair_values(p, grey, masks), self.plans))
        else:
            results = [self._pair_values(p, grey, masks) for p in self.plans]
        t0 = time.perf_counter()
        out = {c.name: PriorMap.empty(c.height, c.width) for c in self.rig.cameras}
        for values, _ in results:
            for camera, index, z, c in values:
                fuse_into(out[camera].depth, out[camera].confidence, index, z, c)
        for name, prior in out.items():
            mask = masks.get(name)
            if mask is not None:
                prior.depth[~mask] = 0
                prior.confidence[~mask] = 0
        timings = {k: sum(t[k] for _, t in results) for k in ("warp", "match", "backproject")}
        timings["fuse"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start
        self.last_timings = timings
        return out


__all__ = ["PRIOR_ALGO_VERSION", "PairPlan", "PriorBuilder", "PriorConfig", "PriorMap"]
