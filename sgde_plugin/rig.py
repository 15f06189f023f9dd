"""The `Rig` (cameras, extrinsics, adjacent pairs, frames) and the `sgde-rig/1` folder format."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .cameras import Camera, CameraModel
from .errors import InputError
from .geometry import invert_transform
from .io import (
    atomic_write_text,
    check_pixel_format,
    image_header,
    is_plain_name,
    read_depth_png,
    read_image,
    read_mask,
)
from .lidar import LidarDepthConfig, LidarSweep, sweep_depth
from .panorama import load_panorama_depth
from .rigfile import MAX_MOUNT_M, intrinsics_from_dict, transform_field

FORMAT = "sgde-rig/1"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True, eq=False)
class CameraCapture:
    """One camera's own capture in a frame (`frames[].cameras.<name>`); None = take the frame's value."""

    timestamp_us: int | None = None
    ego_to_world: np.ndarray | None = None

    def to_dict(self) -> dict[str, Any]:
        """The `rig.json` entry: only the keys that are set."""
        out: dict[str, Any] = {}
        if self.timestamp_us is not None:
            out["timestamp_us"] = int(self.timestamp_us)
        if self.ego_to_world is not None:
            out["ego_to_world"] = np.asarray(self.ego_to_world, dtype=np.float64).tolist()
        return out


def own_captures(timestamp_us: int, ego_to_world: np.ndarray,
                 per_camera: Mapping[str, tuple[int, np.ndarray]]) -> dict[str, CameraCapture]:
    """`Frame.cameras` from every camera's (time, ego pose): only what differs from the frame's own values."""
    out = {}
    for name, (ts, pose) in per_camera.items():
        same_pose = np.array_equal(np.asarray(pose, dtype=np.float64), np.asarray(ego_to_world, dtype=np.float64))
        cap = CameraCapture(None if ts == timestamp_us else int(ts), None if same_pose else np.asarray(pose, float))
        if cap.timestamp_us is not None or cap.ego_to_world is not None:
            out[name] = cap
    return out


@dataclass(frozen=True, eq=False)
class Capture:
    """Where and when one camera took its image of a frame: time, ego pose then, camera pose in the world."""

    timestamp_us: int
    ego_to_world: np.ndarray  # the ego pose at this camera's capture time
    camera_to_world: np.ndarray  # ego_to_world @ sensor_to_ego: camera coordinates -> world


@dataclass(frozen=True, eq=False)
class Frame:
    """One time step: id, timestamp (microseconds), ego pose, per-camera captures, and its files (not compared).

    `cameras` holds the cameras whose capture time or ego pose differ from the frame's (sequential
    capture, as on nuScenes); a camera without an entry was taken at the frame's time and pose.
    """

    id: str
    timestamp_us: int
    ego_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    images: Mapping[str, Path] = field(default_factory=dict)
    depths: Mapping[str, Path] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)
    cameras: Mapping[str, CameraCapture] = field(default_factory=dict)
    lidar: LidarSweep | None = None  # the LiDAR sweep a reader found for ground truth; not serialised

    def capture_time_us(self, camera: str) -> int:
        """The time camera `camera` took its image of this frame (the frame's time unless given)."""
        cap = self.cameras.get(camera)
        return int(self.timestamp_us if cap is None or cap.timestamp_us is None else cap.timestamp_us)

    def capture_ego_to_world(self, camera: str) -> np.ndarray:
        """The ego pose when camera `camera` took its image of this frame (the frame's pose unless given)."""
        cap = self.cameras.get(camera)
        return np.asarray(self.ego_to_world if cap is None or cap.ego_to_world is None else cap.ego_to_world,
                          dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """The frame's `rig.json` entry (unknown keys kept)."""
        out = {
            **dict(self.extra),
            "id": self.id,
            "timestamp_us": int(self.timestamp_us),
            "ego_to_world": np.asarray(self.ego_to_world, dtype=np.float64).tolist(),
        }
        caps = {name: cap.to_dict() for name, cap in self.cameras.items()}
        if caps:
            out["cameras"] = caps
        return out

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Frame) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(self.id)


@dataclass(frozen=True, eq=False)
class Rig:
    """A camera rig and its frames. `pairs` are the adjacent camera pairs (from `ring` or explicit)."""

    cameras: tuple[Camera, ...]
    pairs: tuple[tuple[str, str], ...]
    frames: tuple[Frame, ...]
    ring: tuple[str, ...] | None = None
    root: Path | None = None
    masks: Mapping[str, Path] = field(default_factory=dict)
    extra: Mapping[str, Any] = field(default_factory=dict)
    lidar_config: LidarDepthConfig = field(default_factory=LidarDepthConfig)  # how LiDAR sweeps become depth

    # --- look-ups ---------------------------------------------------------------------------
    @property
    def camera_names(self) -> list[str]:
        """Camera names in file order."""
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> Camera:
        """The camera called `name`."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    def frame(self, frame_id: str) -> Frame:
        """The frame with id `frame_id` (InputError, one line, when the rig has none)."""
        for fr in self.frames:
            if fr.id == frame_id:
                return fr
        raise InputError(self.root, f"frames/{frame_id}", f"not a frame of the rig ({len(self.frames)} frames)")

    def capture(self, frame: str | Frame, camera: str) -> Capture:
        """Camera `camera`'s capture in a frame (id or Frame): its time, the ego pose then, its pose in the world.

        `camera_to_world = ego_to_world(frame, camera) @ sensor_to_ego(camera)`; everything that relates two
        cameras of one frame (rectification, triangulation, back-projection, LiDAR projection) uses it.
        """
        fr = frame if isinstance(frame, Frame) else self.frame(frame)
        ego = fr.capture_ego_to_world(camera)
        return Capture(fr.capture_time_us(camera), ego, ego @ self.camera(camera).sensor_to_ego)

    def as_captured(self, frame: str | Frame) -> Rig:
        """The rig with each camera's sensor_to_ego as it was at its own capture of `frame`, seen from the
        frame's ego pose: inv(ego_to_world(frame)) @ capture(frame, c).camera_to_world.

        Relative poses between its cameras are then the true ones between the images of that frame (what
        rectification, triangulation and back-projection need); with no per-camera entries it is `self`.
        """
        fr = frame if isinstance(frame, Frame) else self.frame(frame)
        if not fr.cameras:
            return self
        world_to_ego = invert_transform(np.asarray(fr.ego_to_world, np.float64))
        return self.with_extrinsics({c: world_to_ego @ self.capture(fr, c).camera_to_world for c in fr.cameras})

    def load_image(self, frame_id: str, camera: str) -> np.ndarray:
        """RGB uint8 image (H, W, 3) of one camera in one frame."""
        path = self.frame(frame_id).images.get(camera)
        if path is None:
            raise InputError(self.root, f"frames/{frame_id}/{camera}", "no image")
        return read_image(path)

    def load_depth(self, frame_id: str, camera: str) -> np.ndarray | None:
        """Ground-truth depth in metres (0 = none) in the camera's convention, or None when the rig has none.

        Depth PNGs are read directly; OmniMVS inverse-depth panoramas (TIFF) are splatted into the camera;
        a frame's LiDAR sweep (nuScenes, DDAD) is projected into the camera at its own capture pose
        (`sgde_plugin.lidar`, settings `lidar_config`), under the camera's mask.
        """
        frame = self.frame(frame_id)
        path = frame.depths.get(camera)
        if path is None and frame.lidar is not None:
            return sweep_depth(frame.lidar, self.camera(camera), self.capture(frame, camera).camera_to_world,
                               self.load_mask(camera), self.lidar_config)
        if path is None:
            return None
        if Path(path).suffix.lower() in (".tif", ".tiff"):
            return load_panorama_depth(path, self.camera(camera))
        return read_depth_png(path)

    def load_mask(self, camera: str) -> np.ndarray | None:
        """Static mask (True = use), or None when the rig has none for this camera."""
        path = self.masks.get(camera)
        return None if path is None else read_mask(path)

    # --- derived rigs -----------------------------------------------------------------------
    def with_extrinsics(self, sensor_to_ego: Mapping[str, np.ndarray]) -> Rig:
        """The same rig with some cameras' sensor_to_ego replaced."""
        cams = tuple(c.with_pose(sensor_to_ego[c.name]) if c.name in sensor_to_ego else c for c in self.cameras)
        return replace(self, cameras=cams)

    def with_intrinsics(self, intrinsics: Mapping[str, CameraModel]) -> Rig:
        """The same rig with some cameras' intrinsics replaced."""
        cams = tuple(Camera(c.name, intrinsics[c.name], c.sensor_to_ego) if c.name in intrinsics else c
                     for c in self.cameras)
        return replace(self, cameras=cams)

    def with_extra(self, **extra: object) -> Rig:
        """The same rig with top-level keys added to `rig.json` (e.g. a calibration block)."""
        return replace(self, extra={**dict(self.extra), **extra})

    # --- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The `rig.json` document (unknown top-level keys kept)."""
        doc: dict[str, Any] = {k: v for k, v in self.extra.items() if k not in ("ring", "pairs")}
        doc["format"] = FORMAT
        doc["cameras"] = [c.to_dict() for c in self.cameras]
        if self.ring is not None:
            doc["ring"] = list(self.ring)
        else:
            doc["pairs"] = [list(p) for p in self.pairs]
        doc["frames"] = [f.to_dict() for f in self.frames]
        return doc

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Rig) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(tuple(self.camera_names))


def ring_pairs(ring: list[str] | tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """Adjacent pairs of a closed ring (last is adjacent to first)."""
    n = len(ring)
    if n < 2:
        return ()
    if n == 2:
        return ((ring[0], ring[1]),)
    return tuple((ring[i], ring[(i + 1) % n]) for i in range(n))


def ring_subset_pairs(ring: tuple[str, ...] | list[str], present: tuple[str, ...] | list[str]
                      ) -> tuple[tuple[str, str], ...]:
    """Adjacent pairs of a closed ring that a subset of its cameras still forms (both cameras present)."""
    keep = set(present)
    return tuple(p for p in ring_pairs(ring) if p[0] in keep and p[1] in keep)


def _captures(doc: object, where: str, names: set[str]) -> dict[str, CameraCapture]:
    """Parse `frames[].cameras` (camera -> {timestamp_us, ego_to_world}); every key optional."""
    if not isinstance(doc, dict):
        raise InputError(None, where, "not an object mapping camera names to captures")
    out = {}
    for name, entry in doc.items():
        here = f"{where}.{name}"
        if name not in names:
            raise InputError(None, here, f"camera {name!r} is not in the rig")
        if not isinstance(entry, dict):
            raise InputError(None, here, "not an object")
        ts = entry.get("timestamp_us")
        if ts is not None and (not isinstance(ts, int) or isinstance(ts, bool)):
            raise InputError(None, f"{here}.timestamp_us", "not an integer")
        pose = transform_field(entry, "ego_to_world", here) if "ego_to_world" in entry else None
        out[name] = CameraCapture(ts, pose)
    return out


def _cameras_from_doc(doc: dict) -> tuple[Camera, ...]:
    """Stage 1 of `rig_from_dict`: the `cameras` list (plain, unique names; intrinsics; mounts)."""
    cams_doc = doc.get("cameras")
    if not isinstance(cams_doc, list) or not cams_doc:
        raise InputError(None, "cameras", "missing or empty")
    cameras: list[Camera] = []
    for i, entry in enumerate(cams_doc):
        where = f"cameras[{i}]"
        if not isinstance(entry, dict):
            raise InputError(None, where, "not an object")
        name = entry.get("name")
        if not isinstance(name, str) or not name:
            raise InputError(None, f"{where}.name", "missing or not a string")
        if not is_plain_name(name):
            raise InputError(None, f"{where}.name", f"{name!r} is not a plain file name (no '/', '\\', '..', "
                             "control characters or surrounding spaces)")
        where = f"cameras[{name}]"
        if any(c.name == name for c in cameras):
            raise InputError(None, where, "duplicate camera name")
        pose = transform_field(entry, "sensor_to_ego", where, max_m=MAX_MOUNT_M)
        cameras.append(Camera(name, intrinsics_from_dict(entry, where), pose))
    return tuple(cameras)


def _ring_from_doc(ring_doc: object, names: set[str]) -> tuple[str, ...]:
    """Stage 2a of `rig_from_dict`: a `ring` of two or more distinct, existing cameras."""
    if not isinstance(ring_doc, list) or not all(isinstance(n, str) for n in ring_doc):
        raise InputError(None, "ring", "not a list of camera names")
    for n in ring_doc:
        if n not in names:
            raise InputError(None, "ring", f"camera {n!r} does not exist")
    if len(set(ring_doc)) != len(ring_doc):
        raise InputError(None, "ring", "names a camera twice")
    if len(ring_doc) < 2:
        raise InputError(None, "ring", "needs at least two cameras (a ring of one has no adjacent pair)")
    return tuple(ring_doc)


def _pairs_from_doc(pairs_doc: object, names: set[str]) -> tuple[tuple[str, str], ...]:
    """Stage 2b of `rig_from_dict`: explicit `pairs` of two different, existing cameras, none repeated."""
    if not isinstance(pairs_doc, list):
        raise InputError(None, "pairs", "not a list of pairs")
    pairs_l: list[tuple[str, str]] = []
    for i, p in enumerate(pairs_doc):
        if not (isinstance(p, list) and len(p) == 2 and all(isinstance(n, str) for n in p)) or p[0] == p[1]:
            raise InputError(None, f"pairs[{i}]", "not a pair of two different camera names")
        for n in p:
            if n not in names:
                raise InputError(None, f"pairs[{i}]", f"camera {n!r} does not exist")
        if any(sorted(p) == sorted(q) for q in pairs_l):
            raise InputError(None, f"pairs[{i}]", f"repeats the pair {p[0]!r}-{p[1]!r}")
        pairs_l.append((p[0], p[1]))
    if not pairs_l:
        raise InputError(None, "pairs", "lists no pair (a rig needs at least one adjacent pair)")
    return tuple(pairs_l)


def _frame_from_doc(entry: object, i: int, seen: set[str], names: set[str]) -> Frame:
    """Stage 3 of `rig_from_dict`, one `frames[i]` (its id is added to `seen`)."""
    where = f"frames[{i}]"
    if not isinstance(entry, dict):
        raise InputError(None, where, "not an object")
    fid = entry.get("id")
    if not isinstance(fid, str) or not is_plain_name(fid):
        raise InputError(None, f"{where}.id", "missing or not a plain file name")
    if fid in seen:
        raise InputError(None, f"{where}.id", f"duplicate frame id {fid!r}")
    seen.add(fid)
    ts = entry.get("timestamp_us", i)
    if not isinstance(ts, int) or isinstance(ts, bool):
        raise InputError(None, f"{where}.timestamp_us", "not an integer")
    pose = transform_field(entry, "ego_to_world", f"frames[{fid}]", required=False)
    captures = _captures(entry.get("cameras", {}), f"frames[{fid}].cameras", names)
    extra = {k: v for k, v in entry.items() if k not in _FRAME_KEYS}
    return Frame(fid, ts, pose, extra=extra, cameras=captures)


_FRAME_KEYS = {"id", "timestamp_us", "ego_to_world", "cameras"}
_RIG_KEYS = ("format", "cameras", "ring", "pairs", "frames")


def rig_from_dict(doc: object, root: Path | None = None) -> Rig:
    """Build and check a Rig from a parsed `rig.json`; InputError names the offending key."""
    if not isinstance(doc, dict):
        raise InputError(None, None, "top level is not a JSON object")
    if doc.get("format") != FORMAT:
        raise InputError(None, "format", f"expected {FORMAT!r}, found {doc.get('format')!r}")
    cameras = _cameras_from_doc(doc)
    names = {c.name for c in cameras}
    if ("ring" in doc) == ("pairs" in doc):
        raise InputError(None, "ring/pairs", "a rig has exactly one of 'ring' and 'pairs'")
    ring = _ring_from_doc(doc["ring"], names) if "ring" in doc else None
    pairs = ring_pairs(ring) if ring is not None else _pairs_from_doc(doc["pairs"], names)
    frames_doc = doc.get("frames", [])
    if not isinstance(frames_doc, list):
        raise InputError(None, "frames", "not a list")
    seen: set[str] = set()
    frames = tuple(_frame_from_doc(entry, i, seen, names) for i, entry in enumerate(frames_doc))
    extra = {k: v for k, v in doc.items() if k not in _RIG_KEYS}
    return Rig(cameras, pairs, frames, ring, root, {}, extra)


def read_rig_json(path: str | Path, root: Path | None = None) -> Rig:
    """Read a `rig.json` file (no image checks); InputError names file, key and problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"bad JSON ({exc})") from None
    except RecursionError:
        raise InputError(path, None, "bad JSON (nested too deeply)") from None
    except OSError as exc:  # a folder named rig.json, no permission, ...
        raise InputError(path, None, f"cannot read ({exc.strerror or exc})") from None
    try:
        return rig_from_dict(doc, root)
    except InputError as exc:
        raise InputError(path, exc.key, exc.problem) from None


def _find_image(folder: Path, camera: str) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        p = folder / f"{camera}{suffix}"
        if p.exists():
            return p
    return None


def attach_files(rig: Rig, root: Path) -> Rig:
    """Locate images, depths and masks of an `sgde-rig/1` folder and attach their paths to the rig."""
    frames = []
    for fr in rig.frames:
        images, depths = {}, {}
        for cam in rig.camera_names:
            img = _find_image(root / "frames" / fr.id, cam)
            if img is not None:
                images[cam] = img
            dep = root / "depth" / fr.id / f"{cam}.png"
            if dep.exists():
                depths[cam] = dep
        frames.append(replace(fr, images=images, depths=depths))
    masks = {c: root / "masks" / f"{c}.png" for c in rig.camera_names if (root / "masks" / f"{c}.png").exists()}
    return replace(rig, frames=tuple(frames), root=root, masks=masks)


def read_rig_folder(root: str | Path, check_images: bool = False) -> Rig:
    """Read an `sgde-rig/1` folder; with `check_images`, every image must exist and match its camera's size."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, None, "not a folder")
    rig = attach_files(read_rig_json(root / "rig.json", root), root)
    if check_images:
        check_folder_files(rig)
    return rig


def check_folder_files(rig: Rig) -> None:
    """The rig has frames; every frame has an 8-bit image per camera whose size matches the camera;
    depth PNGs (single-channel 16-bit) and masks likewise. Headers only."""
    assert rig.root is not None
    if not rig.frames:
        raise InputError(rig.root / "rig.json", "frames", "the rig has no frames")
    for fr in rig.frames:
        for cam in rig.cameras:
            path = fr.images.get(cam.name)
            if path is None:
                raise InputError(rig.root / "frames" / fr.id, cam.name, "image missing")
            check_image_file(path, cam, depth=False)
            if cam.name in fr.depths:
                check_image_file(fr.depths[cam.name], cam, depth=True)
    for name, path in rig.masks.items():
        check_image_file(path, rig.camera(name))


def check_image_file(path: Path, cam: Camera, depth: bool | None = None) -> None:
    """The file's size is the camera's; with `depth` False / True its pixels are an image's / a depth PNG's (one
    header read)."""
    header = image_header(path)
    w, h = header[:2]
    if (w, h) != (cam.width, cam.height):
        raise InputError(path, "size", f"image is {w}x{h}, camera {cam.name} is {cam.width}x{cam.height}")
    if depth is not None:
        check_pixel_format(path, header, depth)


def write_rig_json(rig: Rig, path: str | Path) -> None:
    """Write `rig.json` atomically (temporary name + rename)."""
    atomic_write_text(path, json.dumps(rig.to_dict(), indent=1) + "\n")


def load_frame_images(rig: Rig, frame_id: str) -> dict[str, np.ndarray]:
    """All cameras' RGB images of one frame."""
    return {c: rig.load_image(frame_id, c) for c in rig.camera_names}


__all__ = [
    "FORMAT",
    "Capture",
    "CameraCapture",
    "Frame",
    "Rig",
    "attach_files",
    "check_folder_files",
    "load_frame_images",
    "own_captures",
    "read_rig_folder",
    "read_rig_json",
    "rig_from_dict",
    "ring_pairs",
    "ring_subset_pairs",
    "write_rig_json",
]
