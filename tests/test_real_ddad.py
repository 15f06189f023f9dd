"""The real DDAD sample (../shared/data/ddad-sample): partial rigs, per-camera captures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.readers import load_rig

SAMPLE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ddad-sample"
pytestmark = pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} is absent")


def test_scene_01_is_a_partial_rig_with_two_pairs(capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(SAMPLE / "scene_01")]) == 0
    assert "3 cameras, 2 adjacent pairs, 3 frames" in capsys.readouterr().out
    rig = load_rig(SAMPLE / "scene_01")
    assert rig.pairs == (("CAMERA_01", "CAMERA_06"), ("CAMERA_05", "CAMERA_01")) and rig.ring is None


def test_scene_02_cameras_keep_their_datum_poses(capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(SAMPLE / "scene_02")]) == 0
    assert "6 cameras, 6 adjacent pairs, 3 frames" in capsys.readouterr().out
    rig = load_rig(SAMPLE / "scene_02")
    assert len(rig.camera_names) == 6 and rig.ring is not None
    for fr in rig.frames:
        for cam in rig.camera_names:
            cap = rig.capture(fr, cam)
            assert cap.timestamp_us == fr.timestamp_us  # DDAD's cameras are synchronised
            # the per-datum poses differ from CAMERA_01's by millimetres, not more
            assert np.abs(cap.ego_to_world[:3, 3] - fr.ego_to_world[:3, 3]).max() < 0.02
        assert set(fr.cameras) == set(rig.camera_names) - {"CAMERA_01"}


def test_lidar_truth_of_every_camera() -> None:
    rig = load_rig(SAMPLE / "scene_02")
    fr = rig.frames[0]
    assert fr.lidar is not None and fr.lidar.timestamp_us - fr.timestamp_us == 91_370  # LiDAR 91 ms later
    for cam in rig.camera_names:
        d = rig.load_depth(fr.id, cam)
        assert d.shape == (1216, 1936) and d.dtype == np.float32
        assert np.count_nonzero(d) > 4000 and d[d > 0].min() >= 1.0 and d.max() <= 250.0


def test_bench_real_on_scene_01_one_frame(tmp_path: Path) -> None:
    from sgde_plugin.benchmarks.real import run_real
    from sgde_plugin.rig import write_rig_json
    from sgde_plugin.stereo.pipeline import PriorConfig

    rig = load_rig(SAMPLE / "scene_01")
    write_rig_json(rig, tmp_path / "same.json")  # a second pose source equal to the data set's
    # a third with CAMERA_01's focal length 2 % longer: the prior uses the file's intrinsics, the LiDAR truth
    # stays the data set's (the same points compared at the same pixels)
    cam = rig.camera("CAMERA_01")
    write_rig_json(rig.with_intrinsics({cam.name: cam.intrinsics.with_focal_scale(1.02)}), tmp_path / "f.json")
    config = PriorConfig.from_settings(scale=0.25)
    report = run_real(SAMPLE / "scene_01", [str(tmp_path / "same.json"), str(tmp_path / "f.json")], config,
                      max_frames=1)
    assert report["frames"] == 1 and report["pairs"] == ["CAMERA_01|CAMERA_06", "CAMERA_05|CAMERA_01"]
    a, b = report["sources"]["dataset"], report["sources"][str(tmp_path / "same.json")]
    assert a["overall"] == b["overall"]
    c = report["sources"][str(tmp_path / "f.json")]["overall"]
    assert c["n_overlap"] == a["overall"]["n_overlap"] and c != a["overall"]
    overall = a["overall"]
    assert overall["n_overlap"] == sum(c["n_overlap"] for c in a["cameras"].values()) > 1000
    assert 0 < overall["n_prior"] and 0 < overall["coverage"] < 1
    assert overall["abs_rel"] < 0.5
    # the breakdown splits exactly the compared points; its bands add up to all of them and all of the error
    br = a["breakdown"]
    assert br["n"] == overall["n_prior"]
    for table in ("depth_m", "image_rows", "confidence"):
        assert sum(r["n"] for r in br[table]) == br["n"]
        assert sum(r["share_of_abs_rel"] for r in br[table]) == pytest.approx(1.0)
    mean = sum(r["abs_rel"] * r["n"] for r in br["depth_m"] if r["n"]) / br["n"]
    assert mean == pytest.approx(overall["abs_rel"], rel=1e-4)
    assert set(br["pair_disparity_error_px"]) <= set(report["pairs"]) and br["pair_disparity_error_px"]
    assert a["curve"][0]["n_prior"] == overall["n_prior"]


def _copy_scene(tmp_path: Path) -> Path:
    import shutil

    dst = tmp_path / "scene_01"
    shutil.copytree(SAMPLE / "scene_01", dst)
    return dst


@pytest.mark.parametrize("defect", ["truncated", "missing", "rig_lacks_camera", "unknown_preset", "no_masks"])
def test_bench_real_bad_input_is_one_line_exit_2(defect: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import json

    scene = _copy_scene(tmp_path)
    victim = sorted((scene / "point_cloud" / "LIDAR").iterdir())[1]
    args = ["bench", "real", str(scene)]
    if defect == "unknown_preset":
        pass
    elif defect == "no_masks":
        args += ["--masks", str(tmp_path / "nomasks")]
        expected = "nomasks: mask folder not found"
    elif defect == "truncated":
        victim.write_bytes(victim.read_bytes()[:1000])
        expected = f"{victim}: not a readable .npz"
    elif defect == "missing":
        victim.unlink()
        expected = f"{victim}: point cloud file not found"
    else:
        doc = load_rig(scene).to_dict()
        doc["cameras"] = doc["cameras"][:2]
        doc["pairs"], doc["frames"] = [doc["pairs"][0]], []
        (tmp_path / "two.json").write_text(json.dumps(doc))
        args += ["--rig", str(tmp_path / "two.json")]
        expected = "cameras: lacks CAMERA_05"
    if defect == "unknown_preset":
        args += ["--preset", "kitti"]
        expected = "unknown preset 'kitti'"
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and expected in err, err


def test_bench_options_of_real_only_are_refused_elsewhere(capsys: pytest.CaptureFixture) -> None:
    assert main(["bench", "synth", "--preset", "ddad"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--preset" in err and "bench real" in err, err
