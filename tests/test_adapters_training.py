"""End to end: BEVDepth-style depth branch + mock LSS pooling + mock heatmap head on synthetic frames.

The frames are generated here (fast, a fresh scene every step): a nuScenes-like ring of six
cameras, each facing a wall at a random distance above a flat ground; the image is a random
texture (no cue to the wall's distance, like the scale ambiguity of a single view); the prior is
the true depth with 1 % noise in the outer 20 % columns of each image (where neighbours overlap)
and 0 elsewhere; the BEV target marks the cells holding the walls and ground seen by the cameras.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from mock_bev import HeatmapHead, frustum_points, lss_pool
from torch import nn

from sgde_plugin.adapters import PriorDepthNet
from sgde_plugin.adapters.depth_bins import num_depth_bins
from sgde_plugin.geometry import camera_mount

H, W, STRIDE = 64, 176, 16
B, N = 2, 6
D_BOUND = (2.0, 58.0, 4.0)  # 14 coarse bins: 50 steps are enough to see the prior's effect
MID = 32
LR = 5e-3
BEV_ORIGIN, BEV_CELL, BEV_HW = (-51.2, -51.2), 3.2, (32, 32)
YAWS = (0.0, -55.0, -110.0, 180.0, 110.0, 55.0)


def _rig() -> tuple[torch.Tensor, torch.Tensor]:
    K = torch.tensor([[100.0, 0, (W - 1) / 2], [0, 100.0, (H - 1) / 2], [0, 0, 1]])
    s2e = torch.stack([torch.as_tensor(camera_mount(math.radians(y), np.array([0.0, 0.0, 1.5])),
                                       dtype=torch.float32) for y in YAWS])
    return K.expand(B, N, 3, 3).clone(), s2e.expand(B, N, 4, 4).clone()


def _frame(g: torch.Generator, K: torch.Tensor, s2e: torch.Tensor) -> dict[str, torch.Tensor]:
    v = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    ground = torch.where(v > K[0, 0, 1, 2] + 2, K[0, 0, 1, 1] * 1.5 / (v - K[0, 0, 1, 2]).clamp(min=1e-3),
                         torch.full_like(v, 1e9))
    wall = 5.0 + 45.0 * torch.rand(B, N, 1, 1, generator=g)
    depth = torch.minimum(wall, ground.expand(B, N, H, W))
    texture = F.avg_pool2d(torch.rand(B * N, 3, H, W, generator=g), 3, 1, 1).reshape(B, N, 3, H, W)
    image = texture  # no depth cue in the image: metric depth comes from the prior only
    band = torch.zeros(W, dtype=torch.bool)
    band[: int(0.2 * W)] = True
    band[int(0.8 * W):] = True
    prior = torch.where(band, depth * (1 + 0.01 * torch.randn(B, N, H, W, generator=g)), torch.zeros_like(depth))
    # BEV target: cells of the surfaces sampled at the feature cell centres, at their true depth
    cells = depth[..., STRIDE // 2 :: STRIDE, STRIDE // 2 :: STRIDE]  # [B, N, h, w]
    pts = frustum_points(K, s2e, cells.shape[-2:], STRIDE, (0.0, 1.0, 1.0))[:, :, 0] / 0.5 * cells[..., None]
    ix = ((pts[..., 0] - BEV_ORIGIN[0]) / BEV_CELL).long().clamp(0, BEV_HW[0] - 1)
    iy = ((pts[..., 1] - BEV_ORIGIN[1]) / BEV_CELL).long().clamp(0, BEV_HW[1] - 1)
    target = torch.zeros(B, BEV_HW[0] * BEV_HW[1])
    target.scatter_(1, (ix * BEV_HW[1] + iy).reshape(B, -1), 1.0)
    return {"image": image, "depth": depth, "prior": prior, "bev": target.reshape(B, 1, *BEV_HW)}


class _Model(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.backbone = nn.Sequential(nn.Conv2d(3, 16, STRIDE, stride=STRIDE), nn.ReLU())
        bins = num_depth_bins(D_BOUND)
        self.depth_net = PriorDepthNet(16, MID, 16, bins, d_bound=D_BOUND, downsample=STRIDE,
                                       prior_hidden_channels=16)
        self.head = HeatmapHead(16)


def _train(use_prior: bool, steps: int = 50, seed: int = 0) -> dict[str, list[float]]:
    torch.manual_seed(seed)
    model = _Model()
    opt = torch.optim.Adam(model.parameters(), lr=LR)
    K, s2e = _rig()
    eye = torch.eye(4).expand(B, 1, N, 4, 4)
    K4 = eye.clone()
    K4[..., :3, :3] = K[:, None]
    mats = {"intrin_mats": K4, "ida_mats": eye, "sensor2ego_mats": s2e[:, None],
            "bda_mat": torch.eye(4).expand(B, 4, 4)}
    geom = frustum_points(K, s2e, (H // STRIDE, W // STRIDE), STRIDE, D_BOUND)
    g = torch.Generator().manual_seed(seed + 1)
    log: dict[str, list[float]] = {"total": [], "depth": [], "prior_grad": []}
    for _ in range(steps):
        f = _frame(g, K, s2e)
        feats = model.backbone(f["image"].flatten(0, 1))
        out = model.depth_net(feats, mats, prior=f["prior"] if use_prior else None)
        bins = model.depth_net.depth_channels
        probs = out[:, :bins].softmax(dim=1)
        bev = lss_pool(probs, out[:, bins:], geom, BEV_ORIGIN, BEV_CELL, BEV_HW)
        depth_loss = model.depth_net.get_depth_loss(f["depth"], probs)
        total = depth_loss + HeatmapHead.loss(model.head(bev), f["bev"])
        if use_prior:
            total = total + model.depth_net.get_prior_loss(f["prior"], probs)
        opt.zero_grad()
        total.backward()
        log["prior_grad"].append(sum(p.grad.abs().sum().item() for p in model.depth_net.prior_encoder.parameters()
                                     if p.grad is not None))
        opt.step()
        log["total"].append(total.item())
        log["depth"].append(depth_loss.item())
    return log


def test_depth_branch_trains_end_to_end_and_the_prior_helps():
    # two runs of 50 steps, same seeds and frames (~10 s). Tiny tensors: one thread avoids the
    # oversubscription that makes them 10x slower on a busy 2-core machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with_prior = _train(use_prior=True)
        without = _train(use_prior=False)
    finally:
        torch.set_num_threads(threads)
    first, last = np.mean(with_prior["total"][:5]), np.mean(with_prior["total"][-5:])
    assert last < 0.7 * first, (first, last)
    assert with_prior["prior_grad"][0] > 0 and min(with_prior["prior_grad"]) > 0  # the prior encoder learns
    assert max(without["prior_grad"]) == 0  # no prior, no gradient through its encoder
    # measured 0.88-0.91 over seeds 0-3 (BEVDepth's 0.5 m bins: 0.96 after 50 steps, 0.91 after 150)
    d_with, d_without = np.mean(with_prior["depth"][-10:]), np.mean(without["depth"][-10:])
    assert d_with < 0.95 * d_without, (d_with, d_without)
