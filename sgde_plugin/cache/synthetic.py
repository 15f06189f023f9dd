"""A cheap, deterministic stand-in for the stereo prior (tests, benchmarks of the store alone).

`SyntheticPriorCompute(rig)(frame_id)` returns, per camera, a prior-like map: a ground plane and
a few boxes, present only in a strip at each side of the image (where neighbouring cameras
overlap), with depth quantised the way a disparity of 1/16 pixel quantises it, holes, and a
confidence. The same (seed, frame, camera) always gives the same bytes, in any process.
"""

from __future__ import annotations

import time
import zlib

import numpy as np

from ..rig import Rig


def synthetic_prior(
    height: int, width: int, seed: int, overlap: float = 0.22, max_depth: float = 80.0
) -> tuple[np.ndarray, np.ndarray]:
    """One synthetic prior (depth float32 metres with 0 = none, confidence float32 in [0, 1])."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    f = 0.8 * width
    horizon = 0.5 * height
    ground = 1.5 * f / np.maximum(v - horizon, 1e-3)
    depth = np.where(v > horizon + 1, ground, 30.0 + 8.0 * np.sin(u / (0.06 * width)))
    for _ in range(6):
        bw, bh = int(rng.integers(width // 20, width // 5)), int(rng.integers(height // 10, height // 3))
        x0, y0 = int(rng.integers(0, width - bw)), int(rng.integers(0, height - bh))
        depth[y0 : y0 + bh, x0 : x0 + bw] = rng.uniform(4.0, 40.0)
    fb = 0.25 * f  # focal length x baseline at half resolution, a 0.5 m baseline
    disp = np.maximum(np.round(fb / depth * 16.0) / 16.0, 1.0 / 16.0)
    depth = (fb / disp).astype(np.float32)
    strip = int(round(overlap * width))
    keep = np.zeros((height, width), dtype=bool)
    keep[:, :strip] = True
    keep[:, width - strip :] = True
    keep &= rng.random((height, width)) > 0.03
    keep &= depth < max_depth
    depth = np.where(keep, depth, 0.0).astype(np.float32)
    conf = np.where(keep, np.clip(1.0 - depth / max_depth, 0.05, 1.0), 0.0).astype(np.float32)
    return depth, conf


class SyntheticPriorCompute:
    """Picklable `compute(frame_id) -> {camera: (depth, confidence)}` with synthetic priors."""

    def __init__(self, rig: Rig, seed: int = 0, delay_s: float = 0.0, cameras: list[str] | None = None):
        self.sizes = {c.name: (int(c.height), int(c.width)) for c in rig.cameras}
        self.cameras = list(cameras) if cameras is not None else list(self.sizes)
        self.seed = int(seed)
        self.delay_s = float(delay_s)

    def __call__(self, frame_id: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The frame's synthetic priors (after an optional delay that mimics the matcher's cost)."""
        if self.delay_s > 0:
            time.sleep(self.delay_s)
        out = {}
        for cam in self.cameras:
            h, w = self.sizes[cam]
            out[cam] = synthetic_prior(h, w, zlib.crc32(f"{self.seed}/{frame_id}/{cam}".encode()))
        return out


__all__ = ["SyntheticPriorCompute", "synthetic_prior"]
