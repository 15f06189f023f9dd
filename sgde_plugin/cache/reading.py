"""Reading side of the prior cache, below `PriorCache`: opening a cache and reading one scene's chunks.

`open_cache` opens the root and every finished scene (checking format, scene names and each scene's
attributes against its arrays) into an `OpenCache`; `OpenScene` reads one camera image of one frame,
checking the frame's done marker and each chunk against its written count of valid pixels, so a
missing or damaged chunk is an InputError naming scene, frame and camera.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr

from ..errors import InputError
from .backends import Location, location_name, open_root, open_store
from .fingerprints import CACHE_FORMAT
from .layout import CameraEntry, open_arrays, read_counts, scene_groups, scene_problems


def _float16_table() -> np.ndarray:
    """float32 value of every float16 bit pattern (read-only)."""
    table = np.arange(1 << 16, dtype=np.uint16).view(np.float16).astype(np.float32)
    table.flags.writeable = False
    return table


# a gather through this table is about 3x faster than ndarray.astype for float16 -> float32 (the cache's
# depth reads spent a third of their time in that conversion)
_FLOAT16_TO_32 = _float16_table()


def float16_to_float32(values: np.ndarray) -> np.ndarray:
    """float16 array -> float32, the same values as `values.astype(np.float32)`."""
    return _FLOAT16_TO_32.take(np.ascontiguousarray(values).view(np.uint16))


def damaged(where: str, scene: str, frame_id: str, camera: str, problem: str) -> InputError:
    """The one-line error of a damaged camera image (names the repair)."""
    return InputError(
        where, f"{scene}/{frame_id}/{camera}",
        f"{problem}: the cache is damaged; `sgde prior ... --repair` rebuilds the frame",
    )


@dataclass(eq=False)
class OpenScene:
    """One finished scene of an open cache: its attributes, cameras, arrays and done markers."""

    where: str  # the cache's location, for messages
    group: zarr.Group
    attrs: dict[str, Any]
    cameras: list[CameraEntry]
    frame_ids: list[str]
    arrays: dict[str, zarr.Array]
    counts: np.ndarray  # (frames, cameras) valid pixels written, -1 = frame not built
    unreadable: set[int]  # frames whose done marker does not decode
    camera_index: dict[str, int] = field(init=False)
    done: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.camera_index = {c.name: i for i, c in enumerate(self.cameras)}
        self.done = self.counts[:, 0] >= 0

    @classmethod
    def open(cls, group: zarr.Group, name: str, where: str) -> OpenScene | None:
        """A scene after checking its attributes against its arrays (None while its creation is
        unfinished); InputError names a damaged scene."""
        attrs = dict(group.attrs)
        if not attrs.get("ready"):
            return None
        arrays, problems = open_arrays(group)
        problems += scene_problems(attrs, arrays)
        if problems:
            raise InputError(where, name, f"damaged: {problems[0]} (`sgde cache verify` lists all)")
        ids = list(attrs["frame_ids"])
        counts, unreadable = read_counts(arrays["valid_pixels"], len(ids))
        cams = [CameraEntry(**e) for e in attrs["cameras"]]
        return cls(where, group, attrs, cams, ids, arrays, counts, unreadable)

    @property
    def name(self) -> str:
        """The scene's group name."""
        return self.group.basename

    def slot(self, frame_id: str, fi: int, camera: str) -> tuple[int, CameraEntry]:
        """(camera index, camera) of a built frame; re-reads the done marker of a frame not built when
        the scene was opened (the build may have progressed). KeyError / InputError otherwise."""
        if camera not in self.camera_index:
            raise KeyError(f"camera {camera!r} is not in scene {self.name!r} of the prior cache")
        if fi in self.unreadable:
            raise damaged(self.where, self.name, frame_id, camera, "its done marker (valid_pixels) is unreadable")
        if not self.done[fi]:
            counts, bad = read_counts(self.arrays["valid_pixels"][fi : fi + 1], 1)
            if bad:
                raise damaged(self.where, self.name, frame_id, camera,
                              "its done marker (valid_pixels) is unreadable")
            self.counts[fi] = counts[0]
            self.done[fi] = counts[0, 0] >= 0
            if not self.done[fi]:
                raise KeyError(f"frame {frame_id!r} of scene {self.name!r} is not built yet")
        ci = self.camera_index[camera]
        return ci, self.cameras[ci]

    def read(self, array: str, fi: int, ci: int, cam: CameraEntry, frame_id: str) -> np.ndarray:
        """One camera image of `array` cropped to the camera's size; a chunk that does not decode is an InputError."""
        try:
            return np.asarray(self.arrays[array][fi, ci, : cam.height, : cam.width])
        except Exception as exc:  # noqa: BLE001 - a chunk that does not decode is a damaged cache
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            what = "checksum mismatch" if "checksum" in text.lower() else f"{type(exc).__name__}: {text[:100]}"
            raise damaged(self.where, self.name, frame_id, cam.name, f"{array} chunk unreadable ({what})") from None

    def depth(self, frame_id: str, fi: int, camera: str) -> tuple[int, CameraEntry, np.ndarray]:
        """(camera index, camera, float32 depth) of one camera image, checked against its count of valid pixels."""
        ci, cam = self.slot(frame_id, fi, camera)
        raw = self.read("depth", fi, ci, cam, frame_id)
        # stored depths are 0 or positive finite float16: counting non-zero bit patterns counts valid pixels
        n = int(np.count_nonzero(raw.view(np.uint16)))
        if n != int(self.counts[fi, ci]):
            raise damaged(
                self.where, self.name, frame_id, camera,
                f"depth chunk missing or damaged ({n} valid pixels read, {int(self.counts[fi, ci])} written)",
            )
        return ci, cam, float16_to_float32(raw)

    def confidence(self, frame_id: str, fi: int, ci: int, cam: CameraEntry, depth: np.ndarray) -> np.ndarray:
        """Float32 confidence in [0, 1] of one camera image; an InputError when it is missing under depths."""
        conf = self.read("confidence", fi, ci, cam, frame_id).astype(np.float32) / 255.0
        if self.counts[fi, ci] > 0 and not (conf[depth > 0] != 0).any():
            raise damaged(self.where, self.name, frame_id, cam.name, "confidence chunk missing")
        return conf


@dataclass(eq=False)
class OpenCache:
    """An opened cache in one process: root attributes, finished scenes, and where each frame id lives."""

    pid: int
    root: zarr.Group
    root_attrs: dict[str, Any]
    scenes: dict[str, OpenScene]
    frames: dict[str, tuple[str, int]]  # frame id -> (scene, index), the first scene holding it
    duplicates: set[str]  # frame ids held by several scenes


def open_cache(location: Location, scene: str | None, storage_options: Mapping[str, Any]) -> OpenCache:
    """Open a cache's root and its finished scenes (only `scene` when given); InputError for a location
    that is not a cache of this format, an unknown or damaged scene, or a cache without a finished scene."""
    where = location_name(location)
    store = open_store(location, read_only=True, storage_options=storage_options)
    root = open_root(store, location, "r")
    rattrs = dict(root.attrs)
    if rattrs.get("format") != CACHE_FORMAT:
        raise InputError(where, "format", f"expected {CACHE_FORMAT!r}, found {rattrs.get('format')!r}")
    groups, broken = scene_groups(store, root)
    names = sorted(groups)
    if scene is not None:
        if scene not in groups and scene not in broken:
            raise InputError(where, scene, f"no such scene (has {', '.join(names)})")
        names = [scene] if scene in groups else []
        broken = {k: v for k, v in broken.items() if k == scene}
    for name, why in broken.items():
        raise InputError(where, name, f"damaged: {why} (`sgde cache verify` lists all)")
    scenes: dict[str, OpenScene] = {}
    frame_index: dict[str, tuple[str, int]] = {}
    duplicates: set[str] = set()
    for name in names:
        opened = OpenScene.open(groups[name], name, where)
        if opened is None:
            continue
        scenes[name] = opened
        for i, fid in enumerate(opened.frame_ids):
            if fid in frame_index:
                duplicates.add(fid)
            frame_index.setdefault(fid, (name, i))
    if not scenes:
        raise InputError(where, None, "holds no (finished) scene")
    return OpenCache(os.getpid(), root, rattrs, scenes, frame_index, duplicates)


__all__ = ["OpenCache", "OpenScene", "damaged", "float16_to_float32", "open_cache"]
