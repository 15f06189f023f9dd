"""The layout of a cached scene and its consistency checks: camera entries, frame digests, shard keys,
attributes against arrays, and the per-frame chunk checks shared by readers, `verify` and repairs."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from zarr.abc.store import Store

from ..errors import InputError
from ..rig import Frame, Rig
from .backends import list_prefix
from .fingerprints import digest

UNITS = {"depth": "m", "confidence": "1/255", "timestamps": "us"}
ARRAYS = ("depth", "confidence", "valid_pixels")
SCENE_KEYS = ("fingerprint", "rig_fingerprint", "config_fingerprint", "cameras", "frame_ids", "timestamps_us")


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


def camera_entries(rig: Rig) -> list[CameraEntry]:
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


def frames_digest(frame_ids: Sequence[str], timestamps_us: Sequence[int]) -> str:
    """Digest of a scene's frame list, stored next to it so a hand-edited list is noticed."""
    return digest({"ids": list(frame_ids), "timestamps_us": [int(t) for t in timestamps_us]})


def file_signature(path: Any, edge: int = 16384) -> str:
    """Size and SHA-256 of the first and last `edge` bytes of a file (cheap, and differs between any two
    photographs); '-' when it cannot be read."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = f.read(edge)
            f.seek(max(size - edge, len(head)))
            tail = f.read(edge)
    except (OSError, TypeError):
        return "-"
    return f"{size}:{hashlib.sha256(head + tail).hexdigest()[:16]}"


def frame_source(frame: Frame) -> str:
    """Digest of what a frame's prior is computed from besides the calibration: its rig.json entry
    (timestamp, ego poses) and a signature of each image file, so priors of another scene are noticed.
    Stored per frame in the scene attribute `frame_inputs`."""
    images = {cam: file_signature(path) for cam, path in sorted(dict(getattr(frame, "images", {}) or {}).items())}
    doc = frame.to_dict() if hasattr(frame, "to_dict") else {"id": frame.id, "timestamp_us": int(frame.timestamp_us)}
    return digest({"frame": doc, "images": images})


def scene_groups(store: Store, root: Any) -> tuple[dict[str, Any], dict[str, str]]:
    """{name: group} of a cache's scenes, and {name: problem} of the entries that do not open as one
    (a scene folder whose zarr.json is missing or unreadable)."""
    import zarr
    from zarr.core.sync import sync

    async def _names() -> list[str]:
        return [k async for k in store.list_dir("")]

    groups, broken = {}, {}
    for name in sorted(sync(_names())):
        if name == "zarr.json" or name.startswith(".") or name.endswith(".partial"):
            continue
        try:
            node = root[name]
        except KeyError:
            broken[name] = "scene folder without metadata (zarr.json missing)"
            continue
        except Exception as exc:  # noqa: BLE001 - a corrupted zarr.json is a finding
            broken[name] = f"zarr.json unreadable ({type(exc).__name__})"
            continue
        if isinstance(node, zarr.Group):
            groups[name] = node
        else:
            broken[name] = "an array where a scene group belongs"
    return groups, broken


def shard_key(array: Any, frame_index: int) -> str:
    """Store key of the shard (all cameras) of one frame of a (frames, cameras, H, W) array."""
    return f"{array.path}/{array.metadata.encode_chunk_key((frame_index, 0, 0, 0))}"


def open_arrays(group: Any) -> tuple[dict[str, Any], list[str]]:
    """The scene's arrays by name, and one problem per array that is missing or unreadable."""
    arrays, problems = {}, []
    for name in ARRAYS:
        try:
            arrays[name] = group[name]
        except Exception as exc:  # noqa: BLE001 - a missing or corrupted zarr.json is a finding
            problems.append(f"array {name!r} is missing or its zarr.json is unreadable ({type(exc).__name__})")
    return arrays, problems


def _attribute_problems(attrs: Mapping[str, Any]) -> list[str]:
    missing = [k for k in SCENE_KEYS if k not in attrs]
    if missing:
        return [f"attributes lack {', '.join(missing)}"]
    problems = []
    ids, stamps = list(attrs["frame_ids"]), list(attrs["timestamps_us"])
    if len(set(ids)) != len(ids):
        problems.append("frame_ids lists a frame twice")
    if len(stamps) != len(ids):
        problems.append(f"{len(stamps)} timestamps_us for {len(ids)} frame_ids")
    elif "frames_digest" in attrs and attrs["frames_digest"] != frames_digest(ids, stamps):
        problems.append("frame_ids / timestamps_us were changed after the build (frames_digest differs)")
    if "frame_inputs" in attrs and len(attrs["frame_inputs"]) != len(ids):
        problems.append("frame_inputs and frame_ids differ in length")
    rig = attrs.get("rig")
    if isinstance(rig, Mapping):
        if digest(rig) != attrs["rig_fingerprint"]:
            problems.append("the rig document does not match rig_fingerprint (edited after the build)")
        rig_cams = [(c.get("name"), c.get("width"), c.get("height")) for c in rig.get("cameras", [])]
        mine = [(c.get("name"), c.get("width"), c.get("height")) for c in attrs["cameras"]]
        if rig_cams != mine:
            problems.append("cameras (names or sizes) differ from the rig document's (edited after the build)")
    return problems


def scene_problems(attrs: Mapping[str, Any], arrays: Mapping[str, Any]) -> list[str]:
    """Everything wrong between a scene's attributes and its arrays (empty when consistent)."""
    problems = _attribute_problems(attrs)
    if problems or len(arrays) < len(ARRAYS):
        return problems
    try:
        cams = [CameraEntry(**e) for e in attrs["cameras"]]
    except TypeError:
        return ["attribute 'cameras' is malformed"]
    n, c = len(attrs["frame_ids"]), len(cams)
    h, w = max(e.height for e in cams), max(e.width for e in cams)
    for name in ("depth", "confidence"):
        shape = tuple(arrays[name].shape)
        if shape[1:] != (c, h, w) or shape[0] < n:
            problems.append(f"array {name!r} has shape {list(shape)}, the attributes say ({n}, {c}, {h}, {w})")
    for name, dtype in (("depth", "float16"), ("confidence", "uint8"), ("valid_pixels", "int32")):
        if str(arrays[name].dtype) != dtype:
            problems.append(f"array {name!r} has dtype {arrays[name].dtype}, expected {dtype}")
    shape = tuple(arrays["valid_pixels"].shape)
    if shape[1:] != (c,) or shape[0] < n:
        problems.append(f"array 'valid_pixels' has shape {list(shape)}, the attributes say ({n}, {c})")
    return problems


def read_counts(valid_pixels: Any, n: int) -> tuple[np.ndarray, set[int]]:
    """Valid-pixel counts (n, cameras) with -1 for frames not built, and the frames whose count chunk
    is unreadable (they count as not built)."""
    try:
        return np.asarray(valid_pixels[:n]).reshape(n, -1).astype(np.int64), set()
    except Exception:  # noqa: BLE001 - find the damaged chunks one by one
        pass
    counts = np.full((n, valid_pixels.shape[1]), -1, dtype=np.int64)
    bad = set()
    for i in range(n):
        try:
            counts[i] = np.asarray(valid_pixels[i])
        except Exception:  # noqa: BLE001
            bad.add(i)
    return counts, bad


def missing_shards(store: Store, arrays: Mapping[str, Any], counts: np.ndarray) -> dict[int, str]:
    """Built frames with prior pixels whose depth or confidence shard is absent from the store
    (a cheap listing, no chunk read): {frame index: problem}."""
    out: dict[int, str] = {}
    for name in ("depth", "confidence"):
        arr = arrays[name]
        present = list_prefix(store, f"{arr.path}/")
        for fi in np.flatnonzero((counts[:, 0] >= 0) & (counts.sum(axis=1) > 0)):
            if shard_key(arr, int(fi)) not in present:
                out.setdefault(int(fi), f"{name} shard missing")
    return out


def read_checked(array: Any, index: tuple[int, ...]) -> tuple[np.ndarray | None, str | None]:
    """One chunk read, or (None, what went wrong) when it does not decode."""
    try:
        return np.asarray(array[index]), None
    except Exception as exc:  # noqa: BLE001 - any decoding failure is a finding, not a crash
        text = str(exc).split("\n")[0]
        if "checksum" in text.lower():
            return None, "checksum mismatch (corrupted or truncated)"
        return None, f"unreadable ({type(exc).__name__}: {text[:120]})"


def image_problems(depth: np.ndarray, conf: np.ndarray | None, count: int) -> list[tuple[str, str]]:
    """Problems (array, text) of one decoded camera image (already cropped) against its written count."""
    out = []
    valid = depth > 0
    n = int(np.count_nonzero(valid))
    if n != count:
        out.append(("depth", f"{n} valid pixels read, {count} written (chunk missing or damaged)"))
    if not np.all(np.isfinite(depth)) or (depth < 0).any():
        out.append(("depth", "non-finite or negative depths"))
    if conf is not None:
        if (conf[~valid] != 0).any():
            out.append(("confidence", "confidence where there is no depth"))
        elif n and count and not (conf[valid] != 0).any():
            out.append(("confidence", "no confidence where there is depth (chunk missing)"))
    return out


def frame_problems(
    arrays: Mapping[str, Any], cameras: Sequence[Mapping[str, Any]], fi: int, counts: np.ndarray
) -> list[tuple[str, str, str]]:
    """Read every chunk (depth and confidence, each camera) of one built frame: (camera, array, problem)."""
    out = []
    for ci, cam in enumerate(cameras):
        h, w = cam["height"], cam["width"]
        depth, err_d = read_checked(arrays["depth"], (fi, ci))
        conf, err_c = read_checked(arrays["confidence"], (fi, ci))
        found = [("depth", err_d)] * bool(err_d) + [("confidence", err_c)] * bool(err_c)
        if depth is not None:
            found += image_problems(depth[:h, :w], None if conf is None else conf[:h, :w], int(counts[ci]))
        out += [(cam["name"], a, p) for a, p in found]
    return out


__all__ = [
    "ARRAYS",
    "CameraEntry",
    "UNITS",
    "camera_entries",
    "check_scene_name",
    "file_signature",
    "frame_problems",
    "frame_source",
    "frames_digest",
    "image_problems",
    "missing_shards",
    "open_arrays",
    "read_checked",
    "read_counts",
    "scene_groups",
    "scene_problems",
    "shard_key",
]
