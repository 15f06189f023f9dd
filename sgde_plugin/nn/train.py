"""The depth-net training loop of the benchmarks and the demo: arms, steps, evaluation.

An *arm* is one way of using the prior (none, as input, as L1 supervision, both); every arm of a
comparison starts from the same initial weights (`arm_nets`) and is trained by `train_arm` with the
same seed, data order and budget, then scored by `evaluate` on held-out frames of a `RigSequence`.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import invert_transform
from ..metrics import average_metrics, dep_con_terms, depth_metrics
from .depthnet import DepthNet
from .losses import DEFAULT_WEIGHT, PriorL1Loss
from .sequence import RigSequence

MAX_DEPTH_EVAL = 80.0  # nuScenes evaluation cap


@dataclass(frozen=True)
class Arm:
    """One arm of a comparison: the prior as input channel or not, the prior loss weight or None."""

    name: str
    prior_input: bool
    prior_weight: float | None


SUPERVISED_ARMS = (
    Arm("baseline", False, None),
    Arm("+ input", True, None),
    Arm("+ input & L1", True, DEFAULT_WEIGHT),
)
SELF_SUPERVISED_ARMS = (
    Arm("baseline", False, None),
    Arm("+ input", True, None),
    Arm("+ L1", False, DEFAULT_WEIGHT),
    Arm("+ input & L1", True, DEFAULT_WEIGHT),
)


def arm_nets(init: DepthNet, arms: tuple[Arm, ...], validity: bool = True, prior_max_depth: float | None = None,
             stem: str = "full") -> dict[str, DepthNet]:
    """One network per arm, all copies of the RGB-only ``init`` (prior arms: first conv widened)."""
    nets: dict[str, DepthNet] = {}
    for arm in arms:
        if arm.prior_input:
            nets[arm.name] = DepthNet.with_prior_from(init, validity=validity, prior_max_depth=prior_max_depth,
                                                      stem=stem)
        else:
            nets[arm.name] = copy.deepcopy(init)
    return nets


def frame_tensors(seq: RigSequence, frames: list[int]) -> tuple[Tensor, ...]:
    """[F*N, C, H, W] tensors: rgb in [0, 1], supervision, prior, valid."""
    idx = np.asarray(frames)
    rgb = torch.from_numpy(seq.images[idx]).float().div(255).permute(0, 1, 4, 2, 3).flatten(0, 1)
    sup = torch.from_numpy(seq.supervision[idx]).flatten(0, 1)[:, None]
    prior = torch.from_numpy(seq.prior[idx]).flatten(0, 1)[:, None]
    valid = torch.from_numpy(seq.valid[idx]).flatten(0, 1)[:, None]
    return rgb, sup, prior, valid


def supervised_loss(out: dict, gt: Tensor, scales: tuple[int, ...]) -> Tensor:
    """Mean over scales of the L1 of log depth against sparse ground truth (outputs upsampled)."""
    mask = gt > 0
    total = gt.new_zeros(())
    for s in scales:
        d = F.interpolate(out[("depth", s)], size=gt.shape[-2:], mode="bilinear", align_corners=False)
        total = total + (torch.log(d[mask]) - torch.log(gt[mask])).abs().mean()
    return total / len(scales)


def prior_term(out: dict, prior: Tensor, valid: Tensor, scales: tuple[int, ...], weight: float) -> Tensor:
    """The prior loss lambda * L1(D, D_p) averaged over the output scales."""
    loss = PriorL1Loss(weight=weight)
    return sum(loss(out[("depth", s)], prior, valid) for s in scales) / len(scales)


def train_arm(net: DepthNet, seq: RigSequence, train_frames: list[int], steps: int, seed: int,
              prior_weight: float | None, lr: float = 2e-4) -> float:
    """Train in place for `steps` steps of one frame (all cameras); returns seconds spent."""
    rgb, sup, prior, valid = frame_tensors(seq, train_frames)
    n = len(seq.cameras)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, milestones=[int(steps * 0.75)], gamma=0.2)
    order = np.random.default_rng(seed).integers(0, len(train_frames), size=steps)
    net.train()
    t0 = time.perf_counter()
    for k in order:
        sl = slice(int(k) * n, (int(k) + 1) * n)
        out = net(rgb[sl], prior[sl] if net.use_prior else None, valid[sl] if net.use_prior else None)
        loss = supervised_loss(out, sup[sl], net.scales)
        if prior_weight:
            loss = loss + prior_term(out, prior[sl], valid[sl], net.scales, prior_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    return time.perf_counter() - t0


def _pair_dep_con(seq: RigSequence, pred: np.ndarray, gt: np.ndarray) -> tuple[float, int]:
    """Dep Con sum and count of one frame over all adjacent pairs, both directions."""
    names = [c.name for c in seq.cameras]
    cams = {c.name: c for c in seq.cameras}
    total, count = 0.0, 0
    for a, b in seq.pairs:
        ia, ib = names.index(a), names.index(b)
        for x, y in ((ia, ib), (ib, ia)):
            rel = invert_transform(cams[names[x]].sensor_to_ego) @ cams[names[y]].sensor_to_ego
            s, m = dep_con_terms(pred[x], pred[y], gt[x], cams[names[x]], cams[names[y]], rel,
                                 max_depth=MAX_DEPTH_EVAL)
            total, count = total + s, count + m
    return total, count


def evaluate(net: DepthNet, seq: RigSequence, frames: list[int], paste_prior: bool = False) -> dict[str, float]:
    """Per-image depth metrics (dense ground truth <= 80 m), Abs Rel inside / outside the overlap,
    and Dep Con pooled over all adjacent pairs and frames. ``paste_prior`` replaces the prediction by
    the prior wherever the prior is valid (the most a purely local use of the prior can give)."""
    net.eval()
    n = len(seq.cameras)
    rows, inside, outside = [], [], []
    dc_sum, dc_n = 0.0, 0
    with torch.no_grad():
        for k in frames:
            rgb, _, prior, valid = frame_tensors(seq, [k])
            pred = net.predict(rgb, prior if net.use_prior else None, valid if net.use_prior else None)
            pred = pred[:, 0].numpy().astype(np.float64)
            if paste_prior:
                pred = np.where(seq.valid[k], seq.prior[k], pred)
            gt = seq.depth[k]
            for i in range(n):
                rows.append(depth_metrics(pred[i], gt[i], max_depth=MAX_DEPTH_EVAL))
                inside.append(depth_metrics(pred[i], gt[i], mask=seq.overlap[k, i], max_depth=MAX_DEPTH_EVAL))
                outside.append(depth_metrics(pred[i], gt[i], mask=~seq.overlap[k, i], max_depth=MAX_DEPTH_EVAL))
            s, m = _pair_dep_con(seq, pred, gt)
            dc_sum, dc_n = dc_sum + s, dc_n + m
    res = {k: v for k, v in average_metrics(rows).items() if k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1")}
    res["abs_rel_overlap"] = pooled_abs_rel(inside)
    res["abs_rel_outside"] = pooled_abs_rel(outside)
    res["dep_con"] = dc_sum / dc_n if dc_n else math.nan
    return res


def pooled_abs_rel(rows: list[dict]) -> float:
    """Abs Rel pooled over pixels of several `depth_metrics` results (weighted by their counts)."""
    n = sum(r["n"] for r in rows)
    return sum(r["abs_rel"] * r["n"] for r in rows if r["n"]) / n if n else math.nan
