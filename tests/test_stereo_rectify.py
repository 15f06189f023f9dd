"""Overlap rectification: frame construction, shared K, canvas, and rows of true correspondences (< 0.1 px).

Runtime: about 3 s on 2 cores.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from stereo_scene import fisheye_pair, nuscenes_pair

from sgde_plugin.cameras import Camera
from sgde_plugin.geometry import camera_mount, invert_transform, transform_points
from sgde_plugin.stereo.rectify import WarpMaps, rectified_rotation, rectify_pair, torch_threads


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads, and OpenMP threads crawl on a busy machine."""
    with torch_threads(1):
        yield


def _overlap_points(pair, n: int, rng: np.random.Generator, inset: float = 10) -> np.ndarray:
    """Random ego points at 4-40 m seen by both cameras and both rectified cameras, `inset` px inside."""
    cams = (pair.left, pair.right, pair.rect_left, pair.rect_right)
    masks = [c.intrinsics.valid_mask() for c in cams]
    pts = []
    axis = pair.rotation[:, 2]
    while len(pts) < n:
        d = axis + rng.normal(scale=0.4, size=3)
        d /= np.linalg.norm(d)
        p = pair.left.sensor_to_ego[:3, 3] + d * rng.uniform(4, 40)
        ok = True
        for c, m in zip(cams, masks):
            uv, valid = c.intrinsics.project(transform_points(invert_transform(c.sensor_to_ego), p))
            inner = (inset <= uv[0] <= c.width - 1 - inset) and (inset <= uv[1] <= c.height - 1 - inset)
            ok = ok and bool(valid) and inner and bool(m[int(uv[1]), int(uv[0])])
        if ok:
            pts.append(p)
    return np.array(pts)


def _blob_image(cam: Camera, points: np.ndarray, sigma_rad: float) -> np.ndarray:
    """Float image of Gaussian blobs (angular sigma) around the directions of `points` seen from `cam`."""
    rays, valid = cam.intrinsics.ray_grid()
    rays = rays.numpy() @ cam.sensor_to_ego[:3, :3].T
    img = np.zeros(valid.shape)
    for p in points:
        d = p - cam.sensor_to_ego[:3, 3]
        d /= np.linalg.norm(d)
        img += np.exp(-np.sum((rays - d) ** 2, axis=-1) / (2 * sigma_rad**2))
    return np.where(valid.numpy(), img, 0).astype(np.float32)


def _centroid(img: np.ndarray, near: np.ndarray, radius: int = 6) -> np.ndarray:
    x0, y0 = int(round(near[0])), int(round(near[1]))
    patch = img[y0 - radius:y0 + radius + 1, x0 - radius:x0 + radius + 1].astype(np.float64)
    patch = np.clip(patch - 0.05, 0, None)
    ys, xs = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    w = patch.sum()
    return np.array([x0 + (xs * patch).sum() / w, y0 + (ys * patch).sum() / w])


def test_rectified_frame_is_orthonormal_with_x_along_the_baseline():
    left, right = nuscenes_pair(0.25)
    R = rectified_rotation(left, right)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
    b = right.sensor_to_ego[:3, 3] - left.sensor_to_ego[:3, 3]
    assert np.allclose(R[:, 0], b / np.linalg.norm(b))
    view = left.sensor_to_ego[:3, 2] + right.sensor_to_ego[:3, 2]
    z = view - (view @ R[:, 0]) * R[:, 0]
    assert np.allclose(R[:, 2], z / np.linalg.norm(z))
    assert np.allclose(R[:, 1], np.cross(R[:, 2], R[:, 0]))


def test_pair_order_shared_K_and_disparity_range():
    left, right = nuscenes_pair(0.25)
    pair = rectify_pair(right, left, scale=0.5, min_depth=1.5)  # order of the arguments does not matter
    assert pair.left.name == "FRONT" and pair.right.name == "FRONT_RIGHT"
    K = pair.rect_left.intrinsics.K
    assert np.array_equal(K, pair.rect_right.intrinsics.K) and K[0, 0] == K[1, 1] > 0
    assert np.allclose(pair.rect_left.sensor_to_ego[:3, 3], left.sensor_to_ego[:3, 3])
    assert np.allclose(pair.rect_right.sensor_to_ego[:3, 3], right.sensor_to_ego[:3, 3])
    assert pair.max_disparity % 16 == 0
    # never more than what the minimum depth allows (rounded up to 16)
    assert pair.max_disparity < pair.focal_px * pair.baseline_m / 1.5 + 16
    # canvas = core + padding of the search range on both sides
    x0, x1 = pair.core_x
    assert x0 == pair.max_disparity and pair.size[0] == x1 + pair.max_disparity
    # the rectified focal length follows the sources' resolution at the matching scale
    assert 0.5 * 316 < pair.focal_px < 0.5 * 316 / math.cos(math.radians(35)) ** 1.5


def test_the_canvas_covers_the_shared_sector_only():
    left, right = nuscenes_pair(0.25)
    pair = rectify_pair(left, right)
    x0, x1 = pair.core_x
    both = WarpMaps.between(left, pair.rect_left).valid & WarpMaps.between(right, pair.rect_right).valid
    cols = np.nonzero(both.any(axis=0))[0]
    rows = np.nonzero(both.any(axis=1))[0]
    margin = 8
    # the directions seen by both cameras fill the core up to the margins...
    assert x0 <= cols[0] <= x0 + margin + 3 and x1 - margin - 3 <= cols[-1] < x1
    assert rows[0] <= margin + 3 and rows[-1] >= pair.size[1] - margin - 4
    # ...and the core is much narrower than either image: only the overlap is rectified
    assert x1 - x0 < 0.3 * left.width * pair.focal_px / left.intrinsics.K[0, 0]


def test_no_shared_sector_gives_none():
    left, right = nuscenes_pair(0.25)
    back = Camera("BACK", left.intrinsics, camera_mount(math.pi, np.array([0.0, 0.0, 1.5])))
    assert rectify_pair(left, back) is None


@pytest.mark.parametrize("rig", ["pinhole", "fisheye"])
def test_true_correspondences_share_rows_after_warping(rig):
    """Blobs at known 3-D points, warped into the rectified pair: same row within 0.1 px, right place."""
    left, right = nuscenes_pair(0.4) if rig == "pinhole" else fisheye_pair(320)
    pair = rectify_pair(left, right, scale=1.0)
    rng = np.random.default_rng(3)
    points = _overlap_points(pair, 16, rng)
    sigma = 1.2 / pair.focal_px
    found, expected = [], []
    for src, rect in ((pair.left, pair.rect_left), (pair.right, pair.rect_right)):
        uv, _ = rect.intrinsics.project(transform_points(invert_transform(rect.sensor_to_ego), points))
        img = WarpMaps.between(src, rect).warp(_blob_image(src, points, sigma))
        expected.append(uv)
        found.append(np.array([_centroid(img, q) for q in uv]))
    # keep blobs well apart from each other (a window must see one blob only)
    gap = np.linalg.norm(expected[0][:, None] - expected[0][None], axis=-1) + 1e3 * np.eye(len(points))
    alone = gap.min(axis=1) > 14
    assert alone.sum() >= 6
    vertical = np.abs(found[0][alone, 1] - found[1][alone, 1])
    placement = np.abs(np.concatenate([found[0] - expected[0], found[1] - expected[1]])[np.tile(alone, 2)])
    assert vertical.max() < 0.1, vertical
    # the centroid of a blob stretched by a wide-angle warp moves a little; rows are unaffected
    assert placement.max() < (0.1 if rig == "pinhole" else 0.2), placement
