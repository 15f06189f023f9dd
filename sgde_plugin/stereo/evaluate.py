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
        self.n_overlap = 0
        self.n_covered = 0

    def add(self, prior: np.ndarray, gt: np.ndarray, select: np.ndarray, overlap: np.ndarray) -> None:
        sel = select & (prior > 0) & (gt > 0)
        self.pred.append(prior[sel].astype(np.float32))
        self.gt.append(gt[sel].astype(np.float32))
        self.n_overlap += int(overlap.sum())
        self.n_covered += int((overlap & (prior > 0)).sum())

    def result(self, max_depth: float) -> dict[str, Any]:
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
    ) -> None:
        """One frame: prior depth per camera (0 = none) and ground truth per camera (None = unknown).

        With `frame` (an id of the rig), cameras are related by their poses at their own captures
        (`Rig.capture`), as they must be when they fired at different times; otherwise by the extrinsics.
        """
        masks = masks or {}
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
            self.cameras[name].add(prior, g, everywhere, union)
            self.overall.add(prior, g, everywhere, union)
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

    def result(self) -> dict[str, Any]:
        """{"overall": row, "cameras": {name: row}, "pairs": {"A|B": row}, "frames": n}."""
        return {
            "frames": self.frames,
            "max_depth": self.max_depth,
            "overall": self.overall.result(self.max_depth),
            "cameras": {k: g.result(self.max_depth) for k, g in self.cameras.items()},
            "pairs": {k: g.result(self.max_depth) for k, g in self.pairs.items()},
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
