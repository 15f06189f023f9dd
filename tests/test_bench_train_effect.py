"""Pieces of `sgde bench train-effect` that the demo does not exercise (runtime < 1 s)."""

import numpy as np

from sgde_plugin.benchmarks.train_effect import thin_hits


def test_thin_hits_keeps_the_asked_density_and_only_lidar_pixels():
    rng = np.random.default_rng(0)
    hits = rng.random((4, 6, 64, 112)) < 0.5
    thinned = thin_hits(hits, 0.025, np.random.default_rng(1))
    assert not np.any(thinned & ~hits)
    assert abs(thinned.mean() - 0.025) < 0.002
    # asking for more than there is keeps everything
    assert np.array_equal(thin_hits(hits, 0.9, np.random.default_rng(1)), hits)
