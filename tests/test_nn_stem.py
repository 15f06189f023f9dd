"""Prior encoding and prior-channel stem (runtime ~2 s)."""

import copy
import math

import pytest
import torch
import torchvision
from torch import nn

from sgde_plugin.nn import PriorChannelStem, PriorEncoding, find_first_conv, widen_first_conv


def test_prior_encoding_values():
    prior = torch.tensor([[[[0.0, 40.0], [100.0, -3.0]]]])
    out = PriorEncoding(max_depth=80.0)(prior)
    assert out.shape == (1, 1, 2, 2)
    assert torch.equal(out, torch.tensor([[[[0.0, 0.5], [1.0, 0.0]]]]))
    out2 = PriorEncoding(max_depth=80.0, with_validity=True)(prior)
    assert out2.shape == (1, 2, 2, 2)
    assert torch.equal(out2[:, 1], torch.tensor([[[0.0, 1.0], [1.0, 0.0]]]))


def test_log_prior_encoding_values_and_round_trip():
    prior = torch.tensor([[[[0.0, 10.0, 2.5], [40.0, 0.2, 100.0]]]])
    enc = PriorEncoding(max_depth=80.0, with_validity=True, form="log")
    out = enc(prior)
    # log(d / 10 m): 0 for none, 0 for 10 m (told apart by validity), -log 4, log 4; 0.2 m -> floor 0.5 m,
    # 100 m -> max 80 m
    expected = torch.tensor([[0.0, 0.0, -math.log(4)], [math.log(4), math.log(0.05), math.log(8.0)]])
    assert torch.allclose(out[0, 0], expected, atol=1e-6)
    assert torch.equal(out[0, 1], torch.tensor([[0.0, 1.0, 1.0], [1.0, 1.0, 1.0]]))
    back = enc.decode(out)
    assert torch.allclose(back, torch.tensor([[[[0.0, 10.0, 2.5], [40.0, 0.5, 80.0]]]]), rtol=1e-6)
    depth = PriorEncoding(max_depth=80.0)
    assert torch.allclose(depth.decode(depth(prior)), torch.tensor([[[[0.0, 10.0, 2.5], [40.0, 0.2, 80.0]]]]))
    with pytest.raises(ValueError, match="validity"):
        PriorEncoding(form="log")
    with pytest.raises(ValueError, match="form"):
        PriorEncoding(with_validity=True, form="inverse")


def test_widened_conv_init():
    torch.manual_seed(0)
    conv = nn.Conv2d(3, 4, 3, padding=1, bias=True)
    wide = widen_first_conv(conv, extra_channels=1, validity=True)
    assert wide.in_channels == 5
    assert torch.equal(wide.weight[:, :3], conv.weight)
    assert torch.allclose(wide.weight[:, 3], conv.weight.mean(dim=1))
    assert torch.count_nonzero(wide.weight[:, 4]) == 0
    assert torch.equal(wide.bias, conv.bias)


def test_find_first_conv_resnet():
    net = torchvision.models.resnet18(weights=None)
    parent, attr, conv = find_first_conv(net)
    assert parent is net and attr == "conv1" and conv is net.conv1
    with pytest.raises(ValueError):
        find_first_conv(nn.Sequential(nn.Linear(2, 2)))


@pytest.mark.parametrize("validity", [False, True])
def test_zero_prior_equivalence_resnet18(validity):
    torch.manual_seed(0)
    ref = torchvision.models.resnet18(weights=None).eval()
    wide = widen_first_conv(copy.deepcopy(ref), validity=validity).eval()
    x = torch.randn(2, 3, 64, 96)
    extra = torch.zeros(2, 1 + int(validity), 64, 96)
    with torch.no_grad():
        diff = (wide(torch.cat([x, extra], 1)) - ref(x)).abs().max().item()
    assert diff <= 1e-6
    # a non-zero prior must change the output (the channel is wired in)
    with torch.no_grad():
        moved = (wide(torch.cat([x, extra + 0.5], 1)) - ref(x)).abs().max().item()
    assert moved > 1e-3


def test_prior_channel_stem_zero_prior():
    torch.manual_seed(0)
    conv = nn.Conv2d(3, 8, 7, stride=2, padding=3, bias=False)
    stem = PriorChannelStem(conv, max_depth=80.0, with_validity=True)
    rgb = torch.randn(3, 3, 32, 32)
    prior = torch.zeros(3, 1, 32, 32)
    assert torch.allclose(stem(rgb, prior), conv(rgb), atol=1e-6)


@pytest.mark.parametrize("validity", [False, True])
def test_factored_stem_equals_full_at_start(validity):
    torch.manual_seed(0)
    conv = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
    full = widen_first_conv(conv, validity=validity)
    factored = widen_first_conv(conv, validity=validity, mode="factored", rank=4)
    x = torch.rand(2, 4 + int(validity), 40, 56)
    with torch.no_grad():
        assert (factored(x) - full(x)).abs().max().item() <= 1e-5
        assert torch.allclose(factored.full_weight(), full.weight, atol=1e-7)
        # zero prior: exactly the original convolution
        x[:, 3:] = 0
        assert torch.equal(factored(x), conv(x[:, :3]))


def test_factored_stem_trains_its_own_prior_kernel():
    torch.manual_seed(0)
    conv = nn.Conv2d(3, 8, 7, stride=2, padding=3, bias=False)
    factored = widen_first_conv(conv, mode="factored", rank=2)
    x = torch.rand(1, 4, 16, 16)
    factored(x).square().sum().backward()
    # the zero-initialised 1x1 mix gets a gradient, so the low-rank kernel leaves zero after a step
    assert factored.mix.weight.grad.abs().max().item() > 1e-4
    assert factored.conv.weight.grad.abs().max().item() > 1e-4
    # after one step the basis trains too, and the equivalent kernel has left the mean of RGB
    opt = torch.optim.SGD(factored.parameters(), lr=0.1)
    opt.step()
    opt.zero_grad()
    factored(x).square().sum().backward()
    assert factored.basis.weight.grad.abs().max().item() > 1e-6
    w = factored.full_weight()
    assert (w[:, 3] - w[:, :3].mean(dim=1)).abs().max().item() > 1e-4
    with pytest.raises(ValueError):
        widen_first_conv(conv, mode="sparse")


def test_factored_stem_in_resnet18_zero_prior():
    torch.manual_seed(0)
    ref = torchvision.models.resnet18(weights=None).eval()
    wide = widen_first_conv(copy.deepcopy(ref), validity=True, mode="factored").eval()
    x = torch.randn(2, 3, 64, 96)
    with torch.no_grad():
        diff = (wide(torch.cat([x, torch.zeros(2, 2, 64, 96)], 1)) - ref(x)).abs().max().item()
    assert diff <= 1e-6


def test_lowrank_stem_starts_at_the_best_rank_r_mean_kernel():
    torch.manual_seed(0)
    conv = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
    mean = conv.weight.mean(dim=1).reshape(64, -1)
    sv = torch.linalg.svdvals(mean)
    for rank in (4, 49):
        low = widen_first_conv(conv, validity=True, mode="lowrank", rank=rank)
        w = low.full_weight()
        assert torch.equal(w[:, :3], conv.weight)
        assert torch.count_nonzero(w[:, 4]) == 0  # validity starts at zero
        err = torch.linalg.matrix_norm(w[:, 3].reshape(64, -1) - mean).item()
        # Eckart-Young: the error of the best rank-r approximation is the norm of the dropped singular values
        assert err == pytest.approx(sv[rank:].norm().item(), abs=1e-5)
    x = torch.rand(2, 5, 32, 48)
    full = widen_first_conv(conv, validity=True)
    with torch.no_grad():
        assert (low(x) - full(x)).abs().max().item() <= 1e-5  # rank 49 = the kernel's full rank: the paper's start
        x[:, 3:] = 0
        assert torch.equal(low(x), conv(x[:, :3]))
