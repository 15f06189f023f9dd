"""BEVDepth-style depth branch: contract shapes, camera parameters, prior path, BEVDepth's depth loss."""

from __future__ import annotations

import math

import pytest
import torch
from mock_bev import bevdepth_depthnet_state
from torch import nn

from sgde_plugin.adapters import PRIOR_KEY, PriorDepthNet, depth_bins, inject_prior
from sgde_plugin.adapters.bevdepth import DeformConv3x3
from sgde_plugin.adapters.camera_aware import camera_params
from sgde_plugin.adapters.depth_bins import depth_bin_labels, num_depth_bins
from sgde_plugin.adapters.prior_features import min_pool_nonzero
from sgde_plugin.errors import InputError


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


def test_contract_shapes_with_bevdepth_defaults_and_zero_prior_is_exactly_no_prior():
    # BEVDepth defaults: in 512, mid 512, context 80, D 112; 256x704 input -> 16x44 features
    torch.manual_seed(0)
    net = PriorDepthNet(512, 512, 80, 112).eval()
    plain = PriorDepthNet(512, 512, 80, 112, use_prior=False).eval()
    missing, unexpected = plain.load_state_dict(net.state_dict(), strict=False)
    assert missing == [] and all(k.startswith("prior_encoder.") for k in unexpected) and unexpected
    b, n = 1, 6  # six nuScenes cameras
    x = torch.randn(b * n, 512, 16, 44)
    mats = _mats(b, n)
    prior = torch.zeros(b, n, 256, 704)
    prior[..., :, :128] = 12.5
    with torch.no_grad():
        out = net(x, mats, prior=prior)
    assert out.shape == (b * n, 112 + 80, 16, 44)
    assert torch.isfinite(out).all()
    # without a prior the output is the plain DepthNet's
    with torch.no_grad():
        no_prior = net(x, mats)
        zero_prior = net(x, mats, prior=torch.zeros_like(prior))
        ref = plain(x, mats)
    assert torch.equal(no_prior, ref)
    assert torch.equal(zero_prior, no_prior)  # an all-zero prior is exactly no prior (it was 0.245 off before)
    # the prior changes the depth logits only, never the context, and only where it has values
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
    dcn = net.depth_conv[4]
    # mmcv's DCN as BEVDepth builds it: no bias, groups 4, offsets start at zero
    assert {k for k, _ in dcn.named_parameters()} == {"weight", "conv_offset.weight", "conv_offset.bias"}
    assert dcn.weight.shape == (8, 2, 3, 3) and dcn.conv_offset.weight.abs().max().item() == 0.0
    # Kaiming-uniform for ReLU: bound sqrt(6 / fan_in), fan_in = 2 * 9
    assert dcn.weight.abs().max().item() <= math.sqrt(6 / 18) and dcn.weight.std().item() > 0.5 * math.sqrt(2 / 18)
    with torch.no_grad():
        out = net(torch.randn(2, 8, 2, 3), _mats(1, 2), prior=torch.rand(1, 2, 32, 48) * 50)
    assert out.shape == (2, 116, 2, 3)
    with pytest.raises(ValueError, match="use_prior=False"):
        PriorDepthNet(8, 8, 4, 112, use_prior=False)(torch.randn(2, 8, 2, 3), _mats(1, 2),
                                                      prior=torch.rand(1, 2, 32, 48))


def test_dcn_offsets_are_dy_dx_as_in_mmcv():
    conv = DeformConv3x3(4, groups=4)
    with torch.no_grad():
        conv.weight.zero_()
        conv.weight[:, 0, 1, 1] = 1.0  # identity through the kernel centre
        conv.conv_offset.bias[8] = 1.0  # centre point (index 4), first component: +1 pixel
    x = torch.zeros(1, 4, 5, 5)
    x[0, :, 2, 2] = 1.0
    out = conv(x)
    assert out[0, 0].nonzero().tolist() == [[1, 2]]  # read one row lower: the first component is dy


def _bevdepth_checkpoint(seed: int = 0) -> dict[str, torch.Tensor]:
    return bevdepth_depthnet_state(8, 16, 4, 112, seed)


def test_bevdepth_checkpoint_loads_strictly_with_its_real_key_names():
    ckpt = _bevdepth_checkpoint()
    torch.manual_seed(0)
    net = PriorDepthNet(8, 16, 4, 112, deformable=True)
    assert set(net.state_dict()) - set(ckpt) == {k for k in net.state_dict() if k.startswith("prior_encoder.")}
    net.load_state_dict(ckpt)  # strict by default; the prior path is new
    state = net.state_dict()
    assert all(torch.equal(state[k], v) for k, v in ckpt.items())  # every BEVDepth tensor went in unchanged
    # the new prior path starts at zero: the loaded net computes what the checkpoint computed, prior or not
    net.eval()
    x, mats = torch.randn(4, 8, 2, 3), _mats(2, 2)
    prior = torch.rand(2, 2, 32, 48) * 50
    with torch.no_grad():
        assert torch.equal(net(x, mats, prior=prior), net(x, mats))
    # a whole model's checkpoint (BEVDepth's LightningModule: model.backbone.depth_net.*) loads as well
    other = PriorDepthNet(8, 16, 4, 112, deformable=True)
    other.load_state_dict({f"model.backbone.depth_net.{k}": v for k, v in ckpt.items()}
                          | {"model.head.w": torch.zeros(1)})
    assert torch.equal(other.state_dict()["depth_conv.3.conv1.weight"], ckpt["depth_conv.3.conv1.weight"])
    # round trip with the prior path
    again = PriorDepthNet(8, 16, 4, 112, deformable=True)
    again.load_state_dict(net.state_dict())
    assert all(torch.equal(again.state_dict()[k], v) for k, v in net.state_dict().items())


def test_partial_or_mismatched_checkpoints_are_refused_in_one_line():
    ckpt = _bevdepth_checkpoint()
    net = PriorDepthNet(8, 16, 4, 112, deformable=True)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    partial = {k: v for k, v in ckpt.items() if not k.startswith("depth_conv.3.aspp2.")}
    with pytest.raises(InputError) as err:
        net.load_state_dict(partial)
    line = str(err.value)
    assert "\n" not in line and "missing 5 keys" in line and "depth_conv.3.aspp2.atrous_conv.weight" in line
    assert all(torch.equal(net.state_dict()[k], v) for k, v in before.items())  # nothing half-loaded
    # without deformable=True, BEVDepth's DCN checkpoint is refused with the fix named
    with pytest.raises(InputError, match="build with deformable=True"):
        PriorDepthNet(8, 16, 4, 112).load_state_dict(ckpt)
    # strict=False remains available and reports the difference the torch way
    missing, _ = PriorDepthNet(8, 16, 4, 112, deformable=True).load_state_dict(partial, strict=False)
    assert len(missing) == 5


def test_losses_are_autocast_safe_under_cpu_bf16(monkeypatch):
    torch.manual_seed(0)
    net = PriorDepthNet(4, 8, 2, 112).train()
    gt = torch.where(torch.rand(1, 2, 32, 48) < 0.3, 2 + 50 * torch.rand(1, 2, 32, 48), torch.zeros(1, 2, 32, 48))
    x, mats = torch.randn(2, 4, 2, 3), _mats(1, 2)
    seen = []
    real_bce = depth_bins.F.binary_cross_entropy

    def spy(input, target, *args, **kwargs):  # noqa: A002 - torch's argument name
        seen.append((torch.is_autocast_enabled("cpu"), input.dtype, target.dtype))
        return real_bce(input, target, *args, **kwargs)

    monkeypatch.setattr(depth_bins.F, "binary_cross_entropy", spy)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(x, mats, prior=gt)
        probs = out[:, :112].softmax(1)
        assert probs.dtype == torch.bfloat16  # the net really ran in bf16
        loss = net.get_depth_loss(gt, probs) + net.get_prior_loss(gt, probs)
        logit_loss = net.get_depth_loss(gt, out[:, :112], from_logits=True)
    # CUDA autocast refuses binary_cross_entropy; ours always runs it with autocast off, in float32
    assert seen and all(s == (False, torch.float32, torch.float32) for s in seen)
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    expected = (net.get_depth_loss(gt, probs.float()) + net.get_prior_loss(gt, probs.float())).item()
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    assert logit_loss.item() == pytest.approx(net.get_depth_loss(gt, out[:, :112].float().softmax(1)).item(), rel=1e-6)
    loss.backward()
    assert net.prior_encoder.net[-1].weight.grad.abs().sum().item() > 0


def test_half_net_takes_a_float32_prior():
    torch.manual_seed(0)
    net = PriorDepthNet(4, 8, 2, 112).eval()
    x, mats = torch.randn(2, 4, 2, 3), _mats(1, 2)
    prior = torch.where(torch.rand(1, 2, 32, 48) < 0.3, 2 + 50 * torch.rand(1, 2, 32, 48), torch.zeros(1, 2, 32, 48))
    with torch.no_grad():
        ref = net(x, mats, prior=prior)
        half = net.half()(x.half(), {k: v.half() for k, v in mats.items()}, prior=prior)  # prior stays float32
    assert half.dtype == torch.float16
    assert (half.float() - ref).abs().max().item() < 2e-2 * (ref.max() - ref.min()).item()


class _UserDepthNet(nn.Module):
    """Stand-in for a user's DepthNet: conv over features, with an extra argument and attribute."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(8, 5, 1)
        self.depth_channels = 3

    def forward(self, x, mats_dict, scale=1.0):
        return self.conv(x) * scale + mats_dict["bias"]


def test_injected_net_is_exact_before_training_keeps_class_and_keys_then_learns():
    torch.manual_seed(0)
    user = _UserDepthNet()
    before_keys = dict(user.state_dict())
    x = torch.randn(2, 8, 3, 5)
    mats = {"bias": torch.tensor(0.5)}
    ref = user(x, mats, scale=2.0).detach()
    prior = torch.where(torch.rand(2, 1, 12, 20) < 0.5, torch.rand(2, 1, 12, 20) * 40, torch.zeros(2, 1, 12, 20))
    net = inject_prior(user, in_channels=8, downsample=4, max_depth=50.0)
    assert net is user and isinstance(net, _UserDepthNet) and net.depth_channels == 3
    assert torch.equal(net(x, mats, scale=2.0, prior=prior), ref)
    assert torch.equal(net(x, mats, scale=2.0), ref)
    # keys: the net's own, unchanged, plus sgde_prior.*; checkpoints from before and after load strictly
    keys = set(net.state_dict())
    assert set(before_keys) <= keys and all(k.startswith("sgde_prior.") for k in keys - set(before_keys))
    opt = torch.optim.SGD(net.sgde_prior.parameters(), lr=0.1)
    for _ in range(3):
        opt.zero_grad()
        loss = (net(x, mats, prior=prior) - 1.0).pow(2).mean()
        loss.backward()
        opt.step()
    trained = net(x, mats, scale=2.0, prior=prior).detach()
    assert (trained - ref).abs().max().item() > 1e-4
    fresh = inject_prior(_UserDepthNet(), in_channels=8, downsample=4, max_depth=50.0)
    fresh.load_state_dict(net.state_dict())  # after injection -> after injection
    assert torch.equal(fresh(x, mats, scale=2.0, prior=prior), trained)
    fresh.load_state_dict(before_keys)  # a checkpoint from before the injection: strict, prior path back to zero
    assert torch.equal(fresh(x, mats, scale=2.0, prior=prior), ref)
    plain = _UserDepthNet()
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if not k.startswith("sgde_prior.")})
    with pytest.raises(ValueError, match="already has a prior path"):
        inject_prior(net, in_channels=8)


def test_a_prior_of_the_wrong_rank_in_mats_dict_is_refused_naming_the_key():
    net = PriorDepthNet(4, 8, 2, 112).eval()
    mats = _mats(1, 2) | {PRIOR_KEY: torch.zeros(2, 32, 48)}
    with pytest.raises(ValueError, match=r"sgde_prior must be \[B, S, N, H, W\] or \[B, N, H, W\], got \[2, 32, 48\]"):
        net(torch.randn(2, 4, 2, 3), mats)


def test_a_prior_that_does_not_lie_on_the_features_is_refused_naming_both_shapes():
    net = PriorDepthNet(4, 8, 2, 112).eval()
    x, mats = torch.randn(2, 4, 2, 3), _mats(1, 2)  # one sample of two cameras, features 2x3 at stride 16
    assert net(x, mats, prior=torch.zeros(1, 2, 32, 48)).shape == (2, 114, 2, 3)
    expected = r"does not fit the features \[2, 4, 2, 3\]: expected 2 images of 32x48"
    for bad in (torch.zeros(1, 3, 32, 48), torch.zeros(1, 2, 16, 48), torch.zeros(3, 1, 32, 48),
                torch.zeros(1, 2, 32, 64)):  # another camera count, height, batch, a width that still pools
        with pytest.raises(ValueError, match=rf"prior \[{', '.join(map(str, bad.shape))}\] {expected}"):
            net(x, mats, prior=bad)
    with pytest.raises(TypeError, match="prior must be a torch.Tensor, got list"):
        net(x, mats, prior=[[0.0]])
    user = inject_prior(_UserDepthNet(), in_channels=8, downsample=4)
    with pytest.raises(ValueError, match=r"prior \[2, 1, 12, 16\] does not fit the features \[2, 8, 3, 5\]"):
        user(torch.randn(2, 8, 3, 5), {"bias": torch.tensor(0.5)}, prior=torch.zeros(2, 1, 12, 16))
