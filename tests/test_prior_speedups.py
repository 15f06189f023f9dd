"""The prior's speed-ups change no value (the checks on the box of the matches up to float rounding in box
filters): warps without a mask pass, and pairs scheduled costliest first with each camera fused early (the
one-pass back-projection: test_stereo_prior.py).

Runtime: about 5 s on 2 cores.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch
from test_stereo_prior import fisheye_scene, pinhole_scene

from sgde_plugin.rig import Rig
from sgde_plugin.stereo import checks
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.rectify import torch_threads
from sgde_plugin.stereo.schedule import longest_first, run_pairs


@pytest.fixture(autouse=True)
def _one_torch_thread():
    with torch_threads(1):
        yield


def _whole_core(*confs, halo=checks.HALO):
    """match_box that always answers the whole core (the computation before the speed-up)."""
    if not any((c > 0).any() for c in confs):
        return None
    return slice(0, confs[0].shape[0]), slice(0, confs[0].shape[1])


@pytest.mark.parametrize("scene", [pinhole_scene, fisheye_scene])
def test_checks_on_the_box_of_the_matches_equal_the_whole_core(scene, monkeypatch):
    rig, images, _ = scene()
    rig = Rig(rig.cameras, (tuple(rig.camera_names),), ())
    fast = PriorBuilder(rig, PriorConfig(), threads=1).build(images)
    monkeypatch.setattr(checks, "match_box", _whole_core)
    slow = PriorBuilder(rig, PriorConfig(), threads=1).build(images)
    name = rig.camera_names[0]
    assert (fast[name].depth > 0).mean() > 0.02
    for cam in fast:  # box filters sum along a row from where it starts: float rounding, nothing more
        assert np.array_equal(fast[cam].depth > 0, slow[cam].depth > 0)
        np.testing.assert_allclose(fast[cam].depth, slow[cam].depth, rtol=1e-5, atol=0)
        np.testing.assert_allclose(fast[cam].confidence, slow[cam].confidence, rtol=0, atol=1e-4)


def test_match_box_holds_every_match_and_its_halo():
    conf_l = np.zeros((50, 40), np.float32)
    conf_r = np.zeros_like(conf_l)
    conf_l[10, 12] = 0.5
    conf_r[30, 38] = 0.2
    rows, cols = checks.match_box(conf_l, conf_r, halo=3)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (7, 34, 9, 40)  # clipped at the right edge
    assert checks.match_box(np.zeros((4, 4))) is None


def test_hull_of_the_two_boxes_is_the_box_of_both():
    """check_pair takes the left-right check's box as the hull of the two references' boxes: the same box as
    match_box over both maps, halo and clipping included, on random sparse maps (and an empty side)."""
    rng = np.random.default_rng(2)
    for _ in range(50):
        h, w = rng.integers(5, 40, 2)
        conf_l, conf_r = ((rng.random((h, w)) > rng.uniform(0.9, 1.0)) * rng.random((h, w)) for _ in range(2))
        if rng.random() < 0.2:
            conf_r[:] = 0
        assert checks.hull(checks.match_box(conf_l), checks.match_box(conf_r)) == checks.match_box(conf_l, conf_r)
    assert checks.hull(None, None) is None


@pytest.mark.parametrize(("scene", "edge"), [(pinhole_scene, True), (fisheye_scene, False)])
def test_warp_is_zero_outside_the_valid_canvas_without_a_mask_pass(scene, edge):
    """`edge`: the canvas has pixels its camera does not see (the fisheyes see all of theirs)."""
    rig, images, _ = scene()
    plan = PriorBuilder(rig, PriorConfig()).plans[0]
    rng = np.random.default_rng(0)
    invalid = 0
    for side in (plan.left, plan.right):
        cam = rig.camera(side.camera)
        image = rng.integers(1, 256, (cam.height, cam.width, 3), dtype=np.uint8)
        warps = [side.rect] if side.pre is None else [side.pre, side.rect]
        for maps in warps:
            src = image if maps is warps[0] else warps[0].warp(image)
            out = maps.warp(src)
            invalid += int((~maps.valid).sum())
            assert maps.valid.mean() > 0.2
            assert not out[~maps.valid].any()
            assert out[maps.valid].mean() > 20
    assert invalid > 1000 or not edge


def test_run_pairs_gives_the_sequential_results_in_order():
    items = [3, 1, 4, 1, 5, 9]
    needs = {"a": [0, 1], "b": [1, 2], "c": [5, 0], "lonely": []}

    def consume(key, results):
        return (key, tuple(results))

    plain = run_pairs(items, lambda x: x * x, needs, consume)
    assert plain == ([9, 1, 16, 1, 25, 81], {"a": ("a", (9, 1)), "b": ("b", (1, 16)), "c": ("c", (9, 81)),
                                             "lonely": ("lonely", ())})
    with ThreadPoolExecutor(2) as pool:
        assert run_pairs(items, lambda x: x * x, needs, consume, pool, [float(i) for i in items]) == plain
    assert longest_first([2.0, 5.0, 1.0, 5.0]) == [1, 3, 0, 2]


def test_parallel_build_runs_opencv_single_threaded_in_each_pair_thread_and_restores_it(monkeypatch):
    """With two pair threads every OpenCV call runs in its caller (no nested stripes, no spinning pool); the
    process-wide count is back afterwards, and the priors equal a one-thread build's bit for bit."""
    import cv2

    from sgde_plugin.threads import opencv_threads

    rig, images, _ = fisheye_scene()
    rig = Rig(rig.cameras, (("F", "R"), ("R", "F")), ())
    one = PriorBuilder(rig, PriorConfig(), threads=1).build(images)
    with opencv_threads(2):
        builder = PriorBuilder(rig, PriorConfig(), threads=2)
        seen = []
        match = type(builder.matcher).match
        monkeypatch.setattr(type(builder.matcher), "match",
                            lambda *a: (seen.append(cv2.getNumThreads()), match(*a))[1])
        two = builder.build(images)
        assert cv2.getNumThreads() == 2
    assert len(builder.plans) >= 2 and seen == [1] * (2 * len(builder.plans))  # every canvas pair x two references
    for name in one:
        assert np.array_equal(one[name].depth, two[name].depth)
        assert np.array_equal(one[name].confidence, two[name].confidence)
    calls = []

    def failing(*a):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("matcher failed")
        return match(*a)

    monkeypatch.setattr(type(builder.matcher), "match", failing)
    with opencv_threads(2):
        with pytest.raises(RuntimeError, match="matcher failed"):
            builder.build(images)
        assert cv2.getNumThreads() == 2  # restored after a failed build too
    with opencv_threads(3):
        assert cv2.getNumThreads() == 3
        with pytest.raises(RuntimeError), opencv_threads(1):
            raise RuntimeError
        assert cv2.getNumThreads() == 3


def test_backprojection_float_maps_sit_on_the_fixed_point_grid():
    """The backward maps are float (cv2.remap of float data runs about twice as fast with them) but hold the
    1/32 px positions of OpenCV's fixed-point maps: a fixed-point remap gives the same samples up to float
    rounding of the interpolation, and the same pixels get a value."""
    import cv2

    rig, _, _ = pinhole_scene()
    back = PriorBuilder(rig, PriorConfig()).plans[0].left.back
    assert back.map_x.dtype == np.float32 and back.map_x.shape == back.map_y.shape
    for m in (back.map_x, back.map_y):
        assert np.array_equal(m * 32, np.rint(m * 32))
    h, w = back.core
    yy, xx = np.mgrid[0:h, 0:w]
    disp = (20 + 0.05 * xx + 0.03 * yy).astype(np.float32)
    conf = np.full((h, w), 0.8, np.float32)
    conf[::9, ::4] = 0
    idx, z, c = back.values(disp, conf, 0.5, 80.0)
    map1, map2 = cv2.convertMaps(back.map_x, back.map_y, cv2.CV_16SC2)
    stack = np.dstack([np.where(conf > 0, disp, -1.0e5), conf]).astype(np.float32)
    out = cv2.remap(stack, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(-1.0e5, 0.0, 0.0, 0.0)).reshape(-1, 2)[: back.count]
    ok = out[:, 0] > 0
    ref_z = back.kfb[ok] / out[ok, 0]
    keep = (ref_z >= 0.5) & (ref_z <= 80.0)
    assert idx.size > 0.5 * back.count
    assert np.array_equal(idx, back.index[ok][keep])
    np.testing.assert_allclose(z, ref_z[keep], rtol=1e-5, atol=0)
    np.testing.assert_allclose(c, out[ok, 1][keep], rtol=0, atol=1e-5)


def test_warp_on_the_box_of_the_valid_canvas_equals_a_whole_canvas_remap():
    """The warp maps cover only the box of the target pixels the source sees; grey, colour, float and
    nearest-neighbour warps equal one remap over the whole target bit for bit (a rectified pinhole canvas,
    and a fisheye's virtual pinholes with their rim)."""
    import cv2

    from sgde_plugin.stereo.rectify import WarpMaps, camera_maps
    from sgde_plugin.stereo.virtual import virtual_pinholes

    rig, _, _ = pinhole_scene()
    plan = PriorBuilder(rig, PriorConfig()).plans[0]
    fish, _, _ = fisheye_scene()
    cases = [(rig.camera(plan.left.camera), plan.pair.rect_left, 0),
             (rig.camera(plan.right.camera), plan.pair.rect_right, 0)]
    cases += [(fish.camera("F"), half, 3) for half in virtual_pinholes(fish.camera("F"))]
    rng = np.random.default_rng(1)
    cropped = 0
    for src, dst, rim in cases:
        maps = WarpMaps.between(src, dst, rim)
        rows, cols = maps.box
        assert maps.map1.shape[:2] == (rows.stop - rows.start, cols.stop - cols.start)
        assert maps.valid[rows, cols].sum() == maps.valid.sum() > 0
        cropped += maps.map1.shape[0] * maps.map1.shape[1] < 0.9 * maps.valid.size
        map_x, map_y, _ = camera_maps(src, dst, rim)
        full1, full2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        for image in (rng.integers(0, 256, (src.height, src.width), dtype=np.uint8),
                      rng.integers(0, 256, (src.height, src.width, 3), dtype=np.uint8),
                      rng.random((src.height, src.width), dtype=np.float32)):
            for interp in (cv2.INTER_LINEAR, cv2.INTER_NEAREST):
                ref = cv2.remap(image, full1, full2, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                assert np.array_equal(maps.warp(image, interp), ref)
    assert cropped >= 2  # the rectified canvases are cut, not just the trivial whole box


def _pair_patch(seed: int = 0, h: int = 60, w: int = 90, pad: int = 24):
    """A textured reference box `a` (float32 grey) and the other canvas `b`: b shifted by a smooth disparity."""
    import cv2

    rng = np.random.default_rng(seed)
    b = cv2.GaussianBlur(rng.random((h, w + 2 * pad), np.float32) * 255, (0, 0), 1.2)
    yy, xx = np.mgrid[0:h, 0:w]
    disp = (6 + 0.04 * xx + 0.02 * yy + rng.normal(0, 0.3, (h, w))).astype(np.float32)
    x0 = pad
    map_x = (np.arange(x0, x0 + w, dtype=np.float32)[None, :] - disp).astype(np.float32)
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    a = cv2.remap(b, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) + rng.normal(0, 2, (h, w))
    valid = rng.random((h, w)) > 0.2
    return a.astype(np.float32), b, np.rint(disp * 16) / 16, valid, x0


def test_refinement_and_photometric_scores_equal_the_straightforward_computation():
    """In-place arithmetic changes no value: both functions equal the plain
    (allocating) formulas bit for bit, on a textured pair with a slanted, noisy disparity."""
    import cv2

    from sgde_plugin.stereo import filters

    for seed in range(3):
        a, b, disp, valid, x0 = _pair_patch(seed)
        # refinement, straightforward
        db = np.zeros_like(b)
        db[:, :-1] = b[:, 1:] - b[:, :-1]
        d = disp.copy()
        map_x, map_y = filters.shift_maps(d, -1, x0)
        bw = cv2.remap(b, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        j = -1 * cv2.remap(db, np.floor(map_x), map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        e = a - bw
        mj, me = cv2.blur(j, (5, 5)), cv2.blur(e, (5, 5))
        num = cv2.blur(j * e, (5, 5)) - mj * me
        den = cv2.blur(j * j, (5, 5)) - mj * mj
        step = np.clip(num / np.maximum(den, 1e-3), -0.5, 0.5)
        ok = valid & (den > 1.0)
        d[ok] += step[ok]
        ref = np.where(valid, d, np.float32(0))
        out = filters.refine_disparity(a, b, disp, valid, -1, x0)
        assert np.array_equal(out, ref) and np.abs(out - disp)[valid].max() > 0.05  # it did refine
        # photometric scores, straightforward
        bw = cv2.remap(b, *filters.shift_maps(out, -1, x0), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        e = a - bw
        mad = cv2.blur(np.abs(e - float(np.median(e[valid]))), (7, 7))
        ma, mb = cv2.blur(a, (7, 7)), cv2.blur(bw, (7, 7))
        va, vb = cv2.blur(a * a, (7, 7)) - ma * ma, cv2.blur(bw * bw, (7, 7)) - mb * mb
        ncc = (cv2.blur(a * bw, (7, 7)) - ma * mb) / np.sqrt(np.maximum(va * vb, 1e-6))
        ncc[np.minimum(va, vb) < 4.0] = -1.0
        gx = filters.x_gradient(a)
        texture = np.sqrt(cv2.blur(gx * gx, (7, 7)))
        got = filters.photometric_scores(a, b, out, valid, -1, x0)
        for x, y in zip(got, (ncc, mad, texture)):
            assert x.dtype == np.float32 and np.array_equal(x, y)
        assert np.median(got[0][valid]) > 0.6  # the refined match is good (2 grey levels of noise)


def test_left_right_check_by_nearest_remap_equals_the_gather():
    """The other map is read by a nearest-neighbour remap at the rounded column: the same as the flat-index
    gather it replaced, with matches outside the map (both sides) failing, on random maps and views."""
    from sgde_plugin.stereo.filters import lr_check

    rng = np.random.default_rng(5)
    h, w = 40, 70
    for sign in (-1, 1):
        field = 10 + 0.02 * np.arange(w + 6)[None, :] + rng.normal(0, 0.6, (h, w + 6))
        disp_a = field.astype(np.float32)[:, 3:-3]  # a view, as check_pair passes
        disp_b = (field[:, 3:-3] + rng.normal(0, 0.6, (h, w))).astype(np.float32)[:, ::-1][:, ::-1]
        conf_a = (rng.random((h, w)) > 0.3).astype(np.float32) * 0.9
        conf_b = (rng.random((h, w)) > 0.3).astype(np.float32) * 0.7
        cols = np.arange(w, dtype=np.float32)[None, :]
        x = np.rint(cols + disp_a if sign > 0 else cols - disp_a).astype(np.intp)
        inside = (x >= 0) & (x < w)
        flat = np.clip(x, 0, w - 1) + np.arange(0, h * w, w)[:, None]
        other, other_c = disp_b.reshape(-1)[flat], conf_b.reshape(-1)[flat]
        diff = np.abs(disp_a - other)
        ok = inside & (conf_a > 0) & (other_c > 0) & (diff <= 1.0)
        ref = np.where(ok, conf_a * np.exp(-0.5 * diff**2), 0).astype(np.float32)
        out = lr_check(disp_a, conf_a, disp_b, conf_b, sign, 1.0)
        assert (~inside & (conf_a > 0)).sum() > 50 and ok.sum() > 200
        assert out.dtype == np.float32 and np.array_equal(out, ref)


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000, 1001])
def test_masked_median_is_numpys_median(n):
    from sgde_plugin.stereo.filters import masked_median

    rng = np.random.default_rng(n)
    values = (rng.normal(size=(40, 60)) * 30).astype(np.float32)
    mask = np.zeros(values.shape, bool)
    mask.reshape(-1)[rng.permutation(mask.size)[:n]] = True
    before = values.copy()
    expected = float(np.median(values[mask])) if n else 0.0
    assert masked_median(values, mask) == expected
    np.testing.assert_array_equal(values, before)  # the input is left as it was


def _random_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation by up to `max_deg` about a random axis."""
    import cv2

    axis = rng.normal(size=3)
    axis *= np.radians(rng.uniform(0, max_deg)) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis)[0]


def _landing(rays, ok, R, K, window):
    """Bool (H, W): valid pixels whose ray, turned by R, lands in the canvas window of intrinsics K (brute force)."""
    q = rays.numpy() @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * q[..., 0] / q[..., 2] + K[0, 2]
        v = K[1, 1] * q[..., 1] / q[..., 2] + K[1, 2]
    return ok.numpy() & (q[..., 2] > 1e-6) & (u >= window[0]) & (u <= window[1]) & (v >= window[2]) & (v <= window[3])


def test_candidate_box_holds_every_pixel_that_lands_in_the_canvas_window():
    """The back-projection rotates only a block of the original pixels; on random turns and canvas windows the block
    holds every valid pixel whose ray lands in the window (a pinhole, a strongly distorted one, a 220-degree
    fisheye whose valid area is a disc), also when the window's border is sampled 64x more sparsely (the margin
    then has to cover what lies between samples), and is not much larger than their bounding box."""
    from sgde_plugin.cameras import KannalaBrandt, Pinhole
    from sgde_plugin.rig import Camera
    from sgde_plugin.stereo.backproject import _candidate_box

    K = np.array([[150.0, 0, 99.5], [0, 150.0, 59.5], [0, 0, 1]])
    fish = np.array([[160 / 2 / np.radians(110), 0, 79.5], [0, 160 / 2 / np.radians(110), 79.5], [0, 0, 1]])
    models = [Pinhole(200, 120, K, None), Pinhole(200, 120, K, np.array([-0.32, 0.12, 0.001, -0.002, -0.02])),
              KannalaBrandt(160, 160, fish, np.zeros(4), 220.0)]
    rng = np.random.default_rng(7)
    checked = tight = edge = 0
    for model in models:
        cam = Camera("C", model, np.eye(4))
        rays, ok = model.ray_grid()
        for trial in range(80):
            R = _random_rotation(rng, 120.0 if trial % 4 else 20.0)
            f = rng.uniform(40, 300) if trial % 4 else rng.uniform(10, 40)  # every fourth: a view beyond the image
            Kr = np.array([[f, 0, rng.uniform(0, 120)], [0, f, rng.uniform(0, 80)], [0, 0, 1]])
            u_lo, v_lo = rng.uniform(-20, 100), rng.uniform(-20, 60)
            window = (u_lo, u_lo + rng.uniform(5, 120), v_lo, v_lo + rng.uniform(5, 80))
            rows, cols = np.nonzero(_landing(rays, ok, R, Kr, window))
            if rows.size == 0:
                continue
            checked += 1
            edge += bool(rows.min() == 0 or cols.min() == 0 or rows.max() == model.height - 1
                         or cols.max() == model.width - 1 or not ok.numpy()[rows, cols].all())
            for step in (64.0, 1.0):
                r0, r1, c0, c1 = _candidate_box(cam, R, Kr, window, rays, ok, step_px=step)
                assert r0 <= rows.min() and rows.max() < r1 and c0 <= cols.min() and cols.max() < c1, (model, step)
            span_r, span_c = int(rows.max() - rows.min()) + 1, int(cols.max() - cols.min()) + 1
            tight += (r1 - r0) * (c1 - c0) <= (span_r + 24) * (span_c + 24)
    assert checked >= 80 and edge >= 20 and tight >= 0.9 * checked, (checked, edge, tight)
    # the whole image seen through a wide canvas: no border sample lands in the image, the image's frame holds it
    rays, ok = models[0].ray_grid()
    wide = np.array([[30.0, 0, 60.0], [0, 30.0, 40.0], [0, 0, 1]])
    assert _landing(rays, ok, np.eye(3), wide, (0, 119, 0, 79)).all()
    assert _candidate_box(Camera("C", models[0], np.eye(4)), np.eye(3), wide, (0, 119, 0, 79), rays, ok) == (
        0, 120, 0, 200)
    assert _candidate_box(Camera("C", models[0], np.eye(4)), np.eye(3), K, None, rays, ok) == (0, 0, 0, 0)


@pytest.mark.parametrize("scene", [pinhole_scene, fisheye_scene])
def test_backprojection_on_the_candidate_box_equals_the_whole_image(scene, monkeypatch):
    """Planning with the block (`_candidate_box`) gives the backward maps of rotating every pixel, bit for bit."""
    from sgde_plugin.stereo import backproject
    from sgde_plugin.stereo.planning import plan_pairs

    rig, _, _ = scene()
    boxes = []
    real = backproject._candidate_box

    def recorded(camera, *args, **kwargs):
        boxes.append((real(camera, *args, **kwargs), camera.width * camera.height))
        return boxes[-1][0]

    monkeypatch.setattr(backproject, "_candidate_box", recorded)
    fast = plan_pairs(rig, PriorConfig())
    monkeypatch.setattr(backproject, "_candidate_box", lambda camera, *a, **k: (0, camera.height, 0, camera.width))
    whole = plan_pairs(rig, PriorConfig())
    assert len(fast) == len(whole) >= 1
    for a, b in zip(fast, whole):
        for sa, sb in ((a.left, b.left), (a.right, b.right)):
            assert sa.back.count > 1000
            for name in ("index", "map_x", "map_y", "kfb", "corners"):
                assert np.array_equal(getattr(sa.back, name), getattr(sb.back, name)), name
    assert min((r1 - r0) * (c1 - c0) / area for (r0, r1, c0, c1), area in boxes) < 0.7  # it does restrict
    # a canvas where no pixel can hold a disparity: nothing to rotate, the same empty map either way
    plan, cam = whole[0], rig.camera(whole[0].left.camera)
    none = np.zeros(plan.left.back.core, bool)
    empty = backproject.backprojection(cam, plan.pair.rect_left, plan.pair.baseline_m, plan.pair.core_x, possible=none)
    monkeypatch.setattr(backproject, "_candidate_box", real)
    boxed = backproject.backprojection(cam, plan.pair.rect_left, plan.pair.baseline_m, plan.pair.core_x, possible=none)
    assert boxed.count == empty.count == 0 and np.array_equal(boxed.map_x, empty.map_x)


def test_a_moved_rig_planned_again_with_the_kept_ray_grids_equals_a_fresh_plan(monkeypatch):
    """`plan_pairs(..., shared)` reuses the cameras' ray grids (keyed by intrinsics) for the rig with its cameras
    moved: no original camera's grid is made again and the plans equal a fresh planning."""
    from sgde_plugin.cameras import Pinhole
    from sgde_plugin.stereo.planning import plan_pairs

    rig, _, _ = pinhole_scene()
    shared: dict = {}
    plan_pairs(rig, PriorConfig(), shared)
    models = {c.intrinsics for c in rig.cameras}  # one grid per intrinsics (models compare by value)
    assert {k[0] for k in shared} == {"rays"} and len(shared) == len(models)
    moved = rig.with_extrinsics({"FRONT_RIGHT": rig.camera("FRONT_RIGHT").sensor_to_ego @ np.array(
        [[1, 0, 0, 0.2], [0, 1, 0, 0.0], [0, 0, 1, 0.1], [0, 0, 0, 1.0]])})
    made = []
    real = Pinhole.ray_grid

    def counted(self, *args, **kwargs):
        made.append((self.width, self.height))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Pinhole, "ray_grid", counted)
    again = plan_pairs(moved, PriorConfig(), shared)
    fresh = plan_pairs(moved, PriorConfig())
    originals = (rig.camera("FRONT").width, rig.camera("FRONT").height)
    assert made.count(originals) == len(models)  # the fresh planning's grids; none for the planning with `shared`
    for a, b in zip(again, fresh):
        for sa, sb in ((a.left, b.left), (a.right, b.right)):
            for name in ("index", "map_x", "map_y", "kfb"):
                assert np.array_equal(getattr(sa.back, name), getattr(sb.back, name)), name


@pytest.mark.parametrize("scene", [pinhole_scene, fisheye_scene])
def test_pairs_planned_in_a_thread_pool_equal_the_serial_plans(scene):
    """`plan_pairs(..., pool=...)` (PriorBuilder with threads > 1) gives the serial plans, in order, bit for bit."""
    from sgde_plugin.stereo.planning import plan_pairs

    rig, _, _ = scene()
    rig = Rig(rig.cameras, (tuple(rig.camera_names), tuple(reversed(rig.camera_names))), ())  # two pairs
    serial = plan_pairs(rig, PriorConfig())
    with ThreadPoolExecutor(2) as pool:
        pooled = plan_pairs(rig, PriorConfig(), {}, pool)
    assert len(serial) == len(pooled) >= 2
    for a, b in zip(serial, pooled):
        assert (a.left.camera, a.right.camera) == (b.left.camera, b.right.camera)
        for sa, sb in ((a.left, b.left), (a.right, b.right)):
            assert np.array_equal(sa.valid, sb.valid) and np.array_equal(sa.rect.map1, sb.rect.map1)
            for name in ("index", "map_x", "map_y", "kfb", "corners"):
                assert np.array_equal(getattr(sa.back, name), getattr(sb.back, name)), name


def test_warp_maps_from_an_undistorted_pinhole_equal_the_ray_grid_path():
    """`camera_maps` turns an undistorted pinhole's pixels by one matrix (canvases, virtual views) instead of its
    ray grid: on random turns, a skewed K and three source models the maps agree with the ray-grid path (the same
    pinhole with an all-zero distortion) to 1e-6 px and the validity is the same."""
    from sgde_plugin.cameras import KannalaBrandt, Pinhole
    from sgde_plugin.rig import Camera
    from sgde_plugin.stereo.rectify import camera_maps

    K = np.array([[150.0, 0, 99.5], [0, 150.0, 59.5], [0, 0, 1]])
    fish = np.array([[160 / 2 / np.radians(110), 0, 79.5], [0, 160 / 2 / np.radians(110), 79.5], [0, 0, 1]])
    sources = [Pinhole(200, 120, K, None), Pinhole(200, 120, K, np.array([-0.32, 0.12, 0.001, -0.002, -0.02])),
               KannalaBrandt(160, 160, fish, np.zeros(4), 220.0)]
    rng = np.random.default_rng(11)
    seen = 0
    for trial in range(24):
        f = rng.uniform(40, 300)
        Kd = np.array([[f, rng.uniform(-3, 3), rng.uniform(0, 90)], [0, f * rng.uniform(0.9, 1.1), rng.uniform(0, 60)],
                       [0, 0, 1]])
        pose = np.eye(4)
        pose[:3, :3] = _random_rotation(rng, 60.0)
        src = Camera("S", sources[trial % 3], np.eye(4))
        fast = camera_maps(src, Camera("D", Pinhole(90, 70, Kd, None), pose))
        slow = camera_maps(src, Camera("D", Pinhole(90, 70, Kd, np.zeros(5)), pose))
        assert np.array_equal(fast[2], slow[2])
        np.testing.assert_allclose(fast[0][fast[2]], slow[0][slow[2]], atol=1e-6, rtol=0)
        np.testing.assert_allclose(fast[1][fast[2]], slow[1][slow[2]], atol=1e-6, rtol=0)
        seen += int(fast[2].sum())
    assert seen > 24 * 90 * 70 * 0.2


def test_a_tile_owner_tested_on_the_landing_pixels_equals_the_whole_image_mask():
    """A fisheye tile keeps the pixels whose turn about the baseline it owns: testing only the pixels that land in
    the canvas (`owner=`) gives the backward map of the whole image's ownership mask, bit for bit."""
    from sgde_plugin.stereo.backproject import Owner, backprojection, camera_rays
    from sgde_plugin.stereo.planning import _rectified
    from sgde_plugin.stereo.rectify import rectified_rotation
    from sgde_plugin.synth.sequence import synth_sequence

    fish = synth_sequence("urban-fisheye", 1, seed=3, scale=0.25).rig_true
    a_name, b_name = fish.pairs[0]
    tiles = _rectified(fish.camera(a_name), fish.camera(b_name), PriorConfig.from_settings(fisheye="tiled"))
    assert len(tiles) == 3
    shared = {}
    for pair, own in tiles:
        for src, rect in ((pair.left, pair.rect_left), (pair.right, pair.rect_right)):
            cam = fish.camera(src.name)
            owner = Owner.of(cam, rectified_rotation(pair.left, pair.right), *own)
            rays, ok = camera_rays(cam, shared)
            mine = ok & torch.from_numpy(owner.owns(rays.numpy().reshape(-1, 3)).reshape(ok.shape))
            a = backprojection(cam, rect, pair.baseline_m, pair.core_x, rays, ok, owner=owner)
            b = backprojection(cam, rect, pair.baseline_m, pair.core_x, rays, mine)
            whole = backprojection(cam, rect, pair.baseline_m, pair.core_x, rays, ok)
            for name in ("index", "map_x", "map_y", "kfb", "corners"):
                assert np.array_equal(getattr(a, name), getattr(b, name)), name
            assert 100 < a.count < 0.95 * whole.count  # the owner keeps a part of what lands in the canvas
