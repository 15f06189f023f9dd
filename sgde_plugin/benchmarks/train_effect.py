"""`sgde bench train-effect`: does the depth prior help a depth network? Three arms, one budget.

Supervised training of the reference R18 depth net on a nuScenes-like synthetic sequence (six
cameras), evaluated on held-out frames further down the street:

- baseline:          RGB only;
- + input:           RGB + prior channel (same initial weights, first conv widened);
- + input & L1:      as + input, plus lambda * L1(D, D_p) with lambda = 0.005.

Defaults (about 13 minutes on two idle cores): 64x112 network input (frames rendered at 256x448,
where the prior pipeline matches), 24 training frames and 12 held-out frames per seed, three seeds
(a seed changes the world and the initial weights), 500 steps of one frame (six cameras) per arm,
Adam lr 4e-4, LiDAR-like sparse supervision, evaluation on dense ground truth <= 80 m, and the
prior arms with the optional validity channel. No pretrained weights (offline).

Data enter through one function, `load_sequence`, returning a `RigSequence` (images, ground
truth, LiDAR-like training depth, prior and its validity, per camera per frame, plus the cameras
for Dep Con). Scenes come from `sgde_plugin.synth`; priors from the project's prior pipeline
(`sgde_plugin.stereo`, SGBM with true extrinsics), or on request from the ground truth restricted
to the true overlap of adjacent cameras with stereo-like noise. The output says which was used.

Each arm also reports the downstream effect on a VoxFormer-style stage 1: occupancy IoU / precision /
recall of its depth against the exact occupancy of the test frames, on the Occ3D-nuScenes grid and on
VoxFormer's grid (`occ_<grid>_<metric>`, see `benchmarks.occupancy`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from ..cameras import Camera
from ..metrics import depth_metrics
from ..nn import DepthNet
from ..nn.sequence import RigSequence, lidar_pattern, overlap_masks
from ..nn.train import MAX_DEPTH_EVAL, SUPERVISED_ARMS, arm_nets, evaluate, train_arm
from ..rig import Frame, Rig, ring_pairs
from ..stereo.pipeline import PriorBuilder, PriorConfig
from ..synth.presets import preset_cameras
from ..synth.render import render
from ..synth.world import build_world
from .occupancy import occupancy_eval, occupancy_table

# --- cameras ------------------------------------------------------------------------------------

def rig_cameras(width: int, height: int) -> list[Camera]:
    """The nuScenes preset of `sgde_plugin.synth` resized to (width, height)."""
    return [c.resized(width, height) for c in preset_cameras("nuscenes")]


# --- priors and LiDAR-like supervision ----------------------------------------------------------

def noisy_overlap_prior(
    depth: np.ndarray, overlap: np.ndarray, rng: np.random.Generator,
    stereo_focal_px: float = 633.0, baseline_m: float = 0.6, disparity_sigma_px: float = 0.5,
    outlier_rate: float = 0.03, dropout: float = 0.15, max_depth: float = MAX_DEPTH_EVAL,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth restricted to the overlap with stereo-like noise: depth error sigma_z =
    z^2 sigma_d / (f B) (f of half-resolution nuScenes matching, B of adjacent cameras), a few
    gross outliers, random holes; no prior beyond max_depth."""
    z = depth.astype(np.float64)
    valid = overlap & (z > 0) & (z <= max_depth) & (rng.random(z.shape) >= dropout)
    sigma = z * z * disparity_sigma_px / (stereo_focal_px * baseline_m)
    noisy = z + rng.normal(size=z.shape) * sigma
    outlier = rng.random(z.shape) < outlier_rate
    noisy = np.where(outlier, z * rng.uniform(0.5, 2.0, size=z.shape), noisy)
    valid &= noisy > 0.5
    return np.where(valid, noisy, 0.0).astype(np.float32), valid


def thin_hits(hits: np.ndarray, density: float, rng: np.random.Generator) -> np.ndarray:
    """Keep a random subset of the LiDAR pixels so that about ``density`` of all pixels remain."""
    keep = min(1.0, density / max(float(hits.mean()), 1e-12))
    return hits & (rng.random(hits.shape) < keep)


# --- the data entry point -----------------------------------------------------------------------

Shot = Callable[[Camera, int], tuple[np.ndarray, np.ndarray]]


def _renderer(seed: int, frame_step_s: float) -> Shot:
    """(camera, frame id) -> (RGB, depth) of the `sgde_plugin.synth` street of world ``seed``."""
    world = build_world(seed)

    def shot(cam: Camera, k: int) -> tuple[np.ndarray, np.ndarray]:
        t = k * frame_step_s
        return render(world, cam, world.ego_pose(t), t)

    return shot


def _pipeline_priors(cameras: list[Camera], images: np.ndarray) -> np.ndarray:
    """Priors [F,N,H,W] from the project's prior pipeline (SGBM on rectified adjacent pairs)."""
    names = tuple(c.name for c in cameras)
    rig = Rig(tuple(cameras), ring_pairs(names), (Frame("0", 0),), names)
    builder = PriorBuilder(rig, PriorConfig(scale=1.0))
    out = np.zeros(images.shape[:-1], np.float32)
    for k in range(images.shape[0]):
        maps = builder.build({c.name: images[k, i] for i, c in enumerate(cameras)})
        for i, c in enumerate(cameras):
            out[k, i] = maps[c.name].depth
    return out


def load_sequence(frame_ids: list[int], size: tuple[int, int], seed: int = 0, frame_step_s: float = 0.5,
                  prior: str = "pipeline", render_factor: int = 4,
                  supervision_density: float | None = None) -> RigSequence:
    """Frames `frame_ids` (time = id * frame_step_s) of a six-camera street at network size (H, W).

    Frames are rendered at ``render_factor`` times the network size (as a real cache is built at
    the camera's resolution and resampled to the network's); priors come from the project's prior
    pipeline run on those renders (``prior="pipeline"``, the default), or with
    ``prior="overlap-noise"`` from the ground truth restricted to the true overlap with stereo-like
    noise. Images are area-downsampled, depths (truth, prior) min-pooled, to the network size.
    ``supervision_density`` thins the LiDAR-like training depth to that fraction of pixels.
    """
    from ..cache.resample import resize_depth, resize_matrix, warp_image

    h, w = size
    rh, rw = render_factor * h, render_factor * w
    if prior not in ("pipeline", "overlap-noise"):
        raise ValueError(f"prior must be 'pipeline' or 'overlap-noise', got {prior!r}")
    render_cams = rig_cameras(rw, rh)
    cameras = [c.resized(w, h) for c in render_cams]
    shot = _renderer(seed, frame_step_s)
    n, frames = len(cameras), len(frame_ids)
    big_images = np.zeros((frames, n, rh, rw, 3), np.uint8)
    images = np.zeros((frames, n, h, w, 3), np.uint8)
    depth = np.zeros((frames, n, h, w), np.float32)
    shrink = resize_matrix((rh, rw), (h, w))
    for k, fid in enumerate(frame_ids):
        for i, cam in enumerate(render_cams):
            big_images[k, i], big_depth = shot(cam, fid)
            images[k, i] = warp_image(big_images[k, i], shrink, (h, w))
            depth[k, i] = resize_depth(big_depth, (h, w))[0]
    overlap = np.stack([overlap_masks(depth[k], cameras) for k in range(frames)])
    if prior == "pipeline":
        big_prior = _pipeline_priors(render_cams, big_images)
        prior_map = np.stack([np.stack([resize_depth(big_prior[k, i], (h, w))[0] for i in range(n)])
                              for k in range(frames)])
        prior_map[prior_map > MAX_DEPTH_EVAL] = 0
        valid = prior_map > 0
        prior_source = (f"prior pipeline: sgde_plugin.stereo PriorBuilder (SGBM, true extrinsics) on "
                        f"{rw}x{rh} renders, min-pooled to {w}x{h}")
    else:
        prior_map, valid = noisy_overlap_prior(depth, overlap, np.random.default_rng(seed))
        prior_source = ("ground truth restricted to the true overlap of adjacent cameras, with "
                        "stereo-like noise (sigma_z = z^2 * 0.5 px / (633 px * 0.6 m), 3% outliers, 15% holes)")
    hits = np.stack([np.stack([lidar_pattern(depth[k, i], cameras[i]) for i in range(n)]) for k in range(frames)])
    if supervision_density is not None:
        hits = thin_hits(hits, supervision_density, np.random.default_rng(seed + 7919))
    supervision = np.where(hits, depth, 0.0).astype(np.float32)
    return RigSequence(
        cameras=cameras, pairs=list(ring_pairs([c.name for c in cameras])), images=images, depth=depth,
        supervision=supervision, prior=prior_map.astype(np.float32), valid=valid, overlap=overlap,
        scene_source="sgde_plugin.synth procedural street (nuscenes preset)", prior_source=prior_source,
    )


ARMS = tuple(arm.name for arm in SUPERVISED_ARMS)


def run_seed(seed: int, size: tuple[int, int], steps: int, n_train: int, n_test: int, validity: bool,
             lr: float, log: Callable[[str], None], render_factor: int = 4,
             supervision_density: float | None = None,
             stem: str = "full") -> tuple[dict[str, dict], RigSequence, list[int]]:
    """One world and one initialisation (both from ``seed``): train and evaluate the three arms."""
    gap = 6  # held-out frames come after a gap further down the street (not rendered)
    frame_ids = list(range(n_train)) + list(range(n_train + gap, n_train + gap + n_test))
    t0 = time.perf_counter()
    seq = load_sequence(frame_ids, size, seed=seed, render_factor=render_factor,
                        supervision_density=supervision_density)
    train_idx, test_idx = list(range(n_train)), list(range(n_train, n_train + n_test))
    log(f"seed {seed} data: {len(frame_ids)} frames x {len(seq.cameras)} cameras at {size} "
        f"in {time.perf_counter() - t0:.0f} s")
    prior_quality = depth_metrics(seq.prior[test_idx], seq.depth[test_idx], mask=seq.valid[test_idx],
                                  max_depth=MAX_DEPTH_EVAL)
    torch.manual_seed(seed)
    init = DepthNet(use_prior=False, min_depth=0.5, max_depth=100.0, scales=(0, 1, 2, 3))
    nets = arm_nets(init, SUPERVISED_ARMS, validity=validity, prior_max_depth=MAX_DEPTH_EVAL, stem=stem)
    results: dict[str, dict] = {}
    for arm in SUPERVISED_ARMS:
        name = arm.name
        torch.manual_seed(seed)
        train_s = train_arm(nets[name], seq, train_idx, steps, seed, arm.prior_weight, lr=lr)
        res = evaluate(nets[name], seq, test_idx)
        res.update(occupancy_eval(nets[name], seq, test_idx))
        res["train_s"] = round(train_s, 1)
        res["prior_abs_rel"] = prior_quality["abs_rel"]
        if name == "baseline":
            res["pasted_abs_rel"] = evaluate(nets[name], seq, test_idx, paste_prior=True)["abs_rel"]
            res.update({f"pasted_{k}": v for k, v in occupancy_eval(nets[name], seq, test_idx, True).items()})
        results[name] = res
        log(f"seed {seed} {name}: abs_rel {res['abs_rel']:.4f} dep_con {res['dep_con']:.4f} ({train_s:.0f} s)")
    return results, seq, test_idx


def run(fast: bool = False, size: tuple[int, int] | None = None, steps: int | None = None,
        train_frames: int | None = None, test_frames: int | None = None, seeds: tuple[int, ...] | None = None,
        validity: bool = True, lr: float = 4e-4, log: Callable[[str], None] | None = None,
        render_factor: int = 4, supervision_density: float | None = None, stem: str = "full") -> dict:
    """Run the three arms for each seed and return per-seed and mean figures (see module docstring)."""
    log = log or (lambda _msg: None)
    size = size or ((48, 80) if fast else (64, 112))
    steps = steps or (30 if fast else 500)
    n_train = train_frames or (6 if fast else 24)
    n_test = test_frames or (2 if fast else 12)
    seeds = tuple(seeds) if seeds is not None else ((0,) if fast else (0, 1, 2))
    t0, cpu0 = time.perf_counter(), time.process_time()
    per_seed, seq, test_idx = {}, None, []
    for seed in seeds:
        per_seed[seed], seq, test_idx = run_seed(seed, size, steps, n_train, n_test, validity, lr, log,
                                                 render_factor, supervision_density, stem)
    mean = {arm: {m: float(np.mean([per_seed[s][arm][m] for s in seeds])) for m in per_seed[seeds[0]][arm]}
            for arm in ARMS}
    std = {arm: {m: float(np.std([per_seed[s][arm][m] for s in seeds])) for m in ("abs_rel", "dep_con")}
           for arm in ARMS}
    base, best = mean["baseline"], mean["+ input & L1"]
    abs_rel_change = 100.0 * (best["abs_rel"] - base["abs_rel"]) / base["abs_rel"]
    dep_con_change = 100.0 * (best["dep_con"] - base["dep_con"]) / base["dep_con"]

    def rounded(d: dict) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}

    return {
        "scene": seq.scene_source,
        "prior": seq.prior_source,
        "cameras": len(seq.cameras),
        "size_hw": list(size),
        "train_frames": n_train,
        "test_frames": n_test,
        "seeds": list(seeds),
        "steps_per_arm": steps,
        "batch": len(seq.cameras),
        "lr": lr,
        "validity_channel": validity,
        "stem": stem,
        "supervision": "LiDAR-like (32 beams from the roof, <= 70 m), evaluation on dense ground truth <= 80 m",
        "supervision_density": supervision_density,
        "render_factor": render_factor,
        "prior_pasted_note": "baseline.pasted_abs_rel: the baseline's prediction with the prior pasted in wherever "
                             "it is valid, i.e. what a purely local use of the prior can give",
        "init": "random (no pretrained weights available offline); per seed identical initial weights and data "
                "order for the three arms; a seed also changes the world",
        "overlap_fraction_test": round(float(seq.overlap[test_idx].mean()), 4),
        "prior_fraction_test": round(float(seq.valid[test_idx].mean()), 4),
        "arms": {arm: rounded(mean[arm]) for arm in ARMS},
        "arms_std": {arm: rounded(std[arm]) for arm in ARMS},
        "per_seed": {str(s): {arm: rounded(per_seed[s][arm]) for arm in ARMS} for s in seeds},
        "abs_rel_change_pct": round(abs_rel_change, 2),
        "dep_con_change_pct": round(dep_con_change, 2),
        "target_abs_rel_-10pct": bool(abs_rel_change <= -10.0),
        "target_dep_con_lower": bool(dep_con_change < 0.0),
        "total_s": round(time.perf_counter() - t0, 1),
        "total_cpu_s": round(time.process_time() - cpu0, 1),
        "torch_threads": torch.get_num_threads(),
    }


def table(result: dict) -> str:
    """Markdown table of the three arms (means over seeds)."""
    lines = ["| arm | Abs Rel | Sq Rel | RMSE | RMSE log | d<1.25 | Abs Rel overlap | Abs Rel outside | Dep Con |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["arms"].items():
        lines.append(f"| {name} | {r['abs_rel']:.3f} | {r['sq_rel']:.3f} | {r['rmse']:.3f} | {r['rmse_log']:.3f} | "
                     f"{r['a1']:.3f} | {r['abs_rel_overlap']:.3f} | {r['abs_rel_outside']:.3f} | {r['dep_con']:.3f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    import json
    import sys

    out = run(fast="--fast" in sys.argv, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(json.dumps(out, indent=2))
    print(table(out))
    print(occupancy_table(out["arms"]))
