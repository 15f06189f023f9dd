"""The README recipes, executed as written, inside camera branches with the host stacks' real call structure.

BEVDepth: ``BEVDepthLikeLSSFPN`` (tests/mock_bev.py) follows ``BaseLSSFPN``: forward -> _forward_single_sweep
-> _forward_depth_net(feat, mats_dict), two sweeps (the second under no_grad), its mats_dict keys and shapes.
BEVDet / FB-OCC: a view transformer calling ``depth_net(x, mlp_input)`` once per frame, key frame first.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from mock_bev import BEVDepthLikeLSSFPN
from torch import nn

from sgde_plugin.adapters import PRIOR_KEY, PriorDepthNet
from sgde_plugin.export.models import nuscenes_like_mats

README = Path(__file__).resolve().parents[1] / "README.md"
B, S, N, H, W = 1, 2, 6, 64, 128


def readme_block(heading: str) -> str:
    """The first ```python block after ``heading`` in the README."""
    text = README.read_text()
    start = text.index(heading)
    match = re.compile(r"```python\n(.*?)```", re.S).search(text, start)
    assert match is not None, f"no python block after {heading!r}"
    return match.group(1)


def _conf() -> dict:
    return dict(x_bound=[-51.2, 51.2, 3.2], y_bound=[-51.2, 51.2, 3.2], z_bound=[-5, 3, 8], d_bound=[2.0, 58.0, 0.5],
                final_dim=(H, W), downsample_factor=16, output_channels=8, img_backbone_conf={}, img_neck_conf={},
                depth_net_conf=dict(in_channels=24, mid_channels=16))


def _batch(seed: int = 0) -> list:
    """BEVDepth's collated batch: sweep_imgs, mats_dict, timestamps, img_metas, gt_boxes, gt_labels, depth_labels."""
    g = torch.Generator().manual_seed(seed)
    imgs = torch.rand(B, S, N, 3, H, W, generator=g)
    mats = nuscenes_like_mats(B, N, (H, W), sweeps=S)
    mats["sensor2sensor_mats"] = torch.eye(4).expand(B, S, N, 4, 4).clone()
    depth = torch.where(torch.rand(B, N, H, W, generator=g) < 0.2, 3 + 50 * torch.rand(B, N, H, W, generator=g),
                        torch.zeros(B, N, H, W))
    return [imgs, mats, torch.zeros(B, S, N), [{}] * B, [], [], depth]


def _priors(seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    band = torch.zeros(W, dtype=torch.bool)
    band[: W // 5] = True
    band[-W // 5:] = True
    depth = 4 + 40 * torch.rand(B, S, N, H, W, generator=g)
    return torch.where(band, depth, torch.zeros_like(depth))


def test_readme_recipe_runs_inside_bevdepths_call_structure_and_the_prior_changes_bev_features():
    ns = {"BaseLSSFPN": BEVDepthLikeLSSFPN}
    exec(readme_block("### Into a BEVDepth-style stack"), ns)  # noqa: S102 - the README code, as written
    torch.manual_seed(0)
    model = ns["SGDELSSFPN"](**_conf()).eval()
    assert isinstance(model.depth_net, PriorDepthNet) and model.depth_net.deformable

    def bev(priors: torch.Tensor | None) -> torch.Tensor:
        batch = _batch()
        if priors is not None:
            batch = ns["collate_with_prior"](batch, priors)
        with torch.no_grad():
            return model(batch[0], batch[1])

    none = bev(None)
    c = none.shape[1] // S  # BEVDepth concatenates the sweeps' BEV maps along channels
    assert none.shape == (B, S * c, 32, 32) and none.abs().sum() > 0
    priors = _priors()
    with_prior = bev(priors)
    for s in range(S):  # each sweep got its own prior
        assert (with_prior[:, s * c:(s + 1) * c] - none[:, s * c:(s + 1) * c]).abs().max().item() > 1e-4
    assert torch.equal(bev(torch.zeros_like(priors)), none)  # an all-zero prior is exactly no prior
    only_second = priors.clone()
    only_second[:, 0] = 0
    out = bev(only_second)  # the key sweep sees none, sweep 1 sees its own
    assert torch.equal(out[:, :c], none[:, :c]) and not torch.equal(out[:, c:], none[:, c:])
    out = bev(priors[:, :1])  # key frame only: the other sweep runs as without prior
    assert torch.equal(out[:, :c], with_prior[:, :c]) and torch.equal(out[:, c:], none[:, c:])
    assert torch.equal(bev(priors), with_prior)  # a later batch starts at the key sweep again

    # training: the README's loss on the key sweep, gradients reach the prior path
    model.train()
    batch = ns["collate_with_prior"](_batch(), priors)
    feats, depth_preds = model(batch[0], batch[1], is_return_depth=True)
    loss = ns["depth_losses"](model.depth_net, batch[6], batch[1], depth_preds) + feats.mean()
    net = model.depth_net
    expected = net.get_depth_loss(batch[6], depth_preds) + net.get_prior_loss(priors[:, 0], depth_preds)
    assert torch.isfinite(loss) and (loss - feats.mean()).item() == expected.item()
    loss.backward()
    assert net.prior_encoder.net[-1].weight.grad.abs().sum().item() > 0


def test_a_bevdepth_model_checkpoint_loads_strictly_into_the_recipe_model():
    ns = {"BaseLSSFPN": BEVDepthLikeLSSFPN}
    exec(readme_block("### Into a BEVDepth-style stack"), ns)  # noqa: S102
    torch.manual_seed(0)
    bevdepth = BEVDepthLikeLSSFPN(**_conf()).eval()  # BEVDepth's own DepthNet: no prior path
    ckpt = bevdepth.state_dict()
    model = ns["SGDELSSFPN"](**_conf()).eval()
    model.load_state_dict(ckpt)  # strict, as in BEVDepth
    batch = ns["collate_with_prior"](_batch(), _priors())
    with torch.no_grad():
        ref = bevdepth(batch[0], {k: v for k, v in batch[1].items() if k != PRIOR_KEY})
        assert torch.equal(model(batch[0], batch[1]), ref)  # same function until the prior path trains


class _BEVDetDepthNet(nn.Module):
    """BEVDet's / FB-OCC's calling convention: forward(x, mlp_input), x [B*N, C, h, w] or [B, N, C, h, w]."""

    def __init__(self, cin: int, bins: int, ctx: int) -> None:
        super().__init__()
        self.reduce_conv = nn.Sequential(nn.Conv2d(cin, 16, 3, padding=1), nn.ReLU())
        self.mlp = nn.Linear(27, 16)
        self.depth_conv = nn.Conv2d(16, bins + ctx, 1)
        self.bins = bins

    def forward(self, x, mlp_input):
        five_d = x.dim() == 5
        b, n = (x.shape[0], x.shape[1]) if five_d else (mlp_input.shape[0], mlp_input.shape[1])
        feats = self.reduce_conv(x.flatten(0, 1) if five_d else x)
        feats = feats * torch.sigmoid(self.mlp(mlp_input.reshape(b * n, 27)))[..., None, None]
        out = self.depth_conv(feats)
        return out[:, : self.bins].softmax(1), out[:, self.bins:]


class _BEVDet4DLike(nn.Module):
    """Detector: encodes each frame's images, calls the view transformer's depth net per frame (key first)."""

    def __init__(self) -> None:
        super().__init__()
        self.backbone = nn.Conv2d(3, 24, 16, stride=16)
        self.depth_net = _BEVDetDepthNet(24, 112, 4)

    def forward_train(self, imgs, mlp_input, five_d=False):
        outs = []
        for f in range(imgs.shape[1]):
            x = self.backbone(imgs[:, f].flatten(0, 1))
            if five_d:
                x = x.reshape(imgs.shape[0], imgs.shape[2], *x.shape[1:])
            if f == 0:
                outs.append(self.depth_net(x, mlp_input))
            else:
                with torch.no_grad():
                    outs.append(self.depth_net(x, mlp_input))
        return outs


def test_readme_bevdet_fbocc_recipe_keeps_the_net_then_feeds_each_frame_its_prior():
    ns: dict = {}
    exec(readme_block("### Into BEVDet or FB-OCC"), ns)  # noqa: S102 - the README code, as written
    torch.manual_seed(0)
    det = _BEVDet4DLike()
    imgs, mlp = torch.rand(B, S, N, 3, H, W), torch.randn(B, N, 27)
    priors = _priors()
    for five_d in (False, True):  # BEVDet's [B*N, C, h, w]; FB-OCC's [B, N, C, h, w]
        ref = [tuple(t.detach() for t in o) for o in det.forward_train(imgs, mlp, five_d)]
        net = ns["add_prior_path"](det.depth_net) if five_d is False else det.depth_net
        assert net is det.depth_net and isinstance(net, _BEVDetDepthNet)
        out = ns["forward_with_prior"](net, priors, det.forward_train, imgs, mlp, five_d)
        assert all(torch.equal(a, b) for o, r in zip(out, ref) for a, b in zip(o, r))  # zero-start: unchanged
    with torch.no_grad():  # as after some training
        det.depth_net.sgde_prior.encoder.net[-1].weight.normal_(0.0, 0.5)
    none = det.forward_train(imgs, mlp)
    only_second = priors.clone()
    only_second[:, 0] = 0
    out = ns["forward_with_prior"](det.depth_net, only_second, det.forward_train, imgs, mlp)
    assert torch.equal(out[0][0], none[0][0])  # the key frame had no prior
    assert (out[1][0] - none[1][0]).abs().max().item() > 1e-4  # frame 1 got its own
    out = ns["forward_with_prior"](det.depth_net, priors, det.forward_train, imgs, mlp)
    assert (out[0][0] - none[0][0]).abs().max().item() > 1e-4
    assert torch.equal(det.forward_train(imgs, mlp)[0][0], none[0][0])  # outside the block: no prior
    loss = ns["prior_loss"](priors[:, 0], out[0][0])
    assert torch.isfinite(loss) and loss.item() > 0
