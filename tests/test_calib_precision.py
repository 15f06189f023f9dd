"""A calibration in effect is not replaced by a window that agrees with it and is less precise (a creeping car);
a window taken while the car stood still says so (runtime ~30 s on 2 cores)."""

from dataclasses import replace

import numpy as np
import pytest

from sgde_plugin.calib import AcceptanceRules, calibrate
from sgde_plugin.calib.acceptance import check_precision, default_beta
from sgde_plugin.calib.pipeline import ego_travel_m, pair_sigmas_at
from sgde_plugin.calib.simulate import box_world_rig, noise_texture, render_box_world
from sgde_plugin.errors import InputError
from sgde_plugin.pairs import relative_pose_errors
from sgde_plugin.rig import Frame
from sgde_plugin.stereo.rectify import torch_threads


def test_check_precision_keeps_the_more_precise_calibration_unless_the_mount_moved():
    rules = AcceptanceRules()
    before = {("A", "B"): 0.03, ("B", "C"): 0.05}
    worse = {("A", "B"): 0.3, ("B", "C"): 0.5}
    v = check_precision(before, worse, {("A", "B"): 0.2, ("B", "C"): 0.4}, rules)
    # B-C: 0.4 deg turned against a combined 1-sigma of hypot(0.5, 0.05) = 0.502 deg: 0.8 sigma
    assert not v.accepted and v.rule == "less_precise"
    assert "B-C 1-sigma 0.500 deg against 0.050 deg" in v.reason and "within 0.8 combined" in v.reason
    # 2.0 deg on B-C is 3.98 combined sigmas: the mount moved, the window is adopted
    assert check_precision(before, worse, {("A", "B"): 0.2, ("B", "C"): 2.0}, rules).accepted
    # ... unless the car stood still: such a window's sigmas do not bound its error
    still = check_precision(before, worse, {("A", "B"): 0.2, ("B", "C"): 2.0}, rules, still=True)
    assert still.rule == "less_precise" and still.reason.startswith("was taken while the car stood still")
    # 1.8x less precise is within the ratio of 2
    assert check_precision(before, {("A", "B"): 0.05, ("B", "C"): 0.09}, {}, rules).accepted
    assert check_precision({}, worse, {}, rules).accepted  # nothing in effect to compare with
    assert check_precision(before, {("C", "D"): 9.0}, {}, rules).accepted  # no pair in common
    assert not check_precision(before, worse, {}, AcceptanceRules(max_sigma_ratio=9.9)).accepted
    assert check_precision(before, worse, {}, AcceptanceRules(max_sigma_ratio=10.0)).accepted


def test_pair_sigmas_of_the_history_entry_in_effect():
    block = {"history": [{"from_timestamp_us": 0, "pair_rotation_sigma_deg": [["A", "B", 0.03]]},
                         {"from_timestamp_us": 100}]}
    assert pair_sigmas_at(block, 50) == {("A", "B"): 0.03}
    assert pair_sigmas_at(block, 150) == {}  # an entry without sigmas: nothing to compare with
    assert pair_sigmas_at(block, -1) == {}
    for bad in ([["A", "B"]], [["A", "B", "x"]], [["A", "B", -1.0]], [["A", 3, 0.1]], "A-B"):
        with pytest.raises(InputError, match="pair_rotation_sigma_deg"):
            pair_sigmas_at({"history": [{"from_timestamp_us": 0, "pair_rotation_sigma_deg": bad}]}, 0, "rig.json")


def test_ego_travel_of_a_window():
    ego = np.tile(np.eye(4), (3, 1, 1))
    ego[1, :3, 3] = [3.0, 4.0, 0.0]
    ego[2, :3, 3] = [1.0, 0.0, 0.0]
    assert ego_travel_m(ego) == pytest.approx(5.0)
    assert ego_travel_m(np.stack([ego, ego], axis=1)) == pytest.approx(5.0)  # one pose per camera


@pytest.fixture(scope="module")
def creeping():
    """Six frames in windows of two: driving 1 m per frame, then creeping 5 cm, then standing still."""
    with torch_threads(1):
        rig_true, rig, images = box_world_rig(n_frames=6)
        ego = [f.ego_to_world.copy() for f in rig.frames]
        base = ego[2].copy()
        for t, dx in ((3, 0.05), (4, 0.10), (5, 0.10)):
            ego[t] = base.copy()
            ego[t][0, 3] += dx
        frames = tuple(Frame(f.id, f.timestamp_us, e) for f, e in zip(rig.frames, ego))
        textures = [noise_texture(1024, k) for k in range(6)]
        for f in frames[3:]:
            images[f.id] = {c.name: render_box_world(c, f.ego_to_world, textures) for c in rig_true.cameras}
    return replace(rig_true, frames=frames), replace(rig, frames=frames), images


def test_a_creeping_window_does_not_replace_a_precise_calibration(creeping):
    rig_true, rig, images = creeping
    cache: dict = {}
    out, block = calibrate(rig, lambda f, c: images[f][c], window=2, match_cache=cache)
    w0, w1, w2 = block["windows"]
    assert [round(w["ego_travel_m"], 3) for w in block["windows"]] == [1.0, 0.05, 0.0]
    assert w0["accepted"] and max(p["rotation_sigma_deg"] for p in w0["pairs"]) < 0.1
    assert not w1["accepted"] and w1["rule"] == "less_precise" and "the calibration in effect is kept" in w1["reason"]
    assert max(p["rotation_sigma_deg"] for p in w1["pairs"]) > 0.2
    # standing still: rejected by the adjustment's own rules, with the cause named
    assert not w2["accepted"] and w2["rule"] in ("weakly_constrained", "not_converged", "less_precise")
    if w2["rule"] != "less_precise":
        assert "the ego moved 0.000 m over the window" in w2["reason"]
    assert len(block["history"]) == 1 and len(block["history"][0]["pair_rotation_sigma_deg"]) == 6
    kept = max(r["rotation_deg"] for r in relative_pose_errors(out, rig_true))
    assert kept < 0.06
    # without the rule the creeping window replaces it and the rig comes out several times worse
    loose, block = calibrate(rig, lambda f, c: images[f][c], window=2, match_cache=cache, frames=slice(0, 4),
                             rules=AcceptanceRules(min_correspondences=default_beta(rig), max_sigma_ratio=1e9))
    assert [w["accepted"] for w in block["windows"]] == [True, True]
    assert max(r["rotation_deg"] for r in relative_pose_errors(loose, rig_true)) > 3 * kept
