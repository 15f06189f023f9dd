"""Reference depth network "Baseline (R18)": torchvision ResNet-18 encoder with an optional prior
channel, monodepth2-style decoder, multi-scale metric depth outputs."""

from __future__ import annotations

import copy
from pathlib import Path

import torch
import torch.nn.functional as F
import torchvision
from torch import Tensor, nn

from .encoding import PriorEncoding
from .inputs import require_tensor
from .stem import widen_first_conv

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
ENCODER_CHANNELS = (64, 64, 128, 256, 512)
DECODER_CHANNELS = (16, 32, 64, 128, 256)


def load_resnet18(weights_path: str | Path | None = None) -> torchvision.models.ResNet:
    """torchvision ResNet-18 with random weights, or weights from a local file (never downloads).

    The file is read with ``torch.load(weights_only=True)``; a plain state dict or one nested under
    "state_dict" / "model" is accepted, and the classifier ("fc.*") may be missing.
    """
    net = torchvision.models.resnet18(weights=None)
    if weights_path is None:
        return net
    state = torch.load(Path(weights_path), map_location="cpu", weights_only=True)
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    missing, unexpected = net.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("fc.")]
    if missing or unexpected:
        raise ValueError(f"{weights_path}: not a ResNet-18 state dict (missing {missing[:3]}, "
                         f"unexpected {list(unexpected)[:3]})")
    return net


class ResNet18Encoder(nn.Module):
    """ResNet-18 features at strides 2, 4, 8, 16, 32 for RGB (+ prior channels)."""

    def __init__(self, extra_channels: int = 0, validity: bool = False,
                 weights_path: str | Path | None = None, stem: str = "full") -> None:
        super().__init__()
        net = load_resnet18(weights_path)
        if extra_channels or validity:
            widen_first_conv(net, extra_channels=extra_channels, validity=validity, mode=stem)
        self.conv1, self.bn1, self.relu, self.maxpool = net.conv1, net.bn1, net.relu, net.maxpool
        self.layer1, self.layer2, self.layer3, self.layer4 = net.layer1, net.layer2, net.layer3, net.layer4

    def forward(self, x: Tensor) -> list[Tensor]:
        """Input [B,C,H,W] -> five feature maps, finest first."""
        f0 = self.relu(self.bn1(self.conv1(x)))
        f1 = self.layer1(self.maxpool(f0))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f0, f1, f2, f3, f4]


class ConvBlock(nn.Module):
    """3x3 convolution followed by ELU as in monodepth2 (replicate padding: works on 1-pixel maps)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1, padding_mode="replicate")
        self.act = nn.ELU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        """Apply conv + ELU."""
        return self.act(self.conv(x))


def _check_map(name: str, value: object, images: int, size: tuple[int, int]) -> None:
    """One clear error unless ``value`` is None or a tensor holding one ``size`` map per image (any leading shape)."""
    if value is None:
        return
    value = require_tensor(name, value)
    if tuple(value.shape[-2:]) != tuple(size) or value.numel() != images * size[0] * size[1]:
        raise ValueError(f"{name} must hold one {size[0]}x{size[1]} map per image ({images} images), "
                         f"got shape {list(value.shape)}")


class DepthDecoder(nn.Module):
    """monodepth2-style U-Net decoder: per level upconv, upsample, skip concat, upconv; sigmoid heads."""

    def __init__(self, encoder_channels: tuple[int, ...] = ENCODER_CHANNELS,
                 scales: tuple[int, ...] = (0, 1, 2, 3)) -> None:
        super().__init__()
        self.scales = tuple(scales)
        self.up0 = nn.ModuleList()
        self.up1 = nn.ModuleList()
        for i in range(4, -1, -1):
            c_in = encoder_channels[-1] if i == 4 else DECODER_CHANNELS[i + 1]
            self.up0.append(ConvBlock(c_in, DECODER_CHANNELS[i]))
            c_skip = encoder_channels[i - 1] if i > 0 else 0
            self.up1.append(ConvBlock(DECODER_CHANNELS[i] + c_skip, DECODER_CHANNELS[i]))
        self.heads = nn.ModuleDict({
            str(s): nn.Conv2d(DECODER_CHANNELS[s], 1, 3, padding=1, padding_mode="replicate") for s in self.scales
        })

    def forward(self, features: list[Tensor], out_size: tuple[int, int]) -> dict[int, Tensor]:
        """Features (finest first) -> {scale: sigmoid output [B,1,H/2^s,W/2^s]}; scale 0 has ``out_size``."""
        x = features[-1]
        out: dict[int, Tensor] = {}
        for k, i in enumerate(range(4, -1, -1)):
            x = self.up0[k](x)
            size = features[i - 1].shape[-2:] if i > 0 else out_size
            x = F.interpolate(x, size=size, mode="nearest")
            if i > 0:
                x = torch.cat([x, features[i - 1]], dim=1)
            x = self.up1[k](x)
            if i in self.scales:
                out[i] = torch.sigmoid(self.heads[str(i)](x))
        return out


def sigmoid_to_depth(sig: Tensor, min_depth: float, max_depth: float) -> Tensor:
    """monodepth2 mapping: sigmoid -> inverse depth in [1/max, 1/min] -> depth in [min, max]."""
    min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
    return 1.0 / (min_disp + (max_disp - min_disp) * sig)


class DepthNet(nn.Module):
    """Baseline (R18) depth network with the SGDE prior input.

    ``forward(rgb, prior=None, valid=None)``: ``rgb`` in [0, 1], shape [B,3,H,W] or [B,N,3,H,W]
    (N cameras are folded into the batch and unfolded again); ``prior`` [.., 1, H, W] metres,
    0 = none; ``valid`` optional bool mask applied to the prior. Returns a dict with
    ``("disp", s)`` (sigmoid output) and ``("depth", s)`` (metres in [min_depth, max_depth]) for
    each scale s (resolution H/2^s). ``use_prior=False`` is the plain 3-channel baseline.
    ``stem`` is the prior-channel stem's form: ``"full"`` (the paper), ``"factored"`` or ``"lowrank"``
    (cheaper; see ``nn.stem``). ``prior_encoding`` is the prior channel's form (`PriorEncoding`: ``"depth"``,
    depth / prior_max_depth; ``"log"``, log(depth / 10 m), which needs ``validity``).
    """

    def __init__(
        self,
        use_prior: bool = True,
        validity: bool = False,
        min_depth: float = 0.1,
        max_depth: float = 80.0,
        prior_max_depth: float | None = None,
        scales: tuple[int, ...] = (0, 1, 2, 3),
        weights_path: str | Path | None = None,
        stem: str = "full",
        prior_encoding: str = "depth",
    ) -> None:
        super().__init__()
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        if validity and not use_prior:
            raise ValueError("validity channel needs use_prior=True")
        self.use_prior = use_prior
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.scales = tuple(scales)
        self.encoding = PriorEncoding(prior_max_depth or max_depth, with_validity=validity,
                                      form=prior_encoding) if use_prior else None
        self.encoder = ResNet18Encoder(extra_channels=int(use_prior), validity=validity, weights_path=weights_path,
                                       stem=stem)
        self.decoder = DepthDecoder(ENCODER_CHANNELS, self.scales)
        self.register_buffer("rgb_mean", torch.tensor(IMAGENET_MEAN).reshape(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(IMAGENET_STD).reshape(1, 3, 1, 1), persistent=False)

    def forward(self, rgb: Tensor, prior: Tensor | None = None, valid: Tensor | None = None) -> dict:
        """Multi-scale disparity-sigmoid and metric depth outputs (see class docstring)."""
        lead = rgb.shape[:-3]
        h, w = rgb.shape[-2:]
        x = (rgb.reshape(-1, 3, h, w) - self.rgb_mean) / self.rgb_std
        for name, value in (("prior", prior), ("valid", valid)):
            _check_map(name, value, x.shape[0], (h, w))
        if self.encoding is not None:
            if prior is None:
                prior = torch.zeros_like(x[:, :1])
            prior = prior.reshape(-1, 1, h, w).to(x.dtype)
            if valid is not None:
                prior = prior * valid.reshape(-1, 1, h, w).to(x.dtype)
            x = torch.cat([x, self.encoding(prior)], dim=1)
        sig = self.decoder(self.encoder(x), (h, w))
        out: dict = {}
        for s, v in sig.items():
            v = v.reshape(*lead, 1, *v.shape[-2:])
            out[("disp", s)] = v
            out[("depth", s)] = sigmoid_to_depth(v, self.min_depth, self.max_depth)
        return out

    @classmethod
    def with_prior_from(cls, baseline: DepthNet, validity: bool = False,
                        prior_max_depth: float | None = None, stem: str = "full",
                        prior_encoding: str = "depth") -> DepthNet:
        """A prior-input copy of a (trained) 3-channel ``baseline``: same weights, widened first conv.

        With an all-zero prior it computes exactly what the baseline computes.
        """
        if baseline.use_prior:
            raise ValueError("baseline already takes a prior")
        net = copy.deepcopy(baseline)
        net.use_prior = True
        net.encoding = PriorEncoding(prior_max_depth or baseline.max_depth, with_validity=validity,
                                     form=prior_encoding)
        net.encoder.conv1 = widen_first_conv(net.encoder.conv1, 1, validity, mode=stem)
        return net

    def predict(self, rgb: Tensor, prior: Tensor | None = None, valid: Tensor | None = None) -> Tensor:
        """Full-resolution metric depth only (a single tensor, convenient for export)."""
        return self(rgb, prior, valid)[("depth", 0)]
