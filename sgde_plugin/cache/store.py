"""The prior cache store (zarr v3): layout, scene creation / resume checks, frame writer, read API.

Layout (format `sgde-prior-cache/1`), one zarr group per scene:

    <cache>/zarr.json                   attrs: format, config document, config fingerprint
    <cache>/<scene>/zarr.json           attrs: fingerprints, cameras (name, size, depth kind),
                                        frame ids, timestamps, units, rig document, ready flag
    <cache>/<scene>/depth               float16  (frames, cameras, H, W)  metres, 0 = no prior
    <cache>/<scene>/confidence          uint8    (frames, cameras, H, W)  round(255 * confidence)
    <cache>/<scene>/valid_pixels        int32    (frames, cameras)        -1 = frame not written yet

depth / confidence are sharded by frame (one shard = one frame, one inner chunk = one camera
image), compressed with zstd and checksummed (crc32c) per camera image. Cameras of different sizes
are zero-padded to the largest one and cropped back on reading. `valid_pixels` of a frame is
written after its two shards, so it is the frame's "done" marker: readers and resumed builds
trust a frame only once it is there, and every store write is atomic (a rename on a local
folder, one PUT on object stores), so no reader ever sees half a frame.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
import zarr.storage
from zarr.abc.store import Store
from zarr.codecs import BloscCodec, Crc32cCodec
from zarr.core.sync import sync

from .. import __version__
from ..errors import InputError
from .fingerprints import CACHE_FORMAT, config_document, describe_config_change, digest, rig_document
from .resample import resize_depth

UNITS = {"depth": "m", "confidence": "1/255", "timestamps": "us"}
ARRAYS = ("depth", "confidence", "valid_pixels")
FLOAT16_MAX = 65504.0
FLOAT16_MIN_POSITIVE = 6.2e-5  # smallest normal float16, so a valid depth never rounds to 0


# --- stores ---------------------------------------------------------------------------------
def is_url(location: Any) -> bool:
    """True for fsspec URLs such as memory://..., s3://..., gs://..."""
    return isinstance(location, str) and "://" in location and not location.startswith("file://")


def location_name(location: Any) -> str:
    """The cache location as shown to the user."""
    return str(location) if not isinstance(location, Store) else repr(location)


def open_store(location: Any, read_only: bool, storage_options: Mapping[str, Any] | None = None) -> Store:
    """A zarr store for a local folder, an fsspec URL or an existing zarr Store."""
    if isinstance(location, Store):
        return location.with_read_only(read_only) if location.read_only != read_only else location
    if is_url(location):
        return zarr.storage.FsspecStore.from_url(
            location, read_only=read_only, storage_options=dict(storage_options or {})
        )
    path = Path(str(location).removeprefix("file://"))
    if read_only and not path.exists():
        raise InputError(path, None, "prior cache does not exist")
    return zarr.storage.LocalStore(path, read_only=read_only)


def open_root(store: Store, location: Any, mode: str) -> zarr.Group:
    """The cache's root group; InputError when the location is not a zarr v3 group."""
    try:
        root = zarr.open_group(store, mode=mode, zarr_format=3)
    except (FileNotFoundError, KeyError, ValueError, zarr.errors.GroupNotFoundError) as exc:
        raise InputError(location_name(location), None, f"not a prior cache ({type(exc).__name__})") from None
    return root


def _compressors(itemsize: int) -> list[Any]:
    # byte shuffle + zstd: ~20% smaller than plain zstd on float16 priors; crc32c per camera image
    return [BloscCodec(cname="zstd", clevel=5, shuffle="shuffle", typesize=itemsize), Crc32cCodec()]


# --- scene layout -----------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraEntry:
    """One camera of a cached scene: name, native image size and depth kind ('z' or 'range')."""

    name: str
    width: int
    height: int
    depth: str = "z"

    def to_dict(self) -> dict[str, Any]:
        """The attribute form."""
        return {"name": self.name, "width": self.width, "height": self.height, "depth": self.depth}


def camera_entries(rig: Any) -> list[CameraEntry]:
    """Cache camera entries of a rig, in rig order."""
    out = []
    for cam in rig.cameras:
        kind = "range" if getattr(cam.intrinsics, "depth_is_range", False) else "z"
        out.append(CameraEntry(cam.name, int(cam.width), int(cam.height), kind))
    return out


def check_scene_name(name: str) -> str:
    """A scene name usable as a zarr group name (no '/', not empty, not starting with '.' or '__')."""
    if not name or "/" in name or name.startswith((".", "__")) or name in ARRAYS:
        raise InputError(None, "scene", f"{name!r} is not a usable scene name")
    return name


def _refusal(location: Any, scene: str | None, cached: Mapping[str, Any], parts: Mapping[str, Any]) -> InputError:
    """The one-line refusal for a fingerprint mismatch, naming what differs."""
    where = location_name(location)
    if cached.get("config_fingerprint") != parts["config"]:
        change = describe_config_change(cached.get("config", {}), parts.get("config_document", {}))
        what = f"built with other prior settings ({change})"
    else:
        what = "built for another calibration (cameras, extrinsics, pairs or masks differ)"
    key = f"{scene}: fingerprint" if scene else "fingerprint"
    return InputError(
        where, key, f"{what}: cache {cached.get('fingerprint', '?')} != {parts['fingerprint']}; "
        "refusing to mix them: build into another --out"
    )


@dataclass
class ScenePlan:
    """What a build has to do for one scene: the frame indices still missing."""

    scene: str
    frame_ids: list[str]
    pending: list[int]
    already_done: int


def prepare_scene(
    location: Any,
    scene: str,
    rig: Any,
    parts: Mapping[str, Any],
    storage_options: Mapping[str, Any] | None = None,
) -> ScenePlan:
    """Create the cache and the scene, or reopen them after checking fingerprints and frames; returns
    the frames still to build. `parts` is fingerprint_parts(...) plus 'config_document'."""
    check_scene_name(scene)
    store = open_store(location, read_only=False, storage_options=storage_options)
    root = _prepare_root(store, location, parts)
    cameras = camera_entries(rig)
    ids = [fr.id for fr in rig.frames]
    stamps = {fr.id: int(fr.timestamp_us) for fr in rig.frames}
    if not ids:
        raise InputError(location_name(location), scene, "the rig has no frames")
    group = None
    if scene in set(root.group_keys()):
        group = root[scene]
        if not group.attrs.get("ready"):
            # a creation interrupted before any frame was written: start the scene afresh
            sync(store.delete_dir(scene))
            group = None
    if group is None:
        return _create_scene(root, location, scene, cameras, ids, stamps, rig, parts)
    return _reopen_scene(root, group, location, scene, cameras, ids, stamps, parts)


def _prepare_root(store: Store, location: Any, parts: Mapping[str, Any]) -> zarr.Group:
    try:
        root = zarr.open_group(store, mode="r+", zarr_format=3)
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError):
        if isinstance(store, zarr.storage.LocalStore) and Path(store.root).is_dir():
            for leftover in Path(store.root).glob("*.partial"):  # of an interrupted creation
                leftover.unlink(missing_ok=True)
        attrs = {
            "format": CACHE_FORMAT,
            "config": parts["config_document"],
            "config_fingerprint": parts["config"],
            "sgde_version": __version__,
        }
        try:  # "w-" never deletes anything: a location holding other data is refused
            return zarr.open_group(store, mode="w-", zarr_format=3, attributes=attrs)
        except FileExistsError:
            raise InputError(location_name(location), None, "exists and is not a prior cache") from None
    attrs = dict(root.attrs)
    if attrs.get("format") != CACHE_FORMAT:
        raise InputError(location_name(location), "format", f"expected {CACHE_FORMAT!r}, found {attrs.get('format')!r}")
    if attrs.get("config_fingerprint") != parts["config"]:
        cached = {"config_fingerprint": attrs.get("config_fingerprint"), "config": attrs.get("config", {})}
        cached["fingerprint"] = attrs.get("config_fingerprint")
        raise _refusal(location, None, cached, {**parts, "fingerprint": parts["config"]})
    return root


def _create_scene(
    root: zarr.Group,
    location: Any,
    scene: str,
    cameras: list[CameraEntry],
    ids: list[str],
    stamps: Mapping[str, int],
    rig: Any,
    parts: Mapping[str, Any],
) -> ScenePlan:
    attrs = {
        "format": CACHE_FORMAT,
        "ready": False,
        "fingerprint": parts["fingerprint"],
        "rig_fingerprint": parts["rig"],
        "config_fingerprint": parts["config"],
        "cameras": [c.to_dict() for c in cameras],
        "frame_ids": list(ids),
        "timestamps_us": [int(stamps[i]) for i in ids],
        "units": dict(UNITS),
        "rig": rig_document(rig),
        "sgde_version": __version__,
    }
    group = root.create_group(scene, attributes=attrs)
    n, c = len(ids), len(cameras)
    h, w = max(e.height for e in cameras), max(e.width for e in cameras)
    common = {"config": {"write_empty_chunks": False}, "dimension_names": ["frame", "camera", "y", "x"]}
    group.create_array(
        "depth", shape=(n, c, h, w), dtype="float16", chunks=(1, 1, h, w), shards=(1, c, h, w),
        compressors=_compressors(2), fill_value=0.0, attributes={"units": "m", "no_value": 0}, **common,
    )
    group.create_array(
        "confidence", shape=(n, c, h, w), dtype="uint8", chunks=(1, 1, h, w), shards=(1, c, h, w),
        compressors=_compressors(1), fill_value=0, attributes={"scale": 1 / 255}, **common,
    )
    group.create_array(
        "valid_pixels", shape=(n, c), dtype="int32", chunks=(1, c), compressors=[Crc32cCodec()],
        fill_value=-1, config={"write_empty_chunks": False}, dimension_names=["frame", "camera"],
        attributes={"not_written": -1},
    )
    group.attrs.update({"ready": True})
    return ScenePlan(scene, list(ids), list(range(n)), 0)


def _reopen_scene(
    root: zarr.Group,
    group: zarr.Group,
    location: Any,
    scene: str,
    cameras: list[CameraEntry],
    ids: list[str],
    stamps: Mapping[str, int],
    parts: Mapping[str, Any],
) -> ScenePlan:
    attrs = dict(group.attrs)
    if attrs.get("fingerprint") != parts["fingerprint"]:
        cached = {**attrs, "config": dict(root.attrs).get("config", {})}
        raise _refusal(location, scene, cached, parts)
    if [CameraEntry(**e) for e in attrs["cameras"]] != cameras:
        raise InputError(location_name(location), f"{scene}: cameras", "differ from the rig's cameras")
    known = list(attrs["frame_ids"])
    known_stamps = dict(zip(known, attrs["timestamps_us"]))
    for fid in ids:
        if fid in known_stamps and int(known_stamps[fid]) != int(stamps[fid]):
            raise InputError(
                location_name(location), f"{scene}: frames[{fid}]",
                f"timestamp {stamps[fid]} differs from the cached {known_stamps[fid]}",
            )
    added = [fid for fid in ids if fid not in known_stamps]
    all_ids = known + added
    n = len(all_ids)
    # extension: arrays first, then the frame list, so an interrupted extension is redone
    for name in ARRAYS:
        arr = group[name]
        if arr.shape[0] < n:
            arr.resize((n, *arr.shape[1:]))
    if added:
        group.attrs.update(
            {"frame_ids": all_ids, "timestamps_us": [int(known_stamps.get(i, stamps.get(i, 0))) for i in all_ids]}
        )
    index = {fid: i for i, fid in enumerate(all_ids)}
    done = group["valid_pixels"][:, 0] >= 0
    wanted = [index[fid] for fid in ids]
    pending = [i for i in wanted if not done[i]]
    return ScenePlan(scene, all_ids, pending, len(wanted) - len(pending))


def remove_partial_files(location: Any, scene: str) -> int:
    """Delete temporary files left by writes that a kill interrupted (local folders only)."""
    if isinstance(location, Store) or is_url(location):
        return 0
    base = Path(str(location).removeprefix("file://")) / scene
    count = 0
    for dirpath, _, files in os.walk(base):
        for f in files:
            if f.endswith(".partial"):
                (Path(dirpath) / f).unlink(missing_ok=True)
                count += 1
    return count


# --- writing ----------------------------------------------------------------------------------
def encode_prior(
    depth: np.ndarray, confidence: np.ndarray | None, height: int, width: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """One camera's prior as stored: float16 depth and uint8 confidence padded to (H, W), and its
    number of valid pixels. Non-finite and non-positive depths become 'none'."""
    d = np.asarray(depth, dtype=np.float32)
    h, w = d.shape
    if h > height or w > width:
        raise ValueError(f"prior of size {w}x{h} is larger than the cache's {width}x{height}")
    ok = np.isfinite(d) & (d > 0)
    d16 = np.zeros((height, width), dtype=np.float16)
    d16[:h, :w] = np.where(ok, np.clip(d, FLOAT16_MIN_POSITIVE, FLOAT16_MAX), 0).astype(np.float16)
    c8 = np.zeros((height, width), dtype=np.uint8)
    if confidence is None:
        c = ok.astype(np.float32)
    else:
        c = np.nan_to_num(np.asarray(confidence, dtype=np.float32), nan=0.0)
    c8[:h, :w] = np.where(ok, np.round(np.clip(c, 0.0, 1.0) * 255.0), 0).astype(np.uint8)
    return d16, c8, int(ok.sum())


class SceneWriter:
    """Writes whole frames of one scene; picklable (each process opens the store itself)."""

    def __init__(self, location: Any, scene: str, storage_options: Mapping[str, Any] | None = None):
        self.location = location
        self.scene = scene
        self.storage_options = dict(storage_options or {})
        self._group: zarr.Group | None = None
        self._pid = os.getpid()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_group": None}

    def _open(self) -> zarr.Group:
        if self._group is None or self._pid != os.getpid():
            self._pid = os.getpid()
            store = open_store(self.location, read_only=False, storage_options=self.storage_options)
            self._group = zarr.open_group(store, mode="r+", zarr_format=3)[self.scene]
            attrs = dict(self._group.attrs)
            self._cameras = [CameraEntry(**e) for e in attrs["cameras"]]
            self._frame_ids = list(attrs["frame_ids"])
        return self._group

    def frame_index(self, frame_id: str) -> int:
        """Index of a frame id in the scene."""
        self._open()
        return self._frame_ids.index(frame_id)

    def write_frame(self, index: int, maps: Mapping[str, tuple[np.ndarray, np.ndarray | None]]) -> int:
        """Write all cameras of frame `index` ({camera: (depth, confidence)}; a missing camera is
        empty), then its done marker. Returns the number of valid prior pixels."""
        group = self._open()
        depth_arr, conf_arr = group["depth"], group["confidence"]
        _, n_cam, height, width = depth_arr.shape
        unknown = set(maps) - {c.name for c in self._cameras}
        if unknown:
            raise ValueError(f"prior for unknown cameras {sorted(unknown)}")
        d_all = np.zeros((n_cam, height, width), dtype=np.float16)
        c_all = np.zeros((n_cam, height, width), dtype=np.uint8)
        counts = np.zeros(n_cam, dtype=np.int32)
        for ci, cam in enumerate(self._cameras):
            if cam.name not in maps:
                continue
            depth, conf = maps[cam.name]
            if np.shape(depth) != (cam.height, cam.width):
                raise ValueError(f"prior of {cam.name} is {np.shape(depth)}, expected {(cam.height, cam.width)}")
            d_all[ci], c_all[ci], counts[ci] = encode_prior(depth, conf, height, width)
        # a frame that is not marked done may hold leftovers of an interrupted attempt: drop them
        # so the new shards never merge with them
        self._delete_shards(index)
        depth_arr[index] = d_all
        conf_arr[index] = c_all
        group["valid_pixels"][index] = counts
        return int(counts.sum())

    def _delete_shards(self, index: int) -> None:
        group = self._group
        assert group is not None
        for name in ("depth", "confidence"):
            arr = group[name]
            key = f"{arr.path}/{arr.metadata.encode_chunk_key((index, 0, 0, 0))}"
            sync(arr.store_path.store.delete(key))


# --- reading ----------------------------------------------------------------------------------
class PriorCache:
    """Read-only access to a prior cache (contracts section 5).

    `PriorCache(path)` opens a local folder or an fsspec URL; `scene=` restricts it to one scene;
    `expect=` (a fingerprint) or `rig=` / `config=` refuse a cache built from other inputs.
    Picklable: each process (e.g. a DataLoader worker) reopens the store on first use.
    """

    def __init__(
        self,
        path: Any,
        scene: str | None = None,
        *,
        expect: str | None = None,
        rig: Any = None,
        config: Any = None,
        algo_version: str | None = None,
        storage_options: Mapping[str, Any] | None = None,
    ):
        self.location = str(path) if isinstance(path, Path) else path
        self.scene = scene
        self.storage_options = dict(storage_options or {})
        self._state: dict[str, Any] | None = None
        self._open()
        if expect is not None and expect != self.fingerprint:
            raise InputError(
                location_name(self.location), "fingerprint",
                f"cache {self.fingerprint} != expected {expect}; refusing priors built from other inputs",
            )
        if rig is not None or config is not None:
            self.check(rig=rig, config=config, algo_version=algo_version)

    # --- opening ----------------------------------------------------------------------------
    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_state": None}

    def _open(self) -> dict[str, Any]:
        # a forked process (e.g. a DataLoader worker) reopens the store rather than sharing handles
        if self._state is not None and self._state["pid"] == os.getpid():
            return self._state
        store = open_store(self.location, read_only=True, storage_options=self.storage_options)
        root = open_root(store, self.location, "r")
        rattrs = dict(root.attrs)
        if rattrs.get("format") != CACHE_FORMAT:
            found = rattrs.get("format")
            raise InputError(location_name(self.location), "format", f"expected {CACHE_FORMAT!r}, found {found!r}")
        names = sorted(root.group_keys())
        if self.scene is not None:
            if self.scene not in names:
                raise InputError(location_name(self.location), self.scene, f"no such scene (has {', '.join(names)})")
            names = [self.scene]
        scenes: dict[str, dict[str, Any]] = {}
        frame_index: dict[str, tuple[str, int]] = {}
        duplicates: set[str] = set()
        for name in names:
            group = root[name]
            attrs = dict(group.attrs)
            if not attrs.get("ready"):
                continue
            cams = [CameraEntry(**e) for e in attrs["cameras"]]
            ids = list(attrs["frame_ids"])
            scenes[name] = {
                "group": group,
                "attrs": attrs,
                "cameras": cams,
                "camera_index": {c.name: i for i, c in enumerate(cams)},
                "frame_ids": ids,
                "depth": group["depth"],
                "confidence": group["confidence"],
                "valid_pixels": group["valid_pixels"],
                "done": np.asarray(group["valid_pixels"][: len(ids), 0] >= 0),
            }
            for i, fid in enumerate(ids):
                if fid in frame_index:
                    duplicates.add(fid)
                frame_index.setdefault(fid, (name, i))
        self._state = {
            "pid": os.getpid(), "root": root, "root_attrs": rattrs, "scenes": scenes, "frames": frame_index,
            "dup": duplicates,
        }
        return self._state

    # --- contract API -----------------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """The scene's fingerprint (a digest over all scenes' fingerprints when there are several)."""
        scenes = self._open()["scenes"]
        fps = {name: s["attrs"]["fingerprint"] for name, s in scenes.items()}
        if len(fps) == 1:
            return next(iter(fps.values()))
        return digest(fps)

    def fingerprints(self) -> dict[str, dict[str, str]]:
        """Per scene: {'fingerprint', 'rig', 'config'} digests."""
        return {
            name: {
                "fingerprint": s["attrs"]["fingerprint"],
                "rig": s["attrs"]["rig_fingerprint"],
                "config": s["attrs"]["config_fingerprint"],
            }
            for name, s in self._open()["scenes"].items()
        }

    def scenes(self) -> list[str]:
        """Scene names (zarr groups) in the cache."""
        return list(self._open()["scenes"])

    def frames(self, include_pending: bool = False) -> list[str]:
        """Frame ids whose priors are complete (all frames with include_pending), scene by scene."""
        out = []
        for s in self._open()["scenes"].values():
            out += [f for f, d in zip(s["frame_ids"], s["done"]) if d or include_pending]
        return out

    def cameras(self) -> list[str]:
        """Camera names (union over scenes, in first-seen order)."""
        seen: dict[str, None] = {}
        for s in self._open()["scenes"].values():
            for c in s["cameras"]:
                seen.setdefault(c.name, None)
        return list(seen)

    def camera_size(self, camera: str, frame_id: str | None = None) -> tuple[int, int]:
        """Native (height, width) of a camera's prior."""
        for name, s in self._open()["scenes"].items():
            if frame_id is not None and self._locate(frame_id)[0] != name:
                continue
            if camera in s["camera_index"]:
                entry = s["cameras"][s["camera_index"][camera]]
                return entry.height, entry.width
        raise KeyError(camera)

    def config(self) -> dict[str, Any]:
        """The configuration document the cache was built with (config, algo_version, format)."""
        return dict(self._open()["root_attrs"].get("config", {}))

    def check(self, rig: Any = None, config: Any = None, algo_version: str | None = None) -> None:
        """Refuse (InputError) if the cache was built for another rig calibration or configuration."""
        state = self._open()
        if config is not None:
            doc = config_document(config, algo_version)
            if digest(doc) != state["root_attrs"].get("config_fingerprint"):
                change = describe_config_change(state["root_attrs"].get("config", {}), doc)
                raise InputError(
                    location_name(self.location), "fingerprint",
                    f"built with other prior settings ({change}); refusing to mix them",
                )
        if rig is not None:
            rig_fp = digest(rig_document(rig))
            for name, s in state["scenes"].items():
                if s["attrs"]["rig_fingerprint"] != rig_fp:
                    raise InputError(
                        location_name(self.location), f"{name}: fingerprint",
                        "built for another calibration (cameras, extrinsics, pairs or masks differ); "
                        "refusing to mix them",
                    )

    def _locate(self, frame_id: str) -> tuple[str, int]:
        state = self._open()
        if frame_id not in state["frames"]:
            raise KeyError(f"frame {frame_id!r} is not in the prior cache {location_name(self.location)}")
        if frame_id in state["dup"]:
            raise KeyError(f"frame {frame_id!r} is in several scenes; open the cache with scene=...")
        return state["frames"][frame_id]

    def _slot(self, frame_id: str, camera: str) -> tuple[dict[str, Any], int, int, CameraEntry]:
        scene, fi = self._locate(frame_id)
        s = self._open()["scenes"][scene]
        if camera not in s["camera_index"]:
            raise KeyError(f"camera {camera!r} is not in scene {scene!r} of the prior cache")
        if not s["done"][fi]:
            # the build may have progressed since the cache was opened
            s["done"][fi] = int(s["valid_pixels"][fi, 0]) >= 0
            if not s["done"][fi]:
                raise KeyError(f"frame {frame_id!r} of scene {scene!r} is not built yet")
        ci = s["camera_index"][camera]
        return s, fi, ci, s["cameras"][ci]

    def get(self, frame_id: str, camera: str, size: tuple[int, int] | None = None,
            min_confidence: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(depth float32 metres, valid bool) at native size, or resized to size=(h, w) without
        inventing depths (min-pool of valid values, then nearest). With `min_confidence` > 0 only
        values whose stored confidence (steps of 1/255) rounds to at least it (the rest read as no value)."""
        if min_confidence > 0:
            depth, _, conf = self.get_prior(frame_id, camera, size)
            depth = np.where(conf >= np.float32(min_confidence - 0.5 / 255), depth, 0).astype(np.float32)
            return depth, depth > 0
        s, fi, ci, cam = self._slot(frame_id, camera)
        depth = np.asarray(s["depth"][fi, ci, : cam.height, : cam.width], dtype=np.float32)
        if size is not None and tuple(size) != (cam.height, cam.width):
            (depth,) = resize_depth(depth, tuple(size))
        return depth, depth > 0

    def get_confidence(self, frame_id: str, camera: str, size: tuple[int, int] | None = None) -> np.ndarray:
        """Confidence float32 in [0, 1] (0 where there is no prior), native size or size=(h, w)."""
        return self.get_prior(frame_id, camera, size)[2]

    def get_prior(
        self, frame_id: str, camera: str, size: tuple[int, int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth, valid, confidence) of one camera image, resized together when size is given."""
        s, fi, ci, cam = self._slot(frame_id, camera)
        depth = np.asarray(s["depth"][fi, ci, : cam.height, : cam.width], dtype=np.float32)
        conf = np.asarray(s["confidence"][fi, ci, : cam.height, : cam.width], dtype=np.float32) / 255.0
        if size is not None and tuple(size) != (cam.height, cam.width):
            depth, conf = resize_depth(depth, tuple(size), conf)
        return depth, depth > 0, conf.astype(np.float32)

    def __repr__(self) -> str:
        return f"PriorCache({location_name(self.location)!r}, scenes={self.scenes()}, fingerprint={self.fingerprint})"


def scene_arrays(location: Any, scene: str, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The raw zarr group, attributes and arrays of one scene (for info, verify and tests)."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    group = open_root(store, location, "r")[scene]
    return {"group": group, "attrs": dict(group.attrs), **{name: group[name] for name in ARRAYS}}


def list_scenes(location: Any, storage_options: Mapping[str, Any] | None = None) -> list[str]:
    """Scene names of a cache (including scenes whose creation was interrupted)."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    return sorted(open_root(store, location, "r").group_keys())


def store_keys(location: Any, storage_options: Mapping[str, Any] | None = None) -> dict[str, int]:
    """Every key of the store with its size in bytes."""
    store = open_store(location, read_only=True, storage_options=storage_options)

    async def _collect() -> dict[str, int]:
        out = {}
        async for key in store.list():
            out[key] = await store.getsize(key)
        return out

    return sync(_collect())


def read_key(location: Any, key: str, storage_options: Mapping[str, Any] | None = None) -> bytes | None:
    """Raw bytes of one store key (None when absent)."""
    from zarr.core.buffer import default_buffer_prototype

    store = open_store(location, read_only=True, storage_options=storage_options)
    buf = sync(store.get(key, prototype=default_buffer_prototype()))
    return None if buf is None else buf.to_bytes()


__all__ = [
    "ARRAYS",
    "CameraEntry",
    "PriorCache",
    "ScenePlan",
    "SceneWriter",
    "camera_entries",
    "check_scene_name",
    "encode_prior",
    "is_url",
    "list_scenes",
    "location_name",
    "open_root",
    "open_store",
    "prepare_scene",
    "read_key",
    "remove_partial_files",
    "scene_arrays",
    "store_keys",
]
