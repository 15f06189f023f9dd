"""Synthetic sequences: cross-view truth for all presets, same seed same bytes, calibration noise, CLI.

Runtime: about 30 s on 2 cores (cross-view checks at reduced scale dominate).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.commands.validate import pair_rows
from sgde_plugin.geometry import rotation_angle_deg
from sgde_plugin.rig import read_rig_folder, read_rig_json
from sgde_plugin.synth.presets import preset_cameras, preset_ring
from sgde_plugin.synth.render import render, rig_lod
from sgde_plugin.synth.sequence import perturb_extrinsics, synth_sequence, write_synth
from sgde_plugin.synth.truth import cross_view_check
from sgde_plugin.synth.world import build_world

# scale per preset: small enough to stay fast, large enough that the overlaps are not mostly silhouettes
TRUTH_SCALE = {"nuscenes": 0.3, "ddad": 0.25, "urban-fisheye": 0.5}


@pytest.mark.parametrize("preset", list(TRUTH_SCALE))
def test_cross_view_truth(preset):
    """Every adjacent pair, both directions: >= 95% of the overlap pixels that B really sees agree
    with B's ground truth in depth (1%) and colour (8/255)."""
    world = build_world(0)
    cams = {c.name: c for c in preset_cameras(preset, TRUTH_SCALE[preset])}
    time_s = 0.7
    pose = world.ego_pose(time_s)
    lod = rig_lod(list(cams.values()))  # what synth_sequence uses: one texture LOD for the whole rig
    out = {n: render(world, c, pose, time_s, lod=lod) for n, c in cams.items()}
    ring = preset_ring(preset)
    for a, b in zip(ring, ring[1:] + ring[:1]):
        for x, y in ((a, b), (b, a)):
            r = cross_view_check(world, cams[x], cams[y], pose, time_s, *out[x], *out[y])
            assert r.visible_px > 500, (x, y, r)
            assert r.both_ok >= 0.95, (x, y, r)


def test_cross_view_check_detects_a_wrong_pose():
    """The check is not vacuous: with B's extrinsic off by 1 degree the agreement collapses."""
    world = build_world(0)
    cams = preset_cameras("nuscenes", 0.3)
    pose = world.ego_pose(0.0)
    a, b = cams[0], cams[1]
    lod = rig_lod(cams)
    ra, da = render(world, a, pose, 0.0, lod=lod)
    rb, db = render(world, b, pose, 0.0, lod=lod)
    good = cross_view_check(world, a, b, pose, 0.0, ra, da, rb, db)
    wrong = perturb_extrinsics([b], seed=5, noise_deg=1.0, noise_m=0.0)[b.name]
    bad = cross_view_check(world, a, b.with_pose(wrong), pose, 0.0, ra, da, rb, db)
    assert good.both_ok >= 0.95
    assert bad.both_ok < 0.7


def _tree_bytes(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_different_seed_different_scene(tmp_path):
    kw = dict(scale=0.06, pose_noise_deg=1.0, pose_noise_m=0.05)
    a = _tree_bytes(write_synth("nuscenes", 2, tmp_path / "a", seed=3, **kw))
    b = _tree_bytes(write_synth("nuscenes", 2, tmp_path / "b", seed=3, **kw))
    c = _tree_bytes(write_synth("nuscenes", 2, tmp_path / "c", seed=4, **kw))
    assert a == b
    assert len(a) == 2 + 2 * 2 * 6  # rig.json, rig_true.json, 2 frames x 6 cameras x (image, depth)
    assert set(a) == set(c)
    differing = [k for k in a if k.startswith("frames/") and a[k] != c[k]]
    assert len(differing) == 12
    assert a["rig.json"] != c["rig.json"]  # different calibration noise too
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temporary folder left


@pytest.mark.parametrize("deg,m", [(1.0, 0.05), (2.5, 0.2), (0.0, 0.0)])
def test_perturbation_matches_requested_noise(deg, m):
    seq = synth_sequence("ddad", 1, seed=7, scale=0.02, pose_noise_deg=deg, pose_noise_m=m)
    for cam in seq.rig_true.cameras:
        noisy = seq.rig.camera(cam.name).sensor_to_ego
        dR = noisy[:3, :3] @ cam.sensor_to_ego[:3, :3].T
        assert rotation_angle_deg(dR) == pytest.approx(deg, abs=1e-6)
        assert np.linalg.norm(noisy[:3, 3] - cam.sensor_to_ego[:3, 3]) == pytest.approx(m, abs=1e-12)
    # images are rendered with the true extrinsics: identical whatever the noise
    ref = synth_sequence("ddad", 1, seed=7, scale=0.02, pose_noise_deg=0.0, pose_noise_m=0.0)
    for name in seq.images["000000"]:
        np.testing.assert_array_equal(seq.images["000000"][name], ref.images["000000"][name])


def test_perturbation_axes_are_random_and_seeded():
    cams = preset_cameras("nuscenes", 0.1)
    p1 = perturb_extrinsics(cams, 1, 1.0, 0.05)
    p2 = perturb_extrinsics(cams, 1, 1.0, 0.05)
    p3 = perturb_extrinsics(cams, 2, 1.0, 0.05)
    assert all(np.array_equal(p1[k], p2[k]) for k in p1)
    assert not np.allclose(p1["CAM_FRONT"], p3["CAM_FRONT"])
    axes = [p1[c.name][:3, 3] - c.sensor_to_ego[:3, 3] for c in cams]
    assert min(np.linalg.norm(axes[0] - v) for v in axes[1:]) > 1e-3


def test_cli_writes_a_valid_rig_and_refuses_a_full_folder(tmp_path, capsys):
    out = tmp_path / "seq"
    rc = main(["synth", "--preset", "nuscenes", "--frames", "3", "--out", str(out), "--scale", "0.06",
               "--seed", "1", "--pose-noise-deg", "0.5", "--pose-noise-m", "0.02"])
    assert rc == 0
    assert main(["validate", str(out)]) == 0
    text = capsys.readouterr().out
    assert "overlap_deg" in text
    rig = read_rig_folder(out, check_images=True)
    assert rig.ring == tuple(preset_ring("nuscenes"))
    assert [f.id for f in rig.frames] == ["000000", "000001", "000002"]
    assert [f.timestamp_us for f in rig.frames] == [0, 100000, 200000]
    assert rig.load_depth("000001", "CAM_FRONT").max() > 0
    # the overlaps that `sgde validate` reports are 5-20 degrees on the true and on the noisy rig
    for r in (rig, read_rig_json(out / "rig_true.json")):
        assert all(5.0 <= row["overlap_deg"] <= 20.0 for row in pair_rows(r))
    true_rig = read_rig_json(out / "rig_true.json")
    angle = rotation_angle_deg(rig.camera("CAM_BACK").sensor_to_ego[:3, :3].T
                               @ true_rig.camera("CAM_BACK").sensor_to_ego[:3, :3])
    assert angle == pytest.approx(0.5, abs=1e-6)
    # an existing non-empty --out is refused with exit code 2 and left untouched
    before = _tree_bytes(out)
    assert main(["synth", "--preset", "ddad", "--frames", "1", "--out", str(out), "--scale", "0.05"]) == 2
    assert "exists" in capsys.readouterr().err
    assert _tree_bytes(out) == before
    assert main(["synth", "--preset", "ddad", "--frames", "0", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_depth_written_matches_memory(tmp_path):
    seq = synth_sequence("urban-fisheye", 1, seed=2, scale=0.1)
    out = write_synth("urban-fisheye", 1, tmp_path / "f", seed=2, scale=0.1)
    rig = read_rig_folder(out)
    for cam in preset_ring("urban-fisheye"):
        d = rig.load_depth("000000", cam)
        ref = seq.depths["000000"][cam]
        assert np.abs(d - ref).max() <= 0.5 / 256 + 1e-6
        np.testing.assert_array_equal(rig.load_image("000000", cam), seq.images["000000"][cam])
    assert math.isclose(rig.camera("F").intrinsics.fov_deg, 220.0)


def test_a_killed_writers_temporary_folder_is_removed_by_the_next_run(tmp_path):
    """kill -9 leaves write_synth's temporary sibling behind; the next run removes it when its process is gone and
    leaves a live writer's alone."""
    import subprocess
    import sys

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = tmp_path / f".out.{int(gone.stdout)}.x1.tmp"
    live = tmp_path / f".out.{os.getpid()}.x2.tmp"
    other = tmp_path / f".other.{int(gone.stdout)}.x3.tmp"
    for d in (dead, live, other):
        (d / "frames").mkdir(parents=True)
    write_synth("nuscenes", 1, tmp_path / "out", scale=0.06)
    assert not dead.exists() and live.exists() and other.exists()
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == ["out"]
