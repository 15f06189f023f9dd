"""PriorBuilder end to end on analytic scenes: a plane at known depth, both cameras, masks, depth range,
the fisheye path against the virtual-pinhole path, fusion and configuration.

Runtime: about 15 s on 2 cores.
"""

from __future__ import annotations

import functools
import math
import re

import cv2
import numpy as np
import pytest
from stereo_scene import Plane, fisheye_pair, nuscenes_pair, render, wall

from sgde_plugin.cameras import Camera
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount
from sgde_plugin.rig import Rig
from sgde_plugin.stereo.backproject import fuse_into
from sgde_plugin.stereo.filters import lr_check
from sgde_plugin.stereo.pipeline import PRIOR_ALGO_VERSION, PriorBuilder, PriorConfig
from sgde_plugin.stereo.rectify import torch_threads

GROUND = Plane(np.zeros(3), np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), seed=9)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads, and OpenMP threads crawl on a busy machine."""
    with torch_threads(1):
        yield


@functools.cache
def pinhole_scene(far: float = 10.0):
    """A nuScenes-like front pair (480x270) looking at a wall `far` m away across the overlap, and the ground."""
    left, right = nuscenes_pair(0.3)
    planes = [wall(far, -27.5, seed=1), GROUND]
    images, depths = {}, {}
    for cam in (left, right):
        images[cam.name], depths[cam.name] = render(planes, cam)
    rig = Rig((left, right), ((left.name, right.name),), ())
    return rig, images, depths


@functools.cache
def fisheye_scene():
    """Two 220-degree fisheyes (480x480) inside a box of textured walls."""
    front, right = fisheye_pair(480)
    planes = [wall(12.0, 0.0, seed=1), wall(9.0, -90.0, seed=2), wall(14.0, 180.0, seed=3), wall(9.0, 90.0, seed=4),
              GROUND]
    images, depths = {}, {}
    for cam in (front, right):
        images[cam.name], depths[cam.name] = render(planes, cam)
    rig = Rig((front, right), ((front.name, right.name),), ())
    return rig, images, depths


def _rel(prior: np.ndarray, gt: np.ndarray) -> np.ndarray:
    ok = (prior > 0) & (gt > 0)
    return np.abs(prior[ok] - gt[ok]) / gt[ok]


def test_plane_at_known_depth_comes_back_within_one_percent_in_both_cameras():
    rig, images, depths = pinhole_scene()
    out = PriorBuilder(rig, PriorConfig()).build(images)
    for name in ("FRONT", "FRONT_RIGHT"):
        prior, gt = out[name], depths[name]
        assert prior.depth.shape == gt.shape and prior.depth.dtype == np.float32
        assert np.array_equal(prior.confidence > 0, prior.depth > 0)
        assert prior.confidence.max() <= 1.0
        on_wall = (prior.depth > 0) & (np.abs(gt - 10.0 / math.cos(0)) < 3)  # wall pixels are 8-13 m away
        rel = _rel(np.where(on_wall, prior.depth, 0), gt)
        assert rel.size > 3000
        assert rel.mean() < 0.01 and np.median(rel) < 0.005, (rel.mean(), np.median(rel))
        assert np.mean(rel < 0.01) > 0.85
        # only the overlap gets a prior: FRONT's right edge, FRONT_RIGHT's left edge
        cols = np.nonzero(prior.depth.any(axis=0))[0]
        assert (cols.min() > 0.7 * 480) if name == "FRONT" else (cols.max() < 0.3 * 480)


def test_masks_and_depth_range_are_respected():
    rig, images, depths = pinhole_scene()
    mask = np.ones(depths["FRONT"].shape, bool)
    mask[135:] = False
    out = PriorBuilder(rig, PriorConfig()).build(images, {"FRONT": mask.astype(np.uint8) * 255})  # 0 = ignore
    assert not out["FRONT"].depth[135:].any() and not out["FRONT"].confidence[135:].any()
    assert out["FRONT"].depth[:135].any()
    # the masked pixels cannot be matched from the other side either: FRONT_RIGHT loses their twins
    full = PriorBuilder(rig, PriorConfig()).build(images)
    assert (out["FRONT_RIGHT"].depth > 0).sum() < 0.9 * (full["FRONT_RIGHT"].depth > 0).sum()
    # a closer maximum depth drops the wall (8-13 m) and keeps the nearer ground
    near = PriorBuilder(rig, PriorConfig.from_settings(max_depth=7.0)).build(images)["FRONT"].depth
    assert near.any() and near.max() <= 7.0


def test_fisheye_path_agrees_with_the_virtual_pinhole_path():
    rig, images, depths = fisheye_scene()
    direct = PriorBuilder(rig, PriorConfig.from_settings(fisheye="direct")).build(images)
    virtual = PriorBuilder(rig, PriorConfig.from_settings(fisheye="virtual")).build(images)
    for name in ("F", "R"):
        a, b, gt = direct[name].depth, virtual[name].depth, depths[name]
        both = (a > 0) & (b > 0)
        assert both.sum() > 1000
        diff = np.abs(a[both] - b[both]) / b[both]
        assert np.median(diff) < 0.01 and np.percentile(diff, 95) < 0.04, (np.median(diff), np.percentile(diff, 95))
        for prior in (a, b):  # fisheye depth is range: both against the range ground truth
            rel = _rel(prior, gt)
            assert np.median(rel) < 0.01 and rel.mean() < 0.03


def test_camera_without_overlap_gets_an_empty_map_and_bad_input_is_refused():
    rig, images, _ = pinhole_scene()
    left, right = rig.cameras
    back = Camera("BACK", left.intrinsics, camera_mount(math.pi, np.array([0.0, 0.0, 1.5])))
    rig3 = Rig((left, right, back), (("FRONT", "FRONT_RIGHT"), ("FRONT", "BACK")), ())
    builder = PriorBuilder(rig3, PriorConfig())
    assert len(builder.plans) == 1
    out = builder.build({**images, "BACK": images["FRONT"]})
    assert out["BACK"].depth.shape == (270, 480) and not out["BACK"].depth.any()
    with pytest.raises(InputError, match="FRONT_RIGHT"):
        builder.build({"FRONT": images["FRONT"], "FRONT_RIGHT": images["FRONT_RIGHT"][:100]})
    with pytest.raises(InputError, match="missing"):
        builder.build({"FRONT": images["FRONT"]})
    with pytest.raises(InputError, match="masks"):
        builder.build({**images, "BACK": images["FRONT"]}, {"FRONT": np.ones((10, 10), bool)})


def test_grey_rgb_and_rgba_images_give_one_prior_and_other_arrays_are_one_line():
    """HxW, HxWx1, HxWx3 and HxWx4 (alpha dropped) images of one scene give the same prior; an array that is not an
    image (None, two channels, a batch) is an InputError naming the camera and the shape, not an OpenCV error."""
    rig, images, _ = pinhole_scene()
    builder = PriorBuilder(rig, PriorConfig())
    rgb = {k: np.dstack([v, v // 2, 255 - v]) for k, v in ((k, v[..., 0]) for k, v in images.items())}
    grey = {k: cv2.cvtColor(v, cv2.COLOR_RGB2GRAY) for k, v in rgb.items()}
    ref = builder.build(rgb)
    assert max((ref[k].depth > 0).mean() for k in ref) > 0.02
    for variant in (grey, {k: v[..., None] for k, v in grey.items()},
                    {k: np.dstack([v, np.full(v.shape[:2], 7, np.uint8)]) for k, v in rgb.items()}):
        out = builder.build(variant)
        assert all(np.array_equal(out[k].depth, ref[k].depth) for k in ref)
    bad_images = ((None, "()"), (rgb["FRONT"][..., :2], "(270, 480, 2)"), (rgb["FRONT"][None], "(1, 270, 480, 3)"))
    for bad, shape in bad_images:
        with pytest.raises(InputError, match=rf"images\[FRONT\]: must be HxW \(grey\) or HxWx3 \(RGB\), got shape "
                           rf"{re.escape(shape)}"):
            builder.build({**rgb, "FRONT": bad})


def test_config_dict_tracks_everything_that_changes_the_output(tmp_path):
    base = PriorConfig().to_dict()
    assert base["algo_version"] == PRIOR_ALGO_VERSION and base["matcher"] == "sgbm" and base["scale"] == 0.5
    assert PriorConfig.from_settings(scale=0.25).to_dict() != base
    assert PriorConfig.from_settings(uniqueness=5).to_dict() != base
    model = tmp_path / "m.pt"
    model.write_bytes(b"one")
    d1 = PriorConfig.from_settings(matcher="torch", matcher_path=str(model)).to_dict()
    model.write_bytes(b"two")
    d2 = PriorConfig.from_settings(matcher="torch", matcher_path=str(model)).to_dict()
    assert d1["matcher_sha256"] != d2["matcher_sha256"] and d1["uniqueness"] == 15  # every setting is in
    with pytest.raises(InputError):
        PriorConfig.from_settings(matcher="raft")
    with pytest.raises(InputError):
        PriorConfig.from_settings(matcher="torch")  # needs a file


def test_fusion_of_two_neighbours():
    depth = np.zeros((1, 4), np.float32)
    conf = np.zeros((1, 4), np.float32)
    fuse_into(depth, conf, np.array([0, 1, 2]), np.array([10.0, 10.0, 10.0], np.float32),
              np.array([0.5, 0.5, 0.8], np.float32))
    # pixel 1: agreeing value -> weighted mean; pixel 2: disagreeing -> more confident wins, halved; 3: new
    fuse_into(depth, conf, np.array([1, 2, 3]), np.array([10.3, 20.0, 7.0], np.float32),
              np.array([0.25, 0.4, 0.6], np.float32))
    assert np.allclose(depth, [[10.0, (10 * 0.5 + 10.3 * 0.25) / 0.75, 10.0, 7.0]])
    assert np.allclose(conf, [[0.5, 1 - 0.5 * 0.75, 0.4, 0.6]])


def test_left_right_check():
    disp_l = np.array([[0, 0, 2, 2, 3]], np.float32)
    conf_l = np.array([[0, 0, 1, 1, 1]], np.float32)
    disp_r = np.array([[2, 2, 0, 0, 0]], np.float32)  # right x=0 <- left x=2, right x=1 <- left x=3
    conf_r = np.array([[1, 1, 0, 0, 0]], np.float32)
    out = lr_check(disp_l, conf_l, disp_r, conf_r, -1, 1.0)
    # x=2 -> right 0 (d 2 == 2), x=3 -> right 1 (2 == 2), x=4 -> right 1 (d 3 vs 2: within 1 px, lower conf)
    assert np.allclose(out, [[0, 0, 1, 1, math.exp(-0.5)]])
    back = lr_check(disp_r, conf_r, disp_l, conf_l, +1, 1.0)
    assert np.allclose(back, [[1, 1, 0, 0, 0]])


def test_result_does_not_depend_on_the_thread_count():
    rig, images, _ = fisheye_scene()
    rig = Rig(rig.cameras, (("F", "R"), ("R", "F")), ())  # two plans to run side by side (and fuse)
    one = PriorBuilder(rig, PriorConfig(), threads=1).build(images)
    two = PriorBuilder(rig, PriorConfig(), threads=2).build(images)
    assert one["F"].depth.any()
    for name in one:
        assert np.array_equal(one[name].depth, two[name].depth)
        assert np.array_equal(one[name].confidence, two[name].confidence)


@pytest.mark.parametrize("dense", [False, True])
def test_backprojection_skipping_empty_map_rows_loses_no_sample(dense):
    """Sparse confidence (small patches: map rows skipped) and dense (every row: the one-pass path): `values`
    equals one plain remap of every covered pixel, bit for bit."""
    rig, _, _ = pinhole_scene()
    back = PriorBuilder(rig, PriorConfig()).plans[0].left.back
    h, w = back.core
    yy, xx = np.mgrid[0:h, 0:w]
    disp = (20 + 0.05 * xx + 0.03 * yy).astype(np.float32)  # smooth: no disparity jump to drop
    conf = np.zeros((h, w), np.float32)
    rng = np.random.default_rng(3)
    for y, x in zip(rng.integers(0, h - 1, 25), rng.integers(0, w - 1, 25)):
        conf[y : y + 3, x : x + 3] = rng.uniform(0.2, 1.0)  # 3x3 patches (2x2 at the border)
    if dense:
        conf = np.where(conf > 0, conf, 0.7).astype(np.float32)
        conf[::7, ::5] = 0  # holes
    idx, z, c = back.values(disp, conf, 0.5, 80.0)
    out = np.stack([cv2.remap(img.astype(np.float32), back.map_x, back.map_y, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=fill).reshape(-1)[: back.count]
                    for img, fill in ((np.where(conf > 0, disp, -1.0e5), -1.0e5), (conf, 0.0))], axis=1)
    ok = out[:, 0] > 0
    ref_z = back.kfb[ok] / out[ok, 0]
    keep = (ref_z >= 0.5) & (ref_z <= 80.0)
    assert (idx.size > 0.5 * back.count) if dense else (50 < idx.size < 0.1 * back.count)
    assert np.array_equal(idx, back.index[ok][keep])
    assert np.array_equal(z, ref_z[keep]) and np.array_equal(c, out[ok, 1][keep])
