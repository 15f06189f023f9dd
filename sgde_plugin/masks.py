"""Static (ego-body) masks estimated from a sequence: the parts of an image that do not move while the scene does.

The car's own body (hood, side panels, trunk, mirrors) sits still in a camera's image while the
street flows past. Its reflections move, so a per-pixel "did not change" test alone fails on a
glossy body; what stays put is its outline. The estimator therefore works on regions:

1. static structure: edges with the same orientation at the same pixel in every frame;
2. regions: connected parts of the image once that structure (closed over small gaps) cuts it;
3. a region is the body when it touches the image border, lies mostly in the lower half (the
   hood, panels and trunk do; the sky, the other still region, does not), is at least `min_area` of the image,
   most of its inner boundary is static structure (the outline stayed while the scene moved), and
   it changes over time clearly less than the image as a whole.

The mask follows the rig convention: True / 255 = use the pixel, False / 0 = ignore (body).
Three frames suffice when the car moves between them; more frames make the static edges cleaner.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError
from .rig import Rig

WORK_WIDTH = 384  # estimation runs at about this width; the mask is scaled back up


@dataclass(frozen=True)
class MaskSettings:
    """Thresholds of the static-mask estimator (grey levels of a 0-255 image, fractions of the image)."""

    min_cos: float = 0.95  # an edge is static when its direction agrees (cosine) between every two frames
    min_gradient: float = 4.0  # ... and it is this strong (grey levels per pixel) in every frame
    min_area: float = 0.005  # smallest body region, share of the image
    max_area: float = 0.5  # largest (a larger static region means the car did not move)
    min_outline: float = 0.5  # share of a region's inner boundary on static edges
    max_change_ratio: float = 0.8  # region's median change / the whole image's median change
    close_px: int = 5  # static edges are closed over gaps this wide (working pixels)
    grow_px: int = 2  # the final mask grows by this much (working pixels) over the body's edge


def _grey_small(image: np.ndarray, width: int) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    h, w = grey.shape
    scale = min(1.0, width / w)
    small = cv2.resize(grey, (max(8, round(w * scale)), max(8, round(h * scale))), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(small.astype(np.float32), (0, 0), 1.0)


def static_structure(greys: Sequence[np.ndarray], min_cos: float, min_gradient: float) -> np.ndarray:
    """Bool: edges that are there, with the same orientation, at the same pixel in every frame.

    The body's outline keeps its place and direction while the scene's edges move on; a random
    texture rarely agrees in orientation at one pixel over several frames, flat areas never count.
    """
    grads = []
    for g in greys:
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0) / 4
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1) / 4
        grads.append((gx, gy, np.hypot(gx, gy)))
    out = np.ones(greys[0].shape, bool)
    for _, _, m in grads:
        out &= m > min_gradient
    for i in range(len(grads)):
        for j in range(i + 1, len(grads)):
            xi, yi, mi = grads[i]
            xj, yj, mj = grads[j]
            out &= (xi * xj + yi * yj) > min_cos * mi * mj
    return out


def temporal_change(greys: Sequence[np.ndarray]) -> np.ndarray:
    """Per-pixel median over frame pairs of the absolute grey difference."""
    diffs = [np.abs(greys[i] - greys[j]) for i in range(len(greys)) for j in range(i + 1, len(greys))]
    return np.median(np.stack(diffs), axis=0)


def estimate_static_mask(images: Sequence[np.ndarray], settings: MaskSettings | None = None) -> np.ndarray:
    """Bool (H, W) of the first image's size: True = scene (use), False = static body (ignore).

    `images`: two or more frames of one camera (uint8 RGB or grey), taken while the car moves.
    """
    s = settings or MaskSettings()
    if len(images) < 2:
        raise ValueError("a static mask needs at least two frames")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("all frames of a camera must have the same size")
    greys = [_grey_small(im, WORK_WIDTH) for im in images]
    sh, sw = greys[0].shape
    edges = static_structure(greys, s.min_cos, s.min_gradient)
    change = temporal_change(greys)
    kc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * s.close_px + 1, 2 * s.close_px + 1))
    walls = cv2.morphologyEx(edges.astype(np.uint8), cv2.MORPH_CLOSE, kc) > 0
    n, labels, stats, centroids = cv2.connectedComponentsWithStats((~walls).astype(np.uint8), connectivity=4)
    border = np.zeros((sh, sw), bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    body = np.zeros((sh, sw), bool)
    ring = np.ones((5, 5), np.uint8)
    candidates = []
    for i in range(1, n):
        if not s.min_area * sh * sw <= stats[i, cv2.CC_STAT_AREA] <= s.max_area * sh * sw:
            continue
        region = labels == i
        if not (region & border).any() or centroids[i][1] < sh / 2:  # the sky is the other still region
            continue
        outline = (cv2.dilate(region.astype(np.uint8), ring) > 0) & ~region & ~border
        if not outline.any():  # the region is the whole image: nothing is static
            continue
        on_edges = float((edges | walls)[outline].mean())
        if on_edges >= s.min_outline:
            candidates.append(region)
    scene_change = float(np.median(change[~walls])) if (~walls).any() else 0.0
    for region in candidates:
        if float(np.median(change[region])) <= s.max_change_ratio * max(scene_change, 1e-3):
            body |= region
    if body.any():  # the outline itself (the static structure along it) belongs to the body
        reach = s.close_px + 2
        kr = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
        body |= (cv2.dilate(body.astype(np.uint8), kr) > 0) & walls
        kg = np.ones((2 * s.grow_px + 1, 2 * s.grow_px + 1), np.uint8)
        body = cv2.dilate(body.astype(np.uint8), kg) > 0
    full = cv2.resize(body.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    return ~full


def spread_frames(n_frames: int, count: int) -> list[int]:
    """Up to `count` frame indices spread evenly over a sequence of `n_frames` (first and last included)."""
    if n_frames <= count:
        return list(range(n_frames))
    return sorted({round(i * (n_frames - 1) / (count - 1)) for i in range(count)})


def attach_masks(rig: Rig, folder: str | Path) -> Rig:
    """The rig with `folder/<camera>.png` as static masks for every camera that has no mask of its own.

    Masks already on the rig (the user's, from the rig folder's masks/) take precedence.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, None, "mask folder not found")
    found = {c: folder / f"{c}.png" for c in rig.camera_names if (folder / f"{c}.png").is_file()}
    return replace(rig, masks={**found, **dict(rig.masks)})
