"""`sgde bench synth`: seconds per rendered frame (all cameras) per preset at scale 1 and 0.5.

Targets: a nuscenes frame (6 x 1600x900) in <= 10 s at scale 1 and <= 3 s at scale 0.5 on 2 cores.
Wall seconds depend on the machine's load; CPU seconds (all threads) divided by the worker count
is what an otherwise idle machine would take. Also reports the cross-view truth agreement (worst
directed pair) of the half-scale frame.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

from ..synth.presets import PRESETS, preset_cameras
from ..synth.render import ray_tiles, render, rig_lod, torch_threads
from ..synth.sequence import default_workers
from ..synth.truth import cross_view_check
from ..synth.world import build_world

TARGETS_S = {("nuscenes", 1.0): 10.0, ("nuscenes", 0.5): 3.0}


def _frame_seconds(world, cameras, time_s: float, workers: int) -> tuple[float, float, dict]:
    """Wall and CPU seconds to render one frame of all cameras, `workers` cameras at a time, and the renders."""
    for cam in cameras:  # ray grids are cached per camera model; build them outside the timing
        ray_tiles(cam.intrinsics, 1)
    pose = world.ego_pose(time_s)
    lod = rig_lod(list(cameras))
    start, cpu = time.perf_counter(), time.process_time()
    with torch_threads(1), ThreadPoolExecutor(max_workers=workers) as pool:
        out = dict(zip([c.name for c in cameras], pool.map(lambda c: render(world, c, pose, time_s, lod=lod), cameras)))
    return time.perf_counter() - start, time.process_time() - cpu, out


def _worst_pair(world, cameras, time_s: float, renders: dict) -> float:
    """Lowest cross-view agreement over the adjacent pairs (cameras come in ring order), both directions."""
    ring = list(cameras)
    pose = world.ego_pose(time_s)
    worst = 1.0
    for a, b in zip(ring, ring[1:] + ring[:1]):
        for x, y in ((a, b), (b, a)):
            r = cross_view_check(world, x, y, pose, time_s, *renders[x.name], *renders[y.name])
            worst = min(worst, r.both_ok)
    return worst


def run(fast: bool = False) -> dict:
    """Time one frame per preset and scale; `fast` times scale 0.5 only and skips the truth check."""
    workers = default_workers()
    t0 = time.perf_counter()
    world = build_world(0)
    result: dict = {
        "workers": workers,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "world_build_s": round(time.perf_counter() - t0, 3),
        "s_per_frame": {},
        "cpu_s_per_frame": {},
        "cross_view_worst_pair_both_ok_scale_0.5": {},
    }
    scales = (0.5,) if fast else (1.0, 0.5)
    for preset in PRESETS:
        for scale in scales:
            cameras = preset_cameras(preset, scale)
            seconds, cpu, renders = _frame_seconds(world, cameras, 0.5, workers)
            result["s_per_frame"][f"{preset}@{scale}"] = round(seconds, 3)
            result["cpu_s_per_frame"][f"{preset}@{scale}"] = round(cpu, 3)
            if scale == 0.5 and not fast:
                result["cross_view_worst_pair_both_ok_scale_0.5"][preset] = round(
                    _worst_pair(world, cameras, 0.5, renders), 4)
    result["targets_s"] = {f"{p}@{s}": v for (p, s), v in TARGETS_S.items()}
    result["meets_targets"] = all(
        result["s_per_frame"][f"{p}@{s}"] <= v for (p, s), v in TARGETS_S.items() if f"{p}@{s}" in result["s_per_frame"]
    )
    return result
