"""Acceptance rules of a calibrated window (the paper's), with beta per observation pair.

* beta: "we discard all correspondences between two observations if their number is fewer than beta".
  An observation pair is two images (camera a at frame t, camera b at frame t'), so beta is applied to
  each image pair's verified inliers (`PairMatches.observed_with`). An adjacent camera pair with at least
  one surviving observation pair is `observed`; one without is `through ring`: its relative pose comes
  from the other pairs through the loop constraint. When the observed pairs do not connect every camera of
  the rig, some camera's pose against the others is not constrained at all: with partial acceptance (the
  default, GLC) the window is calibrated block by block (`blocks.py`: each group of cameras the observed
  pairs link keeps its adjusted relative poses and is placed by its fit to the start; a pair between two
  blocks is `not linked` and keeps the start's relative pose, up to that fit), and the rules below judge
  the pairs inside blocks; without it, or when no two cameras are linked, the window is rejected (rule
  `min_correspondences`).
* not_converged: the adjustment did not converge within the iteration limit (200).
* translation_change (alpha): a relative translation that the images measure moved more than alpha from
  the starting extrinsics: a mount does not move by decimetres, so such a move means the adjustment
  followed wrong matches or an ill-conditioned geometry. It is checked on `observed` pairs only. A
  `through ring` pair's relative pose is the composition of the observed ones around the ring; its change
  is reported, and it cannot wander on its own because the mount priors of the adjustment hold what no
  image measures. Firing alpha on it would reject a window for not seeing a pair, which beta already
  decides.
* weakly_constrained: an adjacent pair's relative rotation is not determined by the adjustment to better
  than `max_rotation_sigma_deg` (1-sigma from the adjustment's information, points eliminated, priors
  included). A camera can be "linked" by an observation pair whose geometry does not fix its pose, e.g.
  same-frame matches on one near object (a plane: the pose and the baseline trade off). Measured on the
  random rigs of seeds 10-19: such pairs have sigma 1.1-10 deg, well observed pairs 0.015-0.05 deg (of
  the size of their actual errors); on DDAD scene_02 0.003-0.006 deg; on the tests' 2-frame 256x144 box
  rig 0.16-0.22 deg. The limit, 0.5 deg, is half the typical input error: a pair not known better than
  that is not calibrated, and its camera is as unlinked as one without observations, so the window is
  rejected.
* non_finite: the adjustment produced a non-finite extrinsic.
* less_precise: the window agrees with the calibration in effect (an earlier accepted window whose history
  entry keeps its pairs' 1-sigmas) and determines the rig markedly worse: every pair's rotation 1-sigma is
  more than `max_sigma_ratio` (2) times the calibration in effect's, and every pair's relative rotation is
  within `consistent_sigmas` (6) combined 1-sigmas of it, so nothing says the mount moved. It would then add
  under a fifth of the weight to every pair of the average (`fusion.fuse_calibrations`) and only risks what
  its sigmas understate: a window in which the car creeps (a few centimetres of travel) passes every rule above
  with 0.2-0.5 deg sigmas and would replace a 0.04 deg calibration by one 0.3 deg off (the box rig of the tests,
  5 cm between its frames). A window worse on some pairs only is averaged in, pair by pair (until session 24
  its worst pair decided: a window that saw less of one overlap was dropped with its other, as precise
  pairs). A window that disagrees beyond 6 combined sigmas is a measured change of the mount, unless the car
  stood still over it (ego travel under `STILL_EGO_M`): then its sigmas do not bound its error (urban-fisheye
  preset at half size, a still window after a driven one: worst pair 1-sigma 0.039 deg, error 0.16 deg), so it
  is kept out either way.
* unconfirmed: a window that disagrees with the calibration in effect beyond `consistent_sigmas` and passes the
  rules above is adopted only when the next window agrees with it (both averaged, in effect from the first's
  frames; `pipeline._change_confirmed`): a moved mount shows in every later window, a window whose 1-sigmas
  understate its error once (nuscenes preset, half size, frames 14-20: 0.098 deg off at a 0.012 deg 1-sigma, 7.7
  combined sigmas from the calibration in effect, which was 0.019 deg off).

Every rule that fires is reported (`rules_fired`); the first one is the window's `rule`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..geometry import invert_transform, rotation_angle_deg
from ..rig import Rig
from .blocks import linked_blocks

# beta per observation pair. The paper's values (LoFTR correspondences at full resolution):
BETA_DDAD = 200
BETA_NUSCENES = 50
# Our default matcher, SIFT inside the predicted overlap, finds 15-150 verified inliers per image pair on
# real narrow overlaps (DDAD) and on the synthetic presets' weakest pairs; fewer than 15 fit a spurious
# essential matrix (the matcher's own floor was 15 before beta became per observation pair).
BETA_SIFT = 15
BETA_SYNTH = 100  # LoFTR on the synthetic presets
BETA_DEFAULT = BETA_NUSCENES
ALPHA_M = 0.3
MAX_ITERATIONS = 200
MAX_ROTATION_SIGMA_DEG = 0.5
MAX_SIGMA_RATIO = 2.0
# Two windows of one mount agree within this many combined 1-sigmas. 6, not 3: the adjustment's sigmas are 2-4x
# too small on the worst pairs (keypoint errors stick to physical points, issue #17 sessions 9 and 19), and at 3
# an unchanged mount's next window was taken for a moved mount and replaced the average in 7 of 12 development
# sequences (session 23); a mount turned 0.4 deg on the tests' box rig (8.6 combined sigmas) still replaces.
CONSISTENT_SIGMAS = 6.0
# Below this travel of the ego over a window the car stood still (DDAD scene_01: 0.000 m; a car at walking
# pace moves 0.3 m in 0.2 s); a rejection by the adjustment's rules then names that cause.
STILL_EGO_M = 0.01

RULES = ("min_correspondences", "not_converged", "translation_change", "weakly_constrained", "non_finite",
         "less_precise")
OBSERVED, THROUGH_RING, NOT_LINKED = "observed", "through ring", "not linked"


@dataclass(frozen=True)
class AcceptanceRules:
    """Thresholds of the acceptance test."""

    min_correspondences: int = BETA_DEFAULT
    max_iterations: int = MAX_ITERATIONS
    max_translation_change_m: float = ALPHA_M
    max_rotation_sigma_deg: float = MAX_ROTATION_SIGMA_DEG
    max_sigma_ratio: float = MAX_SIGMA_RATIO
    consistent_sigmas: float = CONSISTENT_SIGMAS

    def to_dict(self) -> dict:
        """JSON-able thresholds."""
        return {"beta": self.min_correspondences, "max_iterations": self.max_iterations,
                "alpha_m": self.max_translation_change_m, "max_rotation_sigma_deg": self.max_rotation_sigma_deg,
                "max_sigma_ratio": self.max_sigma_ratio, "consistent_sigmas": self.consistent_sigmas}


def default_beta(rig: Rig, matcher: str = "sift") -> int:
    """beta per observation pair: SIFT's for the default matcher; with LoFTR the paper's for DDAD (CAMERA_xx
    names) and nuScenes (CAM_* names), ours for the synthetic presets, else nuScenes'."""
    if matcher != "loftr":
        return BETA_SIFT
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
    """Accepted or not, the first rule that fired and its one-line reason, and every rule that fired."""

    accepted: bool
    rule: str | None = None
    reason: str | None = None
    fired: tuple[tuple[str, str], ...] = field(default=())

    @staticmethod
    def of(fired: Sequence[tuple[str, str]]) -> Verdict:
        """The verdict of a list of (rule, reason) that fired (accepted when empty)."""
        if not fired:
            return Verdict(True)
        return Verdict(False, fired[0][0], fired[0][1], tuple(fired))

    def then(self, other: Verdict) -> Verdict:
        """This verdict followed by another check's: every rule that fired, the first one first."""
        return Verdict.of([*self.fired_list(), *other.fired_list()])

    def fired_list(self) -> list[tuple[str, str]]:
        """(rule, reason) of every rule that fired."""
        if self.fired:
            return list(self.fired)
        return [] if self.accepted else [(str(self.rule), str(self.reason))]


def unconstrained_cameras(cameras: Sequence[str], observed: Sequence[tuple[str, str]], reference: str) -> list[str]:
    """Cameras that no chain of observed pairs links to the reference camera."""
    linked = next(b for b in linked_blocks([reference, *cameras], observed) if reference in b)
    return [c for c in cameras if c not in linked]


def check_correspondences(counts: Mapping[tuple[str, str], int], rules: AcceptanceRules,
                          reference: str | None = None) -> Verdict:
    """Reject when the pairs with observation pairs that passed beta leave a camera unconstrained.

    `counts`: per adjacent pair, the number of its observation pairs with at least beta inliers. Checked
    before the adjustment; a pair with none is constrained through the ring.
    """
    cams = list(dict.fromkeys(n for p in counts for n in p))
    if not cams:
        return Verdict(True)
    ref = reference if reference in cams else cams[0]
    observed = [p for p, n in counts.items() if n > 0]
    lost = unconstrained_cameras(cams, observed, ref)
    if not lost:
        return Verdict(True)
    unseen = ", ".join(f"{a}-{b}" for (a, b), n in counts.items() if n == 0)
    return Verdict(False, "min_correspondences",
                   f"camera(s) {', '.join(lost)} not linked to {ref} by any observation pair with at least "
                   f"beta = {rules.min_correspondences} inliers (pairs without one: {unseen})")


def translation_changes(before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
                        pairs: Sequence[tuple[str, str]]) -> dict[tuple[str, str], float]:
    """Per adjacent pair: how far (m) the position of b in a's frame moved."""
    return {(a, b): float(np.linalg.norm(r1[:3, 3] - r0[:3, 3])) for (a, b), r0, r1 in _relatives(before, after, pairs)}


def rotation_changes(before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
                     pairs: Sequence[tuple[str, str]]) -> dict[tuple[str, str], float]:
    """Per adjacent pair: how far (deg) the orientation of b in a's frame turned."""
    return {(a, b): float(rotation_angle_deg(r0[:3, :3].T @ r1[:3, :3])) for (a, b), r0, r1 in
            _relatives(before, after, pairs)}


def _relatives(before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray], pairs: Sequence[tuple[str, str]]):
    """Per pair (a, b): b's pose in a's frame under `before` and under `after`."""
    for a, b in pairs:
        yield (a, b), invert_transform(before[a]) @ before[b], invert_transform(after[a]) @ after[b]


def check_result(
    converged: bool, iterations: int, before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
    pairs: Sequence[tuple[str, str]], rules: AcceptanceRules,
    rotation_sigma_deg: Mapping[tuple[str, str], float] | None = None,
) -> Verdict:
    """Reject a result that is not finite, did not converge in time, moved a relative translation of one
    of `pairs` (the observed ones) by more than alpha, or left an adjacent pair's relative rotation
    undetermined (`rotation_sigma_deg`, per adjacent pair); every rule that fires is listed."""
    fired: list[tuple[str, str]] = []
    if not all(np.all(np.isfinite(T)) for T in after.values()):
        return Verdict.of([("non_finite", "the adjustment produced a non-finite extrinsic")])
    if not converged or iterations > rules.max_iterations:
        fired.append(("not_converged", f"no convergence within {rules.max_iterations} iterations"))
    alpha = rules.max_translation_change_m
    for (a, b), moved in sorted(translation_changes(before, after, pairs).items(), key=lambda kv: -kv[1]):
        if moved > alpha:
            fired.append(("translation_change",
                          f"relative translation {a}-{b} moved {moved:.3f} m, more than alpha = {alpha} m"))
    weak = {p: v for p, v in (rotation_sigma_deg or {}).items() if not v <= rules.max_rotation_sigma_deg}
    if weak:
        worst = ", ".join(f"{a}-{b} {v:.2f} deg" for (a, b), v in sorted(weak.items(), key=lambda kv: -kv[1]))
        fired.append(("weakly_constrained", f"relative rotation not determined by the images (1-sigma {worst}, "
                                            f"more than {rules.max_rotation_sigma_deg} deg)"))
    return Verdict.of(fired)


def common_pairs(in_effect_sigma_deg: Mapping[tuple[str, str], float],
                  sigma_deg: Mapping[tuple[str, str], float]) -> list[tuple[str, str]]:
    """Pairs with a finite, positive 1-sigma in both."""
    return [p for p in sigma_deg if np.isfinite(sigma_deg[p]) and np.isfinite(in_effect_sigma_deg.get(p, np.nan))
            and min(sigma_deg[p], in_effect_sigma_deg[p]) > 0]


def disagreement_sigmas(in_effect_sigma_deg: Mapping[tuple[str, str], float],
                        sigma_deg: Mapping[tuple[str, str], float],
                        turned_deg: Mapping[tuple[str, str], float]) -> float:
    """The largest turn of a pair between the calibration in effect and a window's (`turned_deg`), in combined
    1-sigmas of the two; inf when they have no pair in common."""
    common = common_pairs(in_effect_sigma_deg, sigma_deg)
    if not common:
        return float("inf")
    return max(turned_deg.get(p, 0.0) / float(np.hypot(sigma_deg[p], in_effect_sigma_deg[p])) for p in common)


def check_precision(in_effect_sigma_deg: Mapping[tuple[str, str], float], sigma_deg: Mapping[tuple[str, str], float],
                    turned_deg: Mapping[tuple[str, str], float], rules: AcceptanceRules,
                    still: bool = False) -> Verdict:
    """Reject (`less_precise`) an accepted window that was taken while the car stood still (`still`: its sigmas do
    not bound its error, so it neither shows that the mount moved nor adds to what is known), or whose every pair is
    determined more than `max_sigma_ratio` times worse than in the calibration in effect while it agrees with it
    within `consistent_sigmas` combined 1-sigmas on every pair; `turned_deg`: per pair, how far the window turned
    it from the calibration in effect. Pairs without a finite 1-sigma on both sides are not compared."""
    common = common_pairs(in_effect_sigma_deg, sigma_deg)
    if not common:
        return Verdict(True)
    worst = max(common, key=lambda p: sigma_deg[p])
    worst_before = max(in_effect_sigma_deg[p] for p in common)
    a, b = worst
    sigmas = f"worst pair {a}-{b} 1-sigma {sigma_deg[worst]:.3f} deg against {worst_before:.3f} deg"
    if still:
        return Verdict(False, "less_precise", f"was taken while the car stood still, so its 1-sigmas do not bound its "
                                              f"error ({sigmas}): the calibration in effect is kept")
    ratios = {p: sigma_deg[p] / in_effect_sigma_deg[p] for p in common}
    if not min(ratios.values()) > rules.max_sigma_ratio:
        return Verdict(True)
    z = disagreement_sigmas(in_effect_sigma_deg, sigma_deg, turned_deg)
    if z > rules.consistent_sigmas:
        return Verdict(True)  # the window measures a change of the mount
    best = min(ratios, key=lambda p: ratios[p])
    return Verdict(False, "less_precise",
                   f"agrees with the calibration in effect (every pair within {z:.1f} combined 1-sigma) and is less "
                   f"precise on every pair (more than {rules.max_sigma_ratio:g}x; {sigmas}, best ratio "
                   f"{ratios[best]:.1f}x on {best[0]}-{best[1]}): the calibration in effect is kept")
