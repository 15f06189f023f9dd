"""sgde-plugin: Stereo Guided Depth Estimation for 360-degree camera rigs."""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# Imported on first use (PEP 562), so `import sgde_plugin` loads neither torch nor zarr.
_LAZY = {
    "PriorCache": "sgde_plugin.cache.store",
    "load_rig": "sgde_plugin.readers.detect",
    "load_rigs": "sgde_plugin.readers.detect",
    "list_scenes": "sgde_plugin.readers.detect",
    "Rig": "sgde_plugin.rig",
    "Camera": "sgde_plugin.cameras",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
