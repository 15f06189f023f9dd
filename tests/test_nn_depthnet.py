"""Reference R18 depth net: output shapes and ranges, zero-prior equivalence, local weights (~6 s)."""

import pytest
import torch
import torchvision

from sgde_plugin.nn import DepthNet, load_resnet18


@pytest.mark.parametrize("shape", [(1, 3, 64, 96), (2, 6, 3, 32, 64), (3, 3, 40, 72)])
def test_output_shapes_and_range(shape):
    torch.manual_seed(0)
    net = DepthNet(use_prior=True, validity=True, min_depth=0.5, max_depth=60.0).eval()
    rgb = torch.rand(*shape)
    prior = torch.rand(*shape[:-3], 1, *shape[-2:]) * 40
    with torch.no_grad():
        out = net(rgb, prior)
    h, w = shape[-2:]
    for s in (0, 1, 2, 3):
        d = out[("depth", s)]
        assert d.shape[:-2] == (*shape[:-3], 1)
        assert d.shape[-2:] == ((h + 2**s - 1) // 2**s, (w + 2**s - 1) // 2**s)
        assert out[("disp", s)].shape == d.shape
        assert float(d.min()) >= 0.5 - 1e-5 and float(d.max()) <= 60.0 + 1e-3
    assert torch.equal(net.predict(rgb, prior), out[("depth", 0)])


def test_cameras_fold_into_batch():
    torch.manual_seed(0)
    net = DepthNet(use_prior=True).eval()
    rgb, prior = torch.rand(2, 3, 3, 32, 64), torch.rand(2, 3, 1, 32, 64) * 30
    with torch.no_grad():
        folded = net.predict(rgb, prior)
        flat = net.predict(rgb.reshape(6, 3, 32, 64), prior.reshape(6, 1, 32, 64))
    assert torch.allclose(folded.reshape(6, 1, 32, 64), flat, atol=1e-6)


def test_a_prior_or_validity_map_that_does_not_fit_the_images_is_one_clear_error():
    net = DepthNet(use_prior=True).eval()
    rgb = torch.rand(2, 3, 32, 64)
    with torch.no_grad():
        assert net(rgb, torch.zeros(2, 32, 64))[("depth", 0)].shape == (2, 1, 32, 64)  # any leading shape
        for bad in (torch.zeros(2, 1, 16, 32), torch.zeros(1, 1, 32, 64), torch.zeros(2, 2, 32, 64)):
            with pytest.raises(ValueError, match=rf"prior must hold one 32x64 map per image \(2 images\), got "
                                                 rf"shape \[{', '.join(map(str, bad.shape))}\]"):
                net(rgb, bad)  # before: torch reshape / cat size errors
        with pytest.raises(TypeError, match="prior must be a torch.Tensor, got list"):
            net(rgb, [[0.0]])
        with pytest.raises(ValueError, match="valid must hold one 32x64 map per image"):
            net(rgb, torch.zeros(2, 1, 32, 64), torch.ones(2, 1, 32, 32))


@pytest.mark.parametrize("validity,form", [(False, "depth"), (True, "depth"), (True, "log")])
def test_zero_prior_equivalence(validity, form):
    torch.manual_seed(0)
    base = DepthNet(use_prior=False).eval()
    wide = DepthNet.with_prior_from(base, validity=validity, prior_encoding=form).eval()
    assert wide.encoding.form == form
    assert wide.encoder.conv1.in_channels == 4 + int(validity)
    rgb = torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        ref = base.predict(rgb)
        diff = (wide.predict(rgb, torch.zeros(2, 1, 64, 96)) - ref).abs().max().item()
        moved = (wide.predict(rgb, torch.full((2, 1, 64, 96), 20.0)) - ref).abs().max().item()
    assert diff <= 1e-6
    assert moved > 1e-4


def test_local_weights_are_loaded(tmp_path):
    torch.manual_seed(1)
    ref = torchvision.models.resnet18(weights=None)
    path = tmp_path / "r18.pth"
    torch.save({"state_dict": {k: v for k, v in ref.state_dict().items() if not k.startswith("fc.")}}, path)
    assert torch.equal(load_resnet18(path).layer3[0].conv1.weight, ref.layer3[0].conv1.weight)
    net = DepthNet(use_prior=True, weights_path=path)
    assert torch.equal(net.encoder.conv1.weight[:, :3], ref.conv1.weight)
    assert torch.allclose(net.encoder.conv1.weight[:, 3], ref.conv1.weight.mean(1))
    torch.save({"conv.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError):
        load_resnet18(tmp_path / "bad.pth")
