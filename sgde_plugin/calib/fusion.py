"""Averaging two calibrations of one rig that agree (the calibration in effect and a later window), pair by pair.

Each window's adjustment gives every adjacent pair's relative rotation a 1-sigma, and one window can determine a
pair far worse than another while determining the rest as well (a pair whose overlap the later frames see less
of: 0.107 against 0.023 deg, the others 0.003-0.008 deg in both; issue #17 session 23). Weighting whole windows by
their worst pair then throws the good pairs of such a window away. Here each camera gets the small offset from the
calibration in effect that best fits both calibrations' relative poses, every pair weighted by 1 / its 1-sigma^2
in that calibration (a weighted least-squares fit on the pair graph; translations with the same weights, since a
pair's translation is measured by the same matches); what relative poses leave free, the placement of each linked
group of cameras as a whole, is that of the mean of the two weighted by their worst common pairs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..geometry import make_transform, mean_transform, rodrigues, rotation_vector
from .acceptance import common_pairs
from .blocks import linked_blocks


@dataclass
class Fused:
    """Two calibrations of one rig averaged pair by pair (`fuse_calibrations`)."""

    extrinsics: dict[str, np.ndarray]
    pair_sigma_deg: dict[tuple[str, str], float]
    weights: tuple[float, float]  # in effect, window (summing to 1): the placement of the rig as a whole
    pair_weights: dict[tuple[str, str], float]  # per pair both have: the window's share of its relative pose


def usable_sigmas(sigma_deg: Mapping[tuple[str, str], float]) -> dict[tuple[str, str], float]:
    """The pairs whose rotation 1-sigma is finite and positive, with it (the ones a weight can come from)."""
    return {p: float(s) for p, s in sigma_deg.items() if np.isfinite(s) and s > 0}


def fuse_calibrations(in_effect: Mapping[str, np.ndarray], in_effect_sigma_deg: Mapping[tuple[str, str], float],
                      window: Mapping[str, np.ndarray], window_sigma_deg: Mapping[tuple[str, str], float]) -> Fused:
    """Precision-weighted mean of two calibrations of one rig that agree (independent windows), pair by pair: every
    camera's offset from `in_effect` fitted to both sets of relative poses, each pair weighted by 1 / its rotation
    1-sigma^2 in each; each linked group of cameras placed as the mean of the two weighted by their worst common
    pair; a pair's fused 1-sigma combines the two as independent estimates (one that only one of them has keeps
    its own). With no pair in common the window is returned as it is."""
    common = common_pairs(in_effect_sigma_deg, window_sigma_deg)
    if not common:
        return Fused(dict(window), dict(window_sigma_deg), (0.0, 1.0), {})
    w = np.array([1.0 / max(in_effect_sigma_deg[p] for p in common) ** 2,
                  1.0 / max(window_sigma_deg[p] for p in common) ** 2])
    w /= w.sum()
    cams = list(window)
    mean = {n: mean_transform(np.stack([in_effect[n], window[n]]), w) for n in cams}
    index = {c: k for k, c in enumerate(cams)}

    def offsets(ext: Mapping[str, np.ndarray]) -> np.ndarray:
        """Per camera: rotation vector (ego side) and position offset from the calibration in effect, (M, 6)."""
        return np.array([np.concatenate([rotation_vector(ext[c][:3, :3] @ in_effect[c][:3, :3].T),
                                         ext[c][:3, 3] - in_effect[c][:3, 3]]) for c in cams])

    laplacian, rhs, linked = np.zeros((len(cams), len(cams))), np.zeros((len(cams), 6)), set()
    for ext, sigma in ((in_effect, in_effect_sigma_deg), (window, window_sigma_deg)):
        d = offsets(ext)
        for (a, b), s in usable_sigmas(sigma).items():
            if a not in index or b not in index:
                continue
            i, j, wt = index[a], index[b], s ** -2.0
            laplacian[[i, j], [i, j]] += wt
            laplacian[[i, j], [j, i]] -= wt
            rhs[j] += wt * (d[j] - d[i])
            rhs[i] -= wt * (d[j] - d[i])
            linked.add((a, b))
    # the minimum-norm solution sums to zero over each linked group; the group's placement comes from the mean
    x = np.linalg.lstsq(laplacian, rhs, rcond=None)[0]
    d_mean = offsets(mean)
    for block in linked_blocks(cams, sorted(linked)):
        rows = [index[c] for c in block]
        x[rows] += d_mean[rows].mean(axis=0)
    ext = {c: make_transform(rodrigues(x[index[c], :3]) @ in_effect[c][:3, :3], in_effect[c][:3, 3] + x[index[c], 3:])
           for c in cams}
    before = usable_sigmas(in_effect_sigma_deg)
    sigma = {**before, **{p: float((before[p] ** -2 + s ** -2) ** -0.5) if p in before else s
                          for p, s in usable_sigmas(window_sigma_deg).items()}}
    shares = {p: float(window_sigma_deg[p] ** -2 / (window_sigma_deg[p] ** -2 + in_effect_sigma_deg[p] ** -2))
              for p in common}
    return Fused(ext, sigma, (float(w[0]), float(w[1])), shares)
