"""LiDAR ground truth: hand-computed projections, ego-motion compensation, range and mask, bad files."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount, make_transform
from sgde_plugin.io import write_image
from sgde_plugin.lidar import LidarDepthConfig, LidarSweep, read_points
from sgde_plugin.rig import CameraCapture, Frame, Rig

W, H, F = 64, 48, 40.0
K = np.array([[F, 0.0, 31.5], [0.0, F, 23.5], [0.0, 0.0, 1.0]])
LIDAR_MOUNT = make_transform(np.eye(3), [0.0, 0.0, 1.75])  # roof LiDAR, axes as the ego's
FRONT = camera_mount(0.0, np.array([1.5, 0.0, 1.5]))  # looks along ego +x from 1.5 m forward, 1.5 m up


def write_bin(path: Path, pts: np.ndarray) -> Path:
    raw = np.zeros((len(pts), 5), np.float32)
    raw[:, :3] = pts
    raw[:, 3] = 0.5
    path.write_bytes(raw.tobytes())
    return path


def one_camera_rig(sweep: LidarSweep, capture: CameraCapture | None = None, **cfg) -> Rig:
    cam = Camera("CAM_FRONT", Pinhole(W, H, K), FRONT)
    frame = Frame("0", 1_000_000, np.eye(4), cameras={"CAM_FRONT": capture} if capture else {}, lidar=sweep)
    return Rig((cam,), (), (frame,), lidar_config=LidarDepthConfig(**cfg))


def test_hand_computed_points_nearest_return_and_range(tmp_path: Path) -> None:
    # points in the LiDAR frame (ego axes, 1.75 m up; float32-exact); the camera sits at (1.5, 0, 1.5) in the ego frame
    pts = np.array([
        [11.5, 0.0, -0.25],  # ego (11.5, 0, 1.5): straight ahead at depth 10 -> principal point (31.5, 23.5)
        [6.5, -1.0, -0.75],  # ego (6.5, -1, 1.0): depth 5, x_cam = +1 (right), y_cam = +0.5 (down)
        [11.5, -2.0, -1.25], # ego (11.5, -2, 0.5): depth 10, same pixel as the previous one, farther: loses
        [-5.0, 0.0, 0.0],    # behind the camera
        [1.9, -0.1, -0.25],  # 0.4 m in front (pixel (42, 24)): under min_depth
        [301.5, -30.0, -0.25],  # 300 m (pixel (36, 24)): beyond max_depth
    ])
    sweep = LidarSweep(write_bin(tmp_path / "a.pcd.bin", pts), "nuscenes_bin", LIDAR_MOUNT, np.eye(4), 1_000_000)
    d = one_camera_rig(sweep).load_depth("0", "CAM_FRONT")
    assert d.dtype == np.float32 and d.shape == (H, W)
    # (31.5, 23.5) rounds half to even: column 32, row 24; the second point: (31.5 + 8, 23.5 + 4) -> (40, 28)
    assert d[24, 32] == pytest.approx(10.0) and d[28, 40] == pytest.approx(5.0)
    assert np.count_nonzero(d) == 2
    assert np.count_nonzero(one_camera_rig(sweep, max_depth_m=400.0).load_depth("0", "CAM_FRONT")) == 3
    assert np.count_nonzero(one_camera_rig(sweep, min_depth_m=0.1).load_depth("0", "CAM_FRONT")) == 3


def test_moving_ego_is_compensated_and_ignoring_time_costs_the_motion(tmp_path: Path) -> None:
    """A wall 20 m ahead; the LiDAR sweeps at t = 0, the camera fires 45 ms later at 10 m/s (0.45 m on)."""
    v, dt = 10.0, 0.045
    ys, zs = np.meshgrid(np.linspace(-6, 6, 60), np.linspace(-1.5, 2.5, 30))
    wall_world = np.stack([np.full(ys.size, 21.5), ys.ravel(), zs.ravel()], 1)  # x = 21.5 m in the world
    ego_lidar = np.eye(4)
    pts = wall_world - LIDAR_MOUNT[:3, 3]  # world == ego at t = 0; LiDAR frame = ego shifted up
    sweep = LidarSweep(write_bin(tmp_path / "w.pcd.bin", pts), "nuscenes_bin", LIDAR_MOUNT, ego_lidar, 0)
    ego_cam = make_transform(np.eye(3), [v * dt, 0.0, 0.0])
    right = one_camera_rig(sweep, CameraCapture(45_000, ego_cam)).load_depth("0", "CAM_FRONT")
    wrong = one_camera_rig(sweep, CameraCapture(45_000, ego_lidar)).load_depth("0", "CAM_FRONT")
    # the camera at ego x = 1.5 + 0.45 sees the wall at depth 21.5 - 1.95 = 19.55 m
    assert np.count_nonzero(right) > 200
    np.testing.assert_allclose(right[right > 0], 19.55, rtol=1e-5)
    # ignoring the capture times puts the wall v * dt = 0.45 m too far (2.3 %)
    np.testing.assert_allclose(wrong[wrong > 0], 20.0, rtol=1e-5)
    assert np.median(wrong[wrong > 0] - 19.55) == pytest.approx(v * dt, abs=1e-4)


def test_mask_and_occlusion_filter(tmp_path: Path) -> None:
    # a near post (5 m) in front of a far wall (30 m): LiDAR returns from both land side by side
    near = np.array([[6.5, 0.0, -0.25 + dz] for dz in np.linspace(-0.2, 0.2, 5)])
    far = np.array([[31.5, -(0.75 * k + 0.375), -0.25] for k in range(-3, 4)])  # columns 29..35 of row 24
    sweep = LidarSweep(write_bin(tmp_path / "o.pcd.bin", np.vstack([near, far])), "nuscenes_bin", LIDAR_MOUNT,
                       np.eye(4), 0)
    plain = one_camera_rig(sweep).load_depth("0", "CAM_FRONT")
    filtered = one_camera_rig(sweep, occlusion_window_px=2).load_depth("0", "CAM_FRONT")
    far_kept = lambda d: int(np.count_nonzero(d > 20))  # noqa: E731
    # column 32 is the post's (z-buffer); the filter drops the wall within 2 px of the post (30..34)
    assert far_kept(plain) == 6 and far_kept(filtered) == 2
    assert np.count_nonzero((filtered > 0) & (filtered < 6)) == np.count_nonzero((plain > 0) & (plain < 6))
    rig = one_camera_rig(sweep)
    mask = np.ones((H, W), bool)
    mask[:, 32:] = False
    rig = replace(rig, masks={"CAM_FRONT": tmp_path / "m.png"})
    write_image(tmp_path / "m.png", mask.astype(np.uint8) * 255)
    masked = rig.load_depth("0", "CAM_FRONT")
    assert np.count_nonzero(masked[:, 32:]) == 0 and np.count_nonzero(masked) == np.count_nonzero(plain[:, :32])


@pytest.mark.parametrize("defect", ["missing", "truncated", "npz_shape", "npz_key", "npz_garbage"])
def test_bad_point_cloud_files(defect: str, tmp_path: Path) -> None:
    if defect == "missing":
        sweep = LidarSweep(tmp_path / "nope.pcd.bin", "nuscenes_bin", LIDAR_MOUNT, np.eye(4), 0)
        problem = "point cloud file not found"
    elif defect == "truncated":
        path = write_bin(tmp_path / "t.pcd.bin", np.ones((10, 3)))
        path.write_bytes(path.read_bytes()[:-6])
        sweep = LidarSweep(path, "nuscenes_bin", LIDAR_MOUNT, np.eye(4), 0)
        problem = "truncated or wrong shape: 194 bytes"
    else:
        path = tmp_path / "p.npz"
        if defect == "npz_shape":
            np.savez(path, data=np.ones((10, 2)))
            problem = "expected an (N, >=3) numeric array"
        elif defect == "npz_key":
            np.savez(path, points=np.ones((10, 4)))
            problem = "data: missing (keys: points)"
        else:
            path.write_bytes(b"PK\x03\x04 not a zip")
            problem = "not a readable .npz"
        sweep = LidarSweep(path, "dgp_npz", LIDAR_MOUNT, np.eye(4), 0)
    with pytest.raises(InputError, match=problem.replace("(", r"\(").replace(")", r"\)")) as exc:
        read_points(sweep)
    assert "\n" not in str(exc.value)


def test_points_read_as_written(tmp_path: Path) -> None:
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]])
    np.savez(tmp_path / "d.npz", data=np.hstack([pts, np.ones((2, 1))]))
    np.testing.assert_array_equal(read_points(LidarSweep(tmp_path / "d.npz", "dgp_npz", np.eye(4), np.eye(4), 0)), pts)
    got = read_points(LidarSweep(write_bin(tmp_path / "b.pcd.bin", pts), "nuscenes_bin", np.eye(4), np.eye(4), 0))
    np.testing.assert_allclose(got, pts, rtol=1e-7)
    assert math.isclose(got[1, 2], 6.5)
