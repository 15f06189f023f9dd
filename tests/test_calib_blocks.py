"""Blocks of a partially linked window and their placement (calib/blocks.py; runtime < 1 s)."""

from dataclasses import replace

import numpy as np

from sgde_plugin.calib.acceptance import Verdict, unconstrained_cameras
from sgde_plugin.calib.blocks import between_blocks, fit_block, linked_blocks, place_blocks
from sgde_plugin.calib.methods import MethodResult
from sgde_plugin.calib.pipeline import Judged, _common_blocks, _phases_rejected, _same_blocks
from sgde_plugin.geometry import invert_transform, make_transform, rodrigues, rotation_angle_deg


def _pose(rng, spread_m=1.5):
    return make_transform(rodrigues(rng.normal(size=3)), rng.normal(scale=spread_m, size=3))


def test_linked_blocks_and_the_pairs_between_them():
    cams = ["A", "B", "C", "D", "E", "F"]
    ring = [("A", "B"), ("B", "C"), ("C", "D"), ("D", "E"), ("E", "F"), ("F", "A")]
    assert linked_blocks(cams, ring) == [tuple(cams)]
    observed = [("A", "B"), ("D", "E"), ("F", "A")]
    blocks = linked_blocks(cams, observed)
    assert blocks == [("A", "B", "F"), ("C",), ("D", "E")]
    assert between_blocks(ring, blocks) == [("B", "C"), ("C", "D"), ("E", "F")]
    assert between_blocks(ring, [tuple(cams)]) == []
    assert unconstrained_cameras(cams, observed, "A") == ["C", "D", "E"]
    assert unconstrained_cameras(cams, observed, "D") == ["A", "B", "C", "F"]
    assert linked_blocks(["A", "B"], []) == [("A",), ("B",)]


def test_a_block_moved_rigidly_is_put_back_and_keeps_its_relative_poses():
    rng = np.random.default_rng(3)
    start = {n: _pose(rng) for n in "ABCD"}
    C = make_transform(rodrigues(np.radians([0.8, -1.5, 0.6])), np.array([0.07, -0.03, 0.05]))
    moved = {n: C @ start[n] for n in "ABCD"}
    assert np.allclose(fit_block(moved, start, "ABC"), invert_transform(C), atol=1e-12)
    placed = place_blocks(moved, start, [("A", "B", "C"), ("D",)])
    for n in "ABCD":
        assert np.allclose(placed[n], start[n], atol=1e-12)


def test_the_fit_averages_independent_start_errors_and_keeps_the_block_rigid():
    rng = np.random.default_rng(4)
    truth = {n: _pose(rng) for n in "ABCDEF"}
    # the start: every camera off by its own 1 deg / 5 cm; the adjusted block: exact relative poses, anywhere
    start = {n: make_transform(rodrigues(rng.normal(size=3) * np.radians(1.0) / np.sqrt(3)),
                               rng.normal(scale=0.05 / np.sqrt(3), size=3)) @ T for n, T in truth.items()}
    anywhere = make_transform(rodrigues(np.array([0.3, 0.2, -0.4])), np.array([2.0, -1.0, 0.5]))
    adjusted = {n: anywhere @ T for n, T in truth.items()}
    placed = place_blocks(adjusted, start, [tuple("ABCDEF")])
    for a in "ABCDEF":
        for b in "ABCDEF":
            rel = invert_transform(placed[a]) @ placed[b]
            assert np.allclose(rel, invert_transform(truth[a]) @ truth[b], atol=1e-9)
    # placed by the fit: its offset from the truth is the mean of six independent errors, so well under one
    off_deg = rotation_angle_deg((placed["A"] @ invert_transform(truth["A"]))[:3, :3])
    each_deg = [rotation_angle_deg((start[n] @ invert_transform(truth[n]))[:3, :3]) for n in "ABCDEF"]
    assert off_deg < 0.75 * float(np.mean(each_deg))
    # exactly the least-squares placement: a small turn or shift of the placed block raises the misfit
    def misfit(P):
        return sum(np.sum((P[n][:3, 3] - start[n][:3, 3]) ** 2) for n in P)
    base = misfit(placed)
    for d in np.eye(3) * 1e-3:
        for nudge in (make_transform(np.eye(3), d), make_transform(np.eye(3), -d)):
            assert misfit({n: nudge @ T for n, T in placed.items()}) > base


def test_view_phase_runs_are_averaged_only_with_runs_linked_alike():
    def run(blocks, rule=None):
        return Judged(Verdict(True) if rule is None else Verdict(False, rule, "why"), None, [], [], blocks=blocks)

    split = [("A", "B"), ("C",)]
    whole, a, b = run([]), run(split), run(split)
    assert _same_blocks([whole, a, b]) == [a, b]
    assert _same_blocks([whole, a]) == [whole]  # a tie: the first run's linking
    assert _same_blocks([]) == []
    # four runs, two linked whole and two split: no linking is shared by more than half
    rejected = _phases_rejected([whole, run([]), a, b], 2)
    assert rejected.verdict.rule == "min_correspondences" and "different blocks" in rejected.verdict.reason
    assert rejected.verdict.reason.startswith("2 of 4 view phases accepted with the same cameras linked")
    rejected = _phases_rejected([whole, run([], "weakly_constrained"), a, b], 2)
    assert rejected.verdict.rule == "weakly_constrained" and rejected.verdict.reason.endswith("first rejected: why")


def test_runs_linked_differently_are_averaged_on_the_blocks_they_all_share():
    rng = np.random.default_rng(5)
    start = {n: _pose(rng) for n in "ABCD"}
    turn = make_transform(rodrigues(np.radians([0.5, 1.0, -0.7])), np.array([0.02, 0.05, -0.03]))
    # run 1 links everything and moves D; run 2 leaves D alone (placed at its start); A, B, C agree
    one = {**start, "D": turn @ start["D"]}
    sigma = {("A", "B"): 0.01, ("B", "C"): 0.01, ("C", "D"): 0.01, ("D", "A"): 0.01}
    runs = [Judged(Verdict(True), MethodResult(one, pair_rotation_sigma_deg=sigma), [], [], blocks=[]),
            Judged(Verdict(True), MethodResult(dict(start), pair_rotation_sigma_deg=sigma), [], [],
                   blocks=[("A", "B", "C"), ("D",)], not_linked="camera(s) D not linked to A")]
    common = _common_blocks(runs, start)
    assert [r.blocks for r in common] == [[("A", "B", "C"), ("D",)]] * 2
    for r in common:
        assert np.allclose(r.result.sensor_to_ego["D"], start["D"], atol=1e-12)
        assert set(r.result.pair_rotation_sigma_deg) == {("A", "B"), ("B", "C")}
        assert r.not_linked.startswith("camera(s) D not linked to A; the view phases link the cameras differently")
    # runs that share no two linked cameras give nothing to average
    apart = [replace(runs[1], blocks=[("A", "B"), ("C",), ("D",)]), replace(runs[1], blocks=[("A",), ("B", "C", "D")])]
    assert _common_blocks(apart, start) == []
