"""Prior losses L_dp(D, D_p) of SGDE: L1, virtual normal (Yin et al. 2019), structure-guided ranking
(Xian et al. 2020). Each is masked to prior-valid pixels and multiplied by its weight lambda.

All take ``pred`` [B,1,h,w] metric depth (resized bilinearly to the prior's size when it differs),
``prior`` [B,1,H,W] metres (0 = no prior) and optionally ``valid`` [B,1,H,W] bool (default prior > 0).
Sampling losses draw from their own ``torch.Generator`` seeded at construction (or one passed to
``forward``), so a run is reproducible and independent of the global RNG.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

DEFAULT_WEIGHT = 0.005  # lambda of the paper


def _prepare(pred: Tensor, prior: Tensor, valid: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Match pred to the prior's resolution and build the boolean validity mask."""
    if pred.dim() != 4 or prior.dim() != 4 or pred.shape[1] != 1 or prior.shape[1] != 1:
        raise ValueError(f"expected [B,1,H,W] tensors, got pred {tuple(pred.shape)} prior {tuple(prior.shape)}")
    if pred.shape[-2:] != prior.shape[-2:]:
        pred = F.interpolate(pred, size=prior.shape[-2:], mode="bilinear", align_corners=False)
    mask = prior > 0
    if valid is not None:
        mask = mask & valid.to(torch.bool)
    return pred, prior.to(pred.dtype), mask


def _zero(pred: Tensor) -> Tensor:
    """A zero that stays attached to the graph (no valid pixel / sample)."""
    return pred.sum() * 0.0


def _generator(own: torch.Generator, given: torch.Generator | None) -> torch.Generator:
    return given if given is not None else own


class PriorL1Loss(nn.Module):
    """lambda * mean |D - D_p| over prior-valid pixels."""

    def __init__(self, weight: float = DEFAULT_WEIGHT) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, pred: Tensor, prior: Tensor, valid: Tensor | None = None, **_: object) -> Tensor:
        """Weighted L1 between prediction and prior where the prior is valid."""
        pred, prior, mask = _prepare(pred, prior, valid)
        if not bool(mask.any()):
            return _zero(pred)
        return self.weight * (pred - prior).abs()[mask].mean()


def pinhole_rays(K: Tensor, height: int, width: int) -> Tensor:
    """Per-pixel vectors r with point = r * z for a pinhole camera: K^-1 [u, v, 1], shape [B,3,H,W]."""
    K = K.reshape(-1, 3, 3)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=K.dtype, device=K.device),
        torch.arange(width, dtype=K.dtype, device=K.device),
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=0).reshape(3, -1)
    return (torch.linalg.inv(K) @ pix).reshape(-1, 3, height, width)


def depth_rays(model: object, dtype: torch.dtype = torch.float32) -> Tensor:
    """Vectors r [1,3,H,W] with point = r * depth for any ``sgde_plugin.cameras.CameraModel``.

    Pinhole depth is z (rays scaled to z = 1), fisheye depth is range (unit rays); pixels outside
    the model's field of view get zero vectors.
    """
    rays, ok = model.ray_grid(dtype=torch.float64)
    if not model.depth_is_range:
        z = rays[..., 2:3]
        rays = rays / torch.where(z.abs() > 1e-9, z, torch.ones_like(z))
    rays = torch.where(ok[..., None], rays, torch.zeros_like(rays))
    return rays.permute(2, 0, 1)[None].to(dtype)


class PriorVirtualNormalLoss(nn.Module):
    """lambda * virtual-normal loss (Yin et al., ICCV 2019) against the prior's 3-D points.

    Random triplets of prior-valid pixels are lifted to 3-D with the prior and with the prediction;
    triplets that are degenerate in the prior (points closer than ``min_dist`` on every axis, or
    nearly collinear: |cos| of an angle above ``max_cos``) are dropped. The loss is the mean L1
    distance between the unit normals of the remaining prior and predicted triangles.
    Geometry comes from ``K`` [B,3,3] (pinhole) or ``rays`` [B|1,3,H,W] (point = rays * depth).
    """

    def __init__(
        self,
        weight: float = DEFAULT_WEIGHT,
        num_triplets: int = 2000,
        max_cos: float = 0.867,
        min_dist: float = 0.01,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.num_triplets = int(num_triplets)
        self.max_cos = float(max_cos)
        self.min_dist = float(min_dist)
        self.generator = torch.Generator().manual_seed(seed)

    def sample(self, mask: Tensor, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Triplet pixel indices [B,T,3] (flattened H*W) among valid pixels and the rows that have any."""
        b = mask.shape[0]
        flat = mask.reshape(b, -1).to(torch.float64).cpu()
        has = flat.sum(1) > 0
        flat[~has] = 1.0
        idx = torch.multinomial(flat, 3 * self.num_triplets, replacement=True,
                                generator=_generator(self.generator, generator))
        return idx.reshape(b, self.num_triplets, 3).to(mask.device), has.to(mask.device)

    def forward(
        self,
        pred: Tensor,
        prior: Tensor,
        valid: Tensor | None = None,
        K: Tensor | None = None,
        rays: Tensor | None = None,
        generator: torch.Generator | None = None,
        **_: object,
    ) -> Tensor:
        """Weighted virtual-normal loss; needs ``K`` or ``rays``."""
        pred, prior, mask = _prepare(pred, prior, valid)
        b, _, h, w = prior.shape
        if rays is None:
            if K is None:
                raise ValueError("PriorVirtualNormalLoss needs K or rays")
            rays = pinhole_rays(K.to(pred.dtype), h, w)
        rays = rays.to(pred.dtype).expand(b, 3, h, w).reshape(b, 3, -1)
        if not bool(mask.any()):
            return _zero(pred)
        idx, has = self.sample(mask, generator)  # [B,T,3]
        flat_idx = idx.reshape(b, 1, -1)

        def points(depth: Tensor) -> Tensor:  # [B,T,3 points,3 xyz]
            d = torch.gather(depth.reshape(b, 1, -1), 2, flat_idx)
            r = torch.gather(rays, 2, flat_idx.expand(b, 3, -1))
            return (r * d).permute(0, 2, 1).reshape(b, self.num_triplets, 3, 3)

        p_gt, p_pr = points(prior), points(pred)
        keep = self._keep(p_gt) & has[:, None]
        if not bool(keep.any()):
            return _zero(pred)
        n_gt, n_pr = self._normal(p_gt), self._normal(p_pr)
        err = (n_gt - n_pr).abs().sum(-1)
        return self.weight * err[keep].mean()

    def _keep(self, p: Tensor) -> Tensor:
        """Non-degenerate triplets of the prior: spread out and not collinear."""
        e01, e02, e12 = p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0], p[:, :, 2] - p[:, :, 1]
        close = torch.stack([(e.abs() < self.min_dist).all(-1) for e in (e01, e02, e12)], -1).any(-1)

        def cos(a: Tensor, c: Tensor) -> Tensor:
            return (a * c).sum(-1) / (a.norm(dim=-1) * c.norm(dim=-1)).clamp_min(1e-12)

        cosines = torch.stack([cos(e01, e02), cos(-e01, e12), cos(e02, e12)], -1)
        collinear = (cosines.abs() > self.max_cos).any(-1)
        return ~close & ~collinear

    @staticmethod
    def _normal(p: Tensor) -> Tensor:
        n = torch.linalg.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0], dim=-1)
        return n / torch.sqrt((n * n).sum(-1, keepdim=True) + 1e-12)


_SOBEL_X = ((-1.0, 0.0, 1.0), (-2.0, 0.0, 2.0), (-1.0, 0.0, 1.0))


class PriorRankingLoss(nn.Module):
    """lambda * structure-guided ranking loss (Xian et al., CVPR 2020) with pairs sampled from the prior.

    Pairs come from edge-guided sampling (anchors on strong edges of the log prior, four points along
    the gradient direction at 2..30 px, pairs A-B, B-C, C-D) plus random pairs of valid pixels. The
    ordinal label of a pair is +1 / -1 when the prior depth ratio exceeds 1 + ``sigma`` either way,
    else 0. The loss on the log predicted depth is log(1 + exp(-l (p_a - p_b))) for ordered pairs
    and (p_a - p_b)^2 for equal pairs, averaged over pairs of two distinct valid pixels.
    """

    def __init__(
        self,
        weight: float = DEFAULT_WEIGHT,
        num_pairs: int = 2000,
        sigma: float = 0.02,
        edge_fraction: float = 0.5,
        edge_threshold: float = 0.1,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.num_pairs = int(num_pairs)
        self.sigma = float(sigma)
        self.edge_fraction = float(edge_fraction)
        self.edge_threshold = float(edge_threshold)
        self.generator = torch.Generator().manual_seed(seed)

    def sample(self, prior: Tensor, mask: Tensor, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Pixel index pairs [B,P,2] (flattened H*W) and their validity [B,P]; computed on the CPU."""
        g = _generator(self.generator, generator)
        prior, mask = prior.detach().cpu().to(torch.float64), mask.cpu()
        b, _, h, w = prior.shape
        flat = mask.reshape(b, -1).to(torch.float64)
        has = flat.sum(1) > 0
        n_edge_anchor = int(self.num_pairs * self.edge_fraction) // 3
        n_rand = self.num_pairs - 3 * n_edge_anchor

        if n_rand > 0:
            rand = torch.multinomial(torch.where(has[:, None], flat, torch.ones_like(flat)), 2 * n_rand,
                                     replacement=True, generator=g).reshape(b, n_rand, 2)
        else:
            rand = torch.zeros(b, 0, 2, dtype=torch.long)
        rand_ok = has[:, None].expand(b, n_rand)
        if n_edge_anchor == 0:
            return rand, rand_ok & (rand[..., 0] != rand[..., 1])

        logp = F.pad(torch.log(prior.clamp_min(1e-6)) * mask, (1, 1, 1, 1), mode="replicate")
        kx = torch.tensor(_SOBEL_X, dtype=torch.float64).reshape(1, 1, 3, 3)
        gx = F.conv2d(logp, kx)
        gy = F.conv2d(logp, kx.transpose(2, 3))
        # an edge only counts where its whole 3x3 neighbourhood has a prior (not the overlap's border)
        full = -F.max_pool2d(-mask.to(torch.float64), 3, stride=1, padding=1) > 0.5
        mag = torch.sqrt(gx * gx + gy * gy) * full
        peak = mag.reshape(b, -1).amax(1).clamp_min(1e-12)
        edges = (mag.reshape(b, -1) >= self.edge_threshold * peak[:, None]) & (mag.reshape(b, -1) > 0)
        has_edge = edges.any(1)
        anchors = torch.multinomial(torch.where(has_edge[:, None], edges.to(torch.float64), torch.ones_like(flat)),
                                    n_edge_anchor, replacement=True, generator=g)  # [B,A]
        theta = torch.atan2(torch.gather(gy.reshape(b, -1), 1, anchors), torch.gather(gx.reshape(b, -1), 1, anchors))
        dist = torch.randint(2, 31, (b, n_edge_anchor, 4), generator=g).to(torch.float64)
        dist = dist * torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64)
        dist = torch.sort(dist, dim=-1).values  # A, B before the edge, C, D after it, in line order
        row = (anchors // w).to(torch.float64)[..., None] + dist * torch.sin(theta)[..., None]
        col = (anchors % w).to(torch.float64)[..., None] + dist * torch.cos(theta)[..., None]
        row, col = row.round().long(), col.round().long()
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        pts = row.clamp(0, h - 1) * w + col.clamp(0, w - 1)  # [B,A,4]
        pts_ok = inside & torch.gather(flat, 1, pts.reshape(b, -1)).reshape(b, -1, 4).bool()
        pts_ok = pts_ok & has_edge[:, None, None]
        edge_pairs = torch.stack([pts[..., :3], pts[..., 1:]], -1).reshape(b, -1, 2)
        edge_ok = (pts_ok[..., :3] & pts_ok[..., 1:]).reshape(b, -1)
        pairs, ok = torch.cat([edge_pairs, rand], 1), torch.cat([edge_ok, rand_ok], 1)
        return pairs, ok & (pairs[..., 0] != pairs[..., 1])

    def forward(
        self, pred: Tensor, prior: Tensor, valid: Tensor | None = None,
        generator: torch.Generator | None = None, **_: object,
    ) -> Tensor:
        """Weighted ranking loss on log depth over pairs sampled from the prior."""
        pred, prior, mask = _prepare(pred, prior, valid)
        if not bool(mask.any()):
            return _zero(pred)
        b = pred.shape[0]
        pairs, ok = self.sample(prior, mask, generator)
        pairs, ok = pairs.to(pred.device), ok.to(pred.device)
        if not bool(ok.any()):
            return _zero(pred)
        idx = pairs.reshape(b, -1)
        za, zb = torch.gather(prior.reshape(b, -1), 1, idx).reshape(b, -1, 2).unbind(-1)
        pa, pb = torch.gather(torch.log(pred.clamp_min(1e-6)).reshape(b, -1), 1, idx).reshape(b, -1, 2).unbind(-1)
        ratio = za / zb
        label = (ratio >= 1 + self.sigma).to(pred.dtype) - (ratio <= 1 / (1 + self.sigma)).to(pred.dtype)
        diff = pa - pb
        per_pair = torch.where(label == 0, diff * diff, F.softplus(-label * diff))
        return self.weight * per_pair[ok].mean()


LOSSES: dict[str, type[nn.Module]] = {
    "l1": PriorL1Loss,
    "vnl": PriorVirtualNormalLoss,
    "ranking": PriorRankingLoss,
}


class PriorLoss(nn.Module):
    """One of the SGDE prior losses chosen by name ("l1", "vnl", "ranking"), weight lambda = 0.005."""

    def __init__(self, kind: str = "l1", weight: float = DEFAULT_WEIGHT, **kwargs: object) -> None:
        super().__init__()
        if kind not in LOSSES:
            raise ValueError(f"unknown prior loss {kind!r}; choose from {sorted(LOSSES)}")
        self.kind = kind
        self.loss = LOSSES[kind](weight=weight, **kwargs)

    def forward(self, pred: Tensor, prior: Tensor, valid: Tensor | None = None, **kwargs: object) -> Tensor:
        """Weighted prior loss; extra keywords (K, rays, generator) go to the chosen loss."""
        return self.loss(pred, prior, valid, **kwargs)


__all__ = [
    "DEFAULT_WEIGHT", "LOSSES", "PriorL1Loss", "PriorLoss", "PriorRankingLoss", "PriorVirtualNormalLoss",
    "depth_rays", "pinhole_rays",
]
