"""Evaluation of depth priors against ground truth: accuracy where a prior exists, coverage of the true overlap.

Accuracy: Abs Rel, Sq Rel, RMSE, RMSE log and delta < 1.25^k (`sgde_plugin.metrics.depth_metrics`)
over prior-valid pixels with ground truth, pooled over frames. Coverage: the share of ground-truth
pixels inside the TRUE overlap that received a prior, where a pixel of camera A is in the true
overlap with its neighbour B when its ground-truth 3-D point projects into B (true extrinsics) and
B's ground truth there confirms the point is visible (not occluded). Per camera, per pair, overall.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import torch

from ..cameras import Camera
from ..geometry import invert_transform
from ..metrics import METRIC_KEYS, depth_metrics
from ..rig import Rig
from ..splat import lift_depth_torch, project_to_pixels, transform_points_torch
from .rectify import torch_threads

GROUP_COLUMNS = ("coverage", *METRIC_KEYS, "n_prior", "n_overlap")
CURVE_THRESHOLDS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
CURVE_COLUMNS = ("min_confidence", "coverage", "abs_rel", "a1", "rmse", "n_prior")


def sparsification_curve(
    pred: np.ndarray, gt: np.ndarray, conf: np.ndarray, overlap_conf: np.ndarray | None = None,
    thresholds: Iterable[float] = CURVE_THRESHOLDS, max_depth: float = 80.0,
) -> list[dict[str, float]]:
    """Accuracy and coverage of the prior kept at each confidence threshold (conf >= t).

    `pred`, `gt`, `conf`: flat arrays over prior pixels with ground truth. `overlap_conf`: the
    confidence of every true-overlap pixel (0 where there is no prior), for the coverage column
    (NaN without it). A confidence that ranks errors gives an Abs Rel that falls as t rises.
    """
    rows = []
    for t in thresholds:
        keep = conf >= t if t > 0 else conf >= -1
        m = depth_metrics(pred[keep], gt[keep], max_depth=max_depth)
        cov = float("nan")
        if overlap_conf is not None and overlap_conf.size:
            cov = float(((overlap_conf >= t) & (overlap_conf > 0)).mean())
        rows.append({"min_confidence": float(t), "coverage": cov, "abs_rel": m["abs_rel"], "a1": m["a1"],
                     "rmse": m["rmse"], "n_prior": int(m["n"])})
    return rows


def true_overlap(
    cam_a: Camera, gt_a: np.ndarray, cam_b: Camera, gt_b: np.ndarray | None, mask_b: np.ndarray | None = None,
    rel_tol: float = 0.03, abs_tol: float = 0.1, a_to_b: np.ndarray | None = None,
) -> np.ndarray:
    """Bool (H, W) of camera A: ground-truth pixels whose 3-D point B sees unoccluded.

    B "sees" the point when it projects inside B's image (and mask) and B's ground-truth depth at
    the nearest pixel agrees with the point's depth in B within `rel_tol` (relative) + `abs_tol` m.
    With `gt_b` None (sparse truth such as LiDAR, which cannot confirm visibility) projecting inside
    B is enough. `a_to_b` (4x4, camera A's frame -> camera B's) defaults to the extrinsics'
    inv(sensor_to_ego_B) @ sensor_to_ego_A; pass the per-capture one when the cameras fired apart.
    Both cameras must carry their true extrinsics.
    """
    h, w = gt_a.shape
    out = np.zeros((h, w), bool)
    if a_to_b is None:
        a_to_b = invert_transform(cam_b.sensor_to_ego) @ cam_a.sensor_to_ego
    with torch_threads(1):
        gt = torch.as_tensor(np.asarray(gt_a, dtype=np.float64))
        pts, lifted = lift_depth_torch(gt, cam_a)
        hits = project_to_pixels(transform_points_torch(torch.as_tensor(a_to_b), pts), cam_b)
    ys, xs = np.nonzero(lifted.numpy())
    seen, index = hits.valid.numpy(), hits.index.numpy()
    if gt_b is not None:
        found = np.asarray(gt_b).reshape(-1)[index]
        expected = hits.depth.numpy()
        seen &= (found > 0) & (np.abs(found - expected) <= rel_tol * expected + abs_tol)
    if mask_b is not None:
        seen &= np.asarray(mask_b).reshape(-1)[index]
    out[ys[seen], xs[seen]] = True
    return out


class _Group:
    """Pooled prediction / ground-truth samples and coverage counts of one row of the report."""

    def __init__(self) -> None:
        self.pred: list[np.ndarray] = []
        self.gt: list[np.ndarray] = []
        self.conf: list[np.ndarray] = []
        self.overlap_conf: list[np.ndarray] = []
        self.n_overlap = 0
        self.n_covered = 0

    def add(self, prior: np.ndarray, gt: np.ndarray, select: np.ndarray, overlap: np.ndarray,
            conf: np.ndarray | None = None) -> None:
        """Pool one image's prior and ground truth at the selected pixels (and its confidence, when given)."""
        sel = select & (prior > 0) & (gt > 0)
        self.pred.append(prior[sel].astype(np.float32))
        self.gt.append(gt[sel].astype(np.float32))
        if conf is not None:
            c = np.where(prior > 0, conf, 0).astype(np.float32)
            self.conf.append(c[sel])
            self.overlap_conf.append(c[overlap])
        self.n_overlap += int(overlap.sum())
        self.n_covered += int((overlap & (prior > 0)).sum())

    def curve(self, max_depth: float) -> list[dict[str, float]] | None:
        """Sparsification curve of the pooled samples (None when no confidence was given)."""
        if not self.conf or len(self.conf) != len(self.pred):
            return None
        return sparsification_curve(np.concatenate(self.pred), np.concatenate(self.gt), np.concatenate(self.conf),
                                    np.concatenate(self.overlap_conf), max_depth=max_depth)

    def result(self, max_depth: float) -> dict[str, Any]:
        """Coverage and depth metrics of everything pooled so far."""
        pred = np.concatenate(self.pred) if self.pred else np.zeros(0, np.float32)
        gt = np.concatenate(self.gt) if self.gt else np.zeros(0, np.float32)
        m = depth_metrics(pred, gt, max_depth=max_depth)
        out: dict[str, Any] = {
            "coverage": self.n_covered / self.n_overlap if self.n_overlap else float("nan"),
            **{k: m[k] for k in METRIC_KEYS},
            "n_prior": int(m["n"]),
            "n_overlap": self.n_overlap,
        }
        return out


class PriorEvaluator:
    """Accumulates frames of priors and ground truth of one rig (true extrinsics); `.result()` reports.

    `sparse_truth` (LiDAR): a ground-truth point is in the true overlap when it projects inside the
    neighbour (and its mask); the neighbour's sparse truth cannot confirm that it is not occluded there.
    """

    def __init__(self, rig_true: Rig, max_depth: float = 80.0, sparse_truth: bool = False):
        self.rig = rig_true
        self.max_depth = max_depth
        self.sparse_truth = sparse_truth
        self.frames = 0
        self.cameras = {c: _Group() for c in rig_true.camera_names}
        self.pairs = {f"{a}|{b}": _Group() for a, b in rig_true.pairs}
        self.overall = _Group()

    def add(
        self, priors: Mapping[str, np.ndarray], gts: Mapping[str, np.ndarray | None],
        masks: Mapping[str, np.ndarray | None] | None = None, frame: str | None = None,
        confidences: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """One frame: prior depth per camera (0 = none) and ground truth per camera (None = unknown).

        With `frame` (an id of the rig), cameras are related by their poses at their own captures
        (`Rig.capture`), as they must be when they fired at different times; otherwise by the extrinsics.
        `masks` (True = use) drop pixels from the ground truth and the overlap (ego body);
        `confidences` per camera feed the sparsification curve of `result()["curve"]`.
        """
        masks = masks or {}
        confidences = confidences or {}
        in_range = {}
        for name, gt in gts.items():
            if gt is None:
                continue
            g = np.where(gt <= self.max_depth, gt, 0).astype(np.float32)
            if masks.get(name) is not None:
                g = np.where(masks[name], g, 0)
            in_range[name] = g
        overlap: dict[tuple[str, str], np.ndarray] = {}
        for a, b in self.rig.pairs:
            if a in in_range and b in in_range:
                ca, cb = self.rig.camera(a), self.rig.camera(b)
                a_to_b = None if frame is None else self._relative(frame, a, b)
                b_to_a = None if a_to_b is None else invert_transform(a_to_b)
                confirm_a, confirm_b = (None, None) if self.sparse_truth else (gts[a], gts[b])
                overlap[a, b] = true_overlap(ca, in_range[a], cb, confirm_b, masks.get(b), a_to_b=a_to_b)
                overlap[b, a] = true_overlap(cb, in_range[b], ca, confirm_a, masks.get(a), a_to_b=b_to_a)
        for name, g in in_range.items():
            prior = priors.get(name)
            if prior is None:
                prior = np.zeros_like(g)
            union = np.zeros(g.shape, bool)
            for (x, _), m in overlap.items():
                if x == name:
                    union |= m
            everywhere = np.ones(g.shape, bool)
            conf = confidences.get(name)
            self.cameras[name].add(prior, g, everywhere, union, conf)
            self.overall.add(prior, g, everywhere, union, conf)
        for a, b in self.rig.pairs:
            if (a, b) not in overlap:
                continue
            group = self.pairs[f"{a}|{b}"]
            for x, y in ((a, b), (b, a)):
                prior = priors.get(x)
                prior = np.zeros_like(in_range[x]) if prior is None else prior
                group.add(prior, in_range[x], overlap[x, y], overlap[x, y])
        self.frames += 1

    def _relative(self, frame: str, a: str, b: str) -> np.ndarray:
        """4x4 camera a -> camera b, each at its own capture of `frame`."""
        return invert_transform(self.rig.capture(frame, b).camera_to_world) @ self.rig.capture(frame, a).camera_to_world

    def pair_samples(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{"A|B": (prior, truth)}: the pooled samples of each pair's true overlap that have a prior."""
        def cat(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0, np.float32)

        return {k: (cat(g.pred), cat(g.gt)) for k, g in self.pairs.items()}

    def result(self) -> dict[str, Any]:
        """{"overall": row, "cameras": {name: row}, "pairs": {"A|B": row}, "frames": n}."""
        return {
            "frames": self.frames,
            "max_depth": self.max_depth,
            "overall": self.overall.result(self.max_depth),
            "cameras": {k: g.result(self.max_depth) for k, g in self.cameras.items()},
            "pairs": {k: g.result(self.max_depth) for k, g in self.pairs.items()},
            "curve": self.overall.curve(self.max_depth),
        }


def evaluate_priors(
    rig_true: Rig,
    prior: Callable[[str, str], np.ndarray | None],
    gt: Callable[[str, str], np.ndarray | None],
    frame_ids: Iterable[str] | None = None,
    masks: Mapping[str, np.ndarray | None] | None = None,
    max_depth: float = 80.0,
) -> dict[str, Any]:
    """Evaluate priors `prior(frame_id, camera)` against ground truth `gt(frame_id, camera)`.

    `rig_true` must carry the true extrinsics (they define the true overlap). Returns the report of
    `PriorEvaluator.result()`: per camera, per pair (pixels of both cameras inside that pair's true
    overlap) and overall, each with coverage, Abs Rel, Sq Rel, RMSE, RMSE log, a1..a3 and counts.
    """
    ev = PriorEvaluator(rig_true, max_depth)
    ids = [f.id for f in rig_true.frames] if frame_ids is None else list(frame_ids)
    for fid in ids:
        priors = {c: prior(fid, c) for c in rig_true.camera_names}
        gts = {c: gt(fid, c) for c in rig_true.camera_names}
        ev.add({k: v for k, v in priors.items() if v is not None}, gts, masks)
    return ev.result()


def report_rows(report: Mapping[str, Any]) -> tuple[list[dict], list[dict], list[dict]]:
    """Table rows (cameras, pairs, overall) of an evaluation report."""
    def rows(groups: Mapping[str, Any], key: str) -> list[dict]:
        return [{key: name, **{c: g[c] for c in GROUP_COLUMNS}} for name, g in groups.items()]

    return rows(report["cameras"], "camera"), rows(report["pairs"], "pair"), rows({"all": report["overall"]}, "scope")
