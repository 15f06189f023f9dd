"""evaluate_priors (accuracy on prior pixels, coverage of the true overlap, occlusion) and `sgde eval` end to end.

Runtime: about 10 s on 2 cores.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_stereo_prior import pinhole_scene

from sgde_plugin.cli import main
from sgde_plugin.io import write_depth_png, write_image
from sgde_plugin.rig import Frame, write_rig_json
from sgde_plugin.stereo.evaluate import PriorEvaluator, evaluate_priors, true_overlap
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads, and OpenMP threads crawl on a busy machine."""
    with torch_threads(1):
        yield


def _overlaps():
    rig, images, depths = pinhole_scene()
    a, b = rig.cameras
    ov = {
        a.name: true_overlap(a, depths[a.name], b, depths[b.name]),
        b.name: true_overlap(b, depths[b.name], a, depths[a.name]),
    }
    return rig, depths, ov


def test_true_overlap_is_where_the_neighbour_sees_the_point():
    rig, depths, ov = _overlaps()
    for name in ("FRONT", "FRONT_RIGHT"):
        m = ov[name]
        assert 0.05 < m.mean() < 0.3  # an edge strip of the image
        cols = np.nonzero(m.any(axis=0))[0]
        assert (cols.min() > 300) if name == "FRONT" else (cols.max() < 180)
    # an occluder in front of the neighbour (its ground truth much closer) removes those pixels
    a, b = rig.cameras
    occluded = depths[b.name].copy()
    occluded[:, :40] = 1.0
    smaller = true_overlap(a, depths[a.name], b, occluded)
    assert smaller.sum() < 0.8 * ov[a.name].sum() and not (smaller & ~ov[a.name]).any()


def test_metrics_and_coverage_by_hand():
    rig, depths, ov = _overlaps()
    a, b = rig.camera_names
    gt = {n: np.where(depths[n] <= 80, depths[n], 0) for n in (a, b)}
    # prior = exact truth on the overlap: perfect metrics, full coverage
    perfect = evaluate_priors(rig, lambda f, c: np.where(ov[c], gt[c], 0), lambda f, c: depths[c], ["0"])
    assert perfect["overall"]["coverage"] == 1.0 and perfect["overall"]["abs_rel"] < 1e-6
    assert perfect["overall"]["a1"] == 1.0 and perfect["pairs"][f"{a}|{b}"]["coverage"] == 1.0
    # 10 % too far on the top half of the overlap: Abs Rel 0.1 exactly, coverage = share of the top half
    ev = PriorEvaluator(rig)
    top = np.zeros_like(ov[a])
    top[: top.shape[0] // 2] = True
    priors = {c: np.where(ov[c] & top, 1.1 * gt[c], 0).astype(np.float32) for c in (a, b)}
    ev.add(priors, depths)
    r = ev.result()
    expected_cov = sum((ov[c] & top).sum() for c in (a, b)) / sum(ov[c].sum() for c in (a, b))
    assert abs(r["overall"]["coverage"] - expected_cov) < 1e-12
    assert abs(r["overall"]["abs_rel"] - 0.1) < 1e-5
    assert abs(r["cameras"][a]["rmse"] - np.sqrt(np.mean((0.1 * gt[a][ov[a] & top]) ** 2))) < 1e-3
    # a prior outside the true overlap counts for its camera but not for the pair
    stray = {c: p.copy() for c, p in priors.items()}
    outside = (gt[a] > 0) & ~ov[a]
    stray[a][outside] = 2 * gt[a][outside]
    ev2 = PriorEvaluator(rig)
    ev2.add(stray, depths)
    r2 = ev2.result()
    assert r2["cameras"][a]["abs_rel"] > 0.5 and abs(r2["pairs"][f"{a}|{b}"]["abs_rel"] - 0.1) < 1e-5
    assert r2["cameras"][a]["coverage"] == r["cameras"][a]["coverage"]


def test_sgde_eval_command(tmp_path, capsys):
    rig, images, depths = pinhole_scene()
    root = tmp_path / "rig"
    rig = type(rig)(rig.cameras, rig.pairs, (Frame("000000", 0),))
    for cam in rig.camera_names:
        write_image(root / "frames" / "000000" / f"{cam}.png", images[cam])
        write_depth_png(root / "depth" / "000000" / f"{cam}.png", depths[cam])
    write_rig_json(rig, root / "rig.json")
    cache, out = tmp_path / "cache", tmp_path / "eval.json"
    assert main(["prior", str(root), "--out", str(cache), "--workers", "1"]) == 0
    capsys.readouterr()
    assert main(["eval", str(root), "--cache", str(cache), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "FRONT|FRONT_RIGHT" in text and "coverage" in text and "rig.json (no rig_true.json" in text
    report = json.loads(out.read_text())
    assert report["frames"] == 1 and set(report["cameras"]) == {"FRONT", "FRONT_RIGHT"}
    assert report["overall"]["abs_rel"] < 0.02 and report["overall"]["a1"] > 0.98
    assert report["overall"]["coverage"] > 0.3  # small images: borders and speckle limits weigh more
    # bad input: one line, exit 2
    assert main(["eval", str(root), "--cache", str(tmp_path / "nothing")]) == 2
    assert main(["eval", str(root), "--cache", str(cache), "--truth", str(tmp_path / "none.json")]) == 2
