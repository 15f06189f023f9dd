"""Prior-channel stem: widen the first convolution of a backbone from RGB to RGB + prior (+ validity)."""

from __future__ import annotations

import torch
from torch import nn

from .encoding import PriorEncoding


def find_first_conv(module: nn.Module, in_channels: int | None = 3) -> tuple[nn.Module, str, nn.Conv2d]:
    """Locate the first ``nn.Conv2d`` of a backbone (e.g. ``resnet.conv1``): (parent, attribute, conv).

    Modules are visited in registration order, which for torchvision backbones is input order.
    With ``in_channels`` set, the first convolution with that many input channels is returned.
    """
    for qual_name, child in module.named_modules():
        if not isinstance(child, nn.Conv2d) or not qual_name:
            continue
        if in_channels is not None and child.in_channels != in_channels:
            continue
        parent_name, _, attr = qual_name.rpartition(".")
        parent = module.get_submodule(parent_name) if parent_name else module
        return parent, attr, child
    want = f" with {in_channels} input channels" if in_channels is not None else ""
    raise ValueError(f"no nn.Conv2d{want} found in {type(module).__name__}")


def widened_conv(conv: nn.Conv2d, extra_channels: int = 1, validity: bool = False) -> nn.Conv2d:
    """A copy of ``conv`` with ``extra_channels`` prior inputs (+1 validity input) appended.

    Prior channels start at the mean of the existing (RGB) input weights, as in the SGDE paper;
    the validity channel starts at zero. The original input weights and the bias are copied
    unchanged, so with zero extra inputs the result equals the original convolution.
    """
    if not isinstance(conv, nn.Conv2d):
        raise TypeError(f"expected nn.Conv2d, got {type(conv).__name__}")
    if conv.groups != 1:
        raise ValueError("cannot widen a grouped convolution")
    if extra_channels < 0:
        raise ValueError(f"extra_channels must be >= 0, got {extra_channels}")
    n_new = extra_channels + int(validity)
    weight = conv.weight
    new = nn.Conv2d(
        conv.in_channels + n_new,
        conv.out_channels,
        kernel_size=conv.kernel_size,
        stride=conv.stride,
        padding=conv.padding,
        dilation=conv.dilation,
        groups=1,
        bias=conv.bias is not None,
        padding_mode=conv.padding_mode,
        device=weight.device,
        dtype=weight.dtype,
    )
    with torch.no_grad():
        mean = weight.mean(dim=1, keepdim=True)
        parts = [weight, mean.expand(-1, extra_channels, -1, -1)]
        if validity:
            parts.append(torch.zeros_like(mean))
        new.weight.copy_(torch.cat(parts, dim=1))
        if conv.bias is not None:
            new.bias.copy_(conv.bias)
    new.weight.requires_grad_(weight.requires_grad)
    return new


def widen_first_conv(
    module_or_conv: nn.Module, extra_channels: int = 1, validity: bool = False
) -> nn.Module:
    """Widen the first convolution of a backbone (in place) or a bare ``nn.Conv2d`` (returns a new one).

    For a backbone the module itself is returned with its first 3-channel convolution replaced,
    so ``resnet = widen_first_conv(resnet18())`` takes RGB + prior inputs.
    """
    if isinstance(module_or_conv, nn.Conv2d):
        return widened_conv(module_or_conv, extra_channels, validity)
    parent, attr, conv = find_first_conv(module_or_conv)
    setattr(parent, attr, widened_conv(conv, extra_channels, validity))
    return module_or_conv


class PriorChannelStem(nn.Module):
    """RGB + metric prior -> first-layer features: PriorEncoding followed by a widened convolution.

    ``rgb`` is expected already normalised the way the original backbone wants; the prior is
    encoded inside the graph (depth / max_depth, 0 = no prior) and never uses RGB statistics.
    """

    def __init__(self, conv: nn.Conv2d, max_depth: float = 80.0, with_validity: bool = False) -> None:
        super().__init__()
        self.encoding = PriorEncoding(max_depth=max_depth, with_validity=with_validity)
        self.conv = widened_conv(conv, extra_channels=1, validity=with_validity)

    def forward(self, rgb: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        """``rgb`` [B,3,H,W], ``prior`` [B,1,H,W] metres -> the convolution's output."""
        return self.conv(torch.cat([rgb, self.encoding(prior)], dim=1))
