"""nuScenes reader: a tiny table set written from the documented v1.0 schema, read back exactly."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount, make_transform, quaternion_to_rotation, rotation_to_quaternion
from sgde_plugin.io import write_image
from sgde_plugin.readers import list_scenes, load_rig, load_rigs
from sgde_plugin.rig import CameraCapture, Frame, Rig, read_rig_folder, ring_pairs, write_rig_json

VERSION = "v1.0-mini"
RING = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
# nuScenes-like mounting: yaw (deg), position (m), focal and principal point of a 1600x900 image
MOUNTS = {
    "CAM_FRONT": (0.0, (1.70, 0.016, 1.51), 1266.42, 816.27, 491.51),
    "CAM_FRONT_RIGHT": (-55.0, (1.55, -0.49, 1.50), 1260.85, 807.97, 495.33),
    "CAM_BACK_RIGHT": (-110.0, (1.03, -0.48, 1.56), 1259.51, 807.25, 501.20),
    "CAM_BACK": (180.0, (0.03, 0.0, 1.57), 809.22, 829.22, 481.77),
    "CAM_BACK_LEFT": (110.0, (1.04, 0.48, 1.56), 1256.75, 817.79, 451.95),
    "CAM_FRONT_LEFT": (55.0, (1.52, 0.49, 1.51), 1272.60, 826.62, 479.75),
}
FIRE_US = {c: 12_000 + 8_000 * i for i, c in enumerate(RING)}  # cameras fire in turn after the lidar
W, H = 1600, 900


def tok(*parts: object) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def ego_pose(t_us: int) -> tuple[list[float], list[float]]:
    """Ego driving at 5 m/s along a gentle left curve: (rotation wxyz, translation)."""
    s = (t_us - 1_532_402_927_000_000) / 1e6
    yaw = 0.3 + 0.02 * s
    q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    return q, [411.3 + 5.0 * s * math.cos(0.3), 1180.9 + 5.0 * s * math.sin(0.3), 0.0]


def write_tables(root: Path, scenes: dict[str, int], sweeps_between: int = 3, version: str = VERSION,
                 images: bool = True) -> dict:
    """Write nuScenes tables (+ tiny stand-in lidar/radar rows) and, optionally, the camera images."""
    tables: dict[str, list] = {t: [] for t in ("scene", "sample", "sample_data", "calibrated_sensor",
                                                "sensor", "ego_pose", "log")}
    channels = [*RING, "LIDAR_TOP", "RADAR_FRONT"]
    for ch in channels:
        modality = "camera" if ch.startswith("CAM") else ch.split("_")[0].lower()
        tables["sensor"].append({"token": tok("sensor", ch), "channel": ch, "modality": modality})
    truth = {"cameras": {}, "scenes": {}}
    t0 = 1_532_402_927_000_000
    for si, (name, n_samples) in enumerate(scenes.items()):
        log = tok("log", name)
        tables["log"].append({"token": log, "logfile": f"n015-{name}", "vehicle": "n015",
                              "date_captured": "2018-07-24", "location": "singapore-onenorth"})
        calib = {}
        for ch in channels:
            calib[ch] = tok("calib", name, ch)
            row = {"token": calib[ch], "sensor_token": tok("sensor", ch), "translation": [0.94, 0.0, 1.84],
                   "rotation": [0.7071, 0.0, 0.0, 0.7071], "camera_intrinsic": []}
            if ch in RING:
                yaw, pos, f, cx, cy = MOUNTS[ch]
                T = camera_mount(math.radians(yaw), np.array(pos))
                q = rotation_to_quaternion(T[:3, :3])
                row.update(translation=list(pos), rotation=q.tolist(),
                           camera_intrinsic=[[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
                truth["cameras"][ch] = (T, row["camera_intrinsic"], q.tolist())
            tables["calibrated_sensor"].append(row)
        scene_tok = tok("scene", name)
        samples = [tok("sample", name, k) for k in range(n_samples)]
        start = t0 + si * 100_000_000
        tables["scene"].append({"token": scene_tok, "log_token": log, "nbr_samples": n_samples,
                                "first_sample_token": samples[0], "last_sample_token": samples[-1],
                                "name": name, "description": "tiny fixture"})
        keyframes, sweeps = [], []
        for k, s in enumerate(samples):
            ts = start + 500_000 * k
            tables["sample"].append({"token": s, "timestamp": ts, "prev": samples[k - 1] if k else "",
                                     "next": samples[k + 1] if k + 1 < n_samples else "", "scene_token": scene_tok})
            per_sample = {}
            for ch in channels:
                fire = FIRE_US.get(ch, 0)
                rows = [(ts + fire, True)]
                if k + 1 < n_samples and ch in RING:  # sweeps until the next keyframe, at ~12 Hz
                    rows += [(ts + fire + 83_000 * (j + 1), False) for j in range(sweeps_between)]
                for t, key in rows:
                    sd = tok("sd", name, ch, t)
                    folder = "samples" if key else "sweeps"
                    ext = "jpg" if ch in RING else "pcd"
                    sample_of = s if key else samples[k + 1]
                    tables["sample_data"].append({
                        "token": sd, "sample_token": sample_of, "ego_pose_token": tok("ego", sd),
                        "calibrated_sensor_token": calib[ch], "timestamp": t, "fileformat": ext,
                        "is_key_frame": key, "height": H if ch in RING else 0, "width": W if ch in RING else 0,
                        "filename": f"{folder}/{ch}/n015-{name}__{ch}__{t}.{ext}", "prev": "", "next": ""})
                    q, tr = ego_pose(t)
                    tables["ego_pose"].append({"token": tok("ego", sd), "timestamp": t, "rotation": q,
                                               "translation": tr})
                    if ch in RING and key:
                        per_sample[ch] = sd
                    elif ch in RING:
                        sweeps.append((t, ch, sd))
            keyframes.append((s, per_sample))
        truth["scenes"][name] = {"token": scene_tok, "keyframes": keyframes, "sweeps": sweeps}
    tables["sample_data"].reverse()  # table order must not matter
    folder = root / version
    folder.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        # nuScenes writes its tables with indent=0
        (folder / f"{name}.json").write_text(json.dumps(rows, indent=0), encoding="utf-8")
    if images:
        img = np.zeros((H, W, 3), np.uint8)
        for row in tables["sample_data"]:
            if row["fileformat"] == "jpg":
                write_image(root / row["filename"], img)
    truth["tables"] = tables
    return truth


def expected_rig(root: Path, truth: dict, scene: str) -> Rig:
    """The rig the reader must return, built from the written quaternions and rows."""
    from sgde_plugin.cameras import Camera, Pinhole

    cams = []
    for ch in RING:
        _, K, q = truth["cameras"][ch]
        cams.append(Camera(ch, Pinhole(W, H, np.array(K)), make_transform(quaternion_to_rotation(q),
                                                                          MOUNTS[ch][1])))
    rows = {r["token"]: r for r in truth["tables"]["sample_data"]}
    poses = {r["token"]: r for r in truth["tables"]["ego_pose"]}
    frames = []
    for sample, per in truth["scenes"][scene]["keyframes"]:
        front = rows[per["CAM_FRONT"]]
        ego = poses[front["ego_pose_token"]]
        own = {}  # every other camera's own capture time and ego pose
        for ch in RING[1:]:
            row = rows[per[ch]]
            pose = poses[row["ego_pose_token"]]
            own[ch] = CameraCapture(row["timestamp"], make_transform(quaternion_to_rotation(pose["rotation"]),
                                                                     pose["translation"]))
        frames.append(Frame(sample, front["timestamp"],
                            make_transform(quaternion_to_rotation(ego["rotation"]), ego["translation"]),
                            {ch: root / rows[per[ch]]["filename"] for ch in RING}, cameras=own))
    return Rig(tuple(cams), ring_pairs(RING), tuple(frames), RING, root, extra={"scene": scene})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("nuscenes")
    return root, write_tables(root, {"scene-0061": 3, "scene-0103": 2})


def test_exact_calibration_ring_timestamps_and_poses(dataset: tuple[Path, dict]) -> None:
    root, truth = dataset
    rig = load_rig(f"{root}::{VERSION}::scene-0061")
    assert rig.ring == RING and rig.camera_names == list(RING)
    assert rig.pairs == tuple(zip(RING, RING[1:] + RING[:1]))
    for cam in rig.cameras:
        T, K, _ = truth["cameras"][cam.name]
        assert cam.model == "pinhole" and (cam.width, cam.height) == (W, H) and cam.intrinsics.dist is None
        assert cam.intrinsics.K.tolist() == K
        np.testing.assert_allclose(cam.sensor_to_ego, T, rtol=0, atol=1e-9)
    keyframes = truth["scenes"]["scene-0061"]["keyframes"]
    rows = {r["token"]: r for r in truth["tables"]["sample_data"]}
    assert [f.id for f in rig.frames] == [s for s, _ in keyframes]
    for frame, (_, per) in zip(rig.frames, keyframes):
        front = rows[per["CAM_FRONT"]]
        assert frame.timestamp_us == front["timestamp"]
        q, t = ego_pose(front["timestamp"])
        yaw = 2 * math.atan2(q[3], q[0])
        np.testing.assert_allclose(frame.ego_to_world[:3, 3], t, atol=1e-9)
        np.testing.assert_allclose(frame.ego_to_world[:2, 0], [math.cos(yaw), math.sin(yaw)], atol=1e-9)
        assert frame.images["CAM_BACK"] == root / rows[per["CAM_BACK"]]["filename"]


def test_same_rig_as_sgde_rig_folder(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    root, truth = dataset
    write_rig_json(expected_rig(root, truth, "scene-0103"), tmp_path / "rig.json")
    from_folder = read_rig_folder(tmp_path)
    from_nuscenes = load_rig(root, scene="scene-0103")
    assert from_nuscenes == from_folder
    assert from_nuscenes.to_dict() == from_folder.to_dict()
    assert len(from_nuscenes.frames) == 2


def test_sweeps_add_front_camera_sweeps_with_nearest_neighbours(dataset: tuple[Path, dict]) -> None:
    root, truth = dataset
    keyframes = load_rig(f"{root}::scene-0061")
    sweeps = load_rig(f"{root}::scene-0061::sweeps")
    assert load_rig(root, scene="scene-0061", sweeps=True) == sweeps
    sc = truth["scenes"]["scene-0061"]
    front_sweeps = sorted(t for t, ch, _ in sc["sweeps"] if ch == "CAM_FRONT")
    assert len(sweeps.frames) == 3 + len(front_sweeps) == 9
    times = [f.timestamp_us for f in sweeps.frames]
    assert times == sorted(times)
    by_id = {f.id: f for f in sweeps.frames}
    for kf in keyframes.frames:  # keyframes are identical in both modes
        assert by_id[kf.id] == kf and dict(by_id[kf.id].images) == dict(kf.images)
    rows = {r["filename"]: r for r in truth["tables"]["sample_data"]}
    for f in sweeps.frames:
        if f.id in {k.id for k in keyframes.frames}:
            continue
        assert "sweeps/CAM_FRONT/" in str(f.images["CAM_FRONT"])
        for ch in RING:  # each camera's sweep fired FIRE_US[ch] - FIRE_US[front] after the front one
            row = rows[str(f.images[ch].relative_to(root))]
            assert row["timestamp"] - f.timestamp_us == FIRE_US[ch] - FIRE_US["CAM_FRONT"]


def test_scene_listing_and_selection(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    root, truth = dataset
    assert list_scenes(root) == ["scene-0061", "scene-0103"]
    assert list_scenes(root / VERSION) == ["scene-0061", "scene-0103"]
    rigs = load_rigs(f"{root}::{VERSION}")
    assert [len(r.frames) for r in rigs] == [3, 2]
    by_token = load_rig(f"{root}::{truth['scenes']['scene-0103']['token']}")
    assert by_token == rigs[1]
    assert load_rig(root / VERSION, scene="scene-0061") == rigs[0]
    with pytest.raises(InputError, match=r"holds 2 scenes \(scene-0061, scene-0103\); pick one"):
        load_rig(root)
    with pytest.raises(InputError, match="no scene 'scene-9999'"):
        load_rig(f"{root}::scene-9999")
    write_rig_json(rigs[0], tmp_path / "rig.json")
    with pytest.raises(InputError, match="only nuScenes has sweeps"):
        load_rig(f"{tmp_path}::sweeps")
    with pytest.raises(InputError, match="holds one scene; no scene selector"):
        load_rig(f"{tmp_path}::scene-0061")


def test_two_versions_need_a_choice(tmp_path: Path) -> None:
    write_tables(tmp_path, {"scene-0001": 2}, sweeps_between=0, images=False)
    write_tables(tmp_path, {"scene-0002": 2}, sweeps_between=0, version="v1.0-test", images=False)
    with pytest.raises(InputError, match=r"holds 2 versions \(v1.0-mini, v1.0-test\)"):
        load_rig(tmp_path)
    assert load_rig(f"{tmp_path}::v1.0-test").frames[0].id == tok("sample", "scene-0002", 0)
    assert list_scenes(tmp_path, version="v1.0-mini") == ["scene-0001"]


def _truncate(root: Path) -> str:
    path = root / VERSION / "sample_data.json"
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    return "sample_data.json: element"


def _missing_camera(root: Path) -> str:
    path = root / VERSION / "sample_data.json"
    rows = [r for r in json.loads(path.read_text()) if "/CAM_BACK/" not in r["filename"] or not r["is_key_frame"]
            or r["sample_token"] != tok("sample", "scene-0061", 1)]
    path.write_text(json.dumps(rows, indent=0))
    return f"sample {tok('sample', 'scene-0061', 1)}: camera CAM_BACK is missing"


def _missing_sensor(root: Path) -> str:
    path = root / VERSION / "sensor.json"
    path.write_text(json.dumps([r for r in json.loads(path.read_text()) if r["channel"] != "CAM_FRONT_LEFT"]))
    return "sensor.json: channel: camera CAM_FRONT_LEFT is missing"


def _missing_file(root: Path) -> str:
    rows = json.loads((root / VERSION / "sample_data.json").read_text())
    row = next(r for r in rows if r["sample_token"] == tok("sample", "scene-0061", 2) and r["is_key_frame"]
               and "/CAM_FRONT_RIGHT/" in r["filename"])
    (root / row["filename"]).unlink()
    return f"sample_data.json: [token={row['token']}].filename: points at a missing file"


@pytest.fixture(scope="module")
def small_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("nuscenes_small")
    write_tables(root, {"scene-0061": 3}, sweeps_between=0)
    assert main(["validate", f"{root}::scene-0061"]) == 0
    return root


@pytest.mark.parametrize("defect", [_truncate, _missing_camera, _missing_sensor, _missing_file])
def test_defects_are_one_line_exit_2(defect, small_set: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    tmp_path = tmp_path / "copy"
    shutil.copytree(small_set, tmp_path)
    capsys.readouterr()
    expected = defect(tmp_path)
    assert main(["validate", f"{tmp_path}::scene-0061"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sgde validate: ") and "Traceback" not in err
    assert expected in err, err


def test_quaternion_and_intrinsic_defects(tmp_path: Path) -> None:
    write_tables(tmp_path, {"scene-0061": 2}, sweeps_between=0, images=False)
    path = tmp_path / VERSION / "calibrated_sensor.json"
    rows = json.loads(path.read_text())
    cam = next(r for r in rows if r["token"] == tok("calib", "scene-0061", "CAM_BACK"))
    good = dict(cam)
    cam["rotation"] = [0.5, 0.5, 0.5, 0.6]
    path.write_text(json.dumps(rows))
    with pytest.raises(InputError, match=r"rotation: quaternion is not unit length"):
        load_rig(tmp_path)
    cam.update(good, camera_intrinsic=[[0.0, 0.0, 800.0], [0.0, 0.0, 450.0], [0.0, 0.0, 1.0]])
    path.write_text(json.dumps(rows))
    with pytest.raises(InputError, match=r"calibrated_sensor.json: \[token=\w+\]\.camera_intrinsic: is singular"):
        load_rig(tmp_path)


@pytest.mark.parametrize(("table", "column", "message"), [
    ("ego_pose", "token", r"ego_pose.json: token: \['x'\] is not a string"),
    ("sample_data", "ego_pose_token", r"sample_data.json: \[token=\w+\]: token/ego_pose_token has the wrong type"),
])
def test_a_token_that_is_not_a_string_is_named(table: str, column: str, message: str, tmp_path: Path) -> None:
    write_tables(tmp_path, {"scene-0061": 2}, sweeps_between=0, images=False)
    path = tmp_path / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    for row in rows:  # every row: whichever the reader needs first
        row[column] = ["x"]
    path.write_text(json.dumps(rows))
    with pytest.raises(InputError, match=message):
        load_rig(tmp_path)


def test_braces_in_strings_fall_back_to_the_exact_parser(tmp_path: Path) -> None:
    truth = write_tables(tmp_path, {"scene-0061": 2}, sweeps_between=1, images=False)
    fast = load_rig(tmp_path, sweeps=True)
    path = tmp_path / VERSION / "sample_data.json"
    rows = json.loads(path.read_text())
    for r in rows:  # a '}' and a '{' inside strings defeat the fast splitter, not the reader
        r["filename"] = r["filename"].replace("n015-", "n015-{x}-")
    path.write_text(json.dumps(rows, indent=0))
    exact = load_rig(tmp_path, sweeps=True)
    assert exact == fast and len(exact.frames) == 3
    assert "{x}" in str(exact.frames[0].images["CAM_FRONT"])
    assert truth["scenes"]["scene-0061"]["keyframes"][0][0] == exact.frames[0].id


@pytest.mark.parametrize("cut", [0.5, 0.999])
def test_scan_table_truncation_both_paths(tmp_path: Path, cut: float) -> None:
    from sgde_plugin.readers.jsonio import scan_table

    rows = [{"token": f"{i:032x}", "note": "{}" if i == 3 else "x"} for i in range(50)]
    for flat in (True, False):
        text = json.dumps(rows if not flat else [{**r, "note": "x"} for r in rows], indent=0)
        (tmp_path / "t.json").write_text(text)
        assert len(scan_table(tmp_path / "t.json", lambda r: r["token"])) == 50
        (tmp_path / "t.json").write_text(text[: int(len(text) * cut)])
        with pytest.raises(InputError, match=r"t.json: element \d+: truncated"):
            scan_table(tmp_path / "t.json", lambda r: r["token"])


def test_each_camera_keeps_its_own_capture_time_and_ego_pose(dataset: tuple[Path, dict]) -> None:
    root, truth = dataset
    rig = load_rig(f"{root}::{VERSION}::scene-0061")
    rows = {r["token"]: r for r in truth["tables"]["sample_data"]}
    for frame, (_, per) in zip(rig.frames, truth["scenes"]["scene-0061"]["keyframes"]):
        for ch in RING:
            cap = rig.capture(frame.id, ch)
            t = rows[per[ch]]["timestamp"]
            assert cap.timestamp_us == t and t - frame.timestamp_us == FIRE_US[ch] - FIRE_US["CAM_FRONT"]
            q, tr = ego_pose(t)
            np.testing.assert_allclose(cap.ego_to_world[:3, 3], tr, atol=1e-9)
            np.testing.assert_allclose(cap.camera_to_world, cap.ego_to_world @ rig.camera(ch).sensor_to_ego,
                                       atol=1e-12)
        # 5 m/s over the 40 ms between CAM_FRONT and CAM_FRONT_LEFT: 0.2 m of ego motion
        moved = rig.capture(frame.id, "CAM_FRONT_LEFT").ego_to_world[:3, 3] - frame.ego_to_world[:3, 3]
        assert abs(np.linalg.norm(moved) - 5.0 * 0.040) < 1e-3


def test_lidar_sweep_projects_at_each_cameras_own_capture(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    root, truth = dataset
    rig = load_rig(f"{root}::{VERSION}::scene-0061")
    frame = rig.frames[1]
    sweep = frame.lidar
    assert sweep is not None and sweep.fmt == "nuscenes_bin" and sweep.path.name.endswith(".pcd")
    assert sweep.timestamp_us == frame.timestamp_us - FIRE_US["CAM_FRONT"]  # the LiDAR fired first
    q, t = ego_pose(sweep.timestamp_us)
    np.testing.assert_allclose(sweep.ego_to_world[:3, 3], t, atol=1e-9)
    np.testing.assert_allclose(sweep.sensor_to_ego[:3, 3], [0.94, 0.0, 1.84], atol=1e-12)
    # world points 8-12 m in front of CAM_FRONT_LEFT at its capture, written in the LiDAR frame
    cap = rig.capture(frame, "CAM_FRONT_LEFT")
    rng = np.random.default_rng(3)
    cam_pts = np.stack([rng.uniform(-3, 3, 40), rng.uniform(-1, 1, 40), rng.uniform(8, 12, 40)], 1)
    world = cam_pts @ cap.camera_to_world[:3, :3].T + cap.camera_to_world[:3, 3]
    to_lidar = np.linalg.inv(sweep.lidar_to_world)
    lidar_pts = world @ to_lidar[:3, :3].T + to_lidar[:3, 3]
    raw = np.zeros((40, 5), np.float32)
    raw[:, :3] = lidar_pts
    sweep.path.parent.mkdir(parents=True, exist_ok=True)
    sweep.path.write_bytes(raw.tobytes())
    try:
        depth = rig.load_depth(frame.id, "CAM_FRONT_LEFT")
    finally:
        sweep.path.unlink()
    _, K, _ = truth["cameras"]["CAM_FRONT_LEFT"]
    K = np.array(K)
    uv = cam_pts @ K.T
    col, row = np.rint(uv[:, 0] / uv[:, 2]).astype(int), np.rint(uv[:, 1] / uv[:, 2]).astype(int)
    # every point on its own pixel at its depth (float32 file: 1e-4); ignoring the 52 ms between the LiDAR
    # and this camera (0.26 m of ego motion) would move them by far more than that
    np.testing.assert_allclose(depth[row, col], cam_pts[:, 2], rtol=1e-4)
    assert np.count_nonzero(depth) == 40


def test_tables_load_without_a_garbage_collection_and_the_collector_is_restored(dataset: tuple[Path, dict]) -> None:
    # each full collection walks every parsed row: on trainval's tables that was a third of the load (95 -> 68 s)
    import gc

    from sgde_plugin.readers.jsonio import paused_gc
    from sgde_plugin.readers.nuscenes import load_nuscenes

    root, _ = dataset
    starts: list[int] = []

    def count(phase: str, info: dict) -> None:
        if phase == "start":
            starts.append(info["generation"])

    gc.callbacks.append(count)
    try:
        gc.collect()
        starts.clear()
        rigs = load_nuscenes(root, VERSION, sweeps=True)
        assert not starts and gc.isenabled()
        junk = [[i] for i in range(10 * gc.get_threshold()[0])]  # the collector still runs afterwards
        assert starts and junk
        gc.disable()
        with paused_gc():
            pass
        assert not gc.isenabled()  # a caller's own pause is left as it was
        gc.enable()
        with pytest.raises(KeyError), paused_gc():
            raise KeyError("x")
        assert gc.isenabled()
    finally:
        gc.callbacks.remove(count)
        gc.enable()
    assert sum(len(r.frames) for r in rigs) > 10


def test_scan_table_parses_the_selected_rows_of_each_chunk_and_names_a_bad_one(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    import re

    from sgde_plugin.readers import jsonio

    monkeypatch.setattr(jsonio, "_CHUNK", 4096)  # many chunks, each starting inside a separator
    rows = [{"token": f"{i:032x}", "kind": "cam" if i % 3 else "radar", "v": i} for i in range(5000)]
    text = json.dumps(rows, indent=0)
    (tmp_path / "t.json").write_text(text)
    kind = (re.compile(r'"kind"\s*:\s*"([^"\\]*)"'), {"radar"}, False)
    kept = jsonio.scan_table(tmp_path / "t.json", lambda r: r["v"] if r["kind"] == "cam" else None, [kind])
    assert kept == [i for i in range(5000) if i % 3]
    assert jsonio.scan_table(tmp_path / "t.json", lambda r: r["v"]) == list(range(5000))
    for bad in (37, 4999):  # a kept row with a value that is not JSON, in the middle and last
        (tmp_path / "t.json").write_text(text.replace(f'"v": {bad}\n', f'"v": {bad}x\n'))
        with pytest.raises(InputError, match=rf"t.json: element {bad}: bad JSON"):
            jsonio.scan_table(tmp_path / "t.json", lambda r: r["v"], [kind])
