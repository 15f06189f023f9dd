"""BEVDepth-style depth branch with the SGDE prior as input and as extra supervision.

``PriorDepthNet`` honours BEVDepth's ``DepthNet(in_channels, mid_channels, context_channels,
depth_channels).forward(x, mats_dict)`` contract and adds ``prior=`` (metres, [B, N, H, W] at the
augmented image size, 0 = none). It owns its losses, so a BEVDepth trainer swaps one module:

    net = PriorDepthNet(512, 512, 80, 112)
    out = net(feats, mats_dict, prior=prior)                # [B*N, 112 + 80, h, w], logits first
    probs = out[:, :112].softmax(1)
    loss = net.get_depth_loss(gt_depth, probs) + net.get_prior_loss(prior, probs)

``PriorInjector`` wraps any existing DepthNet-like module instead (BEVDepth, BEVDet, FB-OCC).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn
from torchvision.models.resnet import BasicBlock

from .camera_aware import ASPP, CAMERA_PARAMS, Mlp, SELayer, camera_params
from .depth_bins import D_BOUND, depth_bce_loss, depth_bin_labels, num_depth_bins
from .prior_features import PriorFeatureEncoder

DEPTH_LOSS_WEIGHT = 3.0  # BEVDepth's factor on the depth BCE
PRIOR_LOSS_WEIGHT = 0.005  # lambda of the SGDE paper on the prior term


class _ZeroInitDeformConv(nn.Module):
    """3x3 deformable convolution (torchvision) whose offsets start at zero; not ONNX-exportable."""

    def __init__(self, channels: int, groups: int = 4) -> None:
        super().__init__()
        from torchvision.ops import DeformConv2d

        self.offset = nn.Conv2d(channels, 2 * 9, kernel_size=3, padding=1)
        nn.init.zeros_(self.offset.weight)
        nn.init.zeros_(self.offset.bias)
        self.conv = DeformConv2d(channels, channels, kernel_size=3, padding=1, groups=groups)

    def forward(self, x: Tensor) -> Tensor:
        """[M, C, h, w] -> [M, C, h, w]."""
        return self.conv(x, self.offset(x))


class PriorDepthNet(nn.Module):
    """BEVDepth's camera-aware DepthNet plus the SGDE prior, added to the depth-branch features.

    Args:
        in_channels, mid_channels, context_channels, depth_channels: as BEVDepth's DepthNet.
        d_bound: depth bins (start, stop, step); must give ``depth_channels`` bins.
        downsample: feature stride of ``x`` relative to the image (and the prior).
        use_prior: build the prior path; without it the module is BEVDepth's DepthNet.
        prior_max_depth: normalisation of the prior (default: the last bin edge, d_bound[1]).
        deformable: BEVDepth's deformable 3x3 convolution before the bin classifier (off by
            default: it has no ONNX export).
        depth_loss_weight, prior_loss_weight: factors of ``get_depth_loss`` and ``get_prior_loss``.
    """

    def __init__(
        self,
        in_channels: int,
        mid_channels: int,
        context_channels: int,
        depth_channels: int,
        *,
        d_bound: tuple[float, float, float] = D_BOUND,
        downsample: int = 16,
        use_prior: bool = True,
        prior_max_depth: float | None = None,
        prior_hidden_channels: int = 64,
        deformable: bool = False,
        depth_loss_weight: float = DEPTH_LOSS_WEIGHT,
        prior_loss_weight: float = PRIOR_LOSS_WEIGHT,
    ) -> None:
        super().__init__()
        if num_depth_bins(d_bound) != depth_channels:
            raise ValueError(f"d_bound {tuple(d_bound)} gives {num_depth_bins(d_bound)} bins, not {depth_channels}")
        self.depth_channels = depth_channels
        self.context_channels = context_channels
        self.d_bound = tuple(float(v) for v in d_bound)
        self.downsample = int(downsample)
        self.depth_loss_weight = float(depth_loss_weight)
        self.prior_loss_weight = float(prior_loss_weight)

        self.reduce_conv = nn.Sequential(
            nn.Conv2d(in_channels, mid_channels, kernel_size=3, padding=1),
            nn.BatchNorm2d(mid_channels),
            nn.ReLU(inplace=True),
        )
        self.context_conv = nn.Conv2d(mid_channels, context_channels, kernel_size=1)
        self.bn = nn.BatchNorm1d(CAMERA_PARAMS)
        self.depth_mlp = Mlp(CAMERA_PARAMS, mid_channels, mid_channels)
        self.depth_se = SELayer(mid_channels)
        self.context_mlp = Mlp(CAMERA_PARAMS, mid_channels, mid_channels)
        self.context_se = SELayer(mid_channels)
        self.prior_encoder = (
            PriorFeatureEncoder(
                mid_channels,
                downsample=self.downsample,
                max_depth=prior_max_depth if prior_max_depth is not None else self.d_bound[1],
                hidden_channels=prior_hidden_channels,
            )
            if use_prior
            else None
        )
        layers: list[nn.Module] = [BasicBlock(mid_channels, mid_channels) for _ in range(3)]
        layers.append(ASPP(mid_channels, mid_channels))
        if deformable:
            layers.append(_ZeroInitDeformConv(mid_channels))
        layers.append(nn.Conv2d(mid_channels, depth_channels, kernel_size=1))
        self.depth_conv = nn.Sequential(*layers)

    @property
    def use_prior(self) -> bool:
        """Whether the module has a prior path."""
        return self.prior_encoder is not None

    def forward(self, x: Tensor, mats_dict: dict[str, Tensor], prior: Tensor | None = None) -> Tensor:
        """Features [B*N, C, h, w] + camera matrices (+ prior [B, N, h*s, w*s] m) -> [B*N, D + C_ctx, h, w]."""
        mlp_input = self.bn(camera_params(mats_dict))
        x = self.reduce_conv(x)
        context = self.context_conv(self.context_se(x, self.context_mlp(mlp_input)[..., None, None]))
        depth = self.depth_se(x, self.depth_mlp(mlp_input)[..., None, None])
        if prior is not None:
            if self.prior_encoder is None:
                raise ValueError("this PriorDepthNet was built with use_prior=False")
            depth = depth + self.prior_encoder(prior)
        depth = self.depth_conv(depth)
        return torch.cat([depth, context], dim=1)

    def get_downsampled_gt_depth(self, gt_depths: Tensor) -> Tensor:
        """Ground truth [B, N, H, W] metres -> one-hot bin labels [B*N*h*w, D] (BEVDepth's semantics)."""
        return depth_bin_labels(gt_depths, self.downsample, self.d_bound)

    def get_depth_loss(self, gt_depths: Tensor, depth_preds: Tensor, from_logits: bool = False) -> Tensor:
        """BEVDepth's depth loss: weight * BCE(bin probabilities, one-hot gt bins) over foreground cells.

        ``depth_preds`` [B*N, D, h, w] are softmax probabilities as in BEVDepth (or logits with
        ``from_logits``); cells without ground truth get no loss.
        """
        probs = depth_preds.softmax(dim=1) if from_logits else depth_preds
        return self.depth_loss_weight * depth_bce_loss(self.get_downsampled_gt_depth(gt_depths), probs)

    def get_prior_loss(self, prior: Tensor, depth_preds: Tensor, from_logits: bool = False) -> Tensor:
        """The same BCE with the prior [B, N, H, W] as target, times lambda (``prior_loss_weight``)."""
        probs = depth_preds.softmax(dim=1) if from_logits else depth_preds
        return self.prior_loss_weight * depth_bce_loss(self.get_downsampled_gt_depth(prior), probs)


class PriorInjector(nn.Module):
    """Wrap a DepthNet-like module: add the encoded prior to its input features, forward the rest.

    ``forward(x, *args, prior=None, **kwargs)`` calls ``depth_net(x + enc(prior), *args, **kwargs)``.
    The encoder's last layer starts at zero, so before training the wrapped net computes exactly what
    it computed alone. Attributes not found on the injector are looked up on the wrapped net.
    """

    def __init__(
        self,
        depth_net: nn.Module,
        in_channels: int,
        downsample: int = 16,
        max_depth: float = 58.0,
        hidden_channels: int = 64,
    ) -> None:
        super().__init__()
        self.depth_net = depth_net
        self.prior_encoder = PriorFeatureEncoder(
            in_channels, downsample=downsample, max_depth=max_depth,
            hidden_channels=hidden_channels, zero_init=True,
        )

    def forward(self, x: Tensor, *args: Any, prior: Tensor | None = None, **kwargs: Any) -> Any:
        """The wrapped net's forward, with ``x`` shifted by the encoded prior when one is given."""
        if prior is not None:
            x = x + self.prior_encoder(prior)
        return self.depth_net(x, *args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        try:
            return super().__getattr__(name)
        except AttributeError:
            depth_net = super().__getattr__("depth_net")
            return getattr(depth_net, name)
