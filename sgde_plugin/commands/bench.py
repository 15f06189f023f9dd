"""`sgde bench [NAME ...] [--json OUT] [--fast] [--supervision {lidar,self}]`: run benchmarks, describe the machine."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import sys
import time

from ..errors import InputError

HELP = ("run benchmarks (synth, readers, prior, calibrate, stem, train-effect, cache, export, capture, learned) and "
        "write one JSON; "
        "`sgde bench real DIR [--rig RIG.json ...]` scores the prior on real frames against LiDAR")

# name on the command line -> module in sgde_plugin.benchmarks; the fast set is what `make bench` runs
BENCHMARKS = {
    "synth": "synth",
    "readers": "readers",
    "prior": "prior",
    "calibrate": "calibrate",
    "stem": "stem",
    "train-effect": "train_effect",
    "cache": "cache",
    "export": "export",
    "capture": "capture",
    "learned": "learned",
}
SLOW = {"train-effect", "learned"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde bench`."""
    names = ", ".join(BENCHMARKS)
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"benchmarks to run (default: all): {names}")
    parser.add_argument("--json", dest="json_out", help="write all results to this JSON file")
    parser.add_argument("--fast", action="store_true", help="smaller sizes, and skip the slow benchmarks unless named")
    parser.add_argument("--peer", choices=("colmap",), default=None,
                        help="calibrate: GLC against COLMAP's rig bundle adjustment on the presets and random rigs "
                             "(needs the extra `peer`: pycolmap)")
    parser.add_argument("--scale", type=float, default=None, metavar="F",
                        help="calibrate --peer only: render scale of the accuracy table's rigs (default 0.5; 1 = "
                             "each rig's own size, about 4x the time)")
    parser.add_argument("--supervision", choices=("lidar", "self"), default="lidar",
                        help="train-effect: LiDAR-like supervision (default) or self-supervised view synthesis")
    parser.add_argument("--rig", action="append", default=[], metavar="RIG.json",
                        help="`real` only: another pose source (sgde-rig/1 extrinsics and intrinsics, e.g. a "
                             "calibration); repeatable")
    parser.add_argument("--preset", default=None,
                        help="`real` only: prior settings preset (ddad, nuscenes, fisheye, synthetic; default: none)")
    parser.add_argument("--config", default=None, metavar="FILE",
                        help="`real` only: YAML file of prior settings, as for `sgde prior --config`")
    parser.add_argument("--masks", default=None, metavar="MASKDIR",
                        help="`real` only: static masks <camera>.png (e.g. from `sgde masks`); the prior and the "
                             "LiDAR truth leave the masked pixels out")


def machine_description() -> dict:
    """CPU, cores, memory and library versions of this machine, for the benchmark record."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gib = None
    try:
        mem_gib = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    import numpy
    import torch

    from .. import __version__

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gib,
        "gpu": torch.cuda.is_available(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "torch_threads": torch.get_num_threads(),
        "sgde_plugin": __version__,
        "platform": platform.platform(),
    }


def _checked_options(args: argparse.Namespace) -> float | None:
    """Refuse the options that the named benchmarks do not take; the accuracy table's scale (None: default)."""
    for flag, value in (("--rig", args.rig), ("--preset", args.preset), ("--config", args.config),
                        ("--masks", args.masks)):
        if value:
            raise InputError(None, flag, "only `sgde bench real DIR` takes this option")
    scale = getattr(args, "scale", None)
    if scale is not None and (not getattr(args, "peer", None) or args.names != ["calibrate"]):
        raise InputError(None, "--scale", "only `sgde bench calibrate --peer colmap` takes this option")
    if scale is not None and not (math.isfinite(scale) and 0.05 <= scale <= 2.0):
        raise InputError(None, "--scale", f"must be a number from 0.05 to 2, got {scale}")
    return scale


def run(args: argparse.Namespace) -> int:
    """Run the named (or all) benchmarks, print each result, optionally write the JSON."""
    from ..io import atomic_write_text, check_writable

    check_writable(args.json_out)
    if args.names[:1] == ["real"]:
        return run_real_bench(args)
    scale = _checked_options(args)
    names = args.names or [n for n in BENCHMARKS if not (args.fast and n in SLOW)]
    for n in names:
        if n not in BENCHMARKS:
            raise InputError(None, "NAME", f"unknown benchmark {n!r} (choose from {', '.join(BENCHMARKS)})")
    record: dict = {"machine": machine_description(), "fast": bool(args.fast), "results": {}}
    failed = 0
    for n in names:
        start = time.perf_counter()
        print(f"== {n}", flush=True)
        try:
            module = importlib.import_module(f"sgde_plugin.benchmarks.{BENCHMARKS[n]}")
            options = {"supervision": args.supervision} if n == "train-effect" else {}
            if n == "calibrate" and getattr(args, "peer", None):
                options = {"peer": args.peer, **({"scale": scale} if scale is not None else {})}
            result = module.run(fast=args.fast, **options)
        except ModuleNotFoundError as exc:
            result = {"error": f"not available: {exc}"}
            failed += 1
        except Exception as exc:  # noqa: BLE001 - one failing benchmark must not hide the others
            result = {"error": f"{type(exc).__name__}: {exc}"}
            failed += 1
        result["wall_s"] = round(time.perf_counter() - start, 2)
        record["results"][n] = result
        print(json.dumps(result, indent=1, default=str), flush=True)
    if args.json_out:
        atomic_write_text(args.json_out, json.dumps(record, indent=1, default=str) + "\n")
        print(f"wrote {args.json_out}", file=sys.stderr)
    return 1 if failed else 0


def run_real_bench(args: argparse.Namespace) -> int:
    """`sgde bench real DIR [--rig RIG.json ...] [--preset P] [--config F] [--masks M] [--json OUT]`: tables, JSON."""
    from ..benchmarks.real import report_tables, run_real
    from ..io import atomic_write_text

    if len(args.names) != 2:
        raise InputError(None, "DIR", "`sgde bench real` takes exactly one scene folder (DIR)")
    from ..stereo.presets import load_prior_config

    config = load_prior_config(args.config, args.preset)
    report = run_real(args.names[1], args.rig, config, masks=args.masks)
    print(report_tables(report), flush=True)
    if args.json_out:
        record = {"machine": machine_description(), "results": {"real": report}}
        atomic_write_text(args.json_out, json.dumps(record, indent=1, default=_json_number) + "\n")
        print(f"wrote {args.json_out}", file=sys.stderr)
    return 0


def _json_number(value: object) -> object:
    """NumPy scalars as Python numbers in the JSON record."""
    return value.item() if hasattr(value, "item") else str(value)
