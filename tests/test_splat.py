"""The one splatting and min-pool core (sgde_plugin.splat): hand-computed pixels, z-buffer, pooling, dtypes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgde_plugin.cameras import KannalaBrandt, Pinhole
from sgde_plugin.geometry import make_transform, yaw_pitch_roll_to_rotation
from sgde_plugin.splat import (
    min_pool_nonzero,
    min_pool_nonzero_torch,
    project_to_pixels,
    splat_depth,
    splat_depth_torch,
    transform_points_torch,
    warp_depth,
)

K = np.array([[100.0, 0.0, 31.5], [0.0, 100.0, 23.5], [0.0, 0.0, 1.0]])
CAM = Pinhole(64, 48, K)


def test_splat_hand_computed_pixels_and_nearest_wins() -> None:
    pts = np.array([
        [0.0, 0.0, 10.0],      # optical axis: (31.5, 23.5) -> rounds (half to even) to col 32, row 24
        [1.0, -0.5, 5.0],      # u = 100 * 0.2 + 31.5 = 51.5 -> 52, v = -10 + 23.5 = 13.5 -> 14
        [2.0, -1.0, 10.0],     # same pixel, farther: loses
        [0.0, 0.0, -3.0],      # behind
        [10.0, 0.0, 1.0],      # outside the image
    ])
    d = splat_depth(pts, CAM)
    assert d.shape == (48, 64) and d.dtype == np.float64
    assert d[24, 32] == 10.0 and d[14, 52] == 5.0
    assert np.count_nonzero(d) == 2
    hits = project_to_pixels(torch.as_tensor(pts), CAM)
    assert hits.valid.tolist() == [True, True, True, False, False]
    assert hits.index[:3].tolist() == [24 * 64 + 32, 14 * 64 + 52, 14 * 64 + 52]


def test_splat_fisheye_depth_is_range() -> None:
    fish = KannalaBrandt(80, 80, np.array([[25.0, 0, 39.5], [0, 25.0, 39.5], [0, 0, 1]]), np.zeros(4), 200.0)
    p = np.array([[3.0, 0.0, 4.0]])  # range 5 m, 36.87 deg off axis: r = f * theta
    d = splat_depth(p, fish)
    theta = math.atan2(3.0, 4.0)
    col = round(39.5 + 25.0 * theta)
    assert d[40, col] == pytest.approx(5.0) and np.count_nonzero(d) == 1


def test_warp_depth_moves_a_plane_by_the_transform() -> None:
    depth = np.full((48, 64), 8.0)
    T = make_transform(np.eye(3), [0.0, 0.0, -2.0])  # destination 2 m further forward: plane at 6 m
    out = warp_depth(depth, CAM, CAM, T)
    assert np.allclose(out[out > 0], 6.0) and np.count_nonzero(out) > 0.5 * out.size
    # a yawed destination: every landed depth is the plane's z in that camera
    R = yaw_pitch_roll_to_rotation(0.0, 0.05, 0.0)
    T2 = make_transform(R, [0.1, 0.0, 0.0])
    out2 = warp_depth(depth, CAM, CAM, T2)
    ys, xs = np.nonzero(out2)
    rays = np.stack([(xs - 31.5) / 100.0, (ys - 23.5) / 100.0, np.ones_like(xs, float)], 1)
    # the plane z = 8 in the source frame is n . x = 8 with n = R's image of e_z in the destination frame
    n, c = R @ np.array([0.0, 0.0, 1.0]), 8.0 + n_dot_t(R, T2)
    np.testing.assert_allclose(out2[ys, xs], c / (rays @ n), rtol=0.02)


def n_dot_t(R: np.ndarray, T: np.ndarray) -> float:
    return float((R @ np.array([0.0, 0.0, 1.0])) @ T[:3, 3])


def test_transform_points_torch_batched() -> None:
    T = torch.as_tensor(np.stack([make_transform(np.eye(3), [1.0, 0, 0]), make_transform(np.eye(3), [0, 2.0, 0])]))
    pts = torch.zeros(2, 3, 3, dtype=torch.float64)
    out = transform_points_torch(T, pts)
    assert out[0, :, 0].tolist() == [1.0] * 3 and out[1, :, 1].tolist() == [2.0] * 3


def test_min_pool_ignores_zeros_and_extra_maps_follow() -> None:
    d = np.array([[0, 3, 5, 0, 7],
                  [4, 0, 0, 0, 0],
                  [0, 0, 2, 9, 1]], np.float32)
    label = np.arange(15, dtype=np.int32).reshape(3, 5)
    out, lab = min_pool_nonzero(d, 2, 2, label)
    # blocks (ceil): rows {0,1},{2}; cols {0,1},{2,3},{4}
    assert out.tolist() == [[3, 5, 7], [0, 2, 1]]
    assert lab.tolist() == [[1, 2, 4], [0, 12, 14]]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.float64])
def test_min_pool_torch_dtypes_and_batches(dtype: torch.dtype) -> None:
    x = torch.zeros(2, 3, 4, 4, dtype=dtype)
    x[0, 1, 0, 1] = 12.5
    x[0, 1, 1, 0] = 30.0
    x[1, 2, 3, 3] = 60000.0 if dtype == torch.float16 else 1e6
    out = min_pool_nonzero_torch(x, 2)
    assert out.shape == (2, 3, 2, 2) and out.dtype == dtype
    assert out[0, 1, 0, 0].item() == 12.5 and out[1, 2, 1, 1].item() == x[1, 2, 3, 3].item()
    assert torch.count_nonzero(out).item() == 2


def test_splat_torch_float32_matches_float64() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([-5, -4, 1], [5, 4, 40], (2000, 3))
    d64 = splat_depth_torch(torch.as_tensor(pts), CAM)
    d32 = splat_depth_torch(torch.as_tensor(pts, dtype=torch.float32), CAM)
    assert d32.dtype == torch.float32
    same = (d64 > 0) == (d32 > 0)
    assert same.float().mean() > 0.99
    both = (d64 > 0) & (d32 > 0)
    close = (d64[both] - d32[both].double()).abs() <= 1e-5 * d64[both]
    assert close.double().mean() > 0.99


def test_quaternion_to_rotation_batched_equals_one_by_one() -> None:
    from sgde_plugin.geometry import quaternion_to_rotation, rotation_to_quaternion

    rng = np.random.default_rng(1)
    q = rng.standard_normal((5, 4)) * 3  # not unit length: normalised inside
    R = quaternion_to_rotation(q)
    assert R.shape == (5, 3, 3)
    for qi, Ri in zip(q, R):
        np.testing.assert_allclose(Ri, quaternion_to_rotation(qi), atol=1e-15)
        np.testing.assert_allclose(Ri @ Ri.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(abs(rotation_to_quaternion(Ri) @ (qi / np.linalg.norm(qi))), 1.0, atol=1e-12)


def test_core_on_every_device_and_dtype(device: torch.device, float_dtype: torch.dtype) -> None:
    """Transform, project, z-buffer and min-pool stay on the input's device and dtype with the same pixels."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([0.5, -0.25, 2.0])
    ego = torch.tensor([
        [-0.48, 0.28, 8.0],     # camera (0.02, 0.03, 10): u = 31.5 + 0.2 -> col 32, v = 23.5 + 0.3 -> row 24
        [0.515, -0.24, 3.0],    # camera (1.015, -0.49, 5): u = 31.5 + 20.3 -> 52, v = 23.5 - 9.8 -> 14
        [1.53, -0.73, 8.0],     # camera (2.03, -0.98, 10): same pixel, farther: loses
        [-0.5, 0.25, -5.0],     # behind
    ], dtype=float_dtype, device=device)
    pts = transform_points_torch(T.to(device), ego)
    assert pts.device.type == device.type and pts.dtype == float_dtype
    torch.testing.assert_close(pts[1], torch.tensor([1.015, -0.49, 5.0], dtype=float_dtype, device=device))
    hits = project_to_pixels(pts, CAM)
    assert hits.valid.tolist() == [True, True, True, False]
    assert hits.index[:3].tolist() == [24 * 64 + 32, 14 * 64 + 52, 14 * 64 + 52]
    d = splat_depth_torch(pts, CAM)
    assert d.shape == (48, 64) and d.dtype == float_dtype and d.device.type == device.type
    assert d[24, 32].item() == pytest.approx(10.0, rel=1e-6) and d[14, 52].item() == pytest.approx(5.0, rel=1e-6)
    assert torch.count_nonzero(d).item() == 2
    pooled = min_pool_nonzero_torch(d[None, None], 8)
    assert pooled.shape == (1, 1, 6, 8) and pooled.dtype == float_dtype and pooled.device.type == device.type
    assert pooled[0, 0, 3, 4].item() == pytest.approx(10.0, rel=1e-6)  # row 24 // 8, col 32 // 8
    assert pooled[0, 0, 1, 6].item() == pytest.approx(5.0, rel=1e-6) and torch.count_nonzero(pooled).item() == 2
