"""Prior settings from presets, YAML files and command-line overrides, checked setting by setting.

A `PriorConfig` is resolved in layers, later ones winning: the field defaults, a named per-data-set
preset (`PRESETS`), a YAML file (a mapping of flat setting names such as `block_size: 5`, or of
groups such as `sgbm: {block_size: 5}`, or both; it may name a `preset` itself), then explicit
overrides (the command line). An unknown key or a value of the wrong type is refused with one line
naming the file and the key. `save_prior_config` writes every setting (grouped), so
`load_prior_config(save_prior_config(c))` gives `c` back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError
from ..io import atomic_write_text
from .config import GROUPS, MATCHER_DEFAULTS, SETTINGS, PriorConfig, flatten_settings, setting_type

# Per-data-set settings over the field defaults (which are the synthetic world's, where they were tuned).
# Ground-truth ranges: DDAD's LiDAR reaches 200 m, nuScenes' evaluation stops at 80 m.
# Real cameras differ in exposure, gain and vignetting, and their images alias when resampled at half
# resolution: per-overlap local-contrast normalisation, a looser photometric check on the normalised
# images and a low-pass before resampling (measured on the DDAD sample, README "The prior on real frames").
# Occlusion edges carry most of the large errors on real frames: the confidence falls where the local depth
# ratio exceeds 1.1 (zero at 1.5). The edge factor and the threshold were chosen on DDAD scene_02 (GLC poses),
# random rigs seeds 10-19 and the synthetic presets together (each keeps >= 95 % of its synthetic coverage).
REAL_CAMERAS: dict[str, Any] = {"normalize": "local", "max_abs_diff": 30.0, "antialias": True,
                                "edge_depth_ratio": 0.1, "edge_window_px": 15, "min_confidence": 0.2}
PRESETS: dict[str, dict[str, Any]] = {
    "synthetic": {},
    "nuscenes": {"max_depth": 80.0, **REAL_CAMERAS},
    "ddad": {"max_depth": 200.0, **REAL_CAMERAS},
    "fisheye": {"fisheye": "tiled", "ground_depth_ratio": 0.0},
}
PRESET_KEY = "preset"
MATCHER_DEPENDENT = (*MATCHER_DEFAULTS, "matcher_flow_output", "matcher_iters")


def _kind(annotation: str) -> tuple[str, bool]:
    """(base type name, None allowed) of a setting's annotation such as 'float | None'."""
    parts = [p.strip() for p in annotation.split("|")]
    nullable = "None" in parts
    base = next((p for p in parts if p != "None"), "Any")
    return ("dict" if base.startswith("dict") else base), nullable


def _check_value(name: str, value: object, source: str | Path | None) -> object:
    """`value` for setting `name`, type-checked (ints accepted for floats); one-line InputError otherwise."""
    base, nullable = _kind(setting_type(name))
    if value is None:
        if nullable:
            return None
        raise InputError(source, name, "must not be empty")
    expected = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string",
                "dict": "a mapping"}.get(base)
    ok = {
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "bool": isinstance(value, bool),
        "str": isinstance(value, str),
        "dict": isinstance(value, Mapping),
    }.get(base, True)
    if not ok:
        raise InputError(source, name, f"expected {expected}, got {value!r}")
    if base == "float":
        if not math.isfinite(value):
            raise InputError(source, name, f"must be a finite number, got {value!r}")
        return float(value)
    if base == "dict":
        return dict(value)
    return value


def check_settings(values: Mapping[str, Any], source: str | Path | None = None) -> dict[str, Any]:
    """Validate a mapping of PriorConfig settings (flat names and/or groups): known keys, right types.
    Returns a plain dict of flat names."""
    return {key: _check_value(key, value, source) for key, value in flatten_settings(values, source).items()}


def preset_settings(name: str, source: str | Path | None = None) -> dict[str, Any]:
    """The settings of a named preset."""
    if name not in PRESETS:
        raise InputError(source, PRESET_KEY, f"unknown preset {name!r} (expected {', '.join(PRESETS)})")
    return dict(PRESETS[name])


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A YAML settings file as a checked mapping (its `preset` key, if any, kept)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(path, None, f"cannot read ({exc.strerror or exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(path, None, f"not valid YAML{where}") from None
    if doc is None:
        return {}
    if not isinstance(doc, Mapping):
        raise InputError(path, None, "expected a mapping of PriorConfig settings")
    for group in GROUPS:  # a group must be a mapping (a flat `matcher: NAME` is the matcher's name)
        if group != "matcher" and group in doc and not isinstance(doc[group], Mapping):
            raise InputError(path, group, f"expected a mapping of {group} settings, got {doc[group]!r}")
    preset = doc.get(PRESET_KEY)
    if preset is not None and not isinstance(preset, str):
        raise InputError(path, PRESET_KEY, f"expected a preset name, got {preset!r}")
    out = check_settings({k: v for k, v in doc.items() if k != PRESET_KEY}, path)
    if preset is not None:
        out[PRESET_KEY] = preset
    return out


def load_prior_config(
    file: str | Path | None = None, preset: str | None = None, overrides: Mapping[str, Any] | None = None
) -> PriorConfig:
    """PriorConfig from defaults < preset (argument, else the file's) < file < overrides (None values skipped)."""
    from_file = read_config_file(file) if file is not None else {}
    name = preset if preset is not None else from_file.pop(PRESET_KEY, None)
    from_file.pop(PRESET_KEY, None)
    settings: dict[str, Any] = preset_settings(name, file if preset is None else None) if name else {}
    settings.update(from_file)
    settings.update(check_settings({k: v for k, v in (overrides or {}).items() if v is not None}))
    try:
        return PriorConfig.from_settings(settings)
    except InputError as exc:
        key = exc.key
        blame = file if file is not None and key in from_file else None
        raise InputError(blame, key, exc.problem) from None


def save_prior_config(config: PriorConfig, path: str | Path) -> Path:
    """Write every setting of `config` as YAML (atomically); reading it back gives the same config."""
    settings = config.nested()
    plain = PriorConfig.from_settings(matcher=config.matcher.name, matcher_path=config.matcher.path)
    for name in MATCHER_DEPENDENT:  # null = "the matcher's default", so a file stays right when the matcher changes
        if config.get(name) == plain.get(name):
            group, leaf = SETTINGS[name]
            settings[group][leaf] = None
    text = "# sgde prior settings (PriorConfig, by group); null = the default; load with `sgde prior --config FILE`\n"
    text += yaml.safe_dump(settings, sort_keys=False, default_flow_style=None)
    atomic_write_text(Path(path), text)
    return Path(path)


__all__ = ["PRESETS", "check_settings", "load_prior_config", "preset_settings", "read_config_file",
           "save_prior_config"]
