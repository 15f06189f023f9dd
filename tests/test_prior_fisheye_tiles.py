"""`fisheye: tiled`: a fisheye pair's shared field in canvases turned about the baseline (`planning.baseline_tiles`).

The tiles cover the whole shared field of two 220-degree fisheyes (one canvas of +-50 degrees holds less than
half of it), stay epipolar (equal rows, disparity f B / z), own disjoint parts of it, leave pinhole pairs as
`direct` does, and raise the coverage of the urban-fisheye rig's true overlap without losing accuracy.

Runtime: about 8 s on 2 cores (the end-to-end test renders one quarter-size frame: about 4 s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from stereo_scene import fisheye_pair, nuscenes_pair

from sgde_plugin.cameras import Camera
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import invert_transform, transform_points
from sgde_plugin.rig import Rig
from sgde_plugin.stereo.backproject import backprojection
from sgde_plugin.stereo.evaluate import PriorEvaluator
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.planning import baseline_tiles, plan_pairs, shared_turns
from sgde_plugin.stereo.rectify import rectify_pair, tile_pair, torch_threads
from sgde_plugin.synth.presets import preset_cameras
from sgde_plugin.synth.sequence import synth_sequence


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads."""
    with torch_threads(1):
        yield


def test_tiles_cover_the_shared_field_of_two_wide_fisheyes():
    front, right = preset_cameras("urban-fisheye", 0.25)[:2]
    turns = np.degrees(shared_turns(front, right, 60.0))
    # 220-degree cameras 90 degrees apart share every turn about the baseline within about 119 degrees of
    # the rectified axis (cos psi cos 45 >= cos 110)
    assert -121 <= turns.min() <= -117 and 117 <= turns.max() <= 121
    tiles = baseline_tiles(front, right, 60.0, 50.0)
    assert tiles is not None and len(tiles) == 3
    centres = [math.degrees(t[0]) for t in tiles]
    assert centres == pytest.approx([-79.3, 0.0, 79.3], abs=1.0)
    assert all(half <= math.radians(50.0) + 1e-12 for *_, half in tiles)
    # ownership: contiguous, the outer tiles own everything beyond them
    assert tiles[0][1] == -math.inf and tiles[-1][2] == math.inf
    for a, b in zip(tiles, tiles[1:]):
        assert a[2] == pytest.approx(b[1])
        assert a[0] + a[3] > a[2] and b[0] - b[3] < b[1]  # each canvas reaches past its seam (context)


def test_one_canvas_when_it_holds_the_shared_field():
    assert baseline_tiles(*nuscenes_pair(0.25), 60.0, 50.0) is None  # a pinhole pair: the `direct` canvas
    front, right = preset_cameras("urban-fisheye", 0.25)[:2]
    assert baseline_tiles(front, right, 60.0, 130.0) is None  # a limit wider than the field: one canvas


def test_a_pair_that_cannot_be_rectified_gives_no_tiles():
    front, right = fisheye_pair(96)
    twin = Camera("T", front.intrinsics, front.sensor_to_ego.copy())  # the same centre: no baseline
    assert baseline_tiles(front, twin, 60.0, 50.0) is None
    rig = Rig(cameras=(front, twin, right), pairs=(("F", "T"), ("F", "R")), frames=())
    plans = plan_pairs(rig, PriorConfig.from_settings(fisheye="tiled"))
    assert {p.name for p in plans} == {"F|R"} and len(plans) == 3


def test_an_unturned_tile_is_rectify_pair():
    a, b = nuscenes_pair(0.25)
    ref = rectify_pair(a, b, 0.5, 1.5, 8, 60.0, 50.0)
    got = tile_pair(a, b, 0.0, math.radians(50.0), 0.5, 1.5, 8, 60.0)
    assert got.size == ref.size and got.core_x == ref.core_x and got.max_disparity == ref.max_disparity
    assert np.allclose(got.rect_left.intrinsics.K, ref.rect_left.intrinsics.K, atol=1e-9)
    assert np.allclose(got.rect_right.sensor_to_ego, ref.rect_right.sensor_to_ego, atol=1e-12)


@pytest.mark.parametrize("turn_deg", [-75.0, 0.0, 75.0])
def test_turned_tiles_are_epipolar(turn_deg):
    front, right = fisheye_pair(160)
    pair = tile_pair(front, right, math.radians(turn_deg), math.radians(40.0), 1.0, 1.5, 8, 60.0)
    R = pair.rotation
    rng = np.random.default_rng(int(turn_deg) + 100)
    rows = []
    for _ in range(40):
        d = R @ np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.6), 1.0])
        p = pair.left.sensor_to_ego[:3, 3] + d * rng.uniform(2.0, 30.0)
        uv = []
        for cam in (pair.rect_left, pair.rect_right):
            local = transform_points(invert_transform(cam.sensor_to_ego), p)
            uv.append((cam.intrinsics.project(local)[0], local[2]))
        (ul, zl), (ur, _) = uv
        rows.append(abs(ul[1] - ur[1]))
        assert ul[0] - ur[0] == pytest.approx(pair.focal_px * pair.baseline_m / zl, rel=1e-9)
    assert max(rows) < 1e-9
    # the tile looks where it is turned: its z is the base frame's z turned about x (the baseline) towards y
    base = tile_pair(front, right, 0.0, math.radians(40.0), 1.0, 1.5, 8, 60.0).rotation
    assert np.allclose(R[:, 0], base[:, 0], atol=1e-12)
    assert float(R[:, 2] @ base[:, 2]) == pytest.approx(math.cos(math.radians(turn_deg)), abs=1e-12)
    assert float(R[:, 2] @ base[:, 1]) == pytest.approx(math.sin(math.radians(turn_deg)), abs=1e-12)


def test_tiles_own_disjoint_parts_and_pinhole_plans_are_direct():
    fish = synth_sequence("urban-fisheye", 1, seed=3, scale=0.25).rig_true
    tiled = plan_pairs(fish, PriorConfig())  # the default
    direct = plan_pairs(fish, PriorConfig.from_settings(fisheye="direct"))
    assert len(direct) == 4 and len(tiled) == 12
    for k in range(4):  # each rig pair: its tiles back-project disjoint parts of each camera, together more
        plans = tiled[3 * k : 3 * k + 3]
        assert len({p.name for p in plans}) == 1
        for side in ("left", "right"):
            index = np.concatenate([getattr(p, side).back.index for p in plans])
            assert np.unique(index).size == index.size
            assert index.size > 1.4 * getattr(direct[k], side).back.count
        for p in plans:  # each canvas reaches past the part it owns (matching context)
            whole = backprojection(fish.camera(p.left.camera), p.pair.rect_left, p.pair.baseline_m, p.pair.core_x)
            assert p.left.back.count < 0.95 * whole.count
    pin = synth_sequence("nuscenes", 1, seed=3, scale=0.2).rig_true
    a, b = plan_pairs(pin, PriorConfig.from_settings(fisheye="direct")), plan_pairs(pin, PriorConfig())
    assert [p.pair.size for p in a] == [p.pair.size for p in b]
    assert all(np.array_equal(p.left.back.index, q.left.back.index) for p, q in zip(a, b))


def test_tiled_is_a_setting():
    assert PriorConfig.from_settings(fisheye="tiled").geometry.fisheye == "tiled"
    with pytest.raises(InputError, match="fisheye"):
        PriorConfig.from_settings(fisheye="tiles")
    assert PriorConfig().geometry.fisheye == "tiled"  # the default
    assert PriorConfig().to_dict() != PriorConfig.from_settings(fisheye="direct").to_dict()  # in the fingerprint


def test_tiled_covers_more_of_the_fisheye_overlap_as_accurately():
    seq = synth_sequence("urban-fisheye", 1, seed=3, scale=0.25)
    rows = {}
    for path in ("direct", "tiled"):
        config = PriorConfig.from_settings(fisheye=path)
        builder = PriorBuilder(seq.rig_true, config)
        evaluator = PriorEvaluator(seq.rig_true, config.geometry.max_depth)
        for fid, images in seq.images.items():
            evaluator.add({c: m.depth for c, m in builder.build(images).items()}, seq.depths[fid])
        rows[path] = evaluator.result()["overall"]
    # measured: direct 0.557 / 0.060, tiled 0.697 / 0.050 (coverage of the true overlap / Abs Rel)
    assert rows["tiled"]["coverage"] > rows["direct"]["coverage"] + 0.1
    assert rows["tiled"]["abs_rel"] <= rows["direct"]["abs_rel"] * 1.05
