"""Per-camera capture (sgde-rig/1 `frames[].cameras`): round trip, defaults, the Rig.capture accessor, defects."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_rig import make_rig, write_folder

from sgde_plugin.cli import main
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import make_transform, yaw_pitch_roll_to_rotation
from sgde_plugin.rig import CameraCapture, read_rig_json, rig_from_dict, write_rig_json


def _moved(dx: float, yaw: float = 0.0) -> np.ndarray:
    return make_transform(yaw_pitch_roll_to_rotation(yaw), [dx, 0.1, 0.0])


def rig_with_captures():
    rig = make_rig(frames=2)
    fr = rig.frames[1]
    caps = {"CAM_FRONT_RIGHT": CameraCapture(fr.timestamp_us + 8_000, _moved(0.84, 0.01)),  # both keys
            "CAM_BACK": CameraCapture(timestamp_us=fr.timestamp_us + 24_000),  # time only
            "CAM_FRONT_LEFT": CameraCapture(ego_to_world=_moved(0.9))}  # pose only
    return replace(rig, frames=(rig.frames[0], replace(fr, cameras=caps)))


def test_round_trip_keeps_only_given_keys(tmp_path: Path) -> None:
    rig = rig_with_captures()
    write_rig_json(rig, tmp_path / "a.json")
    doc = json.loads((tmp_path / "a.json").read_text())
    assert "cameras" not in doc["frames"][0]
    entry = doc["frames"][1]["cameras"]
    assert set(entry) == {"CAM_FRONT_RIGHT", "CAM_BACK", "CAM_FRONT_LEFT"}
    assert set(entry["CAM_BACK"]) == {"timestamp_us"} and set(entry["CAM_FRONT_LEFT"]) == {"ego_to_world"}
    back = read_rig_json(tmp_path / "a.json")
    assert back == rig
    write_rig_json(back, tmp_path / "b.json")
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()


def test_capture_accessor_falls_back_to_the_frame() -> None:
    rig = rig_with_captures()
    fr = rig.frames[1]
    for name in rig.camera_names:
        cap = rig.capture(fr.id, name)
        S = rig.camera(name).sensor_to_ego
        np.testing.assert_allclose(cap.camera_to_world, cap.ego_to_world @ S, atol=1e-15)
    assert rig.capture(fr, "CAM_FRONT").timestamp_us == fr.timestamp_us == 100_000
    np.testing.assert_array_equal(rig.capture(fr, "CAM_FRONT").ego_to_world, fr.ego_to_world)
    assert rig.capture(fr, "CAM_FRONT_RIGHT").timestamp_us == 108_000
    np.testing.assert_allclose(rig.capture(fr, "CAM_FRONT_RIGHT").ego_to_world[:3, 3], [0.84, 0.1, 0.0])
    back = rig.capture(fr, "CAM_BACK")  # time only: the frame's pose
    assert back.timestamp_us == 124_000 and np.array_equal(back.ego_to_world, fr.ego_to_world)
    left = rig.capture(fr, "CAM_FRONT_LEFT")  # pose only: the frame's time
    assert left.timestamp_us == 100_000 and left.ego_to_world[0, 3] == 0.9
    # frame 0 has no entries: every camera at the frame's pose
    np.testing.assert_array_equal(rig.capture(rig.frames[0].id, "CAM_BACK").ego_to_world, rig.frames[0].ego_to_world)


@pytest.mark.parametrize("defect, key", [
    ("unknown_camera", "frames[000000].cameras.CAM_NOPE: camera 'CAM_NOPE' is not in the rig"),
    ("bad_time", "frames[000000].cameras.CAM_BACK.timestamp_us: not an integer"),
    ("bad_pose", "frames[000000].cameras.CAM_BACK.ego_to_world: rotation is not orthonormal"),
    ("not_object", "frames[000000].cameras: not an object"),
])
def test_capture_defects_are_one_line_exit_2(defect: str, key: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture) -> None:
    rig = make_rig(frames=1)
    write_folder(tmp_path, rig)
    doc = rig.to_dict()
    pose = np.eye(4).tolist()
    entry = {"unknown_camera": {"CAM_NOPE": {"timestamp_us": 5}},
             "bad_time": {"CAM_BACK": {"timestamp_us": 1.5}},
             "bad_pose": {"CAM_BACK": {"ego_to_world": [[2.0, 0, 0, 0], *pose[1:]]}},
             "not_object": ["CAM_BACK"]}[defect]
    doc["frames"][0]["cameras"] = entry
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    assert main(["validate", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and key in err and "Traceback" not in err
    with pytest.raises(InputError):
        rig_from_dict(doc)


def test_as_captured_places_cameras_at_their_own_capture() -> None:
    rig = rig_with_captures()
    fr = rig.frames[1]
    cap = rig.as_captured(fr)
    assert rig.as_captured(rig.frames[0]) is rig  # no per-camera entries: the rig itself
    for a, b in (("CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_FRONT_LEFT", "CAM_BACK")):
        want = np.linalg.inv(rig.capture(fr, b).camera_to_world) @ rig.capture(fr, a).camera_to_world
        got = np.linalg.inv(cap.camera(b).sensor_to_ego) @ cap.camera(a).sensor_to_ego
        np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_array_equal(cap.camera("CAM_BACK").sensor_to_ego, rig.camera("CAM_BACK").sensor_to_ego)


def test_synth_sequential_capture_writes_each_cameras_time_and_pose(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    from sgde_plugin.synth.presets import preset_world

    out = tmp_path / "seq"
    assert main(["synth", "--preset", "nuscenes", "--frames", "2", "--out", str(out), "--scale", "0.1",
                 "--capture", "sequential", "--sweep-ms", "60", "--pose-noise-deg", "0"]) == 0
    rig, true = read_rig_json(out / "rig.json"), read_rig_json(out / "rig_true.json")
    world = preset_world("nuscenes", 0)
    for fr in true.frames:
        assert set(fr.cameras) == set(true.camera_names[1:])  # the first camera fires at the frame's time
        for i, name in enumerate(true.camera_names):
            cap = true.capture(fr, name)
            assert cap.timestamp_us == fr.timestamp_us + 10_000 * i  # 60 ms over six cameras
            np.testing.assert_allclose(cap.ego_to_world, world.ego_pose(cap.timestamp_us * 1e-6), atol=1e-9)
            assert rig.capture(fr.id, name).timestamp_us == cap.timestamp_us
    assert true.extra["synth"]["capture"] == "sequential"
    assert main(["synth", "--preset", "nuscenes", "--frames", "1", "--out", str(tmp_path / "x"),
                 "--capture", "sequential", "--sweep-ms", "150"]) == 2
    assert "--sweep-ms" in capsys.readouterr().err


def test_prior_needs_the_per_camera_poses_under_sequential_capture() -> None:
    from sgde_plugin.benchmarks.capture import ARMS, run

    out = run(frames=1, scale=0.4)
    sync, own, frame_only = (out["arms"][k]["abs_rel"] for k in ARMS)
    # with each camera's capture pose the prior is as good as in a synchronised world (within 25 % at
    # this small size); placing every camera at the frame's pose makes it several times worse
    assert own <= 1.25 * sync and frame_only >= 4 * own
    assert out["arms"][ARMS[1]]["coverage"] >= 0.9 * out["arms"][ARMS[0]]["coverage"]
    # the builder planned the mount geometry; the frame's captures moved it, so its one frame was planned again
    assert [out["arms"][k]["replanned_frames"] for k in ARMS] == [0, 1, 0]
    assert out["arms"][ARMS[1]]["seconds_per_replan"] > 0 and out["arms"][ARMS[0]]["seconds_per_replan"] is None
    # the fisheye rig (reported, no target): its tiles re-planned per capture, the frame pose alone far worse; the
    # per-camera poses leave it within 30 % of sync (1.14 at this size, 1.20 at full size: the sweep changes the pairs'
    # baselines, a synchronised render with those mounts gives 1.13; at a sweep of 0 ms the three arms agree)
    fish = out["fisheye"]
    sync, own, frame_only = (fish["arms"][k]["abs_rel"] for k in ARMS)
    assert fish["preset"] == "urban-fisheye" and own <= 1.3 * sync and frame_only >= 2.5 * own
    assert [fish["arms"][k]["replanned_frames"] for k in ARMS] == [0, 1, 0]
