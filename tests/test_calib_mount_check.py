"""`MatchConfig.mount_check_px`: every observation pair keeps only the matches that agree with one mount of its
camera pair (the ego motion known), not only the guided ones (runtime < 1 s)."""

import numpy as np

from sgde_plugin.calib.correspondences import MatchConfig, ObservationPair, Verified, _consistent
from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.geometry import make_transform, rodrigues


def _observation_pairs(seed: int = 0):
    """Camera b 40 deg right of a, its starting mount 0.5 deg / 3 cm off; six observation pairs (the ego driving
    1 m per frame), 15 % of the matches moved 2 px down b's image (wrong matches a free essential matrix per
    observation pair can absorb). Returns cameras, per-frame poses of a and b (starting rig), verified parts and
    which matches are wrong."""
    rng = np.random.default_rng(seed)
    K = np.array([[300.0, 0.0, 320.0], [0.0, 300.0, 240.0], [0.0, 0.0, 1.0]])
    S_a = make_transform(np.eye(3), np.zeros(3))
    S_b_true = make_transform(rodrigues(np.radians([0.0, 40.0, 0.0])), np.array([0.8, 0.0, -0.3]))
    D = make_transform(rodrigues(np.radians([0.2, 0.3, -0.3])), np.array([0.02, -0.02, 0.01]))
    S_b0 = S_b_true @ np.linalg.inv(D)
    ca, cb = Camera("a", Pinhole(640, 480, K, None), S_a), Camera("b", Pinhole(640, 480, K, None), S_b0)
    ego = [make_transform(np.eye(3), np.array([0.0, 0.0, 1.0 * k])) for k in range(6)]
    poses_a = np.stack([e @ S_a for e in ego])
    poses_b = np.stack([e @ S_b0 for e in ego])
    verified, wrong = [], []
    for t, t2 in [(0, 0), (1, 1), (2, 2), (0, 2), (1, 3), (2, 5)]:
        A, B = ego[t] @ S_a, ego[t2] @ S_b_true
        n = 120
        d = np.c_[rng.normal(0.7, 0.2, n), rng.normal(0, 0.2, n), np.ones(n)]
        X = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(5, 30, (n, 1))
        Xb = (X @ A[:3, :3].T + A[:3, 3] - B[:3, 3]) @ B[:3, :3]
        uv_a, _ = ca.intrinsics.project(X)
        uv_b, _ = cb.intrinsics.project(Xb)
        seen = (Xb[:, 2] > 1.0) & (uv_b[:, 0] > 0) & (uv_b[:, 0] < 639) & (uv_b[:, 1] > 0) & (uv_b[:, 1] < 479)
        X, uv_a, uv_b, n = X[seen], uv_a[seen], uv_b[seen], int(seen.sum())
        bad = rng.random(n) < 0.15
        uv_b[bad, 1] += 2.0
        ra, _ = ca.intrinsics.unproject(uv_a)
        rb, _ = cb.intrinsics.unproject(uv_b)
        part = {"uva": uv_a, "uvb": uv_b, "ra": ra, "rb": rb, "siga": np.full(n, 0.1), "sigb": np.full(n, 0.1),
                "ka": np.arange(n), "kb": np.arange(n)}
        verified.append(Verified(ObservationPair(t, t2, n, n, n, n), part))
        wrong.append(bad)
    return ca, cb, poses_a, poses_b, verified, wrong


def test_mount_check_drops_the_matches_off_the_pairs_one_mount_in_every_observation_pair():
    ca, cb, pa, pb, verified, wrong = _observation_pairs()
    # off (the default before): unguided observation pairs pass unchanged
    assert _consistent(ca, cb, verified, pa, pb, MatchConfig()) is verified
    out = _consistent(ca, cb, verified, pa, pb, MatchConfig(mount_check_px=1.0))
    kept_good = kept_bad = n_good = n_bad = 0
    for v, o, bad in zip(verified, out, wrong):
        keep = np.isin(v.part["ka"], o.part["ka"])
        kept_good += int(keep[~bad].sum())
        kept_bad += int(keep[bad].sum())
        n_good += int((~bad).sum())
        n_bad += int(bad.sum())
        assert o.pair.inliers == o.part["ka"].size and not o.guided
    assert kept_good == n_good  # every true match is within 1 px of the fitted mount
    # a 2-px shift down is partly along the epipolar lines of the cross-time pairs: most, not all, are caught
    assert kept_bad < 0.2 * n_bad, (kept_bad, n_bad)  # measured 12 of 98
