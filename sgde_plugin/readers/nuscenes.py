"""nuScenes v1.0 tables (read directly, no devkit) -> one `Rig` per scene.

Layout: `<root>/<version>/{scene,sample,sample_data,calibrated_sensor,sensor,ego_pose}.json` and the
images under `<root>/samples/...` and `<root>/sweeps/...` (paths in `sample_data.filename` are
relative to `<root>`). Quaternions are (w, x, y, z), timestamps microseconds, translations metres;
`calibrated_sensor` maps sensor -> ego and `ego_pose` maps ego -> world, both in the nuScenes ego
frame (x forward, y left, z up), which is ours. Images are undistorted pinholes (`dist` null).

Frames: one per keyframe (`sample`), with frame id = sample token; with `sweeps=True` also one per
12 Hz CAM_FRONT sweep (frame id = that sample_data token), the other cameras taking their sweep
nearest in time. Keyframes are identical in both modes. The frame's timestamp and `ego_to_world`
come from the CAM_FRONT sample_data; nuScenes stores one ego pose per sample_data timestamp and its
cameras fire one after another over ~50 ms, so every other camera keeps its own timestamp and ego pose
as its capture (`Frame.cameras`). Sweeps reuse the keyframe calibration (nuScenes calibrates per scene,
not per sweep). A frame's LiDAR sweep (`Frame.lidar`, for ground truth) is the sample's key LIDAR_TOP
sample_data, or for a 12 Hz frame the LIDAR_TOP sample_data nearest in time, with its own ego pose.

The big tables (`sample_data`, `ego_pose`: ~2.6M rows each in v1.0-trainval) are streamed: each row
is parsed, reduced to a small tuple (cameras only; keyframes only unless sweeps are asked for; only
the asked-for scenes) and the text is dropped, so the full trainval set loads in bounded memory.
"""

from __future__ import annotations

import re
from bisect import bisect_left
from collections import defaultdict
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..geometry import make_transform, quaternion_to_rotation
from ..io import image_size
from ..lidar import LidarSweep
from ..rig import CameraCapture, Frame, Rig, ring_pairs
from ..rigfile import intrinsics_from_dict
from .jsonio import QUATERNION_TOL, get, number_list, paused_gc, read_json, scan_table, unit_quaternion

RING = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
REFERENCE = "CAM_FRONT"  # the camera whose timestamp and ego pose a frame takes
LIDAR = "LIDAR_TOP"  # its sweeps (.pcd.bin) become the depth ground truth
TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose")

# kept per camera sample_data row (a plain tuple: ~1.2M of them for trainval with sweeps)
_TOKEN, _SAMPLE, _EGO, _CHANNEL, _CALIB, _TIME, _KEY, _FILE, _SIZE = range(9)
# cheap look-ups in a row's text, so rows we do not keep are never parsed (see jsonio.scan_table)
_CALIB_RE = re.compile(r'"calibrated_sensor_token"\s*:\s*"([^"\\]*)"')
_SAMPLE_RE = re.compile(r'"sample_token"\s*:\s*"([^"\\]*)"')
_KEY_RE = re.compile(r'"is_key_frame"\s*:\s*(true|false)')
_TOKEN_RE = re.compile(r'"token"\s*:\s*"([^"\\]*)"')


def is_tables_folder(folder: Path) -> bool:
    """True if `folder` holds nuScenes tables (scene.json and sample_data.json)."""
    return (folder / "scene.json").is_file() and (folder / "sample_data.json").is_file()


def versions(root: Path) -> list[str]:
    """Table folders (versions such as v1.0-mini) directly under a nuScenes root, sorted."""
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and is_tables_folder(p))


def scene_table(root: Path, version: str) -> list[tuple[str, str]]:
    """(name, token) of every scene of one version, in table order (reads scene.json only)."""
    path = root / version / "scene.json"
    return [(get(row, "name", path, f"[{i}]", str), get(row, "token", path, f"[{i}]", str))
            for i, row in enumerate(_rows(path))]


def _rows(path: Path) -> list[dict]:
    doc = read_json(path)
    if not isinstance(doc, list) or not all(isinstance(r, dict) for r in doc):
        raise InputError(path, None, "expected a JSON array of objects")
    return doc


def _pose(row: dict, file: Path, where: str) -> np.ndarray:
    """4x4 transform from a row's `rotation` (w, x, y, z) and `translation`."""
    q = unit_quaternion(number_list(row, "rotation", 4, file, where), file, where)
    return make_transform(quaternion_to_rotation(q), number_list(row, "translation", 3, file, where))


def _poses(rows: list[tuple[str, dict]], file: Path) -> dict[str, np.ndarray]:
    """token -> 4x4 of many pose rows, checked at once (row by row only to name a bad one)."""
    try:
        q = np.array([r["rotation"] for _, r in rows], dtype=np.float64)
        t = np.array([r["translation"] for _, r in rows], dtype=np.float64)
        ok = q.shape == (len(rows), 4) and t.shape == (len(rows), 3)
        ok = ok and bool(np.isfinite(q).all() and np.isfinite(t).all())
        ok = ok and bool(np.abs(q).max(initial=0.0) <= 2.0)  # larger entries: no unit q, and squares may overflow
        ok = ok and bool((np.abs(np.linalg.norm(q, axis=1) - 1.0) <= QUATERNION_TOL).all())
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        for token, row in rows:
            _pose(row, file, f"[token={token}]")
    T = make_transform(quaternion_to_rotation(q), t) if rows else np.zeros((0, 4, 4))
    return {token: T[i] for i, (token, _) in enumerate(rows)}


@dataclass
class _Scene:
    token: str
    name: str
    samples: list[tuple[int, str]] = field(default_factory=list)  # (timestamp, sample token)


class NuScenesTables:
    """The nuScenes tables of one version, indexed by token once; `rig(scene)` builds a scene's Rig."""

    def __init__(self, root: str | Path, version: str, scenes: Collection[str] | None = None,
                 sweeps: bool = False):
        """Load `<root>/<version>`; `scenes` (names or tokens) restricts what is kept, `sweeps` adds 12 Hz frames."""
        self.root = Path(root)
        self.version = version
        self.sweeps = sweeps
        self.dir = self.root / version
        if not is_tables_folder(self.dir):
            raise InputError(self.dir, None, "not a nuScenes table folder (no scene.json / sample_data.json)")
        for name in TABLES:
            if not (self.dir / f"{name}.json").is_file():
                raise InputError(self.dir / f"{name}.json", None, "file not found (a nuScenes table)")
        with paused_gc():
            self._load_scenes(scenes)
            self._load_samples()
            self._load_calibration()
            self._load_sample_data()
            self._load_ego_poses()
        self._mounts: dict[str, np.ndarray] = {}  # LiDAR calibration token -> sensor_to_ego

    # --- tables ------------------------------------------------------------------------------
    def _load_scenes(self, wanted: Collection[str] | None) -> None:
        path = self.dir / "scene.json"
        self._scenes: dict[str, _Scene] = {}
        for i, row in enumerate(_rows(path)):
            token = get(row, "token", path, f"[{i}]", str)
            self._scenes[token] = _Scene(token, get(row, "name", path, f"[{i}]", str))
        if wanted is not None:
            by_key = {s.name: s for s in self._scenes.values()} | self._scenes
            missing = [w for w in wanted if w not in by_key]
            if missing:
                names = [s.name for s in self._scenes.values()]
                some = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
                raise InputError(path, "name", f"no scene {missing[0]!r} ({len(names)} scenes: {some})")
            keep = {by_key[w].token for w in wanted}
            self._scenes = {t: s for t, s in self._scenes.items() if t in keep}

    def _load_samples(self) -> None:
        path = self.dir / "sample.json"
        self._sample_scene: dict[str, str | None] = {}  # every sample token -> its scene if kept, else None
        for i, row in enumerate(_rows(path)):
            token = get(row, "token", path, f"[{i}]", str)
            scene_token = get(row, "scene_token", path, f"[token={token}]", str)
            scene = self._scenes.get(scene_token)
            self._sample_scene[token] = scene.token if scene else None
            if scene is not None:
                scene.samples.append((get(row, "timestamp", path, f"[token={token}]", int), token))
        for scene in self._scenes.values():
            scene.samples.sort()

    def _load_calibration(self) -> None:
        sensors_path = self.dir / "sensor.json"
        channel_of: dict[str, str] = {}
        for i, row in enumerate(_rows(sensors_path)):
            token = get(row, "token", sensors_path, f"[{i}]", str)
            channel_of[token] = get(row, "channel", sensors_path, f"[token={token}]", str)
        missing = [c for c in RING if c not in channel_of.values()]
        if missing:
            raise InputError(sensors_path, "channel", f"camera {missing[0]} is missing")
        path = self.dir / "calibrated_sensor.json"
        self._calib_rows: dict[str, dict] = {}
        self._calib_channel: dict[str, str | None] = {}  # every calibration token -> ring camera or None
        for i, row in enumerate(_rows(path)):
            token = get(row, "token", path, f"[{i}]", str)
            sensor = get(row, "sensor_token", path, f"[token={token}]", str)
            if sensor not in channel_of:
                raise InputError(path, f"[token={token}].sensor_token", f"unknown sensor {sensor!r}")
            channel = channel_of[sensor]
            self._calib_channel[token] = channel if channel in RING or channel == LIDAR else None
            if channel in RING or channel == LIDAR:
                self._calib_rows[token] = row
        self._channels = {c: c for c in (*RING, LIDAR)}  # one shared string object per channel

    def _load_sample_data(self) -> None:
        path = self.dir / "sample_data.json"
        calib_channel, sample_scene, channels = self._calib_channel, self._sample_scene, self._channels
        keyframes_only = not self.sweeps
        sizes: dict[tuple[int, int], tuple[int, int]] = {}
        shared_calib = {t: t for t in calib_channel}

        # rows `reduce` would drop, recognised without parsing them (other scenes, sweeps, non-camera sensors); the
        # other scenes first: when some scenes are chosen it drops nearly every row, and the later selections then
        # test the few rows left one by one instead of the whole chunk (all scenes: an empty set, no scan)
        select = [(_SAMPLE_RE, {t for t, sc in sample_scene.items() if sc is None}, False),
                  (_CALIB_RE, {t for t, c in calib_channel.items() if c is None}, False)]
        if keyframes_only:
            select.insert(1, (_KEY_RE, {"false"}, False))

        def reduce(row: dict) -> tuple | None:
            try:
                calib = row["calibrated_sensor_token"]
                channel = calib_channel[calib]
                if channel is None:
                    return None
                key = row["is_key_frame"]
                if keyframes_only and key is not True:
                    return None
                sample = row["sample_token"]
                if sample_scene[sample] is None:
                    return None
                ts, w, h, filename = row["timestamp"], row["width"], row["height"], row["filename"]
                out = (row["token"], sample, row["ego_pose_token"], channels[channel], shared_calib[calib],
                       ts, key, filename, sizes.setdefault((w, h), (w, h)))
            except (KeyError, TypeError) as exc:
                raise _row_error(path, row, exc) from None
            if type(ts) is not int or type(w) is not int or type(h) is not int or type(filename) is not str:
                raise InputError(path, f"[token={row['token']}]", "timestamp/width/height/filename has the wrong type")
            if type(out[0]) is not str or type(out[2]) is not str:
                raise InputError(path, f"[token={row['token']}]", "token/ego_pose_token has the wrong type")
            return out

        self._rows_by_scene: dict[str, list[tuple]] = defaultdict(list)
        for item in scan_table(path, reduce, select):
            self._rows_by_scene[sample_scene[item[_SAMPLE]]].append(item)

    def _load_ego_poses(self) -> None:
        path = self.dir / "ego_pose.json"
        needed: set[str] = set()
        for rows in self._rows_by_scene.values():
            needed.update(r[_EGO] for r in rows)

        def reduce(row: dict) -> tuple | None:
            token = row.get("token")
            if type(token) is not str:
                raise InputError(path, "token", f"{token!r} is not a string")
            return (token, row) if token in needed else None

        rows = scan_table(path, reduce, [(_TOKEN_RE, needed, True)])
        self._ego: dict[str, np.ndarray] = _poses(rows, path)

    # --- rigs --------------------------------------------------------------------------------
    def scene_names(self) -> list[str]:
        """Names of the loaded scenes, in table order."""
        return [s.name for s in self._scenes.values()]

    def rig(self, scene: str, check_images: bool = False) -> Rig:
        """The Rig of one loaded scene (name or token); `check_images` checks every file and size."""
        with paused_gc():
            return _SceneRig(self, self._find_scene(scene), check_images).build()

    def _find_scene(self, scene: str) -> _Scene:
        """The loaded scene with this name or token."""
        found = [s for s in self._scenes.values() if scene in (s.name, s.token)]
        if not found:
            raise InputError(self.dir / "scene.json", "name", f"no scene {scene!r} loaded")
        return found[0]


class _SceneRig:
    """One scene's Rig assembled from the indexed tables (`NuScenesTables.rig`)."""

    def __init__(self, tables: NuScenesTables, scene: _Scene, check_images: bool):
        self.tables, self.sc, self.check_images = tables, scene, check_images
        self.dir, self.root = tables.dir, tables.root

    def build(self) -> Rig:
        """The scene's Rig: cameras, key frames (or 12 Hz frames), per-camera captures, LiDAR sweeps."""
        sc, check_images = self.sc, self.check_images
        rows = self.tables._rows_by_scene.get(sc.token, [])
        by_channel: dict[str, list[tuple]] = {c: [] for c in (*RING, LIDAR)}
        for r in rows:
            by_channel[r[_CHANNEL]].append(r)
        cameras = self._cameras(by_channel)
        key_rows = {(r[_SAMPLE], r[_CHANNEL]): r for r in rows if r[_KEY] is True}
        keyframe_of = self._key_frames(key_rows)
        frames = _sweep_frames(by_channel, keyframe_of) if self.tables.sweeps else list(keyframe_of.values())
        lidar_rows = sorted(by_channel[LIDAR], key=lambda r: r[_TIME])
        lidar_times = [r[_TIME] for r in lidar_rows]

        def lidar_of(fid: str, chosen: dict[str, tuple]) -> tuple | None:
            """The sample's key LiDAR sweep; for a 12 Hz frame the LiDAR sweep nearest in time."""
            row = key_rows.get((fid, LIDAR))
            if row is None and lidar_rows:
                row = _nearest(lidar_rows, lidar_times, chosen[REFERENCE][_TIME])
            return row

        return Rig(
            tuple(cameras), ring_pairs(RING),
            tuple(self._frame(fid, ch, check_images, cameras, lidar_of(fid, ch)) for fid, ch in frames),
            RING, self.root, extra={"scene": sc.name},
        )

    def _cameras(self, by_channel: dict[str, list[tuple]]) -> list[Camera]:
        """One Camera per ring channel (its rows are sorted by time in place)."""
        sc = self.sc
        data_path = self.dir / "sample_data.json"
        cameras = []
        for channel in RING:
            chan_rows = by_channel[channel]
            if not chan_rows:
                raise InputError(data_path, f"scene {sc.name}", f"camera {channel} is missing (no key frames)")
            cameras.append(self._camera(channel, chan_rows))
            chan_rows.sort(key=lambda r: r[_TIME])
        return cameras

    def _key_frames(self, key_rows: dict[tuple[str, str], tuple]) -> dict[str, tuple[str, dict[str, tuple]]]:
        """CAM_FRONT token -> (sample token, key row of each ring camera), in sample order."""
        sc = self.sc
        if not sc.samples:
            raise InputError(self.dir / "sample.json", f"scene {sc.name}", "has no samples")
        data_path = self.dir / "sample_data.json"
        keyframe_of: dict[str, tuple[str, dict[str, tuple]]] = {}
        for _, sample in sc.samples:
            chosen = {}
            for channel in RING:
                r = key_rows.get((sample, channel))
                if r is None:
                    raise InputError(data_path, f"sample {sample}", f"camera {channel} is missing (no key frame)")
                chosen[channel] = r
            keyframe_of[chosen[REFERENCE][_TOKEN]] = (sample, chosen)
        return keyframe_of

    def _camera(self, channel: str, rows: list[tuple]) -> Camera:
        """The pinhole camera of one channel: its one calibration and image size in this scene."""
        sc = self.sc
        calibs = {r[_CALIB] for r in rows}
        sizes = {r[_SIZE] for r in rows}
        data_path = self.dir / "sample_data.json"
        if len(calibs) != 1:
            raise InputError(data_path, f"scene {sc.name}", f"{channel} uses {len(calibs)} calibrations (expected 1)")
        if len(sizes) != 1:
            raise InputError(data_path, f"scene {sc.name}", f"{channel} images have {len(sizes)} different sizes")
        token = calibs.pop()
        (w, h), = sizes
        path = self.dir / "calibrated_sensor.json"
        row = self.tables._calib_rows[token]
        where = f"[token={token}]"
        entry = {"model": "pinhole", "width": w, "height": h, "K": get(row, "camera_intrinsic", path, where, list),
                 "dist": None}
        try:
            intrinsics = intrinsics_from_dict(entry, where)
        except InputError as exc:
            key = exc.key.replace(f"{where}.K", f"{where}.camera_intrinsic") if exc.key else exc.key
            raise InputError(path, key, exc.problem) from None
        return Camera(channel, intrinsics, _pose(row, path, where))

    def _ego_pose(self, row: tuple) -> np.ndarray:
        """The ego pose of a sample_data row."""
        pose = self.tables._ego.get(row[_EGO])
        if pose is None:
            raise InputError(self.dir / "ego_pose.json", f"token {row[_EGO]}",
                             f"missing (referenced by sample_data {row[_TOKEN]})")
        return pose

    def _lidar(self, row: tuple | None) -> LidarSweep | None:
        """A LIDAR_TOP sample_data row as a sweep: its file, mount, ego pose and time."""
        if row is None:
            return None
        mounts = self.tables._mounts
        mount = mounts.get(row[_CALIB])
        if mount is None:
            mount = _pose(self.tables._calib_rows[row[_CALIB]], self.dir / "calibrated_sensor.json",
                          f"[token={row[_CALIB]}]")
            mounts[row[_CALIB]] = mount
        return LidarSweep(self.root / row[_FILE], "nuscenes_bin", mount, self._ego_pose(row), row[_TIME])

    def _frame(self, frame_id: str, chosen: dict[str, tuple], check: bool, cameras: list[Camera],
               lidar: tuple | None = None) -> Frame:
        """One frame: the reference camera's time and pose, the other cameras' captures, images, LiDAR."""
        ref = chosen[REFERENCE]
        pose = self._ego_pose(ref)
        captures = {c: CameraCapture(None if r[_TIME] == ref[_TIME] else r[_TIME],
                                     None if r[_EGO] == ref[_EGO] else self._ego_pose(r))
                    for c, r in chosen.items() if r[_TIME] != ref[_TIME] or r[_EGO] != ref[_EGO]}
        images = _Files(self.root, {c: r[_FILE] for c, r in chosen.items()})
        if check:
            for cam in cameras:
                path, r = images[cam.name], chosen[cam.name]
                if not path.is_file():
                    raise InputError(self.dir / "sample_data.json", f"[token={r[_TOKEN]}].filename",
                                     f"points at a missing file {path}")
                if image_size(path) != (cam.width, cam.height):
                    w, h = image_size(path)
                    raise InputError(path, "size", f"image is {w}x{h}, sample_data says {cam.width}x{cam.height}")
        return Frame(frame_id, ref[_TIME], pose, images, cameras=captures, lidar=self._lidar(lidar))


def _sweep_frames(by_channel: dict[str, list[tuple]], keyframe_of: dict[str, tuple[str, dict[str, tuple]]]
                  ) -> list[tuple[str, dict[str, tuple]]]:
    """12 Hz frames: every CAM_FRONT row (key frames as they are; others with each camera's nearest row)."""
    frames = []
    times = {c: [r[_TIME] for r in by_channel[c]] for c in RING}
    for r in by_channel[REFERENCE]:
        if r[_TOKEN] in keyframe_of:
            frames.append(keyframe_of[r[_TOKEN]])
        elif r[_KEY] is not True:
            frames.append((r[_TOKEN], {c: _nearest(by_channel[c], times[c], r[_TIME]) for c in RING}))
    return frames


class _Files(Mapping):
    """camera -> image Path, built on access (a trainval rig with sweeps has ~1M of them)."""

    def __init__(self, root: Path, names: dict[str, str]):
        self._root, self._names = root, names

    def __getitem__(self, camera: str) -> Path:
        return self._root / self._names[camera]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


def _nearest(rows: list[tuple], times: list[int], t: int) -> tuple:
    i = bisect_left(times, t)
    if i == 0:
        return rows[0]
    if i == len(rows):
        return rows[-1]
    return rows[i] if times[i] - t < t - times[i - 1] else rows[i - 1]


def _row_error(path: Path, row: dict, exc: Exception) -> InputError:
    """A missing column, a token of the wrong type or a token that points nowhere, named by the row's token."""
    where = f"[token={row.get('token', '?')}]"
    for column in ("token", "calibrated_sensor_token", "is_key_frame", "sample_token", "timestamp", "width",
                   "height", "filename", "ego_pose_token"):
        if column not in row:
            return InputError(path, f"{where}.{column}", "missing")
    if not isinstance(exc, KeyError):
        return InputError(path, where, "a token or size column has the wrong type")
    key = exc.args[0]
    column = "calibrated_sensor_token" if row.get("calibrated_sensor_token") == key else "sample_token"
    table = "calibrated_sensor" if column == "calibrated_sensor_token" else "sample"
    return InputError(path, f"{where}.{column}", f"points at no {table} row ({key!r})")


def load_nuscenes(root: str | Path, version: str, scene: str | None = None, sweeps: bool = False,
                  check_images: bool = False) -> list[Rig]:
    """Rigs of one scene (name or token) or of every scene of a nuScenes version."""
    with paused_gc():
        tables = NuScenesTables(root, version, None if scene is None else [scene], sweeps)
        return [tables.rig(name, check_images) for name in tables.scene_names()]


__all__ = ["RING", "NuScenesTables", "is_tables_folder", "load_nuscenes", "scene_table", "versions"]
