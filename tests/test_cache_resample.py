"""Resizing / augmenting depth maps without inventing depths, and images with the same affine. <1 s."""

from __future__ import annotations

import numpy as np
import pytest

from sgde_plugin.cache.resample import ida_matrix, resize_depth, resize_matrix, warp_depth_affine, warp_image


def test_min_pool_of_valid_values_hand_computed():
    d = np.array([[1, 2, 0, 0], [3, 0, 0, 5], [0, 0, 7, 8], [0, 0, 9, 6]], dtype=np.float32)
    out, conf = resize_depth(d, (2, 2), d * 10)
    np.testing.assert_array_equal(out, [[1, 5], [0, 6]])
    np.testing.assert_array_equal(conf, [[10, 50], [0, 60]])  # the extra map follows the chosen pixel


def test_upsampling_is_nearest():
    d = np.array([[1, 0], [3, 4]], dtype=np.float32)
    out, = resize_depth(d, (4, 4))
    np.testing.assert_array_equal(out, np.repeat(np.repeat(d, 2, 0), 2, 1))


@pytest.mark.parametrize("out_hw", [(20, 29), (80, 100), (37, 53), (9, 70)])
def test_no_depth_is_invented_across_edges_or_holes(out_hw):
    rng = np.random.default_rng(0)
    d = np.where(np.arange(53)[None, :] < 25, 10.0, 40.0) * np.ones((37, 1))
    d[:, 25:28] = 0  # a hole along the edge
    d[rng.random(d.shape) < 0.2] = 0
    d = d.astype(np.float32)
    for m in (resize_matrix(d.shape, out_hw), ida_matrix(out_hw[1] / 53, (1, 0), True, 7.0, out_hw)):
        out, = warp_depth_affine(d, m, out_hw)
        assert out.shape == out_hw
        assert set(np.unique(out)) <= {0.0, 10.0, 40.0}


def test_flip_and_rotation_are_exact_permutations():
    rng = np.random.default_rng(1)
    d = (rng.random((16, 16)) * 50).astype(np.float32)
    img = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
    flip = ida_matrix(1.0, flip=True, out_hw=(16, 16))
    np.testing.assert_array_equal(warp_depth_affine(d, flip, (16, 16))[0], d[:, ::-1])
    np.testing.assert_array_equal(warp_image(img, flip, (16, 16)), img[:, ::-1])
    rot = ida_matrix(1.0, rotate_deg=90.0, out_hw=(16, 16))
    np.testing.assert_array_equal(warp_depth_affine(d, rot, (16, 16))[0], np.rot90(d, -1))
    np.testing.assert_array_equal(warp_image(img, rot, (16, 16)), np.rot90(img, -1))


def test_bevdepth_4x4_matrix_equals_3x3():
    m3 = ida_matrix(0.44, (10, 30), True, -5.0, (64, 176))
    m4 = np.eye(4)
    m4[:2, :2], m4[:2, 3] = m3[:2, :2], m3[:2, 2]
    d = (np.random.default_rng(2).random((225, 400)) * 60).astype(np.float32)
    np.testing.assert_array_equal(warp_depth_affine(d, m3, (64, 176))[0], warp_depth_affine(d, m4, (64, 176))[0])


def test_image_and_depth_land_on_the_same_pixels():
    """A ramp image (value = source column) and a depth map encoding the source column, warped by one
    augmentation, agree: min-pooling 2-pixel blocks picks the nearer of two columns, so the depth's
    column is half a pixel left of the image's (depth rising to the right) or right (falling)."""
    h, w = 225, 400
    cols = np.ascontiguousarray(np.broadcast_to(np.arange(w, dtype=np.float32), (h, w)))
    out_hw = (64, 176)
    m = ida_matrix(0.44, (0, 20), True, 4.0, out_hw)
    img = warp_image(cols, m, out_hw)
    interior = np.zeros(out_hw, dtype=bool)
    interior[3:-3, 3:-3] = True
    for depth, to_col, expected in ((cols + 1.0, lambda d: d - 1.0, -0.5), (w - cols, lambda d: w - d, 0.5)):
        dep, = warp_depth_affine(depth, m, out_hw)
        both = (dep > 0) & (img > 2) & (img < w - 3) & interior
        assert both.mean() > 0.5
        diff = to_col(dep) - img
        assert np.abs(diff[both]).max() <= 1.5
        assert np.median(diff[both]) == pytest.approx(expected, abs=0.1)
