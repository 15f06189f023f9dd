"""Pieces of `sgde bench train-effect` that the demo does not exercise (runtime < 1 s)."""

import numpy as np
import pytest

from sgde_plugin.benchmarks.train_effect import thin_hits


def test_thin_hits_keeps_the_asked_density_and_only_lidar_pixels():
    rng = np.random.default_rng(0)
    hits = rng.random((4, 6, 64, 112)) < 0.5
    thinned = thin_hits(hits, 0.025, np.random.default_rng(1))
    assert not np.any(thinned & ~hits)
    assert abs(thinned.mean() - 0.025) < 0.002
    # asking for more than there is keeps everything
    assert np.array_equal(thin_hits(hits, 0.9, np.random.default_rng(1)), hits)


def test_self_supervised_nets_start_at_the_asked_depth():
    import torch

    from sgde_plugin.nn import DepthNet, sigmoid_to_depth
    from sgde_plugin.nn.train import start_at_depth

    net = DepthNet(use_prior=False, min_depth=0.5, max_depth=100.0)
    start_at_depth(net, 10.0)
    for head in net.decoder.heads.values():
        assert float(sigmoid_to_depth(torch.sigmoid(head.bias.detach()), 0.5, 100.0)) == pytest.approx(10.0, rel=1e-5)
