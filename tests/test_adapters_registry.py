"""mmdet3d registration: registers with a (faked) mmdet3d, and costs and breaks nothing without it."""

from __future__ import annotations

import importlib
import subprocess
import sys
import types

from sgde_plugin.adapters import registry


class _FakeRegistry:
    def __init__(self) -> None:
        self.modules: dict[str, type] = {}

    def register_module(self, name=None, module=None, force=False):
        if name in self.modules and not force:
            raise KeyError(name)
        self.modules[name] = module
        return module

    def build(self, cfg):
        cfg = dict(cfg)
        return self.modules[cfg.pop("type")](**cfg)


def _fake_mmdet3d(monkeypatch) -> _FakeRegistry:
    reg = _FakeRegistry()
    mmdet3d = types.ModuleType("mmdet3d")
    mmdet3d_registry = types.ModuleType("mmdet3d.registry")
    mmdet3d_registry.MODELS = reg
    mmdet3d.registry = mmdet3d_registry
    monkeypatch.setitem(sys.modules, "mmengine", types.ModuleType("mmengine"))
    monkeypatch.setitem(sys.modules, "mmdet3d", mmdet3d)
    monkeypatch.setitem(sys.modules, "mmdet3d.registry", mmdet3d_registry)
    return reg


def test_registers_in_mmdet3d_models_when_available(monkeypatch):
    reg = _fake_mmdet3d(monkeypatch)
    importlib.reload(registry)  # importing the registry module registers (config custom_imports path)
    from sgde_plugin.adapters import DepthToVoxelProposals, PriorDepthNet

    assert reg.modules == {"SGDEPriorDepthNet": PriorDepthNet, "SGDEPriorInjector": registry.inject_prior_from_config,
                           "SGDEDepthToVoxelProposals": DepthToVoxelProposals}
    # a config wraps a depth net built from its own config: the net itself comes back, with a prior path
    net = reg.build({"type": "SGDEPriorInjector", "in_channels": 8,
                     "depth_net": {"type": "SGDEPriorDepthNet", "in_channels": 8, "mid_channels": 8,
                                   "context_channels": 4, "depth_channels": 112, "use_prior": False}})
    assert isinstance(net, PriorDepthNet) and hasattr(net, "sgde_prior")
    # registering again (re-import) is harmless, and importing the package registers too
    reg.modules.clear()
    import sgde_plugin.adapters as adapters

    importlib.reload(adapters)
    assert set(reg.modules) == {"SGDEPriorDepthNet", "SGDEPriorInjector", "SGDEDepthToVoxelProposals"}


def test_without_mmdet3d_nothing_is_registered_and_nothing_fails(monkeypatch):
    # this environment has no mmdet3d installed
    assert not registry.mmdet3d_available()
    assert registry.register_mmdet3d() == []
    monkeypatch.setitem(sys.modules, "mmdet3d", None)  # import of mmdet3d fails like a missing package
    assert registry.register_mmdet3d() == []
    assert registry.register_if_loaded() == []


def test_importing_the_adapters_loads_neither_mmdet3d_nor_the_modules():
    code = ("import sys; import sgde_plugin.adapters as a; import sgde_plugin.adapters.registry; "
            "bad = [m for m in ('mmdet3d', 'mmengine', 'mmcv', 'sgde_plugin.adapters.bevdepth') if m in sys.modules]; "
            "assert not bad, bad; assert a.PriorDepthNet.__name__ == 'PriorDepthNet'; print('ok')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"
