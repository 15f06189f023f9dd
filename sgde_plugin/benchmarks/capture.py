"""`sgde bench capture`: the prior under sequential capture, with and without the per-camera poses.

The synthetic `nuscenes` rig is rendered twice with the same world and seed: `sync` (every camera at
the frame's time) and `sequential` (cameras in ring order over 50 ms while the car drives on, each
rendered at its own time and ego pose). Priors are built with the true extrinsics (no pose noise) and
scored against the rendered depth: sync; sequential with the per-camera poses (`PriorBuilder.build(...,
frame=...)`); sequential ignoring them (every camera placed at the frame's ego pose, as a reader that
keeps one ego pose per frame would). The overlap is always the true one, at each camera's capture. Unless
`--fast`, the same three arms on the `urban-fisheye` rig follow under "fisheye" (no target: its re-plans and
what a sequential sweep does to a 220-degree pair's geometry).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from typing import Any

from ..rig import Rig
from ..stereo.config import PriorConfig
from ..stereo.evaluate import PriorEvaluator
from ..stereo.pipeline import PriorBuilder
from ..synth.sequence import SynthSequence, synth_sequence

ARMS = ("sync", "sequential, per-camera poses", "sequential, frame pose only")


def _score(seq: SynthSequence, rig_builder: Rig, use_frames: bool, config: PriorConfig) -> dict[str, Any]:
    """Priors of every frame of `seq` built on `rig_builder`'s geometry, scored against seq's truth, and the
    builder's set-up and mean wall time per frame (with per-camera poses a frame re-plans its pairs when its
    capture geometry moved: how many did, what a re-plan cost, and the time per frame if every frame did, as on a
    car whose speed varies from frame to frame)."""
    t = time.perf_counter()
    builder = PriorBuilder(rig_builder, config)
    setup_s = time.perf_counter() - t
    evaluator = PriorEvaluator(seq.rig_true, config.geometry.max_depth)
    build_s, plans = 0.0, []
    for fid, images in seq.images.items():
        t = time.perf_counter()
        out = builder.build(images, frame=fid if use_frames else None)
        build_s += time.perf_counter() - t
        plans += [builder.last_timings["plan"]] if builder.last_timings["plan"] > 0 else []
        evaluator.add({c: m.depth for c, m in out.items()}, seq.depths[fid], frame=fid)
    overall = evaluator.result()["overall"]
    n = max(1, len(seq.images))
    per_plan = sum(plans) / len(plans) if plans else None
    return {**{k: overall[k] for k in ("abs_rel", "sq_rel", "rmse", "a1", "coverage", "n_prior")},
            "setup_seconds": round(setup_s, 3), "seconds_per_frame": round(build_s / n, 3),
            "replanned_frames": len(plans), "seconds_per_replan": None if per_plan is None else round(per_plan, 3),
            "seconds_per_frame_every_frame_replanned": None if per_plan is None else round(
                (build_s - sum(plans)) / n + per_plan, 3)}


def _arms(preset: str, frames: int, seed: int, sweep_ms: float, scale: float) -> dict[str, Any]:
    """One preset rendered synchronised and sequentially: the three arms and the per-camera-poses / sync ratio."""
    config = PriorConfig()
    kw = {"seed": seed, "scale": scale, "pose_noise_deg": 0.0, "pose_noise_m": 0.0}
    sync = synth_sequence(preset, frames, **kw)
    seq = synth_sequence(preset, frames, capture="sequential", sweep_ms=sweep_ms, **kw)
    no_captures = replace(seq.rig_true, frames=tuple(replace(f, cameras={}) for f in seq.rig_true.frames))
    arms = {
        ARMS[0]: _score(sync, sync.rig_true, True, config),
        ARMS[1]: _score(seq, seq.rig_true, True, config),
        ARMS[2]: _score(seq, no_captures, False, config),
    }
    ratio = arms[ARMS[1]]["abs_rel"] / arms[ARMS[0]]["abs_rel"]
    return {"preset": preset, "frames": frames, "seed": seed, "scale": scale, "sweep_ms": sweep_ms, "arms": arms,
            "abs_rel_per_camera_poses_over_sync": round(ratio, 3)}


def run(fast: bool = False, preset: str = "nuscenes", frames: int = 3, seed: int = 0, sweep_ms: float = 50.0,
        scale: float | None = None, fisheye: str | None = "urban-fisheye") -> dict[str, Any]:
    """The three arms' accuracy, coverage and time on `preset` (the target: per-camera poses within 10 % of sync)
    and, unless `fast`, on the `fisheye` preset (reported, no target); `fast`: 2 frames at half size."""
    t0 = time.perf_counter()
    scale = (0.5 if fast else 1.0) if scale is None else scale
    frames = 2 if fast else frames
    out = _arms(preset, frames, seed, sweep_ms, scale)
    out.update(target_ratio=1.10, met=bool(out["abs_rel_per_camera_poses_over_sync"] <= 1.10))
    if fisheye and not fast:  # a fisheye rig re-plans tiles of four 220-degree cameras: the costliest re-plan
        out["fisheye"] = _arms(fisheye, frames, seed, sweep_ms, scale)
    return {**out, "seconds": round(time.perf_counter() - t0, 1), "load_avg": [round(x, 2) for x in os.getloadavg()]}


__all__ = ["ARMS", "run"]
