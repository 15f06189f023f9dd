"""In-graph normalisation of a metric depth prior for use as a network input channel."""

from __future__ import annotations

import torch
from torch import nn

PRIOR_FORMS = ("depth", "log")
LOG_REFERENCE_M = 10.0  # the "log" form's zero: a prior of 10 m encodes to 0
LOG_FLOOR_M = 0.5  # priors nearer than this are encoded as this depth by the "log" form


class PriorEncoding(nn.Module):
    """Map a metric prior [B,1,H,W] (0 = no prior) to a network input channel (+ optional validity).

    ``form="depth"`` (default): depth / max_depth in [0, 1]. ``form="log"``: log(depth / 10 m), depth
    clamped to [0.5 m, max_depth] (about -3 to +2 for 0.5-80 m: the spread of a normalised RGB channel, and
    equal relative depth errors are equal steps); it needs the validity channel, since a 10 m prior and
    "no prior" both encode to 0. Either way the prior is never normalised with RGB statistics: pixels
    without a prior stay exactly 0 so a widened stem sees the same input as the original network wherever
    there is no overlap. The computation is branch-free so it exports to ONNX unchanged.
    """

    def __init__(self, max_depth: float = 80.0, with_validity: bool = False, form: str = "depth") -> None:
        super().__init__()
        if not max_depth > 0:
            raise ValueError(f"max_depth must be positive, got {max_depth}")
        if form not in PRIOR_FORMS:
            raise ValueError(f"prior encoding form must be one of {PRIOR_FORMS}, got {form!r}")
        if form == "log" and not with_validity:
            raise ValueError("the 'log' prior encoding needs the validity channel (10 m and 'none' both encode to 0)")
        self.max_depth = float(max_depth)
        self.with_validity = bool(with_validity)
        self.form = form

    @property
    def out_channels(self) -> int:
        """Number of channels produced (1, or 2 with the validity channel)."""
        return 2 if self.with_validity else 1

    def forward(self, prior: torch.Tensor) -> torch.Tensor:
        """Encode ``prior`` [B,1,H,W] in metres; returns [B,1 or 2,H,W] in the prior's dtype."""
        valid = (prior > 0).to(prior.dtype)
        # clamp(min=0) also maps negative or NaN-free garbage below zero to "no prior"
        if self.form == "log":
            encoded = torch.log(torch.clamp(prior, LOG_FLOOR_M, self.max_depth) / LOG_REFERENCE_M) * valid
        else:
            encoded = torch.clamp(prior / self.max_depth, 0.0, 1.0) * valid
        if self.with_validity:
            return torch.cat([encoded, valid], dim=1)
        return encoded

    def decode(self, encoded: torch.Tensor) -> torch.Tensor:
        """Metres back from the first channel of `forward`'s output (0 where there is no prior; depths
        clamped by the encoding come back clamped)."""
        value = encoded[:, :1]
        if self.form == "log":
            return torch.exp(value) * LOG_REFERENCE_M * encoded[:, 1:2]
        return value * self.max_depth

    def extra_repr(self) -> str:
        """Constructor arguments for printing."""
        return f"max_depth={self.max_depth}, with_validity={self.with_validity}, form={self.form!r}"
