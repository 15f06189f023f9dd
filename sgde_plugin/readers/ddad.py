"""DDAD in the DGP layout -> one `Rig` per scene folder.

Schema (TRI-ML/dgp, `dgp/proto/{scene,sample,image,geometry,identifiers}.proto`, written as JSON by
`dgp.utils.protobuf.save_pbobject_as_json` with the proto field names):

- `<scene>/scene_<sha1>.json`: a `Scene` with `samples` (each: `id` {log, name, timestamp, index},
  `datum_keys`, `calibration_key`) and `data` (each `Datum`: `id` {name e.g. "CAMERA_01", timestamp},
  `key`, `datum` {`image` {filename, height, width, channels, pose}}). Timestamps are protobuf JSON
  Timestamps (RFC 3339 strings). `image.pose` is the camera's pose in the scene's world frame at the
  image time (DGP's `pose_WC`; an all-zero quaternion means identity).
- `<scene>/calibration/<calibration_key>.json`: a `SampleCalibration` with parallel lists `names`,
  `intrinsics` (`CameraIntrinsics`: fx, fy, cx, cy, skew, and k1..k6, p1, p2, fisheye, ...) and
  `extrinsics` (`Pose`: `translation` {x, y, z}, `rotation` {qx, qy, qz, qw}), the sensor's pose in the
  vehicle frame (DGP's `pose_VS`).
- Images `rgb/CAMERA_xx/<timestamp>.png` (the path comes from `image.filename`).

Vehicle frame x forward, y left, z up and camera frame x right, y down, z forward, as ours. DGP's
JSON parser also accepts lowerCamelCase names (`datumKeys`), so we do too. Frame ids are the sample's
position in the scene ("000000"...); a frame's timestamp and ego pose come from the reference camera
(CAMERA_01, else the first ring camera present): ego_to_world = pose_WC(ref) @ inverse(pose_VC(ref)).
Every other camera keeps its own datum's time and pose as its capture (`Frame.cameras`,
ego_to_world(c) = pose_WC(c) @ inverse(pose_VC(c))): DDAD's cameras are synchronised, but its per-datum
poses differ by a few millimetres. DDAD images are undistorted; non-zero k1, k2, p1, p2, k3 become an
OpenCV `dist`, a fisheye calibration is refused.

Partial rigs: a scene with only some of the six cameras (the front three, say) loads with the ring
cameras its first sample has; its pairs are the adjacent ring pairs among them (`pairs`, no closed
`ring`, unless all six are there). Every later sample must have the same cameras.
"""

from __future__ import annotations

import calendar
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..geometry import invert_transform, make_transform, quaternion_to_rotation
from ..io import image_size
from ..lidar import LidarSweep
from ..rig import Frame, Rig, own_captures, ring_pairs, ring_subset_pairs
from ..rigfile import MAX_MOUNT_M, MAX_WORLD_M, check_translation, intrinsics_from_dict
from .jsonio import get, read_json, unit_quaternion

RING = ("CAMERA_01", "CAMERA_06", "CAMERA_08", "CAMERA_09", "CAMERA_07", "CAMERA_05")
REFERENCE = "CAMERA_01"
LIDAR = "LIDAR"

_RFC3339 = re.compile(
    r"^(\d{4})-(\d{2})-(\d{2})[Tt ](\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?([Zz]|[+-]\d{2}:\d{2})$"
)


def scene_files(folder: Path) -> list[Path]:
    """`scene_*.json` files directly in a folder, sorted."""
    return sorted(folder.glob("scene_*.json")) if folder.is_dir() else []


def is_scene_folder(folder: Path) -> bool:
    """True if `folder` holds a DGP scene JSON."""
    return bool(scene_files(folder))


def scene_folders(root: Path) -> list[Path]:
    """Scene folders directly under a DDAD root (sorted by name)."""
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and is_scene_folder(p))


def parse_timestamp_us(value: object, file: Path, key: str) -> int:
    """Microseconds since the epoch of a protobuf JSON Timestamp (RFC 3339, Z or offset)."""
    m = _RFC3339.match(value) if isinstance(value, str) else None
    if m is None:
        raise InputError(file, key, f"not an RFC 3339 timestamp ({value!r})")
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    frac, zone = m.group(7) or "", m.group(8)
    seconds = calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0))
    if zone not in ("Z", "z"):
        sign = 1 if zone[0] == "+" else -1
        seconds -= sign * (int(zone[1:3]) * 3600 + int(zone[4:6]) * 60)
    return seconds * 1_000_000 + int((frac + "000000")[:6])


def _field(row: dict, name: str, file: Path, where: str, kinds=None, default=...):
    camel = re.sub(r"_([a-z])", lambda m: m.group(1).upper(), name)
    return get(row, name, file, where, kinds, alt=camel if camel != name else None, default=default)


def _num(row: dict, name: str, file: Path, where: str, default: float | None = 0.0) -> float:
    value = _field(row, name, file, where, (int, float), default=... if default is None else default)
    if not np.isfinite(value):
        raise InputError(file, f"{where}.{name}", "not finite")
    return float(value)


def _pose(row: object, file: Path, where: str, zero_is_identity: bool = False, max_m: float = MAX_WORLD_M
          ) -> np.ndarray:
    """4x4 transform of a DGP `Pose` (translation {x, y, z} within `max_m`, rotation {qx, qy, qz, qw})."""
    if not isinstance(row, dict):
        raise InputError(file, where, "not a pose object")
    t = _field(row, "translation", file, where, dict, default={})
    r = _field(row, "rotation", file, where, dict, default={})
    trans = [_num(t, k, file, f"{where}.translation") for k in ("x", "y", "z")]
    check_translation(np.array(trans), file, f"{where}.translation", max_m)
    q = np.array([_num(r, k, file, f"{where}.rotation") for k in ("qw", "qx", "qy", "qz")])
    q = unit_quaternion(q, file, where, zero_is_identity)
    return make_transform(quaternion_to_rotation(q), trans)


def _intrinsics(row: object, width: int, height: int, file: Path, where: str):
    if not isinstance(row, dict):
        raise InputError(file, where, "not an intrinsics object")
    fx, fy, cx, cy = (_num(row, k, file, where, default=None) for k in ("fx", "fy", "cx", "cy"))
    skew = _num(row, "skew", file, where)
    if _num(row, "fisheye", file, where) != 0:
        raise InputError(file, f"{where}.fisheye", "fisheye DGP calibrations are not supported")
    for k in ("k4", "k5", "k6"):
        if _num(row, k, file, where) != 0:
            raise InputError(file, f"{where}.{k}", "rational distortion (k4..k6) is not supported")
    dist = [_num(row, k, file, where) for k in ("k1", "k2", "p1", "p2", "k3")]
    entry = {"model": "pinhole", "width": width, "height": height,
             "K": [[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], "dist": dist if any(dist) else None}
    try:
        return intrinsics_from_dict(entry, where)
    except InputError as exc:
        raise InputError(file, exc.key, exc.problem) from None


def _scene_file(folder: Path) -> Path:
    """The scene JSON of a folder; with several, the newest `creation_date` (as DGP does)."""
    files = scene_files(folder)
    if not files:
        raise InputError(folder, None, "no scene_*.json (not a DDAD / DGP scene folder)")
    if len(files) == 1:
        return files[0]
    dated = []
    for f in files:
        doc = read_json(f)
        date = doc.get("creation_date", doc.get("creationDate", "")) if isinstance(doc, dict) else ""
        dated.append((parse_timestamp_us(date, f, "creation_date") if date else -1, f.name, f))
    return max(dated)[2]


Keyed = tuple[str, dict]  # (datum key, datum) of one sensor in one sample


@dataclass(frozen=True)
class _Samples:
    """Stage 1 of `load_ddad_scene`: per sample, the ring cameras' and LiDAR's datums; the cameras present."""

    frames: list[dict[str, Keyed]]
    present: tuple[str, ...]
    calibration_key: str


@dataclass(frozen=True)
class _Calibration:
    """Stage 2 of `load_ddad_scene`: the present cameras (intrinsics, mounts) and the LiDAR mount."""

    cameras: tuple[Camera, ...]
    lidar_mount: np.ndarray | None


def _datums_by_key(data: list, scene_path: Path) -> dict[str, dict]:
    """The scene's `data` list keyed by datum key."""
    datums: dict[str, dict] = {}
    for i, d in enumerate(data):
        if not isinstance(d, dict):
            raise InputError(scene_path, f"data[{i}]", "not an object")
        datums[_field(d, "key", scene_path, f"data[{i}]", str)] = d
    return datums


def _sample_sensors(s: dict, datums: dict[str, dict], scene_path: Path, where: str) -> dict[str, Keyed]:
    """The ring cameras' and LiDAR's datums of one sample, by upper-case sensor name."""
    by_name: dict[str, Keyed] = {}
    for key in _field(s, "datum_keys", scene_path, where, list):
        if not isinstance(key, str):
            raise InputError(scene_path, f"{where}.datum_keys", f"key {key!r} is not a string")
        d = datums.get(key)
        if d is None:
            raise InputError(scene_path, f"{where}.datum_keys", f"key {key!r} is not in data")
        name = _field(_field(d, "id", scene_path, f"data[key={key}]", dict), "name", scene_path,
                      f"data[key={key}].id", str).upper()
        if name in RING or name == LIDAR:
            by_name[name] = (key, d)
    return by_name


def _read_samples(doc: dict, scene_path: Path) -> _Samples:
    """Stage 1: every sample's sensors; the first sample fixes the cameras, which every sample must hold."""
    samples = _field(doc, "samples", scene_path, "scene", list)
    data = _field(doc, "data", scene_path, "scene", list)
    if not samples:
        raise InputError(scene_path, "samples", "empty")
    datums = _datums_by_key(data, scene_path)
    calib_keys = set()
    frames_datums: list[dict[str, Keyed]] = []
    present: tuple[str, ...] = ()
    for i, s in enumerate(samples):
        where = f"samples[{i}]"
        if not isinstance(s, dict):
            raise InputError(scene_path, where, "not an object")
        calib_keys.add(_field(s, "calibration_key", scene_path, where, str))
        by_name = _sample_sensors(s, datums, scene_path, where)
        if not frames_datums:
            present = tuple(c for c in RING if c in by_name)
            if not ring_subset_pairs(RING, present):
                raise InputError(scene_path, where, f"has no two adjacent ring cameras ({', '.join(present)})")
        for cam in present:
            if cam not in by_name:
                raise InputError(scene_path, where, f"camera {cam} is missing")
        frames_datums.append(by_name)
    if len(calib_keys) != 1:
        raise InputError(scene_path, "samples[].calibration_key", f"{len(calib_keys)} calibrations (expected 1)")
    return _Samples(frames_datums, present, calib_keys.pop())


def _read_calibration(folder: Path, samples: _Samples, scene_path: Path) -> _Calibration:
    """Stage 2: `calibration/<key>.json` -> the present cameras (size from the first sample) and LiDAR mount."""
    calib_path = folder / "calibration" / f"{samples.calibration_key}.json"
    calib = read_json(calib_path)
    if not isinstance(calib, dict):
        raise InputError(calib_path, None, "top level is not a JSON object")
    names = _field(calib, "names", calib_path, "calibration", list)
    intr = _field(calib, "intrinsics", calib_path, "calibration", list)
    extr = _field(calib, "extrinsics", calib_path, "calibration", list)
    if not (len(names) == len(intr) == len(extr)):
        raise InputError(calib_path, "names/intrinsics/extrinsics", "lists have different lengths")
    index = {str(n).upper(): i for i, n in enumerate(names)}

    cameras = []
    first = samples.frames[0]
    for cam in samples.present:
        if cam not in index:
            raise InputError(calib_path, "names", f"camera {cam} is missing")
        i = index[cam]
        key, d = first[cam]
        image = _image(d, scene_path, key)
        w = _field(image, "width", scene_path, f"data[key={key}].datum.image", int)
        h = _field(image, "height", scene_path, f"data[key={key}].datum.image", int)
        K = _intrinsics(intr[i], w, h, calib_path, f"intrinsics[{i}]")
        cameras.append(Camera(cam, K, _pose(extr[i], calib_path, f"extrinsics[{i}]", max_m=MAX_MOUNT_M)))
    lidar_mount = (_pose(extr[index[LIDAR]], calib_path, f"extrinsics[{index[LIDAR]}]", max_m=MAX_MOUNT_M)
                   if LIDAR in index else None)
    return _Calibration(tuple(cameras), lidar_mount)


def _frame_images(by_name: dict[str, Keyed], cameras: tuple[Camera, ...], folder: Path, scene_path: Path,
                  check_images: bool) -> dict[str, Path]:
    """The image path of each camera in one sample (size and file checked with `check_images`)."""
    images = {}
    for cam in cameras:
        key, d = by_name[cam.name]
        image = _image(d, scene_path, key)
        where = f"data[key={key}].datum.image"
        filename = _field(image, "filename", scene_path, where, str)
        images[cam.name] = folder / filename
        if check_images:
            size = (_field(image, "width", scene_path, where, int), _field(image, "height", scene_path, where, int))
            if size != (cam.width, cam.height):
                raise InputError(scene_path, where, f"size {size[0]}x{size[1]} differs from the scene's first "
                                 f"sample ({cam.width}x{cam.height})")
            _check_image(images[cam.name], cam, scene_path, f"{where}.filename")
    return images


def load_ddad_scene(path: str | Path, check_images: bool = False) -> Rig:
    """One DDAD scene (a folder with scene_<sha1>.json, or that file) as a Rig."""
    path = Path(path)
    scene_path = path if path.is_file() else _scene_file(path)
    folder = scene_path.parent
    doc = read_json(scene_path)
    if not isinstance(doc, dict):
        raise InputError(scene_path, None, "top level is not a JSON object")
    samples = _read_samples(doc, scene_path)
    calib = _read_calibration(folder, samples, scene_path)
    present = samples.present
    reference = REFERENCE if REFERENCE in present else present[0]
    frames = []
    for n, by_name in enumerate(samples.frames):  # stage 3: one Frame per sample, posed by the reference camera
        images = _frame_images(by_name, calib.cameras, folder, scene_path, check_images)
        captures = {cam.name: _capture(by_name[cam.name], cam, scene_path) for cam in calib.cameras}
        ts, ego_to_world = captures[reference]
        lidar = _lidar_sweep(by_name.get(LIDAR), calib.lidar_mount, folder, scene_path)
        frames.append(Frame(f"{n:06d}", ts, ego_to_world, images, cameras=own_captures(ts, ego_to_world, captures),
                            lidar=lidar))
    ring = RING if present == RING else None
    pairs = ring_pairs(RING) if ring else ring_subset_pairs(RING, present)
    return Rig(calib.cameras, pairs, tuple(frames), ring, folder, extra={"scene": folder.name})


def _lidar_sweep(keyed: Keyed | None, mount: np.ndarray | None, folder: Path, scene_path: Path
                 ) -> LidarSweep | None:
    """The sample's LIDAR datum as a sweep (file, mount, ego pose = pose_WL @ inverse(pose_VL), time)."""
    if keyed is None or mount is None:
        return None
    key, d = keyed
    where = f"data[key={key}]"
    cloud = _field(_field(d, "datum", scene_path, where, dict), "point_cloud", scene_path, f"{where}.datum", dict,
                   default=None)
    if cloud is None:
        return None
    where = f"{where}.datum.point_cloud"
    filename = _field(cloud, "filename", scene_path, where, str)
    raw_pose = _field(cloud, "pose", scene_path, where, dict, default=None)
    world_from_lidar = np.eye(4) if raw_pose is None else _pose(raw_pose, scene_path, f"{where}.pose",
                                                               zero_is_identity=True)
    ident = _field(d, "id", scene_path, f"data[key={key}]", dict)
    ts = parse_timestamp_us(_field(ident, "timestamp", scene_path, f"data[key={key}].id"), scene_path,
                            f"data[key={key}].id.timestamp")
    return LidarSweep(folder / filename, "dgp_npz", mount, world_from_lidar @ invert_transform(mount), ts)


def _capture(keyed: Keyed, cam: Camera, scene_path: Path) -> tuple[int, np.ndarray]:
    """(timestamp, ego_to_world) of one camera datum: its own time, pose_WC @ inverse(pose_VC)."""
    key, d = keyed
    ident = _field(d, "id", scene_path, f"data[key={key}]", dict)
    ts = parse_timestamp_us(_field(ident, "timestamp", scene_path, f"data[key={key}].id"), scene_path,
                            f"data[key={key}].id.timestamp")
    image = _image(d, scene_path, key)
    raw_pose = _field(image, "pose", scene_path, f"data[key={key}].datum.image", dict, default=None)
    if raw_pose is None:
        return ts, np.eye(4)
    world_from_cam = _pose(raw_pose, scene_path, f"data[key={key}].datum.image.pose", zero_is_identity=True)
    return ts, world_from_cam @ invert_transform(cam.sensor_to_ego)


def _image(d: dict, file: Path, key: str) -> dict:
    datum = _field(d, "datum", file, f"data[key={key}]", dict)
    return _field(datum, "image", file, f"data[key={key}].datum", dict)


def _check_image(path: Path, cam: Camera, file: Path, key: str) -> None:
    if not path.is_file():
        raise InputError(file, key, f"points at a missing file {path}")
    w, h = image_size(path)
    if (w, h) != (cam.width, cam.height):
        raise InputError(path, "size", f"image is {w}x{h}, camera {cam.name} is {cam.width}x{cam.height}")


__all__ = ["RING", "is_scene_folder", "load_ddad_scene", "parse_timestamp_us", "scene_files", "scene_folders"]
