"""BEVDepth's depth-bin supervision: nearest depth per feature cell, one-hot bins, BCE on foreground."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .prior_features import min_pool_nonzero

D_BOUND = (2.0, 58.0, 0.5)  # BEVDepth's default depth bins: [2.0, 58.0) metres in 0.5 m steps


def num_depth_bins(d_bound: tuple[float, float, float] | list[float]) -> int:
    """Number of bins of ``d_bound`` = (start, stop, step), as ``torch.arange`` counts them."""
    return len(torch.arange(*d_bound))


def depth_bin_labels(gt_depths: Tensor, downsample: int, d_bound: tuple[float, float, float]) -> Tensor:
    """Ground-truth depth [B, N, H, W] (0 = none) -> one-hot labels [B*N*h*w, D] (float).

    BEVDepth's semantics: per downsample x downsample patch the smallest non-zero depth, bin
    index floor((d - (start - step)) / step) - 1; a cell without depth or outside
    [start, start + D * step) gets an all-zero row (background).
    """
    start, _, step = d_bound
    n_bins = num_depth_bins(d_bound)
    cells = min_pool_nonzero(gt_depths.flatten(0, -3), downsample)  # [B*N, h, w]
    shifted = (cells - (start - step)) / step
    keep = (cells > 0) & (shifted >= 0.0) & (shifted < n_bins + 1)
    index = torch.where(keep, shifted, torch.zeros_like(shifted)).long()
    one_hot = F.one_hot(index, num_classes=n_bins + 1).reshape(-1, n_bins + 1)[:, 1:]
    return one_hot.to(gt_depths.dtype)


def depth_bce_loss(labels: Tensor, depth_probs: Tensor) -> Tensor:
    """BCE of per-cell bin probabilities against one-hot labels, summed per cell, averaged over foreground.

    ``labels`` [M, D] from ``depth_bin_labels``; ``depth_probs`` [B*N, D, h, w] (softmax over D).
    Cells whose label row is all zero contribute nothing; with no foreground at all the loss is 0.
    Safe under fp16 / bf16 autocast, as BEVDepth does it: the BCE runs with autocast off, in float32
    (CUDA autocast refuses ``binary_cross_entropy`` otherwise).
    """
    n_bins = labels.shape[1]
    if depth_probs.shape[1] != n_bins:
        raise ValueError(f"depth_preds have {depth_probs.shape[1]} bins, labels have {n_bins}")
    preds = depth_probs.permute(0, 2, 3, 1).reshape(-1, n_bins)
    if preds.shape[0] != labels.shape[0]:
        raise ValueError(f"{preds.shape[0]} predicted cells but {labels.shape[0]} labelled cells")
    fg = labels.max(dim=1).values > 0
    with torch.autocast(device_type=preds.device.type, enabled=False):
        bce = F.binary_cross_entropy(preds[fg].float(), labels[fg].float(), reduction="none").sum()
    return bce / fg.sum().clamp_min(1)
