"""KITTI calibration: P2's offset column folded into sensor_to_ego round-trips exactly; bad files named."""

from __future__ import annotations

import numpy as np
import pytest

from sgde_plugin.errors import InputError
from sgde_plugin.geometry import invert_transform
from sgde_plugin.readers.kitti import kitti_camera, projection_offset, read_kitti_calib, read_kitti_poses

# values of the form of SemanticKITTI sequence 00's calib.txt
P2 = np.array([[718.856, 0.0, 607.1928, 45.38225],
               [0.0, 718.856, 185.2157, -0.1130887],
               [0.0, 0.0, 1.0, 0.003779761]])
TR = np.array([[4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
               [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
               [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
               [0.0, 0.0, 0.0, 1.0]])
W, H = 1241, 376


def _lidar_points(n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(3, 50, n), rng.uniform(-10, 10, n), rng.uniform(-1.7, 2.5, n)], axis=1)


def _kitti_project(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KITTI's own projection: pixel ~ P2 @ Tr @ X; the third row is the depth in camera 2."""
    h = (P2 @ TR @ np.c_[X, np.ones(len(X))].T).T
    return h[:, :2] / h[:, 2:], h[:, 2]


def test_p2_offset_folded_into_the_pose_round_trips_exactly():
    X = _lidar_points()
    uv_kitti, depth_kitti = _kitti_project(X)
    seen = np.all((uv_kitti > 0) & (uv_kitti < [W - 1, H - 1]), axis=1)
    X, uv_kitti, depth_kitti = X[seen], uv_kitti[seen], depth_kitti[seen]
    assert len(X) > 50
    cam = kitti_camera(P2, TR, W, H)
    cam_pts = (X - cam.sensor_to_ego[:3, 3]) @ cam.sensor_to_ego[:3, :3]  # LiDAR -> camera 2
    uv, ok = cam.intrinsics.project(cam_pts)
    assert ok.all()
    # projection: pixels agree with P2 @ Tr (to 1e-5 px: KITTI's Tr rotation is orthonormal to ~1e-7 only,
    # and the pose is its rigid inverse, as kitti_util's inverse_rigid_trans)
    assert np.abs(uv - uv_kitti).max() < 1e-5
    assert np.abs(cam.intrinsics.depth(cam_pts) - depth_kitti).max() < 1e-6  # depth = third row of P2 @ Tr @ X
    back, valid = cam.intrinsics.points_from_depth(uv_kitti, depth_kitti)  # pixel + depth -> camera 2
    ego = back @ cam.sensor_to_ego[:3, :3].T + cam.sensor_to_ego[:3, 3]
    assert valid.all() and np.abs(ego - X).max() < 1e-5  # ... and back to the LiDAR point (10 um at 50 m)
    # the offset: t = K^-1 P2[:, 3], 6.0 cm, nearly all of it along x
    K, t = projection_offset(P2)
    assert np.allclose(K, P2[:, :3]) and np.linalg.norm(t) == pytest.approx(0.0600, abs=5e-4)
    assert t[2] == pytest.approx(0.003779761)
    # the obvious mapping (K = P2[:3, :3], sensor_to_ego = inv(Tr)) misses every point by |t|
    naive, _ = cam.intrinsics.points_from_depth(uv_kitti, depth_kitti)
    naive_ego = naive @ invert_transform(TR)[:3, :3].T + invert_transform(TR)[:3, 3]
    assert np.linalg.norm(naive_ego - X, axis=1).min() > 0.059


def test_voxformer_convention_reproduces_kitti_util_unprojection():
    # VoxFormer's depth2lidar: x = (u - cu) d / fu + b_x, b_x = -P[0,3] / fu (same for y), z = d, then C2V
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [W, H], size=(50, 2))
    d = rng.uniform(2, 60, 50)
    fu, fv, cu, cv = P2[0, 0], P2[1, 1], P2[0, 2], P2[1, 2]
    rect = np.stack([(uv[:, 0] - cu) * d / fu - P2[0, 3] / fu, (uv[:, 1] - cv) * d / fv - P2[1, 3] / fv, d], 1)
    R, t = TR[:3, :3], TR[:3, 3]
    velo = (rect - t) @ R  # R^T (x - t), kitti_util's inverse_rigid_trans
    cam = kitti_camera(P2, TR, W, H, convention="voxformer")
    pts, _ = cam.intrinsics.points_from_depth(uv, d)
    ours = pts @ cam.sensor_to_ego[:3, :3].T + cam.sensor_to_ego[:3, 3]
    assert np.abs(ours - velo).max() < 1e-9
    # it differs from the exact geometry by P2[2, 3] and the resulting x shift: a few millimetres
    exact = kitti_camera(P2, TR, W, H)
    gap = np.linalg.norm(exact.sensor_to_ego[:3, 3] - cam.sensor_to_ego[:3, 3])
    assert 0.003 < gap < 0.006


def test_calib_and_poses_files(tmp_path):
    lines = [f"P{i}: " + " ".join(f"{v:.12e}" for v in P2.ravel()) for i in range(4)]
    lines.append("Tr: " + " ".join(f"{v:.12e}" for v in TR[:3].ravel()))
    (tmp_path / "calib.txt").write_text("\n".join(lines) + "\n")
    calib = read_kitti_calib(tmp_path / "calib.txt")
    assert np.allclose(calib["P2"], P2) and np.allclose(calib["Tr"], TR) and calib["Tr"].shape == (4, 4)
    # a camera-0 pose moving 2 m forward (camera z) is a LiDAR pose moving ~2 m along LiDAR x
    pose = np.eye(4)
    pose[2, 3] = 2.0
    (tmp_path / "poses.txt").write_text("\n".join(" ".join(f"{v:.9e}" for v in p[:3].ravel())
                                                  for p in (np.eye(4), pose)) + "\n")
    lidar = read_kitti_poses(tmp_path / "poses.txt", calib["Tr"])
    assert lidar.shape == (2, 4, 4) and np.allclose(lidar[0], np.eye(4))
    assert lidar[1, 0, 3] == pytest.approx(2.0, abs=1e-3) and abs(lidar[1, 1, 3]) < 2e-3

    (tmp_path / "bad.txt").write_text("P2: 1 2 3\nTr: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(InputError, match=r"bad.txt: P2: has 3 values, expected 12"):
        read_kitti_calib(tmp_path / "bad.txt")
    (tmp_path / "no_tr.txt").write_text(lines[2] + "\n")
    with pytest.raises(InputError, match=r"no_tr.txt: Tr: missing"):
        read_kitti_calib(tmp_path / "no_tr.txt")
    with pytest.raises(InputError, match="cannot read"):
        read_kitti_calib(tmp_path / "absent.txt")
    # NaN, infinity or absurd values were read as numbers and made NaN poses
    (tmp_path / "nan.txt").write_text(lines[2] + "\nTr: nan" + " 0" * 11 + "\n")
    with pytest.raises(InputError, match=r"nan.txt: Tr: contains NaN or infinity"):
        read_kitti_calib(tmp_path / "nan.txt")
    (tmp_path / "inf_poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 inf 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"inf_poses.txt: line 2: contains NaN or infinity"):
        read_kitti_poses(tmp_path / "inf_poses.txt", calib["Tr"])
    (tmp_path / "huge_poses.txt").write_text("1 0 0 1e308 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"huge_poses.txt: line 1: has a value beyond 1e\+08"):
        read_kitti_poses(tmp_path / "huge_poses.txt", calib["Tr"])
    with pytest.raises(ValueError, match="rectified pinhole"):
        projection_offset(np.c_[np.ones((3, 3)), np.zeros(3)])
