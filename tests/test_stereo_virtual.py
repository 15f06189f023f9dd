"""Virtual pinhole halves of fisheyes: orientation, resolution, resampled images against direct renders, rim.

Runtime: about 4 s on 2 cores.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from stereo_scene import Plane, fisheye_pair, render, wall

from sgde_plugin.cameras import Camera, Ocam, Pinhole
from sgde_plugin.stereo.rectify import WarpMaps, angular_resolution, torch_threads
from sgde_plugin.stereo.virtual import virtual_pinhole_images, virtual_pinholes

PLANES = [wall(8.0, 0.0, seed=1), wall(6.0, -90.0, seed=2), wall(6.0, 90.0, seed=3), wall(9.0, 180.0, seed=5),
          Plane(np.zeros(3), np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), seed=9)]


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads, and OpenMP threads crawl on a busy machine."""
    with torch_threads(1):
        yield


def _blurred_diff(a: np.ndarray, b: np.ndarray, where: np.ndarray, sigma: float = 2.0) -> float:
    """Mean absolute grey difference after a Gaussian blur: the virtual image is sharp only up to the
    fisheye's own resolution, which the wide-angle pinhole stretches."""
    ga = cv2.GaussianBlur(a[..., 0].astype(np.float32), (0, 0), sigma)
    gb = cv2.GaussianBlur(b[..., 0].astype(np.float32), (0, 0), sigma)
    return float(np.abs(ga - gb)[where].mean())


def _yaw4(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[[0, 0, 2, 2], [0, 2, 0, 2]] = [math.cos(angle), math.sin(angle), -math.sin(angle), math.cos(angle)]
    return T


def test_halves_look_left_and_right_with_matching_resolution():
    front, _ = fisheye_pair(400)
    left, right = virtual_pinholes(front)
    assert left.name == "F.L" and right.name == "F.R"
    R = front.sensor_to_ego[:3, :3]
    for half, sign in ((left, -1), (right, 1)):
        assert isinstance(half.intrinsics, Pinhole) and half.intrinsics.dist is None
        assert np.allclose(half.sensor_to_ego[:3, 3], front.sensor_to_ego[:3, 3])
        axis = R.T @ half.sensor_to_ego[:3, 2]  # in the fisheye's frame
        assert math.isclose(math.degrees(math.atan2(axis[0], axis[2])), sign * 55.0, abs_tol=1e-9)  # 220 / 4
        assert abs(axis[1]) < 1e-12  # turned about the vertical axis only
        K = half.intrinsics.K
        assert K[0, 0] == K[1, 1]
        assert math.isclose(K[0, 0], angular_resolution(front, half.sensor_to_ego[:3, 2]), rel_tol=1e-9)
        assert math.isclose(half.intrinsics.hfov_deg, 110.0, abs_tol=0.5)
    small, _ = virtual_pinholes(front, hfov_deg=60, vfov_deg=40, yaw_deg=30, scale=0.5)
    assert math.isclose(small.intrinsics.hfov_deg, 60.0, abs_tol=1.0)
    assert math.isclose(small.intrinsics.K[0, 0], 0.5 * angular_resolution(front, small.sensor_to_ego[:3, 2]))


def test_resampled_halves_match_a_direct_render_and_drop_the_rim():
    front, _ = fisheye_pair(400)
    image, _ = render(PLANES, front)
    (img_l, cam_l), (img_r, cam_r) = virtual_pinhole_images(front, image)
    for img, cam in ((img_l, cam_l), (img_r, cam_r)):
        direct, _ = render(PLANES, cam)
        seen = img.max(axis=2) > 0
        assert seen.mean() > 0.6  # most of the half lies inside the fisheye's field of view
        inner = cv2.erode(seen.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        assert _blurred_diff(img, direct, inner) < 3.0
        # the comparison is sharp enough to see a 0.5-degree error of the half's orientation
        turned = Camera(cam.name, cam.intrinsics, cam.sensor_to_ego @ _yaw4(math.radians(0.5)))
        assert _blurred_diff(img, render(PLANES, turned)[0], inner) > 2 * _blurred_diff(img, direct, inner)
    # the rim: with the default 3 px discarded, fewer pixels survive, none within 3 px of the circle's edge
    (no_rim, _), _ = virtual_pinhole_images(front, image, rim_px=0)
    kept = img_l.max(axis=2) > 0
    assert kept.sum() < (no_rim.max(axis=2) > 0).sum()
    assert np.array_equal(WarpMaps.between(front, cam_l, rim_px=3).valid[kept], np.ones(kept.sum(), bool))
    circle = front.intrinsics.valid_mask().astype(np.uint8)
    edge_zone = circle - cv2.erode(circle, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    rays, _ = cam_l.intrinsics.ray_grid()
    to_fisheye = front.sensor_to_ego[:3, :3].T @ cam_l.sensor_to_ego[:3, :3]
    uv, _ = front.intrinsics.project(rays.numpy()[kept] @ to_fisheye.T)
    iu, iv = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert not edge_zone[iv, iu].any()


def test_ocam_fisheye_halves():
    """The Synthetic-Urban-like ocam model goes through the same function."""
    from sgde_plugin.synth.presets import equidistant_ocam

    model = equidistant_ocam(320, 300, 220.0)
    assert isinstance(model, Ocam)
    cam = Camera("F", model, fisheye_pair(320)[0].sensor_to_ego)
    image, _ = render(PLANES, cam)
    (img_l, cam_l), (img_r, cam_r) = virtual_pinhole_images(cam, image)
    for img, half in ((img_l, cam_l), (img_r, cam_r)):
        direct, _ = render(PLANES, half)
        seen = cv2.erode((img.max(axis=2) > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        assert seen.mean() > 0.5
        assert _blurred_diff(img, direct, seen) < 3.0
