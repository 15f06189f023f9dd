"""Matches across time on static points only (`calib.static_world`): an object that drives beside the swaying
car is left out, a wall 20 m away is kept (runtime ~15 s on 2 cores, most of it rendering 18 images)."""

import math

import numpy as np
import pytest

from sgde_plugin.benchmarks.ring_truth import on_moving_box
from sgde_plugin.calib.correspondences import MatchConfig, find_correspondences
from sgde_plugin.calib.features import Keypoints
from sgde_plugin.calib.pipeline import window_ego_poses
from sgde_plugin.calib.static_world import StaticConfig, mark_static_evidence, static_consistent
from sgde_plugin.cameras import Pinhole
from sgde_plugin.geometry import camera_mount, make_transform, yaw_pitch_roll_to_rotation
from sgde_plugin.stereo.rectify import torch_threads

SPEED, SWAY_M, PERIOD_S, RATE_HZ, T = 6.0, 0.25, 9.0, 10.0, 7
MODEL = Pinhole(480, 300, np.array([[240.0, 0, 239.5], [0, 240.0, 149.5], [0, 0, 1]]))
MOUNTS = {"a": camera_mount(math.radians(60), np.array([1.4, 0.8, 1.6])),
          "b": camera_mount(math.radians(120), np.array([0.4, 0.85, 1.6]))}


def _ego(s: float) -> np.ndarray:
    """The synthetic world's ego pose: constant speed along x with a lane sway (synth.world.World.ego_pose)."""
    w = 2 * math.pi / PERIOD_S
    yaw = math.atan2(SWAY_M * w * math.cos(w * s), SPEED)
    return make_transform(yaw_pitch_roll_to_rotation(yaw), np.array([SPEED * s, SWAY_M * math.sin(w * s), 0.0]))


def _perturbed(mount: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A starting mount about 1 deg and 5 cm off."""
    out = mount.copy()
    out[:3, :3] = yaw_pitch_roll_to_rotation(*np.radians(rng.normal(0, 0.6, 3))) @ mount[:3, :3]
    out[:3, 3] += rng.normal(0, 0.03, 3)
    return out


def _window(t0: float, seed: int):
    """Keypoints of cameras a and b over T frames from time t0: a van side 3.5 m to the left driving along
    (the ego's nominal velocity, no sway: synth.world.with_companions) and a facade 20 m to the left."""
    rng = np.random.default_rng(seed)
    ego0 = _ego(t0)
    van = np.stack(np.meshgrid(np.linspace(-0.4, 2.2, 8), [4.3], np.linspace(0.5, 2.0, 5)), -1).reshape(-1, 3)
    van_w = van @ ego0[:3, :3].T + ego0[:3, 3]
    wall = np.column_stack([rng.uniform(-20, 25, 300), np.full(300, 20.0), rng.uniform(0.0, 8.0, 300)])
    wall[:, :2] += ego0[:2, 3]
    n_van = len(van)
    desc = rng.random((n_van + len(wall), 128)).astype(np.float32)
    frames = {c: [] for c in MOUNTS}
    for k in range(T):
        s = t0 + k / RATE_HZ
        world = np.concatenate([van_w + [SPEED * (s - t0), 0.0, 0.0], wall])
        for c, mount in MOUNTS.items():
            pose = _ego(s) @ mount
            X = (world - pose[:3, 3]) @ pose[:3, :3]
            uv, ok = MODEL.project(X)
            ok &= (uv[:, 0] > 0) & (uv[:, 0] < 479) & (uv[:, 1] > 0) & (uv[:, 1] < 299)
            idx = np.flatnonzero(ok)
            d = desc[idx] + rng.normal(0, 0.02, (idx.size, 128)).astype(np.float32)
            frames[c].append(Keypoints(uv[idx] + rng.normal(0, 0.2, (idx.size, 2)), d, index=idx))
    start = {c: _perturbed(m, rng) for c, m in MOUNTS.items()}
    return frames, start, n_van, wall


@pytest.mark.parametrize("t0", [0.0, 1.5, 3.0, 4.5, 6.0, 7.5])
def test_an_object_driving_along_is_left_out_of_matches_across_time_and_a_wall_kept(t0):
    """Every phase of the sway (the van drifts 1-2 px per frame, on or off its epipolar lines), starting mounts
    about 1 deg and 5 cm off: of the van's matches across time at most 5 % pass the gate (measured: none); of
    the wall's at least 95 % (measured: all). The camera's own frames put 15-50 % of the wall keypoints at
    their range (median within 10 %; measured 26-28 m for about 27 m) and the van 500-2000 m away or behind."""
    frames, start, n_van, wall_w = _window(t0, seed=int(t0 * 10))
    poses = {c: np.stack([_ego(t0 + k / RATE_HZ) @ start[c] for k in range(T)]) for c in MOUNTS}
    for c in MOUNTS:
        mark_static_evidence(frames[c], MODEL, poses[c], 240.0)
    kept = {"van": [], "wall": []}
    for t in range(T):
        for t2 in range(T):
            if t == t2:
                continue
            fa, fb = frames["a"][t], frames["b"][t2]
            common = np.intersect1d(fa.index, fb.index)
            ra, _ = MODEL.unproject(fa.uv[np.searchsorted(fa.index, common)])
            rb, _ = MODEL.unproject(fb.uv[np.searchsorted(fb.index, common)])
            rel = np.linalg.inv(poses["b"][t2]) @ poses["a"][t]
            keep = static_consistent(common, common, ra, rb, fa, fb, rel)
            kept["van"].append(keep[common < n_van])
            kept["wall"].append(keep[common >= n_van])
    van, wall = np.concatenate(kept["van"]), np.concatenate(kept["wall"])
    assert van.size > 300 and wall.size > 2000
    assert van.mean() <= 0.05, van.mean()
    assert wall.mean() >= 0.95, wall.mean()
    # the wall is tested, not merely unseen by the test: its own camera's frames place part of it at its range
    for c in MOUNTS:
        k = frames[c][3]
        on_wall = k.index >= n_van
        centre = (_ego(t0 + 3 / RATE_HZ) @ MOUNTS[c])[:3, 3]
        true_range = np.linalg.norm(wall_w[k.index[on_wall] - n_van] - centre, axis=1)
        measured = 1.0 / k.inv_range[on_wall]
        seen = np.isfinite(measured)
        assert seen.mean() >= 0.15
        assert np.median(np.abs(measured[seen] / true_range[seen] - 1)) < 0.1
        # the van, 3.5 m away, drifts like a point hundreds of metres away (or behind the camera)
        van_range = 1.0 / k.inv_range[~on_wall]
        van_range = van_range[np.isfinite(van_range)]
        assert np.all((van_range > 100) | (van_range < 0))


@pytest.fixture(scope="module")
def blocked_window():
    from sgde_plugin.synth.sequence import synth_sequence

    with torch_threads(1):
        return synth_sequence("random", 3, seed=24, scale=0.5)  # CAM_05-CAM_00: a near object drives in the overlap


def _on_moving_object(seq, cam: str, frames: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Truth: whether the rendered point of each keypoint is on a moving box (the object driving along)."""
    out = np.zeros(len(uv), dtype=bool)
    c = seq.rig_true.camera(cam)
    for t in np.unique(frames):
        fr = seq.rig_true.frames[int(t)]
        sel = np.flatnonzero(frames == t)
        px = np.round(uv[sel]).astype(int)
        depth = seq.depths[fr.id][cam][px[:, 1], px[:, 0]].astype(np.float64)
        pts, _ = c.intrinsics.points_from_depth(uv[sel], depth)
        pose = fr.ego_to_world @ c.sensor_to_ego
        out[sel] = on_moving_box(seq.world, pts @ pose[:3, :3].T + pose[:3, 3], fr.timestamp_us * 1e-6)
    return out


def test_rendered_blocked_pair_keeps_no_match_across_time_on_the_object_driving_along(blocked_window):
    """Development rig 24 (3 frames, noisy start), the blocked pair CAM_05-CAM_00: without the static-world test
    about a third of its matches across time are on the object that drives along (measured 89 of 261); with it
    none (<= 2), and the static ones stay (measured 172 -> 173), 0.14 px median from where the truth puts them."""
    seq = blocked_window
    rig, ids = seq.rig, [f.id for f in seq.rig.frames]
    ego = window_ego_poses(rig, rig.frames, rig.camera_names)
    counts = {}
    for enabled in (False, True):
        with torch_threads(1):
            (pm,) = find_correspondences(list(rig.cameras), [("CAM_05", "CAM_00")], ego,
                                         lambda t, c: seq.images[ids[t]][c], None,
                                         MatchConfig(static=StaticConfig(enabled=enabled)))
        cross = pm.frame_a != pm.frame_b
        moving = _on_moving_object(seq, "CAM_05", pm.frame_a, pm.uv_a)
        counts[enabled] = (int(np.sum(cross & moving)), int(np.sum(cross & ~moving)))
    assert counts[False][0] >= 40
    assert counts[True][0] <= 2
    assert counts[True][1] >= 0.9 * counts[False][1]
