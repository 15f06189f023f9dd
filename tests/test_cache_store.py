"""Prior cache store: round trips, fingerprints, resume, extension, fsspec, verify, info, workers.

Runtime ~12 s on 2 cores (most of it the 2-process build; +~8 s for the Ray build when ray is
installed).
"""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from cache_fixtures import ALGO, CONFIG, build, content, tiny_rig

from sgde_plugin.cache.fingerprints import fingerprint, fingerprint_parts
from sgde_plugin.cache.inspection import cache_info, verify_cache
from sgde_plugin.cache.reading import float16_to_float32
from sgde_plugin.cache.store import PriorCache, SceneWriter, prepare_scene, store_keys
from sgde_plugin.cache.synthetic import SyntheticPriorCompute
from sgde_plugin.cli import main as cli_main
from sgde_plugin.errors import InputError


def test_round_trip_matches_compute_within_float16(tmp_path):
    rig = tiny_rig(3)
    report = build(rig, tmp_path / "c")
    assert (report.frames_built, report.frames_already_done, report.frames_total) == (3, 0, 3)
    cache = PriorCache(tmp_path / "c")
    assert cache.frames() == ["000000", "000001", "000002"]
    assert cache.cameras() == ["A", "B", "C"]
    assert cache.fingerprint == fingerprint(rig, CONFIG, ALGO)
    compute = SyntheticPriorCompute(rig)
    for fid in cache.frames():
        expected = compute(fid)
        for cam in cache.cameras():
            d_ref, c_ref = expected[cam]
            depth, valid = cache.get(fid, cam)
            assert depth.dtype == np.float32 and valid.dtype == bool
            assert depth.shape == d_ref.shape  # camera C is cropped back from the padded array
            np.testing.assert_array_equal(valid, d_ref > 0)
            np.testing.assert_allclose(depth, d_ref, rtol=2.0**-11, atol=0)
            assert np.all(depth[~valid] == 0)
            conf = cache.get_confidence(fid, cam)
            np.testing.assert_allclose(conf, np.where(d_ref > 0, c_ref, 0), atol=0.5 / 255 + 1e-6)


def test_float16_reads_convert_every_bit_pattern_as_numpy_does():
    every = np.arange(1 << 16, dtype=np.uint16).view(np.float16)
    np.testing.assert_array_equal(float16_to_float32(every), every.astype(np.float32))  # NaNs compare equal here
    cropped = every.reshape(256, 256)[3:200:2, 5:100]  # a strided view, as a cropped camera is read
    out = float16_to_float32(cropped)
    assert out.dtype == np.float32 and out.shape == cropped.shape
    np.testing.assert_array_equal(out, cropped.astype(np.float32))


def test_resized_get_is_min_pooled(tmp_path):
    rig = tiny_rig(1)
    build(rig, tmp_path / "c")
    cache = PriorCache(tmp_path / "c")
    full, _ = cache.get("000000", "A")
    half, valid = cache.get("000000", "A", size=(20, 32))
    blocks = np.where(full > 0, full, np.inf).reshape(20, 2, 32, 2).min(axis=(1, 3))
    np.testing.assert_array_equal(half, np.where(np.isfinite(blocks), blocks, 0))
    np.testing.assert_array_equal(valid, np.isfinite(blocks))


def test_other_configuration_or_calibration_is_refused(tmp_path):
    rig = tiny_rig(2)
    out = tmp_path / "c"
    build(rig, out)
    with pytest.raises(InputError, match=r"other prior settings \(scale 0.5 -> 0.25\)"):
        build(rig, out, config={**CONFIG, "scale": 0.25})
    with pytest.raises(InputError, match="another calibration"):
        build(tiny_rig(2, shift_m=0.01), out)
    with pytest.raises(InputError, match="another calibration"):
        PriorCache(out, rig=tiny_rig(2, shift_m=0.01))
    with pytest.raises(InputError, match="other prior settings"):
        PriorCache(out, config={**CONFIG, "matcher": "x"}, algo_version=ALGO)
    with pytest.raises(InputError, match="algo_version 'test-1' -> 'test-2'"):
        PriorCache(out, config=CONFIG, algo_version="test-2")
    PriorCache(out, rig=rig, config=CONFIG, algo_version=ALGO)  # the right inputs open fine
    with pytest.raises(InputError, match="fingerprint"):
        PriorCache(out, expect="0" * 20)


def test_fingerprint_covers_calibration_and_config_not_frames(tmp_path):
    rig = tiny_rig(2)
    parts = fingerprint_parts(rig, CONFIG, ALGO)
    assert parts == fingerprint_parts(tiny_rig(5), CONFIG, ALGO)  # frames are content, not inputs
    moved = fingerprint_parts(tiny_rig(2, shift_m=1e-9), CONFIG, ALGO)
    assert moved["rig"] != parts["rig"] and moved["config"] == parts["config"]
    other = fingerprint_parts(rig, {**CONFIG, "scale": 0.25}, ALGO)
    assert other["rig"] == parts["rig"] and other["config"] != parts["config"]
    assert fingerprint_parts(rig, CONFIG, "test-2")["config"] != parts["config"]
    assert len({parts["fingerprint"], moved["fingerprint"], other["fingerprint"]}) == 3


def test_readers_see_only_finished_frames_and_resume_overwrites_leftovers(tmp_path):
    rig = tiny_rig(4)
    out = str(tmp_path / "c")
    parts = {**fingerprint_parts(rig, CONFIG, ALGO)}
    from sgde_plugin.cache.fingerprints import config_document

    parts["config_document"] = config_document(CONFIG, ALGO)
    plan = prepare_scene(out, "s", rig, parts)
    assert plan.pending == [0, 1, 2, 3]
    compute, writer = SyntheticPriorCompute(rig), SceneWriter(out, "s")
    for i in (0, 2):
        writer.write_frame(i, compute(f"{i:06d}"))
    # frame 1: a shard from an interrupted attempt (garbage) and a stray temporary file, no done marker
    shard = Path(out) / "s" / "depth" / "c" / "1" / "0" / "0" / "0"
    shard.parent.mkdir(parents=True, exist_ok=True)
    shard.write_bytes(b"half a shard")
    (shard.parent / "0.deadbeef.partial").write_bytes(b"x")
    cache = PriorCache(out)
    assert cache.frames() == ["000000", "000002"]
    assert cache.frames(include_pending=True) == ["000000", "000001", "000002", "000003"]
    with pytest.raises(KeyError, match="not built yet"):
        cache.get("000001", "A")
    report = build(rig, out, scene="s")
    assert (report.frames_built, report.frames_already_done) == (2, 2)
    assert not list(shard.parent.glob("*.partial"))
    build(rig, tmp_path / "ref", scene="s")
    assert content(out) == content(tmp_path / "ref")
    assert cache.get("000001", "A")[1].any()  # an open reader sees frames finished since it opened


def test_adding_frames_extends_the_scene(tmp_path):
    build(tiny_rig(2), tmp_path / "c", scene="s")
    report = build(tiny_rig(5), tmp_path / "c", scene="s")
    assert (report.frames_built, report.frames_already_done, report.frames_total) == (3, 2, 5)
    build(tiny_rig(5), tmp_path / "ref", scene="s")
    assert content(tmp_path / "c") == content(tmp_path / "ref")


def test_fsspec_memory_store_matches_local_folder(tmp_path):
    pytest.importorskip("fsspec")
    rig = tiny_rig(2)
    url = f"memory://sgde-test-{uuid.uuid4().hex}/cache"
    build(rig, url, scene="s")
    build(rig, tmp_path / "c", scene="s")
    assert content(url) == content(tmp_path / "c")
    cache = PriorCache(url)
    np.testing.assert_array_equal(cache.get("000001", "C")[0], PriorCache(tmp_path / "c").get("000001", "C")[0])
    assert verify_cache(url)["ok"]


def test_two_worker_processes_write_the_same_bytes(tmp_path):
    rig = tiny_rig(6)
    r2 = build(rig, tmp_path / "w2", scene="s", workers=2)
    assert r2.workers == 2 and r2.frames_built == 6
    build(rig, tmp_path / "w1", scene="s", workers=1)
    assert content(tmp_path / "w2") == content(tmp_path / "w1")


def test_ray_engine_writes_the_same_bytes(tmp_path):
    pytest.importorskip("ray")
    rig = tiny_rig(4)
    report = build(rig, tmp_path / "ray", scene="s", workers=2, engine="ray")
    assert report.frames_built == 4 and report.engine == "ray"
    build(rig, tmp_path / "local", scene="s")
    assert content(tmp_path / "ray") == content(tmp_path / "local")


def _corrupt(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "flip":
        data[len(data) // 4] ^= 0xFF  # inside the first camera's chunk
        path.write_bytes(bytes(data))
    else:
        path.write_bytes(bytes(data[: len(data) - 40]))


def test_verify_names_bad_chunks_by_scene_frame_camera(tmp_path, capsys):
    rig = tiny_rig(4)
    out = tmp_path / "c"
    build(rig, out, scene="s")
    assert verify_cache(out) == {"location": str(out), "ok": True, "chunks_read": 4 + 4 * 3 * 2,
                                 "frames_checked": 4, "problems": []}
    _corrupt(out / "s" / "depth" / "c" / "1" / "0" / "0" / "0", "flip")
    _corrupt(out / "s" / "confidence" / "c" / "2" / "0" / "0" / "0", "truncate")
    (out / "s" / "depth" / "c" / "3" / "0" / "0" / "0").unlink()
    result = verify_cache(out)
    found = {(p["scene"], p["frame"], p["camera"], p["array"]) for p in result["problems"]}
    assert ("s", "000001", "A", "depth") in found
    assert not any(f == "000001" and c in ("B", "C") and a == "depth" for _, f, c, a in found)
    assert {("s", "000002", c, "confidence") for c in "ABC"} <= found  # a truncated shard loses its index
    assert {("s", "000003", c, "depth") for c in "ABC"} <= found  # a vanished shard of a finished frame
    assert not any(f == "000000" for _, f, _, _ in found)
    assert cli_main(["cache", "verify", str(out)]) == 2
    captured = capsys.readouterr()
    assert "s/000001/A: depth: checksum mismatch" in captured.out
    assert "problem(s)" in captured.err


def test_info_reports_frames_coverage_and_size(tmp_path, capsys):
    rig = tiny_rig(3)
    out = tmp_path / "c"
    build(rig, out, scene="s")
    info = cache_info(out)
    compute = SyntheticPriorCompute(rig)
    maps = [compute(f.id) for f in rig.frames]
    (scene,) = info["scenes"]
    assert (scene["frames_done"], scene["frames_total"], scene["cameras"]) == (3, 3, 3)
    for row in info["cameras"]:
        expected = np.mean([(m[row["camera"]][0] > 0).mean() for m in maps])
        assert row["coverage"] == pytest.approx(expected, rel=1e-9)
    assert info["bytes"] == sum(store_keys(out).values())
    assert scene["fingerprint"] == fingerprint(rig, CONFIG, ALGO)
    assert cli_main(["cache", "info", str(out)]) == 0
    assert scene["fingerprint"] in capsys.readouterr().out


def test_lazy_package_exports_do_not_import_torch_or_zarr():
    import subprocess
    import sys

    code = (
        "import sys, sgde_plugin\n"
        "assert 'torch' not in sys.modules and 'zarr' not in sys.modules\n"
        "from sgde_plugin import PriorCache, load_rig\n"
        "from sgde_plugin.cache import PriorCache as P2, fingerprint\n"
        "assert PriorCache is P2 and callable(load_rig) and callable(fingerprint)\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_extrapolation_table_arithmetic():
    from sgde_plugin.benchmarks.cache import extrapolation

    rows = {r["set"]: r for r in extrapolation(50_000, 0.18)}
    key = rows["keyframes, trainval"]
    assert key["camera_images"] == 204_894
    assert key["GB_800x450"] == pytest.approx(204_894 * 50_000 / 1e9)
    assert key["core_h_800x450"] == pytest.approx(34_149 * 0.18 / 3600)
    assert key["h_on_64_cores_1600x900_est"] == pytest.approx(4 * 34_149 * 0.18 / 3600 / 64)
    assert rows["all camera images (sweeps)"]["GB_1600x900_est"] == pytest.approx(4 * 1.4e6 * 50_000 / 1e9)


def test_not_a_cache_is_refused_with_one_line(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.txt").write_text("x")
    with pytest.raises(InputError, match="exists and is not a prior cache"):
        build(tiny_rig(1), tmp_path / "photos")
    assert (tmp_path / "photos" / "a.txt").read_text() == "x"  # refused, never wiped
    fsspec = pytest.importorskip("fsspec")
    url = f"memory://sgde-test-{uuid.uuid4().hex}/data"
    fsspec.filesystem("memory").pipe(url.removeprefix("memory://") + "/keep.bin", b"keep")
    with pytest.raises(InputError, match="exists and is not a prior cache"):
        build(tiny_rig(1), url)
    assert fsspec.filesystem("memory").cat(url.removeprefix("memory://") + "/keep.bin") == b"keep"
    with pytest.raises(InputError, match="prior cache does not exist"):
        PriorCache(tmp_path / "nothing")
    with pytest.raises(InputError, match="not a prior cache"):
        PriorCache(tmp_path / "photos")


def test_several_scenes_in_one_cache(tmp_path):
    from dataclasses import replace

    out = tmp_path / "c"
    rig1 = tiny_rig(2)
    rig2 = replace(tiny_rig(3), frames=tuple(replace(f, id=f"b{f.id}") for f in tiny_rig(3).frames))
    build(rig1, out, scene="s1")
    build(rig2, out, scene="s2")
    cache = PriorCache(out)
    assert cache.scenes() == ["s1", "s2"]
    assert cache.frames() == ["000000", "000001", "b000000", "b000001", "b000002"]
    fps = cache.fingerprints()
    assert fps["s1"]["fingerprint"] == fps["s2"]["fingerprint"] == fingerprint(rig1, CONFIG, ALGO)
    np.testing.assert_array_equal(cache.get("b000002", "B")[0], PriorCache(out, scene="s2").get("b000002", "B")[0])
    assert PriorCache(out, scene="s1").frames() == ["000000", "000001"]
    build(tiny_rig(2), out, scene="s3")  # the same frame ids as s1: ambiguous without a scene
    with pytest.raises(KeyError, match="several scenes"):
        PriorCache(out).get("000000", "A")
    with pytest.raises(InputError, match="no such scene"):
        PriorCache(out, scene="s9")
