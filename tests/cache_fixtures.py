"""Shared cache-test set-up: a tiny three-pinhole rig and builds with the synthetic stand-in compute."""

from __future__ import annotations

import numpy as np

from sgde_plugin.cache.backends import Location, read_key, store_keys
from sgde_plugin.cache.build import BuildReport, build_cache
from sgde_plugin.cache.synthetic import SyntheticPriorCompute
from sgde_plugin.rig import Rig, rig_from_dict

CONFIG = {"matcher": "stand-in", "scale": 0.5}
ALGO = "test-1"


def tiny_rig(frames: int = 4, shift_m: float = 0.0) -> Rig:
    """Three pinholes (one smaller than the others) in a ring, `frames` frames."""
    cams = []
    for i, (name, w, h) in enumerate([("A", 64, 40), ("B", 64, 40), ("C", 48, 32)]):
        yaw = 2 * np.pi * i / 3
        T = np.eye(4)
        T[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        T[0, 3] = shift_m if name == "A" else 0.0
        K = [[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1]]
        cams.append({"name": name, "model": "pinhole", "width": w, "height": h, "K": K, "dist": None,
                     "sensor_to_ego": T.tolist()})
    doc = {"format": "sgde-rig/1", "cameras": cams, "ring": ["A", "B", "C"],
           "frames": [{"id": f"{i:06d}", "timestamp_us": 1000 * i} for i in range(frames)]}
    return rig_from_dict(doc)


def build(rig: Rig, out: Location, **kw: object) -> BuildReport:
    """Build with the synthetic stand-in compute."""
    kw.setdefault("compute", SyntheticPriorCompute(rig))
    return build_cache(rig, out, kw.pop("config", CONFIG), algo_version=ALGO, show_progress=False, **kw)


def content(location: Location) -> dict[str, bytes | None]:
    """Every key of a store with its bytes (temporary files excluded)."""
    return {k: read_key(location, k) for k in store_keys(location) if not k.endswith(".partial")}
