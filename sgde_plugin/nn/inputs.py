"""Checks of what callers hand to the nets and adapters: one clear error naming the argument."""

from __future__ import annotations

from torch import Tensor


def require_tensor(name: str, value: object) -> Tensor:
    """``value`` itself when it is a tensor; a TypeError naming ``name`` otherwise."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value
