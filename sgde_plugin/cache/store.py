"""The prior cache (zarr v3): its layout and the read API, `PriorCache`.

Layout (format `sgde-prior-cache/1`), one zarr group per scene:

    <cache>/zarr.json                   attrs: format, config document, config fingerprint
    <cache>/<scene>/zarr.json           attrs: fingerprints, cameras (name, size, depth kind),
                                        frame ids, timestamps, frames digest, frame inputs,
                                        units, rig document, ready flag
    <cache>/<scene>/depth               float16  (frames, cameras, H, W)  metres, 0 = no prior
    <cache>/<scene>/confidence          uint8    (frames, cameras, H, W)  round(255 * confidence)
    <cache>/<scene>/valid_pixels        int32    (frames, cameras)        -1 = frame not written yet

depth / confidence are sharded by frame (one shard = one frame, one inner chunk = one camera
image), compressed with zstd and checksummed (crc32c) per camera image. Cameras of different sizes
are zero-padded to the largest one and cropped back on reading. `valid_pixels` of a frame is
written after its two shards, so it is the frame's "done" marker: readers and resumed builds
trust a frame only once it is there, and every store write is atomic (a rename on a local
folder, one PUT on object stores), so no reader ever sees half a frame. It also holds each camera
image's count of valid pixels, which every read checks, so a missing or damaged chunk is an error
naming the frame and camera, never an empty prior.

The other jobs live next to this module: `backends` (locations and stores), `lock` (the writer
lock), `layout` (scene layout and consistency checks), `creation` (create / resume / repair a
scene), `writer` (frame writes), `reading` (opening a cache, reading and checking one scene's
chunks, below `PriorCache`). Their names are re-exported here.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import Rig
from .backends import (  # noqa: F401 - re-exported
    Location,
    get_bytes,
    is_url,
    list_prefix,
    local_path,
    location_name,
    open_root,
    open_store,
    read_key,
    store_keys,
)
from .creation import ScenePlan, prepare_scene, remove_partial_files  # noqa: F401 - re-exported
from .fingerprints import ConfigLike, config_document, describe_config_change, digest, rig_document
from .layout import (  # noqa: F401 - re-exported
    ARRAYS,
    UNITS,
    CameraEntry,
    camera_entries,
    check_scene_name,
    frame_source,
    open_arrays,
    read_counts,
    scene_groups,
    scene_problems,
)
from .reading import OpenCache, OpenScene, damaged, open_cache
from .resample import resize_depth
from .writer import FLOAT16_MAX, FLOAT16_MIN_POSITIVE, SceneWriter, encode_prior  # noqa: F401 - re-exported


# --- reading ----------------------------------------------------------------------------------
class PriorCache:
    """Read-only access to a prior cache (contracts section 5).

    `PriorCache(path)` opens a local folder or an fsspec URL; `scene=` restricts it to one scene;
    `expect=` (a fingerprint) or `rig=` / `config=` refuse a cache built from other inputs.
    Picklable: each process (e.g. a DataLoader worker) reopens the store on first use.
    """

    def __init__(
        self,
        path: Location,
        scene: str | None = None,
        *,
        expect: str | None = None,
        rig: Rig | None = None,
        config: ConfigLike = None,
        algo_version: str | None = None,
        storage_options: Mapping[str, Any] | None = None,
    ):
        self.location = str(path) if isinstance(path, Path) else path
        self.scene = scene
        self.storage_options = dict(storage_options or {})
        self._state: OpenCache | None = None
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

    def _open(self) -> OpenCache:
        # a forked process (e.g. a DataLoader worker) reopens the store rather than sharing handles
        if self._state is None or self._state.pid != os.getpid():
            self._state = open_cache(self.location, self.scene, self.storage_options)
        return self._state

    # --- contract API -----------------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """The scene's fingerprint (a digest over all scenes' fingerprints when there are several)."""
        fps = {name: s.attrs["fingerprint"] for name, s in self._open().scenes.items()}
        if len(fps) == 1:
            return next(iter(fps.values()))
        return digest(fps)

    def fingerprints(self) -> dict[str, dict[str, str]]:
        """Per scene: {'fingerprint', 'rig', 'config'} digests."""
        return {
            name: {
                "fingerprint": s.attrs["fingerprint"],
                "rig": s.attrs["rig_fingerprint"],
                "config": s.attrs["config_fingerprint"],
            }
            for name, s in self._open().scenes.items()
        }

    def scenes(self) -> list[str]:
        """Scene names (zarr groups) in the cache."""
        return list(self._open().scenes)

    def frames(self, include_pending: bool = False) -> list[str]:
        """Frame ids whose priors are complete (all frames with include_pending), scene by scene."""
        out = []
        for s in self._open().scenes.values():
            out += [f for f, d in zip(s.frame_ids, s.done) if d or include_pending]
        return out

    def cameras(self) -> list[str]:
        """Camera names (union over scenes, in first-seen order)."""
        seen: dict[str, None] = {}
        for s in self._open().scenes.values():
            for c in s.cameras:
                seen.setdefault(c.name, None)
        return list(seen)

    def config(self) -> dict[str, Any]:
        """The configuration document the cache was built with (config, algo_version, format)."""
        return dict(self._open().root_attrs.get("config", {}))

    def check(self, rig: Rig | None = None, config: ConfigLike = None, algo_version: str | None = None) -> None:
        """Refuse (InputError) if the cache was built for another rig calibration or configuration."""
        state = self._open()
        if config is not None:
            doc = config_document(config, algo_version)
            if digest(doc) != state.root_attrs.get("config_fingerprint"):
                change = describe_config_change(state.root_attrs.get("config", {}), doc)
                raise InputError(
                    location_name(self.location), "fingerprint",
                    f"built with other prior settings ({change}); refusing to mix them",
                )
        if rig is not None:
            rig_fp = digest(rig_document(rig))
            for name, s in state.scenes.items():
                if s.attrs["rig_fingerprint"] != rig_fp:
                    raise InputError(
                        location_name(self.location), f"{name}: fingerprint",
                        "built for another calibration (cameras, extrinsics, pairs or masks differ); "
                        "refusing to mix them",
                    )

    def _locate(self, frame_id: str) -> tuple[OpenScene, int]:
        """The scene holding `frame_id` and the frame's index there; KeyError when absent or ambiguous."""
        state = self._open()
        if frame_id not in state.frames:
            raise KeyError(f"frame {frame_id!r} is not in the prior cache {location_name(self.location)}")
        if frame_id in state.duplicates:
            raise KeyError(f"frame {frame_id!r} is in several scenes; open the cache with scene=...")
        scene, fi = state.frames[frame_id]
        return state.scenes[scene], fi

    def check_frames(self, rig: Rig) -> None:
        """Refuse (InputError) when a cached frame of the rig was built from other images or poses (the
        cache of another scene whose frames share ids) or another timestamp."""
        state = self._open()
        for fr in rig.frames:
            if fr.id not in state.frames or fr.id in state.duplicates:
                continue
            scene, fi = state.frames[fr.id]
            attrs = state.scenes[scene].attrs
            sources = attrs.get("frame_inputs") or []
            stamp_ok = int(attrs["timestamps_us"][fi]) == int(fr.timestamp_us)
            if not stamp_ok or (fi < len(sources) and sources[fi] != frame_source(fr)):
                raise InputError(
                    location_name(self.location), f"{scene}: frames[{fr.id}]",
                    "was built from other images, poses or timestamps than this rig's (the cache of another "
                    "scene?); refusing to use it",
                )

    def check_done_markers(self, frame_ids: Iterable[str]) -> None:
        """Refuse (InputError naming scene and frame) a frame of `frame_ids` whose done marker does not
        decode: damage, not a frame still to build (`frames()` leaves both out)."""
        state = self._open()
        for fid in frame_ids:
            if fid in state.frames and fid not in state.duplicates:
                name, fi = state.frames[fid]
                if fi in state.scenes[name].unreadable:
                    raise damaged(location_name(self.location), name, fid, "*",
                                  "its done marker (valid_pixels) is unreadable")

    def get(self, frame_id: str, camera: str, size: tuple[int, int] | None = None,
            min_confidence: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(depth float32 metres, valid bool) at native size, or resized to size=(h, w) without
        inventing depths (min-pool of valid values, then nearest). A missing or corrupted chunk raises
        InputError naming the scene, frame and camera. With `min_confidence` > 0 only values whose
        stored confidence (steps of 1/255) rounds to at least it are kept (the rest read as no value)."""
        if not isinstance(min_confidence, numbers.Real) or not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be a number in [0, 1], got {min_confidence!r}")
        if min_confidence > 0:
            depth, _, conf = self.get_prior(frame_id, camera, size)
            depth = np.where(conf >= np.float32(min_confidence - 0.5 / 255), depth, 0).astype(np.float32)
            return depth, depth > 0
        size = check_size(size)
        scene, fi = self._locate(frame_id)
        _, cam, depth = scene.depth(frame_id, fi, camera)
        if size is not None and size != (cam.height, cam.width):
            (depth,) = resize_depth(depth, size)
        return depth, depth > 0

    def get_confidence(self, frame_id: str, camera: str, size: tuple[int, int] | None = None) -> np.ndarray:
        """Confidence float32 in [0, 1] (0 where there is no prior), native size or size=(h, w)."""
        return self.get_prior(frame_id, camera, size)[2]

    def get_prior(
        self, frame_id: str, camera: str, size: tuple[int, int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth, valid, confidence) of one camera image, resized together when size is given."""
        size = check_size(size)
        scene, fi = self._locate(frame_id)
        ci, cam, depth = scene.depth(frame_id, fi, camera)
        conf = scene.confidence(frame_id, fi, ci, cam, depth)
        if size is not None and size != (cam.height, cam.width):
            depth, conf = resize_depth(depth, size, conf)
        return depth, depth > 0, conf.astype(np.float32)

    def __repr__(self) -> str:
        return f"PriorCache({location_name(self.location)!r}, scenes={self.scenes()}, fingerprint={self.fingerprint})"


def check_size(size: Sequence[int] | None) -> tuple[int, int] | None:
    """A requested (height, width) as two positive ints (None stays None); ValueError otherwise."""
    if size is None:
        return None
    try:
        h, w = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be (height, width), got {size!r}") from None
    if h <= 0 or w <= 0 or (h, w) != tuple(size):
        raise ValueError(f"size must be two positive integers (height, width), got {size!r}")
    return h, w


def scene_arrays(location: Location, scene: str, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The raw zarr group, attributes and arrays of one scene (for info, verify and tests)."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    group = open_root(store, location, "r")[scene]
    return {"group": group, "attrs": dict(group.attrs), **{name: group[name] for name in ARRAYS}}


def list_scenes(location: Location, storage_options: Mapping[str, Any] | None = None) -> list[str]:
    """Scene names of a cache (including scenes whose creation was interrupted or whose metadata is damaged)."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    groups, broken = scene_groups(store, open_root(store, location, "r"))
    return sorted([*groups, *broken])


__all__ = [
    "ARRAYS",
    "CameraEntry",
    "PriorCache",
    "ScenePlan",
    "SceneWriter",
    "camera_entries",
    "check_scene_name",
    "check_size",
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
