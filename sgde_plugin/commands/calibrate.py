"""`sgde calibrate DIR --out RIG.json`: refine a rig's extrinsics with the geometric loop constraint."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import InputError
from ..tables import format_table
from .options import integer, number

HELP = "refine the extrinsics of a rig folder (GLC bundle adjustment) and write an sgde-rig/1 file"

METHODS = ("glc", "wo-glc", "pairwise", "none")


# --links: the MatchConfig fields of each mode
LINK_MODES = {"auto": {}, "all": {"temporal_links": True, "mono_links": True}, "touching": {"temporal_links": True},
              "off": {"auto_links": False}}
PHASE_MODES = {"auto": {"view_phases": 1, "auto_phases": True},
               **{str(k): {"view_phases": k, "auto_phases": False} for k in range(1, 5)}}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde calibrate`."""
    parser.add_argument("dir", help="rig folder (sgde-rig/1 or a supported data set)")
    parser.add_argument("--out", required=True, help="output rig.json (refined sensor_to_ego + calibration block)")
    parser.add_argument("--method", choices=METHODS, default="glc", help="calibration method (default glc)")
    parser.add_argument("--frames", default=None, metavar="A:B", help="frame index range (Python slice, default all)")
    parser.add_argument("--matcher", choices=("sift", "loftr"), default="sift", help="feature matcher (default sift)")
    parser.add_argument("--masks", default=None, metavar="MASKDIR",
                        help="static masks <camera>.png (e.g. from `sgde masks`) for cameras without their own: "
                             "no features are taken there")
    parser.add_argument("--loftr-weights", default=None, metavar="CKPT",
                        help="local LoFTR checkpoint for --matcher loftr (nothing is downloaded)")
    parser.add_argument("--window", type=integer(1, 100000), default=7,
                        help="frames per calibration window T (default 7); the frames are split into consecutive "
                             "windows and a rejected window keeps the last accepted calibration")
    parser.add_argument("--beta", type=integer(0, 10**9), default=None,
                        help="minimum verified inliers per observation pair, i.e. per two images (default 15 with "
                             "sift; with loftr the paper's 200 DDAD, 50 nuScenes); a camera pair without one is "
                             "constrained through the ring")
    parser.add_argument("--alpha", type=number(0, 1e3, lo_open=True), default=0.3,
                        help="largest accepted relative translation change, m")
    parser.add_argument("--max-iterations", type=integer(1, 10**6), default=200,
                        help="iteration limit of the adjustment; a window that needs more is rejected (default 200)")
    parser.add_argument("--refine-focal", action=argparse.BooleanOptionalAction, default=None,
                        help="glc: estimate one focal-length scale per camera (prior 1 %%) and write the refined "
                             "intrinsics (default: AdjustConfig.refine_focal)")
    parser.add_argument("--refine-keypoints", action=argparse.BooleanOptionalAction, default=None,
                        help="sift: move each verified keypoint to the sub-pixel position where its patch aligns "
                             "with its track's (calib/refine.py; default: on when the rig has a non-pinhole camera, "
                             "MatchConfig.refine='auto')")
    parser.add_argument("--links", choices=LINK_MODES, default="auto",
                        help="sift: same-camera matches between consecutive frames in the adjustment: 'auto' (every "
                             "one, when a pair seen only across time comes out with a rotation 1-sigma above 0.02 "
                             "deg: the window is redone with them), 'all', 'touching' (those that extend a pair's "
                             "tracks) or 'off'")
    parser.add_argument("--view-phases", choices=PHASE_MODES, default="auto", metavar="K|auto",
                        help="match and adjust each window K times (1-4) with the overlap views' pixel grids moved by "
                             "half a pixel, and keep the mean of the accepted runs (lowers the part of the error "
                             "that follows the views' sampling; K times the work); 'auto': once, and at all four "
                             "phases when an adjacent pair comes out with a rotation 1-sigma above 0.02 deg "
                             "(default: auto)")
    parser.add_argument("--fuse-windows", action=argparse.BooleanOptionalAction, default=True,
                        help="average an accepted window that agrees with the calibration in effect (within 6 "
                             "combined 1-sigmas) with it, weighted by precision, instead of replacing it (default on)")
    parser.add_argument("--partial", action=argparse.BooleanOptionalAction, default=True,
                        help="calibrate a window whose observed pairs do not link every camera block by block, each "
                             "block placed by its fit to the starting extrinsics (default on; --no-partial rejects "
                             "it, rule min_correspondences)")
    parser.add_argument("--json", default=None, metavar="REPORT", help="also write the calibration block here")
    parser.add_argument("--strict", action="store_true",
                        help="exit with code 3 when no window is accepted (default: exit 0, one line on stderr)")


def parse_frames(text: str | None) -> slice | None:
    """'A:B', 'A:', ':B' or 'A' (one frame) -> slice; InputError otherwise."""
    if text is None:
        return None
    parts = text.split(":")
    try:
        if len(parts) == 1:
            i = int(parts[0])
            return slice(i, i + 1 if i != -1 else None)
        if len(parts) == 2:
            a, b = (int(p) if p.strip() else None for p in parts)
            return slice(a, b)
    except ValueError:
        pass
    raise InputError(None, "--frames", f"expected A:B (integers), got {text!r}")


def summary_rows(block: dict) -> list[dict]:
    """One row per window and adjacent pair for the printed table."""
    rows = []
    for w in block["windows"]:
        for p in w["pairs"] or [{}]:
            rows.append({
                "window": w["index"],
                "first_frame": w["frames"][0],
                "pair": f"{p['a']}-{p['b']}" if p else "-",
                "inliers": p.get("inliers"),
                "adjusted": p.get("adjusted_correspondences"),
                "rms_px": p.get("rms_px"),
                # how well the window's images determine the pair's relative rotation (the adjustment's 1-sigma)
                "sigma_deg": None if p.get("rotation_sigma_deg") is None else f"{p['rotation_sigma_deg']:.4f}",
                "accepted": w["accepted"],
                "rule": w["rule"] or _accepted_as(w),
            })
    return rows


def _accepted_as(window: dict) -> str:
    """How an accepted window was taken: "partial" (block by block), "averaged" (with the calibration in effect),
    "confirms N" (adopted with window N, which it confirmed), joined by "+", or "-"."""
    confirms = window.get("confirms")
    tags = [t for t, on in (("partial", window.get("partial")), ("averaged", window.get("fused_weights")),
                            (f"confirms {confirms['window']}" if confirms else "", confirms)) if on]
    return "+".join(tags) or "-"


def run(args: argparse.Namespace) -> int:
    """Calibrate, write the rig atomically, print the per-pair table and the verdict."""
    from ..calib import AcceptanceRules, AdjustConfig, MatchConfig, calibrate, default_beta
    from ..io import atomic_write_text, check_writable
    from ..readers.detect import load_rig
    from ..rig import write_rig_json

    frames = parse_frames(args.frames)
    _check_numbers(args)
    check_writable(args.out)
    check_writable(args.json)
    rig = load_rig(args.dir, check_images=True)
    if args.masks:
        from ..masks import attach_masks

        rig = attach_masks(rig, args.masks)
    beta = default_beta(rig, args.matcher) if args.beta is None else args.beta
    rules = AcceptanceRules(min_correspondences=beta, max_translation_change_m=args.alpha,
                            max_iterations=args.max_iterations)
    acfg = AdjustConfig() if args.refine_focal is None else AdjustConfig(refine_focal=args.refine_focal)
    refine = {} if args.refine_keypoints is None else {"refine": args.refine_keypoints}
    mcfg = MatchConfig(**refine, **LINK_MODES[args.links], **PHASE_MODES[args.view_phases])
    out_rig, block = calibrate(rig, method=args.method, frames=frames, matcher=args.matcher, window=args.window,
                               loftr_weights=args.loftr_weights, rules=rules, adjust_config=acfg, match_config=mcfg,
                               fuse_windows=args.fuse_windows, partial=args.partial)
    write_rig_json(out_rig, args.out)
    if args.json:
        atomic_write_text(Path(args.json), json.dumps(block, indent=1) + "\n")
    print(format_table(summary_rows(block), digits=3))
    _print_focal(block)
    n_ok = sum(w["accepted"] for w in block["windows"])
    print(f"{args.method}: {n_ok}/{len(block['windows'])} windows accepted; wrote {args.out}")
    for line in (partial_line(block), rejection_line(block)):
        if line:
            print(line, file=sys.stderr)
    return STRICT_EXIT if args.strict and n_ok == 0 else 0


STRICT_EXIT = 3


def _check_numbers(args: argparse.Namespace) -> None:
    """One InputError for the first numeric option out of range (or an option the chosen matcher does not take)."""
    if args.loftr_weights is not None and args.matcher != "loftr":
        raise InputError(None, "--loftr-weights",
                         f"only `--matcher loftr` takes a checkpoint (matcher: {args.matcher})")
    if args.window < 1:
        raise InputError(None, "--window", "must be at least 1")
    if args.beta is not None and args.beta < 0:
        raise InputError(None, "--beta", "must be >= 0")
    if not args.alpha > 0:
        raise InputError(None, "--alpha", "must be positive")
    if args.max_iterations < 1:
        raise InputError(None, "--max-iterations", "must be at least 1")


def _print_focal(block: dict) -> None:
    """The focal length estimates of each accepted window that made them."""
    for w in block["windows"]:
        if w["accepted"] and w.get("focal"):
            print(f"window {w['index']} focal length estimate (%, 1-sigma; * adopted): " + ", ".join(
                f"{f['camera']} {f['estimate_pct']:+.3f} ({f['sigma_pct'] or float('nan'):.3f})"
                f"{'*' if f['adopted'] else ''}" for f in w["focal"]))


def partial_line(block: dict) -> str | None:
    """One line for stderr about windows accepted block by block (None when there is none)."""
    partial = [w for w in block["windows"] if w["accepted"] and w.get("partial")]
    if not partial:
        return None
    w = partial[0]
    blocks = " | ".join(", ".join(b) for b in w["blocks"])
    return (f"calibrate: {len(partial)} window(s) calibrated block by block; first: window {w['index']} (frames "
            f"{w['frames'][0]}..{w['frames'][-1]}): {w['not_linked']}; blocks {blocks}, each placed by its fit to the "
            f"starting extrinsics (pairs between blocks keep them)")


def rejection_line(block: dict) -> str | None:
    """One line for stderr about rejected windows (None when every window was accepted)."""
    rejected = [w for w in block["windows"] if not w["accepted"]]
    if not rejected:
        return None
    w = rejected[0]
    where = f"window {w['index']} (frames {w['frames'][0]}..{w['frames'][-1]}): {w['rule']}: {w['reason']}"
    if len(rejected) == len(block["windows"]):
        return f"calibrate: no window accepted, the input extrinsics are kept; {where}"
    return (f"calibrate: {len(rejected)} of {len(block['windows'])} windows rejected, each keeps the last accepted "
            f"calibration; first: {where}")
