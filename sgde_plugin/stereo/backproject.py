"""Back-projection of rectified disparities into an original camera, by backward mapping, and fusion.

For every pixel of the original camera: its ray, the rectified pixel on that ray (same optical
centre, so no occlusion can arise from the re-projection itself), the disparity there, and the
depth in the camera's own convention (z for pinholes, range for fisheyes):
depth = k * f * B / disparity with k = (depth of the point) / (rectified z of the point), a
per-pixel constant precomputed once per rig. Disparities are interpolated bilinearly, but only
from four valid neighbours: pixels next to a disparity jump are dropped first, so no depths are
invented between foreground and background.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..cameras import Camera
from .rectify import torch_threads, turned

_ROW = 64  # sample positions are laid out in rows of this length for cv2.remap; a frame remaps only the rows
# whose footprint in the canvas holds a usable disparity
_SENTINEL = -1.0e5  # disparity of "no value"; any bilinear weight >= 1/32 on it gives a negative sample


@dataclass(frozen=True, eq=False)
class BackProjection:
    """Precomputed backward map from one original camera into one rectified camera."""

    shape: tuple[int, int]  # (H, W) of the original camera
    index: np.ndarray  # flat indices of the original pixels that land in the rectified canvas
    map_x: np.ndarray  # float32 cv2.remap maps (rows x _ROW) of their rectified positions (padded), on the
    map_y: np.ndarray  # 1/32 px grid of OpenCV's fixed-point maps (float maps remap float data faster)
    kfb: np.ndarray  # (N,) float32: depth = kfb / disparity
    core: tuple[int, int]  # (H, Wc) of the disparity maps sampled (the core columns)
    corners: np.ndarray  # (rows, 4) flat indices into the core's summed-area table bounding each map row's footprint

    @property
    def count(self) -> int:
        """Number of original pixels covered."""
        return int(self.index.shape[0])

    def sample(
        self, disparity: np.ndarray, confidence: np.ndarray, edge_px: float = 1.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Disparity (N,), confidence (N,) and validity (N,) at the covered pixels, edge-aware.

        Invalid pixels, and both pixels of every horizontal or vertical neighbour pair whose
        disparities differ by more than `edge_px`, get a large negative sentinel; a bilinear sample
        that touches one comes out negative and is dropped (-1 here). One remap does the whole job.
        """
        pos, d, c = self._samples(disparity, confidence, edge_px)
        dd = np.full(self.count, -1.0, np.float32)
        cc = np.zeros(self.count, np.float32)
        dd[pos], cc[pos] = d, c
        return dd, cc, dd > 0

    def _samples(
        self, disparity: np.ndarray, confidence: np.ndarray, edge_px: float = 1.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`sample` at the covered pixels that get a value: (positions in 0..N-1, disparity > 0, confidence)."""
        rows, out = self._remapped(disparity, confidence, edge_px)
        if out is None:
            return np.zeros(0, np.intp), np.zeros(0, np.float32), np.zeros(0, np.float32)
        got = np.flatnonzero(out[0] > 0)
        pos = got if rows is None else rows[got // _ROW] * _ROW + got % _ROW
        return pos, out[0][got], out[1][got]

    def _remapped(
        self, disparity: np.ndarray, confidence: np.ndarray, edge_px: float = 1.0
    ) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
        """(map rows remapped, None = all; their flat disparity and confidence samples), (None, None) if none.

        Map rows whose bilinear footprints hold no usable canvas pixel (summed-area test) would
        only sample the sentinel; where they are the majority they are skipped, the others remapped
        exactly as they are.
        """
        ok = confidence > 0
        d = np.where(ok, disparity, np.float32(_SENTINEL)).astype(np.float32, copy=False)
        jump_x = ok[:, 1:] & ok[:, :-1] & (np.abs(d[:, 1:] - d[:, :-1]) > edge_px)
        jump_y = ok[1:] & ok[:-1] & (np.abs(d[1:] - d[:-1]) > edge_px)
        edge = np.zeros_like(ok)
        edge[:, 1:] |= jump_x
        edge[:, :-1] |= jump_x
        edge[1:] |= jump_y
        edge[:-1] |= jump_y
        d[edge] = _SENTINEL
        ok &= ~edge
        if ok.shape != self.core:
            raise ValueError(f"disparity is {ok.shape}, the backward map was made for {self.core}")
        table = cv2.integral(ok.view(np.uint8)).reshape(-1)
        a, b, c, e = (table[self.corners[:, i]] for i in range(4))
        rows = np.flatnonzero(a - b - c + e > 0)
        if rows.size == 0:
            return None, None
        full = rows.size > 0.5 * self.corners.shape[0]  # gathering most rows costs more than it saves
        map_x, map_y = (self.map_x, self.map_y) if full else (self.map_x[rows], self.map_y[rows])
        conf = np.asarray(confidence, np.float32)
        out = tuple(cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=fill).reshape(-1) for img, fill in ((d, _SENTINEL), (conf, 0.0)))
        return (None if full else rows), out

    def values(
        self, disparity: np.ndarray, confidence: np.ndarray, min_depth: float, max_depth: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(flat pixel indices, depth in the camera's convention, confidence) of the pixels that got a value."""
        rows, out = self._remapped(disparity, confidence)
        if out is None:
            return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32)
        d_all, c_all = out
        if rows is not None:  # a few map rows: gather their pixels, then as `_samples`
            got = np.flatnonzero(d_all > 0)
            pos = rows[got // _ROW] * _ROW + got % _ROW
            z = self.kfb[pos] / d_all[got]
            keep = (z >= min_depth) & (z <= max_depth)
            return self.index[pos[keep]], z[keep], c_all[got[keep]]
        d = d_all[: self.count]  # every map row: the first N samples are the covered pixels
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.kfb / d
        # kfb > 0: a sample without a value (d <= 0) gives z <= 0 or -inf, outside any range with min_depth > 0
        ok = (z >= min_depth) & (z <= max_depth) if min_depth > 0 else (d > 0) & (z >= min_depth) & (z <= max_depth)
        keep = np.flatnonzero(ok)  # one pass over the mask, then three gathers (faster than three masked ones)
        return self.index.take(keep), z.take(keep), c_all.take(keep)

    def depth(
        self, disparity: np.ndarray, confidence: np.ndarray, min_depth: float, max_depth: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Full-size depth (camera convention) and confidence maps; 0 where there is no value."""
        idx, z, c = self.values(disparity, confidence, min_depth, max_depth)
        depth = np.zeros(self.shape[0] * self.shape[1], np.float32)
        conf = np.zeros_like(depth)
        depth[idx] = z
        conf[idx] = c
        return depth.reshape(self.shape), conf.reshape(self.shape)


@dataclass(frozen=True, eq=False)
class Owner:
    """The rays a tile back-projects: those turned by an angle in [lo, hi) about the x axis of the frame
    `rotation` (ego columns), from its z towards its y; `to_frame` takes the camera's rays into that frame."""

    to_frame: np.ndarray  # (3, 3): rotation.T @ camera's sensor-to-ego rotation
    lo: float
    hi: float

    @staticmethod
    def of(camera: Camera, rotation: np.ndarray, lo: float, hi: float) -> Owner:
        """The owner of turns [lo, hi) about `rotation`'s x axis, for `camera`'s rays."""
        return Owner(rotation.T @ camera.sensor_to_ego[:3, :3], lo, hi)

    def owns(self, rays: np.ndarray) -> np.ndarray:
        """Bool (N,): which camera rays (N, 3) are owned."""
        q = turned(rays, self.to_frame)
        angle = np.arctan2(q[:, 1], q[:, 2])
        return (angle >= self.lo) & (angle < self.hi)


def camera_rays(camera: Camera, shared: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """`camera`'s `ray_grid()`, made once per intrinsics (models compare by value) in `shared`."""
    key = ("rays", camera.intrinsics)
    if key not in shared:
        shared[key] = camera.intrinsics.ray_grid()
    return shared[key]


def backprojection(
    camera: Camera, rect: Camera, baseline_m: float, x_range: tuple[int, int] | None = None,
    rays: torch.Tensor | None = None, ray_valid: torch.Tensor | None = None, possible: np.ndarray | None = None,
    owner: Owner | None = None,
) -> BackProjection:
    """Backward map of `camera` into the rectified pinhole `rect` (same optical centre).

    Only pixels landing in canvas columns `x_range` = [x0, x1) are kept, and their rectified x is
    stored relative to x0 (disparity maps of the core columns). `rays`/`ray_valid` may pass the
    camera's precomputed `ray_grid()` to share it between pairs. `possible` (bool, core columns)
    marks the rectified pixels that can ever hold a disparity; pixels whose bilinear footprint
    misses them all are left out. With an `owner`, only the pixels it owns are kept (a tile of a fisheye pair).
    """
    x0, x1 = (0, rect.width) if x_range is None else x_range
    with torch_threads(1):
        return _backprojection(camera, rect, baseline_m, x0, x1, rays, ray_valid, possible, owner)


def _backprojection(
    camera: Camera, rect: Camera, baseline_m: float, x0: int, x1: int, rays: torch.Tensor | None,
    ray_valid: torch.Tensor | None, possible: np.ndarray | None, owner: Owner | None,
) -> BackProjection:
    if rays is None or ray_valid is None:
        rays, ray_valid = camera.intrinsics.ray_grid()
    R = rect.sensor_to_ego[:3, :3].T @ camera.sensor_to_ego[:3, :3]
    K = rect.intrinsics.K
    h, w = rect.height, x1 - x0
    reach = None if possible is None else cv2.dilate(possible.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    # only the block of original pixels that can land in the canvas (or in its reach) is rotated
    r0, r1, c0, c1 = _candidate_box(camera, R, K, _canvas_window(x0, x1, h, reach), rays, ray_valid)
    r = rays.numpy()[r0:r1, c0:c1].reshape(-1, 3)
    front, zq, u, v = _rectified_pixels(r, R, K)
    inside = front & ray_valid.numpy()[r0:r1, c0:c1].reshape(-1) & (u >= x0) & (u <= x1 - 1) & (v >= 0) & (v <= h - 1)
    index = np.flatnonzero(inside)  # into the box
    us, vs = u[index], v[index]
    if reach is not None:
        col = np.clip(np.rint(us - x0).astype(np.intp), 0, reach.shape[1] - 1)
        row = np.clip(np.rint(vs).astype(np.intp), 0, reach.shape[0] - 1)
        near = reach.reshape(-1)[row * reach.shape[1] + col]
        index, us, vs = index[near], us[near], vs[near]
    if owner is not None:  # tested on the landing pixels only: the whole image would cost a fisheye re-plan 20 %
        mine = owner.owns(r[index])
        index, us, vs = index[mine], us[mine], vs[mine]
    # point = ray * t with t * q_z = rectified z; depth = t (range) or t * r_z (pinhole z)
    k = 1.0 / zq[index]
    if not camera.intrinsics.depth_is_range:
        k = k * r[:, 2][index]
    n = int(index.shape[0])
    rows = max(1, -(-n // _ROW))
    map_x = np.full(rows * _ROW, -1.0, np.float32)
    map_y = np.full(rows * _ROW, -1.0, np.float32)
    map_x[:n] = us - x0
    map_y[:n] = vs
    map1, map2 = cv2.convertMaps(map_x.reshape(rows, _ROW), map_y.reshape(rows, _ROW), cv2.CV_16SC2)
    fine_x, fine_y = cv2.convertMaps(map1, map2, cv2.CV_32FC1)  # the same positions, as float maps
    # each map row's footprint: the integer corners remap uses (map1) and the next column and row
    cx, cy = map1[..., 0].astype(np.int64), map1[..., 1].astype(np.int64)
    cc0, cc1 = np.clip(cx.min(1), 0, w - 1), np.clip(cx.max(1) + 1, 0, w - 1) + 1
    rr0, rr1 = np.clip(cy.min(1), 0, h - 1), np.clip(cy.max(1) + 1, 0, h - 1) + 1
    corners = np.stack([rr1 * (w + 1) + cc1, rr0 * (w + 1) + cc1, rr1 * (w + 1) + cc0, rr0 * (w + 1) + cc0], axis=1)
    local = index.astype(np.int64)
    return BackProjection(
        shape=(camera.height, camera.width),
        index=(local // (c1 - c0) + r0) * camera.width + local % (c1 - c0) + c0 if n else local,
        map_x=fine_x,
        map_y=fine_y,
        kfb=(k * K[0, 0] * baseline_m).astype(np.float32),
        core=(h, w),
        corners=corners,
    )


def _rectified_pixels(rays: np.ndarray, R: np.ndarray, K: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(in front, rectified z (1 behind), u, v) of camera rays (N, 3) turned by R into a rectified camera K."""
    q = turned(rays, R)
    front = q[:, 2] > 1e-6
    zq = np.where(front, q[:, 2], 1.0)
    return front, zq, K[0, 0] * q[:, 0] / zq + K[0, 2], K[1, 1] * q[:, 1] / zq + K[1, 2]


def _canvas_window(x0: int, x1: int, h: int, reach: np.ndarray | None) -> tuple[float, float, float, float] | None:
    """(u_lo, u_hi, v_lo, v_hi): the canvas positions a kept pixel can have (inside columns [x0, x1) and rows, and
    rounding into `reach`, a core-column mask); None when `reach` is empty."""
    u_lo, u_hi, v_lo, v_hi = float(x0), float(x1 - 1), 0.0, float(h - 1)
    if reach is None:
        return u_lo, u_hi, v_lo, v_hi
    cols, rows = np.flatnonzero(reach.any(axis=0)), np.flatnonzero(reach.any(axis=1))
    if cols.size == 0:
        return None
    return (max(u_lo, x0 + cols[0] - 0.5), min(u_hi, x0 + cols[-1] + 0.5),
            max(v_lo, rows[0] - 0.5), min(v_hi, rows[-1] + 0.5))


def _valid_edge(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the valid pixels with a 4-neighbour that is not valid or outside the image."""
    h, w = valid.shape
    if valid.all():  # the image's frame
        rows, cols = np.arange(h), np.arange(w)
        return (np.concatenate([np.zeros(w, np.intp), np.full(w, h - 1), rows, rows]),
                np.concatenate([cols, cols, np.zeros(h, np.intp), np.full(h, w - 1)]))
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    inner = cv2.erode(valid.view(np.uint8), cross, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return np.nonzero(valid & ~inner)


def _candidate_box(
    camera: Camera, R: np.ndarray, K: np.ndarray, window: tuple[float, float, float, float] | None,
    rays: torch.Tensor, ray_valid: torch.Tensor, step_px: float = 1.0,
) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1): a block of `camera`'s pixels holding every valid pixel whose ray (rotated by `R` into the
    rectified frame of intrinsics `K`) lands in the canvas `window`; (0, 0, 0, 0) when none can.

    The pixels that land there form a region whose edge is either the window's edge seen by the camera or the edge
    of the valid pixels; its extremes are on that edge. So the block bounds the window's border, sampled every
    `step_px` canvas pixels and projected into the camera, and the valid-edge pixels that land in the window, widened
    by the largest gap between projected samples and two pixels (a pixel next to the border lies within one).
    """
    if window is None:
        return 0, 0, 0, 0
    u_lo, u_hi, v_lo, v_hi = window
    H, W = camera.height, camera.width
    us = np.linspace(u_lo, u_hi, max(2, int(np.ceil((u_hi - u_lo) / step_px)) + 1))
    vs = np.linspace(v_lo, v_hi, max(2, int(np.ceil((v_hi - v_lo) / step_px)) + 1))
    sides = [(us, np.full_like(us, v_lo)), (us, np.full_like(us, v_hi)), (np.full_like(vs, u_lo), vs),
             (np.full_like(vs, u_hi), vs)]
    K_inv = np.linalg.inv(K)
    points, gap = [], 0.0
    for su, sv in sides:
        d = np.stack([su, sv, np.ones_like(su)], axis=1) @ K_inv.T @ R  # canvas rays in the camera frame
        px, ok = camera.intrinsics.project(d)
        both = ok[1:] & ok[:-1]  # neighbouring samples that both land in the image
        if both.any():
            gap = max(gap, float(np.abs(np.diff(px, axis=0)[both]).max()))
        points.append(px[ok])
    ev, eu = _valid_edge(ray_valid.numpy())
    front, _, eu_c, ev_c = _rectified_pixels(rays.numpy()[ev, eu], R, K)
    lands = front & (eu_c >= u_lo) & (eu_c <= u_hi) & (ev_c >= v_lo) & (ev_c <= v_hi)
    points.append(np.stack([eu[lands], ev[lands]], axis=1).astype(np.float64))
    pts = np.concatenate(points)
    pts = pts[(pts[:, 0] > -1) & (pts[:, 0] < W) & (pts[:, 1] > -1) & (pts[:, 1] < H)]
    if len(pts) == 0:
        return 0, 0, 0, 0
    m = gap + 2.0
    c0, c1 = max(0, int(np.floor(pts[:, 0].min() - m))), min(W, int(np.ceil(pts[:, 0].max() + m)) + 1)
    r0, r1 = max(0, int(np.floor(pts[:, 1].min() - m))), min(H, int(np.ceil(pts[:, 1].max() + m)) + 1)
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else (0, 0, 0, 0)


def fuse_into(
    depth: np.ndarray, conf: np.ndarray, index: np.ndarray, z: np.ndarray, c: np.ndarray, agree_rel: float = 0.05
) -> None:
    """Fuse sparse values (flat `index`, depth `z`, confidence `c`) into a camera's maps, in place.

    Where the map is empty the new value is taken. Where both have a value and agree within
    `agree_rel`, the confidence-weighted mean is taken and the confidence becomes 1 - prod(1 - c);
    where they disagree the more confident one wins with its confidence halved.
    """
    flat_d, flat_c = depth.reshape(-1), conf.reshape(-1)
    if index.size == 0:
        return
    old_c = flat_c[index]
    if not old_c.any():
        flat_d[index] = z
        flat_c[index] = c
        return
    old_d = flat_d[index]
    both = old_c > 0
    new_d, new_c = z.copy(), c.copy()
    if both.any():
        a, ca, b, cb = old_d[both], old_c[both], z[both], c[both]
        agree = np.abs(a - b) <= agree_rel * np.minimum(a, b)
        mean = (a * ca + b * cb) / (ca + cb)
        new_d[both] = np.where(agree, mean, np.where(cb > ca, b, a))
        new_c[both] = np.where(agree, 1 - (1 - ca) * (1 - cb), 0.5 * np.maximum(ca, cb))
    flat_d[index] = new_d
    flat_c[index] = new_c
