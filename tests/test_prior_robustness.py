"""Photometric normalisation, confidence that ranks errors, sparsification curves, PriorCache.get(min_confidence)."""

from __future__ import annotations

import numpy as np
import pytest
from test_stereo_prior import pinhole_scene

from sgde_plugin.stereo.evaluate import PriorEvaluator, sparsification_curve
from sgde_plugin.stereo.filters import depth_edge_factor, discontinuity_factor, normalize_image
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(autouse=True)
def _one_torch_thread():
    with torch_threads(1):
        yield


def _exposed(image: np.ndarray, gain: float, offset: float) -> np.ndarray:
    return np.clip(image.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)


def test_normalisation_undoes_a_gain_and_offset():
    """'gain' maps an image and its 0.6x + 20 copy to the same grey levels; 'local' nearly so."""
    rng = np.random.default_rng(0)
    a = (rng.random((60, 80)) * 120 + 60).astype(np.uint8)
    b = _exposed(a, 0.6, 20.0)
    valid = np.ones(a.shape, bool)
    valid[:, :5] = False
    ga, gb = normalize_image(a, valid, "gain"), normalize_image(b, valid, "gain")
    assert np.abs(ga.astype(int) - gb.astype(int))[valid].max() <= 2
    assert (ga[~valid] == 0).all()
    la, lb = normalize_image(a, valid, "local"), normalize_image(b, valid, "local")
    assert np.median(np.abs(la.astype(int) - lb.astype(int))[valid]) <= 3
    assert normalize_image(a, valid, "none") is a


def test_normalisation_keeps_a_pair_with_a_known_gain_difference():
    """One camera 0.55x darker (+25 offset): without normalisation the photometric checks drop most of the
    prior; per-overlap 'gain' or 'local' normalisation brings the coverage back at the same accuracy."""
    rig, images, depths = pinhole_scene()
    dark = dict(images)
    dark["FRONT_RIGHT"] = _exposed(images["FRONT_RIGHT"], 0.55, 25.0)

    def run(mode, imgs):
        out = PriorBuilder(rig, PriorConfig.from_settings(normalize=mode)).build(imgs)
        n, errs = 0, []
        for cam in ("FRONT", "FRONT_RIGHT"):
            p, g = out[cam].depth, depths[cam]
            ok = (p > 0) & (g > 0)
            n += int(ok.sum())
            errs.append(np.abs(p[ok] - g[ok]) / g[ok])
        errs = np.concatenate(errs)
        return n, float(errs.mean()) if errs.size else float("nan")

    n_same, _ = run("none", images)
    n_dark, _ = run("none", dark)
    assert n_dark < 0.6 * n_same
    for mode in ("gain", "local"):
        n, err = run(mode, dark)
        assert n > 0.85 * n_same, (mode, n, n_same)
        assert err < 0.01, (mode, err)


def test_confidence_ranks_errors_on_a_rendered_rig():
    """Sparsification on a rendered random rig: Abs Rel of the prior kept at rising confidence thresholds
    falls (never rises by more than 2 %), the most confident part is several times better than all of it,
    and coverage falls monotonically."""
    from sgde_plugin.synth.sequence import synth_sequence

    seq = synth_sequence("random", 1, seed=100, scale=0.5, pose_noise_deg=0.0, pose_noise_m=0.0)
    fid = next(iter(seq.images))
    out = PriorBuilder(seq.rig_true, PriorConfig()).build(seq.images[fid])
    ev = PriorEvaluator(seq.rig_true)
    ev.add({c: m.depth for c, m in out.items()}, seq.depths[fid], confidences={c: m.confidence for c, m in out.items()})
    curve = [r for r in ev.result()["curve"] if r["n_prior"] >= 500]
    assert len(curve) >= 10
    rel = [r["abs_rel"] for r in curve]
    assert all(b <= a * 1.02 for a, b in zip(rel, rel[1:])), rel
    assert rel[-1] < 0.5 * rel[0], rel
    cov = [r["coverage"] for r in curve]
    assert all(b <= a for a, b in zip(cov, cov[1:])) and cov[0] > 0.4


def test_sparsification_curve_by_hand():
    pred = np.array([10.0, 10.0, 12.0, 20.0])
    gt = np.full(4, 10.0)
    conf = np.array([0.9, 0.6, 0.3, 0.1])
    rows = sparsification_curve(pred, gt, conf, overlap_conf=np.array([0.9, 0.6, 0.3, 0.1, 0.0]),
                                thresholds=(0.0, 0.2, 0.5, 0.8))
    assert [r["n_prior"] for r in rows] == [4, 3, 2, 1]
    assert rows[0]["abs_rel"] == pytest.approx((0 + 0 + 0.2 + 1.0) / 4)
    assert rows[1]["abs_rel"] == pytest.approx(0.2 / 3)
    assert rows[2]["abs_rel"] == 0.0
    assert [r["coverage"] for r in rows] == pytest.approx([0.8, 0.6, 0.4, 0.2])


def test_discontinuity_factor():
    disp = np.full((20, 20), 10.0, np.float32)
    disp[:, 10:] = 20.0
    f = discontinuity_factor(disp, np.ones_like(disp, bool), jump_px=2.0)
    assert f[:, :6].min() == 1.0 and f[:, 14:].min() == 1.0
    assert f[:, 9:11].max() == pytest.approx(0.2)


def test_depth_edge_factor_by_ratio():
    """Full confidence up to a local depth ratio of 1 + r, linear to zero at 1 + 5 r, the same near and far."""
    for near in (2.0, 40.0):
        depth = np.full((40, 40), near, np.float32)
        depth[:, 20:] = near * 1.3  # ratio 1.3: factor 1 - (0.3 - 0.1) / 0.4 = 0.5 within the window of the edge
        depth[:, 30:] = 0  # no prior: factor 1, and not counted as a depth
        f = depth_edge_factor(depth, ratio=0.1, window=5)
        assert f[:, :17].min() == 1.0 and f[:, 23:].min() == 1.0
        assert f[:, 18:22] == pytest.approx(np.full((40, 4), 0.5), abs=1e-5)
    depth[:, :20] = 10.0
    depth[:, 20:30] = 16.0  # ratio 1.6 > 1.5: zero
    assert depth_edge_factor(depth, 0.1, 5)[:, 18:22].max() == 0.0


def test_edge_factor_in_the_prior_costs_nothing_without_occlusion_edges():
    """A rendered wall and ground (no occlusion edge): the edge factor keeps every value and its depth."""
    rig, images, _ = pinhole_scene()
    plain = PriorBuilder(rig, PriorConfig()).build(images)
    edged = PriorBuilder(rig, PriorConfig.from_settings(edge_depth_ratio=0.1)).build(images)
    for name, p in plain.items():
        e = edged[name]
        assert p.valid.sum() > 1000 and np.array_equal(e.valid, p.valid)
        assert np.array_equal(e.depth, p.depth) and np.all(e.confidence <= p.confidence)
        # only where the ground's depth changes fast near the car is the confidence lowered (12 % here)
        assert np.mean(e.confidence[e.valid] >= 0.99 * p.confidence[p.valid]) > 0.8


def test_cache_get_min_confidence(tmp_path):
    """get(..., min_confidence=c) keeps exactly the values whose stored confidence reaches c."""
    from cache_fixtures import build, tiny_rig

    from sgde_plugin import PriorCache

    rig = tiny_rig(1)
    build(rig, tmp_path / "c")
    cache = PriorCache(tmp_path / "c")
    fid = cache.frames()[0]
    for cam in cache.cameras():
        depth, valid, conf = cache.get_prior(fid, cam)
        assert valid.any()
        c = float(np.median(conf[valid]))
        d2, v2 = cache.get(fid, cam, min_confidence=c)
        np.testing.assert_array_equal(v2, valid & (conf >= c - 0.5 / 255))
        np.testing.assert_array_equal(d2[v2], depth[v2])
        assert (d2[~v2] == 0).all() and 0 < v2.sum() < valid.sum()
        d3, v3 = cache.get(fid, cam, size=(20, 30), min_confidence=c)
        assert d3.shape == (20, 30) and v3.sum() <= cache.get(fid, cam, size=(20, 30))[1].sum()
