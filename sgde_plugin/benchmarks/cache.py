"""`sgde bench cache`: the prior cache on a synthetic nuScenes rig at 800x450.

Measures bytes per camera image, random single-prior read latency, PriorDataset + DataLoader
throughput with 0 and 2 workers, build throughput with 1 and 2 worker processes (real SGBM priors),
and extrapolates size and build time to nuScenes keyframes and sweeps.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import DataLoader, Subset

from ..cache.build import build_cache
from ..cache.dataset import PriorDataset
from ..cache.inspection import cache_info
from ..cache.store import PriorCache, store_keys
from ..rig import Rig, attach_files, read_rig_json
from ..stereo.config import PriorConfig
from ..synth.sequence import write_synth
from ..tables import markdown_table

# nuScenes v1.0: 850 trainval + 150 test scenes; 34,149 + 6,008 keyframes (samples) of 6 cameras;
# cameras run at 12 Hz against 2 Hz keyframes, 1.4M camera images in all (keyframes + sweeps).
NUSCENES_SETS = (
    ("keyframes, trainval", 34_149 * 6),
    ("keyframes, trainval + test", 40_157 * 6),
    ("all camera images (sweeps)", 1_400_000),
)
TARGETS = {"bytes_per_image": 150 * 1024, "read_ms_median": 5.0, "build_speedup_2_workers": 1.6}


def _rig(tmp: Path, rendered: int, frames: int):
    """A 800x450 synthetic nuScenes rig (true extrinsics) with `frames` frames cycling over the
    `rendered` rendered ones (the build cost per frame is the same)."""
    root = write_synth("nuscenes", rendered, tmp / "nuscenes", scale=0.5)
    rig = attach_files(read_rig_json(Path(root) / "rig_true.json"), Path(root))
    base = rig.frames
    out = [replace(base[i % len(base)], id=f"{i:06d}", timestamp_us=i * 83_333) for i in range(frames)]
    return replace(rig, frames=tuple(out))


def _build(rig: Rig, out: Path, workers: int) -> dict[str, float]:
    """One build; with one worker (in this process) its CPU time per frame is load-independent."""
    cpu = time.process_time()
    report = build_cache(rig, out, PriorConfig(), workers=workers, scene="bench", show_progress=False)
    cpu = time.process_time() - cpu
    first = sorted(report.frame_seconds)[max(0, report.workers - 1)] if report.frame_seconds else 0.0
    out_row = {
        "seconds": report.seconds,
        "frames": report.frames_built,
        "startup_s": first,
        "frames_per_s_total": report.frames_built / report.seconds,
        "frames_per_s_steady": report.steady_rate(),
    }
    if workers == 1:
        out_row["cpu_s_per_frame"] = cpu / max(report.frames_built, 1)
    return out_row


def _best_builds(rig: Rig, tmp: Path, reps: int) -> tuple[dict[str, float], dict[str, float]]:
    """1- and 2-worker builds, alternated `reps` times; the best steady throughput of each (the
    machine may be shared: alternating and keeping the best rejects most of others' load), with
    the shortest total time over the repetitions as `best_seconds` (the first 2-worker build also
    starts the fork server, a one-off cost per process)."""
    best: dict[int, dict[str, float]] = {}
    shortest: dict[int, float] = {}
    for rep in range(reps):
        for workers in (1, 2):
            row = _build(rig, tmp / f"cache{workers}_{rep}", workers)
            shortest[workers] = min(shortest.get(workers, float("inf")), row["seconds"])
            if workers not in best or row["frames_per_s_steady"] > best[workers]["frames_per_s_steady"]:
                best[workers] = row
    for workers in (1, 2):
        best[workers]["best_seconds"] = shortest[workers]
    return best[1], best[2]


def _read_latency(cache_dir: Path, frames: list[str], cameras: list[str], n: int) -> dict[str, float]:
    cache = PriorCache(cache_dir)
    rng = np.random.default_rng(0)
    cache.get(frames[0], cameras[0])  # open the arrays once
    native, resized = [], []
    cpu = time.process_time()
    for _ in range(n):
        f, c = frames[rng.integers(len(frames))], cameras[rng.integers(len(cameras))]
        t = time.perf_counter()
        cache.get(f, c)
        native.append(time.perf_counter() - t)
        t = time.perf_counter()
        cache.get(f, c, size=(256, 704))
        resized.append(time.perf_counter() - t)
    cpu = time.process_time() - cpu
    return {
        "read_cpu_ms_mean": 1000 * cpu / (2 * n) if n else 0.0,  # both read kinds, all threads
        "read_ms_median": 1000 * float(np.median(native)),
        "read_ms_p90": 1000 * float(np.percentile(native, 90)),
        "read_resized_256x704_ms_median": 1000 * float(np.median(resized)),
    }


def _loader_throughput(rig: Rig, cache_dir: Path, workers: int, limit: int) -> float:
    ds = PriorDataset(rig, str(cache_dir), (256, 704), with_gt=False)
    ds = Subset(ds, list(range(min(limit, len(ds)))))
    loader = DataLoader(ds, batch_size=6, num_workers=workers)
    t = time.perf_counter()
    count = sum(int(batch["image"].shape[0]) for batch in loader)
    return count / (time.perf_counter() - t)


def extrapolation(bytes_per_image: float, cpu_s_per_frame: float, cameras: int = 6) -> list[dict[str, Any]]:
    """Size and build time of nuScenes-scale caches from the measured figures at 800x450.

    Build time is in core-hours (one worker = one core; the build scales with workers). At the
    native 1600x900 a prior has 4x the pixels: size and matching time are scaled by 4 (an
    estimate: compression and the matcher need not scale exactly)."""
    rows = []
    for name, images in NUSCENES_SETS:
        frames = images / cameras
        core_h = frames * cpu_s_per_frame / 3600
        rows.append({
            "set": name,
            "camera_images": images,
            "GB_800x450": images * bytes_per_image / 1e9,
            "GB_1600x900_est": 4 * images * bytes_per_image / 1e9,
            "core_h_800x450": core_h,
            "core_h_1600x900_est": 4 * core_h,
            "h_on_2_cores_1600x900_est": 4 * core_h / 2,
            "h_on_64_cores_1600x900_est": 4 * core_h / 64,
        })
    return rows


def run(fast: bool = False) -> dict[str, Any]:
    """All figures of the cache benchmark (fast: fewer frames, fewer reads)."""
    rendered, frames, reads, reps = (1, 6, 50, 1) if fast else (3, 60, 300, 2)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="sgde-bench-cache-") as tmp_name:
        tmp = Path(tmp_name)
        t = time.perf_counter()
        rig = _rig(tmp, rendered, frames)
        render_s = time.perf_counter() - t
        b1, b2 = _best_builds(rig, tmp, reps)
        cache_dir = tmp / "cache2_0"
        info = cache_info(cache_dir)
        scene = info["scenes"][0]
        n_images = scene["frames_done"] * scene["cameras"]
        data_bytes = sum(v for k, v in store_keys(cache_dir).items() if not k.endswith("zarr.json"))
        latency = _read_latency(cache_dir, [f.id for f in rig.frames], rig.camera_names, reads)
        limit = 24 if fast else 72
        loader0 = _loader_throughput(rig, cache_dir, 0, limit)
        loader2 = _loader_throughput(rig, cache_dir, 2, limit)
    per_image = info["bytes"] / n_images
    rows = extrapolation(per_image, b1["cpu_s_per_frame"])
    speedup = b2["frames_per_s_steady"] / b1["frames_per_s_steady"]
    return {
        "image_size": f"{rig.cameras[0].width}x{rig.cameras[0].height}",
        "load_average_before_after": [load_before, os.getloadavg()[0]],
        "frames": frames,
        "cameras": len(rig.cameras),
        "render_s": render_s,
        "coverage": scene["coverage"],
        "bytes_per_image": per_image,
        "data_bytes_per_image": data_bytes / n_images,
        **latency,
        "loader_samples_per_s_0_workers": loader0,
        "loader_samples_per_s_2_workers": loader2,
        "build_1_worker": b1,
        "build_2_workers": b2,
        "build_speedup_2_workers": speedup,
        "build_speedup_2_workers_total_time": b1["best_seconds"] / b2["best_seconds"],
        "targets": TARGETS,
        "meets": {
            "bytes_per_image": per_image <= TARGETS["bytes_per_image"],
            "read_ms_median": latency["read_ms_median"] <= TARGETS["read_ms_median"],
            "build_speedup_2_workers": speedup >= TARGETS["build_speedup_2_workers"],
        },
        "extrapolation": rows,
        "extrapolation_markdown": markdown_table(rows, digits=1),
    }


__all__ = ["extrapolation", "run"]
