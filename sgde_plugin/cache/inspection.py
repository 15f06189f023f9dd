"""`cache_info` (what a prior cache holds) and `verify_cache` (read every chunk, name bad ones)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .store import list_scenes, location_name, open_root, open_store, scene_arrays, store_keys


def cache_info(location: Any, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Scenes, frames (done / total), cameras with sizes and prior coverage, bytes, fingerprints."""
    store = open_store(location, read_only=True, storage_options=storage_options)
    root = open_root(store, location, "r")
    rattrs = dict(root.attrs)
    keys = store_keys(location, storage_options)
    total_bytes = sum(keys.values())
    scenes, cameras = [], {}
    for name in list_scenes(location, storage_options):
        arrays = scene_arrays(location, name, storage_options)
        attrs = arrays["attrs"]
        if not attrs.get("ready"):
            scenes.append({"scene": name, "frames_done": 0, "frames_total": 0, "note": "creation interrupted"})
            continue
        ids = list(attrs["frame_ids"])
        counts = np.asarray(arrays["valid_pixels"][: len(ids)])
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


def _read_check(array: Any, index: tuple[int, ...]) -> tuple[np.ndarray | None, str | None]:
    try:
        return np.asarray(array[index]), None
    except Exception as exc:  # noqa: BLE001 - any decoding failure is a finding, not a crash
        text = str(exc).split("\n")[0]
        if "checksum" in text.lower():
            return None, "checksum mismatch (corrupted or truncated)"
        return None, f"unreadable ({type(exc).__name__}: {text})"


def verify_cache(location: Any, storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Read every chunk of every scene; problems are named by scene, frame and camera. A frame that
    is not built yet is a problem too (the cache is incomplete)."""
    problems: list[dict[str, Any]] = []
    chunks = 0
    frames_checked = 0
    for name in list_scenes(location, storage_options):
        arrays = scene_arrays(location, name, storage_options)
        attrs = arrays["attrs"]
        if not attrs.get("ready"):
            problems.append(_problem(name, "-", "-", "-", "scene creation was interrupted (run the build again)"))
            continue
        ids = list(attrs["frame_ids"])
        if min(arrays[a].shape[0] for a in ("depth", "confidence", "valid_pixels")) < len(ids):
            problems.append(_problem(name, "-", "-", "-", "arrays shorter than the frame list (run the build again)"))
            continue
        for fi, fid in enumerate(ids):
            counts, err = _read_check(arrays["valid_pixels"], (fi,))
            chunks += 1
            if err is not None or counts[0] < 0:
                problems.append(_problem(name, fid, "*", "valid_pixels", err or "not built yet"))
                continue
            frames_checked += 1
            for ci, cam in enumerate(attrs["cameras"]):
                chunks += 2
                for p in _check_image(arrays, fi, ci, cam, int(counts[ci])):
                    problems.append(_problem(name, fid, cam["name"], *p))
    return {
        "location": location_name(location),
        "ok": not problems,
        "chunks_read": chunks,
        "frames_checked": frames_checked,
        "problems": problems,
    }


def _check_image(arrays: Mapping[str, Any], fi: int, ci: int, cam: Mapping[str, Any], count: int) -> list[tuple]:
    """Problems (array, text) of one camera image of one frame."""
    out = []
    depth, err_d = _read_check(arrays["depth"], (fi, ci))
    conf, err_c = _read_check(arrays["confidence"], (fi, ci))
    if err_d:
        out.append(("depth", err_d))
    if err_c:
        out.append(("confidence", err_c))
    if depth is None:
        return out
    inside = depth[: cam["height"], : cam["width"]]
    valid = int((inside > 0).sum())
    if valid != count:
        out.append(("depth", f"{valid} valid pixels read, {count} written (data lost)"))
    if not np.all(np.isfinite(inside)) or (inside < 0).any():
        out.append(("depth", "non-finite or negative depths"))
    if conf is not None and (conf[: cam["height"], : cam["width"]][inside <= 0] != 0).any():
        out.append(("confidence", "confidence where there is no depth"))
    return out


__all__ = ["cache_info", "verify_cache"]
