"""Bad input (issue #22, failures 3, 5 and 6): every case is refused with one line on stderr naming the
file and key (exit code 2), never a traceback, an "internal error" or exit 0 on a wrong result.

Runtime ~15 s on 2 cores (one `sgde export` argument check imports torch; a closed-pipe subprocess).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from cache_fixtures import build, tiny_rig
from test_readers_ddad import write_scene
from test_rig import make_rig, write_folder

from sgde_plugin.cache.dataset import PriorDataset
from sgde_plugin.cache.store import PriorCache
from sgde_plugin.cli import main
from sgde_plugin.errors import InputError
from sgde_plugin.io import atomic_write_text
from sgde_plugin.rig import write_rig_json


@pytest.fixture
def rig_dir(tmp_path: Path) -> Path:
    root = tmp_path / "rig"
    write_folder(root, make_rig(frames=1))
    return root


def _edit(root: Path, change) -> None:
    doc = json.loads((root / "rig.json").read_text())
    change(doc)
    (root / "rig.json").write_text(json.dumps(doc))


def _rename_camera(doc: dict, new: str) -> None:
    old = doc["cameras"][1]["name"]
    doc["cameras"][1]["name"] = new
    doc["ring"] = [new if n == old else n for n in doc["ring"]]


def _pairs(doc: dict, pairs: list) -> None:
    del doc["ring"]
    doc["pairs"] = pairs


RIG_DEFECTS = {
    "name_escapes_folder": (lambda d: _rename_camera(d, "../../../x"), "cameras[1].name: '../../../x' is not a plain"),
    "name_with_newline": (lambda d: _rename_camera(d, "CAM\nX"), "cameras[1].name: 'CAM\\nX' is not a plain"),
    "ring_of_one": (lambda d: d.update(ring=["CAM_FRONT"]), "ring: needs at least two cameras"),
    "no_pairs": (lambda d: _pairs(d, []), "pairs: lists no pair"),
    "pair_twice": (lambda d: _pairs(d, [["CAM_FRONT", "CAM_BACK"], ["CAM_BACK", "CAM_FRONT"]]),
                   "pairs[1]: repeats the pair"),
    "absurd_K": (lambda d: d["cameras"][0]["K"][0].__setitem__(0, 1e308), "cameras[CAM_FRONT].K: has an absurd"),
    "absurd_mount": (lambda d: d["cameras"][0]["sensor_to_ego"][0].__setitem__(3, 1e6),
                     "cameras[CAM_FRONT].sensor_to_ego: translation of 1e+06 m is absurd"),
    "frame_id_dots": (lambda d: d["frames"][0].update(id=".."), "frames[0].id: missing or not a plain file name"),
    "reflection": (lambda d: d["cameras"][0]["sensor_to_ego"][0].__setitem__(
        slice(0, 3), [-v for v in d["cameras"][0]["sensor_to_ego"][0][:3]]),
        "cameras[CAM_FRONT].sensor_to_ego: rotation has determinant -1 (a reflection)"),
}


def _one_line(capsys, code: int = 2) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err and "internal error" not in err, err
    return lines[0]


@pytest.mark.parametrize("defect", sorted(RIG_DEFECTS))
def test_degenerate_or_unsafe_rigs_are_refused(defect, rig_dir, capsys):
    change, expected = RIG_DEFECTS[defect]
    _edit(rig_dir, change)
    assert main(["validate", str(rig_dir)]) == 2
    line = _one_line(capsys)
    assert expected in line and str(rig_dir / "rig.json") in line


def _png(root: Path) -> Path:
    return root / "frames" / "000000" / "CAM_BACK.png"


def test_validate_decodes_every_image_and_quick_reads_headers(rig_dir, capsys):
    data = _png(rig_dir).read_bytes()
    _png(rig_dir).write_bytes(data[: len(data) // 2])
    assert main(["validate", str(rig_dir), "--quick"]) == 0  # the header is intact
    capsys.readouterr()
    assert main(["validate", str(rig_dir)]) == 2
    assert _one_line(capsys).endswith("CAM_BACK.png: truncated PNG (no IEND chunk)")
    corrupt = bytearray(data)
    corrupt[len(data) // 2] ^= 0xFF  # inside the pixel data: the chunk's CRC no longer matches
    _png(rig_dir).write_bytes(bytes(corrupt))
    assert main(["validate", str(rig_dir)]) == 2
    assert "CAM_BACK.png: corrupted PNG (IDAT chunk at byte" in _one_line(capsys)
    _png(rig_dir).unlink()
    _png(rig_dir).mkdir()  # a folder where the image belongs
    assert main(["validate", str(rig_dir)]) == 2
    assert "CAM_BACK.png: cannot read" in _one_line(capsys)


def test_damaged_images_are_refused_by_the_readers_without_decoder_noise(rig_dir, capfd):
    from sgde_plugin.io import read_image

    data = _png(rig_dir).read_bytes()
    expected = read_image(_png(rig_dir))
    for damaged, problem in ((data[:-100], "truncated PNG"), (data[:60] + bytes([data[60] ^ 1]) + data[61:],
                                                               "corrupted PNG")):
        _png(rig_dir).write_bytes(damaged)
        with pytest.raises(InputError, match=problem):
            read_image(_png(rig_dir))
    assert capfd.readouterr().err == ""  # nothing from libpng on stderr
    _png(rig_dir).write_bytes(data)
    np.testing.assert_array_equal(read_image(_png(rig_dir)), expected)


def _write_png(path: Path, pixels: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), pixels)


def _depth_8bit(root: Path) -> Path:
    path = root / "depth" / "000000" / "CAM_FRONT.png"
    _write_png(path, np.full(_camera_shape(root, "CAM_FRONT"), 7, np.uint8))
    return root


def _image_16bit(root: Path) -> Path:
    _write_png(_png(root), np.full((*_camera_shape(root, "CAM_BACK"), 3), 40000, np.uint16))
    return root


def _camera_shape(root: Path, camera: str) -> tuple[int, int]:
    """(height, width) of a camera of the rig folder."""
    (cam,) = [c for c in json.loads((root / "rig.json").read_text())["cameras"] if c["name"] == camera]
    return cam["height"], cam["width"]


def _no_frames(root: Path) -> Path:
    _edit(root, lambda d: d.update(frames=[]))
    return root


# what `validate` must refuse because other commands do (or the contract says so), with their one line
FOLDER_DEFECTS = {
    "depth_8bit": (_depth_8bit, "depth/000000/CAM_FRONT.png: not a single-channel uint16 depth PNG"),
    "image_16bit": (_image_16bit, "frames/000000/CAM_BACK.png: not an 8-bit colour image (16 bits per channel)"),
    "no_frames": (_no_frames, "rig.json: frames: the rig has no frames"),
    "rig_file": (lambda root: root / "rig.json", "rig.json: expected a rig folder (the folder holding rig.json)"),
}


@pytest.mark.parametrize("defect", sorted(FOLDER_DEFECTS))
def test_validate_refuses_what_the_other_commands_refuse_in_the_same_line(defect, rig_dir, tmp_path, capsys):
    make, expected = FOLDER_DEFECTS[defect]
    where = make(rig_dir)
    lines = {}
    for argv in (["validate", str(where)], ["validate", str(where), "--quick"],
                 ["prior", str(where), "--out", str(tmp_path / "c"), "--workers", "1"],
                 ["calibrate", str(where), "--out", str(tmp_path / "r.json")]):
        assert main(argv) == 2, argv
        lines[argv[0]] = _one_line(capsys).split(": ", 1)[1]  # without the "sgde <command>: " prefix
        assert expected in lines[argv[0]], (argv, lines[argv[0]])
    assert len(set(lines.values())) == 1, lines
    assert not (tmp_path / "c").exists() and not (tmp_path / "r.json").exists()
    if defect == "depth_8bit":  # eval's reader refuses it in the same words
        from sgde_plugin.io import read_depth_png

        with pytest.raises(InputError) as info:
            read_depth_png(rig_dir / "depth" / "000000" / "CAM_FRONT.png")
        assert info.value.line() == lines["validate"]


def test_deeply_nested_json_is_one_line(rig_dir, capsys):
    (rig_dir / "rig.json").write_text("[" * 100_000 + "]" * 100_000)
    assert main(["validate", str(rig_dir)]) == 2
    assert "rig.json" in _one_line(capsys)


def test_options_and_output_paths(rig_dir, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    two = tmp_path / "two"
    write_folder(two, make_rig(frames=2))
    cases = [
        (["synth", "--preset", "nuscenes", "--frames", "1", "--out", str(tmp_path / "s"), "--pose-noise-deg", "nan"],
         "argument --pose-noise-deg: must be a finite number"),
        (["eval", str(rig_dir), "--cache", str(tmp_path / "c"), "--max-depth", "-1"],
         "argument --max-depth: must be in (0, 10000]"),
        (["prior", str(rig_dir), "--out", str(rig_dir), "--scale", "inf"], "argument --scale"),
        (["prior", str(rig_dir), "--out", str(afile), "--workers", "1"], "exists and is not a folder"),
        (["synth", "--preset", "nuscenes", "--frames", "1", "--out", str(afile / "sub")], "afile is a file"),
        (["export", "onnx", "--model", "r18", "--out", str(tmp_path / "m.onnx"), "--opset", "99"],
         "--opset: must be between 17 and"),
        (["cache", "info", "nosuchprotocol://x"], "unsupported cache location"),
        (["calibrate", str(rig_dir), "--out", "x.json", "--alpha", "nan"], "argument --alpha"),
        (["calibrate", str(rig_dir), "--out", "x.json", "--loftr-weights", str(afile)],
         "--loftr-weights: only `--matcher loftr` takes a checkpoint (matcher: sift)"),
        (["calibrate", str(rig_dir), "--out", str(tmp_path / "x.json"), "--masks", str(afile)],
         "mask folder not found"),
        (["masks", str(two), "--out", str(afile / "sub")], "cannot create the folder (Not a directory)"),
        (["masks", str(two), "--out", str(afile)], "afile: exists and is not a folder"),
        (["demo", "--out", str(afile / "sub")], "cannot create the folder (Not a directory)"),
    ]
    for argv, expected in cases:
        assert main(argv) == 2, argv
        assert expected in _one_line(capsys), argv


def test_outputs_that_cannot_be_written_are_named(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(InputError, match="is a folder"):  # calibrate --out DIR, eval --json DIR
        atomic_write_text(tmp_path / "d", "x")
    with pytest.raises(InputError, match="cannot write"):
        write_rig_json(make_rig(1), tmp_path / "afile" / "rig.json") if (tmp_path / "afile").write_text("x") else None


def test_outputs_that_cannot_be_written_are_refused_before_the_work(rig_dir, tmp_path, capsys, monkeypatch):
    import sgde_plugin.calib

    def never(*args, **kwargs):
        raise AssertionError("the command worked before it checked its output")

    monkeypatch.setattr(sgde_plugin.calib, "calibrate", never)
    afile = tmp_path / "afile"
    afile.write_text("kept")
    cases = [
        ["calibrate", str(rig_dir), "--out", str(afile / "rig.json")],
        ["calibrate", str(rig_dir), "--out", str(tmp_path / "ok.json"), "--json", str(afile / "r.json")],
        ["calibrate", str(rig_dir), "--out", str(tmp_path)],
        ["eval", str(rig_dir), "--cache", str(tmp_path / "nocache"), "--json", str(afile / "e.json")],
        ["cache", "info", str(tmp_path / "nocache"), "--json", str(afile / "c.json")],
        ["bench", "nosuchbench", "--json", str(afile / "b.json")],
    ]
    for argv in cases:
        assert main(argv) == 2, argv
        line = _one_line(capsys)
        assert "afile" in line and "cannot write" in line or "is a folder" in line, (argv, line)
    assert afile.read_text() == "kept" and sorted(p.name for p in tmp_path.iterdir()) == ["afile", "rig"]
    assert main(["cache", "info", str(tmp_path / "nocache"), "--json", str(afile)]) == 2  # checked, not replaced
    assert afile.read_text() == "kept"


def test_damaged_cache_metadata_is_one_line(tmp_path, capsys):
    out = tmp_path / "c"
    build(tiny_rig(2), out, scene="s")
    (out / "zarr.json").write_text("{ corrupted")
    assert main(["cache", "info", str(out)]) == 2
    assert "zarr.json: not a prior cache" in _one_line(capsys)


def test_priors_of_another_scene_are_refused(tmp_path):
    rig = tiny_rig(3)
    out = tmp_path / "c"
    build(rig, out, scene="s")
    cache = PriorCache(out)
    cache.check_frames(rig)  # its own rig passes
    moved = np.eye(4)
    moved[0, 3] = 5.0  # same ids and timestamps, another drive
    other = dataclasses.replace(rig, frames=tuple(dataclasses.replace(f, ego_to_world=moved) for f in rig.frames))
    with pytest.raises(InputError, match=r"s: frames\[000000\]: was built from other images, poses"):
        cache.check_frames(other)
    with pytest.raises(InputError, match="images or poses differ"):
        build(other, out, scene="s")  # nor are they mixed into it


def test_api_misuse_of_sizes_is_a_clear_error(tmp_path):
    rig = tiny_rig(1)
    build(rig, tmp_path / "c", scene="s")
    with pytest.raises(ValueError, match=r"size must be two positive integers \(height, width\), got \(0, 0\)"):
        PriorCache(tmp_path / "c").get("000000", "A", size=(0, 0))
    with pytest.raises(ValueError, match="size must be two positive integers"):
        PriorDataset(rig, tmp_path / "c", size=(0, 0))
    cache = PriorCache(tmp_path / "c")
    for bad in (float("nan"), -0.1, 1.5, "0.5", None):  # NaN read as "no threshold" and served every value
        with pytest.raises(ValueError, match=r"min_confidence must be a number in \[0, 1\], got"):
            cache.get("000000", "A", min_confidence=bad)
    depth, _ = cache.get("000000", "A")
    assert np.array_equal(cache.get("000000", "A", min_confidence=np.float32(0.0))[0], depth) and depth.any()


def test_a_closed_pipe_ends_quietly(rig_dir):
    proc = subprocess.Popen([sys.executable, "-m", "sgde_plugin.cli", "validate", str(rig_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # like `| head` that has already exited
    err = proc.stderr.read().decode()
    assert proc.wait(120) == 141 and err == ""


def test_eval_refuses_the_cache_of_another_scene(tmp_path, capsys):
    import shutil

    from sgde_plugin.cache.synthetic import SyntheticPriorCompute
    from sgde_plugin.io import write_image
    from sgde_plugin.rig import read_rig_folder

    a, b = tmp_path / "a", tmp_path / "b"
    write_folder(a, make_rig(frames=1))
    shutil.copytree(a, b)
    noise = np.random.default_rng(7).integers(0, 255, (36, 64, 3), np.uint8)  # another drive, same ids
    write_image(_png(b), noise)
    rig = read_rig_folder(a)
    build(rig, tmp_path / "c", scene="a", compute=SyntheticPriorCompute(rig))
    assert main(["eval", str(a), "--cache", str(tmp_path / "c")]) == 2
    assert "no ground-truth depth" in _one_line(capsys)  # its own scene passes the check
    assert main(["eval", str(b), "--cache", str(tmp_path / "c")]) == 2
    assert "a: frames[000000]: was built from other images, poses or timestamps" in _one_line(capsys)


def _json_paths(node: object, path: tuple = (), items: int = 2) -> list[tuple]:
    """Every key path of a JSON document (lists: their first `items` items)."""
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _json_paths(v, (*path, k), items)
    elif isinstance(node, list):
        for i, v in enumerate(node[:items]):
            out += _json_paths(v, (*path, i), items)
    return out


MUTATIONS = (None, "x", [], {}, [[1, 2], [3]], True, -1, 1e308, float("nan"), "delete")


def _every_mutation_is_valid_or_one_line(folder: Path, file: Path, capsys, mutations: tuple = MUTATIONS,
                                         items: int = 2) -> tuple[int, int]:
    """Each key of the JSON `file` in `folder` (lists: their first `items` items) replaced by each of `mutations` in
    turn: `sgde validate` accepts the folder (exit 0) or names the problem on one line (exit 2), never an internal
    error (exit 1) or a warning (a second stderr line). Returns (runs, refused)."""
    good = json.loads(file.read_text())
    runs = refused = 0
    for path in _json_paths(good, items=items):
        for value in mutations:
            if value == "delete" and isinstance(path[-1], int):
                continue
            doc = json.loads(json.dumps(good))
            parent = doc
            for key in path[:-1]:
                parent = parent[key]
            if value == "delete":
                del parent[path[-1]]
            else:
                parent[path[-1]] = value
            file.write_text(json.dumps(doc))
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                code = main(["validate", str(folder)])
            err = capsys.readouterr().err.strip().splitlines()
            assert code in (0, 2) and (code == 0 or len(err) == 1), (path, value, code, err)
            runs, refused = runs + 1, refused + (code == 2)
    file.write_text(json.dumps(good))
    return runs, refused


def test_every_key_of_rig_json_broken_every_way_is_one_line_or_valid(rig_dir, capsys):
    runs, refused = _every_mutation_is_valid_or_one_line(rig_dir, rig_dir / "rig.json", capsys)
    assert runs > 500 and refused > 0.9 * runs  # nearly every change breaks the contract


def test_every_key_of_a_ddad_scene_broken_every_way_is_one_line_or_valid(tmp_path, capsys):
    folder = tmp_path / "000000"
    write_scene(folder, n=2, scale=0.125)  # each validate decodes the scene's images: small ones
    few = (None, "x", [[1, 2], [3]], 1e308, "delete")  # and a smaller set of values
    calibration = next((folder / "calibration").iterdir())
    runs, refused = _every_mutation_is_valid_or_one_line(folder, calibration, capsys, few, items=1)
    assert runs > 100 and refused > 0.8 * runs
    scene = next(folder.glob("scene_*.json"))
    runs, refused = _every_mutation_is_valid_or_one_line(folder, scene, capsys, few, items=1)
    assert runs > 100 and refused > 0.5 * runs  # metadata keys the reader does not use may take any value


@pytest.mark.parametrize("command", ["calibrate", "prior"])
def test_a_mask_folder_with_a_mask_of_another_size_is_one_line(rig_dir, tmp_path, capsys, command):
    from sgde_plugin.io import write_image
    from sgde_plugin.rig import read_rig_folder

    cam = read_rig_folder(rig_dir).cameras[0]
    masks = tmp_path / "masks"
    write_image(masks / f"{cam.name}.png", np.full((cam.height // 2, cam.width), 255, np.uint8))  # read at wrong pixels
    out = tmp_path / ("out.json" if command == "calibrate" else "cache")
    assert main([command, str(rig_dir), "--out", str(out), "--masks", str(masks)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{cam.name}.png: size: image is {cam.width}x{cam.height // 2}, camera {cam.name} is " \
        f"{cam.width}x{cam.height}" in err[0], err
    assert not out.exists()
