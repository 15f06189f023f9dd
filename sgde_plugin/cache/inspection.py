"""`cache_info` (what a prior cache holds) and `verify_cache` (read every chunk, name bad ones)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import zarr
from zarr.abc.store import Store

from .backends import Location, location_name, open_root, open_store, store_keys
from .fingerprints import CACHE_FORMAT, digest
from .layout import frame_problems, missing_shards, open_arrays, read_counts, scene_groups, scene_problems
from .reading import damaged
from .store import list_scenes, scene_arrays


def cache_info(location: Location, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Scenes, frames (done / total), cameras with sizes and prior coverage, bytes, fingerprints."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    root = open_root(store, location, "r")
    rattrs = dict(root.attrs)
    keys = store_keys(location, storage_options)
    total_bytes = sum(keys.values())
    scenes, cameras = [], {}
    for name in list_scenes(location, storage_options):
        try:
            arrays = scene_arrays(location, name, storage_options)
        except Exception as exc:  # noqa: BLE001 - a damaged scene is reported, `cache verify` names it
            scenes.append({"scene": name, "frames_done": 0, "frames_total": 0,
                           "note": f"damaged ({type(exc).__name__}): see `sgde cache verify`"})
            continue
        attrs = arrays["attrs"]
        if not attrs.get("ready"):
            scenes.append({"scene": name, "frames_done": 0, "frames_total": 0, "note": "creation interrupted"})
            continue
        ids = list(attrs["frame_ids"])
        counts, unreadable = read_counts(arrays["valid_pixels"], len(ids))
        if unreadable:  # a frame that may or may not be built: counting it either way would be wrong
            fid = ids[min(unreadable)]
            raise damaged(location_name(location), name, fid, "*", "its done marker (valid_pixels) is unreadable")
        done = counts[:, 0] >= 0
        prefix = f"{name}/"
        scene_bytes = sum(v for k, v in keys.items() if k.startswith(prefix))
        cams = attrs["cameras"]
        pixels = np.array([c["width"] * c["height"] for c in cams], dtype=np.float64)
        n_done = int(done.sum())
        cov = counts[done].sum(axis=0) / (pixels * max(n_done, 1)) if n_done else np.zeros(len(cams))
        scenes.append(
            {
                "scene": name,
                "frames_done": n_done,
                "frames_total": len(ids),
                "cameras": len(cams),
                "coverage": float(counts[done].sum() / (pixels.sum() * n_done)) if n_done else 0.0,
                "bytes": int(scene_bytes),
                "bytes_per_image": float(scene_bytes / max(n_done * len(cams), 1)),
                "fingerprint": attrs.get("fingerprint"),
                "rig_fingerprint": attrs.get("rig_fingerprint"),
            }
        )
        for c, cv in zip(cams, cov):
            entry = cameras.setdefault(
                c["name"], {"camera": c["name"], "width": c["width"], "height": c["height"], "depth": c["depth"],
                            "_valid": 0.0, "_pixels": 0.0}
            )
            entry["_valid"] += float(cv) * c["width"] * c["height"] * n_done
            entry["_pixels"] += float(c["width"] * c["height"] * n_done)
    cam_rows = []
    for entry in cameras.values():
        valid, pix = entry.pop("_valid"), entry.pop("_pixels")
        cam_rows.append({**entry, "coverage": valid / pix if pix else 0.0})
    return {
        "location": location_name(location),
        "format": rattrs.get("format"),
        "config": rattrs.get("config", {}),
        "config_fingerprint": rattrs.get("config_fingerprint"),
        "bytes": int(total_bytes),
        "scenes": scenes,
        "cameras": cam_rows,
    }


def _problem(scene: str, frame: str, camera: str, array: str, problem: str) -> dict[str, str]:
    return {"scene": scene, "frame": frame, "camera": camera, "array": array, "problem": problem}


def _root_problems(root: zarr.Group, names: list[str], broken: Mapping[str, str]) -> list[dict[str, str]]:
    """Problems of the cache as a whole: root attributes, no scene at all, scenes that do not open."""
    out = [_problem(name, "-", "-", "zarr.json", why) for name, why in broken.items()]
    rattrs = dict(root.attrs)
    if rattrs.get("format") != CACHE_FORMAT:
        out.append(_problem("-", "-", "-", "zarr.json", f"format is {rattrs.get('format')!r}, not {CACHE_FORMAT!r}"))
    elif "config" in rattrs and digest(rattrs["config"]) != rattrs.get("config_fingerprint"):
        out.append(_problem("-", "-", "-", "zarr.json", "the config document does not match config_fingerprint"))
    if not names and not out:
        out.append(_problem("-", "-", "-", "-", "the cache holds no scene"))
    return out


def verify_cache(location: Location, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Read every chunk of every array of every scene and check the scene attributes against the arrays;
    problems are named by scene, frame and camera. A frame not built yet is a problem (incomplete cache)."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    root = open_root(store, location, "r")
    groups, broken = scene_groups(store, root)
    problems = _root_problems(root, list(groups), broken)
    tally = {"chunks": 0, "frames": 0}
    for name, group in groups.items():
        problems += _verify_scene(store, group, name, tally)
    return {
        "location": location_name(location),
        "ok": not problems,
        "chunks_read": tally["chunks"],
        "frames_checked": tally["frames"],
        "problems": problems,
    }


def _verify_scene(store: Store, group: zarr.Group, name: str, tally: dict[str, int]) -> list[dict[str, str]]:
    """Problems of one scene; `tally` counts chunks read and frames checked."""
    attrs = dict(group.attrs)
    if not attrs.get("ready"):
        return [_problem(name, "-", "-", "-", "scene creation was interrupted (run the build again)")]
    arrays, texts = open_arrays(group)
    texts += scene_problems(attrs, arrays)
    if texts:
        return [_problem(name, "-", "-", "attributes", t) for t in texts]
    ids, cams = list(attrs["frame_ids"]), attrs["cameras"]
    counts, unreadable = read_counts(arrays["valid_pixels"], len(ids))
    tally["chunks"] += len(ids)
    out = []
    missing = missing_shards(store, arrays, counts)
    for fi, fid in enumerate(ids):
        if fi in unreadable or counts[fi, 0] < 0:
            why = "done marker unreadable (checksum or decoding)" if fi in unreadable else "not built yet"
            out.append(_problem(name, fid, "*", "valid_pixels", why))
            continue
        tally["frames"] += 1
        tally["chunks"] += 2 * len(cams)
        if fi in missing:
            out.append(_problem(name, fid, "*", missing[fi].split()[0], missing[fi]))
        out += [_problem(name, fid, cam, array, p) for cam, array, p in frame_problems(arrays, cams, fi, counts[fi])]
    return out


__all__ = ["cache_info", "verify_cache"]
