"""`load_rig(path)`: one entry point that recognises a data layout and returns a Rig.

A location is `PATH[::SELECTOR...]`, so a single string (a command's DIR) can name any of:

- sgde-rig/1: a folder with `rig.json`; no selectors. The `rig.json` file alone is refused (one line:
  the images, depths and masks live in its folder; `rig.read_rig_json` reads a file).
- nuScenes: the data root (holding `v1.0-mini/`, `v1.0-trainval/`...) or one table folder;
  selectors: a version (`v1.0-mini`), a scene name or token (`scene-0061`), `sweeps`.
- DDAD (DGP): a scene folder (`scene_<sha1>.json`), that file, or a root of scene folders;
  selector: a scene folder name (`000150`).
- Synthetic Urban / OmniMVS: a folder with `config.yaml`; no selectors.

Examples: `data/nuscenes::v1.0-mini::scene-0061`, `data/nuscenes/v1.0-trainval::scene-0103::sweeps`,
`data/ddad_train_val::000150`. The keyword arguments `version=`, `scene=`, `sweeps=` do the same as
the selectors. `load_rig` needs exactly one scene (a data set root with several asks you to pick
one, naming a few); `load_rigs` returns every selected scene and `list_scenes` only names them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..rig import Rig, read_rig_folder
from . import ddad, nuscenes, omnimvs

SEPARATOR = "::"
LAYOUTS = ("sgde-rig", "rig-json", "nuscenes", "ddad", "ddad-root", "omnimvs")
EXPECTED = ("expected an sgde-rig/1 folder (rig.json), a nuScenes root (v1.0-*/scene.json), "
            "a DDAD scene (scene_*.json) or a Synthetic Urban folder (config.yaml)")


@dataclass(frozen=True)
class Location:
    """A recognised layout: its kind, the path, and the version / scene / sweeps asked for."""

    layout: str
    path: Path
    version: str | None = None
    scene: str | None = None
    sweeps: bool = False


def _layout(path: Path) -> tuple[str, Path, str | None]:
    """(layout, path, version implied by the path) of a path without selectors."""
    if not path.exists():
        raise InputError(path, None, "does not exist")
    if path.is_file():
        if path.name.startswith("scene_") and path.suffix == ".json":
            return "ddad", path, None
        if path.suffix == ".json":
            return "rig-json", path, None
        raise InputError(path, None, f"not a recognised rig layout ({EXPECTED})")
    if (path / "rig.json").is_file():
        return "sgde-rig", path, None
    if nuscenes.is_tables_folder(path):
        return "nuscenes", path.parent, path.name
    if nuscenes.versions(path):
        return "nuscenes", path, None
    if ddad.is_scene_folder(path):
        return "ddad", path, None
    if omnimvs.is_omnimvs_folder(path):
        return "omnimvs", path, None
    if ddad.scene_folders(path):
        return "ddad-root", path, None
    raise InputError(path, None, f"not a recognised rig layout ({EXPECTED})")


def _apply_selectors(path: str | Path, layout: str, known: list[str], selectors: list[str],
                     version: str | None, scene: str | None, sweeps: bool) -> tuple[str | None, str | None, bool]:
    """(version, scene, sweeps) after the `::` selectors, each checked against the keyword choices."""
    for sel in selectors:
        if not sel:
            raise InputError(path, None, f"empty selector after {SEPARATOR!r}")
        if sel == "sweeps":
            sweeps = True
        elif layout == "nuscenes" and sel in known:
            if version not in (None, sel):
                raise InputError(path, "version", f"two versions asked for ({version}, {sel})")
            version = sel
        elif scene not in (None, sel):
            raise InputError(path, "scene", f"two scenes asked for ({scene}, {sel})")
        else:
            scene = sel
    return version, scene, sweeps


def _resolve_version(path: str | Path, base: str, layout: str, known: list[str], version: str | None) -> str | None:
    """The nuScenes version to read (the only one, or the one asked for); None for other layouts."""
    if layout != "nuscenes":
        if version is not None:
            raise InputError(path, "version", f"a {layout} layout has no versions")
        return None
    if version is None:
        if len(known) != 1:
            raise InputError(base, "version", f"holds {len(known)} versions ({', '.join(known)}); "
                             f"pick one with PATH{SEPARATOR}VERSION")
        return known[0]
    if version not in known:
        raise InputError(base, "version", f"no table folder {version!r} (found: {', '.join(known) or 'none'})")
    return version


def locate(path: str | Path, version: str | None = None, scene: str | None = None,
           sweeps: bool = False) -> Location:
    """Parse `PATH[::SELECTOR...]` plus keyword choices into a Location; InputError if they do not fit."""
    base, *selectors = str(path).split(SEPARATOR)
    layout, where, implied = _layout(Path(base))
    if implied is not None:
        if version not in (None, implied):
            raise InputError(base, "version", f"path is version {implied!r}, {version!r} was asked for")
        version = implied
    known = nuscenes.versions(where) if layout == "nuscenes" else []
    version, scene, sweeps = _apply_selectors(path, layout, known, selectors, version, scene, sweeps)
    if sweeps and layout != "nuscenes":
        raise InputError(path, "sweeps", "only nuScenes has sweeps")
    version = _resolve_version(path, base, layout, known, version)
    if scene is not None and layout not in ("nuscenes", "ddad-root"):
        raise InputError(path, "scene", f"a {layout} layout holds one scene; no scene selector")
    if layout == "ddad-root" and scene is not None and not ddad.is_scene_folder(where / scene):
        raise InputError(where / scene, None, "not a DDAD scene folder (no scene_*.json)")
    return Location(layout, where, version, scene, sweeps)


def list_scenes(path: str | Path, *, version: str | None = None) -> list[str]:
    """Names of the scenes a location holds (cheap: no big tables are read)."""
    loc = locate(path, version)
    if loc.layout == "nuscenes":
        table = nuscenes.scene_table(loc.path, loc.version)
        if loc.scene is None:
            return [name for name, _ in table]
        found = [name for name, token in table if loc.scene in (name, token)]
        if not found:
            raise InputError(loc.path / loc.version / "scene.json", "name", f"no scene {loc.scene!r}")
        return found
    if loc.layout == "ddad-root":
        return [loc.scene] if loc.scene else [p.name for p in ddad.scene_folders(loc.path)]
    if loc.layout in ("rig-json", "ddad") and loc.path.is_file():
        return [loc.path.stem] if loc.layout == "rig-json" else [loc.path.parent.name]
    return [loc.path.name]


def load_rigs(path: str | Path, check_images: bool = False, *, version: str | None = None,
              scene: str | None = None, sweeps: bool = False) -> list[Rig]:
    """Every scene a location selects, as Rigs (one for single-scene layouts)."""
    loc = locate(path, version, scene, sweeps)
    if loc.layout == "nuscenes":
        return nuscenes.load_nuscenes(loc.path, loc.version, loc.scene, loc.sweeps, check_images)
    if loc.layout == "ddad-root":
        folders = [loc.path / loc.scene] if loc.scene else ddad.scene_folders(loc.path)
        return [ddad.load_ddad_scene(f, check_images) for f in folders]
    return [_load_single(loc, check_images)]


def load_rig(path: str | Path, check_images: bool = False, *, version: str | None = None,
             scene: str | None = None, sweeps: bool = False) -> Rig:
    """Exactly one rig from any supported layout (see the module docstring for PATH::SELECTOR)."""
    loc = locate(path, version, scene, sweeps)
    if loc.layout in ("nuscenes", "ddad-root") and loc.scene is None:
        names = list_scenes(path, version=version)
        if len(names) != 1:
            some = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
            raise InputError(str(path), "scene", f"holds {len(names)} scenes ({some}); pick one with "
                             f"PATH{SEPARATOR}SCENE (list them with sgde_plugin.readers.list_scenes)")
        loc = Location(loc.layout, loc.path, loc.version, names[0], loc.sweeps)
    if loc.layout == "nuscenes":
        return nuscenes.load_nuscenes(loc.path, loc.version, loc.scene, loc.sweeps, check_images)[0]
    if loc.layout == "ddad-root":
        return ddad.load_ddad_scene(loc.path / loc.scene, check_images)
    return _load_single(loc, check_images)


def _load_single(loc: Location, check_images: bool) -> Rig:
    if loc.layout == "sgde-rig":
        return read_rig_folder(loc.path, check_images=check_images)
    if loc.layout == "rig-json":
        raise InputError(loc.path, None, "expected a rig folder (the folder holding rig.json), not a rig file")
    if loc.layout == "ddad":
        return ddad.load_ddad_scene(loc.path, check_images)
    return omnimvs.load_omnimvs(loc.path, check_images)


__all__ = ["LAYOUTS", "Location", "list_scenes", "load_rig", "load_rigs", "locate"]
