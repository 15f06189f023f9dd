"""Band-limited procedural texture: a bank of tileable value-noise octaves and box-filtered stripes.

Every texture of the synthetic world is a function of a surface's own 2-D coordinates (metres),
so a surface point has the same colour from every camera. To avoid aliasing without view-dependent
blur beyond what a pixel integrates anyway, each octave fades out once the pixel footprint
approaches its lattice spacing (a manual mip-map), and stripe patterns are box-filtered exactly
over the footprint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor


@dataclass(frozen=True, eq=False)
class NoiseBank:
    """Tileable value-noise octaves: `table` (1, C, S+1, S+1), channel c has lattice spacing 2**c texels."""

    table: Tensor
    size: int

    @property
    def octaves(self) -> int:
        """Number of octaves (channels)."""
        return int(self.table.shape[1])


def make_noise_bank(seed: int, size: int = 512, octaves: int = 7) -> NoiseBank:
    """Octaves of periodic cubic value noise, each with zero mean and unit standard deviation."""
    rng = np.random.default_rng(seed)
    chans = []
    for c in range(octaves):
        step = 2**c
        lattice = rng.standard_normal((size // step, size // step))
        up = ndimage.zoom(lattice, step, order=3, mode="grid-wrap", grid_mode=True) if step > 1 else lattice
        up = (up - up.mean()) / (up.std() + 1e-12)
        chans.append(up)
    table = np.stack(chans).astype(np.float32)
    table = np.concatenate([table, table[:, :1]], axis=1)  # wrap row/column for bilinear lookups
    table = np.concatenate([table, table[:, :, :1]], axis=2)
    return NoiseBank(torch.from_numpy(np.ascontiguousarray(table))[None], size)


def sample_octaves(bank: NoiseBank, s: Tensor, t: Tensor, texel_m: float) -> Tensor:
    """All octaves at surface coordinates (s, t) in metres: (n, C)."""
    period = bank.size * texel_m
    # coordinates wrapped to [0, 1) of one period, then to [-1, 1] of the padded table
    u = torch.remainder(s / period, 1.0) * 2.0 - 1.0
    v = torch.remainder(t / period, 1.0) * 2.0 - 1.0
    grid = torch.stack([u, v], dim=-1).reshape(1, 1, -1, 2)
    out = F.grid_sample(bank.table, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, :, 0].T  # (n, C)


def octave_weights(footprint_m: Tensor, texel_m: float, octaves: int) -> Tensor:
    """Per-pixel weight of each octave: 1 while its lattice spacing is >= 3 footprints, 0 below 1 footprint."""
    spacing = texel_m * (2.0 ** torch.arange(octaves, dtype=footprint_m.dtype))
    half_inv = 0.5 / footprint_m.clamp_min(1e-6)
    return torch.clamp_(half_inv[:, None] * spacing[None, :] - 0.5, 0.0, 1.0)


def fbm(bank: NoiseBank, s: Tensor, t: Tensor, footprint_m: Tensor, texel_m: float, gains: Tensor) -> Tensor:
    """Footprint-filtered sum of octaves: sum_c gains[c] * w_c * noise_c, zero mean."""
    n = sample_octaves(bank, s, t, texel_m)
    w = octave_weights(footprint_m, texel_m, bank.octaves)
    return (n.mul_(w) @ gains.to(n.dtype)).contiguous()


def _stripe_integral(x: Tensor, period: float, width: float) -> Tensor:
    """Integral from 0 to x of the indicator of [k * period, k * period + width)."""
    k = torch.floor(x / period)
    return k * width + (x - k * period).clamp(max=width)


def stripes(x: Tensor, period: float | Tensor, width: float | Tensor, footprint: Tensor) -> Tensor:
    """Coverage in [0, 1] of stripes [k P, k P + w) by a box filter of size `footprint` centred at x."""
    f = footprint.clamp_min(1e-6)
    hi = _stripe_integral(x + f / 2, period, width)
    lo = _stripe_integral(x - f / 2, period, width)
    return ((hi - lo) / f).clamp(0.0, 1.0)


def band(x: Tensor, lo: float | Tensor, hi: float | Tensor, footprint: Tensor) -> Tensor:
    """Coverage in [0, 1] of the interval [lo, hi) by a box filter of size `footprint` centred at x."""
    f = footprint.clamp_min(1e-6)
    a = torch.maximum(x - f / 2, torch.as_tensor(lo, dtype=x.dtype))
    b = torch.minimum(x + f / 2, torch.as_tensor(hi, dtype=x.dtype))
    return ((b - a) / f).clamp(0.0, 1.0)
