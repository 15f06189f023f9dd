"""Virtual views: how the resampling into a view moves SIFT's keypoints."""

import numpy as np

from sgde_plugin.calib.features import sift_features
from sgde_plugin.calib.views import VIEW_INTERPOLATIONS, VirtualView
from sgde_plugin.cameras import Camera, Pinhole


def _blobs(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Small bright and dark Gaussian blobs (sigma 1-1.6 px) at known sub-pixel centres on a grey image."""
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    img, centres = np.full((size, size), 100.0), []
    for i in range(12):
        for j in range(12):
            cx, cy = 14 + 18.5 * i + rng.uniform(-2, 2), 14 + 18.5 * j + rng.uniform(-2, 2)
            centres.append((cx, cy))
            sigma = rng.uniform(1.0, 1.6)
            img += rng.choice([-1, 1]) * 80 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
    return np.clip(img, 0, 255).astype(np.uint8), np.array(centres)


def test_lanczos_views_keep_keypoints_where_the_blobs_are():
    """A view that samples its camera 1.25-1.4x finer and turned by 5-15 degrees (as the fisheye's views do):
    with bilinear sampling SIFT's positions, mapped back to the camera, miss the blob centres by a median
    0.019 px, with Lanczos (the default) by 0.010 px, because bilinear blurs each view pixel by
    how far it falls between source pixels. Three random images; asserted: Lanczos below 0.7x bilinear."""
    rng = np.random.default_rng(0)
    S = 240
    err = {"linear": [], "lanczos": []}
    for _ in range(3):
        img, centres = _blobs(rng, S)
        zoom, th = 1.0 / rng.uniform(0.72, 0.8), np.radians(rng.uniform(5, 15))
        W = int(S * zoom * 0.95)
        A = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) / zoom  # view offset -> source offset
        vy, vx = np.mgrid[0:W, 0:W].astype(float)
        off = np.stack([vx - (W - 1) / 2, vy - (W - 1) / 2], -1) @ A.T + (S - 1) / 2
        K = np.array([[zoom * 100.0, 0, (W - 1) / 2], [0, zoom * 100.0, (W - 1) / 2], [0, 0, 1]])
        view = VirtualView(Camera("v", Pinhole(W, W, K), np.eye(4)), off[..., 0].astype(np.float32),
                           off[..., 1].astype(np.float32), np.ones((W, W), bool), np.eye(3), 1.0 / zoom)
        for name in err:
            src = (sift_features(view.warp(img, VIEW_INTERPOLATIONS[name])).uv - (W - 1) / 2) @ A.T + (S - 1) / 2
            d = np.linalg.norm(src[None] - centres[:, None], axis=2).min(axis=1)
            err[name].extend(d[d < 1.0])
    med = {k: float(np.median(v)) for k, v in err.items()}
    assert min(len(v) for v in err.values()) > 300
    assert med["lanczos"] < 0.7 * med["linear"], med
    assert med["linear"] < 0.03 and med["lanczos"] < 0.015, med


def test_a_view_is_cut_to_where_its_camera_has_data():
    """A pinhole view turned 35 degrees off a pinhole camera's axis is mostly empty; `_trimmed` keeps every valid
    pixel with the same samples (maps, rays) and a 16 px margin, its corner on SIFT's 32 px octave grid, and
    drops the rest (here over a third of the pixels)."""
    from sgde_plugin.calib.views import _trimmed
    from sgde_plugin.geometry import make_transform, rodrigues
    from sgde_plugin.stereo.rectify import camera_maps

    src = Camera("c", Pinhole(400, 240, np.array([[300.0, 0, 199.5], [0, 300.0, 119.5], [0, 0, 1]])), np.eye(4))
    R = rodrigues(np.array([0.0, np.radians(35.0), 0.0]))
    virtual = Camera("v", Pinhole(600, 500, np.array([[300.0, 0, 299.5], [0, 300.0, 249.5], [0, 0, 1]])),
                     make_transform(R, np.zeros(3)))
    mx, my, valid = camera_maps(src, virtual)
    view = VirtualView(virtual, mx, my, valid, R, 1.0)
    cut = _trimmed(view, 16)
    x0 = int(round(virtual.intrinsics.K[0, 2] - cut.camera.intrinsics.K[0, 2]))
    y0 = int(round(virtual.intrinsics.K[1, 2] - cut.camera.intrinsics.K[1, 2]))
    h, w = cut.valid.shape
    assert x0 % 32 == 0 and y0 % 32 == 0 and (cut.camera.intrinsics.width, cut.camera.intrinsics.height) == (w, h)
    assert cut.valid.sum() == valid.sum() > 0 and h * w < 0.65 * valid.size
    np.testing.assert_array_equal(cut.map_x, mx[y0:y0 + h, x0:x0 + w])
    np.testing.assert_array_equal(cut.map_y, my[y0:y0 + h, x0:x0 + w])
    rows, cols = np.nonzero(cut.valid)
    H, W = valid.shape
    assert rows.min() >= 16 or y0 == 0
    assert cols.min() >= 16 or x0 == 0
    assert h - 1 - rows.max() >= 16 or y0 + h == H
    assert w - 1 - cols.max() >= 16 or x0 + w == W
    uv = np.stack([cols, rows], 1)[::97].astype(float)
    np.testing.assert_allclose(cut.rays_in_source(uv), view.rays_in_source(uv + [x0, y0]), atol=1e-12)


def test_a_view_phase_moves_the_pixel_grid_by_that_fraction_of_a_pixel():
    """`overlap_view(..., phase=(dx, dy))`: the same view (size, orientation, focal length) whose pixel (u, v) sees
    the ray the unshifted view sees at (u - dx, v - dy); the maps sample the camera at the moved positions."""
    from sgde_plugin.calib.overlap import overlap_grid
    from sgde_plugin.calib.views import overlap_view
    from sgde_plugin.geometry import camera_mount
    from sgde_plugin.stereo.rectify import torch_threads

    K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
    front = Camera("F", Pinhole(320, 240, K), camera_mount(0.0, np.array([1.5, 0.0, 1.6])))
    side = Camera("R", Pinhole(320, 240, K), camera_mount(-np.radians(55.0), np.array([1.2, -0.6, 1.6])))
    with torch_threads(1):
        grid = overlap_grid(front, side, np.eye(4)[None], margin_px=0.0)
        base = overlap_view(front, grid, other=side, crop=True)
        moved = overlap_view(front, grid, other=side, crop=True, phase=(0.5, 0.25))
    assert base is not None and moved is not None
    assert np.array_equal(base.R, moved.R)
    assert np.array_equal(base.camera.intrinsics.K[:2, :2], moved.camera.intrinsics.K[:2, :2])  # focal length
    # the principal point moves by the phase (plus whole 32 px steps where the cut to the data moved the corner)
    shift = moved.camera.intrinsics.K[:2, 2] - base.camera.intrinsics.K[:2, 2]
    np.testing.assert_allclose(np.mod(shift - [0.5, 0.25], 32.0), 0.0, atol=1e-9)
    np.testing.assert_array_less(np.abs(np.subtract(base.valid.shape, moved.valid.shape)), 2)
    rows, cols = np.nonzero(moved.valid)
    uv = np.stack([cols, rows], 1)[::53].astype(float)
    np.testing.assert_allclose(moved.rays_in_source(uv), base.rays_in_source(uv - shift), atol=1e-12)
    # the camera is sampled elsewhere: on the pixels both views have (integer offset), the moved view's samples
    # lie about half a view pixel (here about half a source pixel) left and a quarter above the base view's
    whole = np.round(shift - [0.5, 0.25]).astype(int)
    r_b, c_b = rows - whole[1], cols - whole[0]
    inside = (r_b >= 0) & (r_b < base.valid.shape[0]) & (c_b >= 0) & (c_b < base.valid.shape[1])
    inside[inside] &= base.valid[r_b[inside], c_b[inside]]
    dx = base.map_x[r_b[inside], c_b[inside]] - moved.map_x[rows[inside], cols[inside]]
    dy = base.map_y[r_b[inside], c_b[inside]] - moved.map_y[rows[inside], cols[inside]]
    assert inside.sum() > 1000 and 0.3 < np.median(dx) < 0.7 and 0.1 < np.median(dy) < 0.4
