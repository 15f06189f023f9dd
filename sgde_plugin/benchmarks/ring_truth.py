"""Truth of a rendered window: how much static, textured world each adjacent pair sees in common, in the same
frame and across time, and whether those pairs link the ring (benchmark code: it reads the synthetic world's
depth and moving boxes, which no calibration method may use).

For camera a at frame t and camera b at frame t2 the count is the number of a's pixels (every `stride`-th
row and column, scaled to all pixels) whose rendered point is on no moving box (an object that drives along,
traffic), has texture (grey-level gradient >= `min_gradient`), and is seen by b at t2: inside b's image and
not hidden (b's rendered depth there agrees within 3 %), seen from directions at most `max_angle_deg` apart
(SIFT matches views of a surface turned by up to about that much), and the width of what they see in common (the 2-98 %
spread of the pixels' azimuths in camera a, degrees). A pair is `linked` when some observation pair sees at
least `min_pixels` such pixels over at least `min_width_deg` (session 5 measured that strips of 5-10 degrees
determine a pair's rotation to a few tenths of a degree only, even with matches filtered by the truth); the
ring is connected when at most one pair is not linked (a ring without one edge is still a chain).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..synth.sequence import FRAME_RATE_HZ, SynthSequence

MIN_PIXELS = 2000  # a 45 x 45 px patch of texture at the rigs' 480-px width
MIN_WIDTH_DEG = 10.0
MAX_ANGLE_DEG = 20.0


def on_moving_box(world: Any, points: np.ndarray, time_s: float, margin_m: float = 0.1) -> np.ndarray:
    """True for world points (n, 3) inside (by `margin_m`) a box that moves (nonzero velocity) at `time_s`."""
    moving = np.linalg.norm(world.box_velocity, axis=1) > 0
    out = np.zeros(points.shape[0], dtype=bool)
    for centre, half, yaw in zip(world.box_centers(time_s)[moving], world.box_half[moving], world.box_yaw[moving]):
        d = points - centre
        c, s = np.cos(yaw), np.sin(yaw)
        local = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        out |= np.all(np.abs(local) <= half + margin_m, axis=1)
    return out


def _textured(rgb: np.ndarray, min_gradient: float) -> np.ndarray:
    """Pixels whose grey-level gradient (Sobel, 0-255 scale) reaches `min_gradient`."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) if rgb.ndim == 3 else rgb.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.hypot(gx, gy) >= min_gradient


def common_static_pixels(seq: SynthSequence, a: str, b: str, t: int, t2: int, stride: int = 4,
                         min_gradient: float = 4.0, max_angle_deg: float = MAX_ANGLE_DEG) -> tuple[int, float]:
    """Textured static pixels of camera a at frame t that camera b sees at frame t2, and their azimuth spread
    in camera a (degrees; module docstring)."""
    rig, world = seq.rig_true, seq.world
    fa, fb = rig.frames[t], rig.frames[t2]
    ca, cb = rig.camera(a), rig.camera(b)
    depth_a = seq.depths[fa.id][a][::stride, ::stride].astype(np.float64)
    vv, uu = np.nonzero((depth_a > 0) & _textured(seq.images[fa.id][a], min_gradient)[::stride, ::stride])
    if not vv.size:
        return 0, 0.0
    uv = np.column_stack([uu, vv]).astype(np.float64) * stride
    pts, ok = ca.intrinsics.points_from_depth(uv, depth_a[vv, uu])
    pose_a = rig.capture(fa, a).ego_to_world @ ca.sensor_to_ego
    world_pts = pts[ok] @ pose_a[:3, :3].T + pose_a[:3, 3]
    static = ~on_moving_box(world, world_pts, rig.capture(fa, a).timestamp_us * 1e-6)
    world_pts, azimuth = world_pts[static], np.degrees(np.arctan2(pts[ok][static, 0], pts[ok][static, 2]))
    pose_b = np.linalg.inv(rig.capture(fb, b).ego_to_world @ cb.sensor_to_ego)
    pts_b = world_pts @ pose_b[:3, :3].T + pose_b[:3, 3]
    uv_b, inside = cb.intrinsics.project(pts_b)
    h, w = cb.height, cb.width
    inside &= (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= w - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= h - 1)
    uv_b, pts_b, azimuth = uv_b[inside], pts_b[inside], azimuth[inside]
    depth_b = seq.depths[fb.id][b]
    seen = depth_b[np.round(uv_b[:, 1]).astype(int), np.round(uv_b[:, 0]).astype(int)]
    expected = cb.intrinsics.depth(pts_b)
    both = np.abs(seen - expected) <= 0.03 * expected
    from_a = world_pts[inside] - pose_a[:3, 3]
    from_b = pts_b @ pose_b[:3, :3]  # b's rays in the world's axes
    cos = np.sum(from_a * from_b, axis=1) / (np.linalg.norm(from_a, axis=1) * np.linalg.norm(from_b, axis=1))
    both &= cos >= np.cos(np.radians(max_angle_deg))
    if not both.any():
        return 0, 0.0
    lo, hi = np.percentile(azimuth[both], [2, 98])
    return int(np.count_nonzero(both)) * stride * stride, float(hi - lo)


def ring_truth(seq: SynthSequence, min_pixels: int = MIN_PIXELS, min_width_deg: float = MIN_WIDTH_DEG,
               stride: int = 4) -> dict[str, Any]:
    """Per adjacent pair of the rendered window: the largest common static textured view (pixels, width) over its
    same-frame and over its cross-time observation pairs, whether it is linked, and whether the ring is connected."""
    T = len(seq.rig_true.frames)
    pairs = []
    for a, b in seq.rig_true.pairs:
        row: dict[str, Any] = {"pair": f"{a}-{b}"}
        best = {"same_frame": (0, 0.0), "cross_time": (0, 0.0)}
        linked = False
        for t in range(T):
            for t2 in range(T):
                n, width = common_static_pixels(seq, a, b, t, t2, stride)
                key = "same_frame" if t == t2 else "cross_time"
                best[key] = max(best[key], (n, width))
                linked |= n >= min_pixels and width >= min_width_deg
        for key, (n, width) in best.items():
            row[f"{key}_px"], row[f"{key}_width_deg"] = n, round(width, 1)
        row["linked"] = linked
        pairs.append(row)
    unlinked = [p["pair"] for p in pairs if not p["linked"]]
    return {"pairs": pairs, "unlinked": unlinked, "ring_connected": len(unlinked) <= 1, "min_pixels": min_pixels,
            "min_width_deg": min_width_deg, "frame_rate_hz": FRAME_RATE_HZ}
