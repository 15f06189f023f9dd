"""Per-camera focal-length scale in the loop-constrained adjustment (AdjustConfig.refine_focal)."""

import numpy as np
import pytest
from test_calib_ba import assert_pose_jacobian, rel_errors, ring

from sgde_plugin.calib import AdjustConfig, calibrate
from sgde_plugin.calib.ba import Observations, _Problem, initial_points, robust_adjust
from sgde_plugin.calib.focal import focal_map
from sgde_plugin.calib.simulate import (
    box_world_rig,
    noise_texture,
    perturb_extrinsics,
    render_box_world,
    simulate_observations,
    straight_drive,
)
from sgde_plugin.cameras import Camera, KannalaBrandt, Pinhole
from sgde_plugin.geometry import invert_transform, make_transform
from sgde_plugin.pairs import relative_pose_errors
from sgde_plugin.rig import read_rig_json, write_rig_json
from sgde_plugin.stereo.rectify import torch_threads
from sgde_plugin.synth.presets import equidistant_ocam

K_PIN = np.array([[500.0, 0, 399.5], [0, 500, 224.5], [0, 0, 1]])
MODELS = {
    "pinhole": Pinhole(800, 450, K_PIN),
    "pinhole_radial": Pinhole(800, 450, K_PIN, np.array([-0.1, 0.02, 0.0, 0.0, 0.001])),
    "kannala_brandt": KannalaBrandt(800, 768, np.array([[250.0, 0, 399.5], [0, 250, 383.5], [0, 0, 1]]),
                                    np.array([0.01, -0.002, 0.0003, 0.0]), 200.0),
    "ocam": equidistant_ocam(800, 768, 200.0),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_focal_map_gives_the_rays_of_the_scaled_camera(name):
    """A direction imaged by the camera with its focal length x 1.008 lands on the pixel whose ray under the
    rig's intrinsics is the map's output; the map's Jacobians match finite differences; s = 1 is the identity."""
    model, s = MODELS[name], 1.008
    fm = focal_map(model)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [model.width - 1, model.height - 1], (400, 2))
    true_rays, ok = model.with_focal_scale(s).unproject(uv)
    rig_rays, ok2 = model.unproject(uv)
    ok &= ok2
    q = true_rays[ok] * rng.uniform(0.5, 3.0, (int(ok.sum()), 1))
    v, dv_dq, dv_ds = fm.apply(q, s)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.abs(v - rig_rays[ok]).max() < 1e-7  # radians: < 1e-4 px here
    moved = np.degrees(np.arccos(np.clip(np.sum(true_rays[ok] * rig_rays[ok], axis=1), -1, 1)))
    assert moved.max() > 0.2  # the scale is not negligible at the image edges
    eps = 1e-6
    for k in range(3):
        dq = np.zeros(3)
        dq[k] = eps
        fd = (fm.apply(q + dq, s)[0] - fm.apply(q - dq, s)[0]) / (2 * eps)
        assert np.abs(fd - dv_dq[:, :, k]).max() < 1e-4 * max(1.0, np.abs(fd).max()), k
    fd = (fm.apply(q, s + eps)[0] - fm.apply(q, s - eps)[0]) / (2 * eps)
    assert np.abs(fd - dv_ds).max() < 1e-4 * np.abs(fd).max()
    same, _, _ = fm.apply(q, 1.0)
    assert np.allclose(same / np.linalg.norm(same, axis=1, keepdims=True),
                       q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12)


def test_tangential_distortion_gets_no_focal_unknown():
    assert focal_map(Pinhole(800, 450, K_PIN, np.array([0.0, 0.0, 1e-3, 0.0, 0.0]))) is None


def _ring_observations(bad: int | None, scale: float, seed: int = 8):
    """The ring of test_calib_ba seen by cameras whose `bad` one has its focal length x `scale` (true),
    with rays from the rig's (unscaled) intrinsics; 0.3 px noise."""
    cams, f = ring()
    M = len(cams)
    pairs = [(m, (m + 1) % M) for m in range(M)]
    ego = straight_drive(3, 1.5, 2.0)
    S_true = np.stack([c.sensor_to_ego for c in cams])
    S0 = perturb_extrinsics(S_true, 1.0, 0.05, np.random.default_rng(4))
    true_cams = [Camera(c.name, c.intrinsics.with_focal_scale(scale), c.sensor_to_ego) if m == bad else c
                 for m, c in enumerate(cams)]
    obs, _, _ = simulate_observations(true_cams, pairs, ego, per_view_pair=20, noise_px=0.3,
                                      rng=np.random.default_rng(seed))
    rays = obs.ray.copy()
    if bad is not None:  # the pixel's ray under the rig's focal length: x, y times the scale
        rays[obs.camera == bad] *= [scale, scale, 1.0]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    obs = Observations(obs.camera, obs.frame, obs.point, rays, np.full(len(obs), 0.3))
    return cams, f, pairs, ego, S_true, S0, obs


def _both(cams, f, ego, S0, obs):
    maps = [focal_map(c.intrinsics) for c in cams]
    focal = np.full(len(cams), f)
    fixed, _ = robust_adjust(S0, ego, obs, focal, config=AdjustConfig(refine_focal=False), focal_maps=maps)
    refined, _ = robust_adjust(S0, ego, obs, focal, config=AdjustConfig(refine_focal=True), focal_maps=maps)
    return fixed, refined


@pytest.mark.parametrize("bad", [2, 0])
def test_a_focal_length_off_by_0_8_percent_is_recovered(bad):
    """Camera `bad` (0 is the reference camera, which carries the gauge) images with a focal length 0.8 %
    longer than the rig says: its scale is adopted (about 16 sigma) and lands within 0.15 % (3 sigma; sigma
    about 0.05 %) of 1.008, the others' free estimates stay within 0.15 % of 1 and are not adopted, and the
    ring's relative rotations are better than with fixed intrinsics (max error 0.12-0.16 deg fixed, < 0.04
    deg refined)."""
    cams, f, pairs, ego, S_true, S0, obs = _ring_observations(bad, 1.008)
    fixed, refined = _both(cams, f, ego, S0, obs)
    rot_fixed, _ = rel_errors(fixed.sensor_to_ego, S_true, pairs)
    rot, trans = rel_errors(refined.sensor_to_ego, S_true, pairs)
    s, free = refined.focal_scale, refined.focal_scale_free
    assert abs(s[bad] - 1.008) < 0.0015 and abs(free[bad] - 1.008) < 0.0015
    assert np.all(np.delete(s, bad) == 1.0) and np.abs(np.delete(free, bad) - 1.0).max() < 0.0015
    assert np.all((refined.focal_scale_sigma > 2e-4) & (refined.focal_scale_sigma < 1e-3))
    assert rot_fixed.max() > 0.1 and rot.max() < 0.04 and rot.max() < 0.4 * rot_fixed.max()
    assert trans.max() < 0.015
    assert refined.final_rms_px < fixed.final_rms_px


def test_exact_intrinsics_stay():
    """With exact intrinsics every free estimate stays within 0.1 % of 1, none is significant, and the result
    is the fixed-intrinsics one, unchanged, whether those passes ran beside the free ones or after them."""
    cams, f, pairs, ego, S_true, S0, obs = _ring_observations(None, 1.0)
    fixed, refined = _both(cams, f, ego, S0, obs)
    assert np.abs(refined.focal_scale_free - 1.0).max() < 0.001
    assert np.all(refined.focal_scale == 1.0)
    assert np.array_equal(refined.sensor_to_ego, fixed.sensor_to_ego) and refined.iterations == fixed.iterations
    one_thread, _ = robust_adjust(S0, ego, obs, np.full(len(cams), f), config=AdjustConfig(threads=1),
                                  focal_maps=[focal_map(c.intrinsics) for c in cams])
    assert np.array_equal(one_thread.sensor_to_ego, refined.sensor_to_ego)
    assert np.array_equal(one_thread.focal_scale_free, refined.focal_scale_free)
    rot, _ = rel_errors(refined.sensor_to_ego, S_true, pairs)
    assert rot.max() < 0.04


def test_jacobians_with_focal_scales_match_finite_differences():
    cams, f, pairs, ego, S_true, S0, obs = _ring_observations(1, 1.008)
    sub = obs.point < 60
    obs = Observations(obs.camera[sub], obs.frame[sub], obs.point[sub], obs.ray[sub], obs.sigma_px[sub])
    maps = [focal_map(c.intrinsics) for c in cams]
    maps[4] = focal_map(MODELS["ocam"])  # the tabulated map in the same problem
    prob = _Problem(S0, ego, obs, np.full(len(cams), f), 0, AdjustConfig(refine_focal=True), focal_maps=maps)
    n_pts = int(obs.point.max()) + 1
    st = prob.initial_state(n_pts)
    ego0 = np.einsum("tij,jk->tik", make_transform(st.R_t, st.c_t), invert_transform(S0[0]))
    pts, anchors, _ = initial_points(S0, ego0, obs, n_pts)
    st.set_points(pts + 0.3, anchors)
    zero = np.zeros((n_pts, 3))
    st = prob.apply(st, np.random.default_rng(3).normal(scale=0.01, size=prob.n_full), zero)
    assert prob.pose_idx.shape[1] == 13 and np.abs(st.s - 1).max() > 1e-3
    assert_pose_jacobian(prob, st, list(prob.solve_idx[::7]) + list(prob.f_idx + np.arange(len(cams))), 1e-4)


def test_calibrate_writes_the_refined_focal_length(tmp_path):
    """Images of the box world where camera C3's focal length is 1 % longer than the rig says: `calibrate`
    with refine_focal reports C3's change (+1 % within 0.3 %) and its sigma, and the written rig carries it."""
    with torch_threads(1):
        rig_true, rig, images = box_world_rig(n_frames=3)
        cam = rig_true.camera("C3")
        long = Camera("C3", cam.intrinsics.with_focal_scale(1.01), cam.sensor_to_ego)
        textures = [noise_texture(1024, k) for k in range(6)]
        for fr in rig_true.frames:
            images[fr.id]["C3"] = render_box_world(long, fr.ego_to_world, textures)
    out, block = calibrate(rig, lambda fid, c: images[fid][c], method="glc",
                           adjust_config=AdjustConfig(refine_focal=True))
    w = block["windows"][0]
    assert w["accepted"]
    rows = {r["camera"]: r for r in w["focal"]}
    assert abs(rows["C3"]["change_pct"] - 1.0) < 0.3 and 0 < rows["C3"]["sigma_pct"] < 0.3
    assert max(abs(r["change_pct"]) for n, r in rows.items() if n != "C3") < 0.3
    write_rig_json(out, tmp_path / "rig.json")
    back = read_rig_json(tmp_path / "rig.json")
    fx = back.camera("C3").intrinsics.K[0, 0]
    assert np.isclose(fx, rows["C3"]["fx_after"]) and np.isclose(rows["C3"]["fx_before"], cam.intrinsics.K[0, 0])
    assert block["history"][0]["intrinsics"]["C3"]["K"][0][0] == pytest.approx(fx)
    rot = np.array([r["rotation_deg"] for r in relative_pose_errors(out, rig_true)])
    assert rot.max() < 0.15
