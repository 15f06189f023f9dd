"""Dataset readers (nuScenes, DDAD, Synthetic Urban) into the common Rig; `load_rig` detects the layout."""

from __future__ import annotations

from .detect import list_scenes, load_rig, load_rigs, locate

__all__ = ["list_scenes", "load_rig", "load_rigs", "locate"]
