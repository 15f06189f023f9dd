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
scene), `writer` (frame writes). Their names are re-exported here.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

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
from .fingerprints import CACHE_FORMAT, ConfigLike, config_document, describe_config_change, digest, rig_document
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
        groups, broken = scene_groups(store, root)
        names = sorted(groups)
        if self.scene is not None:
            if self.scene not in groups and self.scene not in broken:
                raise InputError(location_name(self.location), self.scene, f"no such scene (has {', '.join(names)})")
            names = [self.scene] if self.scene in groups else []
            broken = {k: v for k, v in broken.items() if k == self.scene}
        for name, why in broken.items():
            raise InputError(location_name(self.location), name, f"damaged: {why} (`sgde cache verify` lists all)")
        scenes: dict[str, dict[str, Any]] = {}
        frame_index: dict[str, tuple[str, int]] = {}
        duplicates: set[str] = set()
        for name in names:
            state = self._open_scene(groups[name], name)
            if state is None:
                continue
            scenes[name] = state
            for i, fid in enumerate(state["frame_ids"]):
                if fid in frame_index:
                    duplicates.add(fid)
                frame_index.setdefault(fid, (name, i))
        if not scenes:
            raise InputError(location_name(self.location), None, "holds no (finished) scene")
        self._state = {
            "pid": os.getpid(), "root": root, "root_attrs": rattrs, "scenes": scenes, "frames": frame_index,
            "dup": duplicates,
        }
        return self._state

    def _open_scene(self, group: zarr.Group, name: str) -> dict[str, Any] | None:
        """One scene's arrays and attributes, after checking them against each other (None while the
        scene's creation is unfinished); InputError names a damaged scene."""
        where = location_name(self.location)
        attrs = dict(group.attrs)
        if not attrs.get("ready"):
            return None
        arrays, problems = open_arrays(group)
        problems += scene_problems(attrs, arrays)
        if problems:
            raise InputError(where, name, f"damaged: {problems[0]} (`sgde cache verify` lists all)")
        cams = [CameraEntry(**e) for e in attrs["cameras"]]
        ids = list(attrs["frame_ids"])
        counts, unreadable = read_counts(arrays["valid_pixels"], len(ids))
        return {
            "group": group,
            "attrs": attrs,
            "cameras": cams,
            "camera_index": {c.name: i for i, c in enumerate(cams)},
            "frame_ids": ids,
            **arrays,
            "counts": counts,
            "unreadable": unreadable,
            "done": counts[:, 0] >= 0,
        }

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

    def config(self) -> dict[str, Any]:
        """The configuration document the cache was built with (config, algo_version, format)."""
        return dict(self._open()["root_attrs"].get("config", {}))

    def check(self, rig: Rig | None = None, config: ConfigLike = None, algo_version: str | None = None) -> None:
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

    def check_frames(self, rig: Rig) -> None:
        """Refuse (InputError) when a cached frame of the rig was built from other images or poses (the
        cache of another scene whose frames share ids) or another timestamp."""
        state = self._open()
        for fr in rig.frames:
            if fr.id not in state["frames"] or fr.id in state["dup"]:
                continue
            scene, fi = state["frames"][fr.id]
            attrs = state["scenes"][scene]["attrs"]
            sources = attrs.get("frame_inputs") or []
            stamp_ok = int(attrs["timestamps_us"][fi]) == int(fr.timestamp_us)
            if not stamp_ok or (fi < len(sources) and sources[fi] != frame_source(fr)):
                raise InputError(
                    location_name(self.location), f"{scene}: frames[{fr.id}]",
                    "was built from other images, poses or timestamps than this rig's (the cache of another "
                    "scene?); refusing to use it",
                )

    def _slot(self, frame_id: str, camera: str) -> tuple[dict[str, Any], int, int, CameraEntry]:
        scene, fi = self._locate(frame_id)
        s = self._open()["scenes"][scene]
        if camera not in s["camera_index"]:
            raise KeyError(f"camera {camera!r} is not in scene {scene!r} of the prior cache")
        if fi in s["unreadable"]:
            raise self._damaged(scene, frame_id, camera, "its done marker (valid_pixels) is unreadable")
        if not s["done"][fi]:
            # the build may have progressed since the cache was opened
            counts, bad = read_counts(s["valid_pixels"][fi : fi + 1], 1)
            if bad:
                raise self._damaged(scene, frame_id, camera, "its done marker (valid_pixels) is unreadable")
            s["counts"][fi] = counts[0]
            s["done"][fi] = counts[0, 0] >= 0
            if not s["done"][fi]:
                raise KeyError(f"frame {frame_id!r} of scene {scene!r} is not built yet")
        ci = s["camera_index"][camera]
        return s, fi, ci, s["cameras"][ci]

    def _damaged(self, scene: str, frame_id: str, camera: str, problem: str) -> InputError:
        return InputError(
            location_name(self.location), f"{scene}/{frame_id}/{camera}",
            f"{problem}: the cache is damaged; `sgde prior ... --repair` rebuilds the frame",
        )

    def _read(self, s: dict[str, Any], name: str, fi: int, ci: int, cam: CameraEntry, frame_id: str) -> np.ndarray:
        try:
            return np.asarray(s[name][fi, ci, : cam.height, : cam.width])
        except Exception as exc:  # noqa: BLE001 - a chunk that does not decode is a damaged cache
            text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            what = "checksum mismatch" if "checksum" in text.lower() else f"{type(exc).__name__}: {text[:100]}"
            raise self._damaged(s["group"].basename, frame_id, cam.name, f"{name} chunk unreadable ({what})") from None

    def _depth(self, frame_id: str, camera: str) -> tuple[dict[str, Any], int, int, CameraEntry, np.ndarray]:
        """The stored depth of one camera image, checked against its written count of valid pixels."""
        s, fi, ci, cam = self._slot(frame_id, camera)
        raw = self._read(s, "depth", fi, ci, cam, frame_id)
        # stored depths are 0 or positive finite float16: counting non-zero bit patterns counts valid pixels
        n = int(np.count_nonzero(raw.view(np.uint16)))
        if n != int(s["counts"][fi, ci]):
            raise self._damaged(
                s["group"].basename, frame_id, camera,
                f"depth chunk missing or damaged ({n} valid pixels read, {int(s['counts'][fi, ci])} written)",
            )
        return s, fi, ci, cam, raw.astype(np.float32)

    def get(self, frame_id: str, camera: str, size: tuple[int, int] | None = None,
            min_confidence: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(depth float32 metres, valid bool) at native size, or resized to size=(h, w) without
        inventing depths (min-pool of valid values, then nearest). A missing or corrupted chunk raises
        InputError naming the scene, frame and camera. With `min_confidence` > 0 only values whose
        stored confidence (steps of 1/255) rounds to at least it are kept (the rest read as no value)."""
        if min_confidence > 0:
            depth, _, conf = self.get_prior(frame_id, camera, size)
            depth = np.where(conf >= np.float32(min_confidence - 0.5 / 255), depth, 0).astype(np.float32)
            return depth, depth > 0
        size = check_size(size)
        _, _, _, cam, depth = self._depth(frame_id, camera)
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
        s, fi, ci, cam, depth = self._depth(frame_id, camera)
        conf = self._read(s, "confidence", fi, ci, cam, frame_id).astype(np.float32) / 255.0
        if s["counts"][fi, ci] > 0 and not (conf[depth > 0] != 0).any():
            raise self._damaged(s["group"].basename, frame_id, camera, "confidence chunk missing")
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
