"""Synthetic sequences: a preset rig driving down the street at 10 Hz, in memory or as an sgde-rig/1 folder.

`rig_true` carries the true extrinsics the images were rendered with; `rig` carries extrinsics
perturbed like a real data set's calibration: each camera's rotation is multiplied by a rotation
of exactly `pose_noise_deg` degrees about a random axis, and its position moved by exactly
`pose_noise_m` metres in a random direction (seeded).

Capture: `sync` renders every camera of a frame at the frame's time. `sequential` fires the cameras
in ring order over `sweep_ms` (nuScenes-like 50 ms: camera i of M at i * sweep / M after the frame's
time) while the ego moves on; each camera is rendered at its own time and ego pose, and both rig
files carry them as per-camera captures (`frames[].cameras`).
"""

from __future__ import annotations

import glob
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..geometry import make_transform, rodrigues
from ..io import write_depth_png, write_image
from ..progress import progress
from ..rig import CameraCapture, Frame, Rig, ring_pairs, write_rig_json
from .ego_body import body_mask
from .presets import preset_cameras, preset_ring, preset_world
from .random_rig import random_rig
from .render import render, rig_lod, torch_threads
from .world import MAX_FRAMES, World

FRAME_RATE_HZ = 10.0
CAPTURES = ("sync", "sequential")
SWEEP_MS = 50.0  # nuScenes: the six cameras fire over about 50 ms


@dataclass(frozen=True, eq=False)
class SynthSequence:
    """A rendered synthetic sequence: true and perturbed rigs, images and depths per frame and camera."""

    rig_true: Rig
    rig: Rig
    world: World
    images: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    depths: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    body_masks: dict[str, np.ndarray] = field(default_factory=dict)  # --ego-body: True where the body is


def frame_id(index: int) -> str:
    """Frame id of the index-th frame."""
    return f"{index:06d}"


def perturb_extrinsics(cameras: list[Camera], seed: int, noise_deg: float, noise_m: float) -> dict[str, np.ndarray]:
    """Per camera: sensor_to_ego rotated by exactly `noise_deg` about a random axis, moved by exactly `noise_m`."""
    rng = np.random.default_rng([int(seed), 0xCA11B])
    out = {}
    for cam in cameras:
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        R = rodrigues(axis * math.radians(noise_deg)) @ cam.sensor_to_ego[:3, :3]
        t = cam.sensor_to_ego[:3, 3] + direction * noise_m
        out[cam.name] = make_transform(R, t)
    return out


def _check(preset: str, frames: int, scale: float, pose_noise_deg: float, pose_noise_m: float,
           capture: str = "sync", sweep_ms: float = SWEEP_MS) -> None:
    preset_ring(preset)  # raises for an unknown preset
    if capture not in CAPTURES:
        raise ValueError(f"capture must be one of {', '.join(CAPTURES)}, got {capture!r}")
    if not 0 <= sweep_ms < 1e3 / FRAME_RATE_HZ:
        raise ValueError(f"sweep_ms must be in [0, {1e3 / FRAME_RATE_HZ:g}), got {sweep_ms}")
    if not 1 <= frames <= MAX_FRAMES:
        raise ValueError(f"frames must be in 1..{MAX_FRAMES}, got {frames}")
    if not 0 < scale <= 4:
        raise ValueError(f"scale must be in (0, 4], got {scale}")
    if pose_noise_deg < 0 or pose_noise_m < 0:
        raise ValueError("pose noise must be >= 0")


def _frame(index: int, world: World, ring: tuple[str, ...], capture: str, sweep_ms: float) -> Frame:
    """Frame `index` at 10 Hz; with sequential capture, camera i of M fires i * sweep / M later."""
    t_us = int(round(index * 1e6 / FRAME_RATE_HZ))
    captures = {}
    if capture == "sequential":
        for i, name in enumerate(ring[1:], start=1):
            ts = t_us + int(round(i * sweep_ms * 1e3 / len(ring)))
            captures[name] = CameraCapture(ts, world.ego_pose(ts * 1e-6))
    return Frame(frame_id(index), t_us, world.ego_pose(t_us * 1e-6), cameras=captures)


def _rigs(preset: str, frames: int, seed: int, scale: float, noise_deg: float, noise_m: float,
          world: World, capture: str = "sync", sweep_ms: float = SWEEP_MS) -> tuple[Rig, Rig]:
    cameras = preset_cameras(preset, scale, seed)
    ring = tuple(c.name for c in cameras)
    frame_list = tuple(_frame(i, world, ring, capture, sweep_ms) for i in range(frames))
    info = {"preset": preset, "seed": int(seed), "scale": float(scale), "frame_rate_hz": FRAME_RATE_HZ}
    if capture != "sync":
        info.update(capture=capture, sweep_ms=float(sweep_ms))
    if preset == "random":
        info["random_rig"] = random_rig(seed).summary()
    rig_true = Rig(tuple(cameras), ring_pairs(ring), frame_list, ring, extra={"synth": {**info, "extrinsics": "true"}})
    noisy = perturb_extrinsics(cameras, seed, noise_deg, noise_m)
    rig = rig_true.with_extrinsics(noisy).with_extra(
        synth={**info, "extrinsics": "perturbed", "pose_noise_deg": float(noise_deg), "pose_noise_m": float(noise_m)}
    )
    return rig_true, rig


def _body_masks(world: World, rig_true: Rig) -> dict[str, np.ndarray]:
    """True ego-body pixels of every camera (empty without a body)."""
    if world.ego_body is None:
        return {}
    return {c.name: body_mask(world.ego_body, c) for c in rig_true.cameras}


def default_workers() -> int:
    """Cameras rendered concurrently: one per core, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


def _render_frames(world: World, rig_true: Rig, supersample: int,
                   sink: Callable[[str, str, np.ndarray, np.ndarray], None], show_progress: bool | None,
                   workers: int) -> None:
    """Render every (frame, camera) with the true rig, `workers` at a time; `sink` receives them in order."""
    jobs = [(fr, cam) for fr in rig_true.frames for cam in rig_true.cameras]

    lod = rig_lod(list(rig_true.cameras))

    def one(job: tuple[Frame, Camera]) -> tuple[np.ndarray, np.ndarray]:
        fr, cam = job
        cap = rig_true.capture(fr, cam.name)  # the camera's own time and ego pose (sequential capture)
        return render(world, cam, cap.ego_to_world, cap.timestamp_us * 1e-6, supersample, threads=1, lod=lod)

    with torch_threads(1), ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = pool.map(one, jobs)
        for (fr, cam), (rgb, depth) in progress(zip(jobs, results), desc="synth", total=len(jobs),
                                                enabled=show_progress):
            sink(fr.id, cam.name, rgb, depth)


def synth_sequence(preset: str, frames: int, seed: int = 0, scale: float = 1.0, pose_noise_deg: float = 1.0,
                   pose_noise_m: float = 0.05, supersample: int = 1, workers: int | None = None,
                   capture: str = "sync", sweep_ms: float = SWEEP_MS, ego_body: bool = False) -> SynthSequence:
    """Render a sequence in memory (images and depths keyed by frame id, then camera name).

    `ego_body`: draw the car's glossy body into every camera (`synth.ego_body`); `body_masks` then
    holds each camera's true body pixels.
    """
    _check(preset, frames, scale, pose_noise_deg, pose_noise_m, capture, sweep_ms)
    world = preset_world(preset, seed, ego_body)
    rig_true, rig = _rigs(preset, frames, seed, scale, pose_noise_deg, pose_noise_m, world, capture, sweep_ms)
    seq = SynthSequence(rig_true, rig, world, body_masks=_body_masks(world, rig_true))

    def keep(fid: str, cam: str, rgb: np.ndarray, depth: np.ndarray) -> None:
        seq.images.setdefault(fid, {})[cam] = rgb
        seq.depths.setdefault(fid, {})[cam] = depth

    _render_frames(world, rig_true, supersample, keep, False, workers or default_workers())
    return seq


def _remove_dead_temporaries(out: Path) -> None:
    """Remove the temporary siblings `write_synth` left for `out` when it was killed (kill -9, power loss): those
    whose process (the number in the name) no longer runs. A live writer's folder is left alone."""
    prefix = f".{out.name}."
    for tmp in out.parent.glob(f"{glob.escape(prefix)}*.tmp"):
        pid = tmp.name[len(prefix):].split(".", 1)[0]
        if tmp.is_dir() and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(tmp, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether a process with this number runs (or runs under another user)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def write_synth(preset: str, frames: int, out_dir: str | Path, seed: int = 0, scale: float = 1.0,
                pose_noise_deg: float = 1.0, pose_noise_m: float = 0.05, supersample: int = 1,
                show_progress: bool | None = None, workers: int | None = None, capture: str = "sync",
                sweep_ms: float = SWEEP_MS, ego_body: bool = False) -> Path:
    """Render a sequence into an sgde-rig/1 folder (built in a temporary sibling, renamed at the end).

    `out_dir` must not exist or be an empty folder. Writes rig.json (perturbed extrinsics),
    rig_true.json (true extrinsics), frames/<id>/<camera>.png and depth/<id>/<camera>.png.
    """
    _check(preset, frames, scale, pose_noise_deg, pose_noise_m, capture, sweep_ms)
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} exists and is not an empty folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    world = preset_world(preset, seed, ego_body)
    rig_true, rig = _rigs(preset, frames, seed, scale, pose_noise_deg, pose_noise_m, world, capture, sweep_ms)
    _remove_dead_temporaries(out)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}.", suffix=".tmp", dir=out.parent))
    try:
        def save(fid: str, cam: str, rgb: np.ndarray, depth: np.ndarray) -> None:
            write_image(tmp / "frames" / fid / f"{cam}.png", rgb)
            write_depth_png(tmp / "depth" / fid / f"{cam}.png", depth)

        for fr in rig_true.frames:
            (tmp / "frames" / fr.id).mkdir(parents=True, exist_ok=True)
            (tmp / "depth" / fr.id).mkdir(parents=True, exist_ok=True)
        _render_frames(world, rig_true, supersample, save, show_progress, workers or default_workers())
        for cam, body in _body_masks(world, rig_true).items():  # the truth, not masks/: those are estimated
            write_image(tmp / "masks_true" / f"{cam}.png", np.where(body, 0, 255).astype(np.uint8))
        write_rig_json(rig, tmp / "rig.json")
        write_rig_json(rig_true, tmp / "rig_true.json")
        os.chmod(tmp, 0o755)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
