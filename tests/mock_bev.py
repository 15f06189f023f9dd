"""Mock BEV heads for adapter tests: pure-torch LSS pooling with a heatmap head, and an occupancy head.

Small and differentiable, no custom ops: enough to train a depth branch end to end through a
bird's-eye-view task and to consume VoxFormer-style proposals.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def frustum_points(
    K: Tensor, sensor_to_ego: Tensor, feat_hw: tuple[int, int], stride: int, d_bound: tuple[float, float, float]
) -> Tensor:
    """Ego points of every (depth bin centre, feature cell centre): [B, N, D, h, w, 3] for pinholes.

    ``K`` [B, N, 3, 3] at the image size, ``sensor_to_ego`` [B, N, 4, 4].
    """
    h, w = feat_hw
    start, stop, step = d_bound
    depths = torch.arange(start, stop - 1e-9, step, dtype=K.dtype) + step / 2
    v = (torch.arange(h, dtype=K.dtype) + 0.5) * stride - 0.5
    u = (torch.arange(w, dtype=K.dtype) + 0.5) * stride - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    pix = torch.stack([uu, vv, torch.ones_like(uu)], dim=-1)  # [h, w, 3]
    rays = torch.einsum("bnij,hwj->bnhwi", torch.linalg.inv(K), pix)  # z = 1
    cam = rays[:, :, None] * depths[None, None, :, None, None, None]  # [B, N, D, h, w, 3]
    rot, trans = sensor_to_ego[..., :3, :3], sensor_to_ego[..., :3, 3]
    return torch.einsum("bnij,bndhwj->bndhwi", rot, cam) + trans[:, :, None, None, None, :]


def lss_pool(
    depth_probs: Tensor, context: Tensor, points: Tensor, origin: tuple[float, float], cell: float,
    bev_hw: tuple[int, int],
) -> Tensor:
    """Lift-splat: depth-weighted context scattered (summed) into BEV cells -> [B, C, X, Y].

    ``depth_probs`` [B*N, D, h, w], ``context`` [B*N, C, h, w], ``points`` [B, N, D, h, w, 3].
    """
    b, n = points.shape[:2]
    c = context.shape[1]
    nx, ny = bev_hw
    feats = depth_probs.unsqueeze(1) * context.unsqueeze(2)  # [B*N, C, D, h, w]
    feats = feats.reshape(b, n, c, -1).permute(0, 1, 3, 2).reshape(b, -1, c)  # [B, N*D*h*w, C]
    ix = torch.floor((points[..., 0] - origin[0]) / cell).long().reshape(b, -1)
    iy = torch.floor((points[..., 1] - origin[1]) / cell).long().reshape(b, -1)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    flat = torch.where(inside, ix * ny + iy, torch.full_like(ix, nx * ny))
    bev = torch.zeros(b, nx * ny + 1, c, dtype=feats.dtype)
    bev = bev.scatter_add(1, flat.unsqueeze(-1).expand(-1, -1, c), feats)
    return bev[:, : nx * ny].reshape(b, nx, ny, c).permute(0, 3, 1, 2)


class HeatmapHead(nn.Module):
    """BEV features -> one-class centre heatmap logits [B, 1, X, Y]."""

    def __init__(self, channels: int, hidden: int = 16) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(),
                                 nn.Conv2d(hidden, 1, 1))

    def forward(self, bev: Tensor) -> Tensor:
        """[B, C, X, Y] -> [B, 1, X, Y] logits."""
        return self.net(bev)

    @staticmethod
    def loss(logits: Tensor, target: Tensor) -> Tensor:
        """Binary cross-entropy against a {0, 1} target heatmap."""
        return F.binary_cross_entropy_with_logits(logits, target)


class OccupancyHead(nn.Module):
    """Query proposals [B, X, Y, Z] -> occupancy logits at the same resolution (a tiny 3-D CNN)."""

    def __init__(self, hidden: int = 8) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv3d(1, hidden, 3, padding=1), nn.ReLU(), nn.Conv3d(hidden, 1, 1))

    def forward(self, proposals: Tensor) -> Tensor:
        """[B, X, Y, Z] in {0, 1} -> [B, X, Y, Z] logits."""
        return self.net(proposals.unsqueeze(1)).squeeze(1)

    @staticmethod
    def loss(logits: Tensor, target: Tensor) -> Tensor:
        """Binary cross-entropy against a {0, 1} occupancy target."""
        return F.binary_cross_entropy_with_logits(logits, target)


class BEVDepthLikeLSSFPN(nn.Module):
    """A camera branch with BEVDepth's ``BaseLSSFPN`` call structure, in pure torch, for adapter tests.

    Read from BEVDepth's public code (``bevdepth/layers/backbones/base_lss_fpn.py``), written anew:
    ``forward(sweep_imgs [B, S, N, 3, H, W], mats_dict)`` runs ``_forward_single_sweep`` for the key
    sweep with gradients and for every other sweep under ``no_grad``, concatenating the BEV maps along
    channels; each sweep calls ``_forward_depth_net(feat [B*N, C, h, w], mats_dict)`` with the whole
    ``mats_dict`` (``sensor2ego_mats``, ``intrin_mats``, ``ida_mats``, ``sensor2sensor_mats``
    [B, S, N, 4, 4]; ``bda_mat`` [B, 4, 4]), takes the softmax of the first ``depth_channels``
    outputs, lifts the next ``output_channels`` along the frustum and sum-pools them into voxels.
    The image backbone + neck are one strided convolution to ``depth_net_conf['in_channels']``
    channels (BEVDepth's SECONDFPN gives 512), and the depth net is BEVDepth's DepthNet (here
    ``PriorDepthNet(use_prior=False, deformable=True)``: the same modules and keys).
    """

    def __init__(self, x_bound, y_bound, z_bound, d_bound, final_dim, downsample_factor, output_channels,
                 img_backbone_conf, img_neck_conf, depth_net_conf, use_da=False):
        super().__init__()
        self.downsample_factor = downsample_factor
        self.d_bound = d_bound
        self.final_dim = final_dim
        self.output_channels = output_channels
        bounds = (x_bound, y_bound, z_bound)
        self.register_buffer("voxel_size", torch.tensor([b[2] for b in bounds], dtype=torch.float32))
        self.register_buffer("voxel_coord", torch.tensor([b[0] + b[2] / 2.0 for b in bounds], dtype=torch.float32))
        self.register_buffer("voxel_num", torch.tensor([round((b[1] - b[0]) / b[2]) for b in bounds]))
        self.register_buffer("frustum", self.create_frustum())
        self.depth_channels = self.frustum.shape[0]
        self.img_backbone = nn.Conv2d(3, depth_net_conf["in_channels"], downsample_factor, stride=downsample_factor)
        self.img_neck = nn.Identity()
        self.depth_net = self._configure_depth_net(depth_net_conf)

    def _configure_depth_net(self, depth_net_conf):
        from sgde_plugin.adapters import PriorDepthNet

        return PriorDepthNet(depth_net_conf["in_channels"], depth_net_conf["mid_channels"], self.output_channels,
                             self.depth_channels, d_bound=tuple(self.d_bound), downsample=self.downsample_factor,
                             use_prior=False, deformable=True)

    def create_frustum(self) -> Tensor:
        """[D, fH, fW, 4]: (u, v) of the feature cells spread over the image (linspace), depth, 1."""
        img_h, img_w = self.final_dim
        fh, fw = img_h // self.downsample_factor, img_w // self.downsample_factor
        d = torch.arange(*self.d_bound, dtype=torch.float32)
        dd, vv, uu = torch.meshgrid(d, torch.linspace(0, img_h - 1, fh), torch.linspace(0, img_w - 1, fw),
                                    indexing="ij")
        return torch.stack([uu, vv, dd, torch.ones_like(dd)], dim=-1)

    def get_geometry(self, sensor2ego_mat, intrin_mat, ida_mat, bda_mat) -> Tensor:
        """Ego points [B, N, D, fH, fW, 3] of the frustum: undo the image augmentation, unproject, to ego, bda."""
        b, n = sensor2ego_mat.shape[:2]
        pts = torch.linalg.inv(ida_mat).view(b, n, 1, 1, 1, 4, 4) @ self.frustum.unsqueeze(-1)
        pts = torch.cat([pts[..., :2, :] * pts[..., 2:3, :], pts[..., 2:, :]], dim=-2)  # (u d, v d, d, 1)
        cam_to_ego = sensor2ego_mat @ torch.linalg.inv(intrin_mat)
        pts = cam_to_ego.view(b, n, 1, 1, 1, 4, 4) @ pts
        if bda_mat is not None:
            pts = bda_mat.view(b, 1, 1, 1, 1, 4, 4) @ pts
        return pts.squeeze(-1)[..., :3]

    def get_cam_feats(self, imgs: Tensor) -> Tensor:
        """[B, S, N, 3, H, W] -> [B, S, N, C, h, w]."""
        b, s, n = imgs.shape[:3]
        feats = self.img_neck(self.img_backbone(imgs.flatten(0, 2)))
        return feats.reshape(b, s, n, *feats.shape[1:])

    def _voxel_pooling(self, geom_xyz: Tensor, feats: Tensor) -> Tensor:
        """Sum features [B, N, D, fH, fW, C] into the voxels of ``geom_xyz`` (int) -> BEV [B, C, Y, X]."""
        b, c = feats.shape[0], feats.shape[-1]
        nx, ny, nz = (int(v) for v in self.voxel_num)
        ix, iy, iz = geom_xyz[..., 0], geom_xyz[..., 1], geom_xyz[..., 2]
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
        flat = torch.where(inside, iy * nx + ix, torch.full_like(ix, nx * ny)).reshape(b, -1).long()
        bev = feats.new_zeros(b, nx * ny + 1, c)
        bev = bev.scatter_add(1, flat.unsqueeze(-1).expand(-1, -1, c), feats.reshape(b, -1, c))
        return bev[:, : nx * ny].reshape(b, ny, nx, c).permute(0, 3, 1, 2)

    def _forward_depth_net(self, feat, mats_dict):
        return self.depth_net(feat, mats_dict)

    def _forward_single_sweep(self, sweep_index, sweep_imgs, mats_dict, is_return_depth=False):
        b, _, n = sweep_imgs.shape[:3]
        source = self.get_cam_feats(sweep_imgs)[:, 0]
        depth_feature = self._forward_depth_net(source.reshape(b * n, *source.shape[2:]), mats_dict)
        depth = depth_feature[:, : self.depth_channels].softmax(1)
        context = depth_feature[:, self.depth_channels: self.depth_channels + self.output_channels]
        lifted = depth.unsqueeze(1) * context.unsqueeze(2)  # [B*N, C, D, h, w]
        lifted = lifted.reshape(b, n, *lifted.shape[1:]).permute(0, 1, 3, 4, 5, 2)  # [B, N, D, h, w, C]
        geom = self.get_geometry(mats_dict["sensor2ego_mats"][:, sweep_index], mats_dict["intrin_mats"][:, sweep_index],
                                 mats_dict["ida_mats"][:, sweep_index], mats_dict.get("bda_mat"))
        geom = ((geom - (self.voxel_coord - self.voxel_size / 2.0)) / self.voxel_size).int()
        feature_map = self._voxel_pooling(geom, lifted)
        return (feature_map, depth) if is_return_depth else feature_map

    def forward(self, sweep_imgs, mats_dict, timestamps=None, is_return_depth=False):
        num_sweeps = sweep_imgs.shape[1]
        key = self._forward_single_sweep(0, sweep_imgs[:, 0:1], mats_dict, is_return_depth=is_return_depth)
        if num_sweeps == 1:
            return key
        maps = [key[0] if is_return_depth else key]
        for sweep_index in range(1, num_sweeps):
            with torch.no_grad():
                maps.append(self._forward_single_sweep(sweep_index, sweep_imgs[:, sweep_index:sweep_index + 1],
                                                       mats_dict, is_return_depth=False))
        out = torch.cat(maps, 1)
        return (out, key[1]) if is_return_depth else out


def bevdepth_depthnet_shapes(cin: int, mid: int, ctx: int, bins: int) -> dict[str, tuple[int, ...]]:
    """Key names and shapes of BEVDepth's DepthNet (base_lss_fpn.py; mmdet BasicBlock, mmcv DCN), written out."""
    def bn(name, c):
        return {f"{name}.weight": (c,), f"{name}.bias": (c,), f"{name}.running_mean": (c,),
                f"{name}.running_var": (c,), f"{name}.num_batches_tracked": ()}

    keys = {"reduce_conv.0.weight": (mid, cin, 3, 3), "reduce_conv.0.bias": (mid,), **bn("reduce_conv.1", mid),
            "context_conv.weight": (ctx, mid, 1, 1), "context_conv.bias": (ctx,), **bn("bn", 27)}
    for mlp in ("depth_mlp", "context_mlp"):
        keys |= {f"{mlp}.fc1.weight": (mid, 27), f"{mlp}.fc1.bias": (mid,), f"{mlp}.fc2.weight": (mid, mid),
                 f"{mlp}.fc2.bias": (mid,)}
    for se in ("depth_se", "context_se"):
        keys |= {f"{se}.conv_reduce.weight": (mid, mid, 1, 1), f"{se}.conv_reduce.bias": (mid,),
                 f"{se}.conv_expand.weight": (mid, mid, 1, 1), f"{se}.conv_expand.bias": (mid,)}
    for i in range(3):
        keys |= {f"depth_conv.{i}.conv1.weight": (mid, mid, 3, 3), **bn(f"depth_conv.{i}.bn1", mid),
                 f"depth_conv.{i}.conv2.weight": (mid, mid, 3, 3), **bn(f"depth_conv.{i}.bn2", mid)}
    for i, k in ((1, 1), (2, 3), (3, 3), (4, 3)):
        keys |= {f"depth_conv.3.aspp{i}.atrous_conv.weight": (mid, mid, k, k), **bn(f"depth_conv.3.aspp{i}.bn", mid)}
    keys |= {"depth_conv.3.global_avg_pool.1.weight": (mid, mid, 1, 1), **bn("depth_conv.3.global_avg_pool.2", mid),
             "depth_conv.3.conv1.weight": (mid, 5 * mid, 1, 1), **bn("depth_conv.3.bn1", mid),
             "depth_conv.4.weight": (mid, mid // 4, 3, 3), "depth_conv.4.conv_offset.weight": (18, mid, 3, 3),
             "depth_conv.4.conv_offset.bias": (18,),
             "depth_conv.5.weight": (bins, mid, 1, 1), "depth_conv.5.bias": (bins,)}
    return keys


def bevdepth_depthnet_state(cin: int, mid: int, ctx: int, bins: int, seed: int = 0) -> dict[str, Tensor]:
    """A random state dict with BEVDepth DepthNet's key names and shapes (a stand-in for its checkpoints)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, shape in bevdepth_depthnet_shapes(cin, mid, ctx, bins).items():
        if k.endswith("num_batches_tracked"):
            out[k] = torch.tensor(100)
        elif k.endswith("running_var"):
            out[k] = 0.5 + torch.rand(shape, generator=g)
        else:
            out[k] = 0.1 * torch.randn(shape, generator=g)
    return out
