"""Creating a cached scene, or reopening it to resume, extend or repair a build.

`prepare_scene` runs before any frame is computed. It creates the cache and the scene, or checks
that the cached scene was built from the same calibration, prior settings and frames; it then
lists the frames still to build: those never finished, plus those found damaged (a missing shard
or an unreadable done marker always; every chunk read back with `repair=True`). The done marker
of a damaged frame is cleared before it is rebuilt, so readers never see it half rewritten.
A build calls it while holding the cache's writer lock (`lock.writer_lock`); only then is a scene
whose creation was interrupted deleted and created afresh.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
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
from ..rig import Rig
from .backends import Location, local_path, location_name, open_store
from .fingerprints import CACHE_FORMAT, describe_config_change, rig_document
from .layout import (
    ARRAYS,
    UNITS,
    CameraEntry,
    camera_entries,
    check_scene_name,
    frame_problems,
    frame_source,
    frames_digest,
    missing_shards,
    open_arrays,
    read_counts,
    scene_groups,
    scene_problems,
)


def _compressors(itemsize: int) -> list[Any]:
    # byte shuffle + zstd: ~20% smaller than plain zstd on float16 priors; crc32c per camera image
    return [BloscCodec(cname="zstd", clevel=5, shuffle="shuffle", typesize=itemsize), Crc32cCodec()]


def _refusal(location: Location, scene: str | None, cached: Mapping[str, Any], parts: Mapping[str, Any]) -> InputError:
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
    """What a build has to do for one scene: the frame indices still missing, and the damaged frames
    among them ({frame id: what was wrong})."""

    scene: str
    frame_ids: list[str]
    pending: list[int]
    already_done: int
    damaged: dict[str, str] = field(default_factory=dict)


def prepare_scene(
    location: Location,
    scene: str,
    rig: Rig,
    parts: Mapping[str, Any],
    storage_options: Mapping[str, Any] | None = None,
    *,
    repair: bool = False,
    locked: bool = False,
) -> ScenePlan:
    """Create the cache and the scene, or reopen them after checking fingerprints and frames; returns
    the frames still to build. `parts` is fingerprint_parts(...) plus 'config_document'. `repair` reads
    every chunk to find damaged frames; `locked` says the caller holds the writer lock."""
    check_scene_name(scene)
    if not rig.frames:
        raise InputError(location_name(location), scene, "the rig has no frames")
    store = open_store(location, read_only=False, storage_options=storage_options)
    root = _prepare_root(store, location, parts)
    groups, broken = scene_groups(store, root)
    if scene in broken:
        raise InputError(location_name(location), scene, f"damaged: {broken[scene]}; it cannot be repaired in "
                         "place: build into another --out")
    group = groups.get(scene)
    if group is not None:
        if not group.attrs.get("ready"):
            if not locked and group.attrs.get("fingerprint") != parts["fingerprint"]:
                raise InputError(
                    location_name(location), scene, "is being created by another build with other inputs (or its "
                    "creation was interrupted): wait for that build, or delete the scene, or use another --out",
                )
            # a creation interrupted before any frame was written: start the scene afresh
            sync(store.delete_dir(scene))
            group = None
    if group is None:
        return _create_scene(root, scene, rig, parts)
    return _reopen_scene(root, group, store, location, scene, rig, parts, repair)


def _prepare_root(store: Store, location: Location, parts: Mapping[str, Any]) -> zarr.Group:
    try:
        root = zarr.open_group(store, mode="r+", zarr_format=3)
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError):
        path = local_path(location) if isinstance(store, zarr.storage.LocalStore) else None
        if path is not None and path.is_dir():
            for leftover in Path(path).glob("*.partial"):  # of an interrupted creation
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
    except (ValueError, TypeError) as exc:
        raise InputError(location_name(location), "zarr.json", f"unreadable ({type(exc).__name__})") from None
    attrs = dict(root.attrs)
    if attrs.get("format") != CACHE_FORMAT:
        raise InputError(location_name(location), "format", f"expected {CACHE_FORMAT!r}, found {attrs.get('format')!r}")
    if attrs.get("config_fingerprint") != parts["config"]:
        cached = {"config_fingerprint": attrs.get("config_fingerprint"), "config": attrs.get("config", {})}
        cached["fingerprint"] = attrs.get("config_fingerprint")
        raise _refusal(location, None, cached, {**parts, "fingerprint": parts["config"]})
    return root


def _frame_lists(rig: Rig) -> tuple[list[str], dict[str, int], dict[str, str]]:
    ids = [fr.id for fr in rig.frames]
    return ids, {fr.id: int(fr.timestamp_us) for fr in rig.frames}, {fr.id: frame_source(fr) for fr in rig.frames}


def _create_scene(root: zarr.Group, scene: str, rig: Rig, parts: Mapping[str, Any]) -> ScenePlan:
    cameras = camera_entries(rig)
    ids, stamps, sources = _frame_lists(rig)
    attrs = {
        "format": CACHE_FORMAT,
        "ready": False,
        "fingerprint": parts["fingerprint"],
        "rig_fingerprint": parts["rig"],
        "config_fingerprint": parts["config"],
        "cameras": [c.to_dict() for c in cameras],
        "frame_ids": list(ids),
        "timestamps_us": [int(stamps[i]) for i in ids],
        "frames_digest": frames_digest(ids, [stamps[i] for i in ids]),
        "frame_inputs": [sources[i] for i in ids],
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


def _check_same_scene(location: Location, scene: str, attrs: Mapping[str, Any], rig: Rig) -> None:
    """Refuse frames whose timestamp or source (rig entry, image sizes) differs from the cached ones."""
    ids, stamps, sources = _frame_lists(rig)
    known = list(attrs["frame_ids"])
    known_stamps = dict(zip(known, attrs["timestamps_us"]))
    known_sources = dict(zip(known, attrs.get("frame_inputs") or []))
    for fid in ids:
        if fid in known_stamps and int(known_stamps[fid]) != stamps[fid]:
            raise InputError(
                location_name(location), f"{scene}: frames[{fid}]",
                f"timestamp {stamps[fid]} differs from the cached {known_stamps[fid]}",
            )
        if fid in known_sources and known_sources[fid] != sources[fid]:
            raise InputError(
                location_name(location), f"{scene}: frames[{fid}]",
                "its images or poses differ from the ones the cache was built from (another scene?); "
                "refusing to mix them: build into another --out",
            )


def _extend(group: zarr.Group, arrays: Mapping[str, Any], attrs: Mapping[str, Any], rig: Rig) -> list[str]:
    """Append the rig's frames that the scene lacks; returns the scene's whole frame list."""
    ids, stamps, sources = _frame_lists(rig)
    known = list(attrs["frame_ids"])
    added = [fid for fid in ids if fid not in set(known)]
    all_ids = known + added
    # arrays first, then the frame list, so an interrupted extension is redone
    for name in ARRAYS:
        arr = arrays[name]
        if arr.shape[0] < len(all_ids):
            arr.resize((len(all_ids), *arr.shape[1:]))
    if added:
        all_stamps = [int(t) for t in attrs["timestamps_us"]] + [stamps[i] for i in added]
        update: dict[str, Any] = {"frame_ids": all_ids, "timestamps_us": all_stamps,
                                  "frames_digest": frames_digest(all_ids, all_stamps)}
        if "frame_inputs" in attrs:
            update["frame_inputs"] = list(attrs["frame_inputs"]) + [sources[i] for i in added]
        group.attrs.update(update)
    return all_ids


def _reopen_scene(
    root: zarr.Group, group: zarr.Group, store: Store, location: Location, scene: str, rig: Rig,
    parts: Mapping[str, Any], repair: bool,
) -> ScenePlan:
    attrs = dict(group.attrs)
    arrays, problems = open_arrays(group)
    problems += scene_problems(attrs, arrays)
    if problems:
        raise InputError(location_name(location), scene, f"damaged ({problems[0]}); it cannot be repaired in "
                         "place: build into another --out")
    if attrs.get("fingerprint") != parts["fingerprint"]:
        raise _refusal(location, scene, {**attrs, "config": dict(root.attrs).get("config", {})}, parts)
    if [CameraEntry(**e) for e in attrs["cameras"]] != camera_entries(rig):
        raise InputError(location_name(location), f"{scene}: cameras", "differ from the rig's cameras")
    _check_same_scene(location, scene, attrs, rig)
    all_ids = _extend(group, arrays, attrs, rig)
    index = {fid: i for i, fid in enumerate(all_ids)}
    counts, unreadable = read_counts(arrays["valid_pixels"], len(all_ids))
    wanted = [index[fr.id] for fr in rig.frames]
    damaged = _find_damaged(store, arrays, attrs["cameras"], counts, unreadable, wanted, repair)
    for fi in damaged:  # cleared before the rebuild, so no reader sees the frame half rewritten
        arrays["valid_pixels"][fi] = np.full(counts.shape[1], -1, dtype=np.int32)
        counts[fi] = -1
    pending = [i for i in wanted if counts[i, 0] < 0]
    return ScenePlan(scene, all_ids, pending, len(wanted) - len(pending),
                     {all_ids[fi]: why for fi, why in sorted(damaged.items())})


def _find_damaged(
    store: Store, arrays: Mapping[str, Any], cameras: list[Mapping[str, Any]], counts: np.ndarray,
    unreadable: set[int], wanted: list[int], repair: bool,
) -> dict[int, str]:
    """{frame index: problem} of the wanted frames that are damaged (every chunk read when `repair`)."""
    damaged = {fi: "done marker (valid_pixels) unreadable" for fi in unreadable}
    for fi, why in missing_shards(store, arrays, counts).items():
        damaged.setdefault(fi, why)
    if repair:
        for fi in wanted:
            if fi in damaged or counts[fi, 0] < 0:
                continue
            found = frame_problems(arrays, cameras, fi, counts[fi])
            if found:
                cam, array, problem = found[0]
                damaged[fi] = f"{cam}: {array}: {problem}"
    keep = set(wanted)
    return {fi: why for fi, why in damaged.items() if fi in keep}


def remove_partial_files(location: Location, scene: str) -> int:
    """Delete temporary files left by writes that a kill interrupted (local folders only)."""
    import os

    path = local_path(location)
    if path is None:
        return 0
    count = 0
    for dirpath, _, files in os.walk(path / scene):
        for f in files:
            if f.endswith(".partial"):
                (Path(dirpath) / f).unlink(missing_ok=True)
                count += 1
    return count


__all__ = ["ScenePlan", "prepare_scene", "remove_partial_files"]
