"""calibrate(): windows, methods, acceptance rules, history by timestamp (runtime ~7 s on 2 cores)."""

import numpy as np
import pytest

from sgde_plugin.calib import AcceptanceRules, calibrate, calibration_at, check_extrinsics, default_beta
from sgde_plugin.calib.acceptance import (
    BETA_DDAD,
    BETA_NUSCENES,
    BETA_SIFT,
    BETA_SYNTH,
    check_correspondences,
    check_result,
)
from sgde_plugin.calib.simulate import box_world_rig
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import rotation_vector
from sgde_plugin.pairs import relative_pose_errors
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(scope="module")
def box():
    with torch_threads(1):
        rig_true, rig, images = box_world_rig(n_frames=4)
    # the second window (frames 2 and 3) has a black camera
    for fid in ("000002", "000003"):
        images[fid]["C2"] = np.zeros_like(images[fid]["C2"])
    return rig_true, rig, images


def errors(rig, rig_true):
    rows = relative_pose_errors(rig, rig_true)
    return np.array([r["rotation_deg"] for r in rows]), np.array([r["translation_m"] for r in rows])


def test_glc_window_accepted_black_camera_window_rejected(box):
    rig_true, rig, images = box
    out, block = calibrate(rig, lambda f, c: images[f][c], method="glc", window=2, partial=False)
    w0, w1 = block["windows"]
    assert w0["accepted"] and w0["rule"] is None and w0["converged"] and w0["iterations"] <= 200
    assert not w1["accepted"] and w1["rule"] == "min_correspondences"
    assert "C2 not linked to C0" in w1["reason"] and f"beta = {BETA_SIFT}" in w1["reason"]
    assert w1["rules_fired"] == [{"rule": "min_correspondences", "reason": w1["reason"]}]
    assert {p["status"] for p in w1["pairs"] if "C2" in (p["a"], p["b"])} == {"through ring"}
    assert w1["iterations"] == 0  # rejected before the adjustment
    # the output keeps the last accepted calibration, which is much better than the input
    rot0, trans0 = errors(rig, rig_true)
    rot, trans = errors(out, rig_true)
    assert rot0.min() > 0.5 and rot.max() < 0.15 and trans.max() < 0.03
    assert len(block["history"]) == 1 and block["history"][0]["from_timestamp_us"] == 0
    at_w1 = calibration_at(block, rig.frames[2].timestamp_us)
    for cam in out.cameras:
        assert np.allclose(at_w1[cam.name], cam.sensor_to_ego)
    assert calibration_at(block, -1) is None
    assert np.allclose(out.camera("C0").sensor_to_ego, rig.camera("C0").sensor_to_ego)  # the reference
    # the report: per pair counts and residuals
    pair = w0["pairs"][0]
    assert pair["inliers"] >= pair["adjusted_correspondences"] > 0 and 0 < pair["rms_px"] < 1.0
    assert out.extra["calibration"] is block and block["method"] == "glc" and block["accepted"]
    assert block["keypoint_refinement"] is False  # the default ("auto") on a pinhole rig


def test_previous_calibration_is_carried_forward(box):
    _, rig, images = box
    first, block1 = calibrate(rig, lambda f, c: images[f][c], frames=slice(0, 2))
    second, block2 = calibrate(first, lambda f, c: images[f][c], frames=slice(2, 4), partial=False)
    assert not block2["accepted"] and block2["rule"] == "min_correspondences"
    assert block2["history"] == block1["history"]  # the accepted window of the first run is kept
    for cam in second.cameras:
        assert np.array_equal(cam.sensor_to_ego, first.camera(cam.name).sensor_to_ego)


def test_a_window_that_leaves_a_camera_unlinked_is_calibrated_block_by_block(box):
    """The black C2 links to nothing: by default the other five cameras are calibrated as one block, placed by
    their fit to the start, and C2 keeps its starting extrinsics exactly."""
    rig_true, rig, images = box
    out, block = calibrate(rig, lambda f, c: images[f][c], frames=slice(2, 4))
    w = block["windows"][0]
    assert w["accepted"] and w["partial"] and w["rule"] is None and w["rules_fired"] == []
    assert w["blocks"] == [["C0", "C1", "C3", "C4", "C5"], ["C2"]] and "C2 not linked to C0" in w["not_linked"]
    assert block["partial_windows"] == [0] and block["accepted"]
    status = {(p["a"], p["b"]): p["status"] for p in w["pairs"]}
    assert status.pop(("C1", "C2")) == status.pop(("C2", "C3")) == "not linked"
    assert set(status.values()) == {"observed"}
    assert [p["rotation_sigma_deg"] is None for p in w["pairs"]] == ["C2" in p for p in rig.pairs]
    assert np.allclose(out.camera("C2").sensor_to_ego, rig.camera("C2").sensor_to_ego, rtol=0, atol=1e-12)
    rot, trans = errors(out, rig_true)
    rot0, trans0 = errors(rig, rig_true)
    inside = [k for k, (a, b) in enumerate(rig.pairs) if "C2" not in (a, b)]
    assert rot0[inside].min() > 0.5 and rot[inside].max() < 0.15 and trans[inside].max() < 0.03
    # the block's placement is the least-squares fit to the start, so the start's per-camera errors average out
    # on the pairs towards C2 instead of being replaced by the reference camera's alone
    assert rot[[1, 2]].max() < 1.5 * rot0.max()
    # and the history keeps no 1-sigma for the pairs the images do not determine
    assert sorted(tuple(r[:2]) for r in block["history"][0]["pair_rotation_sigma_deg"]) == sorted(
        rig.pairs[k] for k in inside)
    # after a window that linked every camera, the split one leaves C2 where that window put it
    out2, block2 = calibrate(rig, lambda f, c: images[f][c], window=2)
    w1 = block2["windows"][1]
    assert [w["partial"] for w in block2["windows"]] == [False, True] and w1["blocks"][1] == ["C2"]
    # averaged pair by pair with window 0: C2, which window 1 does not see, follows its neighbours by the relative
    # poses window 0 measured (its offset the mean of C1's and C3's, weighted by window 0's 1-sigmas of C1-C2, C2-C3)
    assert w1["rule"] is None and w1["fused_weights"] is not None and w1["disagreement_sigmas"] <= 6
    first = {k: np.asarray(v) for k, v in block2["history"][0]["sensor_to_ego"].items()}
    sig = {(a, b): s for a, b, s in block2["history"][0]["pair_rotation_sigma_deg"]}
    w12, w23 = sig[("C1", "C2")] ** -2, sig[("C2", "C3")] ** -2
    moved = {c: (rotation_vector(out2.camera(c).sensor_to_ego[:3, :3] @ first[c][:3, :3].T),
                 out2.camera(c).sensor_to_ego[:3, 3] - first[c][:3, 3]) for c in ("C1", "C2", "C3")}
    for k in (0, 1):
        assert moved["C2"][k] == pytest.approx((w12 * moved["C1"][k] + w23 * moved["C3"][k]) / (w12 + w23), abs=1e-12)
    assert np.linalg.norm(moved["C1"][0]) > 1e-5  # C1 did move
    assert errors(out2, rig_true)[0].max() < 0.15
    # only GLC calibrates block by block: the chained methods reject the window as before
    _, chained = calibrate(rig, lambda f, c: images[f][c], frames=slice(2, 4), method="wo-glc")
    assert chained["windows"][0]["rule"] == "min_correspondences" and not chained["windows"][0]["partial"]


def test_method_none_and_wo_glc(box):
    _, rig, images = box
    out, block = calibrate(rig, lambda f, c: images[f][c], method="none", frames=slice(0, 2))
    assert block["windows"][0]["accepted"] and out.cameras == rig.cameras
    out, block = calibrate(rig, lambda f, c: images[f][c], method="wo-glc", frames=slice(0, 2))
    used = [p["used_in_adjustment"] for p in block["windows"][0]["pairs"]]
    # a ring of 6 chained from C0: one pair (opposite the reference) stays open
    assert used.count(False) == 1 and block["windows"][0]["pairs"][used.index(False)]["a"] == "C3"


def test_rules_fire_with_their_names(box):
    _, rig, images = box
    out, block = calibrate(rig, lambda f, c: images[f][c], frames=slice(0, 2),
                           rules=AcceptanceRules(min_correspondences=10**6))
    w = block["windows"][0]
    assert w["rule"] == "min_correspondences" and "beta = 1000000" in w["reason"]
    assert w["pairs"][0]["inliers"] > 100 and w["iterations"] == 0 and not block["history"]
    assert out.cameras == rig.cameras  # the previous (here: input) calibration is kept
    _, block = calibrate(rig, lambda f, c: images[f][c], frames=slice(0, 2),
                         rules=AcceptanceRules(min_correspondences=BETA_SYNTH, max_iterations=2))
    assert block["windows"][0]["rule"] == "not_converged" and not block["history"]
    _, block = calibrate(rig, lambda f, c: images[f][c], frames=slice(0, 2),
                         rules=AcceptanceRules(min_correspondences=BETA_SYNTH, max_translation_change_m=0.001))
    assert block["windows"][0]["rule"] == "translation_change" and "alpha = 0.001" in block["windows"][0]["reason"]


def test_acceptance_functions():
    rules = AcceptanceRules(min_correspondences=50, max_iterations=200, max_translation_change_m=0.3)
    ring = {("A", "B"): 3, ("B", "C"): 1, ("C", "A"): 0}  # observation pairs passing beta, per camera pair
    assert check_correspondences(ring, rules, "A").accepted  # C-A is constrained through the ring
    v = check_correspondences({("A", "B"): 3, ("B", "C"): 0, ("C", "A"): 0}, rules, "A")
    assert not v.accepted and v.rule == "min_correspondences" and "camera(s) C not linked to A" in v.reason
    eye = np.eye(4)
    moved = np.eye(4)
    moved[0, 3] = 0.31
    before, after = {"A": eye, "B": eye}, {"A": eye, "B": moved}
    assert check_result(True, 10, before, after, [("A", "B")], rules).rule == "translation_change"
    # alpha is checked on observed pairs only: a pair seen through the ring is not judged by it
    assert check_result(True, 10, before, after, [], rules).accepted
    assert check_result(True, 201, before, before, [("A", "B")], rules).rule == "not_converged"
    both = check_result(False, 10, before, after, [("A", "B")], rules)
    assert both.rule == "not_converged" and [r for r, _ in both.fired] == ["not_converged", "translation_change"]
    assert check_result(True, 10, before, {"A": eye, "B": eye * np.nan}, [("A", "B")], rules).rule == "non_finite"
    assert check_result(True, 200, before, before, [("A", "B")], rules).accepted
    # a relative rotation the adjustment cannot determine rejects the window, one it pins down does not
    weak = check_result(True, 10, before, before, [("A", "B")], rules, {("A", "B"): 0.3, ("B", "C"): 1.2})
    assert weak.rule == "weakly_constrained" and "B-C 1.20 deg" in weak.reason
    assert check_result(True, 10, before, before, [("A", "B")], rules, {("A", "B"): 0.3}).accepted


def test_a_pair_without_matches_is_calibrated_through_the_ring(box):
    """C2's side towards C3 is black: C2-C3 has no observation, the window is accepted and that pair's
    relative pose, which comes through the ring, is within 2x of the worst observed pair's error."""
    rig_true, rig, images = box
    blind = {f: dict(cams) for f, cams in images.items()}
    for fid in ("000000", "000001"):
        img = images[fid]["C2"].copy()
        img[:, 2 * img.shape[1] // 3 :] = 0
        blind[fid]["C2"] = img
    out, block = calibrate(rig, lambda f, c: blind[f][c], frames=slice(0, 2))
    w = block["windows"][0]
    assert w["accepted"] and w["rules_fired"] == []
    assert block["window"] == 7 and len(w["frames"]) == 2  # a short window is calibrated with what it has
    status = {(p["a"], p["b"]): p["status"] for p in w["pairs"]}
    assert status.pop(("C2", "C3")) == "through ring" and set(status.values()) == {"observed"}
    rot, trans = errors(out, rig_true)
    rot0, _ = errors(rig, rig_true)
    others = np.delete(rot, 2)
    assert rot0.min() > 0.5 and rot[2] <= 2 * others.max() and rot.max() < 0.5 and trans.max() < 0.03


def test_default_beta(box):
    _, rig, _ = box
    assert default_beta(rig) == BETA_SIFT == 15  # SIFT: one value for every data set
    assert default_beta(rig, "loftr") == BETA_SYNTH
    plain = rig.with_extra(synth=None)
    from dataclasses import replace

    from sgde_plugin.cameras import Camera

    renamed = replace(plain, extra={}, cameras=tuple(Camera(f"CAMERA_0{i}", c.intrinsics, c.sensor_to_ego)
                                                      for i, c in enumerate(rig.cameras)))
    assert default_beta(renamed, "loftr") == BETA_DDAD == 200
    renamed = replace(renamed, cameras=tuple(Camera(f"CAM_{i}", c.intrinsics, c.sensor_to_ego)
                                             for i, c in enumerate(rig.cameras)))
    assert default_beta(renamed, "loftr") == BETA_NUSCENES == 50


def test_bad_initial_extrinsics_are_input_errors(box):
    _, rig, images = box
    bad = rig.camera("C3").sensor_to_ego.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        check_extrinsics(rig.with_extrinsics({"C3": bad}))
    skew = rig.camera("C3").sensor_to_ego.copy()
    skew[:3, :3] *= 1.01
    with pytest.raises(InputError, match="orthonormal"):
        calibrate(rig.with_extrinsics({"C3": skew}), lambda f, c: images[f][c])
    with pytest.raises(InputError, match="method"):
        calibrate(rig, lambda f, c: images[f][c], method="bundle")


@pytest.fixture(scope="module")
def phase_singles(box):
    """The first window of the box rig calibrated once at each of the view phases (rig, report)."""
    from sgde_plugin.calib import MatchConfig
    from sgde_plugin.calib.correspondences import VIEW_PHASES

    _, rig, images = box
    load = lambda f, c: images[f][c]  # noqa: E731
    return [calibrate(rig, load, frames=slice(0, 2), match_config=MatchConfig(view_phase=p, auto_phases=False))
            for p in VIEW_PHASES]


def test_view_phases_average_the_runs_with_moved_view_grids(box, phase_singles):
    """`MatchConfig.view_phases=2`: the window is matched and adjusted with the views at phase (0, 0) and (0.5, 0.5)
    and the result is the mean of the two runs' extrinsics (each run equals a single run at that phase); the
    report says how far each run's relative rotations are from the mean."""
    from dataclasses import replace

    from sgde_plugin.calib import MatchConfig
    from sgde_plugin.geometry import mean_transform

    rig_true, rig, images = box
    load = lambda f, c: images[f][c]  # noqa: E731
    one = MatchConfig()
    runs = [r for r, _ in phase_singles[:2]]
    out, block = calibrate(rig, load, frames=slice(0, 2), match_config=replace(one, view_phases=2))
    w = block["windows"][0]
    assert w["accepted"] and [p["phase"] for p in w["view_phases"]] == [[0.0, 0.0], [0.5, 0.5]]
    for cam in out.cameras:
        expected = mean_transform(np.stack([r.camera(cam.name).sensor_to_ego for r in runs]))
        np.testing.assert_allclose(cam.sensor_to_ego, expected, atol=1e-12)
    # the two runs differ (the views sample other sub-pixel positions), each by half their difference from the mean
    diffs = [max(p["pair_rotation_from_mean_deg"].values()) for p in w["view_phases"]]
    assert min(diffs) > 1e-5 and np.isclose(diffs[0], diffs[1], rtol=0.05)
    assert errors(out, rig_true)[0].max() < 0.15
    with pytest.raises(InputError, match="view_phases"):
        calibrate(rig, load, frames=slice(0, 2), match_config=replace(one, view_phases=5))
    with pytest.raises(InputError, match="octave_layers: must be 1 to 8, got 0"):
        calibrate(rig, load, frames=slice(0, 2), match_config=replace(one, octave_layers=0))


def test_auto_phases_redo_a_window_with_a_weak_pair_at_every_view_phase(box, phase_singles):
    """`MatchConfig.auto_phases`: a window whose adjacent pairs all come out with a rotation 1-sigma under
    `auto_phases_sigma_deg` runs once (the single-phase result bit for bit); above it, the window is matched and
    adjusted at every view phase and the result is the mean of the four runs, each pair named with its sigma; a
    rejected window is not redone."""
    from dataclasses import replace

    from sgde_plugin.calib import MatchConfig
    from sgde_plugin.calib.correspondences import VIEW_PHASES
    from sgde_plugin.geometry import mean_transform

    rig_true, rig, images = box
    load = lambda f, c: images[f][c]  # noqa: E731
    one = MatchConfig(auto_phases=False)
    singles = phase_singles
    sigmas = [p["rotation_sigma_deg"] for p in singles[0][1]["windows"][0]["pairs"]]
    assert min(sigmas) > 0.001

    out, block = calibrate(rig, load, frames=slice(0, 2),
                           match_config=replace(one, auto_phases=True, auto_phases_sigma_deg=max(sigmas) * 1.01))
    w = block["windows"][0]
    assert w["accepted"] and w["view_phases"] == [] and w["view_phases_because"] == []
    for cam in out.cameras:
        assert np.array_equal(cam.sensor_to_ego, singles[0][0].camera(cam.name).sensor_to_ego)

    threshold = float(np.median(sigmas))
    out, block = calibrate(rig, load, frames=slice(0, 2),
                           match_config=replace(one, auto_phases=True, auto_phases_sigma_deg=threshold))
    w = block["windows"][0]
    assert w["accepted"] and [p["phase"] for p in w["view_phases"]] == [list(p) for p in VIEW_PHASES]
    weak = [f"{p['a']}-{p['b']}" for p in singles[0][1]["windows"][0]["pairs"] if p["rotation_sigma_deg"] > threshold]
    assert weak and [why.split(":")[0] for why in w["view_phases_because"]] == weak
    for cam in out.cameras:
        expected = mean_transform(np.stack([r.camera(cam.name).sensor_to_ego for r, _ in singles]))
        np.testing.assert_allclose(cam.sensor_to_ego, expected, atol=1e-12)
    assert errors(out, rig_true)[0].max() < 0.15

    _, block = calibrate(rig, load, frames=slice(2, 4), partial=False,
                         match_config=replace(one, auto_phases=True, auto_phases_sigma_deg=0.0))
    w = block["windows"][0]
    assert not w["accepted"] and w["view_phases"] == [] and w["view_phases_because"] == []
