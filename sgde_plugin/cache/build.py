"""Building a prior cache: resumable, in parallel processes or as Ray actors, all writing one store.

`build_cache(rig, out, config)` computes the prior of every frame that the cache does not hold
yet and writes it frame by frame. Each worker computes and writes whole frames itself (so a Ray
cluster writes straight into a shared store); a frame counts as done only once its done marker
is written after its data, so a build killed at any moment restarts where it stopped and ends
with the same content as an uninterrupted one.

The computation is a picklable callable `compute(frame_id) -> {camera: (depth, confidence)}`;
the default, `PriorCompute`, runs the stereo `PriorBuilder` on the rig's images. Each worker uses
one thread for OpenCV and torch, so N workers use N cores.
"""

from __future__ import annotations

import collections
import multiprocessing
import os
import re
import signal
import sys
import time
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ..errors import InputError
from ..progress import progress
from ..rig import Rig, load_frame_images
from ..stereo.config import PriorConfig
from ..stereo.matchers import Matcher
from ..stereo.pipeline import PriorBuilder
from .backends import Location, location_name
from .creation import prepare_scene, remove_partial_files
from .fingerprints import ConfigLike, config_document, fingerprint_parts
from .lock import writer_lock
from .writer import SceneWriter

Compute = Callable[[str], Mapping[str, tuple[np.ndarray, np.ndarray | None]]]
ENGINES = ("local", "ray")


class PriorCompute:
    """The default compute: load a frame's images (and the rig's masks) and run PriorBuilder."""

    def __init__(self, rig: Rig, config: ConfigLike, matcher: Matcher | None = None):
        """`matcher`: one `config.make_matcher()` already made, used by the first builder in this process (worker
        processes make their own)."""
        self.rig = rig
        self.config = config
        self._matcher = matcher
        self._builder: PriorBuilder | None = None
        self._masks: dict[str, np.ndarray] | None = None
        self.last_warning: str | None = None  # the builder's note when the last frame's prior came out empty

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_builder": None, "_masks": None, "_matcher": None}

    def __call__(self, frame_id: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Priors of all cameras of one frame."""
        if self._builder is None:
            self._builder = PriorBuilder(self.rig, self.config, matcher=self._matcher)
            self._matcher = None
            masks = {c: self.rig.load_mask(c) for c in self.rig.camera_names}
            self._masks = {c: m for c, m in masks.items() if m is not None} or None
        maps = self._builder.build(load_frame_images(self.rig, frame_id), self._masks, frame=frame_id)
        self.last_warning = self._builder.last_warning
        return {cam: (m.depth, m.confidence) for cam, m in maps.items()}


@dataclass
class BuildReport:
    """What a build did."""

    location: str
    scene: str
    fingerprint: str
    frames_total: int
    frames_built: int
    frames_already_done: int
    valid_pixels: int
    seconds: float
    workers: int
    engine: str
    frame_seconds: list[float] = field(default_factory=list)  # when each built frame was done, from start
    warnings: list[tuple[str, str]] = field(default_factory=list)  # (frame id, why its prior is empty)
    frames_repaired: dict[str, str] = field(default_factory=dict)  # damaged frames rebuilt: {frame id: problem}
    locked: bool = False  # whether the cache's writer lock was held (local folders)

    def steady_rate(self) -> float:
        """Frames per second once every worker has finished its first frame (start-up excluded)."""
        t = sorted(self.frame_seconds)
        k = max(1, self.workers)
        if len(t) <= k:
            return len(t) / self.seconds if self.seconds > 0 else 0.0
        return (len(t) - k) / max(t[-1] - t[k - 1], 1e-9)

    def line(self) -> str:
        """One-line summary for the command line."""
        rate = self.frames_built / self.seconds if self.seconds > 0 else 0.0
        return (
            f"{self.location} [{self.scene}]: {self.frames_built} frames built, {self.frames_already_done} already "
            f"there, {self.frames_total} in scene; {self.seconds:.1f} s ({rate:.2f} frames/s, {self.workers} "
            f"{self.engine} workers); fingerprint {self.fingerprint}{self.repair_text()}"
        )

    def repair_text(self) -> str:
        """'; N damaged frames rebuilt: id (problem), ...' or '' when none was."""
        if not self.frames_repaired:
            return ""
        shown = ", ".join(f"{fid} ({why})" for fid, why in list(self.frames_repaired.items())[:10])
        more = f", +{len(self.frames_repaired) - 10} more" if len(self.frames_repaired) > 10 else ""
        return f"; {len(self.frames_repaired)} damaged frame(s) rebuilt: {shown}{more}"


def sanitize_scene_name(name: str) -> str:
    """A name made usable as a zarr group name (letters, digits, '.', '_', '-')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).lstrip("._") or "scene"


def default_scene_name(rig: Rig) -> str:
    """The rig's scene name: rig.json's 'scene' key, else its folder's name, else 'scene'."""
    name = rig.extra.get("scene") if isinstance(getattr(rig, "extra", None), Mapping) else None
    if not isinstance(name, str) or not name:
        name = Path(rig.root).resolve().name if getattr(rig, "root", None) is not None else "scene"
    return sanitize_scene_name(name)


def limit_threads(n: int, torch_n: int | None = None) -> dict[str, int]:
    """Set OpenCV's thread count to n and torch's to torch_n (default n); returns the previous values."""
    previous = {"cv2": cv2.getNumThreads(), "torch": torch.get_num_threads()}
    cv2.setNumThreads(n)
    torch.set_num_threads(n if torch_n is None else torch_n)
    return previous


def _restore_threads(previous: Mapping[str, int]) -> None:
    if "cv2" in previous:
        cv2.setNumThreads(previous["cv2"])
    if "torch" in previous:
        torch.set_num_threads(previous["torch"])


class StrictWarningError(Exception):
    """A frame's prior came out empty and the build was asked to be strict (`sgde prior --strict`, exit 3)."""


def run_frame(compute: Compute, writer: SceneWriter, index: int, frame_id: str) -> tuple:
    """Compute and write one frame: (index, valid pixels, error as (file, key, problem) or None, warning or None).

    The warning is the compute's `last_warning` (PriorCompute: why the frame's prior is empty)."""
    try:
        maps = compute(frame_id)
        return index, writer.write_frame(index, maps), None, getattr(compute, "last_warning", None)
    except InputError as exc:  # passed back as a tuple: InputError does not pickle
        return index, 0, (exc.file, exc.key, exc.problem), None
    except OSError as exc:  # unreadable input, a full disk, a read-only cache: named, not a crash
        where = exc.filename if getattr(exc, "filename", None) else location_name(writer.location)
        return index, 0, (str(where), f"frame {frame_id}", exc.strerror or str(exc)), None


# --- local processes ----------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(compute: Compute, writer: SceneWriter, torch_n: int = 1) -> None:
    from .lifetime import die_with_parent  # here: importing it arms the kill switch inside a fork server

    die_with_parent()  # the fork server; it dies with the main process in turn
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the main process stops the workers
    limit_threads(1, torch_n)
    _WORKER["compute"], _WORKER["writer"] = compute, writer


def _worker_frame(index: int, frame_id: str) -> tuple:
    return run_frame(_WORKER["compute"], _WORKER["writer"], index, frame_id)


def _mp_context() -> multiprocessing.context.BaseContext:
    # a fork server (single-threaded, unlike this process with zarr's I/O thread) that has imported
    # the heavy modules this process already uses, so each worker starts by a cheap fork
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" in methods:
        ctx = multiprocessing.get_context("forkserver")
        heavy = ("torch", "cv2", "sgde_plugin.rig", "sgde_plugin.stereo.pipeline")
        preload = ["sgde_plugin.cache.lifetime", "sgde_plugin.cache.build"]
        ctx.set_forkserver_preload([*preload, *(m for m in heavy if m in sys.modules)])
        return ctx
    return multiprocessing.get_context("spawn")


def _run_local(tasks: list[tuple[int, str]], compute: Compute, writer: SceneWriter, workers: int, on_done) -> None:
    torch_n = torch_threads_per_worker(workers)  # a learned matcher parallelises inside torch
    if workers <= 1:
        previous = limit_threads(1, torch_n)
        try:
            for index, fid in tasks:
                on_done(run_frame(compute, writer, index, fid))
        finally:
            _restore_threads(previous)
        return
    pool = ProcessPoolExecutor(workers, mp_context=_mp_context(), initializer=_init_worker,
                               initargs=(compute, writer, torch_n))
    with pool as ex:
        queue = collections.deque(tasks)
        running = set()
        try:
            while queue or running:
                while queue and len(running) < 2 * workers:
                    running.add(ex.submit(_worker_frame, *queue.popleft()))
                finished, running = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    on_done(fut.result())
        except BaseException:
            # interrupted (Ctrl-C, SIGTERM) or failed: stop at once; a killed frame write is harmless,
            # its done marker comes last
            for fut in running:
                fut.cancel()
            for proc in list(getattr(ex, "_processes", {}).values()):
                proc.terminate()
            ex.shutdown(wait=False, cancel_futures=True)
            raise


# --- Ray ----------------------------------------------------------------------------------
class RayFrameWorker:
    """A Ray actor body: holds one compute (built once) and a writer, processes frames."""

    def __init__(self, compute: Compute, writer: SceneWriter):
        limit_threads(1)
        self.compute, self.writer = compute, writer

    def run(self, index: int, frame_id: str) -> tuple:
        """Compute and write one frame."""
        return run_frame(self.compute, self.writer, index, frame_id)


def _run_ray(
    tasks: list[tuple[int, str]], compute: Compute, writer: SceneWriter, workers: int, address: str | None, on_done
) -> int:
    try:
        import ray
    except ImportError:
        raise InputError(None, "--engine ray", "ray is not installed (pip install 'sgde-plugin[ray]')") from None
    own = not ray.is_initialized()
    if own:
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=max(1, workers), **kwargs)
    try:
        if address and workers <= 0:
            workers = int(ray.cluster_resources().get("CPU", 1))
        workers = max(1, min(workers, len(tasks)))
        actor_cls = ray.remote(num_cpus=1)(RayFrameWorker)
        actors = [actor_cls.remote(compute, writer) for _ in range(workers)]
        queue = collections.deque(tasks)
        running: dict[Any, Any] = {}
        for actor in actors:
            for _ in range(2):
                if queue:
                    running[actor.run.remote(*queue.popleft())] = actor
        while running:
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                actor = running.pop(ref)
                on_done(ray.get(ref))
                if queue:
                    running[actor.run.remote(*queue.popleft())] = actor
        return workers
    finally:
        if own:
            ray.shutdown()


# --- the build ----------------------------------------------------------------------------
def _note_warning(
    frame_id: str, text: str, warnings: list[tuple[str, str]], on_warning: Callable[[str, str], None] | None,
    strict: bool,
) -> None:
    """Record a frame's warning, tell the caller, and stop the build when strict."""
    warnings.append((frame_id, text))
    if on_warning is not None:
        on_warning(frame_id, text)
    if strict:
        raise StrictWarningError(f"frame {frame_id}: {text}")


def _learned_matcher(config: ConfigLike) -> Matcher | None:
    """A learned matcher of `config`, loaded now (so a file that does not load is refused before the cache exists);
    None for SGBM or the plane sweep. A build in this process uses it; worker processes load their own."""
    return config.make_matcher() if isinstance(config, PriorConfig) and config.learned else None


def build_cache(
    rig: Rig,
    out: Location,
    config: ConfigLike = None,
    workers: int = 1,
    engine: str = "local",
    *,
    scene: str | None = None,
    compute: Compute | None = None,
    algo_version: str | None = None,
    ray_address: str | None = None,
    storage_options: Mapping[str, Any] | None = None,
    show_progress: bool | None = None,
    on_warning: Callable[[str, str], None] | None = None,
    strict: bool = False,
    repair: bool = False,
    wait_s: float = 0.0,
) -> BuildReport:
    """Build (or resume) the priors of every frame of `rig` into the cache `out` (folder or fsspec
    URL). Refuses (InputError) a cache built with another calibration or configuration, and a cache
    another build is writing (after waiting up to `wait_s` s for its writer lock). Damaged frames are
    rebuilt: those with a missing shard always, those with any unreadable chunk with `repair=True`.
    A frame whose prior comes out empty goes to `on_warning(frame_id, text)` and the report's
    `warnings`; `strict` stops there.

    With workers > 1 the frames run in processes started by a fork server, which imports the calling
    script's main module: call it from a script under `if __name__ == "__main__":`."""
    if engine not in ENGINES:
        raise InputError(None, "--engine", f"unknown engine {engine!r} (choose from {', '.join(ENGINES)})")
    if config is None and compute is None:
        config = PriorConfig()
    if config is None:
        config = {}
    out = str(out) if isinstance(out, Path) else out
    scene = scene or default_scene_name(rig)
    parts = dict(fingerprint_parts(rig, config, algo_version))
    parts["config_document"] = config_document(config, algo_version)
    matcher = _learned_matcher(config) if compute is None else None  # a file that does not load: no cache made
    start = time.perf_counter()
    with writer_lock(out, wait_s) as locked:
        try:
            plan = prepare_scene(out, scene, rig, parts, storage_options, repair=repair, locked=locked)
            remove_partial_files(out, scene)
        except OSError as exc:  # a read-only file system, a full disk, no permission
            raise InputError(location_name(out), None, f"cannot write ({exc.strerror or exc})") from None
        if compute is None:
            compute = PriorCompute(rig, config, matcher if engine == "local" and int(workers) <= 1 else None)
        writer = SceneWriter(out, scene, storage_options, expect=parts["fingerprint"])
        tasks = [(i, plan.frame_ids[i]) for i in plan.pending]
        workers = max(1, int(workers)) if engine == "local" or not ray_address else int(workers)
        bar = progress(range(len(tasks)), desc=f"priors {scene}", total=len(tasks), enabled=show_progress)
        run = _Run(start, bar, plan.frame_ids, on_warning, strict)
        used = 0
        try:
            if tasks and engine == "ray":
                used = _run_ray(tasks, compute, writer, workers, ray_address, run.on_done)
            elif tasks:
                used = max(1, min(workers, len(tasks)))
                _run_local(tasks, compute, writer, used, run.on_done)
        finally:
            run.bar.close()
    return BuildReport(
        location=location_name(out), scene=scene, fingerprint=parts["fingerprint"],
        frames_total=len(plan.frame_ids), frames_built=run.built, frames_already_done=plan.already_done,
        valid_pixels=run.pixels, seconds=time.perf_counter() - start, workers=used, engine=engine,
        frame_seconds=run.stamps, warnings=run.warnings, frames_repaired=dict(plan.damaged), locked=bool(locked),
    )


class _Run:
    """Progress of one build: frames built, pixels, completion times, warnings; raises a worker's input error."""

    def __init__(self, start: float, bar: tqdm, frame_ids: list[str],
                 on_warning: Callable[[str, str], None] | None, strict: bool):
        self.start, self.bar, self.frame_ids = start, bar, frame_ids
        self.on_warning, self.strict = on_warning, strict
        self.built, self.pixels = 0, 0
        self.stamps: list[float] = []
        self.warnings: list[tuple[str, str]] = []

    def on_done(self, result: tuple) -> None:
        """Account one finished frame."""
        index, count, error, warning = result
        if error is not None:
            raise InputError(*error)
        if warning:
            _note_warning(self.frame_ids[index], warning, self.warnings, self.on_warning, self.strict)
        self.built += 1
        self.pixels += count
        self.stamps.append(time.perf_counter() - self.start)
        self.bar.update(1)


def usable_cpus() -> int:
    """The CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def available_memory() -> int | None:
    """Bytes of memory available to new processes (MemAvailable), None where unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


# peak memory of one worker running a learned matcher (RAFT-Stereo, six-camera frame at scale 0.5: 1.1-1.8 GB)
LEARNED_WORKER_BYTES = 2 * 1024**3


def default_workers(config: ConfigLike = None) -> int:
    """Worker processes by default: one per CPU; a learned matcher: as many as memory allows (2 GiB each),
    and one on a GPU (torch then uses the CPUs inside that worker)."""
    cpus = usable_cpus()
    if not getattr(config, "learned", False):  # None or a fingerprint mapping: SGBM
        return cpus
    if config.matcher.device != "cpu":  # a PriorConfig
        return 1
    memory = available_memory()
    return cpus if memory is None else max(1, min(cpus, memory // LEARNED_WORKER_BYTES))


def torch_threads_per_worker(workers: int) -> int:
    """Torch threads per worker process: OMP_NUM_THREADS when set, else the idle CPUs shared out (one worker
    on an idle machine gets them all; on a busy one, 1: OpenMP threads that wait for a core run ~10x slower)."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    cpus = usable_cpus()
    idle = cpus - round(os.getloadavg()[0]) if hasattr(os, "getloadavg") else cpus
    return max(1, min(cpus // max(1, workers), idle))


__all__ = [
    "BuildReport",
    "ENGINES",
    "PriorCompute",
    "RayFrameWorker",
    "build_cache",
    "default_scene_name",
    "default_workers",
    "StrictWarningError",
    "available_memory",
    "torch_threads_per_worker",
    "usable_cpus",
    "sanitize_scene_name",
    "limit_threads",
    "run_frame",
]
