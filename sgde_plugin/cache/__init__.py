"""Prior cache: zarr store, builds, the read API and the training-side dataset.

Names are imported lazily, so `import sgde_plugin.cache` does not load zarr, OpenCV or torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "PriorCache": "store",
    "SceneWriter": "store",
    "fingerprint": "fingerprints",
    "fingerprint_parts": "fingerprints",
    "CACHE_FORMAT": "fingerprints",
    "build_cache": "build",
    "BuildReport": "build",
    "PriorCompute": "build",
    "PriorDataset": "dataset",
    "SyntheticPriorCompute": "synthetic",
    "cache_info": "inspection",
    "verify_cache": "inspection",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        module = importlib.import_module(f"{__name__}.{_EXPORTS[name]}")
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = sorted(_EXPORTS)
