"""Guided matching on narrow overlaps and the one-mount consistency check (runtime ~10 s)."""

import cv2
import numpy as np
import pytest

from sgde_plugin.calib.correspondences import MatchConfig, find_correspondences
from sgde_plugin.calib.guided import epipolar_segment, guided_search
from sgde_plugin.calib.outliers import epipolar_angle_deg, mount_consensus
from sgde_plugin.calib.pipeline import window_ego_poses
from sgde_plugin.geometry import make_transform, rodrigues


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.uniform(0, 255, (h // 4, w // 4)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_epipolar_segment_ends_at_infinity_and_at_the_nearest_depth():
    K = np.array([[200.0, 0, 100], [0, 200.0, 80], [0, 0, 1]])
    rel = make_transform(np.eye(3), np.array([-0.5, 0.0, 0.0]))  # b is 0.5 m right of a
    far, near, ok = epipolar_segment(np.array([[120.0, 80.0]]), K, K, rel, 2.0)
    assert ok.all() and np.allclose(far, [[120.0, 80.0]])
    # a ray of a at 2 m ray depth, seen from b: disparity f * B / z
    ray = np.array([20.0, 0.0, 200.0]) / np.linalg.norm([20.0, 0.0, 200.0])
    z = 2.0 * ray[2]
    assert np.allclose(near, [[120.0 - 200.0 * 0.5 / z, 80.0]], atol=1e-9)


def test_guided_search_finds_a_shifted_texture_to_a_tenth_of_a_pixel():
    """View b is view a seen from 0.4 m to the right, a fronto-parallel wall at 8 m: disparity 10.25 px.
    Rotated by 1 deg in the prediction (the starting rig's error), the band still holds the truth."""
    h, w, f = 120, 160, 205.0
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    a = _texture(h, w)
    disparity = f * 0.4 / 8.0
    b = cv2.warpAffine(a, np.array([[1.0, 0, -disparity], [0, 1.0, 0]]), (w, h), flags=cv2.INTER_CUBIC)
    valid = np.ones((h, w), bool)
    rng = np.random.default_rng(1)
    uv = np.c_[rng.uniform(30, w - 20, 80), rng.uniform(15, h - 15, 80)]
    rel = make_transform(rodrigues(np.radians([0.0, 1.0, 0.0])), np.array([-0.4, 0.0, 0.0]))
    idx, uv_b = guided_search(a, valid, b, valid, uv, K, K, rel)
    assert idx.size >= 60  # most of the textured points are found
    err = np.linalg.norm(uv_b - (uv[idx] - [disparity, 0.0]), axis=1)
    assert np.median(err) < 0.05 and err.max() < 0.3
    # a flat image has nothing to find
    idx, _ = guided_search(np.full_like(a, 128), valid, b, valid, uv, K, K, rel)
    assert idx.size == 0


def test_mount_consensus_recovers_the_mount_and_flags_outliers():
    """Matches of one camera pair at 6 frame pairs (ego moving 1 m per frame): the starting mount of b is
    0.8 deg / 4 cm off; the fitted correction brings every true match within 0.1 px and the wrong ones
    (20 %) stay over 1.5 px."""
    rng = np.random.default_rng(0)
    f = 300.0
    S_a = make_transform(np.eye(3), np.zeros(3))
    S_b_true = make_transform(rodrigues(np.radians([0.0, -60.0, 0.0])), np.array([0.8, 0.0, -0.3]))
    D = make_transform(rodrigues(np.radians([0.3, 0.6, -0.4])), np.array([0.03, -0.02, 0.02]))
    S_b0 = S_b_true @ np.linalg.inv(D)  # the starting mount: b's true mount = S_b0 D
    rel0, ra, rb, bad = [], [], [], []
    for t, t2 in [(0, 0), (1, 1), (0, 2), (1, 3), (2, 4), (0, 5)]:
        ego = [make_transform(np.eye(3), np.array([0.0, 0.0, 1.0 * k])) for k in (t, t2)]  # driving along a's z
        A, B = ego[0] @ S_a, ego[1] @ S_b_true
        n = 60
        d = np.c_[rng.normal(0.7, 0.2, n), rng.normal(0, 0.2, n), np.ones(n)]
        X = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(5, 30, (n, 1))
        Xw = X @ A[:3, :3].T + A[:3, 3]
        Xb = (Xw - B[:3, 3]) @ B[:3, :3]
        r_b = Xb / np.linalg.norm(Xb, axis=1, keepdims=True)
        wrong = rng.random(n) < 0.2
        r_b[wrong] = r_b[wrong] @ rodrigues(np.radians([0.0, 0.0, 1.5])).T
        rel0.append(np.repeat((np.linalg.inv(ego[1] @ S_b0) @ A)[None], n, axis=0))
        ra.append(X / np.linalg.norm(X, axis=1, keepdims=True))
        rb.append(r_b)
        bad.append(wrong)
    rel0, ra, rb, bad = np.concatenate(rel0), np.concatenate(ra), np.concatenate(rb), np.concatenate(bad)
    _, start = mount_consensus(rel0, ra, rb, f, iterations=0)
    assert np.median(np.abs(start[~bad])) > 1.5  # the starting mount is visibly off
    d, err = mount_consensus(rel0, ra, rb, f)
    assert np.abs(err[~bad]).max() < 0.1  # the weak priors pull a little
    assert (np.abs(err[bad]) > 1.5).mean() > 0.95
    assert np.allclose(d[:3], np.radians([0.3, 0.6, -0.4]), atol=np.radians(0.01))


@pytest.fixture(scope="module")
def narrow_seq():
    from sgde_plugin.synth.sequence import synth_sequence

    return synth_sequence("random", 4, seed=12, scale=0.5)  # CAM_00-CAM_01: a 9.8-degree unblocked overlap


def _true_epipolar_px(seq, ids, a, b, pm):
    """Distance (px) of each match to its epipolar line under the true rig."""
    ca, cb = seq.rig_true.camera(a), seq.rig_true.camera(b)
    out = np.zeros(len(pm))
    for k, (t, t2) in enumerate(zip(pm.frame_a, pm.frame_b)):
        A = seq.rig_true.frame(ids[t]).ego_to_world @ ca.sensor_to_ego
        B = seq.rig_true.frame(ids[t2]).ego_to_world @ cb.sensor_to_ego
        rel = np.linalg.inv(B) @ A
        out[k] = np.radians(epipolar_angle_deg(pm.rays_a[k:k + 1], pm.rays_b[k:k + 1], rel[:3, :3], rel[:3, 3]))[0]
    return out * cb.intrinsics.K[0, 0]


def test_guided_matching_raises_a_narrow_overlaps_observation_pairs_over_beta(narrow_seq):
    """Rendered random rig (seed 12), the 9.8-degree overlap CAM_00-CAM_01 over 4 frames from the noisy start:
    descriptor matching alone verifies fewer than beta = 15 inliers in every observation pair (at most 9, 17 in
    all); with guided matching an observation pair passes and the window's inliers grow several-fold (measured
    since session 15's views cut to the camera's data: 107 in all, observation pairs of 18, 13, 13, 13; before,
    109 with 18 and 15, the second exactly at beta), and the matches lie within a pixel of the true epipolar
    lines. Guided matching (opt-in) was developed on bilinear views; with the Lanczos views of session 6 no
    observation pair of this overlap reaches 15 (README, known limits), so this test keeps bilinear views."""
    seq = narrow_seq
    rig, ids = seq.rig, [f.id for f in seq.rig.frames]
    ego = window_ego_poses(rig, rig.frames, rig.camera_names)
    out = {}
    for below in (0, 30):
        (pm,) = find_correspondences(list(rig.cameras), [("CAM_00", "CAM_01")], ego,
                                     lambda t, c: seq.images[ids[t]][c], None,
                                     MatchConfig(guided_below=below, view_interpolation="linear"))
        out[below] = pm
    plain, guided = out[0], out[30]
    assert max(o.inliers for o in plain.observation_pairs) < 15
    passing = [o for o in guided.observation_pairs if o.inliers >= 15]
    assert len(passing) >= 1
    assert guided.inliers >= 4 * plain.inliers
    err = _true_epipolar_px(seq, ids, "CAM_00", "CAM_01", guided)
    assert np.median(err) < 0.5 and np.mean(err < 1.5) > 0.85


def test_level_views_of_a_pair_share_one_orientation_and_antialias_blurs_the_coarser_view():
    """Two pinholes 55 deg apart, one pitched 12 deg down and rolled 2 deg, the other pitched 2 deg up: their
    own-axis overlap views differ by several degrees of roll, the level views by < 0.5 deg; a view that
    samples its source 1.7x coarser, with `antialias`, low-passes a 1-px checkerboard instead of aliasing it."""
    from sgde_plugin.calib.overlap import overlap_grid
    from sgde_plugin.calib.views import overlap_view
    from sgde_plugin.cameras import Camera, Pinhole
    from sgde_plugin.geometry import camera_mount
    from sgde_plugin.stereo.rectify import torch_threads

    K = np.array([[120.0, 0, 119.5], [0, 120.0, 79.5], [0, 0, 1]])
    a = Camera("A", Pinhole(240, 160, K), camera_mount(0.0, np.array([1.5, 0.0, 1.6]), np.radians(12), np.radians(2)))
    K_b = np.array([[300.0, 0, 119.5], [0, 300.0, 79.5], [0, 0, 1]])  # 2.5x finer than A
    b = Camera("B", Pinhole(240, 160, K_b), camera_mount(np.radians(-55), np.array([1.0, -0.8, 1.5]), np.radians(-2)))
    rolls = {}
    with torch_threads(1):
        gab = overlap_grid(a, b, np.eye(4)[None], margin_px=0.0)
        gba = overlap_grid(b, a, np.eye(4)[None], margin_px=0.0)
        for level in (False, True):
            va = overlap_view(a, gab, other=b, crop=True, level=level)
            vb = overlap_view(b, gba, other=a, crop=True, level=level)
            D = va.camera.sensor_to_ego[:3, :3].T @ vb.camera.sensor_to_ego[:3, :3]
            rolls[level] = abs(np.degrees(np.arctan2(D[1, 0], D[0, 0])))
    assert rolls[False] > 3.0 and rolls[True] < 0.5
    assert vb.step > 1.5 and np.isclose(va.step, 1.0, rtol=0.05)  # B is 2.5x finer on axis, 1.7x at A's edge
    checker = ((np.indices((160, 240)).sum(0) % 2) * 255).astype(np.uint8)
    inside = vb.valid
    aliased = vb.warp(checker)[inside].astype(float)
    smooth = vb.warp(checker, antialias=True)[inside].astype(float)
    assert aliased.std() > 30 and smooth.std() < 10 and abs(smooth.mean() - 127.5) < 10
