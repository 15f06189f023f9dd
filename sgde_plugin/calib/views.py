"""Virtual pinhole views of a fisheye aimed at its overlap with one neighbour, for feature detection.

Keypoints found on the raw fisheye image near the rim of its field of view sit on strongly squeezed
texture; their positions carry a systematic error (measured: about 0.2 px, 0.13 deg of relative
rotation on the synthetic 220-degree rig at half resolution). Detecting on a pinhole resampling
centred on the overlap removes most of that squeeze. Keypoints are mapped back to the fisheye's
pixels and rays, so everything downstream stays in the fisheye's own model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..stereo.rectify import angular_resolution, camera_maps, default_rim_px
from .overlap import OverlapGrid

# how a view samples its camera (`MatchConfig.view_interpolation`): Lanczos keeps the blur of a resampled pixel
# nearly the same at every sub-pixel phase of the view's grid against the camera's; bilinear blurs a pixel
# that falls half-way between four source pixels much more than one that falls on a pixel, and SIFT's
# positions follow that varying blur (see tests/test_calib_views.py)
VIEW_INTERPOLATIONS = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4}


@dataclass
class VirtualView:
    """A pinhole sharing the source camera's centre: remap maps and the rotation virtual -> source."""

    camera: Camera
    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray
    R: np.ndarray
    step: float = 1.0  # source pixels per view pixel at the view's centre (> 1: the view samples coarser)

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR, antialias: bool = False) -> np.ndarray:
        """The source image resampled into the view (0 where the source has no data); with `antialias` a view
        coarser than the source is sampled from the source low-passed to the view's pixel (Gaussian of
        0.5 sqrt(step^2 - 1) source pixels), so that both views of a pair see the scene through one blur."""
        if antialias and self.step > 1.05:
            image = cv2.GaussianBlur(image, (0, 0), 0.5 * float(np.sqrt(self.step**2 - 1.0)))
        out = cv2.remap(image, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[~self.valid] = 0
        return out

    def rays_in_source(self, uv: np.ndarray) -> np.ndarray:
        """Unit rays (N, 3) in the source camera's frame of view pixels (N, 2)."""
        rays, _ = self.camera.intrinsics.unproject(np.asarray(uv, dtype=np.float64))
        return rays @ self.R.T


def overlap_view(
    cam: Camera, grid: OverlapGrid, hfov_deg: float = 110.0, vfov_deg: float = 100.0,
    other: Camera | None = None, crop: bool = False, pad_deg: float = 10.0, upsample: float = 1.0,
    pair_scale: str = "min", level: bool = False, trim_margin_px: int = 16, phase: tuple[float, float] = (0.0, 0.0),
) -> VirtualView | None:
    """A virtual pinhole of `cam` looking at the centre of its same-frame overlap in `grid`, or None.

    Its focal length is the camera's own resolution (pixels per radian) there, or, given the `other` camera
    of the pair, the smaller of the two (`pair_scale` "min"; "max": the larger, "mean": their geometric
    mean): both views then see the overlap at one scale (a 48-degree and an 85-degree camera see it at
    about 2:1); `upsample` multiplies that focal length (detection at a finer
    scale; measured: x2 changed nothing on the fisheye preset, the image's own pixels are the limit).
    With `crop` the view covers only the overlap's bounding box (at most hfov x vfov), grown by `pad_deg`
    on each side for matches across frames. With `level` the view's x axis is horizontal in the ego frame
    (its y axis points down along gravity) instead of following the camera's own roll and pitch: the two
    views of a pair then share one orientation up to the small difference of their axes (the random rigs'
    cameras differ by up to 15 degrees of pitch, and their own-axis views by 4-11 degrees of roll).
    The view is then cut to where the camera has data, `trim_margin_px` around it (see `_trimmed`). `phase` moves
    the view's pixel grid by that fraction of a pixel (x, y) against the scene (its principal point), so that a
    second view samples the camera at other sub-pixel positions (`MatchConfig.view_phases`).
    """
    T = grid.mask.shape[0]
    same = np.any(grid.mask[np.arange(T), np.arange(T)], axis=0)
    rows, cols = np.nonzero(same)
    if rows.size == 0:
        return None
    uv = np.stack([np.minimum(cols * grid.stride, cam.width - 1), np.minimum(rows * grid.stride, cam.height - 1)], 1)
    rays, ok = cam.intrinsics.unproject(uv.astype(np.float64))
    if not ok.any():
        return None
    z = rays[ok].mean(axis=0)
    z /= np.linalg.norm(z)
    down = cam.sensor_to_ego[:3, :3].T @ [0.0, 0.0, -1.0] if level else np.array([0.0, 1.0, 0.0])
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-6:
        return None
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z], axis=1)  # virtual -> source camera frame (y stays "down")
    pose = cam.sensor_to_ego.copy()
    pose[:3, :3] = cam.sensor_to_ego[:3, :3] @ R
    own = angular_resolution(cam, pose[:3, 2])
    if own is None:
        return None
    f = own
    if other is not None and (res := angular_resolution(other, pose[:3, 2])) is not None:
        f = {"min": min(own, res), "max": max(own, res), "mean": float(np.sqrt(own * res))}[pair_scale]
    f *= upsample
    w = max(16, int(round(2 * f * np.tan(np.radians(hfov_deg) / 2))))
    h = max(16, int(round(2 * f * np.tan(np.radians(vfov_deg) / 2))))
    x0, y0, x1, y1 = -(w - 1) / 2, -(h - 1) / 2, (w - 1) / 2, (h - 1) / 2
    if crop:  # the same-frame overlap's bounding box, grown by `pad_deg` for matches across frames
        local = rays[ok] @ R  # in the view's frame
        front = local[:, 2] > 0.05
        p = local[front, :2] / local[front, 2:3] * f
        pad = f * np.tan(np.radians(pad_deg))
        x0, y0 = max(x0, np.floor(p[:, 0].min() - pad)), max(y0, np.floor(p[:, 1].min() - pad))
        x1, y1 = min(x1, p[:, 0].max() + pad), min(y1, p[:, 1].max() + pad)
        w, h = max(16, int(np.ceil(x1 - x0)) + 1), max(16, int(np.ceil(y1 - y0)) + 1)
    K = np.array([[f, 0.0, phase[0] - x0], [0.0, f, phase[1] - y0], [0.0, 0.0, 1.0]])
    virtual = Camera(f"{cam.name}.overlap", Pinhole(w, h, K, None), pose)
    map_x, map_y, valid = camera_maps(cam, virtual, default_rim_px(cam))
    return _trimmed(VirtualView(virtual, map_x, map_y, valid, R, own / f), trim_margin_px)


_OCTAVE_STEP = 32


def _trimmed(view: VirtualView, margin_px: int) -> VirtualView:
    """The view cut to the box of its valid pixels grown by `margin_px` (zeros kept around the data so that
    SIFT's blurs see the same edge): a pinhole view of a pinhole camera aimed off-axis is about half empty,
    and SIFT's pyramid costs per pixel, empty or not."""
    rows, cols = np.nonzero(view.valid)
    if rows.size == 0:
        return view
    h, w = view.valid.shape
    # the corner on a multiple of SIFT's coarsest step keeps every octave's grid where it was
    y0 = max(0, rows.min() - margin_px) // _OCTAVE_STEP * _OCTAVE_STEP
    x0 = max(0, cols.min() - margin_px) // _OCTAVE_STEP * _OCTAVE_STEP
    y1, x1 = min(h, rows.max() + 1 + margin_px), min(w, cols.max() + 1 + margin_px)
    if (y1 - y0) * (x1 - x0) >= 0.95 * h * w:
        return view
    K = view.camera.intrinsics.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    camera = Camera(view.camera.name, Pinhole(x1 - x0, y1 - y0, K, None), view.camera.sensor_to_ego)
    box = (slice(y0, y1), slice(x0, x1))
    return VirtualView(camera, view.map_x[box].copy(), view.map_y[box].copy(), view.valid[box].copy(), view.R,
                       view.step)
