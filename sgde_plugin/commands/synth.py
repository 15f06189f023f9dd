"""`sgde synth`: render a synthetic surround sequence into an sgde-rig/1 folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from .options import integer, number

HELP = ("render a synthetic street sequence (nuscenes, ddad, urban-fisheye or a random rig of the seed) into an "
        "sgde-rig/1 folder")

PRESETS = ("nuscenes", "ddad", "urban-fisheye", "random")  # = synth.presets.PRESETS (kept light)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde synth`."""
    parser.add_argument("--preset", required=True, choices=PRESETS,
                        help="camera rig (random: 4-8 cameras drawn from --seed)")
    parser.add_argument("--frames", required=True, type=int, help="number of frames (10 Hz)")
    parser.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    parser.add_argument("--seed", type=integer(0, 2**32 - 1), default=0,
                        help="scene and calibration-noise seed (default 0)")
    parser.add_argument("--scale", type=number(0, 4, lo_open=True), default=1.0, help="image size factor (default 1)")
    parser.add_argument("--pose-noise-deg", type=number(0, 180), default=1.0,
                        help="rotation error of each camera in rig.json, degrees (default 1)")
    parser.add_argument("--pose-noise-m", type=number(0, 100), default=0.05,
                        help="translation error of each camera in rig.json, metres (default 0.05)")
    parser.add_argument("--ego-body", action="store_true",
                        help="draw the car's glossy body into the cameras; true masks go to masks_true/")
    parser.add_argument("--supersample", type=int, default=1, help="k x k colour samples per pixel (default 1)")
    parser.add_argument("--capture", choices=("sync", "sequential"), default="sync",
                        help="sync: all cameras at the frame's time; sequential: in ring order over --sweep-ms "
                        "while the car moves, each camera's time and ego pose written to the rig (default sync)")
    parser.add_argument("--sweep-ms", type=float, default=50.0,
                        help="sequential capture: time from the first to past the last camera, ms (default 50)")


def run(args: argparse.Namespace) -> int:
    """Check the arguments, render, write atomically, print where."""
    from ..synth.sequence import write_synth
    from ..synth.world import MAX_FRAMES

    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "--out", "exists and is not an empty folder")
    blocking = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise InputError(out, "--out", f"{blocking} is a file, not a folder")
    if not 1 <= args.frames <= MAX_FRAMES:
        raise InputError(None, "--frames", f"must be between 1 and {MAX_FRAMES}")
    if not 0 < args.scale <= 4:
        raise InputError(None, "--scale", "must be in (0, 4]")
    if args.pose_noise_deg < 0 or args.pose_noise_m < 0:
        raise InputError(None, "--pose-noise-deg/--pose-noise-m", "must be >= 0")
    if not 1 <= args.supersample <= 4:
        raise InputError(None, "--supersample", "must be between 1 and 4")
    if not 0 <= args.sweep_ms < 100:
        raise InputError(None, "--sweep-ms", "must be in [0, 100) (one 10 Hz frame)")
    path = write_synth(args.preset, args.frames, out, seed=args.seed, scale=args.scale,
                       pose_noise_deg=args.pose_noise_deg, pose_noise_m=args.pose_noise_m,
                       supersample=args.supersample, capture=args.capture, sweep_ms=args.sweep_ms,
                       ego_body=args.ego_body)
    print(f"wrote {path}: preset {args.preset}, {args.frames} frames, seed {args.seed}, scale {args.scale}")
    return 0
