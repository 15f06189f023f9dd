"""BEVDepth's camera-aware building blocks: the 27 camera parameters, an MLP, squeeze-excitation, ASPP."""

from __future__ import annotations

import torch
from torch import Tensor, nn

CAMERA_PARAMS = 27  # 4 intrinsics + 6 image-augmentation + 5 BEV-augmentation + 12 sensor-to-ego values


def _sweep0(mat: Tensor, name: str) -> Tensor:
    """[B, S, N, 4, 4] (or [B, N, 4, 4]) -> the key sweep [B, N, 4, 4]."""
    if mat.dim() == 5:
        return mat[:, 0]
    if mat.dim() == 4:
        return mat
    raise ValueError(f"{name} must be [B, S, N, 4, 4] or [B, N, 4, 4], got {list(mat.shape)}")


def camera_params(mats_dict: dict[str, Tensor]) -> Tensor:
    """BEVDepth's camera-aware MLP input, [B*N, 27], from ``mats_dict`` (sweep 0 only).

    Order: fx, fy, cx, cy; ida (0,0) (0,1) (0,3) (1,0) (1,1) (1,3); bda (0,0) (0,1) (1,0) (1,1)
    (2,2); then the top 3x4 of sensor_to_ego, row-major.
    """
    intrins = _sweep0(mats_dict["intrin_mats"], "intrin_mats")
    ida = _sweep0(mats_dict["ida_mats"], "ida_mats")
    s2e = _sweep0(mats_dict["sensor2ego_mats"], "sensor2ego_mats")
    bda = mats_dict["bda_mat"]
    if bda.dim() != 3:
        raise ValueError(f"bda_mat must be [B, 4, 4], got {list(bda.shape)}")
    bda = bda.unsqueeze(1).expand(-1, intrins.shape[1], -1, -1)
    values = [
        intrins[..., 0, 0], intrins[..., 1, 1], intrins[..., 0, 2], intrins[..., 1, 2],
        ida[..., 0, 0], ida[..., 0, 1], ida[..., 0, 3], ida[..., 1, 0], ida[..., 1, 1], ida[..., 1, 3],
        bda[..., 0, 0], bda[..., 0, 1], bda[..., 1, 0], bda[..., 1, 1], bda[..., 2, 2],
    ]
    params = torch.cat([torch.stack(values, dim=-1), s2e[..., :3, :].flatten(-2)], dim=-1)
    return params.reshape(-1, CAMERA_PARAMS)


class Mlp(nn.Module):
    """Two linear layers with a ReLU between (camera parameters -> per-channel gates)."""

    def __init__(self, in_features: int, hidden_features: int, out_features: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = nn.ReLU()
        self.fc2 = nn.Linear(hidden_features, out_features)

    def forward(self, x: Tensor) -> Tensor:
        """[M, in] -> [M, out]."""
        return self.fc2(self.act(self.fc1(x)))


class SELayer(nn.Module):
    """Squeeze-excitation driven by an external vector: x * sigmoid(conv(relu(conv(x_se))))."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv_reduce = nn.Conv2d(channels, channels, 1)
        self.act = nn.ReLU()
        self.conv_expand = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor, x_se: Tensor) -> Tensor:
        """``x`` [M, C, h, w] gated by ``x_se`` [M, C, 1, 1]."""
        return x * torch.sigmoid(self.conv_expand(self.act(self.conv_reduce(x_se))))


class _AtrousBranch(nn.Module):
    """Convolution (no bias) -> BatchNorm -> ReLU; attribute names as BEVDepth's ``_ASPPModule``."""

    def __init__(self, cin: int, cout: int, kernel: int, dilation: int) -> None:
        super().__init__()
        pad = 0 if kernel == 1 else dilation
        self.atrous_conv = nn.Conv2d(cin, cout, kernel, padding=pad, dilation=dilation, bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU()

    def forward(self, x: Tensor) -> Tensor:
        """[M, cin, h, w] -> [M, cout, h, w]."""
        return self.relu(self.bn(self.atrous_conv(x)))


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling (dilations 1, 6, 12, 18 plus a global branch), as in BEVDepth.

    State-dict keys are BEVDepth's (``aspp1..4.atrous_conv``, ``global_avg_pool.1``/``.2``, ``conv1``,
    ``bn1``), so its checkpoints load; convolutions start Kaiming-normal like BEVDepth's.
    """

    def __init__(self, in_channels: int, mid_channels: int) -> None:
        super().__init__()
        self.aspp1 = _AtrousBranch(in_channels, mid_channels, 1, 1)
        self.aspp2 = _AtrousBranch(in_channels, mid_channels, 3, 6)
        self.aspp3 = _AtrousBranch(in_channels, mid_channels, 3, 12)
        self.aspp4 = _AtrousBranch(in_channels, mid_channels, 3, 18)
        self.global_avg_pool = nn.Sequential(
            nn.AdaptiveAvgPool2d((1, 1)),
            nn.Conv2d(in_channels, mid_channels, 1, bias=False),
            nn.BatchNorm2d(mid_channels),
            nn.ReLU(),
        )
        self.conv1 = nn.Conv2d(5 * mid_channels, mid_channels, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(mid_channels)
        self.relu = nn.ReLU()
        self.dropout = nn.Dropout(0.5)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight)

    def forward(self, x: Tensor) -> Tensor:
        """[M, in, h, w] -> [M, mid, h, w]."""
        branches = [self.aspp1(x), self.aspp2(x), self.aspp3(x), self.aspp4(x)]
        # the pooled 1x1 map upsampled (bilinear, align_corners) is a constant map: broadcast it instead
        branches.append(self.global_avg_pool(x).expand_as(branches[0]))
        return self.dropout(self.relu(self.bn1(self.conv1(torch.cat(branches, dim=1)))))
