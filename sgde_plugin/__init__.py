"""sgde-plugin: Stereo Guided Depth Estimation for 360-degree camera rigs."""

from __future__ import annotations

__version__ = "0.1.0"
