"""Depth metrics on plain arrays / tensors: the standard set (Abs Rel, Sq Rel, RMSE, RMSE log, delta),
the cross-camera depth consistency Dep Con of MCDP, and the OmniMVS fisheye metrics.

Everything accepts NumPy arrays or torch tensors of any shape (matching), computes in float64 on the
CPU and returns plain Python floats, so the prior pipeline and the networks report identical numbers.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from .cameras import Camera, CameraModel
from .geometry import invert_transform
from .splat import warp_depth as splat_warp_depth

METRIC_KEYS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
OMNIMVS_KEYS = (">1", ">3", ">5", "mae", "rms")

ArrayLike = np.ndarray | torch.Tensor  # NumPy array or torch tensor (any device, float dtype); nested lists also work


def _np(x: ArrayLike) -> np.ndarray:
    """Any array-like or tensor -> float64 NumPy array."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _mask(x: ArrayLike | None, shape: tuple[int, ...]) -> np.ndarray:
    if x is None:
        return np.ones(shape, dtype=bool)
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    m = np.asarray(x).astype(bool)
    return np.broadcast_to(m, shape)


def depth_metrics(
    pred: ArrayLike,
    gt: ArrayLike,
    mask: ArrayLike | None = None,
    max_depth: float = 80.0,
    min_depth: float = 1e-3,
    median_scaling: bool = False,
) -> dict[str, float]:
    """Abs Rel, Sq Rel, RMSE, RMSE log and delta < 1.25^k (a1..a3) over the selected pixels, pooled.

    Pixels count where ``mask`` (default all) holds and min_depth < gt <= max_depth; the prediction
    is (optionally median-scaled to the ground truth, then) clipped to [min_depth, max_depth] as in
    the monodepth/KITTI protocol. For a sparse prediction (a depth prior, 0 = no value) pass its
    validity as ``mask``. Per-image averages: call per image and use ``average_metrics``.
    Returns the metrics plus ``n`` (pixel count) and ``scale`` (median ratio, 1 without scaling);
    metrics are NaN when no pixel is selected.
    """
    pred, gt = _np(pred), _np(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred {pred.shape} and gt {gt.shape} differ")
    sel = _mask(mask, gt.shape) & (gt > min_depth) & (gt <= max_depth) & np.isfinite(pred)
    p, g = pred[sel], gt[sel]
    out: dict[str, float] = {"n": int(g.size), "scale": 1.0}
    if g.size == 0:
        out.update({k: math.nan for k in METRIC_KEYS})
        return out
    if median_scaling:
        scale = float(np.median(g) / max(np.median(p), 1e-12))
        p = p * scale
        out["scale"] = scale
    p = np.clip(p, min_depth, max_depth)
    thresh = np.maximum(g / p, p / g)
    diff = g - p
    out.update({
        "abs_rel": float(np.mean(np.abs(diff) / g)),
        "sq_rel": float(np.mean(diff**2 / g)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(g) - np.log(p)) ** 2))),
        "a1": float(np.mean(thresh < 1.25)),
        "a2": float(np.mean(thresh < 1.25**2)),
        "a3": float(np.mean(thresh < 1.25**3)),
    })
    return out


def average_metrics(results: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Mean of per-image metric dicts (images without pixels are skipped); ``n`` is summed."""
    rows = [r for r in results if r.get("n", 1) > 0]
    if not rows:
        return {"n": 0}
    keys = [k for k in rows[0] if k != "n"]
    out = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    out["n"] = int(sum(r.get("n", 0) for r in rows))
    out["images"] = len(rows)
    return out


# --- OmniMVS ------------------------------------------------------------------------------------

def inverse_depth_index(depth: ArrayLike, min_depth: float = 0.5, max_depth: float = math.inf,
                        num_invdepth: int = 192) -> np.ndarray:
    """OmniMVS inverse-depth index: (1/d - 1/max_depth) / step, step = (1/min - 1/max) / (N - 1)."""
    d = _np(depth)
    inv_min, inv_max = 1.0 / max_depth, 1.0 / min_depth
    step = (inv_max - inv_min) / (num_invdepth - 1)
    with np.errstate(divide="ignore"):
        return (1.0 / d - inv_min) / step


def omnimvs_metrics(
    pred: ArrayLike,
    gt: ArrayLike,
    mask: ArrayLike | None = None,
    min_depth: float = 0.5,
    max_depth: float = math.inf,
    num_invdepth: int = 192,
    as_index: bool = False,
) -> dict[str, float]:
    """OmniMVS fisheye metrics on the inverse-depth index (Won et al., OmniMVS, ICCV 2019).

    Following the authors' evaluation (hyu-cvlab/omnimvs-pytorch, ``dataset.py`` ``evalError``):
    error = |idx_pred - idx_gt| / N * 100 (percent of the index range, N = ``num_invdepth``, 192,
    with min depth 0.5 m and no far limit); ">1", ">3", ">5" are the percentages of pixels whose error
    exceeds 1, 3, 5; "mae" and "rms" are the mean and root-mean-square error. Pixels count where the
    ground-truth index lies in [0, N] and ``mask`` holds. Inputs are metric depths (range) unless
    ``as_index`` says they are already indices.
    """
    if as_index:
        ip, ig = _np(pred), _np(gt)
    else:
        ip = inverse_depth_index(pred, min_depth, max_depth, num_invdepth)
        ig = inverse_depth_index(gt, min_depth, max_depth, num_invdepth)
    gt_arr = _np(gt)
    sel = _mask(mask, ig.shape) & (ig >= 0) & (ig <= num_invdepth) & np.isfinite(ip) & np.isfinite(ig)
    if not as_index:
        sel &= gt_arr > 0
    err = np.abs(ip[sel] - ig[sel]) / num_invdepth * 100.0
    out: dict[str, float] = {"n": int(err.size)}
    if err.size == 0:
        out.update({k: math.nan for k in OMNIMVS_KEYS})
        return out
    out.update({
        ">1": float(np.mean(err > 1) * 100),
        ">3": float(np.mean(err > 3) * 100),
        ">5": float(np.mean(err > 5) * 100),
        "mae": float(np.mean(err)),
        "rms": float(np.sqrt(np.mean(err**2))),
    })
    return out


# --- Dep Con ------------------------------------------------------------------------------------

def warp_depth(
    depth_src: ArrayLike,
    src: Camera | CameraModel,
    dst: Camera | CameraModel,
    src_to_dst: ArrayLike,
) -> np.ndarray:
    """Forward-warp a depth map of camera ``src`` into camera ``dst``: [H_dst, W_dst], 0 = nothing.

    Every source pixel with depth > 0 is lifted to 3-D (in the source's depth convention), moved by
    the 4x4 ``src_to_dst`` (source camera frame -> destination camera frame), projected into the
    destination and written at the nearest pixel as depth in the destination's convention; when
    several land on one pixel the nearest surface wins (z-buffer; `sgde_plugin.splat.warp_depth`).
    """
    return splat_warp_depth(_np(depth_src), src, dst, _np(src_to_dst))


def dep_con_terms(
    pred: ArrayLike,
    pred_neighbour: ArrayLike,
    gt: ArrayLike,
    camera: Camera | CameraModel,
    neighbour: Camera | CameraModel,
    neighbour_to_camera: ArrayLike,
    mask: ArrayLike | None = None,
    max_depth: float = math.inf,
) -> tuple[float, int]:
    """Sum of |D - warp(D_neighbour)| / D_gt and the pixel count for one ordered camera pair."""
    warped = warp_depth(pred_neighbour, neighbour, camera, neighbour_to_camera)
    p, g = _np(pred), _np(gt)
    sel = _mask(mask, g.shape) & (warped > 0) & (g > 0) & (g <= max_depth) & (p > 0) & np.isfinite(p)
    return float(np.sum(np.abs(p[sel] - warped[sel]) / g[sel])), int(sel.sum())


def dep_con(
    pred: ArrayLike,
    pred_neighbour: ArrayLike,
    gt: ArrayLike,
    camera: Camera | CameraModel,
    neighbour: Camera | CameraModel,
    neighbour_to_camera: ArrayLike,
    mask: ArrayLike | None = None,
    max_depth: float = math.inf,
) -> dict[str, float]:
    """Depth consistency (MCDP, as used by SGDE): mean |D - warp(D_neighbour)| / D_gt over overlap pixels.

    The neighbour's predicted depth is warped into the camera with the rig's relative transform
    ``neighbour_to_camera`` (4x4, neighbour camera frame -> camera frame, i.e.
    inv(sensor_to_ego_camera) @ sensor_to_ego_neighbour); the mean runs over the camera's pixels that
    receive a warped depth and have ground truth. Lower is more consistent.
    """
    total, n = dep_con_terms(pred, pred_neighbour, gt, camera, neighbour, neighbour_to_camera, mask, max_depth)
    return {"dep_con": total / n if n else math.nan, "n": n}


def rig_dep_con(
    preds: Mapping[str, ArrayLike],
    gts: Mapping[str, ArrayLike],
    cameras: Mapping[str, Camera],
    pairs: Sequence[tuple[str, str]],
    max_depth: float = math.inf,
) -> dict[str, Any]:
    """Dep Con over a rig: both directions of every adjacent pair, pixels pooled; also per pair.

    Cameras are related by their `sensor_to_ego`; for a frame whose cameras fired at different times
    pass `rig.as_captured(frame)`'s cameras, so the relative poses are those at each camera's capture.
    """
    total, count = 0.0, 0
    per_pair: dict[str, float] = {}
    for a, b in pairs:
        pair_total, pair_n = 0.0, 0
        for cam, nb in ((a, b), (b, a)):
            rel = invert_transform(cameras[cam].sensor_to_ego) @ cameras[nb].sensor_to_ego
            s, n = dep_con_terms(preds[cam], preds[nb], gts[cam], cameras[cam], cameras[nb], rel,
                                 max_depth=max_depth)
            pair_total, pair_n = pair_total + s, pair_n + n
        per_pair[f"{a}|{b}"] = pair_total / pair_n if pair_n else math.nan
        total, count = total + pair_total, count + pair_n
    return {"dep_con": total / count if count else math.nan, "n": count, "per_pair": per_pair}
