"""DDAD reader: tiny DGP scenes (scene_<sha1>.json, calibration/<sha1>.json, rgb/CAMERA_xx/*.png)."""

from __future__ import annotations

import calendar
import hashlib
import json
import math
import shutil
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount, make_transform, rotation_to_quaternion, yaw_pitch_roll_to_rotation
from sgde_plugin.io import write_image
from sgde_plugin.readers import list_scenes, load_rig, load_rigs
from sgde_plugin.readers.ddad import parse_timestamp_us

RING = ("CAMERA_01", "CAMERA_06", "CAMERA_08", "CAMERA_09", "CAMERA_07", "CAMERA_05")
W, H = 1936, 1216
# yaw (deg), position (m), fx, fy, cx, cy: DDAD-like values (front camera narrower than the others)
MOUNTS = {
    "CAMERA_01": (0.0, (1.63, 0.02, 1.53), 2181.54, 2181.55, 928.02, 615.60),
    "CAMERA_05": (62.0, (1.42, 0.53, 1.50), 1058.25, 1058.28, 972.31, 618.42),
    "CAMERA_06": (-61.0, (1.41, -0.55, 1.51), 1060.48, 1060.51, 963.84, 605.18),
    "CAMERA_07": (118.0, (0.55, 0.61, 1.49), 1055.77, 1055.70, 960.22, 612.95),
    "CAMERA_08": (-119.0, (0.56, -0.60, 1.50), 1057.13, 1057.16, 958.46, 600.33),
    "CAMERA_09": (180.0, (-0.97, 0.01, 1.62), 1059.90, 1059.87, 967.04, 609.41),
}
T0 = calendar.timegm((2019, 7, 19, 17, 55, 24, 0, 0, 0)) * 1_000_000 + 236_463


def sha(*parts: object) -> str:
    return hashlib.sha1("/".join(map(str, parts)).encode()).hexdigest()


def rfc3339(us: int) -> str:
    s, frac = divmod(us, 1_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(s)) + f".{frac:06d}Z"


def dgp_pose(T: np.ndarray) -> dict:
    q = rotation_to_quaternion(T[:3, :3])
    return {"translation": dict(zip("xyz", T[:3, 3].tolist())),
            "rotation": {"qw": q[0], "qx": q[1], "qy": q[2], "qz": q[3]}}


def ego_at(k: int) -> np.ndarray:
    return make_transform(yaw_pitch_roll_to_rotation(0.1 * k, 0.01, -0.02 * k), [10.0 * k, 2.0 * k, 0.05 * k])


def write_scene(folder: Path, n: int = 3, images: bool = True, scale: float = 1.0) -> dict:
    """One DGP scene with n samples of six cameras and a lidar; returns the truth.

    `scale` shrinks the images and the intrinsics together (tests that only read the JSON decode less).
    """
    w, h = round(W * scale), round(H * scale)
    names = [*sorted(RING), "LIDAR"]
    calib_key = sha("calib", folder.name)
    intr, extr, truth = [], [], {"cameras": {}, "frames": []}
    for name in names:
        if name == "LIDAR":
            intr.append({"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0, "skew": 0.0, "fov": 0.0, "fisheye": 0,
                         "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "k5": 0.0, "k6": 0.0, "p1": 0.0, "p2": 0.0})
            extr.append(dgp_pose(make_transform(np.eye(3), [1.3, 0.0, 1.9])))
            continue
        yaw, pos, *k = MOUNTS[name]
        fx, fy, cx, cy = (scale * v for v in k)
        T = camera_mount(math.radians(yaw), np.array(pos))
        truth["cameras"][name] = (T, [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        intr.append({"fx": fx, "fy": fy, "cx": cx, "cy": cy, "skew": 0.0, "fov": 0.0, "fisheye": 0, "k1": 0.0,
                     "k2": 0.0, "k3": 0.0, "k4": 0.0, "k5": 0.0, "k6": 0.0, "p1": 0.0, "p2": 0.0})
        extr.append(dgp_pose(T))
    (folder / "calibration").mkdir(parents=True, exist_ok=True)
    (folder / "calibration" / f"{calib_key}.json").write_text(
        json.dumps({"names": names, "intrinsics": intr, "extrinsics": extr}, indent=2))
    samples, data = [], []
    img = np.zeros((h, w, 3), np.uint8)
    for k in range(n):
        keys = []
        ts_sample = T0 + 100_000 * k
        for j, name in enumerate(names):
            ts = ts_sample + 1_000 * j
            key = sha("datum", folder.name, name, k)
            keys.append(key)
            ident = {"log": "ddad", "name": name, "timestamp": rfc3339(ts), "index": str(k)}
            if name == "LIDAR":
                datum = {"point_cloud": {"filename": f"point_cloud/LIDAR/{ts}.npz", "point_format": [],
                                         "annotations": {}, "metadata": {}, "pose": dgp_pose(ego_at(k))}}
            else:
                filename = f"rgb/{name}/{ts}.png"
                world_from_cam = ego_at(k) @ truth["cameras"][name][0]
                datum = {"image": {"filename": filename, "height": h, "width": w, "channels": 3,
                                   "annotations": {}, "metadata": {}, "pose": dgp_pose(world_from_cam)}}
                if images:
                    write_image(folder / filename, img)
                if name == "CAMERA_01":
                    truth["frames"].append((f"{k:06d}", ts, ego_at(k)))
            data.append({"id": ident, "key": key, "datum": datum, "next_key": "", "prev_key": ""})
        samples.append({"id": {"log": "ddad", "name": "", "timestamp": rfc3339(ts_sample), "index": str(k)},
                        "datum_keys": keys, "calibration_key": calib_key, "metadata": {}})
    scene = {"name": folder.name, "description": "", "log": "ddad", "samples": samples, "data": data,
             "metadata": {}, "ontologies": {}, "creation_date": "2020-02-28T00:00:00Z"}
    (folder / f"scene_{sha('scene', folder.name)}.json").write_text(json.dumps(scene, indent=2, sort_keys=True))
    return truth


@pytest.fixture(scope="module")
def ddad_root(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("ddad")
    truths = {name: write_scene(root / name, images=(name == "000150")) for name in ("000150", "000151")}
    return root, truths


def test_exact_calibration_ring_timestamps_and_poses(ddad_root: tuple[Path, dict]) -> None:
    root, truths = ddad_root
    rig = load_rig(root / "000150", check_images=True)
    truth = truths["000150"]
    assert rig.ring == RING and rig.camera_names == list(RING)
    for cam in rig.cameras:
        T, K = truth["cameras"][cam.name]
        assert (cam.width, cam.height) == (W, H) and cam.intrinsics.dist is None
        assert cam.intrinsics.K.tolist() == K
        np.testing.assert_allclose(cam.sensor_to_ego, T, rtol=0, atol=1e-9)
    assert [(f.id, f.timestamp_us) for f in rig.frames] == [(i, ts) for i, ts, _ in truth["frames"]]
    for f, (_, _, pose) in zip(rig.frames, truth["frames"]):
        np.testing.assert_allclose(f.ego_to_world, pose, rtol=0, atol=1e-9)
        assert f.images["CAMERA_09"].parent == root / "000150" / "rgb" / "CAMERA_09"
    assert rig.frames[1].timestamp_us - rig.frames[0].timestamp_us == 100_000


def test_scene_file_root_and_camel_case(ddad_root: tuple[Path, dict], tmp_path: Path) -> None:
    root, _ = ddad_root
    scene_json = next((root / "000151").glob("scene_*.json"))
    assert load_rig(scene_json) == load_rig(root / "000151") == load_rig(f"{root}::000151")
    assert list_scenes(root) == ["000150", "000151"]
    assert [len(r.frames) for r in load_rigs(root)] == [3, 3]
    with pytest.raises(InputError, match=r"holds 2 scenes \(000150, 000151\); pick one"):
        load_rig(root)
    # DGP's JSON parser accepts lowerCamelCase field names too
    doc = json.loads(scene_json.read_text())
    for s in doc["samples"]:
        s["datumKeys"] = s.pop("datum_keys")
        s["calibrationKey"] = s.pop("calibration_key")
    (tmp_path / "calibration").mkdir()
    for f in (root / "000151" / "calibration").iterdir():
        (tmp_path / "calibration" / f.name).write_text(f.read_text())
    (tmp_path / scene_json.name).write_text(json.dumps(doc))
    camel = load_rig(tmp_path)
    # the scene name is the folder's, which differs here by construction
    assert camel.to_dict() | {"scene": "x"} == load_rig(root / "000151").to_dict() | {"scene": "x"}


def test_rfc3339_timestamps() -> None:
    f = Path("scene.json")
    assert parse_timestamp_us("1970-01-01T00:00:01.5Z", f, "t") == 1_500_000
    assert parse_timestamp_us("1970-01-01T00:00:00Z", f, "t") == 0
    assert parse_timestamp_us("2019-07-19T17:55:24.236463789Z", f, "t") == T0
    assert parse_timestamp_us("2019-07-19T19:55:24.236463+02:00", f, "t") == T0
    with pytest.raises(InputError, match="not an RFC 3339 timestamp"):
        parse_timestamp_us(1563558924236463, f, "t")


def _truncate(folder: Path) -> str:
    path = next(folder.glob("scene_*.json"))
    text = path.read_text()
    path.write_text(text[: len(text) // 3])
    return "truncated JSON"


def _missing_camera(folder: Path) -> str:
    path = next(folder.glob("scene_*.json"))
    doc = json.loads(path.read_text())
    doc["samples"][1]["datum_keys"].remove(sha("datum", folder.name, "CAMERA_07", 1))
    path.write_text(json.dumps(doc))
    return "samples[1]: camera CAMERA_07 is missing"


def _missing_file(folder: Path) -> str:
    victim = next((folder / "rgb" / "CAMERA_06").iterdir())
    victim.unlink()
    return f"filename: points at a missing file {victim}"


def _missing_calibration(folder: Path) -> str:
    next((folder / "calibration").iterdir()).unlink()
    return "file not found"


def _datum_key_not_a_string(folder: Path) -> str:
    path = next(folder.glob("scene_*.json"))
    doc = json.loads(path.read_text())
    doc["samples"][1]["datum_keys"][0] = ["a", "list"]
    path.write_text(json.dumps(doc))
    return "samples[1].datum_keys: key ['a', 'list'] is not a string"


def _huge_quaternion(folder: Path) -> str:
    path = next((folder / "calibration").iterdir())
    doc = json.loads(path.read_text())
    doc["extrinsics"][1]["rotation"]["qx"] = 1e308  # its square overflows: no warning, one line
    path.write_text(json.dumps(doc))
    return "extrinsics[1].rotation: quaternion is not unit length (norm 1e+308)"


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("ddad_small") / "000000"
    write_scene(folder, n=2)
    assert main(["validate", str(folder)]) == 0
    return folder


@pytest.mark.parametrize("defect", [_truncate, _missing_camera, _missing_file, _missing_calibration,
                                    _datum_key_not_a_string, _huge_quaternion])
def test_defects_are_one_line_exit_2(defect, small_scene: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "000000"
    shutil.copytree(small_scene, folder)
    capsys.readouterr()
    expected = defect(folder)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning would be a second line on stderr
        assert main(["validate", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sgde validate: ") and "Traceback" not in err
    assert expected in err, err


def test_each_camera_keeps_its_own_datum_time_and_pose(ddad_root: tuple[Path, dict]) -> None:
    root, truths = ddad_root
    rig = load_rig(root / "000150")
    truth = truths["000150"]
    names = [*sorted(RING), "LIDAR"]
    for k, fr in enumerate(rig.frames):
        for cam in rig.cameras:
            cap = rig.capture(fr.id, cam.name)
            assert cap.timestamp_us == T0 + 100_000 * k + 1_000 * names.index(cam.name)
            np.testing.assert_allclose(cap.camera_to_world, ego_at(k) @ truth["cameras"][cam.name][0], atol=1e-9)
        assert "CAMERA_01" not in fr.cameras and fr.cameras["CAMERA_09"].timestamp_us - fr.timestamp_us == 5_000


def test_partial_rig_loads_the_cameras_it_has(tmp_path: Path) -> None:
    folder = tmp_path / "000007"
    write_scene(folder, n=2, images=False)
    path = next(folder.glob("scene_*.json"))
    doc = json.loads(path.read_text())
    front = {sha("datum", folder.name, c, k) for c in ("CAMERA_01", "CAMERA_05", "CAMERA_06", "LIDAR")
             for k in range(2)}
    for s in doc["samples"]:
        s["datum_keys"] = [k for k in s["datum_keys"] if k in front]
    path.write_text(json.dumps(doc))
    rig = load_rig(folder)
    assert rig.camera_names == ["CAMERA_01", "CAMERA_06", "CAMERA_05"] and rig.ring is None
    assert rig.pairs == (("CAMERA_01", "CAMERA_06"), ("CAMERA_05", "CAMERA_01"))
    assert rig.to_dict()["pairs"] == [["CAMERA_01", "CAMERA_06"], ["CAMERA_05", "CAMERA_01"]]
    # two cameras that are not adjacent in the ring make no rig
    for s in doc["samples"]:
        s["datum_keys"] = [k for k in s["datum_keys"] if k in {sha("datum", folder.name, c, i)
                                                              for c in ("CAMERA_01", "CAMERA_09") for i in range(2)}]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="no two adjacent ring cameras"):
        load_rig(folder)
