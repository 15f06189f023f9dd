"""Self-supervised view synthesis (monodepth2, Godard et al. 2019; FSM, Guizilini et al. 2022).

A source image is inverse-warped into the target camera with the predicted target depth and a known
relative pose: every target pixel is lifted with the target camera's own unproject (`depth_rays`),
moved into the source camera and projected with the source camera's own project, so pinhole and
fisheye (Kannala-Brandt, ocam) rigs go through one path. The photometric error is
alpha * (1 - SSIM) / 2 + (1 - alpha) * L1 with alpha = 0.85; over several sources the per-pixel
minimum is kept; auto-masking gives pixels whose error against an unwarped temporal source is lower
(static scenes, objects moving with the ego) that identity error instead (monodepth2: they stay in the
mean as constants, so masking a pixel never lowers the loss); an edge-aware smoothness term regularises the
mean-normalised inverse depth; every output scale is upsampled to the input size and scored there.

Sources are temporal (the same camera at t-1 / t+1, poses from the ego trajectory) and spatial (the
adjacent cameras of the same capture, which give metric scale); see `SourceView`. Static masks (ego
body; False = ignore) are honoured in the target and in every source.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..cameras import CameraModel

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
UNSEEN = 1e4  # photometric error of a source pixel that cannot be used (never the minimum)


@dataclass
class SourceView:
    """Source images of a batch of target views: pixels, camera model(s), poses and kind.

    ``image`` [B,3,H,W] in [0, 1]; ``model`` the source camera, or one per batch element (a batch may
    hold the views of several cameras); ``target_to_source`` [B,4,4] maps target-camera points to
    source-camera points; ``temporal`` marks the same camera at another time (these take part in
    auto-masking); ``mask`` [B|1,1,H,W] bool, False where the source pixel must not be used (ego body,
    or an element that has no such source).
    """

    image: Tensor
    model: CameraModel | Sequence[CameraModel]
    target_to_source: Tensor
    temporal: bool
    mask: Tensor | None = None


def _project(model: CameraModel | Sequence[CameraModel], points: Tensor) -> tuple[Tensor, Tensor]:
    """Project [B,P,3] points with one model or one model per batch element: (grid [B,P,2] in [-1, 1], ok [B,P])."""
    b = points.shape[0]
    models = [model] * b if isinstance(model, CameraModel) else list(model)
    if len(models) != b:
        raise ValueError(f"{len(models)} camera models for a batch of {b}")
    groups: dict[int, list[int]] = {}
    for i, m in enumerate(models):  # one projection per distinct camera
        groups.setdefault(id(m), []).append(i)
    grid = points.new_zeros(b, points.shape[1], 2)
    ok = torch.zeros(b, points.shape[1], dtype=torch.bool, device=points.device)
    for idx in groups.values():
        m, sel = models[idx[0]], torch.tensor(idx, device=points.device)
        uv, valid = m.project_torch(points[sel])
        grid = grid.index_copy(0, sel, torch.stack([(uv[..., 0] + 0.5) * (2.0 / m.width) - 1.0,
                                                    (uv[..., 1] + 0.5) * (2.0 / m.height) - 1.0], dim=-1))
        ok = ok.index_copy(0, sel, valid)
    return grid, ok


def inverse_warp(image: Tensor, depth: Tensor, rays: Tensor, model: CameraModel | Sequence[CameraModel],
                 target_to_source: Tensor) -> tuple[Tensor, Tensor]:
    """Sample a source ``image`` [B,C,Hs,Ws] at the target pixels' projections: (warped [B,C,H,W], seen [B,1,H,W]).

    ``depth`` [B,1,H,W] is the target depth in the target camera's convention, ``rays`` [1|B,3,H,W] the
    target's vectors with point = rays * depth (`sgde_plugin.nn.depth_rays`; zero outside its field of
    view), ``model`` the source camera (or one per batch element), ``target_to_source`` [B,4,4].
    ``seen`` is False where the point falls outside the source image or field of view, behind it, or
    the target pixel has no ray. Differentiable in depth.
    """
    b, _, h, w = depth.shape
    pts = (rays.to(depth.dtype) * depth).reshape(b, 3, -1)  # [B,3,HW]
    T = target_to_source.to(depth.dtype)
    moved = (T[:, :3, :3] @ pts + T[:, :3, 3:]).transpose(1, 2)  # [B,HW,3]
    grid, ok = _project(model, moved)
    ok = ok & (rays.abs().sum(1).reshape(-1 if rays.shape[0] == b else 1, h * w) > 0)
    grid = torch.where(ok[..., None], grid, torch.full_like(grid, -2.0)).reshape(b, h, w, 2)
    warped = F.grid_sample(image.to(depth.dtype), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return warped, ok.reshape(b, 1, h, w)


def _box3(x: Tensor) -> Tensor:
    """Mean over 3x3 windows of an input padded by one pixel (as avg_pool2d(x, 3, 1); a depthwise
    convolution is several times faster on the CPU)."""
    c = x.shape[1]
    return F.conv2d(x, torch.full((c, 1, 3, 3), 1.0 / 9.0, dtype=x.dtype, device=x.device), groups=c)


def ssim_distance(x: Tensor, y: Tensor) -> Tensor:
    """(1 - SSIM) / 2 per pixel over 3x3 windows (reflection padding, monodepth2's form), in [0, 1]."""
    c = x.shape[1]
    stats = _box3(F.pad(torch.cat([x, y, x * x, y * y, x * y], 1), (1, 1, 1, 1), mode="reflect"))
    mu_x, mu_y, xx, yy, xy = stats.split(c, 1)
    sigma_x, sigma_y, sigma_xy = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sigma_xy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sigma_x + sigma_y + SSIM_C2)
    return ((1 - num / den) / 2).clamp(0, 1)


def photometric_error(pred: Tensor, target: Tensor, alpha: float = 0.85) -> Tensor:
    """alpha * (1 - SSIM) / 2 + (1 - alpha) * |pred - target|, averaged over channels: [B,1,H,W]."""
    l1 = (pred - target).abs().mean(1, keepdim=True)
    return alpha * ssim_distance(pred, target).mean(1, keepdim=True) + (1 - alpha) * l1


def edge_aware_smoothness(disp: Tensor, image: Tensor) -> Tensor:
    """Mean of |d disp*| exp(-|d I|) along x and y, disp* = disp / mean(disp) (monodepth2)."""
    d = disp / (disp.mean((2, 3), keepdim=True) + 1e-7)
    dx, dy = (d[..., :, 1:] - d[..., :, :-1]).abs(), (d[..., 1:, :] - d[..., :-1, :]).abs()
    ix = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(1, keepdim=True)
    iy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()


def min_reprojection(errors: Tensor, identity: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Per-pixel minimum over sources and the auto-mask: (error [B,1,H,W], use [B,1,H,W] bool).

    ``errors`` [B,S,H,W] holds each source's warped error (UNSEEN where it cannot be used); ``identity``
    [B,T,H,W] the errors of unwarped temporal sources. A pixel is used when some source sees it and,
    with ``identity``, when its best warped error is below every identity error (else the pixel does
    not move against the camera and teaches nothing).
    """
    best, _ = errors.min(1, keepdim=True)
    use = best < UNSEEN
    if identity is not None and identity.shape[1]:
        use = use & (best < identity.min(1, keepdim=True)[0])
    return best, use


def pixel_loss(errors: Tensor, identity: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """monodepth2's per-pixel loss: (loss [B,1,H,W], counted [B,1,H,W] bool).

    With ``identity`` a pixel's loss is the minimum over the warped and the unwarped (identity) errors:
    an auto-masked pixel, or one no source sees, keeps its identity error (a constant without gradient)
    and stays in the mean, so no depth is rewarded for dropping its pixel out of the loss (out of view,
    or onto the identity warp that depth at infinity gives). Without ``identity`` only the pixels some
    source sees are counted.
    """
    best, use = min_reprojection(errors, identity)
    if identity is None or not identity.shape[1]:
        return best, use
    return torch.where(use, best, identity.min(1, keepdim=True)[0]), torch.ones_like(use)


@dataclass(frozen=True)
class PhotometricConfig:
    """Settings of `PhotometricLoss` (monodepth2 defaults)."""

    alpha: float = 0.85
    smoothness: float = 1e-3
    automask: bool = True
    temporal: bool = True
    spatial: bool = True


class PhotometricLoss(nn.Module):
    """Self-supervised loss of a batch of target views: min-reprojection photometric error plus smoothness.

    ``forward(depths, target, rays, sources, mask)``: ``depths`` the net's multi-scale depths
    [B,1,H/2^s,W/2^s] (metres, each target camera's convention), ``target`` [B,3,H,W], ``rays``
    [1|B,3,H,W] of the targets (`depth_rays`), ``sources`` a list of `SourceView` (those whose kind is
    switched off in the config are skipped), ``mask`` [B|1,1,H,W] the targets' static masks (False =
    ignore). The batch may mix cameras (one model per element in the sources and one ray map each).
    """

    def __init__(self, config: PhotometricConfig = PhotometricConfig()) -> None:
        super().__init__()
        self.config = config

    def sources_used(self, sources: Sequence[SourceView]) -> list[SourceView]:
        """The sources whose kind (temporal / spatial) is switched on."""
        return [s for s in sources if (self.config.temporal if s.temporal else self.config.spatial)]

    def reprojection_error(self, depth: Tensor, target: Tensor, rays: Tensor, sources: Sequence[SourceView],
                           identity: Tensor | None, mask: Tensor | None) -> Tensor:
        """Masked mean of the min-reprojection error per group of ``target.shape[0]`` depth maps.

        ``depth`` [G*B,1,H,W] stacks G full-resolution depth maps (one group per output scale) of the B
        targets; returns [G].
        """
        b = target.shape[0]
        g = depth.shape[0] // b
        target = target.repeat(g, 1, 1, 1)
        rays = rays if rays.shape[0] == 1 else rays.repeat(g, 1, 1, 1)
        errors = []
        for src in sources:
            pose = src.target_to_source.repeat(g, 1, 1)
            model = src.model if isinstance(src.model, CameraModel) else list(src.model) * g
            warped, seen = inverse_warp(src.image.repeat(g, 1, 1, 1), depth, rays, model, pose)
            if src.mask is not None:
                src_mask = src.mask.to(depth.dtype).expand(b, -1, -1, -1).repeat(g, 1, 1, 1)
                seen = seen & (inverse_warp(src_mask, depth.detach(), rays, model, pose)[0] > 0.999)
            err = photometric_error(warped, target, self.config.alpha)
            errors.append(torch.where(seen, err, torch.full_like(err, UNSEEN)))
        loss, counted = pixel_loss(torch.cat(errors, 1), None if identity is None else identity.repeat(g, 1, 1, 1))
        counted = counted & (rays.abs().sum(1, keepdim=True) > 0)  # no ray: outside the target's field of view
        if mask is not None:
            counted = counted & mask.to(torch.bool).expand(b, -1, -1, -1).repeat(g, 1, 1, 1)
        loss, counted = loss.reshape(g, -1), counted.reshape(g, -1)
        return torch.where(counted, loss, torch.zeros_like(loss)).sum(1) / counted.sum(1).clamp(min=1)

    def forward(self, depths: Sequence[Tensor], target: Tensor, rays: Tensor, sources: Sequence[SourceView],
                mask: Tensor | None = None) -> Tensor:
        """Mean over scales of photometric error + smoothness (see class docstring)."""
        used = self.sources_used(sources)
        if not used:
            raise ValueError("no source view: switch on temporal or spatial sources")
        h, w = target.shape[-2:]
        identity = None
        temporal = [s for s in used if s.temporal]
        if self.config.automask and temporal:
            # an exact tie (the pixel looks the same unwarped) counts as not moving
            identity = torch.cat([photometric_error(s.image.to(target.dtype), target, self.config.alpha)
                                  for s in temporal], 1)
        full = [d if d.shape[-2:] == (h, w) else F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False)
                for d in depths]
        total = self.reprojection_error(torch.cat(full, 0), target, rays, used, identity, mask).sum()
        if self.config.smoothness:
            for s, depth in enumerate(depths):
                small = target if depth.shape[-2:] == (h, w) else F.interpolate(target, size=depth.shape[-2:],
                                                                                mode="area")
                total = total + self.config.smoothness / 2**s * edge_aware_smoothness(1.0 / depth, small)
        return total / len(depths)
