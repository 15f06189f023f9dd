"""Acceptance rules of a calibrated window (the paper's): enough correspondences per pair (beta),
convergence within the iteration limit, and no relative translation moved more than alpha."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..rig import Rig

# beta: minimum correspondences (RANSAC inliers over the window) per adjacent pair
BETA_DDAD = 200
BETA_NUSCENES = 50
# The synthetic presets render textured streets; at scale 0.5 and T = 7 the weakest nuscenes pair
# (CAM_BACK_RIGHT-CAM_BACK) keeps about 300 inliers, so 100 rejects only clearly broken windows.
BETA_SYNTH = 100
BETA_DEFAULT = BETA_NUSCENES
ALPHA_M = 0.3
MAX_ITERATIONS = 200

RULES = ("min_correspondences", "not_converged", "translation_change", "non_finite")


@dataclass(frozen=True)
class AcceptanceRules:
    """Thresholds of the acceptance test."""

    min_correspondences: int = BETA_DEFAULT
    max_iterations: int = MAX_ITERATIONS
    max_translation_change_m: float = ALPHA_M

    def to_dict(self) -> dict:
        """JSON-able thresholds."""
        return {"beta": self.min_correspondences, "max_iterations": self.max_iterations,
                "alpha_m": self.max_translation_change_m}


def default_beta(rig: Rig) -> int:
    """beta for a rig: synthetic presets, DDAD (CAMERA_xx names), nuScenes (CAM_* names), else nuScenes'."""
    synth = rig.extra.get("synth") if isinstance(rig.extra, Mapping) else None
    if isinstance(synth, Mapping) and "preset" in synth:
        return BETA_SYNTH
    names = rig.camera_names
    if names and all(n.startswith("CAMERA_") for n in names):
        return BETA_DDAD
    if names and all(n.startswith("CAM_") for n in names):
        return BETA_NUSCENES
    return BETA_DEFAULT


@dataclass(frozen=True)
class Verdict:
    """Accepted or not, the rule that fired and a one-line reason."""

    accepted: bool
    rule: str | None = None
    reason: str | None = None


def check_correspondences(counts: Mapping[tuple[str, str], int], rules: AcceptanceRules) -> Verdict:
    """Reject when an adjacent pair has fewer than beta correspondences (checked before the adjustment)."""
    for (a, b), n in counts.items():
        if n < rules.min_correspondences:
            return Verdict(False, "min_correspondences",
                           f"pair {a}-{b} has {n} correspondences, fewer than beta = {rules.min_correspondences}")
    return Verdict(True)


def translation_changes(before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
                        pairs: Sequence[tuple[str, str]]) -> dict[tuple[str, str], float]:
    """Per adjacent pair: how far (m) the position of b in a's frame moved."""
    out = {}
    for a, b in pairs:
        rel0 = np.linalg.inv(before[a]) @ before[b]
        rel1 = np.linalg.inv(after[a]) @ after[b]
        out[(a, b)] = float(np.linalg.norm(rel1[:3, 3] - rel0[:3, 3]))
    return out


def check_result(
    converged: bool, iterations: int, before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
    pairs: Sequence[tuple[str, str]], rules: AcceptanceRules,
) -> Verdict:
    """Reject a result that did not converge in time, is not finite, or moved a relative translation > alpha."""
    if not all(np.all(np.isfinite(T)) for T in after.values()):
        return Verdict(False, "non_finite", "the adjustment produced a non-finite extrinsic")
    if not converged or iterations > rules.max_iterations:
        return Verdict(False, "not_converged", f"no convergence within {rules.max_iterations} iterations")
    moved = translation_changes(before, after, pairs)
    if moved:
        (a, b), worst = max(moved.items(), key=lambda kv: kv[1])
        if worst > rules.max_translation_change_m:
            return Verdict(False, "translation_change",
                           f"relative translation {a}-{b} moved {worst:.3f} m, more than alpha = "
                           f"{rules.max_translation_change_m} m")
    return Verdict(True)
