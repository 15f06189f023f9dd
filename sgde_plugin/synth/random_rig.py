"""Random surround rigs the prior was never tuned on (`sgde synth --preset random --seed S`).

A seed fixes everything: 4-8 pinhole cameras around the car, horizontal fields of view of 50-120
degrees, adjacent overlaps of 5-30 degrees (so the yaw gaps follow: gap = (fov_a + fov_b) / 2 -
overlap, and they add up to 360 degrees), mount positions on an ellipse around the body at varied
heights (1.2-2.2 m), pitches (3 degrees up to 12 down) and small rolls, several image aspects.
Some overlaps are blocked by a near object (a post, a sign or a van side 2.5-5 m away in the middle
of the overlap) that drives along with the ego, so it stays in that overlap for the whole sequence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..cameras import Camera, Pinhole
from ..geometry import camera_mount

N_CAMERAS = (4, 8)
FOV_DEG = (50.0, 120.0)
OVERLAP_DEG = (5.0, 30.0)
HEIGHT_M = (1.2, 2.2)
PITCH_DOWN_DEG = (-3.0, 12.0)
NEAR_DISTANCE_M = (2.5, 5.0)
BLOCK_PROBABILITY = 0.35
_WIDTH = 960
_ASPECTS = (16 / 9, 1936 / 1216, 3 / 2, 4 / 3)


@dataclass(frozen=True)
class NearObject:
    """A box standing on the ground near the car, in ego coordinates: centre, half sizes, yaw, colour."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    color: tuple[float, float, float]
    pair: tuple[str, str]  # the adjacent cameras whose overlap it blocks


@dataclass(frozen=True)
class RandomRig:
    """A random rig: cameras in ring order (true extrinsics), its overlaps and its near objects."""

    seed: int
    cameras: tuple[Camera, ...]
    fov_deg: tuple[float, ...]
    overlap_deg: tuple[float, ...]  # overlap of camera i with camera i + 1 (the last with the first)
    near_objects: tuple[NearObject, ...]

    @property
    def ring(self) -> list[str]:
        """Camera names in ring order."""
        return [c.name for c in self.cameras]

    def summary(self) -> dict:
        """Plain description for rig.json's `synth` block."""
        return {
            "cameras": len(self.cameras),
            "fov_deg": [round(f, 2) for f in self.fov_deg],
            "overlap_deg": [round(o, 2) for o in self.overlap_deg],
            "blocked_pairs": [list(o.pair) for o in self.near_objects],
        }


def _fovs(rng: np.random.Generator, n: int, total: float) -> np.ndarray:
    """n fields of view in FOV_DEG adding up to `total` (feasible by construction)."""
    lo, hi = FOV_DEG
    u = rng.uniform(0.05, 1.0, n)
    target = (total - n * lo) / (hi - lo)  # sum of the unit shares
    a, b = 0.0, 1.0 / u.min()
    for _ in range(60):  # bisection on the scale of the clipped shares
        mid = (a + b) / 2
        if np.clip(u * mid, 0, 1).sum() < target:
            a = mid
        else:
            b = mid
    return lo + (hi - lo) * np.clip(u * b, 0, 1)


def random_rig(seed: int, scale: float = 1.0) -> RandomRig:
    """The random rig of a seed (same seed, same rig); image sizes multiplied by `scale`."""
    rng = np.random.default_rng([int(seed), 0x816])
    n = int(rng.integers(N_CAMERAS[0], N_CAMERAS[1] + 1))
    while True:
        overlaps = rng.uniform(*OVERLAP_DEG, n)
        total = 360.0 + overlaps.sum()
        if n * FOV_DEG[0] <= total <= n * FOV_DEG[1]:
            break
    fovs = _fovs(rng, n, total)
    # ring order turns right (yaw decreasing), like the presets; gap i is between camera i and i + 1
    yaw0 = rng.uniform(-20.0, 20.0)
    gaps = (fovs + np.roll(fovs, -1)) / 2 - overlaps
    yaws = yaw0 - np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    aspect = _ASPECTS[int(rng.integers(len(_ASPECTS)))]
    width = max(8, int(round(_WIDTH * scale)))
    height = max(8, int(round(_WIDTH / aspect * scale)))
    semi_x, semi_y = rng.uniform(1.0, 2.2), rng.uniform(0.5, 1.0)
    centre_x = rng.uniform(0.3, 1.5)
    rig_height = rng.uniform(HEIGHT_M[0] + 0.15, HEIGHT_M[1] - 0.15)
    cameras = []
    for i in range(n):
        psi = math.radians(yaws[i])
        pos = np.array([centre_x + semi_x * math.cos(psi), semi_y * math.sin(psi),
                        rig_height + rng.uniform(-0.15, 0.15)])
        pitch = math.radians(rng.uniform(*PITCH_DOWN_DEG))
        roll = math.radians(rng.uniform(-2.0, 2.0))
        focal = (width / 2) / math.tan(math.radians(fovs[i]) / 2)
        K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
        cameras.append(Camera(f"CAM_{i:02d}", Pinhole(width, height, K), camera_mount(psi, pos, pitch, roll)))
    near = []
    blocked = rng.random(n) < BLOCK_PROBABILITY
    if not blocked.any():
        blocked[int(rng.integers(n))] = True
    for i in np.nonzero(blocked)[0]:
        j = (i + 1) % n
        edge_i = yaws[i] - fovs[i] / 2  # right edge of camera i
        mid = math.radians(edge_i + overlaps[i] / 2)
        base = (cameras[i].sensor_to_ego[:3, 3] + cameras[j].sensor_to_ego[:3, 3]) / 2
        r = rng.uniform(*NEAR_DISTANCE_M)
        kind = int(rng.integers(3))  # post, sign, van side
        half = [(0.15, 0.15, 1.3), (0.05, 0.5, 1.1), (1.2, 0.9, 1.1)][kind]
        x, y = base[0] + r * math.cos(mid), base[1] + r * math.sin(mid)
        colour = tuple(float(c) for c in rng.uniform(0.2, 0.85, 3))
        near.append(NearObject((x, y, half[2]), half, mid, colour, (cameras[i].name, cameras[j].name)))
    return RandomRig(int(seed), tuple(cameras), tuple(float(f) for f in fovs), tuple(float(o) for o in overlaps),
                     tuple(near))
