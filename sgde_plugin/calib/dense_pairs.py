"""Dense same-frame correspondences in each adjacent pair's overlap (`MatchConfig.dense`, issue #17 session 10).

SIFT finds few same-frame matches on narrow overlaps, and its localisation errors repeat for one physical point
across the window's frames. Here camera b's image is resampled into a pinhole that shares the orientation and
intrinsics of camera a's view aimed at their overlap (`views.overlap_view`, the view SIFT already ran on; the warp
is `stereo.rectify.camera_maps`), so that the two views differ only by the parallax of the baseline and the
starting rig's error. Points on a regular grid of a's view where both views have data and the texture is strong
are found in b's view by DIS optical flow (both ways, a forward-backward check) refined by Lucas-Kanade (checked
back again), on the box of the shared area with the views' empty pixels filled. They are mapped to both
cameras' pixels; each frame's set is verified like any other observation pair
(`correspondences.verify_observation_pair`) and joins the frame's SIFT matches as two-view points with their own
sigma (`DenseConfig.sigma_px`). The matching does not need the start to be accurate: the views only have to
overlap, the positions come from the images.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..stereo.rectify import camera_maps, default_rim_px
from .features import to_gray
from .views import VirtualView


@dataclass(frozen=True)
class DenseConfig:
    """Settings of the dense same-frame correspondences (pixels are the overlap views' pixels)."""

    enabled: bool = False
    step_px: int = 6  # grid spacing of the tracked points
    window_px: int = 11  # Lucas-Kanade window and texture measure (odd)
    levels: int = 1  # Lucas-Kanade pyramid levels above the base (it starts from the DIS flow)
    dis_preset: int = 1  # cv2.DISOPTICAL_FLOW_PRESET_* (0 ultrafast, 1 fast, 2 medium)
    coarse_fb_px: float = 1.0  # DIS forward-backward disagreement allowed, and LK's move from DIS
    min_eig: float = 1e-4  # smallest eigenvalue of the window's structure tensor (OpenCV's normalisation)
    fb_px: float = 0.25  # forward-backward disagreement allowed
    sigma_px: float = 0.12  # per end, in the camera's pixels (measured: 0.11 on the development random rigs)
    max_per_frame: int = 300  # kept per camera pair and frame after verification (a random subset)
    ransac_threshold_px: float = 1.0
    margin_px: int = 96  # the flow runs on the box of the views' shared area grown by this
    fill: bool = True  # unusable pixels set to the usable ones' mean before the flow


def same_orientation_view(view_a: VirtualView, cam_b: Camera) -> VirtualView:
    """A pinhole at camera b's centre with the orientation and intrinsics of camera a's view `view_a`."""
    pose = cam_b.sensor_to_ego.copy()
    pose[:3, :3] = view_a.camera.sensor_to_ego[:3, :3]
    K = view_a.camera.intrinsics
    virtual = Camera(f"{cam_b.name}.dense", Pinhole(K.width, K.height, K.K.copy(), None), pose)
    map_x, map_y, valid = camera_maps(cam_b, virtual, default_rim_px(cam_b))
    R = cam_b.sensor_to_ego[:3, :3].T @ pose[:3, :3]  # virtual -> camera b
    return VirtualView(virtual, map_x, map_y, valid, R, view_a.step)


def grid_points(gray: np.ndarray, usable: np.ndarray, cfg: DenseConfig) -> np.ndarray:
    """Grid points (N, 2) of a view, `cfg.step_px` apart, usable over a whole window (`usable`: where both views
    have data) and textured there."""
    w = cfg.window_px
    eig = cv2.cornerMinEigenVal(gray, w, 3)
    inner = cv2.erode(usable.astype(np.uint8), np.ones((w + 2, w + 2), np.uint8)) > 0
    s = cfg.step_px
    ys, xs = np.mgrid[s // 2:gray.shape[0]:s, s // 2:gray.shape[1]:s]
    ok = inner[ys, xs] & (eig[ys, xs] >= cfg.min_eig)
    return np.stack([xs[ok], ys[ok]], axis=1).astype(np.float32)


def _sample(flow: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """A dense flow field (H, W, 2) at sub-pixel points (N, 2), bilinearly."""
    x, y = pts[:, 0].astype(np.float32).reshape(-1, 1), pts[:, 1].astype(np.float32).reshape(-1, 1)
    return cv2.remap(flow, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)


def track(gray_a: np.ndarray, gray_b: np.ndarray, pts: np.ndarray, usable_b: np.ndarray, cfg: DenseConfig
          ) -> tuple[np.ndarray, np.ndarray]:
    """Points of view a found in view b: DIS optical flow both ways (a forward-backward check), refined by
    Lucas-Kanade from there and checked back; (which passed, positions in b)."""
    if len(pts) == 0:
        return np.zeros(0, bool), pts
    dis = cv2.DISOpticalFlow_create(cfg.dis_preset)
    fwd_flow, back_flow = dis.calc(gray_a, gray_b, None), dis.calc(gray_b, gray_a, None)
    guess = pts + _sample(fwd_flow, pts)
    coarse_ok = np.linalg.norm(guess + _sample(back_flow, guess) - pts, axis=1) <= cfg.coarse_fb_px
    lk = {"winSize": (cfg.window_px, cfg.window_px), "maxLevel": cfg.levels, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
    fwd, st1, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, pts, guess.astype(np.float32).copy(), **lk)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(gray_b, gray_a, fwd, pts.copy(), **lk)
    ok = coarse_ok & (st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pts, axis=1) <= cfg.fb_px)
    ok &= np.linalg.norm(fwd - guess, axis=1) <= cfg.coarse_fb_px
    return ok & _lands(fwd, usable_b, cfg.window_px // 2 + 1), fwd.astype(np.float64)


def _lands(uv: np.ndarray, usable: np.ndarray, r: int) -> np.ndarray:
    """Which points (N, 2) lie at least `r` px inside the view and on a usable pixel."""
    h, w = usable.shape
    ok = (uv[:, 0] >= r) & (uv[:, 1] >= r) & (uv[:, 0] < w - r) & (uv[:, 1] < h - r)
    ok[ok] = usable[np.round(uv[ok, 1]).astype(int), np.round(uv[ok, 0]).astype(int)]
    return ok


def _filled(gray: np.ndarray, usable: np.ndarray, cfg: DenseConfig) -> np.ndarray:
    """A view image with its unusable pixels set to the mean of the usable ones (`cfg.fill`): the edge of a
    view's data is no texture of the scene, and it sits at different places in the two views."""
    out = np.ascontiguousarray(gray)
    if not cfg.fill or not usable.any():
        return out
    out = out.copy()
    out[~usable] = np.uint8(round(float(gray[usable].mean())))
    return out


def frame_matches(cam_a: Camera, cam_b: Camera, view_a: VirtualView, gray_a: np.ndarray, usable_a: np.ndarray,
                  view_b: VirtualView, image_b: np.ndarray, mask_b: np.ndarray | None, interpolation: int,
                  cfg: DenseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Dense matches (camera pixels uv_a, uv_b) of one frame of a camera pair, from a's view image `gray_a`."""
    gray_b = to_gray(view_b.warp(image_b, interpolation))
    usable_b = view_b.valid.copy()
    if mask_b is not None:
        usable_b &= view_b.warp(mask_b.astype(np.uint8), cv2.INTER_NEAREST) > 0
    both = usable_a & usable_b
    rows, cols = np.flatnonzero(both.any(axis=1)), np.flatnonzero(both.any(axis=0))
    if rows.size == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    m = cfg.margin_px  # the flow sees the shared area and a margin for the parallax, not the whole view
    box = (slice(max(0, rows[0] - m), rows[-1] + m + 1), slice(max(0, cols[0] - m), cols[-1] + m + 1))
    corner = np.array([box[1].start, box[0].start], np.float64)
    pts = grid_points(gray_a[box], both[box], cfg)
    ok, pb = track(_filled(gray_a[box], usable_a[box], cfg), _filled(gray_b[box], usable_b[box], cfg), pts,
                   usable_b[box], cfg)
    pa, pb = pts[ok] + corner, pb[ok] + corner
    uv_a, ok_a = cam_a.intrinsics.project(view_a.rays_in_source(pa))
    uv_b, ok_b = cam_b.intrinsics.project(view_b.rays_in_source(pb))
    ok = ok_a & ok_b
    return uv_a[ok], uv_b[ok]

