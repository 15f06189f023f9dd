"""BEVDepth-style depth branch: contract shapes, camera parameters, prior path, BEVDepth's depth loss."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from sgde_plugin.adapters import PriorDepthNet, PriorInjector
from sgde_plugin.adapters.camera_aware import camera_params
from sgde_plugin.adapters.depth_bins import depth_bin_labels, num_depth_bins
from sgde_plugin.adapters.prior_features import min_pool_nonzero


def _mats(b: int, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    mats = {k: torch.eye(4).expand(b, 1, n, 4, 4).clone() for k in ("intrin_mats", "ida_mats", "sensor2ego_mats")}
    mats["intrin_mats"][..., 0, 0] = 500 + 50 * torch.rand(b, 1, n, generator=g)
    mats["intrin_mats"][..., 1, 1] = mats["intrin_mats"][..., 0, 0]
    mats["intrin_mats"][..., 0, 2] = 352.0
    mats["intrin_mats"][..., 1, 2] = 128.0
    mats["sensor2ego_mats"][..., :3, 3] = torch.randn(b, 1, n, 3, generator=g)
    mats["bda_mat"] = torch.eye(4).expand(b, 4, 4).clone()
    return mats


def test_contract_shapes_with_bevdepth_defaults_and_prior_none_equals_no_prior_path():
    # BEVDepth defaults: in 512, mid 512, context 80, D 112; 256x704 input -> 16x44 features (~6 s on 2 idle cores)
    torch.manual_seed(0)
    net = PriorDepthNet(512, 512, 80, 112).eval()
    plain = PriorDepthNet(512, 512, 80, 112, use_prior=False).eval()
    missing, unexpected = plain.load_state_dict(net.state_dict(), strict=False)
    assert missing == [] and all(k.startswith("prior_encoder.") for k in unexpected) and unexpected
    for b, n in ((2, 6), (2, 4)):  # six nuScenes cameras; four fisheye virtual views
        x = torch.randn(b * n, 512, 16, 44)
        mats = _mats(b, n)
        prior = torch.zeros(b, n, 256, 704)
        prior[..., :, :128] = 12.5
        with torch.no_grad():
            out = net(x, mats, prior=prior)
        assert out.shape == (b * n, 112 + 80, 16, 44)
        assert torch.isfinite(out).all()
    # (b, n) = (2, 4) from here: without a prior the output is the plain DepthNet's
    with torch.no_grad():
        no_prior = net(x, mats)
        ref = plain(x, mats)
    assert (no_prior - ref).abs().max().item() <= 1e-6
    # the prior changes the depth logits only, never the context
    assert (out[:, :112] - no_prior[:, :112]).abs().max().item() > 1e-3
    assert torch.equal(out[:, 112:], no_prior[:, 112:])


def test_camera_params_are_bevdepths_27_values_in_order():
    b, n = 1, 2
    mats = {k: torch.arange(16, dtype=torch.float32).reshape(4, 4).expand(b, 1, n, 4, 4) + off
            for k, off in (("intrin_mats", 100.0), ("ida_mats", 200.0), ("sensor2ego_mats", 300.0))}
    mats["bda_mat"] = torch.arange(16, dtype=torch.float32).reshape(1, 4, 4) + 400.0
    p = camera_params(mats)
    assert p.shape == (b * n, 27)
    expected = ([100, 105, 102, 106] + [200, 201, 203, 204, 205, 207] + [400, 401, 404, 405, 410]
                + [300 + i for i in range(12)])
    assert p[0].tolist() == expected and p[1].tolist() == expected


def test_min_pool_nonzero_keeps_empty_cells_at_zero():
    d = torch.tensor([[0.0, 3.0, 0.0, 0.0],
                      [5.0, 4.0, 0.0, 0.0],
                      [9.0, 9.0, 0.0, 7.0],
                      [9.0, 2.5, 0.0, 0.0]])
    assert min_pool_nonzero(d[None, None], 2)[0, 0].tolist() == [[3.0, 0.0], [2.5, 7.0]]


def test_depth_loss_matches_hand_computation_and_ignores_empty_cells():
    d_bound = (2.0, 4.0, 0.5)  # 4 bins: [2, 2.5), [2.5, 3), [3, 3.5), [3.5, 4)
    net = PriorDepthNet(4, 4, 2, num_depth_bins(d_bound), d_bound=d_bound, downsample=2)
    gt = torch.tensor([[0.0, 3.2, 0.0, 0.0],   # cell (0,0): min 2.7 -> bin 1; cell (0,1): empty
                       [2.7, 0.0, 0.0, 0.0],
                       [5.0, 0.0, 2.0, 0.0],   # cell (1,0): 5.0 beyond the bins; cell (1,1): 2.0 -> bin 0
                       [0.0, 6.0, 0.0, 2.2]])[None, None]
    labels = net.get_downsampled_gt_depth(gt)
    assert labels.tolist() == [[0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]
    probs = torch.tensor([[0.1, 0.6, 0.2, 0.1], [0.25, 0.25, 0.25, 0.25],
                          [0.4, 0.3, 0.2, 0.1], [0.7, 0.1, 0.1, 0.1]]).reshape(1, 2, 2, 4).permute(0, 3, 1, 2)
    cell00 = -math.log(0.6) - math.log(0.9) - math.log(0.8) - math.log(0.9)
    cell11 = -math.log(0.7) - 3 * math.log(0.9)
    expected = 3.0 * (cell00 + cell11) / 2
    assert net.get_depth_loss(gt, probs).item() == pytest.approx(expected, rel=1e-6)
    # empty / out-of-range cells: any prediction there changes nothing and gets no gradient
    other = probs.clone()
    other[0, :, 0, 1] = torch.tensor([0.97, 0.01, 0.01, 0.01])
    other[0, :, 1, 0] = torch.tensor([0.01, 0.01, 0.01, 0.97])
    assert net.get_depth_loss(gt, other).item() == pytest.approx(expected, rel=1e-6)
    logits = torch.randn(1, 4, 2, 2, requires_grad=True)
    net.get_depth_loss(torch.zeros_like(gt), logits, from_logits=True).backward()
    assert logits.grad.abs().max().item() == 0.0
    # the prior loss is the same BCE on the prior, times lambda instead of BEVDepth's 3.0
    assert net.get_prior_loss(gt, probs).item() == pytest.approx(0.005 * expected / 3.0, rel=1e-6)


def test_bins_follow_bevdepths_edges():
    d = torch.tensor([1.99, 2.0, 2.49, 2.5, 57.99, 58.0, 0.0]).reshape(1, 1, 1, 7)
    labels = depth_bin_labels(d, 1, (2.0, 58.0, 0.5))
    assert labels.shape == (7, 112)
    assert [int(r.argmax()) if r.any() else None for r in labels] == [None, 0, 0, 1, 111, None, None]


def test_depth_channels_must_match_d_bound():
    with pytest.raises(ValueError, match="bins"):
        PriorDepthNet(8, 8, 4, 100)


def test_deformable_option_runs_and_prior_is_refused_without_prior_path():
    torch.manual_seed(0)
    net = PriorDepthNet(8, 8, 4, 112, deformable=True).eval()
    with torch.no_grad():
        out = net(torch.randn(2, 8, 2, 3), _mats(1, 2), prior=torch.rand(1, 2, 32, 48) * 50)
    assert out.shape == (2, 116, 2, 3)
    with pytest.raises(ValueError, match="use_prior=False"):
        PriorDepthNet(8, 8, 4, 112, use_prior=False)(torch.randn(2, 8, 2, 3), _mats(1, 2),
                                                      prior=torch.rand(1, 2, 32, 48))


class _UserDepthNet(nn.Module):
    """Stand-in for a user's DepthNet: conv over features, with an extra argument and attribute."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(8, 5, 1)
        self.depth_channels = 3

    def forward(self, x, mats_dict, scale=1.0):
        return self.conv(x) * scale + mats_dict["bias"]


def test_prior_injector_is_exact_before_training_then_learns():
    torch.manual_seed(0)
    user = _UserDepthNet()
    wrapped = PriorInjector(user, in_channels=8, downsample=4, max_depth=50.0)
    x = torch.randn(2, 8, 3, 5)
    mats = {"bias": torch.tensor(0.5)}
    prior = torch.where(torch.rand(2, 1, 12, 20) < 0.5, torch.rand(2, 1, 12, 20) * 40, torch.zeros(2, 1, 12, 20))
    ref = user(x, mats, scale=2.0)
    assert torch.equal(wrapped(x, mats, scale=2.0, prior=prior), ref)
    assert torch.equal(wrapped(x, mats, scale=2.0), ref)
    assert wrapped.depth_channels == 3  # attributes of the wrapped net stay reachable
    opt = torch.optim.SGD(wrapped.prior_encoder.parameters(), lr=0.1)
    for _ in range(3):
        opt.zero_grad()
        loss = (wrapped(x, mats, prior=prior) - 1.0).pow(2).mean()
        loss.backward()
        opt.step()
    assert (wrapped(x, mats, scale=2.0, prior=prior) - ref).abs().max().item() > 1e-4
