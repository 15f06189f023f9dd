"""`sgde bench calibrate`: GLC self-calibration on the synthetic rigs, speed, accuracy and the ablation.

1. Speed and accuracy: `nuscenes`, T = 7 frames, scale 0.5, default noise (1 deg, 5 cm per camera),
   seed 0 (what `sgde synth --preset nuscenes --frames 7 --scale 0.5` renders). Seconds of `glc`
   split into features, matching (incl. overlap prediction), RANSAC and adjustment (target total
   <= 30 s); adjacent relative-pose errors against the true rig (targets: rotation median <= 0.05
   deg, max <= 0.1 deg, translation <= 2 cm).
2. Prior quality, the paper's "effect of pose optimization" table: for `nuscenes` and `urban-fisheye`,
   the depth prior (PriorBuilder, default PriorConfig) of every frame of the window built with the
   extrinsics of each method (none, pairwise, wo-glc, glc) and with the true ones, evaluated against
   the rendered ground truth: Abs Rel, Sq Rel, RMSE, delta < 1.25, coverage. Target: glc Abs Rel
   within 1.2 x the true rig's on nuscenes.

3. Accuracy on rigs it was not developed on (`accuracy()`, `sgde bench calibrate --peer colmap [--scale F]`):
   the presets (nuscenes also with sequential capture) and the random rigs of seeds 0-9, 7 frames at scale
   0.5 (`--scale 1` renders each rig at its own size), default noise: GLC from the noisy start and from the
   exact extrinsics, and with `peer="colmap"`
   COLMAP's rig bundle adjustment (benchmarks/colmap_peer.py) on the same images from the same noisy
   start; adjacent relative-pose errors against the truth. Targets: median rotation <= 0.02 deg, max
   <= 0.05 deg, translation <= 2 cm, every window accepted where the ring is connected (for the random
   rigs `ring_truth`: which pairs the rendered world lets link, benchmarks/ring_truth.py).

Rendering is not timed. The machine's load average is recorded: wall times on a shared machine depend
on it. `fast`: only the speed and pose accuracy of part 1 (no prior, no ablation).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..calib import MatchConfig, Timings, calibrate
from ..errors import InputError
from ..pairs import relative_pose_errors
from ..rig import Rig
from ..stereo.evaluate import evaluate_priors
from ..stereo.pipeline import PriorBuilder, PriorConfig
from ..synth.sequence import SynthSequence, synth_sequence
from ..tables import markdown_table
from .colmap_peer import calibrate_colmap, colmap_camera
from .ring_truth import ring_truth

METHOD_ORDER = ("none", "pairwise", "wo-glc", "glc")
ACCURACY_TARGETS = {"rotation_median_deg": 0.02, "rotation_max_deg": 0.05, "translation_max_m": 0.02}
ACCURACY_RIGS = (("nuscenes", 0, "sync"), ("nuscenes", 0, "sequential"), ("ddad", 0, "sync"),
                 ("urban-fisheye", 0, "sync"), *(("random", s, "sync") for s in range(10)))
TARGETS = {"seconds_total": 30.0, "rotation_median_deg": 0.05, "rotation_max_deg": 0.1, "translation_max_m": 0.02,
           "abs_rel_over_true": 1.2}
# render scale of the accuracy table: half of each rig's own size (the bench's time); 1.0 renders them at their size
ACCURACY_SCALE = 0.5
PRIOR_KEYS = ("abs_rel", "sq_rel", "rmse", "a1", "coverage")


def _pose_errors(rig: Rig, rig_true: Rig) -> dict[str, float]:
    rows = relative_pose_errors(rig, rig_true)
    rot = [r["rotation_deg"] for r in rows]
    trans = [r["translation_m"] for r in rows]
    return {"rotation_median_deg": float(np.median(rot)), "rotation_max_deg": float(max(rot)),
            "translation_median_m": float(np.median(trans)), "translation_max_m": float(max(trans))}


def _prior_metrics(rig: Rig, seq: SynthSequence) -> dict[str, float]:
    builder = PriorBuilder(rig, PriorConfig())
    priors = {fr.id: builder.build(seq.images[fr.id]) for fr in rig.frames}
    report = evaluate_priors(seq.rig_true, lambda f, c: priors[f][c].depth, lambda f, c: seq.depths[f][c])
    return {k: float(report["overall"][k]) for k in PRIOR_KEYS}


def _ablation(preset: str, frames: int, scale: float) -> dict[str, Any]:
    """All methods on one rendered window, sharing the correspondences; prior metrics per method."""
    t0 = time.perf_counter()
    seq = synth_sequence(preset, frames, seed=0, scale=scale)
    render_s = time.perf_counter() - t0
    cache: dict = {}
    rows, details = [], {}
    for method in ("glc", "wo-glc", "pairwise", "none"):  # glc first: its timing includes the matching
        timings = Timings()
        t0 = time.perf_counter()
        out, block = calibrate(seq.rig, lambda f, c: seq.images[f][c], method=method, timings=timings,
                               match_cache=cache, show_progress=False)
        wall = time.perf_counter() - t0
        win = block["windows"][0]
        details[method] = {
            "accepted": win["accepted"], "rule": win["rule"], "reason": win["reason"],
            "iterations": win["iterations"], "wall_seconds": wall,
            "seconds": {k: round(v, 3) for k, v in timings.seconds.items()},
            "pairs": [{k: p[k] for k in ("a", "b", "inliers", "adjusted_correspondences", "rms_px",
                                         "used_in_adjustment")} for p in win["pairs"]],
            **_pose_errors(out, seq.rig_true),
        }
        details[method]["prior"] = _prior_metrics(out, seq)
    details["true"] = {"prior": _prior_metrics(seq.rig_true, seq)}
    for method in (*METHOD_ORDER, "true"):
        d = details[method]
        rows.append({"method": method, **{k: d["prior"][k] for k in PRIOR_KEYS},
                     "rot_max_deg": d.get("rotation_max_deg"), "trans_max_m": d.get("translation_max_m")})
    return {"preset": preset, "frames": frames, "scale": scale, "render_seconds": render_s, "rows": rows,
            "methods": details, "markdown": markdown_table(rows, digits=4)}


def _accuracy_row(preset: str, seed: int, capture: str, peer: str | None, glc: bool = True,
                  frames: int = 7, match_config: MatchConfig | None = None, scale: float = ACCURACY_SCALE
                  ) -> dict[str, Any]:
    """GLC from the noisy and from the exact start (and the peer from the noisy one) on one rig of `frames`
    frames rendered at `scale`, calibrated as one window (with `match_config`, default: the default settings)."""
    seq = synth_sequence(preset, frames, seed=seed, scale=scale, capture=capture)
    row: dict[str, Any] = {"rig": preset, "seed": seed, "capture": capture, "cameras": len(seq.rig.cameras),
                           "frames": frames, "scale": scale}
    for start, rig in (("noisy", seq.rig), ("exact", seq.rig_true)) if glc else ():
        t0 = time.perf_counter()
        out, block = calibrate(rig, lambda f, c: seq.images[f][c], show_progress=False, window=frames,
                               match_config=match_config)
        w = block["windows"][0]
        row[f"glc_{start}"] = {"accepted": w["accepted"], "rule": w["rule"], "partial": w["partial"],
                               "blocks": w["blocks"], "seconds": time.perf_counter() - t0,
                               "through_ring": [f"{p['a']}-{p['b']}" for p in w["pairs"]
                                                if p["status"] == "through ring"],
                               "same_camera_links": w["same_camera_links"], "links_because": w["links_because"],
                               "rotation_sigma_deg": [p["rotation_sigma_deg"] for p in w["pairs"]],
                               "rotation_deg": [r["rotation_deg"] for r in relative_pose_errors(out, seq.rig_true)],
                               **_pose_errors(out, seq.rig_true)}
    row["input"] = _pose_errors(seq.rig, seq.rig_true)
    if preset == "random":  # which pairs the world lets link (the truth, to judge the rejections)
        row["ring_truth"] = ring_truth(seq)
    skip = _peer_skip_reason(seq, capture) if peer == "colmap" else None
    if skip:
        row["colmap"] = {"skipped": skip}
    elif peer == "colmap":
        ids = [f.id for f in seq.rig.frames]
        ego = np.stack([f.ego_to_world for f in seq.rig.frames])
        t0 = time.perf_counter()
        ref = seq.rig.ring[0] if seq.rig.ring else seq.rig.camera_names[0]
        ext, facts = calibrate_colmap(list(seq.rig.cameras), ego, lambda t, c: seq.images[ids[t]][c], ref)
        row["colmap"] = {"seconds": time.perf_counter() - t0, **facts,
                         **_pose_errors(seq.rig.with_extrinsics(ext), seq.rig_true)}
    return row


def _peer_skip_reason(seq: SynthSequence, capture: str) -> str | None:
    """Why the COLMAP peer cannot run on this rig (None: it can)."""
    if capture != "sync":  # COLMAP's rig frame has one pose for all its images; other capture times do not fit
        return f"{capture} capture: the peer's rig model needs one pose per frame"
    for cam in seq.rig.cameras:
        try:
            colmap_camera(cam)
        except InputError as exc:
            return exc.problem
    return None


def random_rigs(seeds: Sequence[int]) -> tuple[tuple[str, int, str], ...]:
    """The `rigs` argument of `accuracy` for some random-rig seeds (0-9 are the report set, 10+ development)."""
    return tuple(("random", int(s), "sync") for s in seeds)


def accuracy(peer: str | None = None, rigs: Sequence[tuple[str, int, str]] = ACCURACY_RIGS,
             frames: int = 7, match_config: MatchConfig | None = None, scale: float = ACCURACY_SCALE
             ) -> dict[str, Any]:
    """GLC (and a peer) on the presets and the random rigs (`frames` frames rendered at `scale`, one window, GLC
    with `match_config`); the table rows and which targets hold."""
    rows = []
    for preset, seed, capture in rigs:
        row = _accuracy_row(preset, seed, capture, peer, frames=frames, match_config=match_config, scale=scale)
        for start in ("noisy", "exact"):
            g = row[f"glc_{start}"]
            g["meets_targets"] = all(g[k] <= v for k, v in ACCURACY_TARGETS.items())
        if "colmap" in row and "skipped" not in row["colmap"]:
            row["glc_better_than_peer"] = all(row["glc_noisy"][k] < row["colmap"][k] for k in ACCURACY_TARGETS)
        rows.append(row)
        print(json.dumps(row, default=str), flush=True)
    return {"targets": ACCURACY_TARGETS, "rows": rows, "peer": peer, "scale": scale}


def run(fast: bool = False, peer: str | None = None, scale: float = ACCURACY_SCALE) -> dict[str, Any]:
    """Speed and accuracy of glc on nuscenes (T = 7, scale 0.5), then the ablation on two presets; with a
    `peer` ("colmap") only the accuracy table of GLC and the peer on the presets and random rigs, rendered at
    `scale` (1.0: each rig's own size)."""
    if peer is not None:
        load = os.getloadavg()
        return {**accuracy(peer, scale=scale), "load_average": [load, os.getloadavg()],
                "command": f"sgde bench calibrate --peer {peer} --scale {scale:g} --json OUT.json"}

    load_before = os.getloadavg()
    if fast:
        seq = synth_sequence("nuscenes", 7, seed=0, scale=0.5)
        timings = Timings()
        t0 = time.perf_counter()
        out, block = calibrate(seq.rig, lambda f, c: seq.images[f][c], timings=timings, show_progress=False)
        return {
            "setting": "nuscenes, 7 frames, scale 0.5, seed 0, default noise, glc, sift",
            "seconds_total": time.perf_counter() - t0,
            "seconds": {k: round(v, 3) for k, v in timings.seconds.items()},
            "accepted": block["windows"][0]["accepted"],
            "rule": block["windows"][0]["rule"],
            "same_camera_links": block["windows"][0]["same_camera_links"],
            "inliers": [p["inliers"] for p in block["windows"][0]["pairs"]],
            **_pose_errors(out, seq.rig_true),
            "load_average": [load_before, os.getloadavg()],
        }

    nus = _ablation("nuscenes", 7, 0.5)
    fish = _ablation("urban-fisheye", 7, 0.5)
    glc = nus["methods"]["glc"]
    true_abs_rel = nus["methods"]["true"]["prior"]["abs_rel"]
    speed = {
        "setting": "nuscenes, 7 frames, scale 0.5, seed 0, default noise, glc, sift",
        "seconds_total": sum(glc["seconds"].values()),
        "seconds": glc["seconds"],
        "iterations": glc["iterations"],
        "accepted": glc["accepted"],
        **{k: glc[k] for k in ("rotation_median_deg", "rotation_max_deg", "translation_median_m",
                               "translation_max_m")},
        "prior_abs_rel_glc": glc["prior"]["abs_rel"],
        "prior_abs_rel_true": true_abs_rel,
        "abs_rel_over_true": glc["prior"]["abs_rel"] / max(true_abs_rel, 1e-12),
    }
    speed["meets_targets"] = {
        "seconds_total": speed["seconds_total"] <= TARGETS["seconds_total"],
        "rotation_median_deg": speed["rotation_median_deg"] <= TARGETS["rotation_median_deg"],
        "rotation_max_deg": speed["rotation_max_deg"] <= TARGETS["rotation_max_deg"],
        "translation_max_m": speed["translation_max_m"] <= TARGETS["translation_max_m"],
        "abs_rel_over_true": speed["abs_rel_over_true"] <= TARGETS["abs_rel_over_true"],
    }
    return {
        "targets": TARGETS,
        "speed": speed,
        "ablation": {"nuscenes": nus, "urban-fisheye": fish},
        "command": "sgde bench calibrate --json OUT.json",
        "load_average": [load_before, os.getloadavg()],
    }


if __name__ == "__main__":
    import json
    import sys

    result = run(fast="--fast" in sys.argv)
    print(json.dumps(result, indent=1, default=str))
    for name, table in result.get("ablation", {}).items():
        print(f"\n{name}\n{table['markdown']}")
