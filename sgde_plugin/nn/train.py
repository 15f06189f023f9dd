"""The depth-net training loop of the benchmarks and the demo: arms, steps, evaluation.

An *arm* is one way of using the prior (none, as input, as L1 supervision, both); every arm of a
comparison starts from the same initial weights (`arm_nets`) and is trained by `train_arm` with the
same seed, data order and budget, then scored by `evaluate` on held-out frames of a `RigSequence`.
Supervision is LiDAR-like sparse depth, or self-supervised view synthesis (`SelfSupervision`: the
temporal neighbours of each frame and the adjacent cameras of the same capture, `nn.photometric`).
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

from ..cameras import CameraModel
from ..geometry import invert_transform
from ..metrics import average_metrics, dep_con_terms, depth_metrics
from .depthnet import DepthNet
from .losses import DEFAULT_WEIGHT, PriorL1Loss, depth_rays
from .photometric import PhotometricConfig, PhotometricLoss, SourceView
from .sequence import RigSequence

MAX_DEPTH_EVAL = 80.0  # nuScenes evaluation cap


@dataclass(frozen=True)
class PriorWeight:
    """A prior-loss weight that starts at ``start`` and moves linearly to ``final`` over the first ``steps``
    training steps (a warm-up where the prior anchors the first steps), then stays at ``final``."""

    final: float
    start: float | None = None
    steps: int = 0

    def at(self, step: int) -> float:
        """The weight at ``step`` (0-based)."""
        if self.start is None or step >= self.steps:
            return self.final
        return self.start + (self.final - self.start) * step / self.steps


@dataclass(frozen=True)
class Arm:
    """One arm of a comparison: the prior as input channel or not, the prior loss weight or None."""

    name: str
    prior_input: bool
    prior_weight: float | PriorWeight | None
    prior_loss: str = "l1"  # "l1": lambda * |D - D_p| (the paper); "log_l1": lambda * |log D - log D_p|


SUPERVISED_ARMS = (
    Arm("baseline", False, None),
    Arm("+ input", True, None),
    Arm("+ input & L1", True, DEFAULT_WEIGHT),
)
SELF_PRIOR_LOSS, SELF_PRIOR_WEIGHT = "log_l1", 0.05  # the self-supervised arms' prior loss (see `prior_term`)
SELF_PRIOR_ENCODING = "log"  # the self-supervised prior arms' input channel, log(depth / 10 m) (`PriorEncoding`)
SELF_SUPERVISED_ARMS = (
    Arm("baseline", False, None),
    Arm("+ input", True, None),
    Arm("+ L1", False, SELF_PRIOR_WEIGHT, SELF_PRIOR_LOSS),
    Arm("+ input & L1", True, SELF_PRIOR_WEIGHT, SELF_PRIOR_LOSS),
)


def arm_nets(init: DepthNet, arms: tuple[Arm, ...], validity: bool = True, prior_max_depth: float | None = None,
             stem: str = "full", prior_encoding: str = "depth") -> dict[str, DepthNet]:
    """One network per arm, all copies of the RGB-only ``init`` (prior arms: first conv widened, the prior
    channel encoded as ``prior_encoding``, see `PriorEncoding`)."""
    nets: dict[str, DepthNet] = {}
    for arm in arms:
        if arm.prior_input:
            nets[arm.name] = DepthNet.with_prior_from(init, validity=validity, prior_max_depth=prior_max_depth,
                                                      stem=stem, prior_encoding=prior_encoding)
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


def prior_term(out: dict, prior: Tensor, valid: Tensor, scales: tuple[int, ...], weight: float,
               form: str = "l1") -> Tensor:
    """The prior loss averaged over the output scales: lambda * L1(D, D_p) (``form="l1"``, the paper's), or
    lambda * L1(log D, log D_p) (``"log_l1"``: scale-free, comparable in size with a photometric loss)."""
    if form not in ("l1", "log_l1"):
        raise ValueError(f"prior loss form must be 'l1' or 'log_l1', got {form!r}")
    if form == "l1":
        loss = PriorL1Loss(weight=weight)
        return sum(loss(out[("depth", s)], prior, valid) for s in scales) / len(scales)
    target = prior if valid is None else torch.where(valid.to(torch.bool), prior, torch.zeros_like(prior))
    if not bool((target > 0).any()):
        return out[("depth", scales[0])].sum() * 0.0
    return weight * supervised_loss(out, target, scales)  # the prior as sparse log-depth supervision


class SelfSupervision:
    """Self-supervised view-synthesis loss of one rig frame (all cameras in one batch) of a `RigSequence`.

    Each camera's depth is scored by warping its temporal neighbours (the same camera at the context
    instants before and after, `seq.context_images`) and its adjacent cameras of the same capture
    (`seq.pairs`) into it, with the poses of `seq.camera_to_world` / `seq.context_camera_to_world`
    (each camera's pose at its own capture time); `seq.masks` are honoured.
    """

    def __init__(self, seq: RigSequence, config: PhotometricConfig | None = None) -> None:
        config = config or PhotometricConfig()
        if seq.camera_to_world is None or (config.temporal and seq.context_images is None):
            raise ValueError("self-supervision needs camera_to_world (and context images for temporal sources)")
        self.seq, self.loss = seq, PhotometricLoss(config)
        self.models: list[CameraModel] = [c.intrinsics for c in seq.cameras]
        self.rays = torch.cat([depth_rays(m) for m in self.models])
        names = [c.name for c in seq.cameras]
        self.neighbours: list[list[int]] = [[] for _ in names]
        for a, b in seq.pairs:
            self.neighbours[names.index(a)].append(names.index(b))
            self.neighbours[names.index(b)].append(names.index(a))
        n, (h, w) = len(names), seq.images.shape[2:4]
        self.masks = torch.ones(n, 1, h, w, dtype=torch.bool) if seq.masks is None else \
            torch.from_numpy(seq.masks)[:, None].to(torch.bool)

    def _pose(self, source_to_world: np.ndarray, target_to_world: np.ndarray) -> Tensor:
        return torch.from_numpy(invert_transform(source_to_world) @ target_to_world).float()

    def sources(self, k: int, rgb: Tensor) -> list[SourceView]:
        """Source views of every camera in frame ``k``; ``rgb`` [N,3,H,W] the frame's images."""
        seq, n = self.seq, len(self.models)
        out = []
        if self.loss.config.temporal:
            for j in range(seq.context_images.shape[1]):
                image = torch.from_numpy(seq.context_images[k, j]).float().div(255).permute(0, 3, 1, 2)
                poses = torch.stack([self._pose(seq.context_camera_to_world[k, j, i], seq.camera_to_world[k, i])
                                     for i in range(n)])
                out.append(SourceView(image, self.models, poses, True, self.masks))
        if self.loss.config.spatial:
            for slot in range(max(len(nb) for nb in self.neighbours)):
                # camera i's slot-th neighbour; a camera with fewer neighbours gets an all-False mask
                src = [nb[slot] if slot < len(nb) else i for i, nb in enumerate(self.neighbours)]
                poses = torch.stack([self._pose(seq.camera_to_world[k, j], seq.camera_to_world[k, i])
                                     for i, j in enumerate(src)])
                present = torch.tensor([slot < len(nb) for nb in self.neighbours])[:, None, None, None]
                out.append(SourceView(rgb[src], [self.models[j] for j in src], poses, False,
                                      self.masks[src] & present))
        return out

    def __call__(self, out: dict, k: int, rgb: Tensor, scales: tuple[int, ...]) -> Tensor:
        """Photometric loss of frame ``k`` (all cameras) given the net's outputs ``out``."""
        depths = [out[("depth", s)] for s in scales]
        return self.loss(depths, rgb, self.rays, self.sources(k, rgb), self.masks)


@dataclass(frozen=True)
class Schedule:
    """Optimiser settings of `train_arm`: Adam at ``lr`` after a linear warm-up over ``warmup`` steps, x0.2
    after 75 % of the steps, gradients clipped to a total norm of ``clip`` (None: not clipped)."""

    lr: float = 2e-4
    warmup: int = 0
    clip: float | None = None

    def factor(self, step: int, steps: int) -> float:
        """Learning-rate multiplier at ``step`` (0-based) of ``steps``."""
        warm = min(1.0, (step + 1) / self.warmup) if self.warmup else 1.0
        return warm * (0.2 if step >= int(steps * 0.75) else 1.0)


SELF_SCHEDULE = Schedule(lr=1e-3, warmup=20, clip=1.0)  # the self-supervised recipe, every arm alike
SELF_INITIAL_DEPTH_M = 10.0  # self-supervised nets start predicting this depth everywhere


def start_at_depth(net: DepthNet, depth_m: float) -> None:
    """Set the depth heads' biases so that a zero input to them gives ``depth_m`` (a view-synthesis loss
    only sees matches a few pixels from the current depth: a random net's start, 1 / (mean of the
    disparity range), is too near)."""
    sig = (1.0 / depth_m - 1.0 / net.max_depth) / (1.0 / net.min_depth - 1.0 / net.max_depth)
    with torch.no_grad():
        for head in net.decoder.heads.values():
            head.bias.fill_(math.log(sig / (1.0 - sig)))


def train_arm(net: DepthNet, seq: RigSequence, train_frames: list[int], steps: int, seed: int,
              prior_weight: float | PriorWeight | None, lr: float = 2e-4,
              self_supervision: SelfSupervision | None = None, schedule: Schedule | None = None,
              prior_loss: str = "l1") -> float:
    """Train in place for `steps` steps of one frame (all cameras); returns seconds spent.

    The loss is the LiDAR-like supervised loss, or with ``self_supervision`` the view-synthesis loss;
    ``prior_weight`` adds the prior loss (`prior_term` of form ``prior_loss``; a `PriorWeight` varies its weight
    over the steps). ``schedule`` (default: Adam
    at ``lr``, no warm-up, no clipping) sets the optimiser.
    """
    schedule = schedule or Schedule(lr=lr)
    rgb, sup, prior, valid = frame_tensors(seq, train_frames)
    n = len(seq.cameras)
    opt = torch.optim.Adam(net.parameters(), lr=schedule.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: schedule.factor(i, steps))
    order = np.random.default_rng(seed).integers(0, len(train_frames), size=steps)
    weight = prior_weight if isinstance(prior_weight, PriorWeight) or prior_weight is None else \
        PriorWeight(prior_weight)
    net.train()
    t0 = time.perf_counter()
    for step, k in enumerate(order):
        sl = slice(int(k) * n, (int(k) + 1) * n)
        out = net(rgb[sl], prior[sl] if net.use_prior else None, valid[sl] if net.use_prior else None)
        if self_supervision is None:
            loss = supervised_loss(out, sup[sl], net.scales)
        else:
            loss = self_supervision(out, train_frames[int(k)], rgb[sl], net.scales)
        if weight is not None and weight.at(step):
            loss = loss + prior_term(out, prior[sl], valid[sl], net.scales, weight.at(step), prior_loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if schedule.clip is not None:
            torch.nn.utils.clip_grad_norm_(net.parameters(), schedule.clip)
        opt.step()
        sched.step()
    return time.perf_counter() - t0


def _pair_dep_con(seq: RigSequence, k: int, pred: np.ndarray, gt: np.ndarray) -> tuple[float, int]:
    """Dep Con sum and count of frame ``k`` over all adjacent pairs, both directions (relative poses from
    each camera's capture pose when the sequence has them, else from the extrinsics)."""
    names = [c.name for c in seq.cameras]
    cams = {c.name: c for c in seq.cameras}
    total, count = 0.0, 0
    for a, b in seq.pairs:
        ia, ib = names.index(a), names.index(b)
        for x, y in ((ia, ib), (ib, ia)):
            if seq.camera_to_world is not None:
                rel = invert_transform(seq.camera_to_world[k, x]) @ seq.camera_to_world[k, y]
            else:
                rel = invert_transform(cams[names[x]].sensor_to_ego) @ cams[names[y]].sensor_to_ego
            s, m = dep_con_terms(pred[x], pred[y], gt[x], cams[names[x]], cams[names[y]], rel,
                                 max_depth=MAX_DEPTH_EVAL)
            total, count = total + s, count + m
    return total, count


def evaluate(net: DepthNet, seq: RigSequence, frames: list[int], paste_prior: bool = False) -> dict[str, float]:
    """Per-image depth metrics (dense ground truth <= 80 m), Abs Rel with per-image median scaling,
    Abs Rel inside / outside the overlap, and Dep Con pooled over all adjacent pairs and frames.
    ``paste_prior`` replaces the prediction by the prior wherever the prior is valid (the most a purely
    local use of the prior can give)."""
    net.eval()
    n = len(seq.cameras)
    rows, inside, outside, scaled = [], [], [], []
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
                scaled.append(depth_metrics(pred[i], gt[i], max_depth=MAX_DEPTH_EVAL, median_scaling=True))
                inside.append(depth_metrics(pred[i], gt[i], mask=seq.overlap[k, i], max_depth=MAX_DEPTH_EVAL))
                outside.append(depth_metrics(pred[i], gt[i], mask=~seq.overlap[k, i], max_depth=MAX_DEPTH_EVAL))
            s, m = _pair_dep_con(seq, k, pred, gt)
            dc_sum, dc_n = dc_sum + s, dc_n + m
    res = {k: v for k, v in average_metrics(rows).items() if k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1")}
    res["abs_rel_median_scaled"] = average_metrics(scaled)["abs_rel"]
    res["abs_rel_overlap"] = pooled_abs_rel(inside)
    res["abs_rel_outside"] = pooled_abs_rel(outside)
    res["dep_con"] = dc_sum / dc_n if dc_n else math.nan
    return res


def pooled_abs_rel(rows: list[dict]) -> float:
    """Abs Rel pooled over pixels of several `depth_metrics` results (weighted by their counts)."""
    n = sum(r["n"] for r in rows)
    return sum(r["abs_rel"] * r["n"] for r in rows if r["n"]) / n if n else math.nan
