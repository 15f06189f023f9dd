"""BEVDepth-style depth branch with the SGDE prior as input and as extra supervision.

``PriorDepthNet`` is BEVDepth's ``DepthNet(in_channels, mid_channels, context_channels,
depth_channels).forward(x, mats_dict)`` (same state-dict keys: BEVDepth checkpoints load) plus a prior
path. The prior (metres, at the augmented image size, 0 = none) arrives either as ``prior=`` or
inside ``mats_dict[PRIOR_KEY]`` ([B, num_sweeps, N, H, W]), so it rides through BEVDepth's unchanged
``forward`` -> ``_forward_single_sweep`` -> ``_forward_depth_net(feat, mats_dict)``. It owns its losses:

    net = PriorDepthNet(512, 512, 80, 112, deformable=True)
    out = net(feats, mats_dict)                             # [B*N, 112 + 80, h, w], logits first
    probs = out[:, :112].softmax(1)
    loss = net.get_depth_loss(gt_depth, probs) + net.get_prior_loss(prior, probs)

``inject_prior`` gives any existing DepthNet-like module (BEVDet, FB-OCC) a prior path in place.
"""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import AbstractContextManager
from typing import Any

import torch
from torch import Tensor, nn
from torchvision.models.resnet import BasicBlock

from sgde_plugin.errors import InputError

from .camera_aware import ASPP, CAMERA_PARAMS, Mlp, SELayer, camera_params
from .depth_bins import D_BOUND, depth_bce_loss, depth_bin_labels, num_depth_bins
from .prior_features import PriorFeatureEncoder, check_prior_fits
from .prior_path import PriorFeed, keep_missing_prior_path

DEPTH_LOSS_WEIGHT = 3.0  # BEVDepth's factor on the depth BCE
PRIOR_LOSS_WEIGHT = 0.005  # lambda of the SGDE paper on the prior term
INJECTED_NAME = "sgde_prior"  # the submodule inject_prior adds to a depth net
_DCN_KEY = "depth_conv.4.conv_offset."  # present only in a DepthNet with BEVDepth's deformable convolution


class DeformConv3x3(nn.Module):
    """3x3 deformable convolution as mmcv's ``DCN`` (DeformConv2dPack) is built by BEVDepth.

    Keys ``weight`` [C, C/groups, 3, 3] (no bias, Kaiming-uniform for ReLU) and ``conv_offset``
    (a 3x3 convolution with bias to 2 x 9 offsets per pixel, one offset group, starting at zero).
    Offsets are ordered (dy, dx) per kernel point, as in mmcv. Computed by torchvision's
    ``deform_conv2d``; exported to ONNX as the opset-19 ``DeformConv`` (see ``sgde_plugin.export``).
    """

    def __init__(self, channels: int, groups: int = 4) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(channels, channels // groups, 3, 3))
        nn.init.kaiming_uniform_(self.weight, nonlinearity="relu")
        self.conv_offset = nn.Conv2d(channels, 2 * 9, kernel_size=3, padding=1, bias=True)
        nn.init.zeros_(self.conv_offset.weight)
        nn.init.zeros_(self.conv_offset.bias)

    def forward(self, x: Tensor) -> Tensor:
        """[M, C, h, w] -> [M, C, h, w]."""
        from torchvision.ops import deform_conv2d

        return deform_conv2d(x, self.conv_offset(x), self.weight, padding=(1, 1))


def _zero_last_layer(encoder: PriorFeatureEncoder) -> None:
    nn.init.zeros_(encoder.net[-1].weight)
    nn.init.zeros_(encoder.net[-1].bias)


def _depth_net_part(state_dict: Mapping[str, Tensor], probe: str = "reduce_conv.0.weight") -> Mapping[str, Tensor]:
    """The depth net's entries of a whole-model state dict (``...depth_net.`` prefix dropped); else unchanged."""
    if probe in state_dict:
        return state_dict
    prefixes = [k[: -len(probe)] for k in state_dict if k.endswith("depth_net." + probe)]
    if len(prefixes) != 1:
        return state_dict
    p = prefixes[0]
    return {k[len(p):]: v for k, v in state_dict.items() if k.startswith(p)}


def _few(keys: list[str]) -> str:
    return ", ".join(keys[:3]) + (f" (+{len(keys) - 3} more)" if len(keys) > 3 else "")


def _key_differences(module: nn.Module, state_dict: Mapping[str, Tensor], optional: str | None) -> list[str]:
    """Missing, unexpected and wrongly shaped keys of ``state_dict`` against ``module``, as phrases."""
    expected = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    given = set(state_dict)
    if optional and not any(k.startswith(optional) for k in given):
        given |= {k for k in expected if k.startswith(optional)}
    # like torch, a BatchNorm's num_batches_tracked may be absent (older checkpoints)
    missing = sorted(k for k in set(expected) - given if not k.endswith(".num_batches_tracked"))
    unexpected = sorted(given - set(expected))
    wrong = sorted(k for k in set(state_dict) & set(expected) if tuple(state_dict[k].shape) != expected[k])
    groups = (("missing {n} keys", missing), ("unexpected {n} keys", unexpected), ("wrong shape", wrong))
    return [f"{label.format(n=len(keys))}: {_few(keys)}" for label, keys in groups if keys]


def state_dict_mismatch(module: nn.Module, state_dict: Mapping[str, Tensor], optional: str | None = None) -> str | None:
    """One line saying why ``state_dict`` does not fit ``module`` exactly (None when it does).

    Keys under ``optional`` (the prior path) may be absent as a whole; like torch, a BatchNorm's
    ``num_batches_tracked`` may be absent.
    """
    parts = _key_differences(module, state_dict, optional)
    if not parts:
        return None
    hint = ""
    has_dcn = any(k.startswith(_DCN_KEY) for k in state_dict)
    if has_dcn != any(k.startswith(_DCN_KEY) for k in module.state_dict()):
        hint = ("; the checkpoint has BEVDepth's deformable convolution: build with deformable=True" if has_dcn
                else "; the checkpoint has no deformable convolution: build with deformable=False")
    return f"does not fit {type(module).__name__}: " + "; ".join(parts) + hint


class PriorDepthNet(nn.Module):
    """BEVDepth's camera-aware DepthNet plus the SGDE prior, added to the depth-branch features only.

    The prior shifts the depth branch (after the camera-aware gate, before the residual blocks) and
    never the context: the context is what gets splatted into BEV, and keeping it prior-free keeps the
    BEV features' content from depending on where the overlaps happen to be. A cell without prior
    gets exactly nothing added, so an all-zero prior is exactly no prior.

    Args:
        in_channels, mid_channels, context_channels, depth_channels: as BEVDepth's DepthNet.
        d_bound: depth bins (start, stop, step); must give ``depth_channels`` bins.
        downsample: feature stride of ``x`` relative to the image (and the prior).
        use_prior: build the prior path; without it the module is BEVDepth's DepthNet.
        prior_max_depth: normalisation of the prior (default: the last bin edge, d_bound[1]).
        deformable: BEVDepth's deformable 3x3 convolution before the bin classifier (BEVDepth always
            has it; ONNX export then needs opset 19).
        depth_loss_weight, prior_loss_weight: factors of ``get_depth_loss`` and ``get_prior_loss``.

    ``load_state_dict`` takes a BEVDepth DepthNet state dict (or a whole-model one: the
    ``...depth_net.`` entries are used), strict by default, and refuses a partial load with one line;
    a checkpoint without the prior path loads with that path's last layer at zero, so the net then
    computes exactly what the checkpoint computed.
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
        self.deformable = bool(deformable)
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
            layers.append(DeformConv3x3(mid_channels))
        layers.append(nn.Conv2d(mid_channels, depth_channels, kernel_size=1))
        self.depth_conv = nn.Sequential(*layers)
        self.prior_feed = PriorFeed()
        keep_missing_prior_path(self, "prior_encoder", reset=_zero_last_layer)

    @property
    def use_prior(self) -> bool:
        """Whether the module has a prior path."""
        return self.prior_encoder is not None

    def forward(self, x: Tensor, mats_dict: dict[str, Tensor], prior: Tensor | None = None) -> Tensor:
        """Features [B*N, C, h, w] + camera matrices (+ prior [B, N, h*s, w*s] m) -> [B*N, D + C_ctx, h, w].

        Without ``prior`` the prior of this sweep is taken from ``mats_dict[PRIOR_KEY]`` when present.
        """
        if prior is None:
            prior = self.prior_feed.next_prior(mats_dict)
        if prior is not None and self.prior_encoder is not None:
            check_prior_fits(prior, x, self.prior_encoder.downsample)
        mlp_input = self.bn(camera_params(mats_dict))
        x = self.reduce_conv(x)
        context = self.context_conv(self.context_se(x, self.context_mlp(mlp_input)[..., None, None]))
        depth = self.depth_se(x, self.depth_mlp(mlp_input)[..., None, None])
        if prior is not None:
            if self.prior_encoder is None:
                raise ValueError("this PriorDepthNet was built with use_prior=False but was given a prior")
            depth = depth + self.prior_encoder(prior).to(depth.dtype)
        depth = self.depth_conv(depth)
        return torch.cat([depth, context], dim=1)

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any:
        """Load BEVDepth DepthNet keys (or a whole model's ``...depth_net.*``); strict refusals are one line."""
        state_dict = _depth_net_part(state_dict)
        if strict:
            problem = state_dict_mismatch(self, state_dict, optional="prior_encoder.")
            if problem:
                raise InputError(None, "state_dict", problem)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def get_downsampled_gt_depth(self, gt_depths: Tensor) -> Tensor:
        """Ground truth [B, N, H, W] metres -> one-hot bin labels [B*N*h*w, D] (BEVDepth's semantics)."""
        return depth_bin_labels(gt_depths, self.downsample, self.d_bound)

    def get_depth_loss(self, gt_depths: Tensor, depth_preds: Tensor, from_logits: bool = False) -> Tensor:
        """BEVDepth's depth loss: weight * BCE(bin probabilities, one-hot gt bins) over foreground cells.

        ``depth_preds`` [B*N, D, h, w] are softmax probabilities as in BEVDepth (or logits with
        ``from_logits``); cells without ground truth get no loss. Autocast-safe (float32 inside).
        """
        return self.depth_loss_weight * depth_bce_loss(self.get_downsampled_gt_depth(gt_depths),
                                                       _probabilities(depth_preds, from_logits))

    def get_prior_loss(self, prior: Tensor, depth_preds: Tensor, from_logits: bool = False) -> Tensor:
        """The same BCE with the prior [B, N, H, W] as target, times lambda (``prior_loss_weight``)."""
        return self.prior_loss_weight * depth_bce_loss(self.get_downsampled_gt_depth(prior),
                                                       _probabilities(depth_preds, from_logits))


def _probabilities(depth_preds: Tensor, from_logits: bool) -> Tensor:
    return depth_preds.float().softmax(dim=1) if from_logits else depth_preds


class PriorInjector(nn.Module):
    """The prior path ``inject_prior`` adds to an existing depth net (as its ``sgde_prior`` submodule).

    Its encoder's last layer starts at zero, so the net computes exactly what it computed before until
    training moves it. It shifts the net's input features, hence depth and context alike: with an
    opaque net there is no other place; ``PriorDepthNet`` shifts depth only, which is preferable.
    """

    def __init__(self, in_channels: int, downsample: int = 16, max_depth: float = 58.0,
                 hidden_channels: int = 64) -> None:
        super().__init__()
        self.encoder = PriorFeatureEncoder(in_channels, downsample=downsample, max_depth=max_depth,
                                           hidden_channels=hidden_channels, zero_init=True)
        self.feed = PriorFeed()

    def given(self, prior: Tensor | None) -> AbstractContextManager[PriorFeed]:
        """Context manager: within it, the k-th call of the net gets frame k of ``prior`` ([B, S, N, H, W])."""
        return self.feed.given(prior)

    def shift(self, x: Tensor, prior: Tensor) -> Tensor:
        """``x`` [B*N, C, h, w] or [B, N, C, h, w] plus the encoded prior [B, N, H, W] (0 where none)."""
        check_prior_fits(prior, x, self.encoder.downsample)
        return x + self.encoder(prior).reshape(x.shape).to(x.dtype)

    def pre_forward(self, module: nn.Module, args: tuple, kwargs: dict) -> tuple[tuple, dict]:
        """Forward pre-hook: take ``prior=`` (or the feed's prior) and shift the first argument by it."""
        prior = kwargs.pop("prior", None)
        if prior is None:
            mats = next((a for a in args[1:] if isinstance(a, Mapping)), None)
            prior = self.feed.next_prior(mats)
        if prior is None or not args:
            return args, kwargs
        return (self.shift(args[0], prior), *args[1:]), kwargs


def inject_prior(depth_net: nn.Module, in_channels: int, downsample: int = 16, max_depth: float = 58.0,
                 hidden_channels: int = 64) -> nn.Module:
    """Give ``depth_net`` a prior path in place and return it: same object, class, keys and forward.

    The prior reaches it as ``prior=`` (removed before the net's own forward sees it), as
    ``mats_dict[PRIOR_KEY]`` in a dict argument (BEVDepth), or through ``depth_net.sgde_prior.given(p)``
    around the host's forward (BEVDet, FB-OCC). Its keys stay the net's own plus ``sgde_prior.*``;
    checkpoints saved before or after injection load strictly. ``in_channels``: channels of the
    net's first argument (the image features).
    """
    if hasattr(depth_net, INJECTED_NAME):
        raise ValueError(f"{type(depth_net).__name__} already has a prior path ({INJECTED_NAME})")
    injector = PriorInjector(in_channels, downsample, max_depth, hidden_channels)
    depth_net.add_module(INJECTED_NAME, injector)
    depth_net.register_forward_pre_hook(injector.pre_forward, with_kwargs=True)
    keep_missing_prior_path(depth_net, INJECTED_NAME, reset=lambda inj: _zero_last_layer(inj.encoder))
    return depth_net
