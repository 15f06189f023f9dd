"""The demo's sizes and budgets: `sgde demo --help` reads their defaults without loading the demo's stages."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DemoSettings:
    """Sizes and budgets of the demo (defaults fit in about five minutes on two cores)."""

    preset: str = "nuscenes"
    frames: int = 7
    scale: float = 0.5
    seed: int = 0
    net_size: tuple[int, int] = (96, 160)
    train_steps: int = 300
    self_size: tuple[int, int] = (48, 80)  # the self-supervised arm: `sgde bench train-effect --supervision self`
    self_steps: int = 150
    methods: tuple[str, ...] = ("none", "glc")


__all__ = ["DemoSettings"]
