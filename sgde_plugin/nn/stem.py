"""Prior-channel stem: widen the first convolution of a backbone from RGB to RGB + prior (+ validity).

Three forms:

- ``"full"`` (the SGDE paper): one convolution over RGB + prior (+ validity); the prior's kernel starts
  at the mean of the RGB kernels. On ResNet's 7x7/2 conv1 each extra input adds a third of conv1,
  about 2.2 % of ResNet-18's FLOPs.
- ``"factored"``: the same map written as ``conv_rgb(rgb + prior / 3) + U(B(prior, validity))``. The
  fixed fold (the prior added to each RGB input with gain 1/3) is the mean-of-RGB prior kernel, which
  keeps following the RGB kernels as they train; ``B`` (``rank`` 7x7 filters) and ``U`` (1x1, zero at
  start) are a learned low-rank kernel of the prior's own. At ``rank=4`` it adds under 0.4 % of
  ResNet-18's FLOPs; the prior's kernel is restricted to mean(W_rgb) plus a rank-4 term. The fold is
  fixed on purpose: a learned gain would make conv1 compute its input gradient (a full conv1 more
  in every backward pass).
- ``"lowrank"``: ``conv_rgb(rgb) + U(B(prior, validity))`` with ``U B`` starting at the best rank-``rank``
  approximation (SVD) of the mean-of-RGB kernel: the prior's kernel is its own (no tie to the RGB
  kernels) but of rank ``rank``, and equals the paper's start only up to that approximation. Same cost
  as ``"factored"``.

All three compute exactly the original convolution when the prior (and validity) inputs are zero.
"""

from __future__ import annotations

import copy

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


STEM_MODES = ("full", "factored", "lowrank")


def _check_conv(conv: nn.Module, extra_channels: int) -> None:
    if not isinstance(conv, nn.Conv2d):
        raise TypeError(f"expected nn.Conv2d, got {type(conv).__name__}")
    if conv.groups != 1:
        raise ValueError("cannot widen a grouped convolution")
    if extra_channels < 0:
        raise ValueError(f"extra_channels must be >= 0, got {extra_channels}")


class FactoredPriorConv(nn.Module):
    """A first convolution over RGB + prior (+ validity) at almost the cost of the RGB one.

    ``forward(x)`` takes the same [B, 3 + extra (+1), H, W] input as the widened ``nn.Conv2d``. With
    ``tied`` (mode ``"factored"``) it returns the same output as the paper's widened convolution at
    initialisation; without (mode ``"lowrank"``) the same up to a rank-``rank`` approximation.
    """

    def __init__(self, conv: nn.Conv2d, extra_channels: int = 1, validity: bool = False, rank: int = 4,
                 tied: bool = True) -> None:
        super().__init__()
        _check_conv(conv, extra_channels)
        if rank < 1:
            raise ValueError(f"rank must be >= 1, got {rank}")
        self.rgb_channels = conv.in_channels
        self.extra_channels = extra_channels
        n_new = extra_channels + int(validity)
        self.in_channels = conv.in_channels + n_new
        self.out_channels = conv.out_channels
        self.conv = copy.deepcopy(conv)
        factory = {"device": conv.weight.device, "dtype": conv.weight.dtype}
        # tied: each prior enters every RGB input with gain 1/3,
        # conv_rgb(rgb + p/3) = conv_rgb(rgb) + conv(p, mean W_rgb)
        self.fold_gain = 1.0 / conv.in_channels if tied else 0.0
        self.basis = nn.Conv2d(n_new, rank, conv.kernel_size, conv.stride, conv.padding, conv.dilation,
                               bias=False, padding_mode=conv.padding_mode, **factory)
        self.mix = nn.Conv2d(rank, conv.out_channels, 1, bias=False, **factory)
        if tied:
            nn.init.zeros_(self.mix.weight)
        else:
            with torch.no_grad():
                mean = conv.weight.mean(dim=1).reshape(conv.out_channels, -1).double()
                u, sv, vh = torch.linalg.svd(mean, full_matrices=False)
                k = min(rank, sv.numel())
                root = sv[:k].sqrt()
                basis = torch.zeros_like(self.basis.weight, dtype=torch.float64)
                basis[:k, :extra_channels] = (root[:, None] * vh[:k]).reshape(k, 1, *conv.kernel_size)
                mix = torch.zeros_like(self.mix.weight, dtype=torch.float64)
                mix[:, :k, 0, 0] = u[:, :k] * root
                self.basis.weight.copy_(basis)
                self.mix.weight.copy_(mix)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[B, C_rgb + extra, H, W] -> the first layer's output."""
        rgb, extra = x[:, : self.rgb_channels], x[:, self.rgb_channels:]
        if self.fold_gain:
            priors = extra[:, : self.extra_channels]
            if self.extra_channels > 1:
                priors = priors.sum(dim=1, keepdim=True)
            # a broadcast add, not a 1x1 convolution: the latter costs as much as conv1's forward on CPU
            rgb = rgb + priors * self.fold_gain
        out = self.conv(rgb)
        return out.add_(self.mix(self.basis(extra)))  # in place: conv's backward does not need its output

    def full_weight(self) -> torch.Tensor:
        """The equivalent single-convolution kernel [out, C_rgb + extra, kh, kw] (for inspection)."""
        w = self.conv.weight
        n_new = self.in_channels - self.rgb_channels
        folded = torch.zeros(w.shape[0], n_new, *w.shape[2:], dtype=w.dtype, device=w.device)
        if self.fold_gain:
            folded[:, : self.extra_channels] = w.mean(dim=1, keepdim=True)
        low_rank = torch.einsum("or,rnij->onij", self.mix.weight[:, :, 0, 0], self.basis.weight)
        return torch.cat([w, folded + low_rank], dim=1)


def widened_conv(conv: nn.Conv2d, extra_channels: int = 1, validity: bool = False, mode: str = "full",
                 rank: int = 4) -> nn.Module:
    """A copy of ``conv`` with ``extra_channels`` prior inputs (+1 validity input) appended.

    Prior channels start at the mean of the existing (RGB) input weights, as in the SGDE paper;
    the validity channel starts at zero. The original input weights and the bias are copied
    unchanged, so with zero extra inputs the result equals the original convolution.
    ``mode="factored"`` / ``"lowrank"`` return the cheaper ``FactoredPriorConv`` (module docstring).
    """
    if mode not in STEM_MODES:
        raise ValueError(f"stem mode must be one of {STEM_MODES}, got {mode!r}")
    if mode in ("factored", "lowrank"):
        return FactoredPriorConv(conv, extra_channels, validity, rank, tied=mode == "factored")
    _check_conv(conv, extra_channels)
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
    module_or_conv: nn.Module, extra_channels: int = 1, validity: bool = False, mode: str = "full", rank: int = 4
) -> nn.Module:
    """Widen the first convolution of a backbone (in place) or a bare ``nn.Conv2d`` (returns a new one).

    For a backbone the module itself is returned with its first 3-channel convolution replaced,
    so ``resnet = widen_first_conv(resnet18())`` takes RGB + prior inputs.
    """
    if isinstance(module_or_conv, nn.Conv2d):
        return widened_conv(module_or_conv, extra_channels, validity, mode, rank)
    parent, attr, conv = find_first_conv(module_or_conv)
    setattr(parent, attr, widened_conv(conv, extra_channels, validity, mode, rank))
    return module_or_conv


class PriorChannelStem(nn.Module):
    """RGB + metric prior -> first-layer features: PriorEncoding followed by a widened convolution.

    ``rgb`` is expected already normalised the way the original backbone wants; the prior is
    encoded inside the graph (depth / max_depth, 0 = no prior) and never uses RGB statistics.
    """

    def __init__(self, conv: nn.Conv2d, max_depth: float = 80.0, with_validity: bool = False,
                 mode: str = "full", rank: int = 4) -> None:
        super().__init__()
        self.encoding = PriorEncoding(max_depth=max_depth, with_validity=with_validity)
        self.conv = widened_conv(conv, extra_channels=1, validity=with_validity, mode=mode, rank=rank)

    def forward(self, rgb: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        """``rgb`` [B,3,H,W], ``prior`` [B,1,H,W] metres -> the convolution's output."""
        return self.conv(torch.cat([rgb, self.encoding(prior)], dim=1))
