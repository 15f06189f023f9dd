"""The SGDE prior brought to a feature map: zero-aware min pooling, normalisation and a small encoder."""

from __future__ import annotations

from torch import Tensor, nn

from sgde_plugin.nn import PriorEncoding
from sgde_plugin.nn.inputs import require_tensor
from sgde_plugin.splat import min_pool_nonzero_torch


def min_pool_nonzero(depth: Tensor, stride: int) -> Tensor:
    """Minimum non-zero value per stride x stride patch of ``depth`` [..., H, W]; empty patches stay 0.

    This is BEVDepth's ground-truth downsampling (nearest surface per patch), except that a patch
    without any value is 0 ("none") instead of a fill value. H and W must be multiples of stride.
    (`sgde_plugin.splat.min_pool_nonzero_torch`; exports to ONNX, works in half precision.)
    """
    if stride == 1:
        return depth
    h, w = depth.shape[-2:]
    if h % stride or w % stride:
        raise ValueError(f"depth size {h}x{w} is not a multiple of the stride {stride}")
    return min_pool_nonzero_torch(depth, stride)


def check_prior_fits(prior: object, features: Tensor, stride: int) -> None:
    """Raise one ValueError naming both shapes unless ``prior`` ([B, N, H, W] or [B*N, 1, H, W] metres) lies on
    ``features`` ([B*N, C, h, w] or [B, N, C, h, w]) at ``stride``: B*N images, H = h * stride, W = w * stride."""
    prior = require_tensor("prior", prior)
    p, f = list(prior.shape), list(features.shape)
    if prior.dim() != 4:
        raise ValueError(f"prior must be [B, N, H, W] or [B*N, 1, H, W], got {p}")
    images = p[0] if p[1] == 1 else p[0] * p[1]
    feature_images = f[0] * f[1] if features.dim() == 5 else f[0]
    if images != feature_images or p[-2:] != [f[-2] * stride, f[-1] * stride]:
        raise ValueError(f"prior {p} does not fit the features {f}: expected {feature_images} images of "
                         f"{f[-2] * stride}x{f[-1] * stride} (the features' size x the stride {stride})")


class PriorFeatureEncoder(nn.Module):
    """Metric prior at image size -> features at the feature stride, to be added to a feature map.

    Steps: min-pool ignoring zeros to the feature stride, ``PriorEncoding`` (depth / max_depth in
    [0, 1], 0 = none, plus a validity channel), two 1x1 convolutions, then times the cell's validity:
    a cell without prior gets exactly 0, so an all-zero prior adds exactly nothing (the same as no
    prior, in torch and in an exported graph). With ``zero_init`` the last convolution starts at
    zero, so adding the output changes nothing until training moves it. Pooling and normalisation
    run in the prior's dtype, the convolutions in the weights' dtype (a ``.half()`` net takes a
    float32 prior).
    """

    def __init__(
        self,
        out_channels: int,
        downsample: int = 16,
        max_depth: float = 58.0,
        hidden_channels: int = 64,
        with_validity: bool = True,
        zero_init: bool = False,
    ) -> None:
        super().__init__()
        self.downsample = int(downsample)
        self.encoding = PriorEncoding(max_depth=max_depth, with_validity=with_validity)
        self.net = nn.Sequential(
            nn.Conv2d(self.encoding.out_channels, hidden_channels, kernel_size=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden_channels, out_channels, kernel_size=1),
        )
        if zero_init:
            nn.init.zeros_(self.net[-1].weight)
            nn.init.zeros_(self.net[-1].bias)

    def pooled(self, prior: Tensor) -> Tensor:
        """Prior [B, N, H, W] or [B*N, 1, H, W] metres -> [B*N, 1, H/s, W/s] metres (0 = none)."""
        if prior.dim() == 4 and prior.shape[1] != 1:
            prior = prior.flatten(0, 1).unsqueeze(1)
        elif prior.dim() != 4:
            raise ValueError(f"prior must be [B, N, H, W] or [B*N, 1, H, W], got {list(prior.shape)}")
        return min_pool_nonzero(prior, self.downsample)

    def forward(self, prior: Tensor) -> Tensor:
        """Prior [B, N, H, W] (or [B*N, 1, H, W]) in metres -> features [B*N, out, H/s, W/s], 0 where none."""
        pooled = self.pooled(prior)
        feats = self.net(self.encoding(pooled).to(self.net[0].weight.dtype))
        return feats * (pooled > 0).to(feats.dtype)
