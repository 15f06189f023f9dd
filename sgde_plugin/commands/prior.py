"""`sgde prior DIR --out CACHE`: compute every frame's depth prior into a (resumable) prior cache."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from typing import TYPE_CHECKING

from ..errors import InputError
from .options import integer, number

if TYPE_CHECKING:  # the command loads the rig (and torch) only when it runs
    from ..rig import Rig

HELP = "compute the stereo depth prior of every frame into a zarr prior cache (resumable, parallel)"


# Every PriorConfig setting (flat name, stereo.config.SETTINGS) as an option (tests check that none is missing).
# Defaults are None here: an option given on the command line wins over --config, which wins over --preset.
SETTING_OPTIONS: list[tuple[str, str, str]] = [
    ("matcher", "str", "sgbm (default), planesweep (plane sweep between the original views, no rectification), "
     "raft-stereo (official checkpoint + the RAFT-Stereo checkout on PYTHONPATH), "
     "torch (TorchScript, or state dict with --matcher-arch) or onnx"),
    ("matcher_path", "str", "learned matcher file: raftstereo-*.pth, TorchScript / state dict, or ONNX"),
    ("matcher_arch", "str", "pkg.module:factory building the module of a torch state dict"),
    ("matcher_iters", "int", "learned matchers: forward(..., iters=N) (raft-stereo: 32, as its demo)"),
    ("matcher_input_scale", "float", "learned matchers: multiply [0, 255] pixels by this (1)"),
    ("matcher_flow_output", "bool", "learned matchers: the output is a flow, disparity = -x (raft-stereo: yes)"),
    ("matcher_pad", "int", "learned matchers: pad inputs (centred, edge values) to multiples of this (32)"),
    ("device", "str", "learned matchers: cpu (default) or cuda"),
    ("matcher_batch", "int", "learned matchers: same-size images per forward call (2)"),
    ("scale", "float", "matching resolution relative to the images (0.5)"),
    ("min_depth", "float", "nearest depth searched, metres (1.5)"),
    ("max_depth", "float", "farthest depth kept, metres (80; ddad preset 200)"),
    ("block_size", "int", "SGBM block size, odd (3)"),
    ("p1", "int", "SGBM smoothness penalty P1 per channel and block pixel (8)"),
    ("p2", "int", "SGBM smoothness penalty P2 per channel and block pixel (32)"),
    ("uniqueness", "int", "SGBM uniqueness ratio, percent (15)"),
    ("speckle_window", "int", "SGBM speckle window, pixels (100)"),
    ("speckle_range", "int", "SGBM speckle range, disparity steps (2)"),
    ("sweep_planes", "int", "planesweep: most depth planes, uniform in inverse depth (256)"),
    ("sweep_step_px", "float", "planesweep: parallax between neighbouring planes, pixels (1)"),
    ("sweep_window", "int", "planesweep: ZNCC window, odd (7)"),
    ("sweep_paths", "int", "planesweep: semi-global aggregation paths, 0 (window only), 2 or 4 (4)"),
    ("sweep_p1", "float", "planesweep: penalty of a one-plane step, 1 - ZNCC units (0.05)"),
    ("sweep_p2", "float", "planesweep: penalty of a larger step (0.3)"),
    ("sweep_uniqueness", "float", "planesweep: second-best cost must exceed (1 + this) x the best (0.05)"),
    ("lr_max_diff", "float", "left-right consistency, rectified pixels (1)"),
    ("border_px", "int", "matches this close to an image border are dropped (2)"),
    ("refine_iterations", "int", "sub-pixel refinement steps, 0 = off (SGBM 1, learned 0)"),
    ("min_zncc", "float", "photometric check: ZNCC above this (0.5)"),
    ("max_abs_diff", "float", "photometric check: mean absolute difference below this, grey levels (8)"),
    ("min_texture", "float", "RMS x-gradient above this, 0 = off (SGBM 0.5, learned 0)"),
    ("min_region_px", "int", "smallest region of similar disparity kept, pixels (200)"),
    ("ground_depth_ratio", "float", "drop matches farther than this x where their ray meets the ground "
     "(ego z = 0), 0 = off (1.5)"),
    ("color", "bool", "match RGB instead of grey (SGBM no, learned yes)"),
    ("margin_px", "int", "rectified canvas margin, pixels (8)"),
    ("max_azimuth_deg", "float", "rectified canvas half-angle, degrees (60)"),
    ("max_elevation_deg", "float", "rectified canvas half-angle, degrees (50)"),
    ("fisheye", "str", "fisheye path: tiled (default: canvases turned about the baseline, as many as the "
     "shared field needs), direct (one canvas per pair) or virtual (via virtual pinholes)"),
    ("confidence_disparity_px", "float", "confidence x d / (d + this): small disparities are less sure (2)"),
    ("edge_jump_px", "float", "confidence x jump / local disparity range beyond this, 0 = off (0)"),
    ("min_confidence", "float", "drop fused values less confident than this, 0-1 (0; real-camera presets 0.2)"),
    ("edge_depth_ratio", "float", "confidence falls from local depth ratio 1+r to 1+5r, 0 = off (0; real cameras 0.1)"),
    ("edge_window_px", "int", "window of that depth ratio, source pixels (15)"),
    ("antialias", "bool", "low-pass each image before resampling it at --scale (no)"),
    ("normalize", "str", "photometric normalisation of each rectified pair: none, gain or local (none)"),
    ("normalize_sigma", "float", "local normalisation window (Gaussian sigma), rectified pixels (8)"),
]
OPTION_TYPES = {"int": int, "float": number(), "str": str}  # floats: finite (NaN and inf refused)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde prior`."""
    parser.add_argument("dir", help="rig folder or data-set location (PATH[::SELECTOR...])")
    parser.add_argument("--out", required=True, help="prior cache: a folder, or an fsspec URL (s3://..., memory://...)")
    parser.add_argument("--rig", help="sgde-rig/1 file whose cameras (e.g. refined extrinsics) replace DIR's")
    parser.add_argument("--masks", help="folder of static masks <camera>.png (e.g. from `sgde masks`) for the "
                        "cameras without a mask of their own")
    parser.add_argument("--preset", help="per-data-set settings: ddad, nuscenes, fisheye or synthetic")
    parser.add_argument("--config", help="YAML file of prior settings (flat names or groups; may name a preset)")
    settings = parser.add_argument_group("prior settings (each overrides --config and --preset)")
    for name, kind, text in SETTING_OPTIONS:
        flag = "--" + name.replace("_", "-")
        if kind == "bool":
            settings.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            settings.add_argument(flag, dest=name, type=OPTION_TYPES[kind], default=None, help=text)
    settings.add_argument("--matcher-option", dest="matcher_options", action="append", metavar="KEY=VALUE",
                          help="learned matchers: factory keyword / RAFT-Stereo argument (YAML value), repeatable; "
                          "e.g. --matcher-option n_downsample=3")
    parser.add_argument("--workers", type=integer(0, 4096), default=None,
                        help="parallel worker processes (default: all CPUs; learned matchers: as memory allows)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local", help="local processes or Ray actors")
    parser.add_argument("--ray-address", help="Ray cluster address (default: start a local Ray instance)")
    parser.add_argument("--scene", help="scene (zarr group) name in the cache (default: from the rig or DIR)")
    parser.add_argument("--strict", action="store_true", help="exit 3 as soon as a frame's prior comes out empty")
    parser.add_argument("--repair", action="store_true", help="read every chunk of the cached frames and rebuild "
                        "the damaged ones (a resume always rebuilds frames whose shards are missing)")
    parser.add_argument("--wait", type=number(0, 86400), default=0.0, metavar="SECONDS",
                        help="wait this long for another build writing the same cache (default: refuse at once)")


def settings_from_args(args: argparse.Namespace) -> dict:
    """The prior settings given on the command line (None = not given)."""
    import yaml


    values = {name: getattr(args, name, None) for name, _, _ in SETTING_OPTIONS}
    if getattr(args, "matcher_options", None):
        options = {}
        for item in args.matcher_options:
            key, sep, text = item.partition("=")
            if not sep or not key:
                raise InputError(None, "--matcher-option", f"expected KEY=VALUE, got {item!r}")
            try:
                options[key] = yaml.safe_load(text)
            except yaml.YAMLError:
                raise InputError(None, "--matcher-option", f"{key}: not a YAML value: {text!r}") from None
        values["matcher_options"] = options
    return values


def _scene_from_location(location: str) -> str | None:
    parts = [p for p in location.split("::")[1:] if p and p != "sweeps" and not p.startswith("v1.0")]
    return parts[-1] if parts else None


def load_rig_with_override(location: str, rig_json: str | None) -> Rig:
    """The rig of DIR (images checked), with the cameras and pairs of --rig when given."""
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
    from ..cache.build import StrictWarningError, build_cache, default_scene_name, default_workers, sanitize_scene_name
    from ..stereo.presets import load_prior_config

    config = load_prior_config(args.config, args.preset, settings_from_args(args))
    rig = load_rig_with_override(args.dir, args.rig)
    if getattr(args, "masks", None):
        from ..masks import attach_masks

        rig = attach_masks(rig, args.masks)
    workers = args.workers if args.workers is not None else (0 if args.ray_address else default_workers(config))
    if workers < 0 or (workers == 0 and not args.ray_address):
        raise InputError(None, "--workers", "must be at least 1")
    scene = args.scene
    if not scene:
        named = rig.extra.get("scene") or _scene_from_location(args.dir)
        scene = sanitize_scene_name(str(named)) if named else default_scene_name(rig)
    def warn(frame_id: str, text: str) -> None:
        print(f"sgde prior: warning: frame {frame_id}: {text}", file=sys.stderr)

    try:
        report = build_cache(
            rig, args.out, config, workers=workers, engine=args.engine, scene=str(scene), ray_address=args.ray_address,
            on_warning=warn, strict=args.strict, repair=args.repair, wait_s=args.wait,
        )
    except StrictWarningError:
        print("sgde prior: stopped (--strict): a frame's prior came out empty", file=sys.stderr)
        return 3
    print(report.line())
    return 0
