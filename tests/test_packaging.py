"""Both `pip install .` and `pip install -e .` expose sgde_plugin.adapters and sgde_plugin.export."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROBE = (
    "import sgde_plugin, sgde_plugin.adapters as a, sgde_plugin.export as e, sgde_plugin.cli as c;"
    "print(sgde_plugin.__file__); print(a.__file__); print(e.__file__)"
)


def _probe(cwd: Path, extra_path: str | None = None) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if extra_path:
        env["PYTHONPATH"] = extra_path
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=cwd, env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_editable_install_maps_top_level_folders(tmp_path: Path) -> None:
    # the test venv has the project installed with `pip install -e .`
    pkg, adapters, export = _probe(tmp_path)
    assert Path(pkg) == REPO / "sgde_plugin" / "__init__.py"
    assert Path(adapters) == REPO / "adapters" / "__init__.py"
    assert Path(export) == REPO / "export" / "__init__.py"


def test_regular_install_has_subpackages(tmp_path: Path) -> None:
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-compile",
         "--target", str(target), str(REPO)],
        check=True, capture_output=True, text=True,
    )
    assert not (target / "adapters").exists() and not (target / "export").exists(), "no generic top-level names"
    pkg, adapters, export = _probe(tmp_path, str(target))
    assert Path(adapters) == target / "sgde_plugin" / "adapters" / "__init__.py"
    assert Path(export) == target / "sgde_plugin" / "export" / "__init__.py"
    assert Path(pkg).parent == target / "sgde_plugin"
