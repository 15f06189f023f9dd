"""Concurrent writers of one cache (issue #22, failure 1): two builds with different calibrations started
together through a barrier, many times; the cache never mixes them. Also: the writer lock refuses or
waits, the fingerprint is re-checked at every frame write, and a scene another live build is creating is
never deleted.

Runtime ~10 s on 2 cores (24 races of two 3-frame builds in threads, 1 in fork-server processes).
"""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest
import zarr
from cache_fixtures import ALGO, CONFIG, build, tiny_rig

from sgde_plugin.cache.fingerprints import fingerprint
from sgde_plugin.cache.inspection import verify_cache
from sgde_plugin.cache.lock import writer_lock
from sgde_plugin.cache.store import PriorCache, SceneWriter, encode_prior
from sgde_plugin.cache.synthetic import SyntheticPriorCompute
from sgde_plugin.errors import InputError

THREAD_RACES = 24
PROCESS_RACES = 1
FRAMES = 3
RIG_SHIFTS = {1: 0.0, 2: 0.1}  # two calibrations, told apart by their synthetic-prior seeds 1 and 2


def _race(out: str, seed: int, barrier, results: dict) -> None:
    rig = tiny_rig(FRAMES, shift_m=RIG_SHIFTS[seed])
    compute = SyntheticPriorCompute(rig, seed=seed, delay_s=0.01)
    barrier.wait()
    try:
        build(rig, out, scene="s", compute=compute)
        results[seed] = "ok"
    except InputError as exc:
        results[seed] = exc.line()


def _race_process(out: str, seed: int, barrier, queue) -> None:
    results: dict = {}
    _race(out, seed, barrier, results)
    queue.put((seed, results[seed]))


def _stored(rig, seed: int, frame_id: str, camera: str) -> np.ndarray:
    """The float32 depth a build with this seed stores for one camera image."""
    cam = rig.camera(camera)
    depth, conf = SyntheticPriorCompute(rig, seed=seed)(frame_id)[camera]
    return encode_prior(depth, conf, cam.height, cam.width)[0].astype(np.float32)


def _check_not_mixed(out: str, results: dict) -> int:
    """Assert the cache holds exactly one build's priors, labelled with its fingerprint; returns refusals."""
    rigs = {seed: tiny_rig(FRAMES, shift_m=shift) for seed, shift in RIG_SHIFTS.items()}
    by_fp = {fingerprint(rig, CONFIG, ALGO): seed for seed, rig in rigs.items()}
    assert "ok" in results.values(), results
    for line in results.values():
        assert line == "ok" or "another build is writing" in line or "refusing to mix" in line, line
    cache = PriorCache(out)
    seed = by_fp[cache.fingerprint]  # labelled with one of the two calibrations ...
    assert results[seed] == "ok"
    assert cache.frames() == [f"{i:06d}" for i in range(FRAMES)]
    for fid in cache.frames():  # ... and holding exactly that calibration's priors
        for cam in cache.cameras():
            np.testing.assert_array_equal(cache.get(fid, cam)[0], _stored(rigs[seed], seed, fid, cam))
    assert verify_cache(out)["ok"]
    return sum(v != "ok" for v in results.values())


def test_concurrent_builds_in_threads_never_mix_calibrations(tmp_path):
    refused = 0
    for race in range(THREAD_RACES):
        out, barrier, results = str(tmp_path / f"c{race}"), threading.Barrier(2), {}
        threads = [threading.Thread(target=_race, args=(out, seed, barrier, results)) for seed in RIG_SHIFTS]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        refused += _check_not_mixed(out, results)
    assert refused >= 1  # the builds did overlap: one met the other's writer lock


def test_concurrent_builds_in_processes_never_mix_calibrations(tmp_path):
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([__name__])  # children fork from a server that imported this module
    for race in range(PROCESS_RACES):
        out, barrier, queue = str(tmp_path / f"c{race}"), ctx.Barrier(2), ctx.Queue()
        procs = [ctx.Process(target=_race_process, args=(out, seed, barrier, queue)) for seed in RIG_SHIFTS]
        for p in procs:
            p.start()
        results = dict(queue.get(timeout=300) for _ in procs)
        for p in procs:
            p.join(60)
            assert p.exitcode == 0
        _check_not_mixed(out, results)


def test_second_writer_is_refused_with_one_line_or_waits(tmp_path):
    rig = tiny_rig(2)
    out = tmp_path / "c"
    with writer_lock(out):
        with pytest.raises(InputError) as info:
            build(rig, out, scene="s")
    assert "another build is writing this cache" in info.value.line()
    assert "\n" not in info.value.line()
    assert list(out.iterdir()) == []  # the refused build wrote nothing

    held = threading.Event()

    def hold() -> None:
        with writer_lock(out):
            held.set()
            threading.Event().wait(0.5)

    t = threading.Thread(target=hold)
    t.start()
    held.wait(10)
    report = build(rig, out, scene="s", wait_s=30)  # waits for the lock, then builds
    t.join()
    assert report.frames_built == 2 and report.locked


def test_every_frame_write_rechecks_the_fingerprint(tmp_path):
    rig = tiny_rig(2)
    out = tmp_path / "c"
    build(rig, out, scene="s", compute=SyntheticPriorCompute(rig, cameras=[]))  # a built, empty scene
    maps = SyntheticPriorCompute(rig)("000000")
    other = SceneWriter(str(out), "s", expect="0" * 20)
    with pytest.raises(InputError, match="s: fingerprint: changed to .* another build"):
        other.write_frame(0, maps)
    cache = PriorCache(out)
    assert not cache.get("000000", "A")[1].any()  # nothing was written by the refused writer
    mine = SceneWriter(str(out), "s", expect=cache.fingerprint)
    assert mine.write_frame(0, maps) == sum(int((d > 0).sum()) for d, _ in maps.values())


def test_a_scene_being_created_by_another_build_is_not_deleted(tmp_path):
    from sgde_plugin.cache.fingerprints import config_document, fingerprint_parts
    from sgde_plugin.cache.store import prepare_scene, scene_arrays

    out = tmp_path / "c"
    rig_a, rig_b = tiny_rig(2), tiny_rig(2, shift_m=0.1)
    parts_a = {**fingerprint_parts(rig_a, CONFIG, ALGO), "config_document": config_document(CONFIG, ALGO)}
    parts_b = {**fingerprint_parts(rig_b, CONFIG, ALGO), "config_document": config_document(CONFIG, ALGO)}
    prepare_scene(str(out), "s", rig_a, parts_a)
    # as seen while build A is still creating the scene
    zarr.open_group(str(out / "s"), mode="r+").attrs.update({"ready": False})
    with pytest.raises(InputError, match="being created by another build"):
        prepare_scene(str(out), "s", rig_b, parts_b)  # without the writer lock: refused, not deleted
    assert scene_arrays(str(out), "s")["attrs"]["fingerprint"] == parts_a["fingerprint"]
