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


def _conv_bn_relu(cin: int, cout: int, kernel: int, dilation: int = 1) -> nn.Sequential:
    pad = 0 if kernel == 1 else dilation
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, padding=pad, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling (dilations 1, 6, 12, 18 plus a global branch), as in BEVDepth."""

    def __init__(self, in_channels: int, mid_channels: int, dilations: tuple[int, ...] = (1, 6, 12, 18)) -> None:
        super().__init__()
        self.branches = nn.ModuleList(
            [_conv_bn_relu(in_channels, mid_channels, 1 if d == 1 else 3, d) for d in dilations]
        )
        self.global_branch = _conv_bn_relu(in_channels, mid_channels, 1)
        self.project = _conv_bn_relu(mid_channels * (len(dilations) + 1), mid_channels, 1)
        self.dropout = nn.Dropout(0.5)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight)

    def forward(self, x: Tensor) -> Tensor:
        """[M, in, h, w] -> [M, mid, h, w]."""
        outs = [branch(x) for branch in self.branches]
        pooled = self.global_branch(x.mean(dim=(2, 3), keepdim=True))
        # a 1x1 map upsampled (bilinear, align_corners) is a constant map: broadcast it instead
        outs.append(pooled.expand_as(outs[0]))
        return self.dropout(self.project(torch.cat(outs, dim=1)))
