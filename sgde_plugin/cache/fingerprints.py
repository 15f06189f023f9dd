"""Cache fingerprints: what a prior depends on (rig calibration, prior settings, algorithm version).

A cache stores three digests per scene: `rig` (cameras with intrinsics and extrinsics, adjacent
pairs, ego masks), `config` (PriorConfig.to_dict(): every setting but the runtime ones (device,
batching), and for a learned matcher the SHA-256 of its model files and architecture source; the
prior algorithm version and the cache format) and `fingerprint` (both). Opening or extending a cache
with other inputs is refused.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any, Union

import numpy as np

from ..rig import Rig
from ..stereo.config import PRIOR_ALGO_VERSION, PriorConfig

# A PriorConfig, its `to_dict()` mapping, or None for the defaults.
ConfigLike = Union[PriorConfig, Mapping[str, Any], None]  # noqa: UP007 - a runtime alias on Python 3.10
CACHE_FORMAT = "sgde-prior-cache/1"
DIGEST_CHARS = 20


def _default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple | set | frozenset):
        return list(obj)
    return str(obj)


def canonical_json(obj: object) -> str:
    """Deterministic JSON text (sorted keys, no spaces) used for hashing."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_default)


def digest(obj: object) -> str:
    """Short SHA-256 hex digest of an object's canonical JSON."""
    return hashlib.sha256(canonical_json(obj).encode("utf-8")).hexdigest()[:DIGEST_CHARS]


def config_dict(config: ConfigLike) -> dict[str, Any]:
    """A PriorConfig (anything with `to_dict()`) or a mapping, as a plain JSON-able dict."""
    if config is None:
        config = PriorConfig()
    if hasattr(config, "to_dict"):
        config = config.to_dict()
    if not isinstance(config, Mapping):
        raise TypeError(f"config must be a PriorConfig or a mapping, not {type(config).__name__}")
    return json.loads(canonical_json(dict(config)))


def default_algo_version() -> str:
    """The prior algorithm version of the installed code (PRIOR_ALGO_VERSION)."""
    return str(PRIOR_ALGO_VERSION)


def rig_document(rig: Rig) -> dict[str, Any]:
    """Everything about a rig that changes its priors: cameras, pairs (order-free), mask contents."""
    masks = {}
    for name, path in sorted(dict(getattr(rig, "masks", {}) or {}).items()):
        masks[name] = hashlib.sha256(open(path, "rb").read()).hexdigest()  # noqa: SIM115 - small file
    pairs = sorted(sorted(p) for p in rig.pairs)
    return {"cameras": [c.to_dict() for c in rig.cameras], "pairs": pairs, "masks": masks}


def config_document(config: ConfigLike, algo_version: str | None = None) -> dict[str, Any]:
    """Everything about the prior computation that changes its output."""
    version = default_algo_version() if algo_version is None else str(algo_version)
    return {"config": config_dict(config), "algo_version": version, "cache_format": CACHE_FORMAT}


def fingerprint_parts(rig: Rig, config: ConfigLike = None, algo_version: str | None = None) -> dict[str, str]:
    """The three digests {'rig', 'config', 'fingerprint'} of a rig built with a configuration."""
    rig_fp = digest(rig_document(rig))
    cfg_fp = digest(config_document(config, algo_version))
    return {"rig": rig_fp, "config": cfg_fp, "fingerprint": digest({"rig": rig_fp, "config": cfg_fp})}


def fingerprint(rig: Rig, config: ConfigLike = None, algo_version: str | None = None) -> str:
    """Fingerprint of the priors of `rig` computed with `config` (calibration + settings + versions)."""
    return fingerprint_parts(rig, config, algo_version)["fingerprint"]


def describe_config_change(cached: Mapping[str, Any], asked: Mapping[str, Any]) -> str:
    """A short human description of how two config documents differ (for the refusal line)."""
    parts = []
    for key in ("algo_version", "cache_format"):
        if cached.get(key) != asked.get(key):
            parts.append(f"{key} {cached.get(key)!r} -> {asked.get(key)!r}")
    a, b = cached.get("config", {}), asked.get("config", {})
    for key in sorted(set(a) | set(b)):
        if a.get(key) != b.get(key):
            parts.append(f"{key} {a.get(key)!r} -> {b.get(key)!r}")
    return ", ".join(parts) if parts else "settings differ"


__all__ = [
    "CACHE_FORMAT",
    "canonical_json",
    "config_dict",
    "config_document",
    "default_algo_version",
    "describe_config_change",
    "digest",
    "fingerprint",
    "fingerprint_parts",
    "rig_document",
]
