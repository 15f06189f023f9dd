"""Depth prior of a whole rig frame (SGDE step 3): rectify every adjacent pair, match, back-project, fuse.

`PriorBuilder(rig, config)` does all per-rig work once (`planning.plan_pairs`: rectified geometry,
remap maps, backward maps); `.build(images, masks)` then turns one frame's images into one `PriorMap`
per camera: prepare the images, match each pair (batched for a learned matcher), filter, back-project, fuse.
With `matcher: planesweep` the pairs are not rectified: `planesweep.plan_sweeps` and `sweep_values` match
them between the original views instead, and the fusion is the same.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import InputError
from ..rig import Frame, Rig
from ..threads import opencv_threads
from .backproject import fuse_into
from .checks import MatchedPair, check_pair
from .config import PRIOR_ALGO_VERSION, PriorConfig
from .filters import depth_edge_factor, normalize_image
from .matchers import Matcher
from .planesweep import SweepPlan, plan_sweeps, sweep_values
from .planning import PairPlan, plan_pairs, same_pose
from .rectify import torch_threads
from .schedule import OnDemand, run_pairs


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


class PriorBuilder:
    """Builds depth priors for every camera of one rig; all per-rig geometry is computed here once."""

    def __init__(self, rig: Rig, config: PriorConfig | None = None, threads: int | None = None,
                 matcher: Matcher | None = None):
        """Plan `rig`'s pairs for `config`; `matcher`: one `config.make_matcher()` already made (a learned one is
        then not loaded again)."""
        self.rig = rig  # the geometry planned: `rig`, or `rig.as_captured(frame)` of the last frame built
        self._base_rig = rig
        self.config = config or PriorConfig()
        # pairs processed in parallel: OpenCV's thread count by default (1 in a single-threaded worker);
        # a learned matcher parallelises inside torch instead
        default = cv2.getNumThreads() if self.config.matcher.name in ("sgbm", "planesweep") else 1
        self.threads = max(1, default if threads is None else int(threads))
        self.matcher: Matcher | None = None if self.config.sweeps else matcher or self.config.make_matcher()
        self.last_timings: dict[str, float] = {}
        self.last_warning: str | None = None  # set by build() when the frame's prior came out empty
        self._static_masks = {c: rig.load_mask(c) for c in rig.camera_names} if rig.root is not None else {}
        # a rig whose cameras fire one after another is planned again for most frames: what depends on the
        # cameras' intrinsics alone (ray grids: 35 MB per 1600x900 camera) is kept for those plans
        self._per_camera: dict | None = {} if any(f.cameras for f in rig.frames) else None
        self.plans: list[PairPlan] | list[SweepPlan] = self._plan(rig)

    def _plan(self, rig: Rig) -> list[PairPlan] | list[SweepPlan]:
        """The per-rig work: rectified pairs, or the plane sweep's views."""
        if self.config.sweeps:
            return plan_sweeps(rig, self.config, self._per_camera)
        with torch_threads(1):
            if self.threads == 1:
                return plan_pairs(rig, self.config, self._per_camera)
            with opencv_threads(1), ThreadPoolExecutor(self.threads) as pool:  # pairs in parallel, as in build
                return plan_pairs(rig, self.config, self._per_camera, pool)

    def _plan_for(self, rig: Rig) -> float:
        """Re-plan the pairs for `rig`'s extrinsics unless they match the planned ones (1e-4 rad, 1 mm); the
        seconds it took (0 when kept)."""
        if all(same_pose(rig.camera(c).sensor_to_ego, self.rig.camera(c).sensor_to_ego) for c in rig.camera_names):
            return 0.0
        t0 = time.perf_counter()
        self.rig = rig
        self.plans = self._plan(rig)
        return time.perf_counter() - t0

    def _prepare(self, images: Mapping[str, np.ndarray], on_demand: bool = False) -> Mapping[str, np.ndarray]:
        """Check sizes and convert to the matching colour space (grey unless `color`); `on_demand`: check now,
        convert each camera in the (pair) thread that first needs it."""
        used = sorted({s.camera for p in self.plans for s in (p.left, p.right)})
        checked = {name: self._checked(images, name) for name in used}
        if on_demand:
            return OnDemand(used, lambda name: self._matching_image(checked[name]))
        return {name: self._matching_image(img) for name, img in checked.items()}

    def _checked(self, images: Mapping[str, np.ndarray], name: str) -> np.ndarray:
        """`images[name]` as an HxW (grey) or HxWx3 (RGB) array, or InputError when it is missing, not an image
        (HxWx1 is grey, HxWx4 is RGBA: its alpha is dropped), of the wrong size or not uint8."""
        if name not in images:
            raise InputError(None, f"images[{name}]", "missing")
        img = np.asarray(images[name])
        if img.ndim == 3 and img.shape[2] in (1, 4):
            img = img[..., 0] if img.shape[2] == 1 else img[..., :3]
        if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
            raise InputError(None, f"images[{name}]", f"must be HxW (grey) or HxWx3 (RGB), got shape {img.shape}")
        cam = self.rig.camera(name)
        if img.shape[:2] != (cam.height, cam.width):
            raise InputError(
                None, f"images[{name}]", f"is {img.shape[1]}x{img.shape[0]}, camera is {cam.width}x{cam.height}"
            )
        if img.dtype != np.uint8:
            raise InputError(None, f"images[{name}]", f"must be uint8, got {img.dtype}")
        return img

    def _matching_image(self, img: np.ndarray) -> np.ndarray:
        """A checked camera image in the matching colour space, low-passed if `antialias`."""
        if not self.config.images.color and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        if self.config.images.antialias and self.config.geometry.scale < 1:
            # the canvas samples the image about every 1/scale pixels: low-pass it first (no aliasing)
            img = cv2.GaussianBlur(img, (0, 0), 0.5 * float(np.sqrt(self.config.geometry.scale**-2 - 1)))
        return img

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
        disp_l, disp_r = dl[:, x0:], np.ascontiguousarray(dr_f[:, ::-1][:, :wc])
        # a match must start on a pixel its camera sees, away from the black border, and (the ground rule)
        # not beyond the ground: a near object matched far
        border = cfg.sgbm.block_size // 2 + cfg.filters.border_px
        confs = []
        for conf, disp, valid, side in ((cl[:, x0:], disp_l, valid_l, plan.left),
                                        (cr_f[:, ::-1][:, :wc], disp_r, valid_r, plan.right)):
            keep = side.inner_for(valid, border, plan.pair.core_x)
            if side.min_disparity is not None:
                keep = keep & (disp >= side.min_disparity)
            confs.append(conf * keep)  # a new array: 0 where not kept
        conf_l, conf_r = confs
        disp_l, conf_l2, disp_r, conf_r2 = check_pair(MatchedPair(left, right, x0, disp_l, conf_l, disp_r, conf_r), cfg)
        return disp_l, conf_l2, disp_r, conf_r2, t_match

    def _pair_values(
        self, plan: PairPlan | SweepPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None],
        batched: Mapping[int, Any] | None = None,
    ) -> tuple[list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], dict[str, float]]:
        """One pair: warp, match, filter, back-project; (camera, flat index, depth, confidence) per side.

        `batched` maps id(plan) to (canvases, matcher answers, seconds) computed ahead."""
        cfg = self.config
        if isinstance(plan, SweepPlan):
            return sweep_values(plan, grey, masks, cfg)
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
            (side.camera, *side.back.values(disp, conf, cfg.geometry.min_depth, cfg.geometry.max_depth))
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
        plan_s = 0.0 if frame is None else self._plan_for(self._base_rig.as_captured(frame))
        masks = self._masks(masks)
        parallel = self.threads > 1 and len(self.plans) > 1
        grey = self._prepare(images, on_demand=parallel)  # in parallel: converted in the pair threads
        batched = self._match_batched(grey, masks)
        needs = {c: [i for i, p in enumerate(self.plans) if c in (p.left.camera, p.right.camera)]
                 for c in self.rig.camera_names}
        fuse_s: list[float] = []

        def fuse(camera: str, pair_results: list[tuple[list[Any], dict[str, float]]]) -> PriorMap:
            t0 = time.perf_counter()
            values = [(index, z, c) for vals, _ in pair_results for cam, index, z, c in vals if cam == camera]
            prior = self._fuse_camera(camera, values, masks.get(camera))
            fuse_s.append(time.perf_counter() - t0)
            return prior

        # pairs in parallel: each OpenCV call runs in its own pair's thread (no nested stripes, no spinning pool)
        # (the pool is left, i.e. every pair thread has ended, before OpenCV's count is restored)
        with opencv_threads(1 if parallel else cv2.getNumThreads()), ThreadPoolExecutor(self.threads) as pool:
            costs = [p.cost for p in self.plans]
            results, out = run_pairs(self.plans, lambda p: self._pair_values(p, grey, masks, batched), needs, fuse,
                                     pool if parallel else None, costs)
        timings = {k: sum(t[k] for _, t in results) for k in ("warp", "match", "backproject")}
        timings["fuse"] = sum(fuse_s)
        timings["plan"] = plan_s  # re-planning for this frame's capture geometry (0: the plans were kept)
        timings["total"] = time.perf_counter() - t_start
        self.last_timings = timings
        self.last_warning = self._empty_frame_warning(out)
        return out

    def _masks(self, masks: Mapping[str, np.ndarray | None] | None) -> dict[str, np.ndarray | None]:
        """`build`, stage 1: the masks as bool (True = use; the rig's static masks by default), sizes checked."""
        masks = dict(self._static_masks) if masks is None else dict(masks)
        masks = {k: None if m is None else np.asarray(m) > 0 for k, m in masks.items()}  # any dtype, True = use
        for name, m in masks.items():
            if m is not None and name in self.rig.camera_names:
                cam = self.rig.camera(name)
                if m.shape != (cam.height, cam.width):
                    raise InputError(None, f"masks[{name}]", f"is {m.shape[1]}x{m.shape[0]}, camera is "
                                     f"{cam.width}x{cam.height}")
        return masks

    def _fuse_camera(
        self, name: str, values: list[tuple[np.ndarray, np.ndarray, np.ndarray]], mask: np.ndarray | None
    ) -> PriorMap:
        """One camera's map from its (flat index, depth, confidence) values in pair order, then the masks, the
        occlusion-edge factor and the confidence threshold applied (cameras are independent)."""
        cam = self.rig.camera(name)
        prior = PriorMap.empty(cam.height, cam.width)
        for i, (index, z, c) in enumerate(values):
            if i == 0:  # into the empty map: fuse_into would take every value as it is
                prior.depth.reshape(-1)[index] = z
                prior.confidence.reshape(-1)[index] = c
            else:
                fuse_into(prior.depth, prior.confidence, index, z, c)
        conf_cfg = self.config.confidence
        if mask is not None:
            prior.depth[~mask] = 0
            prior.confidence[~mask] = 0
        if conf_cfg.edge_depth_ratio > 0:  # occlusion edges of the fused map (pairs and sides together)
            prior.confidence *= depth_edge_factor(prior.depth, conf_cfg.edge_depth_ratio, conf_cfg.edge_window_px)
            prior.depth[prior.confidence <= 0] = 0
        if conf_cfg.min_confidence > 0:
            unsure = prior.confidence < conf_cfg.min_confidence
            prior.depth[unsure] = 0
            prior.confidence[unsure] = 0
        return prior

    def _canvases(
        self, plan: PairPlan, grey: Mapping[str, np.ndarray], masks: Mapping[str, np.ndarray | None]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A pair's rectified images as matched (normalised if asked) and their valid pixels."""
        cfg = self.config
        left = plan.left.warp(grey[plan.left.camera])
        right = plan.right.warp(grey[plan.right.camera])
        valid_l = plan.left.canvas_valid(masks.get(plan.left.camera))
        valid_r = plan.right.canvas_valid(masks.get(plan.right.camera))
        if cfg.images.normalize != "none":
            left = normalize_image(left, valid_l, cfg.images.normalize, cfg.images.normalize_sigma)
            right = normalize_image(right, valid_r, cfg.images.normalize, cfg.images.normalize_sigma)
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
        name = self.config.matcher.name
        if counts and counts["finite"]:
            if counts["negative"] > 0.5 * counts["finite"]:
                return (f"matcher {name} gave mostly negative disparities ({counts['negative'] / counts['finite']:.0%}"
                        " of the pixels): is the flow sign right? (matcher_flow_output)")
            if counts["valid"] == 0:
                return f"matcher {name} gave no valid disparity (check matcher_input_scale and matcher_flow_output)"
        return f"no valid disparity on this frame (matcher {name}; every match failed the checks)"


__all__ = ["PRIOR_ALGO_VERSION", "PairPlan", "PriorBuilder", "PriorConfig", "PriorMap"]  # the config from .config
