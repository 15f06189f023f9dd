"""`load_rig(path)`: one entry point that recognises a data layout and returns a Rig."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..rig import Rig, read_rig_folder, read_rig_json


def load_rig(path: str | Path, check_images: bool = False) -> Rig:
    """Load a rig from an `sgde-rig/1` folder or a `rig.json` file (other layouts: see readers)."""
    path = Path(path)
    if path.is_dir() and (path / "rig.json").exists():
        return read_rig_folder(path, check_images=check_images)
    if path.is_file() and path.suffix == ".json":
        return read_rig_json(path)
    if not path.exists():
        raise InputError(path, None, "does not exist")
    raise InputError(path, None, "not a recognised rig layout (expected an sgde-rig/1 folder with rig.json)")
