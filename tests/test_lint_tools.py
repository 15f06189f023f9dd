"""The complexity gate of `make lint` (tools/complexity.py) flags what it should and honours its allow-list."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("complexity_gate", ROOT / "tools" / "complexity.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _tree(tmp_path: Path) -> Path:
    pkg = tmp_path / "sgde_plugin"
    pkg.mkdir()
    branches = "\n".join(f"    if x == {i}:\n        return {i}" for i in range(25))  # complexity 26
    long_body = "\n".join(f"    y{i} = {i}" for i in range(85))  # 87 lines, complexity 1
    (pkg / "m.py").write_text(
        f"def branchy(x):\n{branches}\n    return -1\n\n\n"
        f"def long():\n{long_body}\n    return 0\n\n\n"
        "def fine(x):\n    return x + 1\n"
    )
    return tmp_path


def test_flags_complex_and_long_functions(tmp_path):
    mod = _module()
    found, stale = mod.offenders(_tree(tmp_path), set())
    names = sorted(line.split(": complexity")[0] for line in found)
    assert names == ["sgde_plugin/m.py:branchy", "sgde_plugin/m.py:long"]
    assert "complexity 26" in [f for f in found if "branchy" in f][0]
    assert stale == []


def test_allow_list_and_stale_entries(tmp_path):
    mod = _module()
    allowed = {"sgde_plugin/m.py:branchy", "sgde_plugin/m.py:fine"}
    found, stale = mod.offenders(_tree(tmp_path), allowed)
    assert [f.split(": complexity")[0] for f in found] == ["sgde_plugin/m.py:long"]
    assert stale == ["sgde_plugin/m.py:fine"]
