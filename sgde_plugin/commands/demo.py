"""`sgde demo [--out DIR]`: the main job end to end on the built-in synthetic rig."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..demo_settings import DemoSettings
from ..errors import InputError
from .options import integer, number

HELP = "synthesise a rig, calibrate it, build and evaluate priors, train, export; writes DIR/report.md"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde demo` (defaults from `DemoSettings`)."""
    d = DemoSettings()
    parser.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    parser.add_argument("--frames", type=integer(2, 10000), default=d.frames,
                        help=f"frames of the synthetic sequence (default {d.frames})")
    parser.add_argument("--scale", type=number(0.1, 1.0), default=d.scale,
                        help=f"image scale of the 1600x900 rig (default {d.scale})")
    parser.add_argument("--steps", type=integer(0, 10**7), default=d.train_steps,
                        help=f"training steps per network arm (default {d.train_steps})")
    parser.add_argument("--seed", type=integer(0, 2**32 - 1), default=d.seed, help=f"scene seed (default {d.seed})")


def run(args: argparse.Namespace) -> int:
    """Run the demo and print its summary."""
    from ..demo import run_demo

    if args.frames < 2:
        raise InputError(None, "--frames", "needs at least 2 frames (one is held out)")
    if not 0.1 <= args.scale <= 1.0:
        raise InputError(None, "--scale", "must be in [0.1, 1]")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, None, "exists and is not a folder")
    settings = DemoSettings(frames=args.frames, scale=args.scale, train_steps=args.steps, seed=args.seed)
    run_demo(out, settings)
    return 0
