"""`sgde calibrate` on a rig folder: output file, report, exit codes for bad input (runtime ~3 s)."""

import json
import shutil

import numpy as np
import pytest

from sgde_plugin.calib.simulate import box_world_rig
from sgde_plugin.cli import main
from sgde_plugin.io import write_image
from sgde_plugin.pairs import relative_pose_errors
from sgde_plugin.rig import read_rig_json, write_rig_json
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("box_rig")
    with torch_threads(1):
        rig_true, rig, images = box_world_rig(n_frames=2)
    for fid, per_cam in images.items():
        for cam, img in per_cam.items():
            write_image(root / "frames" / fid / f"{cam}.png", img)
    write_rig_json(rig, root / "rig.json")
    write_rig_json(rig_true, root / "rig_true.json")
    return root


def test_calibrate_writes_a_refined_rig(folder, tmp_path, capsys):
    out = tmp_path / "calib" / "rig.json"
    report = tmp_path / "report.json"
    code = main(["calibrate", str(folder), "--out", str(out), "--json", str(report), "--frames", "0:2"])
    assert code == 0
    refined = read_rig_json(out)
    block = refined.extra["calibration"]
    assert json.loads(report.read_text()) == block
    assert block["method"] == "glc" and block["windows"][0]["accepted"]
    assert block["keypoint_refinement"] is False  # no --refine-keypoints: "auto", off on this pinhole rig
    # no --view-phases: "auto"; this toy rig's pairs come out at 0.03-0.05 deg 1-sigma, so all four phases ran
    win = block["windows"][0]
    assert [p["phase"] for p in win["view_phases"]] == [[0.0, 0.0], [0.5, 0.5], [0.5, 0.0], [0.0, 0.5]]
    assert win["view_phases_because"] and all("rotation sigma" in why for why in win["view_phases_because"])
    truth = read_rig_json(folder / "rig_true.json")
    before = max(r["rotation_deg"] for r in relative_pose_errors(read_rig_json(folder / "rig.json"), truth))
    after = max(r["rotation_deg"] for r in relative_pose_errors(refined, truth))
    assert before > 0.5 and after < 0.15
    text = capsys.readouterr().out
    assert "C0-C1" in text and "1/1 windows accepted" in text
    assert [p.name for p in out.parent.iterdir()] == ["rig.json"]  # atomic write, no leftovers


@pytest.mark.parametrize("flag,on", [("--refine-keypoints", True), ("--no-refine-keypoints", False)])
def test_refine_keypoints_flags_force_the_refinement(folder, tmp_path, flag, on):
    """The flags override "auto" (which is off on this pinhole rig); the block says what ran. (`--view-phases 1`: one
    run, no phases, where the default would redo this toy rig's window four times.)"""
    out = tmp_path / "rig.json"
    assert main(["calibrate", str(folder), "--out", str(out), "--frames", "0:2", flag, "--view-phases", "1"]) == 0
    block = read_rig_json(out).extra["calibration"]
    assert block["keypoint_refinement"] is on and block["windows"][0]["accepted"]
    assert block["windows"][0]["view_phases"] == [] and block["windows"][0]["view_phases_because"] == []


@pytest.mark.parametrize("mode,kept", [("all", "all"), ("touching", "touching"), ("off", "none")])
def test_links_option_sets_the_same_camera_links(folder, tmp_path, mode, kept):
    """`--links` chooses which same-camera links the adjustment gets; the window report says which it had."""
    out = tmp_path / "rig.json"
    assert main(["calibrate", str(folder), "--out", str(out), "--frames", "0:2", "--links", mode,
                 "--view-phases", "1"]) == 0
    win = read_rig_json(out).extra["calibration"]["windows"][0]
    assert win["accepted"] and win["same_camera_links"] == kept and win["links_because"] == []
    assert (sum(p["same_camera_links"] for p in win["pairs"]) > 0) == (mode != "off")


def _broken_rig(folder, tmp_path, edit):
    doc = json.loads((folder / "rig.json").read_text())
    edit(doc)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "rig.json").write_text(json.dumps(doc))
    (bad / "frames").symlink_to(folder / "frames")
    return bad


@pytest.mark.parametrize("problem", ["nan", "skew"])
def test_bad_initial_extrinsic_exits_2(folder, tmp_path, capsys, problem):
    def edit(doc):
        T = np.array(doc["cameras"][2]["sensor_to_ego"])
        if problem == "nan":
            T[1, 1] = np.nan
        else:
            T[:3, :3] *= 1.001
        doc["cameras"][2]["sensor_to_ego"] = T.tolist()

    out = tmp_path / "out.json"
    assert main(["calibrate", str(_broken_rig(folder, tmp_path, edit)), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "sensor_to_ego" in err
    assert ("NaN" in err) if problem == "nan" else ("orthonormal" in err)
    assert not out.exists()


def test_bad_options_exit_2(folder, tmp_path, capsys):
    out = tmp_path / "out.json"
    assert main(["calibrate", str(folder), "--out", str(out), "--frames", "one:two"]) == 2
    assert "--frames" in capsys.readouterr().err
    assert main(["calibrate", str(folder), "--out", str(out), "--matcher", "loftr"]) == 2
    assert "--loftr-weights" in capsys.readouterr().err
    assert main(["calibrate", str(folder), "--out", str(out), "--frames", "5:9"]) == 2
    assert "empty" in capsys.readouterr().err
    assert main(["calibrate", str(folder), "--out", str(out), "--view-phases", "5"]) == 2
    assert "--view-phases" in capsys.readouterr().err
    assert not out.exists()


def test_no_window_accepted_one_line_exit_0_or_3_with_strict(folder, tmp_path, capsys):
    out = tmp_path / "out.json"
    args = ["calibrate", str(folder), "--out", str(out), "--frames", "0:2", "--beta", "1000000"]
    assert main(args) == 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no window accepted" in err and "min_correspondences" in err
    block = read_rig_json(out).extra["calibration"]
    assert not block["accepted"] and [f["rule"] for f in block["rules_fired"]] == ["min_correspondences"]
    assert main([*args, "--strict"]) == 3
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    # every rule that fired is kept: a tiny alpha and two iterations fire both after the adjustment
    assert main(["calibrate", str(folder), "--out", str(out), "--frames", "0:2", "--alpha", "1e-6",
                 "--max-iterations", "2", "--strict"]) == 3
    fired = [f["rule"] for f in read_rig_json(out).extra["calibration"]["rules_fired"]]
    assert fired[0] == "not_converged" and "translation_change" in fired


def test_a_camera_linked_to_nothing_partial_by_default_rejected_with_no_partial(folder, tmp_path, capsys):
    blind = tmp_path / "blind"
    shutil.copytree(folder, blind)
    for png in blind.glob("frames/*/C2.png"):
        write_image(png, np.zeros((180, 320, 3), np.uint8))
    out = tmp_path / "partial.json"
    assert main(["calibrate", str(blind), "--out", str(out), "--view-phases", "1"]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "block by block" in err[0] and "C2 not linked to C0" in err[0]
    assert "C0, C1, C3, C4, C5 | C2" in err[0] and "partial" in captured.out
    block = read_rig_json(out).extra["calibration"]
    assert block["partial_windows"] == [0] and block["windows"][0]["blocks"][1] == ["C2"]
    assert np.allclose(read_rig_json(out).camera("C2").sensor_to_ego,
                       read_rig_json(blind / "rig.json").camera("C2").sensor_to_ego, rtol=0, atol=1e-12)
    assert main(["calibrate", str(blind), "--out", str(out), "--view-phases", "1", "--no-partial", "--strict"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no window accepted" in err[0] and "min_correspondences" in err[0]
    assert read_rig_json(out).extra["calibration"]["partial_windows"] == []


def test_the_table_says_how_each_window_was_taken():
    from sgde_plugin.commands.calibrate import summary_rows
    pair = {"a": "C0", "b": "C1", "inliers": 40, "adjusted_correspondences": 30, "rms_px": 0.2}
    windows = [{"index": k, "frames": [f"{k:06d}"], "pairs": [pair], "accepted": ok, "rule": rule, "partial": part,
                "fused_weights": fused}
               for k, (ok, rule, part, fused) in enumerate([
                   (True, None, False, None), (True, None, False, {"in_effect": 0.6, "window": 0.4}),
                   (True, None, True, {"in_effect": 0.5, "window": 0.5}), (True, None, True, None),
                   (False, "less_precise", False, None), (False, "unconfirmed", False, None),
                   (True, None, False, None)])]
    windows[-1]["confirms"] = {"window": 5, "timestamp_us": 0, "disagreement_sigmas": 1.2, "pair_weights": []}
    assert [r["rule"] for r in summary_rows({"windows": windows})] == [
        "-", "averaged", "partial+averaged", "partial", "less_precise", "unconfirmed", "confirms 5"]
    assert {r["sigma_deg"] for r in summary_rows({"windows": windows})} == {None}  # a pair without one: "-"
    windows[0]["pairs"] = [{**pair, "rotation_sigma_deg": 0.01234}]
    assert summary_rows({"windows": windows[:1]})[0]["sigma_deg"] == "0.0123"
