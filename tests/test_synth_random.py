"""The random-rig generator (`sgde synth --preset random`): its rigs keep their promises, and the prior holds on one."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.synth.presets import preset_cameras, preset_ring
from sgde_plugin.synth.random_rig import FOV_DEG, HEIGHT_M, N_CAMERAS, OVERLAP_DEG, random_rig


def _azimuth_deg(cam) -> float:
    axis = cam.sensor_to_ego[:3, 2]
    return math.degrees(math.atan2(axis[1], axis[0]))


@pytest.mark.parametrize("seed", range(0, 40, 3))
def test_random_rig_keeps_its_ranges(seed):
    """Camera count, horizontal FOV, overlap (FOV halves minus yaw gap), yaw gaps closing the ring, mount height."""
    rig = random_rig(seed)
    n = len(rig.cameras)
    assert N_CAMERAS[0] <= n <= N_CAMERAS[1]
    fovs = []
    for cam in rig.cameras:
        fov = math.degrees(2 * math.atan((cam.width / 2) / cam.intrinsics.K[0, 0]))
        assert FOV_DEG[0] - 1e-6 <= fov <= FOV_DEG[1] + 1e-6
        assert HEIGHT_M[0] <= cam.sensor_to_ego[2, 3] <= HEIGHT_M[1]
        fovs.append(fov)
    np.testing.assert_allclose(fovs, rig.fov_deg, atol=1e-6)
    gaps = []
    for i in range(n):
        gap = (_azimuth_deg(rig.cameras[i]) - _azimuth_deg(rig.cameras[(i + 1) % n])) % 360.0
        gaps.append(gap)
        overlap = (fovs[i] + fovs[(i + 1) % n]) / 2 - gap
        assert OVERLAP_DEG[0] - 1e-6 <= overlap <= OVERLAP_DEG[1] + 1e-6, (i, overlap)
    assert sum(gaps) == pytest.approx(360.0, abs=1e-6)
    assert rig.near_objects, "every rig has at least one blocked overlap"


def test_random_rigs_vary_and_repeat():
    """Same seed, same rig; over 40 seeds every camera count 4..8 occurs; presets agree with the generator."""
    counts = {len(random_rig(s).cameras) for s in range(40)}
    assert counts == set(range(N_CAMERAS[0], N_CAMERAS[1] + 1))
    a, b = random_rig(7), random_rig(7)
    assert [c.to_dict() for c in a.cameras] == [c.to_dict() for c in b.cameras]
    assert random_rig(8).fov_deg != a.fov_deg
    assert preset_ring("random", seed=7) == a.ring
    assert [c.to_dict() for c in preset_cameras("random", 1.0, seed=7)] == [c.to_dict() for c in a.cameras]


def test_synth_random_cli_and_prior(tmp_path):
    """`sgde synth --preset random`: a valid folder whose near object is seen close by, and a prior that holds."""
    from sgde_plugin.rig import attach_files, read_rig_json
    from sgde_plugin.stereo.evaluate import PriorEvaluator
    from sgde_plugin.stereo.pipeline import PriorBuilder

    out = tmp_path / "r"
    assert main(["synth", "--preset", "random", "--seed", "3", "--frames", "1", "--scale", "0.5", "--out",
                 str(out), "--pose-noise-deg", "0", "--pose-noise-m", "0"]) == 0
    doc = json.loads((out / "rig.json").read_text())
    assert doc["synth"]["random_rig"]["cameras"] == len(doc["ring"]) == 6
    rig = attach_files(read_rig_json(out / "rig_true.json"), out)
    fid = rig.frames[0].id
    depths = {c: rig.load_depth(fid, c) for c in rig.camera_names}
    blocked = random_rig(3).near_objects[0].pair
    near = [(depths[c] > 0) & (depths[c] < 6.0) for c in blocked]
    assert max(m.mean() for m in near) > 0.01, "the near object shows up in its overlap"
    builder = PriorBuilder(rig)
    priors = builder.build({c: rig.load_image(fid, c) for c in rig.camera_names})
    ev = PriorEvaluator(rig)
    ev.add({c: p.depth for c, p in priors.items()}, depths)
    overall = ev.result()["overall"]
    assert overall["coverage"] > 0.35
    assert overall["abs_rel"] < 0.03
