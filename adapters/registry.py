"""mmdet3d registration of the adapter modules (only when mmengine and mmdet3d are importable).

Importing this module registers the adapters in ``mmdet3d.registry.MODELS`` if mmdet3d can be
imported, so a config can say ``custom_imports = dict(imports=["sgde_plugin.adapters.registry"])``.
Importing ``sgde_plugin.adapters`` itself never imports mmdet3d: it registers only when mmdet3d is
already loaded. Without mmdet3d nothing happens and nothing fails.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # types only: importing this registry for mmdet3d must stay light
    from torch import nn

REGISTERED_NAMES = {
    "SGDEPriorDepthNet": ("sgde_plugin.adapters.bevdepth", "PriorDepthNet"),
    "SGDEPriorInjector": ("sgde_plugin.adapters.registry", "inject_prior_from_config"),
    "SGDEDepthToVoxelProposals": ("sgde_plugin.adapters.voxformer", "DepthToVoxelProposals"),
}


def mmdet3d_available() -> bool:
    """True when both mmengine and mmdet3d can be imported (without importing them)."""
    for name in ("mmengine", "mmdet3d"):
        if name in sys.modules:
            continue
        try:
            if importlib.util.find_spec(name) is None:
                return False
        except (ImportError, ValueError):
            return False
    return True


def _models_registry() -> Any | None:
    try:
        return importlib.import_module("mmdet3d.registry").MODELS
    except (ImportError, AttributeError):
        return None


def inject_prior_from_config(depth_net: nn.Module | dict[str, Any], **kwargs: Any) -> nn.Module:
    """``inject_prior`` for configs: ``depth_net`` may be a module or a config dict built by mmdet3d's MODELS."""
    from .bevdepth import inject_prior

    if isinstance(depth_net, dict):
        registry = _models_registry()
        if registry is None:
            raise ValueError("depth_net is a config dict but mmdet3d's MODELS registry is not available")
        depth_net = registry.build(depth_net)
    return inject_prior(depth_net, **kwargs)


def register_mmdet3d() -> list[str]:
    """Register the adapters in mmdet3d's MODELS registry; returns the names registered (empty without mmdet3d)."""
    if not mmdet3d_available():
        return []
    registry = _models_registry()
    if registry is None:
        return []
    names = []
    for name, (module, attr) in REGISTERED_NAMES.items():
        cls = getattr(importlib.import_module(module), attr)
        registry.register_module(name=name, module=cls, force=True)
        names.append(name)
    return names


def register_if_loaded() -> list[str]:
    """Register only if mmdet3d is already imported (costs nothing otherwise); returns the names."""
    if "mmdet3d" not in sys.modules or "mmengine" not in sys.modules:
        return []
    return register_mmdet3d()


register_mmdet3d()
