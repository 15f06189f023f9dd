"""`sgde eval DIR --cache CACHE [--json OUT]`: accuracy and coverage of cached depth priors against ground truth."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from ..errors import InputError
from ..tables import format_table
from .options import number

HELP = "evaluate cached depth priors against the rig folder's ground truth (accuracy and overlap coverage)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde eval`."""
    parser.add_argument("dir", help="rig folder with ground-truth depth (depth/<frame>/<camera>.png), or a "
                        "nuScenes / DDAD scene (projected LiDAR)")
    parser.add_argument("--cache", required=True, help="prior cache built by `sgde prior`")
    parser.add_argument("--json", dest="json_out", help="also write the full report to this JSON file")
    parser.add_argument(
        "--truth", help="sgde-rig/1 file with the TRUE extrinsics that define the overlap (default: "
        "DIR/rig_true.json when present, else DIR's own rig)",
    )
    parser.add_argument("--max-depth", type=number(0, 1e4, lo_open=True), default=80.0,
                        help="ground truth beyond this is ignored (80 m)")
    parser.add_argument("--masks", help="folder of static masks <camera>.png for cameras without their own: "
                        "masked pixels leave the ground truth and the overlap")
    parser.add_argument("--curve", action="store_true",
                        help="also print coverage and Abs Rel at each confidence threshold (sparsification curve)")
    parser.add_argument("--min-confidence", type=number(0, 1), default=0.0,
                        help="evaluate only prior values whose confidence reaches this (0-1, default 0: all)")


def _truth_rig(rig, dir_arg: str, truth: str | None):
    """The rig with the extrinsics that define the true overlap, and where they came from."""
    from ..rig import read_rig_json

    path = Path(truth) if truth else Path(dir_arg) / "rig_true.json"
    if not path.is_file():
        if truth:
            raise InputError(path, None, "file not found")
        return rig, "rig.json (no rig_true.json: overlap from the rig's own extrinsics)"
    true = read_rig_json(path)
    missing = [c for c in rig.camera_names if c not in true.camera_names]
    if missing:
        raise InputError(path, "cameras", f"lacks {', '.join(missing)}")
    return rig.with_extrinsics({c.name: c.sensor_to_ego for c in true.cameras}), str(path)


def run(args: argparse.Namespace) -> int:
    """Evaluate every cached frame that has ground truth; print the tables; optionally write JSON."""
    from ..cache import PriorCache
    from ..io import atomic_write_text, check_writable
    from ..progress import progress
    from ..readers.detect import load_rig
    from ..stereo.evaluate import PriorEvaluator, report_rows

    check_writable(args.json_out)
    rig = load_rig(args.dir)
    if args.masks:
        from ..masks import attach_masks

        rig = attach_masks(rig, args.masks)
    rig_true, truth_source = _truth_rig(rig, args.dir, args.truth)
    cache = PriorCache(args.cache)
    frames = _cached_frames(cache, rig, args)
    if not any(f.depths or f.lidar is not None for f in frames):
        raise InputError(args.dir, "depth", "no ground-truth depth (depth PNGs or LiDAR) for the cached frames")
    masks = {c: rig.load_mask(c) for c in rig.camera_names}
    lidar = not any(f.depths for f in frames)  # sparse truth: the overlap cannot be confirmed by the neighbour
    evaluator = PriorEvaluator(rig_true, args.max_depth, sparse_truth=lidar)
    for frame in progress(frames, desc="eval", total=len(frames)):
        priors, confs = _cached_priors(cache, frame.id, rig.camera_names, args.min_confidence)
        gts = {cam: rig.load_depth(frame.id, cam) for cam in rig.camera_names}
        evaluator.add(priors, gts, masks, frame=frame.id, confidences=confs if args.curve else None)
    report = evaluator.result()
    report.update({"rig": str(args.dir), "cache": str(args.cache), "truth": truth_source,
                   "cache_fingerprint": cache.fingerprint})
    cams, pairs, overall = report_rows(report)
    print(f"{args.dir}: {report['frames']} frames, priors from {args.cache}, true overlap from {truth_source}")
    print()
    print(format_table(cams))
    print()
    print(format_table(pairs))
    print()
    print(format_table(overall))
    if args.curve and report.get("curve"):
        print()
        print("sparsification (overall): prior values kept where confidence >= min_confidence")
        print(format_table(report["curve"]))
    if args.json_out:
        atomic_write_text(args.json_out, json.dumps(_plain(report), indent=1, allow_nan=False) + "\n")
    return 0


def _cached_frames(cache, rig, args: argparse.Namespace) -> list:
    """The rig's frames that the cache holds (InputError for another scene's cache, missing cameras, a damaged
    frame or no frame at all); a partial build is evaluated on what it has, and one stderr line says so."""
    cache.check_frames(rig)  # the priors of another scene whose frames share ids are refused
    cached_cams = set(cache.cameras())
    missing = [c for c in rig.camera_names if c not in cached_cams]
    if missing:
        raise InputError(args.cache, "cameras", f"has no priors for {', '.join(missing)}")
    cache.check_done_markers(f.id for f in rig.frames)  # a damaged frame is refused, not left out
    cached = set(cache.frames())
    frames = [f for f in rig.frames if f.id in cached]
    if not frames:
        raise InputError(args.cache, "frames", f"none of the {len(rig.frames)} frames of {args.dir} is in the cache")
    if len(frames) < len(rig.frames):
        print(f"sgde eval: {args.cache}: {len(rig.frames) - len(frames)} of the {len(rig.frames)} frames of "
              f"{args.dir} not in the cache (not built yet): the result covers the other {len(frames)}",
              file=sys.stderr)
    return frames


def _cached_priors(cache, frame_id: str, cameras: list[str], min_confidence: float) -> tuple[dict, dict]:
    """Prior depth (0 where none, or below `min_confidence`) and confidence of every camera of a frame."""
    priors, confs = {}, {}
    for cam in cameras:
        depth, valid, conf = cache.get_prior(frame_id, cam)
        if min_confidence > 0:
            valid = valid & (conf >= min_confidence - 0.5 / 255)
        priors[cam], confs[cam] = depth * valid, conf
    return priors, confs


def _plain(value):
    """JSON-safe copy: NaN -> null, NumPy scalars -> Python numbers."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
