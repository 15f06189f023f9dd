"""Writing whole frames of a cached scene: encoding, shards, the done marker and the fingerprint check."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
import zarr
from zarr.core.sync import sync

from ..errors import InputError
from ..stereo.config import FLOAT16_MAX, FLOAT16_MIN_POSITIVE
from .backends import Location, get_bytes, location_name, open_store
from .layout import CameraEntry, shard_key


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
    """Writes whole frames of one scene; picklable (each process opens the store itself).

    With `expect` (the build's fingerprint) every frame write first re-reads the scene's attributes
    and refuses (InputError) when the scene is no longer the one the build prepared, before its data
    and again before its done marker."""

    def __init__(
        self, location: Location, scene: str, storage_options: Mapping[str, Any] | None = None,
        expect: str | None = None,
    ):
        self.location = location
        self.scene = scene
        self.storage_options = dict(storage_options or {})
        self.expect = expect
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

    def check_fingerprint(self, index: int) -> None:
        """Refuse when the scene's stored fingerprint is not the expected one (or the scene is gone)."""
        if self.expect is None:
            return
        group = self._open()
        raw = get_bytes(group.store_path.store, f"{self.scene}/zarr.json")
        attrs = json.loads(raw).get("attributes", {}) if raw else {}
        if attrs.get("fingerprint") != self.expect or not attrs.get("ready"):
            found = attrs.get("fingerprint", "no scene")
            raise InputError(
                location_name(self.location), f"{self.scene}: fingerprint",
                f"changed to {found} while this build (fingerprint {self.expect}) was writing frame {index}; "
                "another build with other inputs took the scene: stopping without writing",
            )

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
        self.check_fingerprint(index)
        # a frame that is not marked done may hold leftovers of an interrupted attempt: drop them
        # so the new shards never merge with them
        self._delete_shards(index)
        depth_arr[index] = d_all
        conf_arr[index] = c_all
        self.check_fingerprint(index)
        group["valid_pixels"][index] = counts
        return int(counts.sum())

    def _delete_shards(self, index: int) -> None:
        group = self._group
        assert group is not None
        for name in ("depth", "confidence"):
            arr = group[name]
            sync(arr.store_path.store.delete(shard_key(arr, index)))


__all__ = ["FLOAT16_MAX", "FLOAT16_MIN_POSITIVE", "SceneWriter", "encode_prior"]
