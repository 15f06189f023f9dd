"""`sgde bench real DIR [--rig RIG.json ...]`: the depth prior on real frames against projected LiDAR.

For each pose source (the data set's extrinsics, then each `--rig` file, e.g. a calibration result, with
its extrinsics and intrinsics: a calibration with `refine_focal` changes focal lengths) the priors of
every frame are built with the default `PriorConfig` and compared with the LiDAR ground truth of
`Rig.load_depth` (ego-motion compensated, nearest return per pixel): Abs Rel, Sq Rel, RMSE, delta < 1.25,
the number of LiDAR points compared, and the coverage: the share of LiDAR points inside the true overlap
(points that project into a neighbouring camera, at its own capture) that receive a prior. Per camera,
per pair and overall; with times. The overlap and the LiDAR projection are always taken from the data
set's extrinsics and intrinsics, so every source is judged on the same LiDAR points at the same pixels.
Each source also gets a breakdown of its errors (`real_breakdown`: by depth, image row and confidence
band, large errors, the median disparity error per pair) and the sparsification curve of its confidence.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..masks import attach_masks
from ..readers.detect import load_rig
from ..rig import Rig, read_rig_json
from ..stereo.config import PriorConfig
from ..stereo.evaluate import PriorEvaluator
from ..stereo.pipeline import PriorBuilder
from ..tables import format_table
from .real_breakdown import ErrorBreakdown, breakdown_tables

COLUMNS = ("abs_rel", "sq_rel", "rmse", "a1", "n_prior", "coverage", "n_overlap")


def _pose_source(rig: Rig, path: str) -> Rig:
    """The scene's rig with the extrinsics and intrinsics of the sgde-rig/1 file at `path` (every camera must
    be there, at the scene's image size): a calibration may refine focal lengths too."""
    other = read_rig_json(path)
    missing = [c for c in rig.camera_names if c not in other.camera_names]
    if missing:
        raise InputError(path, "cameras", f"lacks {', '.join(missing)}")
    for c in rig.camera_names:
        mine, theirs = rig.camera(c).intrinsics, other.camera(c).intrinsics
        if (theirs.width, theirs.height) != (mine.width, mine.height):
            raise InputError(path, f"cameras[{c}]", f"size {theirs.width}x{theirs.height}, the images are "
                             f"{mine.width}x{mine.height}")
    return rig.with_extrinsics({c: other.camera(c).sensor_to_ego for c in rig.camera_names}).with_intrinsics(
        {c: other.camera(c).intrinsics for c in rig.camera_names})


def _truth(rig: Rig) -> tuple[dict, dict, float]:
    """LiDAR depth of every frame and camera, the masks, and the seconds it took."""
    t0 = time.perf_counter()
    gts = {}
    for fr in rig.frames:
        gts[fr.id] = {c: rig.load_depth(fr.id, c) for c in rig.camera_names}
        if all(g is None for g in gts[fr.id].values()):
            raise InputError(rig.root, f"frames[{fr.id}]", "no LiDAR sweep or depth ground truth")
    masks = {c: rig.load_mask(c) for c in rig.camera_names}
    return gts, masks, time.perf_counter() - t0


def _masked(gt: Any, mask: Any) -> Any:
    """LiDAR depth with the ego mask's pixels (False = not used) set to 0; None stays None."""
    return gt if gt is None or mask is None else gt * (mask > 0)


def evaluate_source(rig: Rig, rig_overlap: Rig, images: dict, gts: dict, masks: dict, config: PriorConfig) -> dict:
    """Build the priors of every frame with `rig`'s extrinsics and score them (overlap from `rig_overlap`)."""
    t0 = time.perf_counter()
    builder = PriorBuilder(rig, config)
    setup = time.perf_counter() - t0
    max_depth = config.geometry.max_depth
    evaluator = PriorEvaluator(rig_overlap, max_depth, sparse_truth=True)
    breakdown = ErrorBreakdown()
    build = score = 0.0
    for fid, frame_images in images.items():
        t1 = time.perf_counter()
        priors = builder.build(frame_images, frame=fid)
        t2 = time.perf_counter()
        depth = {c: p.depth for c, p in priors.items()}
        confidence = {c: p.confidence for c, p in priors.items()}
        evaluator.add(depth, gts[fid], masks, frame=fid, confidences=confidence)
        breakdown.add(depth, confidence, {c: _masked(g, masks.get(c)) for c, g in gts[fid].items()}, max_depth)
        build, score = build + t2 - t1, score + time.perf_counter() - t2
    report = evaluator.result()
    fb = {p.name: p.focal_baseline for p in builder.plans}
    report["breakdown"] = breakdown.result(evaluator.pair_samples(), fb)
    report["seconds"] = {"setup": round(setup, 2), "prior_per_frame": round(build / max(1, len(images)), 2),
                         "eval_per_frame": round(score / max(1, len(images)), 2)}
    return report


def run_real(path: str | Path, rigs: list[str] | tuple[str, ...] = (), config: PriorConfig | None = None,
             max_frames: int | None = None, masks: str | Path | None = None) -> dict[str, Any]:
    """The benchmark's report: {"sources": {name: evaluation report}, "seconds": ..., "load_avg": ...}.

    `max_frames` keeps the first frames only (for quick checks; the benchmark uses all); `masks`: a folder
    of static masks (`sgde masks`) for cameras without their own: the prior and the LiDAR truth leave them out."""
    t_start = time.perf_counter()
    config = config or PriorConfig()
    rig = load_rig(path)
    if masks is not None:
        rig = attach_masks(rig, masks)
    if max_frames is not None:
        rig = replace(rig, frames=rig.frames[:max_frames])
    sources = {"dataset": rig, **{str(p): _pose_source(rig, p) for p in rigs}}
    gts, masks, t_truth = _truth(rig)
    t0 = time.perf_counter()
    images = {fr.id: {c: rig.load_image(fr.id, c) for c in rig.camera_names} for fr in rig.frames}
    t_images = time.perf_counter() - t0
    reports = {name: evaluate_source(src, rig, images, gts, masks, config) for name, src in sources.items()}
    return {
        "dir": str(path), "frames": len(rig.frames), "cameras": rig.camera_names,
        "masks": None if masks is None else str(masks),
        "pairs": [f"{a}|{b}" for a, b in rig.pairs], "max_depth": config.geometry.max_depth, "config": config.to_dict(),
        "sources": reports,
        "seconds": {"lidar_truth": round(t_truth, 2), "images": round(t_images, 2),
                    "total": round(time.perf_counter() - t_start, 2)},
        "load_avg": [round(x, 2) for x in os.getloadavg()],
    }


def report_tables(report: dict[str, Any]) -> str:
    """The printed tables: one block per pose source (cameras, pairs, overall) and the times."""
    def row(key: str, name: str, g: dict) -> dict:
        return {key: name, **{c: g[c] for c in COLUMNS}}

    blocks = []
    for name, rep in report["sources"].items():
        s = rep["seconds"]
        blocks.append(f"== poses: {name} ({report['frames']} frames; prior {s['prior_per_frame']} s/frame, "
                      f"set-up {s['setup']} s, scoring {s['eval_per_frame']} s/frame)")
        blocks.append(format_table([row("camera", c, g) for c, g in rep["cameras"].items()]))
        blocks.append(format_table([row("pair", p, g) for p, g in rep["pairs"].items()]))
        blocks.append(format_table([row("scope", "all", rep["overall"])]))
        if "breakdown" in rep:
            blocks.append("where the errors are (LiDAR points with a prior; share_of_abs_rel: of the Abs Rel sum):")
            blocks.append(breakdown_tables(rep["breakdown"]))
        if rep.get("curve"):
            blocks.append("sparsification curve (values kept at confidence >= min_confidence):")
            blocks.append(format_table(rep["curve"]))
    t = report["seconds"]
    blocks.append(f"LiDAR truth {t['lidar_truth']} s, images {t['images']} s, total {t['total']} s "
                  f"(load average {', '.join(map(str, report['load_avg']))})")
    return "\n\n".join(blocks)


__all__ = ["evaluate_source", "report_tables", "run_real"]
