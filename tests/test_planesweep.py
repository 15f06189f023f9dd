"""The plane sweep between the original views (`matcher: planesweep`): a rendered rig against its truth, a
fronto-parallel plane at known depth, a gain difference between the cameras, settings and fingerprint.

Runtime: about 10 s on 2 cores (small images: 480x270 and a 400x225 synthetic rig).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from stereo_scene import Plane, nuscenes_pair, render

from sgde_plugin.cache.fingerprints import config_document, digest
from sgde_plugin.errors import InputError
from sgde_plugin.rig import Rig
from sgde_plugin.stereo.evaluate import PriorEvaluator
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.planesweep import SweepPlan, _view_image, aggregate, cost_volume, plane_homographies, winner
from sgde_plugin.stereo.presets import load_prior_config, save_prior_config
from sgde_plugin.stereo.rectify import torch_threads

SWEEP = PriorConfig.from_settings(matcher="planesweep")


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads."""
    with torch_threads(1):
        yield


@functools.cache
def fronto_scene(depth: float = 8.0):
    """A nuScenes-like front pair (480x270) and a textured plane fronto-parallel to FRONT at `depth` m."""
    left, right = nuscenes_pair(0.3)
    R, c = left.sensor_to_ego[:3, :3], left.sensor_to_ego[:3, 3]
    plane = Plane(c + R[:, 2] * depth, -R[:, 2], R[:, 0], R[:, 1], seed=3)
    images, depths = {}, {}
    for cam in (left, right):
        images[cam.name], depths[cam.name] = render([plane], cam)
    return Rig((left, right), ((left.name, right.name),), ()), images, depths


def _rel(prior: np.ndarray, gt: np.ndarray) -> np.ndarray:
    ok = (prior > 0) & (gt > 0)
    return np.abs(prior[ok] - gt[ok]) / gt[ok]


def test_homography_of_a_plane_maps_its_points():
    rig, _, _ = fronto_scene()
    a, b = rig.cameras
    inv = np.array([1 / 5.0, 1 / 20.0])
    H = plane_homographies(a, b, inv, (10, 4))
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [100, 100], (20, 2))
    for q, h in zip(inv, H):
        rays, _ = a.intrinsics.unproject(uv + [10, 4])
        X = rays / rays[:, 2:] / q  # on the plane z = 1 / q of `a`
        Xo = (np.linalg.inv(b.sensor_to_ego) @ a.sensor_to_ego @ np.c_[X, np.ones(20)].T)[:3].T
        want, _ = b.intrinsics.project(Xo)
        got = (h @ np.c_[uv, np.ones(20)].T).T
        np.testing.assert_allclose(got[:, :2] / got[:, 2:], want, atol=1e-6)


def test_winner_refines_a_parabola_and_rejects_ambiguous_minima():
    k = np.arange(20, dtype=np.float32)[:, None, None]
    costs = 0.2 + np.concatenate([(k - 7.3) ** 2, np.minimum((k - 4) ** 2, (k - 15) ** 2 + 0.005)], axis=2)
    best, offset, unique = winner(costs, 0.05)
    assert best[0, 0] == 7 and abs(best[0, 0] + offset[0, 0] - 7.3) < 1e-4 and unique[0, 0]
    assert best[0, 1] == 4 and not unique[0, 1]  # two minima of nearly the same cost
    # semi-global aggregation: a weak false minimum between clear neighbours takes their plane; 0 paths = the costs
    row = np.repeat(np.minimum(0.2 + 0.02 * (k - 7) ** 2, 0.8), 5, axis=2)
    row[:, :, 2] = 0.3
    row[15, :, 2] = 0.25
    assert aggregate(row, 0, 0.05, 0.3) is row and row.argmin(axis=0)[0, 2] == 15
    for paths in (2, 4):
        assert aggregate(row, paths, 0.05, 0.3).argmin(axis=0)[0].tolist() == [7] * 5


def test_fronto_parallel_plane_comes_back_at_its_depth():
    rig, images, depths = fronto_scene()
    builder = PriorBuilder(rig, SWEEP)
    assert all(isinstance(p, SweepPlan) for p in builder.plans) and builder.matcher is None
    out = builder.build(images)
    front = out["FRONT"]
    assert np.array_equal(front.confidence > 0, front.depth > 0) and front.confidence.max() <= 1
    got = front.depth[front.depth > 0]
    # measured: 5680 pixels, median error 0.30 %, 95 % within 1 %; FRONT_RIGHT (a slanted plane to it): 6152
    # pixels, median 0.48 % (SGBM on the rectified pair: 5884 and 6402 pixels, medians 0.27 % and 0.24 %)
    assert got.size > 4000  # the overlap: the right part of FRONT
    err = np.abs(got / 8.0 - 1)
    assert np.median(err) < 0.005 and np.mean(err < 0.01) > 0.9
    rel = _rel(out["FRONT_RIGHT"].depth, depths["FRONT_RIGHT"])
    assert rel.size > 4000 and np.median(rel) < 0.008 and rel.mean() < 0.01


def test_a_gain_difference_between_the_cameras_changes_little():
    rig, images, depths = fronto_scene()
    dim = dict(images)
    dim["FRONT_RIGHT"] = np.clip(images["FRONT_RIGHT"].astype(np.float32) * 0.55 + 30, 0, 255).astype(np.uint8)
    # the matching cost (ZNCC) itself does not see gain and offset
    builder = PriorBuilder(rig, SWEEP)
    plan = builder.plans[0]
    costs = []
    for imgs in (images, dim):
        grey = builder._prepare(imgs)
        (a, _), (b, valid_b) = (_view_image(s, grey[s.camera], None, SWEEP) for s in (plan.left, plan.right))
        costs.append(cost_volume(a, b, valid_b, plan.left, 7)[0])
    sure = costs[0] < 0.5  # windows whose ZNCC is above 0.5 (rounding to uint8 moves flat ones more)
    assert sure.sum() > 10_000 and np.abs(costs[1] - costs[0])[sure].max() < 0.02
    # the whole prior, with the pipeline's per-overlap normalisation for the absolute-difference check
    config = SWEEP.replace(normalize="gain")
    base, out = PriorBuilder(rig, config).build(images), PriorBuilder(rig, config).build(dim)
    for name in ("FRONT", "FRONT_RIGHT"):
        a, b = base[name].depth, out[name].depth
        both = (a > 0) & (b > 0)
        assert both.sum() > 0.9 * (a > 0).sum() and (b > 0).sum() > 0.9 * (a > 0).sum()
        assert np.median(np.abs(b[both] / a[both] - 1)) < 0.002
        assert _rel(b, depths[name]).mean() < 1.2 * _rel(a, depths[name]).mean() + 1e-3


def test_rendered_rig_against_its_truth():
    synth = pytest.importorskip("sgde_plugin.synth.sequence")
    seq = synth.synth_sequence("nuscenes", 1, scale=0.25, pose_noise_deg=0.0, pose_noise_m=0.0)
    evaluator = PriorEvaluator(seq.rig_true, SWEEP.geometry.max_depth)
    out = PriorBuilder(seq.rig_true, SWEEP).build(seq.images[next(iter(seq.images))])
    evaluator.add({c: m.depth for c, m in out.items()}, seq.depths[next(iter(seq.depths))])
    overall = evaluator.result()["overall"]
    # coverage of the true overlaps / Abs Rel measured 0.448 / 0.0242 (SGBM on the same frame: 0.425 / 0.0241)
    assert overall["coverage"] > 0.38 and overall["abs_rel"] < 0.035 and overall["a1"] > 0.99, overall


def test_settings_round_trip_and_enter_the_fingerprint(tmp_path):
    config = PriorConfig.from_settings(matcher="planesweep", sweep={"paths": 2, "window": 5}, sweep_p2=0.4)
    assert (config.sweeps, config.sweep.paths, config.sweep.window, config.sweep.p2) == (True, 2, 5, 0.4)
    assert load_prior_config(save_prior_config(config, tmp_path / "s.yaml")) == config
    (tmp_path / "f.yaml").write_text("preset: ddad\nmatcher: planesweep\nsweep: {planes: 64}\n")
    loaded = load_prior_config(tmp_path / "f.yaml")
    assert loaded.sweeps and loaded.sweep.planes == 64 and loaded.geometry.max_depth == 200.0
    docs = {digest(config_document(c)) for c in (PriorConfig(), SWEEP, config, SWEEP.replace(sweep_uniqueness=0.1))}
    assert len(docs) == 4
    for bad, needle in (({"sweep_window": 4}, "sweep_window: must be odd"), ({"sweep_paths": 3}, "sweep_paths"),
                        ({"sweep_step_px": 0.0}, "sweep_step_px: must be positive")):
        with pytest.raises(InputError, match=needle):
            PriorConfig.from_settings(matcher="planesweep", **bad)
    with pytest.raises(ValueError, match="original views"):
        SWEEP.make_matcher()
