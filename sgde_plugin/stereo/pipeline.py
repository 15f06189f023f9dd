"""Depth prior of a whole rig frame (SGDE step 3): rectify every adjacent pair, match, back-project, fuse.

`PriorBuilder(rig, config)` does all per-rig work once (rectified geometry, remap maps, backward
maps); `.build(images, masks)` then turns one frame's images into one `PriorMap` per camera.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields
from typing import Any

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..geometry import rotation_vector
from ..rig import Frame, Rig
from .backproject import BackProjection, backprojection, fuse_into
from .filters import (
    NORMALIZATIONS,
    discontinuity_factor,
    grey_float,
    lr_check,
    normalize_image,
    photometric_scores,
    refine_disparity,
    remove_islands,
)
from .matchers import Matcher, SGBMMatcher, load_learned_matcher, model_digests
from .rectify import RectifiedPair, WarpMaps, default_rim_px, rectify_pair, torch_threads
from .virtual import virtual_pinholes

PRIOR_ALGO_VERSION = "1"

MATCHERS = ("sgbm", "raft-stereo", "torch", "onnx")
LEARNED_MATCHERS = MATCHERS[1:]
FISHEYE_PATHS = ("direct", "virtual")
DEVICES = ("cpu", "cuda")
# fields that change how a prior is computed, not what it is (device, batching): not fingerprinted
RUNTIME_FIELDS = ("device", "matcher_batch")
# fields whose default (None) depends on the matcher: SGBM's value, a learned matcher's value
MATCHER_DEFAULTS: dict[str, tuple[Any, Any]] = {
    "color": (False, True),  # learned matchers were trained on RGB
    "refine_iterations": (1, 0),  # the Gauss-Newton step undoes SGBM's pixel locking, and hurts learned output
    "min_texture": (0.5, 0.0),  # learned matchers fill weakly textured rows from context
}


@dataclass(frozen=True)
class PriorConfig:
    """Everything that changes the prior: matcher, matching scale, depth range, filters, geometry.

    Fields left at None take the matcher's own default (see MATCHER_DEFAULTS): after construction
    they hold the resolved value, so readers never see None. `sgde prior --config FILE --preset NAME`
    reaches every field (sgde_plugin.stereo.presets).
    """

    matcher: str = "sgbm"  # "sgbm"; learned: "raft-stereo" (official checkpoint), "torch", "onnx"
    matcher_path: str | None = None  # learned matchers: checkpoint / TorchScript / ONNX file
    matcher_arch: str | None = None  # "pkg.module:factory" building the module of a torch state dict
    matcher_options: dict[str, Any] = field(default_factory=dict)  # factory keywords / RAFT-Stereo args
    matcher_iters: int | None = None  # learned: forward(..., iters=N); raft-stereo default 32 (its demo's)
    matcher_input_scale: float = 1.0  # learned matchers: multiply [0, 255] pixels by this
    matcher_flow_output: bool | None = None  # output is a flow (disparity = -x); raft-stereo: True
    matcher_pad: int = 32  # learned matchers: pad the input (edge values, centred) to multiples of this
    device: str = "cpu"  # learned matchers: "cpu" or "cuda" (torch device / onnxruntime provider)
    matcher_batch: int = 2  # learned matchers: images per forward call (same-size inputs of one frame)
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
    refine_iterations: int | None = None  # sub-pixel Gauss-Newton steps after matching (0 = off); SGBM 1, learned 0
    min_zncc: float = 0.5  # photometric check after the shift (7x7 windows): ZNCC above this,
    max_abs_diff: float = 8.0  # mean absolute difference (grey levels) below this,
    min_texture: float | None = None  # RMS x-gradient (grey levels / px) above this (full confidence at 2x);
    #                                   0 = off; SGBM 0.5, learned 0
    min_region_px: int = 200  # final speckle filter: smallest region of similar disparity kept
    color: bool | None = None  # match RGB instead of grey; SGBM False, learned True
    margin_px: int = 8
    max_azimuth_deg: float = 60.0  # rectified canvas half-angles (matter for fisheyes only)
    max_elevation_deg: float = 50.0
    fisheye: str = "direct"  # "direct": remap straight from the fisheye; "virtual": via virtual pinholes
    confidence_disparity_px: float = 2.0  # confidence x d / (d + this): small disparities give uncertain depth
    edge_jump_px: float = 0.0  # > 0: confidence x jump / local disparity range where that range exceeds it
    min_confidence: float = 0.0  # fused values whose confidence is below this are dropped (real-camera presets 0.4)
    antialias: bool = False  # low-pass each image before it is resampled at `scale` (Gaussian, decimation sigma)
    normalize: str = "none"  # per-overlap photometric normalisation before matching: "none", "gain", "local"
    normalize_sigma: float = 8.0  # "local": Gaussian window of the local mean and contrast, rectified px

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise InputError(None, "matcher", f"unknown matcher {self.matcher!r} (expected {', '.join(MATCHERS)})")
        self._resolve_defaults()
        self._check()

    def _resolve_defaults(self) -> None:
        """Replace the None of matcher-dependent fields by the matcher's default."""
        learned = self.matcher in LEARNED_MATCHERS
        for name, (sgbm, nn) in MATCHER_DEFAULTS.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, nn if learned else sgbm)
        if self.matcher_flow_output is None:
            object.__setattr__(self, "matcher_flow_output", self.matcher == "raft-stereo")
        if self.matcher_iters is None and self.matcher == "raft-stereo":
            object.__setattr__(self, "matcher_iters", 32)
        object.__setattr__(self, "matcher_options", dict(self.matcher_options or {}))

    def _check(self) -> None:
        """One-line InputError for a value out of its range."""
        if self.learned and not self.matcher_path:
            raise InputError(None, "matcher_path", f"matcher {self.matcher!r} needs a model file")
        if self.normalize not in NORMALIZATIONS:
            raise InputError(None, "normalize", f"expected one of {', '.join(NORMALIZATIONS)}")
        if self.fisheye not in FISHEYE_PATHS:
            raise InputError(None, "fisheye", f"expected one of {', '.join(FISHEYE_PATHS)}")
        if self.device not in DEVICES:
            raise InputError(None, "device", f"expected one of {', '.join(DEVICES)}, got {self.device!r}")
        if not 0 <= self.min_confidence < 1:
            raise InputError(None, "min_confidence", "must be in [0, 1)")
        if not 0 < self.scale <= 2:
            raise InputError(None, "scale", "must be in (0, 2]")
        if not 0 < self.min_depth < self.max_depth:
            raise InputError(None, "min_depth/max_depth", "need 0 < min_depth < max_depth")
        for name in ("block_size", "matcher_batch", "matcher_pad"):
            if getattr(self, name) < 1:
                raise InputError(None, name, "must be at least 1")
        if self.block_size % 2 == 0:
            raise InputError(None, "block_size", "must be odd")
        if self.matcher_iters is not None and self.matcher_iters < 1:
            raise InputError(None, "matcher_iters", "must be at least 1")
        for name in ("refine_iterations", "min_region_px", "border_px", "margin_px", "min_texture"):
            if getattr(self, name) < 0:
                raise InputError(None, name, "must not be negative")

    @property
    def learned(self) -> bool:
        """True for a learned matcher (anything but SGBM)."""
        return self.matcher in LEARNED_MATCHERS

    def settings(self) -> dict[str, Any]:
        """Every field by name (resolved values): what `--config` files hold; PriorConfig(**settings()) == self."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_dict(self) -> dict[str, Any]:
        """The fingerprint document: every field but the runtime ones, the algorithm version and, for a
        learned matcher, the hashes of its model files and of its architecture's source code."""
        d = {k: v for k, v in self.settings().items() if k not in RUNTIME_FIELDS}
        d["algo_version"] = PRIOR_ALGO_VERSION
        if self.learned:
            d.update(model_digests(self.matcher, self.matcher_path, self.matcher_arch))
        return d

    def make_matcher(self) -> Matcher:
        """The configured matcher."""
        if self.matcher == "sgbm":
            return SGBMMatcher(
                block_size=self.block_size, p1=self.p1, p2=self.p2, uniqueness=self.uniqueness,
                speckle_window=self.speckle_window, speckle_range=self.speckle_range,
            )
        return load_learned_matcher(
            str(self.matcher_path), self.matcher_arch, self.matcher_input_scale, bool(self.matcher_flow_output),
            self.matcher_pad, kind=self.matcher, options=self.matcher_options, iters=self.matcher_iters,
            device=self.device, batch_size=self.matcher_batch,
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


def _same_pose(a: np.ndarray, b: np.ndarray, rot_tol: float = 1e-4, trans_tol: float = 1e-3) -> bool:
    """True if two rigid transforms differ by less than `rot_tol` radians and `trans_tol` metres."""
    angle = np.linalg.norm(rotation_vector(a[:3, :3].T @ b[:3, :3]))
    return bool(angle < rot_tol and np.linalg.norm(a[:3, 3] - b[:3, 3]) < trans_tol)


def _facing_half(fisheye: Camera, other: Camera) -> Camera:
    """The virtual pinhole half of `fisheye` that faces `other`."""
    halves = virtual_pinholes(fisheye)
    axis = other.sensor_to_ego[:3, 2]
    return max(halves, key=lambda h: float(h.sensor_to_ego[:3, 2] @ axis))


class PriorBuilder:
    """Builds depth priors for every camera of one rig; all per-rig geometry is computed here once."""

    def __init__(self, rig: Rig, config: PriorConfig | None = None, threads: int | None = None):
        self.rig = rig  # the geometry planned: `rig`, or `rig.as_captured(frame)` of the last frame built
        self._base_rig = rig
        self.config = config or PriorConfig()
        # pairs processed in parallel: OpenCV's thread count by default (1 in a single-threaded worker);
        # a learned matcher parallelises inside torch instead
        default = cv2.getNumThreads() if self.config.matcher == "sgbm" else 1
        self.threads = max(1, default if threads is None else int(threads))
        self.matcher: Matcher = self.config.make_matcher()
        self.last_timings: dict[str, float] = {}
        self.last_warning: str | None = None  # set by build() when the frame's prior came out empty
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

    def _plan_for(self, rig: Rig) -> None:
        """Re-plan the pairs for `rig`'s extrinsics unless they match the planned ones (1e-4 rad, 1 mm)."""
        if all(_same_pose(rig.camera(c).sensor_to_ego, self.rig.camera(c).sensor_to_ego) for c in rig.camera_names):
            return
        self.rig = rig
        self.plans = []
        with torch_threads(1):
            self._plan()

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
            if self.config.antialias and self.config.scale < 1:
                # the canvas samples the image about every 1/scale pixels: low-pass it first (no aliasing)
                img = cv2.GaussianBlur(img, (0, 0), 0.5 * float(np.sqrt(self.config.scale**-2 - 1)))
            out[name] = img
        return out

    @staticmethod
    def matcher_inputs(plan: PairPlan, left: np.ndarray, right: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """The two matcher calls of a pair: (left, right) canvas columns [0, x1) for the left reference, and
        the mirrored (right, left) columns [x0, W) for the right reference (the same size)."""
        x0, x1 = plan.pair.core_x
        mirrored = (np.ascontiguousarray(right[:, x0:][:, ::-1]), np.ascontiguousarray(left[:, x0:][:, ::-1]))
        return [(left[:, :x1], right[:, :x1]), mirrored]

    def match_pair(
        self, plan: PairPlan, left: np.ndarray, right: np.ndarray, valid_l: np.ndarray, valid_r: np.ndarray,
        matched: list[tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Left- and right-referenced disparity and confidence over the core columns, and the matching seconds.

        The left reference is matched on canvas columns [0, x1) (the left padding gives every core
        pixel its full search range), the right reference on the mirrored columns [x0, W).
        `matched` passes the matcher's answers to `matcher_inputs` when they were computed in a batch.
        """
        cfg = self.config
        D = plan.pair.max_disparity
        x0, x1 = plan.pair.core_x
        wc = x1 - x0
        t0 = time.perf_counter()
        if matched is None:
            matched = [self.matcher.match(a, b, D) for a, b in self.matcher_inputs(plan, left, right)]
        (dl, cl), (dr_f, cr_f) = matched
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
            if cfg.min_texture > 0:  # rows without x-structure are ambiguous
                conf *= np.clip(texture / cfg.min_texture - 1, 0, 1)
            conf *= disp / (disp + cfg.confidence_disparity_px)  # small disparities give uncertain depth
            if cfg.edge_jump_px > 0:
                conf *= discontinuity_factor(disp, conf > 0, cfg.edge_jump_px)
            remove_islands(disp, conf, cfg.min_region_px)  # isolated islands are mostly wrong matches
        return disp_l, conf_l2, disp_r, conf_r2, t_match

    def _pair_values(
        self, plan: PairPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None],
        batched: Mapping[int, Any] | None = None,
    ) -> tuple[list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], dict[str, float]]:
        """One pair: warp, match, filter, back-project; (camera, flat index, depth, confidence) per side.

        `batched` maps id(plan) to (canvases, matcher answers, seconds) computed ahead."""
        cfg = self.config
        t0 = time.perf_counter()
        ahead = None if batched is None else batched.get(id(plan))
        if ahead is None:
            (left, right, valid_l, valid_r), matched, t_ahead = self._canvases(plan, grey, masks), None, 0.0
        else:
            (left, right, valid_l, valid_r), matched, t_ahead = ahead
        t_warp = time.perf_counter() - t0
        disp_l, conf_l, disp_r, conf_r, t_match = self.match_pair(plan, left, right, valid_l, valid_r, matched)
        t_match += t_ahead
        t0 = time.perf_counter()
        values = [
            (side.camera, *side.back.values(disp, conf, cfg.min_depth, cfg.max_depth))
            for side, disp, conf in ((plan.left, disp_l, conf_l), (plan.right, disp_r, conf_r))
        ]
        return values, {"warp": t_warp, "match": t_match, "backproject": time.perf_counter() - t0}

    def build(
        self, images: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray] | None = None,
        frame: str | Frame | None = None,
    ) -> dict[str, PriorMap]:
        """Priors of all cameras for one frame; `masks` (True = use) default to the rig's static masks.

        With `frame` (a frame of the rig, or its id), each camera is placed where it was at its own
        capture of that frame (`Rig.as_captured`): cameras that fired at different times while the car
        moved are rectified, triangulated and back-projected with their true relative pose; the pairs
        are re-planned only when that geometry differs from the planned one. Pairs run in
        `self.threads` threads (OpenCV and NumPy release the GIL); the fusion into each camera's map then
        happens in pair order, so the result does not depend on the thread count.
        """
        t_start = time.perf_counter()
        if frame is not None:
            self._plan_for(self._base_rig.as_captured(frame))
        masks = dict(self._static_masks) if masks is None else dict(masks)
        masks = {k: None if m is None else np.asarray(m) > 0 for k, m in masks.items()}  # any dtype, True = use
        for name, m in masks.items():
            if m is not None and name in self.rig.camera_names:
                cam = self.rig.camera(name)
                if m.shape != (cam.height, cam.width):
                    raise InputError(None, f"masks[{name}]", f"is {m.shape[1]}x{m.shape[0]}, camera is "
                                     f"{cam.width}x{cam.height}")
        grey = self._prepare(images)
        batched = self._match_batched(grey, masks)
        if self.threads > 1 and len(self.plans) > 1:
            with ThreadPoolExecutor(self.threads) as pool:
                results = list(pool.map(lambda p: self._pair_values(p, grey, masks, batched), self.plans))
        else:
            results = [self._pair_values(p, grey, masks, batched) for p in self.plans]
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
            if self.config.min_confidence > 0:
                unsure = prior.confidence < self.config.min_confidence
                prior.depth[unsure] = 0
                prior.confidence[unsure] = 0
        timings = {k: sum(t[k] for _, t in results) for k in ("warp", "match", "backproject")}
        timings["fuse"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - t_start
        self.last_timings = timings
        self.last_warning = self._empty_frame_warning(out)
        return out

    def _canvases(
        self, plan: PairPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A pair's rectified images as matched (normalised if asked) and their valid pixels."""
        cfg = self.config
        left = plan.left.warp(grey[plan.left.camera])
        right = plan.right.warp(grey[plan.right.camera])
        valid_l = plan.left.canvas_valid(masks.get(plan.left.camera))
        valid_r = plan.right.canvas_valid(masks.get(plan.right.camera))
        if cfg.normalize != "none":
            left = normalize_image(left, valid_l, cfg.normalize, cfg.normalize_sigma)
            right = normalize_image(right, valid_r, cfg.normalize, cfg.normalize_sigma)
        return left, right, valid_l, valid_r

    def _match_batched(
        self, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None]
    ) -> dict[int, Any] | None:
        """A learned matcher's answers for every pair of the frame, same-size inputs batched; None for SGBM."""
        match_many = getattr(self.matcher, "match_many", None)
        if match_many is None or not self.plans:
            return None
        t0 = time.perf_counter()
        canvases = [self._canvases(p, grey, masks) for p in self.plans]
        t_warp = time.perf_counter() - t0
        inputs, ranges = [], []
        for plan, (left, right, _, _) in zip(self.plans, canvases):
            inputs += self.matcher_inputs(plan, left, right)
            ranges += [plan.pair.max_disparity] * 2
        if hasattr(self.matcher, "counts"):
            self.matcher.counts.update(finite=0, valid=0, negative=0)
        t0 = time.perf_counter()
        answers = match_many(inputs, ranges)
        t_each = (time.perf_counter() - t0 + t_warp) / len(self.plans)
        return {id(plan): (canvas, answers[2 * i : 2 * i + 2], t_each)
                for i, (plan, canvas) in enumerate(zip(self.plans, canvases))}

    def _empty_frame_warning(self, out: Mapping[str, PriorMap]) -> str | None:
        """One line when the rig has pairs but the frame's prior is empty, with the likeliest cause."""
        if not self.plans or any(m.confidence.any() for m in out.values()):
            return None
        counts = getattr(self.matcher, "counts", None)
        name = self.config.matcher
        if counts and counts["finite"]:
            if counts["negative"] > 0.5 * counts["finite"]:
                return (f"matcher {name} gave mostly negative disparities ({counts['negative'] / counts['finite']:.0%}"
                        " of the pixels): is the flow sign right? (matcher_flow_output)")
            if counts["valid"] == 0:
                return f"matcher {name} gave no valid disparity (check matcher_input_scale and matcher_flow_output)"
        return f"no valid disparity on this frame (matcher {name}; every match failed the checks)"


__all__ = ["PRIOR_ALGO_VERSION", "PairPlan", "PriorBuilder", "PriorConfig", "PriorMap"]
