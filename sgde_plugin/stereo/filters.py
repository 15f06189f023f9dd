"""Post-processing of rectified disparity maps: sub-pixel refinement, left-right and photometric checks, islands.

All functions work on the "core" columns of a rectified canvas (the shared sector), given as
arrays of shape (H, Wc) whose column j is canvas column x0 + j. The other image of the pair is
passed whole (canvas width), so matches may land in its padding.
"""

from __future__ import annotations

import cv2
import numpy as np

_DX = np.array([[-0.5, 0.0, 0.5]], np.float32)
_MEDIAN_SAMPLES = 2500  # the brightness offset is taken on every second row and column from this many pixels on


def grey_float(image: np.ndarray) -> np.ndarray:
    """uint8 grey or RGB -> float32 grey."""
    return image.astype(np.float32) if image.ndim == 2 else image.astype(np.float32).mean(axis=2)


def shift_maps(disp: np.ndarray, sign: int, x0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps sampling the other image at canvas column x0 + j + sign * d, same row."""
    h, w = disp.shape
    cols, d = np.arange(x0, x0 + w, dtype=np.float32)[None, :], np.asarray(disp, np.float32)
    map_x = cols + d if sign > 0 else cols - d
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    return map_x, map_y


def masked_median(values: np.ndarray, mask: np.ndarray) -> float:
    """`np.median(values[mask])` of a float array (0 when `mask` is empty), with one partition instead of two."""
    x = values[mask]
    n = x.size
    if n == 0:
        return 0.0
    k = n // 2
    x.partition(k)
    if n % 2:
        return float(x[k])
    # np.median's even case: the mean of the two middle values, in the array's precision
    return float((x[:k].max() + x[k]) / x.dtype.type(2))


def x_gradient(image: np.ndarray) -> np.ndarray:
    """Central-difference horizontal gradient of a float32 image."""
    return cv2.filter2D(image, cv2.CV_32F, _DX, borderType=cv2.BORDER_REPLICATE)


def refine_disparity(
    a: np.ndarray, b: np.ndarray, disp: np.ndarray, valid: np.ndarray, sign: int, x0: int = 0,
    iterations: int = 1, window: int = 5, max_step: float = 0.5,
) -> np.ndarray:
    """Sub-pixel refinement of `disp` by Gauss-Newton steps on the windowed photometric error.

    SGBM's parabola fit pulls disparities towards integers ("pixel locking", up to 0.15 px); a few
    offset-compensated Lucas-Kanade steps along the row, with `b` warped by each pixel's own
    disparity (slanted surfaces stay aligned), remove that bias. The derivative used is the one of
    the bilinear interpolant itself (the forward difference of the cell the sample falls in), so a
    step is exact for it even on texture close to the sampling limit, where a central difference
    would underestimate the slope and overshoot. `a` is the reference core (float32), `b` the other
    whole canvas (float32).
    """
    db = np.empty_like(b)
    np.subtract(b[:, 1:], b[:, :-1], out=db[:, :-1])
    db[:, -1] = 0
    d = np.array(disp, np.float32)
    box = (window, window)
    for _ in range(iterations):
        map_x, map_y = shift_maps(d, sign, x0)
        bw = cv2.remap(b, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        j = sign * cv2.remap(db, np.floor(map_x), map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        e = np.subtract(a, bw, out=bw)
        mj, me = cv2.blur(j, box), cv2.blur(e, box)
        num = cv2.blur(np.multiply(j, e, out=e), box)
        num -= np.multiply(mj, me, out=me)
        den = cv2.blur(np.multiply(j, j, out=j), box)
        den -= np.multiply(mj, mj, out=mj)
        step = np.divide(num, np.maximum(den, 1e-3), out=num)
        np.clip(step, -max_step, max_step, out=step)
        np.add(d, step, out=d, where=valid & (den > 1.0))
    return np.where(valid, d, np.float32(0))


def photometric_scores(
    a: np.ndarray, b: np.ndarray, disp: np.ndarray, valid: np.ndarray, sign: int, x0: int = 0,
    window: int = 7, min_std: float = 2.0, origin: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Windowed ZNCC, mean absolute difference and texture of reference `a` against `b` warped by `disp`.

    `b` is sampled at canvas column x0 + j + sign * d (bilinear), so a slanted surface is compared
    after its own per-pixel shift. The absolute difference is taken after removing the pair's
    global brightness offset (median over `valid`; where that holds 4 x 2,500 pixels or more, over
    every second row and column counted from `origin`, the (row, column) of a's first pixel in the map
    it was cut from, so that a cut-out gives the whole map's offset), so differently exposed cameras
    are not penalised. ZNCC is -1 where either patch is flat (std below `min_std` grey levels).
    Texture is the RMS horizontal gradient of `a` in the window (grey levels per pixel).
    """
    map_x, map_y = shift_maps(disp, sign, x0)
    bw = cv2.remap(b, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return window_scores(a, bw, valid, window, min_std, origin=origin)


def window_scores(
    a: np.ndarray, bw: np.ndarray, valid: np.ndarray, window: int = 7, min_std: float = 2.0,
    offset: float | None = None, origin: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`photometric_scores` of reference `a` against `bw`, the other image already warped onto it
    (`offset`: the brightness offset to remove; None = the median of a - bw over `valid` as there)."""
    box = (window, window)
    e = a - bw
    if offset is None:  # a quarter of many pixels gives the same median to a small fraction of a grey level
        r, c = -origin[0] % 2, -origin[1] % 2
        few = np.count_nonzero(valid[r::2, c::2]) < _MEDIAN_SAMPLES
        offset = masked_median(e, valid) if few else masked_median(e[r::2, c::2], valid[r::2, c::2])
    mad = cv2.blur(np.abs(e - offset), box)
    ma, mb = cv2.blur(a, box), cv2.blur(bw, box)
    va = cv2.blur(a * a, box) - ma * ma
    vb = cv2.blur(bw * bw, box) - mb * mb
    cov = cv2.blur(a * bw, box) - ma * mb
    ncc = cov / np.sqrt(np.maximum(va * vb, 1e-6))
    ncc[np.minimum(va, vb) < min_std**2] = -1.0
    gx = x_gradient(a)
    texture = np.sqrt(cv2.blur(gx * gx, box))
    return ncc, mad, texture


def lr_check(
    disp_a: np.ndarray, conf_a: np.ndarray, disp_b: np.ndarray, conf_b: np.ndarray, sign: int, max_diff: float
) -> np.ndarray:
    """Confidence of `disp_a` after the left-right check against `disp_b` (the other reference).

    Both maps cover the same columns. For a left reference (sign=-1) the match of column x is
    x - d; for a right reference (+1), x + d. The check passes when the other map, at the matched
    column, agrees within `max_diff` pixels; the confidence then falls off as a Gaussian of the
    disagreement. Matches outside the other map fail. The other map is read at the rounded column by a
    nearest-neighbour remap (the columns are whole numbers, so it reads exactly that pixel; outside the
    map its confidence reads 0).
    """
    h, w = disp_a.shape
    cols = np.arange(w, dtype=np.float32)[None, :]
    x = np.rint(cols + disp_a if sign > 0 else cols - disp_a).astype(np.float32, copy=False)
    rows = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    other, other_c = (cv2.remap(m, x, rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                      for m in (disp_b, conf_b))
    diff = np.abs(disp_a - other)
    ok = (conf_a > 0) & (other_c > 0) & (diff <= max_diff)
    out = np.divide(diff, max_diff, out=diff)  # in place, the same values as -0.5 * (diff / max_diff) ** 2 ...
    np.multiply(out, out, out=out)
    np.multiply(out, -0.5, out=out)
    np.exp(out, out=out)
    np.multiply(out, conf_a, out=out)  # ... times conf_a, 0 where the check fails
    out[~ok] = 0
    return out.astype(np.float32, copy=False)


def remove_islands(disp: np.ndarray, conf: np.ndarray, min_area: int, max_step: float = 1.0) -> None:
    """Zero (in place) the confidence of connected regions of similar disparity smaller than `min_area` px."""
    if min_area <= 0:
        return
    d16 = np.where(conf > 0, np.rint(disp * 16), -16).astype(np.int16)
    cv2.filterSpeckles(d16, -16, int(min_area), int(round(max_step * 16)))
    conf[d16 < 0] = 0


NORMALIZATIONS = ("none", "gain", "local")


def _masked_blur(image: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian mean of `image` over the pixels where `weight` is 1 (normalised convolution)."""
    num = cv2.GaussianBlur(image * weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(weight, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, 1e-3)


def normalize_image(image: np.ndarray, valid: np.ndarray, mode: str, sigma: float = 8.0,
                    reference: tuple[float, float] | None = None) -> np.ndarray:
    """A uint8 grey canvas made insensitive to exposure: 'gain' (affine to a mean/std), 'local' (local contrast).

    'gain' maps the pixels under `valid` to `reference` = (mean, std) (default 128, 40): one gain and
    offset per image, i.e. per overlap when applied to both canvases of a pair. 'local' subtracts the
    Gaussian mean (sigma px) and divides by the local standard deviation, both taken over `valid`
    only, so the black outside the camera's view does not leak in; it also removes vignetting and
    smooth shading differences. Pixels outside `valid` are 0.
    """
    if mode == "none":
        return image
    if mode not in NORMALIZATIONS:
        raise ValueError(f"unknown normalisation {mode!r} (expected {', '.join(NORMALIZATIONS)})")
    img = grey_float(image)
    w = valid.astype(np.float32)
    target_mean, target_std = reference or (128.0, 40.0)
    if mode == "gain":
        vals = img[valid]
        if vals.size < 2:
            return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        out = (img - vals.mean()) / max(float(vals.std()), 1.0) * target_std + target_mean
    else:
        mean = _masked_blur(img, w, sigma)
        var = _masked_blur(img * img, w, sigma) - mean * mean
        out = (img - mean) / np.sqrt(np.maximum(var, 0) + 4.0) * (target_std / 1.5) + target_mean
    out = np.clip(out, 1, 255)
    out[~valid] = 0
    return (out + 0.5).astype(np.uint8)


def discontinuity_factor(disp: np.ndarray, valid: np.ndarray, jump_px: float, window: int = 7) -> np.ndarray:
    """Per-pixel factor in (0, 1]: jump / (local disparity range) where that range exceeds `jump_px`.

    Matches next to a depth discontinuity are the least reliable (foreground fattening, occlusion
    edges, and a LiDAR that sees round the object from elsewhere); the range is taken over valid
    disparities in a window x window neighbourhood.
    """
    k = np.ones((window, window), np.uint8)
    d = disp.astype(np.float32)
    hi = cv2.dilate(np.where(valid, d, 0).astype(np.float32), k)
    lo = cv2.erode(np.where(valid, d, np.float32(1e6)).astype(np.float32), k)
    rng = np.where(valid, hi - lo, 0)
    return np.where(rng > jump_px, jump_px / np.maximum(rng, 1e-6), 1.0).astype(np.float32)


def depth_edge_factor(depth: np.ndarray, ratio: float, window: int = 15) -> np.ndarray:
    """Per-pixel factor in [0, 1] from the local depth ratio (largest / smallest depth > 0 in a window).

    1 up to a ratio of 1 + `ratio`, falling linearly to 0 at 1 + 5 `ratio`: near an occlusion edge the
    prior is least reliable (foreground fattening, a wrong side of the edge, and a LiDAR that sees round
    the object from elsewhere). Relative, so a given jump counts the same near and far. 1 where depth is 0.
    """
    k = np.ones((window, window), np.uint8)
    d = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.ones(d.shape, np.float32)
    idx = np.flatnonzero(d > 0)
    if idx.size == 0:
        return out
    hi = cv2.dilate(d, k).reshape(-1)[idx]
    lo = cv2.erode(np.where(d > 0, d, np.float32(1e9)), k).reshape(-1)[idx]
    out.reshape(-1)[idx] = np.clip(1 - (hi / lo - 1 - ratio) / (4 * ratio), 0, 1)
    return out
