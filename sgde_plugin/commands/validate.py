"""`sgde validate DIR`: check a rig folder against the contracts and print its camera and pair tables."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from ..tables import format_table

if TYPE_CHECKING:  # the command loads the rig (and torch) only when it runs
    from ..rig import Rig

HELP = "check a rig folder (sgde-rig/1 or a supported data set); exit 0 if valid, 2 with one line if not"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde validate`."""
    parser.add_argument("dir", help="rig folder or data-set root")
    parser.add_argument("--quick", action="store_true",
                        help="check image headers (sizes) only, instead of decoding every image, depth map and mask")


def camera_rows(rig: Rig) -> list[dict]:
    """One table row per camera: model, size, field of view (a fisheye's cone, a pinhole's horizontal), mounting
    position and viewing direction."""
    import numpy as np

    rows = []
    for cam in rig.cameras:
        axis = cam.sensor_to_ego[:3, 2]
        fov = getattr(cam.intrinsics, "fov_deg", None)
        if fov is None:
            fov = cam.intrinsics.hfov_deg
        rows.append({
            "camera": cam.name,
            "model": cam.model,
            "size": f"{cam.width}x{cam.height}",
            "fov_deg": float(fov),
            "x_m": float(cam.sensor_to_ego[0, 3]),
            "y_m": float(cam.sensor_to_ego[1, 3]),
            "z_m": float(cam.sensor_to_ego[2, 3]),
            "yaw_deg": float(np.degrees(np.arctan2(axis[1], axis[0]))),
            "pitch_deg": float(np.degrees(np.arcsin(np.clip(axis[2], -1, 1)))),
        })
    return rows


def pair_rows(rig: Rig) -> list[dict]:
    """One table row per adjacent pair from the pair geometry."""
    from ..pairs import rig_pair_geometry

    return [
        {
            "left": g.left,
            "right": g.right,
            "baseline_m": g.baseline_m,
            "axes_deg": g.axis_angle_deg,
            "overlap_deg": g.sector_deg,
            "left_frac": g.left_fraction,
            "right_frac": g.right_fraction,
        }
        for g in rig_pair_geometry(rig)
    ]


def image_files(rig: Rig) -> list:
    """Every image, depth map and mask file the rig refers to, in frame order."""
    files = []
    for frame in rig.frames:
        files += [frame.images[c] for c in rig.camera_names if c in frame.images]
        files += [p for c, p in frame.depths.items() if str(p).lower().endswith((".png", ".jpg", ".jpeg"))]
    return files + [rig.masks[c] for c in rig.camera_names if c in rig.masks]


def run(args: argparse.Namespace) -> int:
    """Validate (decoding every image unless --quick), then print the tables."""
    from ..io import decode_check
    from ..progress import progress
    from ..readers.detect import load_rig

    rig = load_rig(args.dir, check_images=True)
    if not args.quick:
        files = image_files(rig)
        for path in progress(files, desc="decoding images", total=len(files)):
            decode_check(path)
    print(f"{args.dir}: valid, {len(rig.cameras)} cameras, {len(rig.pairs)} adjacent pairs, {len(rig.frames)} frames")
    print()
    print(format_table(camera_rows(rig), digits=2))
    print()
    print(format_table(pair_rows(rig), digits=3))
    return 0
