"""In-graph normalisation of a metric depth prior for use as a network input channel."""

from __future__ import annotations

import torch
from torch import nn


class PriorEncoding(nn.Module):
    """Map a metric prior [B,1,H,W] (0 = no prior) to depth/max_depth in [0,1] (+ optional validity).

    The prior is never normalised with RGB statistics: pixels without a prior stay exactly 0 so a
    widened stem sees the same input as the original network wherever there is no overlap.
    The computation is branch-free so it exports to ONNX unchanged.
    """

    def __init__(self, max_depth: float = 80.0, with_validity: bool = False) -> None:
        super().__init__()
        if not max_depth > 0:
            raise ValueError(f"max_depth must be positive, got {max_depth}")
        self.max_depth = float(max_depth)
        self.with_validity = bool(with_validity)

    @property
    def out_channels(self) -> int:
        """Number of channels produced (1, or 2 with the validity channel)."""
        return 2 if self.with_validity else 1

    def forward(self, prior: torch.Tensor) -> torch.Tensor:
        """Encode ``prior`` [B,1,H,W] in metres; returns [B,1 or 2,H,W] in the prior's dtype."""
        valid = (prior > 0).to(prior.dtype)
        # clamp(min=0) also maps negative or NaN-free garbage below zero to "no prior"
        encoded = torch.clamp(prior / self.max_depth, 0.0, 1.0) * valid
        if self.with_validity:
            return torch.cat([encoded, valid], dim=1)
        return encoded

    def extra_repr(self) -> str:
        """Constructor arguments for printing."""
        return f"max_depth={self.max_depth}, with_validity={self.with_validity}"
