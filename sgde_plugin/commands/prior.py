"""`sgde prior DIR --out CACHE`: compute every frame's depth prior into a (resumable) prior cache."""

from __future__ import annotations

import argparse

from .options import integer, number

HELP = "compute the stereo depth prior of every frame into a zarr prior cache (resumable, parallel)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde prior`."""
    parser.add_argument("dir", help="rig folder or data-set location (PATH[::SELECTOR...])")
    parser.add_argument("--out", required=True, help="prior cache: a folder, or an fsspec URL (s3://..., memory://...)")
    parser.add_argument("--rig", help="sgde-rig/1 file whose cameras (e.g. refined extrinsics) replace DIR's")
    parser.add_argument("--matcher", default="sgbm", help="sgbm (default), torch or onnx (with --matcher-path)")
    parser.add_argument("--matcher-path", help="learned matcher file (torch module / state dict, or ONNX)")
    parser.add_argument("--scale", type=number(0, 2, lo_open=True), default=0.5,
                        help="matching resolution relative to the images (0.5)")
    parser.add_argument("--min-depth", type=number(0, 1e4, lo_open=True), default=None,
                        help="nearest depth searched, metres (1.5)")
    parser.add_argument("--max-depth", type=number(0, 1e5, lo_open=True), default=None,
                        help="farthest depth kept, metres (80)")
    parser.add_argument("--workers", type=integer(0, 4096), default=None,
                        help="parallel worker processes (default: all CPUs)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local", help="local processes or Ray actors")
    parser.add_argument("--ray-address", help="Ray cluster address (default: start a local Ray instance)")
    parser.add_argument("--scene", help="scene (zarr group) name in the cache (default: from the rig or DIR)")
    parser.add_argument("--repair", action="store_true", help="read every chunk of the cached frames and rebuild "
                        "the damaged ones (a resume always rebuilds frames whose shards are missing)")
    parser.add_argument("--wait", type=number(0, 86400), default=0.0, metavar="SECONDS",
                        help="wait this long for another build writing the same cache (default: refuse at once)")


def _scene_from_location(location: str) -> str | None:
    parts = [p for p in location.split("::")[1:] if p and p != "sweeps" and not p.startswith("v1.0")]
    return parts[-1] if parts else None


def load_rig_with_override(location: str, rig_json: str | None):
    """The rig of DIR (images checked), with the cameras and pairs of --rig when given."""
    from dataclasses import replace

    from ..errors import InputError
    from ..readers.detect import load_rig
    from ..rig import read_rig_json

    rig = load_rig(location, check_images=True)
    if rig_json:
        override = read_rig_json(rig_json)
        if sorted(override.camera_names) != sorted(rig.camera_names):
            raise InputError(rig_json, "cameras", f"names {override.camera_names} differ from DIR's {rig.camera_names}")
        for cam in override.cameras:
            mine = rig.camera(cam.name)
            if (cam.width, cam.height) != (mine.width, mine.height):
                raise InputError(rig_json, f"cameras[{cam.name}]", "image size differs from DIR's images")
        rig = replace(rig, cameras=override.cameras, pairs=override.pairs, ring=override.ring)
    return rig


def run(args: argparse.Namespace) -> int:
    """Build (or resume) the cache and print one summary line."""
    import dataclasses

    from ..cache.build import build_cache, default_scene_name, default_workers, sanitize_scene_name
    from ..errors import InputError
    from ..stereo.pipeline import PriorConfig

    rig = load_rig_with_override(args.dir, args.rig)
    settings = {"matcher": args.matcher, "matcher_path": args.matcher_path, "scale": args.scale,
                "min_depth": args.min_depth, "max_depth": args.max_depth}
    names = {f.name for f in dataclasses.fields(PriorConfig)}
    config = PriorConfig(**{k: v for k, v in settings.items() if v is not None and k in names})
    workers = args.workers if args.workers is not None else (0 if args.ray_address else default_workers())
    if workers < 0 or (workers == 0 and not args.ray_address):
        raise InputError(None, "--workers", "must be at least 1")
    scene = args.scene
    if not scene:
        named = rig.extra.get("scene") or _scene_from_location(args.dir)
        scene = sanitize_scene_name(str(named)) if named else default_scene_name(rig)
    report = build_cache(
        rig, args.out, config, workers=workers, engine=args.engine, scene=str(scene), ray_address=args.ray_address,
        repair=args.repair, wait_s=args.wait,
    )
    print(report.line())
    return 0
