"""Depth metrics, OmniMVS metrics and Dep Con on tiny hand-computed cases (runtime < 1 s)."""

import math

import numpy as np
import pytest
import torch

from sgde_plugin.cameras import Camera, KannalaBrandt, Pinhole
from sgde_plugin.metrics import (
    average_metrics,
    dep_con,
    depth_metrics,
    inverse_depth_index,
    omnimvs_metrics,
    rig_dep_con,
    warp_depth,
)


def test_depth_metrics_hand_values():
    m = depth_metrics(np.array([1.5, 4.0]), np.array([2.0, 4.0]))
    assert m["n"] == 2
    assert m["abs_rel"] == pytest.approx(0.125)  # (0.5/2 + 0) / 2
    assert m["sq_rel"] == pytest.approx(0.0625)  # (0.25/2 + 0) / 2
    assert m["rmse"] == pytest.approx(math.sqrt(0.125))
    assert m["rmse_log"] == pytest.approx(math.log(4 / 3) / math.sqrt(2))
    assert (m["a1"], m["a2"], m["a3"]) == (0.5, 1.0, 1.0)  # max ratio 4/3 > 1.25
    # the same from torch tensors
    mt = depth_metrics(torch.tensor([1.5, 4.0]), torch.tensor([2.0, 4.0]))
    assert all(mt[k] == pytest.approx(m[k]) for k in m)


def test_depth_metrics_mask_range_and_median_scaling():
    gt = np.array([[2.0, 4.0], [0.0, 100.0]])
    pred = np.array([[1.5, 4.0], [9.0, 9.0]])
    m = depth_metrics(pred, gt, max_depth=80.0)  # gt 0 and gt 100 > 80 drop out
    assert m["n"] == 2 and m["abs_rel"] == pytest.approx(0.125)
    m = depth_metrics(pred, gt, mask=np.array([[False, True], [True, True]]), max_depth=80.0)
    assert m["n"] == 1 and m["abs_rel"] == 0.0
    # clipping: a prediction beyond max_depth counts as max_depth
    assert depth_metrics(np.array([200.0]), np.array([40.0]))["abs_rel"] == pytest.approx(1.0)
    scaled = depth_metrics(2 * gt[0], gt[0], median_scaling=True)
    assert scaled["scale"] == pytest.approx(0.5) and scaled["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    empty = depth_metrics(pred, np.zeros_like(gt))
    assert empty["n"] == 0 and math.isnan(empty["abs_rel"])


def test_average_metrics():
    rows = [{"abs_rel": 0.1, "n": 4}, {"abs_rel": 0.3, "n": 2}, {"abs_rel": math.nan, "n": 0}]
    avg = average_metrics(rows)
    assert avg["abs_rel"] == pytest.approx(0.2) and avg["n"] == 6 and avg["images"] == 2


def test_omnimvs_metrics_hand_values():
    m = omnimvs_metrics(np.array([0.0, 2.0, 10.0, 0.0]), np.zeros(4), num_invdepth=100, as_index=True)
    # errors in % of the index range: 0, 2, 10, 0
    assert m[">1"] == 50.0 and m[">3"] == 25.0 and m[">5"] == 25.0
    assert m["mae"] == pytest.approx(3.0) and m["rms"] == pytest.approx(math.sqrt(26.0))
    # index of OmniMVS: min depth 0.5 m, 192 levels, no far limit: 1 m -> 95.5, 0.5 m -> 191
    assert inverse_depth_index(np.array([1.0, 0.5]), 0.5, math.inf, 192) == pytest.approx([95.5, 191.0])
    d = omnimvs_metrics(np.array([1.0, 1.0]), np.array([1.0, 0.5]))
    assert d["n"] == 2 and d["mae"] == pytest.approx((0 + 95.5 / 192 * 100) / 2)
    # gt 0 (no value) and gt nearer than min_depth (index > N) are not evaluated
    assert omnimvs_metrics(np.array([1.0, 1.0]), np.array([0.0, 0.2]))["n"] == 0


def _pinhole(w=8, h=4, f=10.0):
    return Pinhole(w, h, K=np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]]))


def test_dep_con_hand_value():
    # two identical pinholes, the neighbour 1 m to the right; plane z = 10 m in view of both.
    # A neighbour pixel u lands at u + f * 1 / 10 = u + 1 in the camera: columns 1..7 receive depth.
    cam = _pinhole()
    T = np.eye(4)
    T[0, 3] = 1.0
    gt = np.full((4, 8), 10.0)
    res = dep_con(np.full((4, 8), 11.0), np.full((4, 8), 10.0), gt, cam, cam, T)
    assert res["n"] == 7 * 4
    assert res["dep_con"] == pytest.approx(0.1)
    warped = warp_depth(np.full((4, 8), 10.0), cam, cam, T)
    assert np.all(warped[:, 0] == 0) and np.allclose(warped[:, 1:], 10.0)


def test_rig_dep_con_consistent_predictions_score_zero():
    cam = _pinhole()
    pose_b = np.eye(4)
    pose_b[0, 3] = 1.0
    cams = {"A": Camera("A", cam, np.eye(4)), "B": Camera("B", cam, pose_b)}
    depth = {"A": np.full((4, 8), 10.0), "B": np.full((4, 8), 10.0)}
    res = rig_dep_con(depth, depth, cams, [("A", "B")])
    assert res["n"] == 2 * 7 * 4 and res["dep_con"] == pytest.approx(0.0, abs=1e-12)
    inconsistent = {"A": np.full((4, 8), 10.0), "B": np.full((4, 8), 12.0)}
    assert rig_dep_con(inconsistent, depth, cams, [("A", "B")])["dep_con"] > 0.1


def test_warp_depth_fisheye_identity_keeps_range():
    kb = KannalaBrandt(16, 16, K=np.array([[4.0, 0, 7.5], [0, 4.0, 7.5], [0, 0, 1]]), fov_deg=200)
    depth = np.linspace(2, 20, 256).reshape(16, 16) * kb.valid_mask()
    warped = warp_depth(depth, kb, kb, np.eye(4))
    assert np.allclose(warped, depth, atol=1e-9)
