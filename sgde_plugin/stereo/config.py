"""Prior settings (`PriorConfig`), nested by concern: matcher, SGBM, geometry, images, filters, confidence.

Each group is a small frozen dataclass. Files, presets, the command line and the cache fingerprint
use the flat setting names (`SETTINGS`: "block_size", "matcher_path", "min_confidence", ...), which
stay what they were before the nesting, so a cache's fingerprint does not depend on how the code
groups the settings. `PriorConfig.from_settings` takes flat names and/or group mappings;
`settings()` gives the flat names back; `to_dict()` is the fingerprint document (flat names).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

from ..errors import InputError
from .filters import NORMALIZATIONS
from .matchers import Matcher, SGBMMatcher, load_learned_matcher, model_digests

PRIOR_ALGO_VERSION = "1"
# the value of one setting
Setting = Union[str, int, float, bool, dict[str, Any], None]  # noqa: UP007 - a runtime alias on Python 3.10

MATCHERS = ("sgbm", "planesweep", "raft-stereo", "torch", "onnx")
LEARNED_MATCHERS = MATCHERS[2:]
# matchers of the original views (no rectified pair): `stereo.planesweep`
SWEEP_MATCHERS = ("planesweep",)
FISHEYE_PATHS = ("direct", "virtual", "tiled")
DEVICES = ("cpu", "cuda")
# settings that change how a prior is computed, not what it is (device, batching): not fingerprinted
RUNTIME_FIELDS = ("device", "matcher_batch")
# settings whose default (None) depends on the matcher: SGBM's value, a learned matcher's value
MATCHER_DEFAULTS: dict[str, tuple[bool | int | float, bool | int | float]] = {
    "color": (False, True),  # learned matchers were trained on RGB
    "refine_iterations": (1, 0),  # the Gauss-Newton step undoes SGBM's pixel locking, and hurts learned output
    "min_texture": (0.5, 0.0),  # learned matchers fill weakly textured rows from context
}


@dataclass(frozen=True)
class MatcherSettings:
    """Which matcher computes the disparities, and how a learned one is loaded and run."""

    name: str = "sgbm"  # "sgbm"; "planesweep" (original views, `sweep` settings);
    #                     learned: "raft-stereo" (official checkpoint), "torch", "onnx"
    path: str | None = None  # learned matchers: checkpoint / TorchScript / ONNX file
    arch: str | None = None  # "pkg.module:factory" building the module of a torch state dict
    options: dict[str, Any] = field(default_factory=dict)  # factory keywords / RAFT-Stereo args
    iters: int | None = None  # learned: forward(..., iters=N); raft-stereo default 32 (its demo's)
    input_scale: float = 1.0  # learned matchers: multiply [0, 255] pixels by this
    flow_output: bool | None = None  # output is a flow (disparity = -x); raft-stereo: True
    pad: int = 32  # learned matchers: pad the input (edge values, centred) to multiples of this
    device: str = "cpu"  # learned matchers: "cpu" or "cuda" (torch device / onnxruntime provider)
    batch: int = 2  # learned matchers: images per forward call (same-size inputs of one frame)

    @property
    def learned(self) -> bool:
        """True for a learned matcher (anything but SGBM)."""
        return self.name in LEARNED_MATCHERS


@dataclass(frozen=True)
class SGBMSettings:
    """OpenCV SGBM's parameters (tuned on the synthetic world); `block_size` also sets the border kept clear."""

    block_size: int = 3
    p1: int = 8
    p2: int = 32
    uniqueness: int = 15
    speckle_window: int = 100
    speckle_range: int = 2


@dataclass(frozen=True)
class SweepSettings:
    """The plane sweep between the original views (`matcher: planesweep`, `stereo.planesweep`)."""

    planes: int = 256  # most depth planes (uniform in inverse depth); fewer when the parallax range is smaller
    step_px: float = 1.0  # parallax between neighbouring planes, view pixels (f B x the inverse-depth step)
    window: int = 7  # ZNCC window, odd
    paths: int = 4  # semi-global aggregation: 0 (the ZNCC window alone), 2 (along rows) or 4 (rows and columns)
    p1: float = 0.05  # penalty of a one-plane step between neighbours, in 1 - ZNCC units
    p2: float = 0.3  # penalty of a larger step
    uniqueness: float = 0.05  # the best cost beyond the winner's neighbours must exceed (1 + this) x the winner's


@dataclass(frozen=True)
class GeometrySettings:
    """The rectified canvases: matching resolution, depth range (sets the search range), extent, fisheye path."""

    scale: float = 0.5  # matching resolution relative to the source cameras
    min_depth: float = 1.5
    max_depth: float = 80.0
    margin_px: int = 8
    max_azimuth_deg: float = 60.0  # rectified canvas half-angles (matter for fisheyes only; with `fisheye: tiled`,
    max_elevation_deg: float = 50.0  # the elevation one is each tile's, about the baseline)
    fisheye: str = "tiled"  # "tiled": remap straight from the fisheye into as many canvases turned about the
    #                         baseline as the shared field needs (`planning.baseline_tiles`; pairs without a
    #                         fisheye, and fisheye pairs one canvas holds, as "direct"); "direct": one canvas per
    #                         pair (the field beyond +-max_elevation_deg about the baseline is not matched);
    #                         "virtual": via virtual pinholes


@dataclass(frozen=True)
class ImageSettings:
    """How the images are prepared before they are matched."""

    color: bool | None = None  # match RGB instead of grey; SGBM False, learned True
    antialias: bool = False  # low-pass each image before it is resampled at `scale` (Gaussian, decimation sigma)
    normalize: str = "none"  # per-overlap photometric normalisation before matching: "none", "gain", "local"
    normalize_sigma: float = 8.0  # "local": Gaussian window of the local mean and contrast, rectified px


@dataclass(frozen=True)
class FilterSettings:
    """The checks a disparity must pass after matching."""

    lr_max_diff: float = 1.0  # left-right consistency, rectified pixels
    border_px: int = 2  # matches this far (+ half a block) from an image border are dropped
    refine_iterations: int | None = None  # sub-pixel Gauss-Newton steps after matching (0 = off); SGBM 1, learned 0
    min_zncc: float = 0.5  # photometric check after the shift (7x7 windows): ZNCC above this,
    max_abs_diff: float = 8.0  # mean absolute difference (grey levels) below this,
    min_texture: float | None = None  # RMS x-gradient (grey levels / px) above this (full confidence at 2x);
    #                                   0 = off; SGBM 0.5, learned 0
    min_region_px: int = 200  # final speckle filter: smallest region of similar disparity kept
    ground_depth_ratio: float = 1.5  # > 0: a match farther than this times the depth at which its ray meets the
    #                                  ground (the plane ego z = 0) is dropped; 0 = off (ego origin not on the ground)


@dataclass(frozen=True)
class ConfidenceSettings:
    """How a surviving disparity's confidence is scaled, and the confidence a fused value needs."""

    disparity_px: float = 2.0  # confidence x d / (d + this): small disparities give uncertain depth
    edge_jump_px: float = 0.0  # > 0: confidence x jump / local disparity range where that range exceeds it
    min_confidence: float = 0.0  # fused values whose confidence is below this are dropped (real-camera presets 0.2)
    edge_depth_ratio: float = 0.0  # > 0: fused confidence x a factor falling from 1 at a local depth ratio of
    #                                1 + this to 0 at 1 + 5x this (occlusion edges); 0 = off (real cameras 0.1)
    edge_window_px: int = 15  # the window of that ratio, source-camera pixels


GROUPS: dict[str, type] = {
    "matcher": MatcherSettings, "sgbm": SGBMSettings, "sweep": SweepSettings, "geometry": GeometrySettings,
    "images": ImageSettings,
    "filters": FilterSettings, "confidence": ConfidenceSettings,
}
# flat names that are not the group field's own name (the matcher group's are "matcher_<field>")
_FLAT_NAMES = {("matcher", "name"): "matcher", ("matcher", "device"): "device",
               ("confidence", "disparity_px"): "confidence_disparity_px"}


# margins, borders and smoothing windows, rectified px: more only blanks or bloats a canvas (an absurd
# value made OpenCV / torch allocate tens of GB); real settings are a few to a few tens of pixels
MAX_PAD_PX = 1024
# tan(elevation) / tan(azimuth) of the rectified canvas: its shared sector is found on a grid of 241 columns and
# this many times as many rows (1 deg x 89 deg asked for 190 million directions, several GB)
MAX_CANVAS_ASPECT = 16
# the cache stores depths as float16: what it can hold without clipping (a depth outside would be served clipped)
FLOAT16_MAX = 65504.0
FLOAT16_MIN_POSITIVE = 6.2e-5  # smallest normal float16, so a valid depth never rounds to 0
# flat setting -> (the values the code can use, the problem otherwise): checked before any work starts
RANGES: dict[str, tuple[Callable[[float], bool], str]] = {
    # SGBM (OpenCV): penalties and counts are non-negative; uniqueness is a percentage
    "p1": (lambda v: v >= 0, "must not be negative"),
    "uniqueness": (lambda v: 0 <= v <= 100, "must be in [0, 100] (percent)"),
    "speckle_window": (lambda v: v >= 0, "must not be negative (0 = off)"),
    "speckle_range": (lambda v: v >= 0, "must not be negative"),
    # the rectified canvas is a tangent plane: its half-angles are tan()'d and cannot reach 90 degrees
    "max_azimuth_deg": (lambda v: 0 < v < 90, "must be in (0, 90) degrees"),
    "max_elevation_deg": (lambda v: 0 < v < 90, "must be in (0, 90) degrees"),
    "margin_px": (lambda v: 0 <= v <= MAX_PAD_PX, f"must be in [0, {MAX_PAD_PX}] pixels"),
    "border_px": (lambda v: 0 <= v <= MAX_PAD_PX, f"must be in [0, {MAX_PAD_PX}] pixels"),
    "normalize_sigma": (lambda v: 0 < v <= MAX_PAD_PX, f"must be in (0, {MAX_PAD_PX}] pixels (a Gaussian sigma)"),
    # divisors: the left-right disagreement / lr_max_diff, d / (d + confidence_disparity_px), the
    # photometric factors (ncc - min_zncc) / (1 - min_zncc) and mad / max_abs_diff
    "lr_max_diff": (lambda v: v > 0, "must be positive (pixels)"),
    "confidence_disparity_px": (lambda v: v > 0, "must be positive (pixels)"),
    "min_zncc": (lambda v: -1 <= v < 1, "must be in [-1, 1) (a correlation)"),
    "edge_jump_px": (lambda v: v >= 0, "must not be negative (0 = off)"),
    # learned matchers see [0, 255] pixels times this: zero or negative gives them blank or inverted images
    "matcher_input_scale": (lambda v: v > 0, "must be positive"),
    "max_abs_diff": (lambda v: v > 0, "must be positive (grey levels)"),
    "min_depth": (lambda v: v >= FLOAT16_MIN_POSITIVE,
                  f"must be at least {FLOAT16_MIN_POSITIVE:g} m (the cache stores float16 depths)"),
    "max_depth": (lambda v: v <= FLOAT16_MAX, f"must be at most {FLOAT16_MAX:g} m (the cache stores float16 depths)"),
}


_PREFIXED = ("matcher", "sweep")  # groups whose flat names are "<group>_<field>"


def _flat_name(group: str, name: str) -> str:
    """The flat setting name of a group field."""
    return _FLAT_NAMES.get((group, name), f"{group}_{name}" if group in _PREFIXED else name)


# flat setting name -> (group, field), in the groups' order
SETTINGS: dict[str, tuple[str, str]] = {
    _flat_name(group, f.name): (group, f.name) for group, cls in GROUPS.items() for f in dataclasses.fields(cls)
}


def setting_type(name: str) -> str:
    """The annotation of a flat setting, such as 'float | None'."""
    group, leaf = SETTINGS[name]
    return str({f.name: f for f in dataclasses.fields(GROUPS[group])}[leaf].type)


def flatten_settings(values: Mapping[str, Any], source: str | Path | None = None) -> dict[str, Any]:
    """Flat and nested settings as one flat mapping: `{"sgbm": {"p1": 4}, "max_depth": 90}` ->
    `{"p1": 4, "max_depth": 90}`. A group's value is a mapping or a group dataclass; `matcher` may be a
    name (flat) or a mapping (the group). Unknown keys and a setting given twice are refused."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if key in GROUPS and (isinstance(value, Mapping) or dataclasses.is_dataclass(value)):
            inner = value if isinstance(value, Mapping) else dataclasses.asdict(value)
            pairs = []
            for leaf, v in inner.items():
                flat = _flat_name(key, str(leaf))
                if SETTINGS.get(flat) != (key, leaf):
                    raise InputError(source, f"{key}.{leaf}", "unknown setting (see PriorConfig's groups)")
                pairs.append((flat, v))
        elif key in SETTINGS:
            pairs = [(key, value)]
        else:
            raise InputError(source, str(key), "unknown setting (see `sgde prior --help` or stereo.config.SETTINGS)")
        for flat, v in pairs:
            if flat in out:
                raise InputError(source, flat, "given twice (flat and in its group)")
            out[flat] = v
    return out


@dataclass(frozen=True)
class PriorConfig:
    """Everything that changes the prior, by concern: matcher, SGBM, geometry, images, filters, confidence.

    Fields left at None take the matcher's own default (see MATCHER_DEFAULTS): after construction
    they hold the resolved value, so readers never see None. Build one from flat setting names with
    `PriorConfig.from_settings(max_depth=200.0)`; `sgde prior --config FILE --preset NAME` reaches every
    setting (sgde_plugin.stereo.presets).
    """

    matcher: MatcherSettings = field(default_factory=MatcherSettings)
    sgbm: SGBMSettings = field(default_factory=SGBMSettings)
    sweep: SweepSettings = field(default_factory=SweepSettings)
    geometry: GeometrySettings = field(default_factory=GeometrySettings)
    images: ImageSettings = field(default_factory=ImageSettings)
    filters: FilterSettings = field(default_factory=FilterSettings)
    confidence: ConfidenceSettings = field(default_factory=ConfidenceSettings)

    def __post_init__(self) -> None:
        for group, cls in GROUPS.items():
            if not isinstance(getattr(self, group), cls):
                raise TypeError(f"PriorConfig.{group} must be a {cls.__name__} (flat names: PriorConfig.from_settings)")
        if self.matcher.name not in MATCHERS:
            raise InputError(None, "matcher", f"unknown matcher {self.matcher.name!r} (expected {', '.join(MATCHERS)})")
        self._resolve_defaults()
        self._check()
        self._check_sweep()

    @classmethod
    def from_settings(cls, values: Mapping[str, Any] | None = None, /, **more: Setting) -> PriorConfig:
        """A config from flat setting names and/or group mappings (`values` and keywords together)."""
        flat = flatten_settings({**(values or {}), **more})
        groups: dict[str, dict[str, Any]] = {group: {} for group in GROUPS}
        for name, value in flat.items():
            group, leaf = SETTINGS[name]
            groups[group][leaf] = value
        return cls(**{group: GROUPS[group](**kwargs) for group, kwargs in groups.items()})

    def _set(self, name: str, value: Setting) -> None:
        """Set one flat setting during construction (the groups are frozen)."""
        group, leaf = SETTINGS[name]
        object.__setattr__(self, group, dataclasses.replace(getattr(self, group), **{leaf: value}))

    def _resolve_defaults(self) -> None:
        """Replace the None of matcher-dependent settings by the matcher's default."""
        learned = self.learned
        for name, (sgbm, nn) in MATCHER_DEFAULTS.items():
            if self.get(name) is None:
                self._set(name, nn if learned else sgbm)
        if self.matcher.flow_output is None:
            self._set("matcher_flow_output", self.matcher.name == "raft-stereo")
        if self.matcher.iters is None and self.matcher.name == "raft-stereo":
            self._set("matcher_iters", 32)
        self._set("matcher_options", dict(self.matcher.options or {}))

    def _check_model_file(self) -> None:
        """A learned matcher needs a model file; any other refuses one (a forgotten --matcher would otherwise
        build an SGBM prior silently)."""
        m = self.matcher
        if self.learned and not m.path:
            raise InputError(None, "matcher_path", f"matcher {m.name!r} needs a model file")
        if not self.learned and m.path:
            raise InputError(None, "matcher_path", f"matcher {m.name!r} takes no model file (the learned ones do: "
                                                   f"{', '.join(sorted(LEARNED_MATCHERS))})")

    def _check(self) -> None:
        """One-line InputError for a value out of its range (named by its flat setting name)."""
        m, g = self.matcher, self.geometry
        self._check_model_file()
        for name, value, allowed in (("normalize", self.images.normalize, NORMALIZATIONS),
                                     ("fisheye", g.fisheye, FISHEYE_PATHS), ("device", m.device, DEVICES)):
            if value not in allowed:
                got = f", got {value!r}" if name == "device" else ""
                raise InputError(None, name, f"expected one of {', '.join(allowed)}{got}")
        if not 0 <= self.confidence.min_confidence < 1:
            raise InputError(None, "min_confidence", "must be in [0, 1)")
        if not 0 < g.scale <= 2:
            raise InputError(None, "scale", "must be in (0, 2]")
        if not 0 < g.min_depth < g.max_depth:
            raise InputError(None, "min_depth/max_depth", "need 0 < min_depth < max_depth")
        if self.filters.ground_depth_ratio != 0 and not self.filters.ground_depth_ratio >= 1:
            raise InputError(None, "ground_depth_ratio", "must be 0 (off) or at least 1")
        if self.confidence.edge_depth_ratio < 0:
            raise InputError(None, "edge_depth_ratio", "must not be negative")
        for name in ("block_size", "matcher_batch", "matcher_pad", "edge_window_px"):
            if self.get(name) < 1:
                raise InputError(None, name, "must be at least 1")
        if self.sgbm.block_size % 2 == 0:
            raise InputError(None, "block_size", "must be odd")
        if m.iters is not None and m.iters < 1:
            raise InputError(None, "matcher_iters", "must be at least 1")
        for name in ("refine_iterations", "min_region_px", "min_texture"):
            if self.get(name) < 0:
                raise InputError(None, name, "must not be negative")
        self._check_ranges()

    def _check_ranges(self) -> None:
        """One-line InputError for a setting outside `RANGES`, or SGBM penalties OpenCV cannot use."""
        for name, (ok, problem) in RANGES.items():
            value = self.get(name)
            if not ok(value):
                raise InputError(None, name, f"{problem}, got {value!r}")
        el, az = (math.radians(self.get(k)) for k in ("max_elevation_deg", "max_azimuth_deg"))
        aspect = math.tan(el) / math.tan(az)
        if aspect > MAX_CANVAS_ASPECT:  # the canvas's sector is sampled on a grid of this aspect
            raise InputError(None, "max_elevation_deg", f"tan(max_elevation_deg) / tan(max_azimuth_deg) must be at "
                             f"most {MAX_CANVAS_ASPECT}, got {aspect:.3g}")
        if not self.sgbm.p2 > self.sgbm.p1:
            raise InputError(None, "p2", f"must be greater than p1 (OpenCV SGBM needs P2 > P1), got p1 = "
                             f"{self.sgbm.p1!r}, p2 = {self.sgbm.p2!r}")

    @property
    def learned(self) -> bool:
        """True for a learned matcher (anything but SGBM)."""
        return self.matcher.learned

    def _check_sweep(self) -> None:
        """`_check` for the plane sweep's settings."""
        sw = self.sweep
        if sw.window < 3 or sw.window % 2 == 0:
            raise InputError(None, "sweep_window", "must be odd and at least 3")
        if sw.paths not in (0, 2, 4):
            raise InputError(None, "sweep_paths", "expected 0, 2 or 4")
        if sw.planes < 4:
            raise InputError(None, "sweep_planes", "must be at least 4")
        if not sw.step_px > 0:
            raise InputError(None, "sweep_step_px", "must be positive")
        for name in ("sweep_p1", "sweep_p2", "sweep_uniqueness"):
            if self.get(name) < 0:
                raise InputError(None, name, "must not be negative")

    @property
    def sweeps(self) -> bool:
        """True when pairs are matched by the plane sweep between the original views (no rectification)."""
        return self.matcher.name in SWEEP_MATCHERS

    def get(self, name: str) -> Setting:
        """The value of one flat setting, e.g. `config.get("block_size")`."""
        group, leaf = SETTINGS[name]
        return getattr(getattr(self, group), leaf)

    def settings(self) -> dict[str, Any]:
        """Every setting by flat name (resolved values): what `--config` files hold;
        `PriorConfig.from_settings(c.settings()) == c`."""
        return {name: self.get(name) for name in SETTINGS}

    def nested(self) -> dict[str, dict[str, Any]]:
        """Every setting by group and field name (resolved values): the nested form of a `--config` file."""
        return {group: dataclasses.asdict(getattr(self, group)) for group in GROUPS}

    def replace(self, **settings: Setting) -> PriorConfig:
        """A copy with some settings changed (flat names or group mappings)."""
        return PriorConfig.from_settings({**self.settings(), **flatten_settings(settings)})

    def to_dict(self) -> dict[str, Any]:
        """The fingerprint document: every setting by flat name (every group, whatever the matcher) but
        the runtime ones, the algorithm version and, for a learned matcher, the hashes of its model files
        and of its architecture's source code. Flat names keep fingerprints independent of the grouping."""
        d = {k: v for k, v in self.settings().items() if k not in RUNTIME_FIELDS}
        d["algo_version"] = PRIOR_ALGO_VERSION
        if self.learned:
            d.update(model_digests(self.matcher.name, self.matcher.path, self.matcher.arch))
        return d

    def make_matcher(self) -> Matcher:
        """The configured matcher of rectified pairs (the plane sweep has none: `stereo.planesweep` runs it)."""
        m, s = self.matcher, self.sgbm
        if self.sweeps:
            raise ValueError("the plane sweep matches the original views, not rectified pairs: PriorBuilder runs it")
        if m.name == "sgbm":
            return SGBMMatcher(
                block_size=s.block_size, p1=s.p1, p2=s.p2, uniqueness=s.uniqueness,
                speckle_window=s.speckle_window, speckle_range=s.speckle_range,
            )
        return load_learned_matcher(
            str(m.path), m.arch, m.input_scale, bool(m.flow_output), m.pad, kind=m.name, options=m.options,
            iters=m.iters, device=m.device, batch_size=m.batch,
        )


__all__ = [
    "GROUPS", "LEARNED_MATCHERS", "MATCHERS", "MATCHER_DEFAULTS", "MAX_PAD_PX", "PRIOR_ALGO_VERSION", "RANGES",
    "RUNTIME_FIELDS", "SETTINGS",
    "ConfidenceSettings", "FilterSettings", "GeometrySettings", "ImageSettings", "MatcherSettings", "PriorConfig",
    "SGBMSettings", "SWEEP_MATCHERS", "SweepSettings", "flatten_settings", "setting_type",
]
