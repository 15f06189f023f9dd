"""`sgde cache {info,verify} CACHE`: what a prior cache holds, and a full read of every chunk."""

from __future__ import annotations

import argparse
import json
import sys

from ..tables import format_table

HELP = "inspect a prior cache: info (scenes, frames, cameras, coverage, size, fingerprint) or verify (read all)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde cache`."""
    parser.add_argument("action", choices=("info", "verify"), help="info or verify")
    parser.add_argument("cache", help="prior cache folder or fsspec URL")
    parser.add_argument("--json", metavar="OUT", help="also write the result as JSON")


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024.0
    return f"{n:.1f} TB"


def print_info(info: dict) -> None:
    """Human-readable `cache info`."""
    cfg = info.get("config", {}).get("config", {})
    settings = ", ".join(f"{k}={cfg[k]}" for k in ("matcher", "scale", "min_depth", "max_depth") if k in cfg)
    print(f"{info['location']}: {info['format']}, {len(info['scenes'])} scene(s), {_size(info['bytes'])}")
    print(f"config fingerprint {info['config_fingerprint']} ({settings}; algo {info['config'].get('algo_version')})")
    print()
    rows = [
        {
            "scene": s["scene"],
            "frames": f"{s.get('frames_done', 0)}/{s.get('frames_total', 0)}",
            "cameras": s.get("cameras", 0),
            "coverage": s.get("coverage", 0.0),
            "size": _size(s.get("bytes", 0)),
            "per_image": _size(s.get("bytes_per_image", 0)),
            "fingerprint": s.get("fingerprint") or s.get("note", "-"),
        }
        for s in info["scenes"]
    ]
    print(format_table(rows, digits=3))
    if info["cameras"]:
        print()
        print(format_table(info["cameras"], digits=3))


def run(args: argparse.Namespace) -> int:
    """Print info, or verify and exit 2 when any chunk is bad or any frame is missing."""
    from ..cache.inspection import cache_info, verify_cache
    from ..io import atomic_write_text, check_writable

    check_writable(args.json)
    if args.action == "info":
        result = cache_info(args.cache)
        print_info(result)
        code = 0
    else:
        result = verify_cache(args.cache)
        for p in result["problems"]:
            print(f"{p['scene']}/{p['frame']}/{p['camera']}: {p['array']}: {p['problem']}")
        status = "ok" if result["ok"] else f"{len(result['problems'])} problem(s)"
        line = (f"{result['location']}: {result['frames_checked']} frames, {result['chunks_read']} chunks read: "
                f"{status}")
        print(line, file=sys.stdout if result["ok"] else sys.stderr)
        code = 0 if result["ok"] else 2
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1, default=str) + "\n")
    return code
