"""`sgde masks DIR --out MASKDIR`: estimate each camera's static (ego-body) mask from the sequence."""

from __future__ import annotations

import argparse

from ..errors import InputError
from ..tables import format_table

HELP = "estimate each camera's static ego-body mask from a sequence (user masks in DIR/masks take precedence)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde masks`."""
    parser.add_argument("dir", help="rig folder or data-set location with at least two frames")
    parser.add_argument("--out", required=True, help="folder for <camera>.png (255 = use, 0 = ignore); "
                        "DIR/masks makes them the rig's masks")
    parser.add_argument("--frames", type=int, default=8,
                        help="frames used, spread over the sequence (default 8; at least 2, 3 are enough)")
    parser.add_argument("--no-ground", action="store_true",
                        help="do not use the rig's poses (ego motion, extrinsics) to tell the body from the road")


def run(args: argparse.Namespace) -> int:
    """Estimate (or take the user's) mask per camera, write them atomically, print a table."""
    import numpy as np

    from ..io import output_folder, write_image
    from ..masks import MaskSettings, estimate_static_mask, rig_ground_maps, spread_frames
    from ..readers.detect import load_rig

    if args.frames < 2:
        raise InputError(None, "--frames", "must be at least 2")
    rig = load_rig(args.dir)
    if len(rig.frames) < 2:
        raise InputError(args.dir, "frames", f"has {len(rig.frames)} frame; a static mask needs at least 2")
    picked = [rig.frames[i].id for i in spread_frames(len(rig.frames), args.frames)]
    masks, rows = {}, []
    settings = MaskSettings()
    with output_folder(args.out) as out:  # made before the work: an unusable --out fails at once
        for cam in rig.camera_names:
            user = rig.load_mask(cam)
            if user is not None:
                masks[cam], source = user, "user"
            else:
                maps = None if args.no_ground else rig_ground_maps(rig, cam, picked, settings.max_ground_m)
                masks[cam] = estimate_static_mask([rig.load_image(f, cam) for f in picked], settings, maps)
                source = "estimated" if maps is None else "estimated, ground motion"
            rows.append({"camera": cam, "source": source, "masked": float(1.0 - masks[cam].mean())})
        for cam, mask in masks.items():
            write_image(out / f"{cam}.png", np.where(mask, 255, 0).astype(np.uint8))
    print(f"{args.dir}: masks from {len(picked)} frames written to {out}")
    print(format_table(rows))
    return 0
