"""Damaged caches (issue #22, failure 2): every missing or corrupted chunk, edited attribute or missing
scene is named by `verify`; `PriorCache.get` raises naming scene, frame and camera instead of serving
"no prior"; a resumed build rebuilds exactly the damaged frames (missing shards always, any unreadable
chunk with `repair=True`) and reports them, ending byte-identical to an undamaged build.

Runtime ~5 s on 2 cores.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from cache_fixtures import build, content, tiny_rig

from sgde_plugin.cache.inspection import cache_info, verify_cache
from sgde_plugin.cache.store import PriorCache
from sgde_plugin.cli import main as cli_main
from sgde_plugin.errors import InputError

FRAMES = 4


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clean") / "c"
    build(tiny_rig(FRAMES), out, scene="s")
    return out


@pytest.fixture
def damaged(clean, tmp_path) -> Path:
    out = tmp_path / "c"
    shutil.copytree(clean, out)
    return out


def _shard(out: Path, array: str, frame: int) -> Path:
    return out / "s" / array / "c" / str(frame) / "0" / "0" / "0"


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 4] ^= 0xFF  # inside the first camera's chunk
    path.write_bytes(bytes(data))


def _problems(out: Path) -> set[tuple[str, str, str, str]]:
    return {(p["scene"], p["frame"], p["camera"], p["array"]) for p in verify_cache(out)["problems"]}


def test_missing_depth_shard_is_an_error_and_a_resume_rebuilds_exactly_that_frame(clean, damaged):
    _shard(damaged, "depth", 1).unlink()
    assert ("s", "000001", "A", "depth") in _problems(damaged)
    cache = PriorCache(damaged)
    with pytest.raises(InputError) as info:
        cache.get("000001", "A")
    assert info.value.line().startswith(f"{damaged}: s/000001/A: depth chunk missing or damaged")
    assert cache.get("000002", "A")[1].any()  # the other frames are served
    report = build(tiny_rig(FRAMES), damaged, scene="s")
    assert (report.frames_built, report.frames_already_done) == (1, FRAMES - 1)
    assert report.frames_repaired == {"000001": "depth shard missing"}
    assert "1 damaged frame(s) rebuilt: 000001 (depth shard missing)" in report.line()
    assert content(damaged) == content(clean)


def test_missing_confidence_shard_is_found_by_verify_get_prior_and_resume(clean, damaged):
    _shard(damaged, "confidence", 2).unlink()
    assert {("s", "000002", "*", "confidence"), ("s", "000002", "A", "confidence")} <= _problems(damaged)
    with pytest.raises(InputError, match="s/000002/A: confidence chunk missing"):
        PriorCache(damaged).get_prior("000002", "A")
    report = build(tiny_rig(FRAMES), damaged, scene="s")
    assert report.frames_repaired == {"000002": "confidence shard missing"}
    assert content(damaged) == content(clean)


def test_corrupted_chunks_are_named_and_rebuilt_by_repair(clean, damaged):
    _flip(_shard(damaged, "depth", 0))
    _flip(_shard(damaged, "confidence", 3))
    _flip(damaged / "s" / "valid_pixels" / "c" / "2" / "0")
    found = _problems(damaged)
    assert {("s", "000000", "A", "depth"), ("s", "000003", "A", "confidence"),
            ("s", "000002", "*", "valid_pixels")} <= found
    cache = PriorCache(damaged)
    with pytest.raises(InputError, match=r"s/000000/A: depth chunk unreadable \(checksum mismatch\)"):
        cache.get("000000", "A")
    with pytest.raises(InputError, match="s/000002/B: its done marker"):
        cache.get("000002", "B")
    # a plain resume finds what a listing shows (the unreadable done marker); repair reads every chunk
    assert set(build(tiny_rig(FRAMES), damaged, scene="s").frames_repaired) == {"000002"}
    report = build(tiny_rig(FRAMES), damaged, scene="s", repair=True)
    assert set(report.frames_repaired) == {"000000", "000003"} and report.frames_built == 2
    assert content(damaged) == content(clean)
    assert verify_cache(damaged)["ok"]


def _edit_attrs(out: Path, edit) -> None:
    path = out / "s" / "zarr.json"
    doc = json.loads(path.read_text())
    edit(doc["attributes"])
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("edit, expected", [
    (lambda a: a["frame_ids"].reverse(), "frame_ids / timestamps_us were changed"),
    (lambda a: a["cameras"][2].update(width=64), "cameras (names or sizes) differ from the rig document's"),
    (lambda a: a["rig"]["cameras"][0]["K"][0].__setitem__(0, 41.0), "the rig document does not match rig_fingerprint"),
])
def test_edited_scene_attributes_are_refused_by_readers_and_verify(damaged, edit, expected):
    _edit_attrs(damaged, edit)
    (problem,) = verify_cache(damaged)["problems"]
    assert problem["array"] == "attributes" and expected in problem["problem"]
    with pytest.raises(InputError) as info:
        PriorCache(damaged)
    assert f"s: damaged: {expected}" in info.value.line()
    with pytest.raises(InputError, match="cannot be repaired in place"):
        build(tiny_rig(FRAMES), damaged, scene="s")


def test_missing_array_scene_or_metadata_is_named(damaged, capsys):
    shutil.rmtree(damaged / "s" / "confidence")
    assert any("array 'confidence' is missing" in p["problem"] for p in verify_cache(damaged)["problems"])
    with pytest.raises(InputError, match="array 'confidence' is missing"):
        PriorCache(damaged)
    (damaged / "s" / "zarr.json").write_text("{ not json")
    assert cli_main(["cache", "verify", str(damaged)]) == 2
    assert cli_main(["cache", "info", str(damaged)]) == 0  # info shows the scene as damaged
    out = capsys.readouterr().out
    assert "damaged" in out
    (damaged / "s" / "zarr.json").unlink()
    (problem,) = verify_cache(damaged)["problems"]
    assert problem["scene"] == "s" and "scene folder without metadata (zarr.json missing)" in problem["problem"]
    shutil.rmtree(damaged / "s")
    (problem,) = verify_cache(damaged)["problems"]
    assert problem["problem"] == "the cache holds no scene"
    with pytest.raises(InputError, match="holds no"):
        PriorCache(damaged)
    assert cache_info(damaged)["scenes"] == []
