"""How the prior reaches a depth net that a host stack calls without it: a ``mats_dict`` key, or a ``with`` block.

BEVDepth's ``BaseLSSFPN.forward`` calls ``_forward_single_sweep`` once per sweep, key sweep first, and
that calls ``depth_net(feat, mats_dict)`` with the same ``mats_dict`` every time (its matrices are
[B, num_sweeps, N, 4, 4]). A prior stored in that dict under ``PRIOR_KEY`` therefore reaches the depth
net unchanged; ``PriorFeed`` tells the calls apart by their order: the k-th call on one prior tensor is
sweep k. BEVDet and FB-OCC call their depth net with ``(x, mlp_input)`` only: there the prior is given
for the duration of the detector's forward with ``PriorFeed.given`` and the k-th call is frame k.

Shapes: [B, S, N, H, W] metres (one prior per sweep / frame), or [B, N, H, W] (key frame only). Frames
the prior does not cover (k >= S) get no prior, which is exactly the all-zero prior.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn

PRIOR_KEY = "sgde_prior"  # the documented key of the prior in BEVDepth's mats_dict


def frame_prior(prior: Tensor, k: int) -> Tensor | None:
    """The prior [B, N, H, W] of frame ``k`` from [B, S, N, H, W] or key-frame-only [B, N, H, W]; None if absent."""
    if prior.dim() == 4:
        return prior if k == 0 else None
    if prior.dim() == 5:
        return prior[:, k] if k < prior.shape[1] else None
    raise ValueError(f"{PRIOR_KEY} must be [B, S, N, H, W] or [B, N, H, W], got {list(prior.shape)}")


def _num_sweeps(mats_dict: Mapping[str, Any], prior: Tensor) -> int:
    intrins = mats_dict.get("intrin_mats")
    if isinstance(intrins, Tensor) and intrins.dim() == 5:
        return int(intrins.shape[1])
    return int(prior.shape[1]) if prior.dim() == 5 else 1


class PriorFeed:
    """Gives each call of a depth net the prior of its sweep / frame, by call order (see the module docstring)."""

    def __init__(self) -> None:
        self._prior: Tensor | None = None
        self._calls = 0
        self._pinned = False

    @contextmanager
    def given(self, prior: Tensor | None) -> Iterator[PriorFeed]:
        """In the block the k-th call gets frame k of ``prior`` ([B, S, N, H, W] or [B, N, H, W]); None: no prior."""
        if prior is None:
            yield self
            return
        frame_prior(prior, 0)  # shape check before anything runs
        self._prior, self._calls, self._pinned = prior, 0, True
        try:
            yield self
        finally:
            self._prior, self._calls, self._pinned = None, 0, False

    def next_prior(self, mats_dict: Mapping[str, Any] | None = None) -> Tensor | None:
        """The prior of this call: from ``given``, else from ``mats_dict[PRIOR_KEY]``; None without one."""
        if not self._pinned:
            prior = mats_dict.get(PRIOR_KEY) if isinstance(mats_dict, Mapping) else None
            if prior is None:
                return None
            if prior is not self._prior:  # a new batch: start at the key sweep
                self._prior, self._calls = prior, 0
        k = self._calls
        self._calls += 1
        current = frame_prior(self._prior, k)
        if not self._pinned and self._calls >= _num_sweeps(mats_dict, self._prior):
            self._prior, self._calls = None, 0  # forward done: hold no tensor, start over next time
        return current


def keep_missing_prior_path(module: nn.Module, name: str, reset: Callable[[nn.Module], object] | None = None) -> None:
    """Let ``module`` load a checkpoint without its ``name`` submodule (one saved before the prior existed).

    When no key of ``name`` is in the state dict, ``reset(submodule)`` runs (e.g. zero its last layer,
    so the loaded net computes what the checkpoint computed) and its own tensors fill the gap; a strict
    load then passes. This also works when a parent model loads a whole-detector checkpoint.
    """

    def hook(mod: nn.Module, state_dict: dict, prefix: str, *_: Any) -> None:
        sub_prefix = f"{prefix}{name}."
        if any(k.startswith(sub_prefix) for k in state_dict):
            return
        sub = getattr(mod, name, None)
        if sub is None:
            return
        if reset is not None:
            with torch.no_grad():
                reset(sub)
        for key, value in sub.state_dict().items():
            state_dict[sub_prefix + key] = value

    module.register_load_state_dict_pre_hook(hook)
