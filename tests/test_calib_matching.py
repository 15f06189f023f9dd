"""Correspondences: overlap prediction, SIFT matching, USAC outlier removal, LoFTR loading (runtime ~4 s)."""

import numpy as np
import pytest
import torch

from sgde_plugin.calib.correspondences import MatchConfig, find_correspondences
from sgde_plugin.calib.features import (
    Keypoints,
    load_loftr,
    loftr_match,
    mark_fixed,
    match_descriptors,
    sift_features,
)
from sgde_plugin.calib.outliers import epipolar_angle_deg, essential_inliers, rotation_to_z
from sgde_plugin.calib.overlap import overlap_grid, pixels_per_radian
from sgde_plugin.calib.simulate import box_world_rig
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import rodrigues
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(scope="module")
def box():
    with torch_threads(1):
        return box_world_rig(n_frames=2, width=256, height=144)


def test_rotation_to_z():
    for v in ([1.0, 2.0, 3.0], [0.0, 0.0, -1.0], [0.0, 0.0, 2.0], [-1.0, 0.0, 0.0]):
        R = rotation_to_z(np.array(v))
        assert np.allclose(R @ np.array(v) / np.linalg.norm(v), [0, 0, 1], atol=1e-12)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)


def test_essential_inliers_separates_outliers_for_wide_rays():
    """Rays up to 100 deg off axis (fisheye-like) with 30% outliers: USAC keeps the inliers."""
    rng = np.random.default_rng(0)
    n = 300
    R = rodrigues(np.array([0.02, 0.9, -0.05]))  # ~52 deg between the cameras
    t = np.array([0.6, 0.05, 0.1])
    # points in the shared view, far to the side of camera a
    dirs = np.array([1.0, 0.0, -0.2]) + rng.normal(scale=0.35, size=(n, 3))
    pts = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(4, 30, size=(n, 1))
    ra = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    pb = pts @ R.T + t
    rb = pb / np.linalg.norm(pb, axis=1, keepdims=True)
    assert np.degrees(np.arccos(ra[:, 2].min())) > 95  # some rays beyond 90 deg from the axis
    bad = rng.random(n) < 0.3
    rb[bad] = rb[bad] @ rodrigues(rng.normal(scale=0.1, size=3)).T
    err = epipolar_angle_deg(ra, rb, R, t)
    assert err[~bad].max() < 1e-6 and np.median(err[bad]) > 0.5
    inl = essential_inliers(ra, rb, threshold_px=1.0, focal_px=300.0)
    assert inl[~bad].mean() > 0.95 and inl[bad].mean() < 0.05
    assert not essential_inliers(ra[:6], rb[:6], 1.0, 300.0).any()  # too few to decide


def test_overlap_grid_predicts_the_shared_view(box):
    rig_true, _, _ = box
    c0, c1 = rig_true.camera("C0"), rig_true.camera("C1")
    ego = np.stack([f.ego_to_world for f in rig_true.frames])
    g = overlap_grid(c0, c1, ego, margin_px=0.0)
    # C1 looks 60 deg to the right of C0 (80 deg field of view): C0's right edge overlaps, its left edge not
    h = c0.height // 2
    right, left = np.array([[c0.width - 3.0, h]]), np.array([[2.0, h]])
    assert g.lookup(0, 0, right)[0] and not g.lookup(0, 0, left)[0]
    assert 0.05 < g.mask[0, 0].mean() < 0.6
    assert np.isclose(pixels_per_radian(c0.intrinsics), c0.intrinsics.K[0, 0], rtol=1e-3)


def test_sift_matches_follow_the_true_geometry(box):
    rig_true, _, images = box
    a, b = rig_true.camera("C0"), rig_true.camera("C1")
    ka = sift_features(images["000000"]["C0"])
    kb = sift_features(images["000000"]["C1"])
    assert len(ka) > 100 and ka.index.tolist() == list(range(len(ka)))
    ia, ib = match_descriptors(ka.desc, kb.desc)
    ra, _ = a.intrinsics.unproject(ka.uv[ia])
    rb, _ = b.intrinsics.unproject(kb.uv[ib])
    rel = np.linalg.inv(b.sensor_to_ego) @ a.sensor_to_ego
    err_px = np.radians(epipolar_angle_deg(ra, rb, rel[:3, :3], rel[:3, 3])) * a.intrinsics.K[0, 0]
    assert len(ia) > 30 and np.median(err_px) < 0.5


def test_more_octave_layers_sample_more_scales(box):
    """`octave_layers` is OpenCV's nOctaveLayers: five scales per octave find more keypoints than Lowe's three on
    the same image, and the default is three."""
    image = box[2]["000000"]["C0"]
    three, five = sift_features(image), sift_features(image, octave_layers=5)
    assert MatchConfig().octave_layers == 3
    assert len(sift_features(image, octave_layers=3)) == len(three)
    assert len(five) > 1.2 * len(three) > 100


def test_find_correspondences_all_frame_pairs(box):
    """Every T x T observation pair is matched and verified; the answer does not depend on how many threads
    match them (the random subsets of `max_per_view_pair` are drawn in a fixed order)."""
    _, rig, images = box
    ego = np.stack([f.ego_to_world for f in rig.frames])
    ids = [f.id for f in rig.frames]
    with torch_threads(1):
        pms, one = (find_correspondences(list(rig.cameras), list(rig.pairs), ego, lambda t, c: images[ids[t]][c],
                                         config=MatchConfig(max_per_view_pair=40, threads=n)) for n in (2, 1))
    assert sum(p.inliers > len(p) for p in pms) > 0  # some pairs were subsampled
    for p, q in zip(pms, one, strict=True):
        assert np.array_equal(p.rays_a, q.rays_a) and np.array_equal(p.kp_b, q.kp_b) and p.inliers == q.inliers
    assert [(p.cam_a, p.cam_b) for p in pms] == list(rig.pairs)
    seen = set()
    for p in pms:
        assert p.inliers >= len(p) > 0 and p.gated <= p.tentative
        frame_pairs = set(zip(p.frame_a.tolist(), p.frame_b.tolist()))
        assert {(0, 0), (1, 1)} <= frame_pairs
        seen |= frame_pairs
        assert np.allclose(np.linalg.norm(p.rays_a, axis=1), 1.0) and (p.kp_a >= 0).all()
        assert (p.sigma_a >= 0.1).all()
    assert seen == {(0, 0), (0, 1), (1, 0), (1, 1)}  # all T x T frame pairs are searched


def test_loftr_needs_a_local_checkpoint(tmp_path):
    with pytest.raises(InputError, match="checkpoint path"):
        load_loftr(None)
    with pytest.raises(InputError, match="not found"):
        load_loftr(tmp_path / "missing.ckpt")
    junk = tmp_path / "junk.ckpt"
    torch.save({"state_dict": {"nope": torch.zeros(1)}}, junk)
    with pytest.raises(InputError, match="does not fit"):
        load_loftr(junk)


def test_loftr_loads_weights_only_and_matches(tmp_path):
    from kornia.feature import LoFTR

    torch.manual_seed(0)
    ckpt = tmp_path / "loftr.ckpt"
    torch.save({"state_dict": LoFTR(pretrained=None).state_dict()}, ckpt)
    model = load_loftr(ckpt)
    assert not model.training
    img = (np.random.default_rng(0).random((64, 96, 3)) * 255).astype(np.uint8)
    with torch_threads(1):
        uva, uvb = loftr_match(model, img, img, min_confidence=0.0)
    assert uva.shape == uvb.shape and uva.shape[1] == 2


def test_fisheye_overlap_view_maps_back_to_the_fisheye():
    from sgde_plugin.calib.views import overlap_view
    from sgde_plugin.cameras import Camera, KannalaBrandt, Pinhole
    from sgde_plugin.geometry import camera_mount

    K = np.array([[40.0, 0, 79.5], [0, 40.0, 79.5], [0, 0, 1]])
    model = KannalaBrandt(160, 160, K, np.zeros(4), 220.0)
    front = Camera("F", model, camera_mount(0.0, np.array([0.5, 0.0, 1.6])))
    right = Camera("R", model, camera_mount(-np.pi / 2, np.array([0.0, -0.5, 1.6])))
    with torch_threads(1):
        grid = overlap_grid(front, right, np.eye(4)[None], margin_px=0.0)
        view = overlap_view(front, grid)
        assert view is not None
        # the view looks into the front-right quadrant, between the two optical axes
        axis = view.camera.sensor_to_ego[:3, 2]
        assert axis[0] > 0.2 and axis[1] < -0.2
        uv = np.array([[10.0, 12.0], [view.camera.width // 2, view.camera.height // 2], [50.0, 70.0]])
        src_uv, ok = model.project(view.rays_in_source(uv))
    cols, rows = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert ok.all() and view.valid[rows, cols].all()
    assert np.allclose(src_uv[:, 0], view.map_x[rows, cols], atol=1e-3)
    assert np.allclose(src_uv[:, 1], view.map_y[rows, cols], atol=1e-3)
    # a pair of a wide and a narrow camera: the views share the coarser (default), the finer or the mean scale
    narrow = Camera("N", Pinhole(160, 160, np.array([[160.0, 0, 79.5], [0, 160.0, 79.5], [0, 0, 1]])),
                    camera_mount(-np.pi / 4, np.array([0.3, -0.3, 1.6])))
    with torch_threads(1):
        g = overlap_grid(front, narrow, np.eye(4)[None], margin_px=0.0)
        f = {s: overlap_view(front, g, other=narrow, crop=True, pair_scale=s).camera.intrinsics.K[0, 0]
             for s in ("min", "max", "mean")}
        twice = overlap_view(front, g, other=narrow, crop=True, upsample=2.0).camera.intrinsics.K[0, 0]
    assert 30.0 < f["min"] < 60.0 and np.isclose(f["max"], 160.0, rtol=0.02)
    assert np.isclose(f["mean"], np.sqrt(f["min"] * f["max"])) and np.isclose(twice, 2 * f["min"])


def test_keypoints_that_stay_at_one_pixel_are_marked_fixed():
    """Texture that moves with the car (or lies at infinity) recurs at the same pixel in every frame: it is
    marked, texture of the static world that moves in the image is not, nor a different keypoint that
    happens to sit at the same pixel."""
    rng = np.random.default_rng(0)
    desc = rng.random((30, 128)).astype(np.float32)
    uv0 = rng.uniform(0, 300, (30, 2))
    frames = []
    for t in range(3):
        uv = uv0.copy()
        uv[10:] += [25.0 * t, 3.0 * t]  # the static world flows past; keypoints 0-9 ride along with the car
        d = desc.copy()
        if t == 2:
            d[5] = rng.random(128)  # keypoint 5 in frame 2 is another feature at the same pixel
        frames.append(Keypoints(uv + rng.normal(scale=0.2, size=uv.shape), d))
    mark_fixed(frames)
    assert frames[0].fixed[:10].all() and not frames[0].fixed[10:].any()
    assert frames[2].fixed[:5].all() and frames[2].fixed[6:10].all() and not frames[2].fixed[5]
    assert frames[1].subset(np.arange(8, 12)).fixed.tolist() == [True, True, False, False]


def test_sift_keypoints_sit_at_the_blob_centres():
    """Gaussian blobs at known sub-pixel centres: SIFT positions (pixel centres at integers) have no offset.

    OpenCV's default upscale reports every keypoint +0.25 px right and down; the mean error must be < 0.03 px
    (and at both scales of `sift_features`)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:160, 0:160].astype(float)
    for scale in (1.0, 0.5):
        err = []
        for _ in range(6):
            img = np.full((160, 160), 128.0)
            jitter = rng.uniform(-3, 3, (9, 2))
            centres = [(25 + 55 * (i % 3) + jitter[i, 0], 25 + 55 * (i // 3) + jitter[i, 1]) for i in range(9)]
            for cx, cy in centres:
                img += 100 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * rng.uniform(3.0, 5.0) ** 2))
            kp = sift_features(np.clip(img, 0, 255).astype(np.uint8), scale=scale)
            for c in centres:
                d = kp.uv - c
                near = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) < 2.0)
                if near.size:
                    err.append(d[near[np.argmin(np.hypot(d[near, 0], d[near, 1]))]])
        err = np.array(err)
        assert len(err) >= 30
        assert np.all(np.abs(err.mean(axis=0)) < 0.03), (scale, err.mean(axis=0))
