"""Loop-constrained bundle adjustment on simulated correspondences (runtime ~5 s on 2 cores)."""

import numpy as np
import pytest

from sgde_plugin.calib.ba import (
    AdjustConfig,
    Observations,
    _Problem,
    adjust,
    initial_points,
    relative_rotation_sigma_deg,
    robust_adjust,
)
from sgde_plugin.calib.correspondences import PairMatches
from sgde_plugin.calib.methods import observations
from sgde_plugin.calib.schur import inverse_cholesky, point_blocks, point_sums, point_terms, reduced_system
from sgde_plugin.calib.simulate import perturb_extrinsics, simulate_observations, straight_drive
from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.geometry import (
    camera_mount,
    invert_transform,
    make_transform,
    rodrigues,
    rotation_angle_deg,
    rotation_vector,
)


def ring(n=6, width=400, height=225, hfov=80.0, scale=1.0):
    f = (width / 2) / np.tan(np.radians(hfov / 2))
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    cams = []
    for m in range(n):
        yaw = -2 * np.pi * m / n
        pos = scale * np.array([1.0 * np.cos(yaw) + 0.8, 0.8 * np.sin(yaw), 1.6])
        cams.append(Camera(f"C{m}", Pinhole(width, height, K), camera_mount(yaw, pos)))
    return cams, f


def assert_pose_jacobian(prob, st, columns, rel_tol):
    """The analytic d r / d (pose column k) of `prob` at `st` matches central differences, for each k."""
    r, Jp, _ = prob.obs_terms(st, jacobians=True)
    zero = np.zeros((len(st.rho), 3))
    for k in columns:
        dp = np.zeros(prob.n_full)
        dp[k] = 1e-6
        fd = (prob.obs_terms(prob.apply(st, dp, zero), False) - prob.obs_terms(prob.apply(st, -dp, zero), False)) / 2e-6
        an = np.zeros_like(r)
        for j in range(prob.pose_idx.shape[1]):
            hit = prob.pose_idx[:, j] == k
            an[hit] += Jp[hit, :, j]
        assert np.allclose(an, fd, atol=rel_tol * max(1.0, np.abs(fd).max())), k


def rel_errors(S, S_true, pairs):
    rot, trans = [], []
    for a, b in pairs:
        e = np.linalg.inv(S[a]) @ S[b]
        t = np.linalg.inv(S_true[a]) @ S_true[b]
        rot.append(float(rotation_angle_deg(e[:3, :3].T @ t[:3, :3])))
        trans.append(float(np.linalg.norm(e[:3, 3] - t[:3, 3])))
    return np.array(rot), np.array(trans)


@pytest.fixture(scope="module")
def scene():
    cams, f = ring()
    pairs = [(m, (m + 1) % len(cams)) for m in range(len(cams))]
    ego = straight_drive(3, 1.5, 2.0)
    S_true = np.stack([c.sensor_to_ego for c in cams])
    S0 = perturb_extrinsics(S_true, 1.0, 0.05, np.random.default_rng(4))
    return cams, f, pairs, ego, S_true, S0


def test_lie_round_trip():
    w = np.array([[0.3, -0.2, 0.1], [1e-10, 0, 0], [0, 2.5, 0]])
    assert np.allclose(rotation_vector(rodrigues(w)), w, atol=1e-9)
    assert np.isclose(rotation_angle_deg(rodrigues(np.array([0, 0, np.radians(30)]))), 30.0)


def test_jacobians_match_finite_differences(scene):
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=2, noise_px=0.5, rng=np.random.default_rng(1))
    prob = _Problem(S0, ego, obs, np.full(len(cams), f), 0, AdjustConfig())
    st = prob.initial_state(int(obs.point.max()) + 1)
    ego0 = np.einsum("tij,jk->tik", make_transform(st.R_t, st.c_t), invert_transform(S0[0]))
    pts, anchors, _ = initial_points(S0, ego0, obs, int(obs.point.max()) + 1)
    st.set_points(pts + 0.3, anchors)
    st = prob.apply(st, np.random.default_rng(3).normal(scale=0.01, size=prob.n_full), np.zeros((len(st.rho), 3)))
    r, Jp, Jl = prob.obs_terms(st, jacobians=True)
    n, eps = prob.n_full, 1e-6
    zero_pts = np.zeros((len(st.rho), 3))
    for k in prob.solve_idx[::3]:
        dp = np.zeros(n)
        dp[k] = eps
        rp = prob.obs_terms(prob.apply(st, dp, zero_pts), False)
        rm = prob.obs_terms(prob.apply(st, -dp, zero_pts), False)
        fd = (rp - rm) / (2 * eps)
        an = np.zeros_like(r)
        for j in range(12):
            hit = prob.pose_idx[:, j] == k
            an[hit] += Jp[hit, :, j]
        assert np.allclose(an, fd, atol=1e-5 * max(1.0, np.abs(fd).max())), k
    for c in range(3):
        dl = np.zeros_like(zero_pts)
        dl[:, c] = eps
        fd = (prob.obs_terms(prob.apply(st, np.zeros(n), dl), False)
              - prob.obs_terms(prob.apply(st, np.zeros(n), -dl), False)) / (2 * eps)
        assert np.allclose(Jl[:, :, c], fd, atol=1e-4 * np.abs(fd).max())


def test_reduced_system_is_the_schur_complement_of_the_full_normal_equations(scene):
    """S and its right-hand side equal Hpp - Hpl Hll^-1 Hlp and -(gp - Hpl Hll^-1 gl) built from the dense Jacobian
    of every pose and point unknown, with tracks of 2 to 6 observations (the per-point sums, not per pair)."""
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=2, noise_px=0.5, rng=np.random.default_rng(1))
    lengths = np.bincount(obs.point)
    assert lengths.min() >= 2 and lengths.max() >= 3
    prob = _Problem(S0, ego, obs, np.full(len(cams), f), 0, AdjustConfig(refine_focal=False))
    K = int(obs.point.max()) + 1
    st = prob.initial_state(K)
    ego0 = np.einsum("tij,jk->tik", make_transform(st.R_t, st.c_t), invert_transform(S0[0]))
    pts, anchors, _ = initial_points(S0, ego0, obs, K)
    st.set_points(pts + 0.1, anchors)
    lam = 1e-3
    S, rhs, *_ = reduced_system(prob, st, lam)
    r, Jp, Jl = prob.obs_terms(st, jacobians=True)
    _, w = prob.loss(np.sum(r * r, axis=1), prob.cfg.f_scale)
    n, N = prob.n_full, len(obs)
    Jpose = np.zeros((2 * N, n))
    Jpt = np.zeros((2 * N, 3 * K))
    for i in range(N):
        for j in range(prob.pose_idx.shape[1]):
            Jpose[2 * i:2 * i + 2, prob.pose_idx[i, j]] += Jp[i, :, j]
        Jpt[2 * i:2 * i + 2, 3 * obs.point[i]:3 * obs.point[i] + 3] = Jl[i]
    W = np.repeat(w, 2)[:, None]
    Hpp, Hpl, Hll = Jpose.T @ (W * Jpose), Jpose.T @ (W * Jpt), Jpt.T @ (W * Jpt)
    gp, gl = Jpose.T @ (W[:, 0] * r.ravel()), Jpt.T @ (W[:, 0] * r.ravel())
    for x, blocks in prob.prior_terms(st):
        for ia, Ja in blocks:
            gp[ia:ia + Ja.shape[1]] += Ja.T @ x
            for ib, Jb in blocks:
                Hpp[ia:ia + Ja.shape[1], ib:ib + Jb.shape[1]] += Ja.T @ Jb
    Hll_d = Hll + lam * np.diag(np.diag(Hll)) + 1e-12 * np.eye(3 * K)
    Hpp_d = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-12 * np.eye(n)
    Hll_inv = np.linalg.inv(Hll_d)
    keep = prob.solve_idx
    S_ref = Hpp_d - Hpl @ Hll_inv @ Hpl.T
    rhs_ref = -gp + Hpl @ Hll_inv @ gl
    scale = np.abs(S_ref[np.ix_(keep, keep)]).max()
    assert np.allclose(S[np.ix_(keep, keep)], S_ref[np.ix_(keep, keep)], atol=1e-9 * scale)
    assert np.allclose(rhs[keep], rhs_ref[keep], atol=1e-9 * np.abs(rhs_ref[keep]).max())
    # the points are summed in chunks (memory); chunk boundaries do not change the sums
    Hlp_o = np.moveaxis(np.swapaxes(Jl * w[:, None, None], 1, 2) @ Jp, 0, 2)  # (3, c, N)
    L_inv = inverse_cholesky(Hll_d.reshape(K, 3, K, 3)[np.arange(K), :, np.arange(K), :])
    z = (L_inv @ gl.reshape(K, 3, 1))[:, :, 0]
    whole = point_terms(point_blocks(prob.pose_idx, obs.point, n, K), Hlp_o, L_inv, z, n)
    chunked = point_terms(point_blocks(prob.pose_idx, obs.point, n, K, chunk=7), Hlp_o, L_inv, z, n)
    assert len(point_blocks(prob.pose_idx, obs.point, n, K, chunk=7)) == -(-K // 7) > 1
    for a, b in zip(chunked, whole):
        assert np.allclose(a, b, atol=1e-12 * np.abs(b).max())
    assert np.allclose(Hpp_d - whole[0], S, atol=1e-9 * scale)
    assert np.allclose(whole[1][keep] - gp[keep], rhs_ref[keep], atol=1e-9 * np.abs(rhs_ref[keep]).max())


def test_noise_free_recovery(scene):
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=3, noise_px=0.0, rng=np.random.default_rng(2))
    before = rel_errors(S0, S_true, pairs)
    assert before[0].min() > 0.5  # the perturbation is real
    # with the weak priors made negligible the solver lands on the truth
    res = adjust(S0, ego, obs, np.full(len(cams), f), config=AdjustConfig(sigma_rel_t_m=100.0))
    rot, trans = rel_errors(res.sensor_to_ego, S_true, pairs)
    assert res.converged and res.iterations < 30
    assert rot.max() < 0.003 and trans.max() < 0.002
    assert res.final_rms_px < 0.01 < 1.0 < res.initial_rms_px
    assert np.allclose(res.sensor_to_ego[0], S0[0])  # the reference camera carries the gauge
    # the default priors (towards the 1 deg / 5 cm perturbed input; the mount's sigma is 10 cm) bias this
    # light data set (3 points per image pair) by a fraction of the perturbation
    rot, trans = rel_errors(adjust(S0, ego, obs, np.full(len(cams), f)).sensor_to_ego, S_true, pairs)
    assert rot.max() < 0.03 and trans.max() < 0.03


def test_metric_scale_comes_from_the_ego_motion(scene):
    """Baselines are recovered in metres from the ego poses even when the input baselines are 30% short,
    and scaling the whole world (ego motion included) scales the recovered baselines with it."""
    cams, f, pairs, ego, S_true, _ = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=3, noise_px=0.0, rng=np.random.default_rng(5))
    S_short = S_true.copy()
    S_short[:, :3, 3] = S_true[0, :3, 3] + 0.7 * (S_true[:, :3, 3] - S_true[0, :3, 3])
    true_baselines = np.array([np.linalg.norm(S_true[b, :3, 3] - S_true[a, :3, 3]) for a, b in pairs])
    weak_mount = AdjustConfig(sigma_rel_t_m=100.0)
    res = adjust(S_short, ego, obs, np.full(len(cams), f), config=weak_mount)
    got = np.array([np.linalg.norm(res.sensor_to_ego[b, :3, 3] - res.sensor_to_ego[a, :3, 3]) for a, b in pairs])
    assert np.abs(0.7 * true_baselines - true_baselines).min() > 0.15
    assert np.abs(got - true_baselines).max() < 0.01
    # the default mount prior (10 cm) holds back a 26-30 cm input error only partly on this light data set
    res = adjust(S_short, ego, obs, np.full(len(cams), f))
    got = np.array([np.linalg.norm(res.sensor_to_ego[b, :3, 3] - res.sensor_to_ego[a, :3, 3]) for a, b in pairs])
    assert np.abs(got - true_baselines).max() < 0.05

    # the same world twice as large: rays are unchanged, ego translations and mounts double
    big = S_true.copy()
    big[:, :3, 3] *= 2.0
    ego_big = ego.copy()
    ego_big[:, :3, 3] *= 2.0
    res2 = adjust(big, ego_big, obs, np.full(len(cams), f), config=weak_mount)
    got2 = np.array([np.linalg.norm(res2.sensor_to_ego[b, :3, 3] - res2.sensor_to_ego[a, :3, 3]) for a, b in pairs])
    assert np.allclose(got2, 2.0 * true_baselines, atol=0.01)


def test_robust_adjust_survives_outliers(scene, caplog):
    """8% of the rays turned ~3 deg: the passes reject them and land where the clean data lands."""
    caplog.set_level("DEBUG", logger="sgde_plugin.calib.ba")
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=5, noise_px=0.3, rng=np.random.default_rng(6))
    sigma = np.full(len(obs), 0.3)
    clean = Observations(obs.camera, obs.frame, obs.point, obs.ray, sigma)
    rng = np.random.default_rng(7)
    bad = rng.random(len(obs)) < 0.08
    rays = obs.ray.copy()
    rays[bad] = rays[bad] @ rodrigues(rng.normal(scale=0.05, size=(1, 3)))[0].T
    noisy = Observations(obs.camera, obs.frame, obs.point, rays, sigma)
    focal = np.full(len(cams), f)
    ref_rot, ref_trans = rel_errors(adjust(S0, ego, clean, focal).sensor_to_ego, S_true, pairs)
    plain_rot, _ = rel_errors(adjust(S0, ego, noisy, focal).sensor_to_ego, S_true, pairs)
    res, kept = robust_adjust(S0, ego, noisy, focal)
    rot, trans = rel_errors(res.sensor_to_ego, S_true, pairs)
    assert np.abs(rot - ref_rot).max() < 0.04 and np.abs(trans - ref_trans).max() < 0.005
    assert plain_rot.max() > rot.max() + 0.05  # one soft-L1 pass is bent by the outliers
    assert (~kept[bad]).mean() > 0.9 and kept[~bad].mean() > 0.8
    assert res.iterations <= 200
    passes = [r.getMessage() for r in caplog.records if r.name == "sgde_plugin.calib.ba"]
    assert passes[0].startswith("coarse pass") and any(m.startswith("pass: ") for m in passes), passes


def _pm(a, b, fa, fb, ka, kb):
    n = len(ka)
    ray = np.tile([0.0, 0.0, 1.0], (n, 1))
    return PairMatches(a, b, np.array(fa), np.array(fb), np.zeros((n, 2)), np.zeros((n, 2)), ray, ray,
                       np.ones(n), np.ones(n), np.array(ka), np.array(kb))


def test_tracks_merge_shared_keypoints_and_split_conflicts():
    index = {"A": 0, "B": 1, "C": 2}
    # keypoint 5 of A@0 matched to B@0 kp 1 and B@1 kp 2; B@0 kp1 matched to C@0 kp 9: one 4-view track
    m1 = _pm("A", "B", [0, 0], [0, 1], [5, 5], [1, 2])
    m2 = _pm("B", "C", [0], [0], [1], [9])
    # a conflict: A@1 kp 3 matched to B@1 kp 4 and kp 6 (two keypoints of one image in a track)
    m3 = _pm("A", "B", [1, 1], [1, 1], [3, 3], [4, 6])
    # a lone cross-time match (A@0 kp 7 - B@1 kp 8) is dropped, it could be a car driving alongside
    m4 = _pm("A", "B", [0], [1], [7], [8])
    tr = observations([m1, m2, m3, m4], index)
    counts = np.bincount(tr.obs.point)
    assert sorted(counts.tolist()) == [2, 2, 4]
    assert tr.edge_obs.shape == (6, 2) and list(tr.edge_pair) == [0, 0, 1, 2, 2, 3]
    assert list(tr.edge_obs[5]) == [-1, -1]
    # both observations of every kept edge belong to the same point
    e = tr.edge_obs[:5]
    assert np.all(tr.obs.point[e[:, 0]] == tr.obs.point[e[:, 1]])
    assert len(np.bincount(observations([m4], index, min_cross_time_views=2).obs.point)) == 1


def test_per_camera_capture_poses(scene):
    """Cameras fire one after another (camera m 10*m ms after camera 0, 0.1 m per 10 ms): with each camera's
    own ego pose, X(m, t) = ego(t, m) X_rel(m), the adjustment recovers the truth; with the frame's pose
    only it cannot. The Jacobians stay exact with the capture offsets."""
    cams, f, pairs, _, S_true, S0 = scene
    T, M = 3, len(cams)
    fine = straight_drive(10 * T, step_m=0.1, yaw_step_deg=0.2)
    ego_seq = np.stack([[fine[10 * t + m] for m in range(M)] for t in range(T)])
    obs, _, _ = simulate_observations(cams, pairs, ego_seq, per_view_pair=3, noise_px=0.0,
                                      rng=np.random.default_rng(7))
    cfg = AdjustConfig(sigma_rel_t_m=100.0)
    res = adjust(S0, ego_seq, obs, np.full(M, f), config=cfg)
    rot, trans = rel_errors(res.sensor_to_ego, S_true, pairs)
    assert res.converged and rot.max() < 0.003 and trans.max() < 0.002
    rot_sync, trans_sync = rel_errors(adjust(S0, ego_seq[:, 0], obs, np.full(M, f), config=cfg).sensor_to_ego,
                                      S_true, pairs)
    assert trans_sync.max() > 0.1 and rot_sync.max() > 0.05  # the frame's pose for every camera is wrong
    prob = _Problem(S0, ego_seq, obs, np.full(M, f), 0, AdjustConfig())
    st = prob.initial_state(int(obs.point.max()) + 1)
    pts, anchors, _ = initial_points(S0, ego_seq, obs, int(obs.point.max()) + 1)
    st.set_points(pts, anchors)
    assert_pose_jacobian(prob, st, prob.solve_idx[::5], 1e-5)


def test_rotation_sigma_predicts_the_error_and_flags_an_undetermined_camera(scene):
    """The adjustment's 1-sigma of each adjacent relative rotation is of the size of the actual error on
    well observed pairs; a camera left with a handful of rays has a sigma far above the acceptance limit
    (0.5 deg), and the mount prior keeps its translation near the input."""
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=3, noise_px=0.3,
                                            rng=np.random.default_rng(8))
    obs = Observations(obs.camera, obs.frame, obs.point, obs.ray, np.full(len(obs), 0.3))
    focal = np.full(len(cams), f)
    res, _ = robust_adjust(S0, ego, obs, focal)
    sigma = np.array([relative_rotation_sigma_deg(res.rotation_cov, a, b) for a, b in pairs])
    rot, _ = rel_errors(res.sensor_to_ego, S_true, pairs)
    assert sigma.max() < 0.1 and sigma.min() > 0.005
    assert np.all(rot < 3 * sigma)
    # camera 3 loses its observations: only the priors hold it
    keep = obs.camera != 3
    sub = Observations(obs.camera[keep], obs.frame[keep], obs.point[keep], obs.ray[keep], obs.sigma_px[keep])
    res3, _ = robust_adjust(S0, ego, sub, focal)
    sigma3 = {p: relative_rotation_sigma_deg(res3.rotation_cov, *p) for p in pairs}
    assert sigma3[(2, 3)] > 1.0 and sigma3[(3, 4)] > 1.0
    assert max(v for p, v in sigma3.items() if 3 not in p) < 0.1
    assert np.linalg.norm(res3.sensor_to_ego[3, :3, 3] - S0[3, :3, 3]) < 0.01


def test_per_point_sums_equal_add_at_bit_for_bit():
    """The adjustment's per-point sums (bincount) are np.add.at's, bit for bit, for vectors and 3x3 blocks."""
    rng = np.random.default_rng(3)
    point = rng.integers(0, 300, 5000)
    for shape in ((3,), (3, 3)):
        values = rng.normal(size=(5000, *shape))
        expected = np.zeros((301, *shape))
        np.add.at(expected, point, values)
        np.testing.assert_array_equal(point_sums(point, np.moveaxis(values, 0, -1), 301), expected)


def test_inverse_cholesky_of_3x3_blocks():
    """L^-1 of H = L L^T, lower triangular, matches LAPACK's factor; (L^-1)^T L^-1 is H^-1, also for a block whose
    smallest eigenvalue is 1e-9 of its largest (a far point seen along nearly one ray)."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(50, 3, 3))
    H = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    H[0] = Q @ np.diag([1e6, 1.0, 1e-3]) @ Q.T
    L_inv = inverse_cholesky(H)
    assert np.all(np.triu(L_inv, 1) == 0.0)
    np.testing.assert_allclose(L_inv, np.linalg.inv(np.linalg.cholesky(H)), rtol=1e-9, atol=1e-12)
    inv = np.swapaxes(L_inv, 1, 2) @ L_inv
    np.testing.assert_allclose(inv @ H, np.broadcast_to(np.eye(3), H.shape), atol=1e-8)


def test_an_adjustment_without_observations_keeps_the_start(scene):
    """No observation to adjust (a partially linked window whose few matches all disagree with their tracks): the
    start comes back, not converged, so the window is rejected instead of failing."""
    cams, f, pairs, ego, S_true, S0 = scene
    obs, _, _ = simulate_observations(cams, pairs, ego, per_view_pair=2, noise_px=0.3, rng=np.random.default_rng(6))
    none = Observations(obs.camera[:0], obs.frame[:0], obs.point[:0], obs.ray[:0], np.zeros(0))
    res, kept = robust_adjust(S0, ego, none, np.full(len(cams), f))
    assert kept.size == 0 and not res.converged and res.iterations == 0 and res.message == "no observation to adjust"
    assert np.array_equal(res.sensor_to_ego, S0) and res.rotation_cov is None
