"""`calibrate`: windows of T frames -> correspondences -> method -> acceptance -> refined rig + report.

The selected frames are split, in timestamp order, into consecutive windows of `window` frames. Each
window starts from the calibration in effect at its first timestamp (the last accepted one, or the
input extrinsics), is calibrated, and is accepted or rejected by the paper's rules. A rejected window
keeps the last accepted calibration. The returned rig carries the last accepted calibration and a
`calibration` block whose `history` lists every accepted calibration with the timestamp from which
it applies (`calibration_at` looks one up); history from an input rig's block is carried forward.
With `AdjustConfig.refine_focal` (the default, `glc` only) a calibration also refines each camera's focal
length where the images determine it (see `ba.robust_adjust`): the rig carries the refined intrinsics
(fx, fy scaled; an ocam model's polynomials), each window's report lists every camera's estimate, its
1-sigma and whether it was adopted (`focal`), and a history entry that changed any keeps the window's
intrinsics (`intrinsics_at`); the next window starts from them.
A history entry also keeps its pairs' rotation 1-sigmas (`pair_sigmas_at`): a later window that agrees with it
and determines every pair markedly worse (a car that creeps), or was taken standing still, does not replace it (rule
`less_precise`, `acceptance.check_precision`); one that agrees with it within 6 combined 1-sigmas otherwise is
averaged with it pair by pair (`fusion.fuse_calibrations`, each pair weighted by 1 / its sigma^2 in each; its entry
says `fused_with_previous`, its report `fused_weights` and `fused_pair_weights`); one that disagrees beyond that is a
change of the mount and replaces it. Each window's
report gives how far the ego travelled over it (`ego_travel_m`).
With GLC, a window whose observed pairs do not link every camera is calibrated block by block (`partial`, default on;
`blocks.place_blocks`): its report says `partial`, its `blocks` and why (`not_linked`), the pairs between blocks are
`not linked`, and the block lists such windows in `partial_windows`.
The block's top-level `accepted` is true when at least one window of this run was accepted; each
entry of `windows` has its own verdict, the rule that fired and a one-line reason.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..cameras import Camera, CameraModel
from ..errors import InputError
from ..geometry import ORTHONORMAL_TOL, mean_transform, rotation_error
from ..rig import Frame, Rig
from ..rigfile import intrinsics_from_dict
from ..stereo.rectify import torch_threads
from .acceptance import (
    NOT_LINKED,
    OBSERVED,
    STILL_EGO_M,
    THROUGH_RING,
    AcceptanceRules,
    Verdict,
    check_correspondences,
    check_precision,
    check_result,
    default_beta,
    disagreement_sigmas,
    rotation_changes,
    translation_changes,
)
from .ba import AdjustConfig
from .blocks import between_blocks, linked_blocks, place_blocks
from .correspondences import (
    MATCHERS,
    VIEW_PHASES,
    MatchConfig,
    PairMatches,
    Timings,
    match_window,
    refines_keypoints,
    with_links,
)
from .fusion import Fused, fuse_calibrations, usable_sigmas
from .methods import METHODS, MethodResult, run_method

CALIB_VERSION = "1"
DEFAULT_WINDOW = 7


def check_extrinsics(rig: Rig) -> None:
    """InputError (exit code 2) for a NaN, infinite or non-orthonormal initial extrinsic."""
    for cam in rig.cameras:
        T = np.asarray(cam.sensor_to_ego, dtype=np.float64)
        key = f"cameras[{cam.name}].sensor_to_ego"
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(rig.root, key, "contains NaN or infinity")
        err = rotation_error(T[:3, :3])
        if err > ORTHONORMAL_TOL:
            raise InputError(rig.root, key, f"rotation is not orthonormal (error {err:.2g} > 1e-6)")
    for fr in rig.frames:
        if not np.all(np.isfinite(fr.ego_to_world)) or rotation_error(fr.ego_to_world[:3, :3]) > ORTHONORMAL_TOL:
            raise InputError(rig.root, f"frames[{fr.id}].ego_to_world", "not a finite rigid transform")


def reference_camera(rig: Rig) -> str:
    """The camera that carries the gauge: first of the ring, else the first camera of the first pair."""
    if rig.ring:
        return rig.ring[0]
    if rig.pairs:
        return rig.pairs[0][0]
    return rig.camera_names[0]


def _matrix_dict(ext: Mapping[str, np.ndarray]) -> dict[str, list]:
    return {k: np.asarray(v, dtype=np.float64).tolist() for k, v in ext.items()}


def _entry_at(block: Mapping[str, Any], timestamp_us: int) -> Mapping[str, Any] | None:
    """The last accepted calibration (history entry) whose window starts at or before `timestamp_us`."""
    best = None
    for entry in block.get("history", []):
        ts = entry.get("from_timestamp_us")
        if ts is not None and ts <= timestamp_us and (best is None or ts >= best["from_timestamp_us"]):
            best = entry
    return best


def calibration_at(block: Mapping[str, Any], timestamp_us: int) -> dict[str, np.ndarray] | None:
    """Extrinsics of the last accepted calibration whose window starts at or before `timestamp_us`."""
    best = _entry_at(block, timestamp_us)
    if best is None:
        return None
    return {k: np.asarray(v, dtype=np.float64) for k, v in best["sensor_to_ego"].items()}


def pair_sigmas_at(block: Mapping[str, Any], timestamp_us: int, where: Any = None) -> dict[tuple[str, str], float]:
    """Per adjacent pair, the rotation 1-sigma (deg) of the calibration in effect at `timestamp_us` (empty when
    none is, or its history entry predates the field); `where` names the file in the error of a damaged entry."""
    best = _entry_at(block, timestamp_us)
    rows = best.get("pair_rotation_sigma_deg", []) if best is not None else []
    out = {}
    for row in rows if isinstance(rows, list) else [rows]:
        ok = isinstance(row, list) and len(row) == 3 and all(isinstance(x, str) for x in row[:2])
        if not (ok and isinstance(row[2], (int, float)) and not isinstance(row[2], bool) and row[2] > 0):
            raise InputError(where, "calibration.history.pair_rotation_sigma_deg",
                             f"expected [camera, camera, degrees > 0] rows, got {str(row)[:60]}")
        out[(row[0], row[1])] = float(row[2])
    return out


def intrinsics_at(block: Mapping[str, Any], timestamp_us: int) -> dict[str, CameraModel]:
    """Intrinsics refined by that calibration (`AdjustConfig.refine_focal`); empty when it refined none."""
    best = _entry_at(block, timestamp_us)
    doc = {} if best is None else best.get("intrinsics") or {}
    return {k: intrinsics_from_dict(v, f"calibration.history.intrinsics[{k}]") for k, v in doc.items()}


def _windows(frames: tuple[Frame, ...], size: int) -> list[tuple[Frame, ...]]:
    ordered = tuple(sorted(frames, key=lambda f: f.timestamp_us))
    return [ordered[i : i + size] for i in range(0, len(ordered), size)]


def _pair_rows(matches: list[PairMatches], used: list[PairMatches], result: MethodResult | None,
               moved: Mapping[tuple[str, str], float], beta: int, blocks: Sequence[Sequence[str]] = ()) -> list[dict]:
    rows = []
    between = set(between_blocks([(pm.cam_a, pm.cam_b) for pm in matches], blocks)) if blocks else set()
    for pm, pu in zip(matches, used):
        key = (pm.cam_a, pm.cam_b)
        in_ba = result is not None and key in result.pair_rms_px
        rms = result.pair_rms_px.get(key) if in_ba else None
        rows.append({
            "a": pm.cam_a,
            "b": pm.cam_b,
            "status": OBSERVED if pu.view_pairs > 0 else NOT_LINKED if key in between else THROUGH_RING,
            "tentative": int(pm.tentative),
            "after_gate": int(pm.gated),
            "inliers": int(pm.inliers),
            "inliers_used": int(pu.inliers),
            "image_pairs_with_inliers": int(pm.view_pairs),
            "observation_pairs_passing_beta": int(pu.view_pairs),
            "same_frame_observation_pairs_passing_beta": int(pm.same_frame_views(beta)),
            "same_camera_links": int(sum(len(link) for link in pu.links)),
            "beta": int(beta),
            "used_in_adjustment": bool(in_ba and result.pair_used_matches.get(key, 0) > 0),
            "adjusted_correspondences": int(result.pair_used_matches.get(key, 0)) if in_ba else 0,
            "rms_px": float(rms) if rms is not None and np.isfinite(rms) else None,
            "rotation_sigma_deg": _num(result.pair_rotation_sigma_deg.get(key)) if result is not None else None,
            "translation_change_m": float(moved.get(key, 0.0)),
            "observation_pairs": [[o.t, o.t2, o.inliers] for o in pm.observation_pairs if o.tentative > 0],
        })
    return rows


def _links_kept(matches: list[PairMatches]) -> str:
    """Which same-camera links the window's adjustment had: "all" (`mono_links`), "touching" (`temporal_links`
    alone: those that extend a pair's tracks) or "none"."""
    links = [link for pm in matches for link in pm.links]
    return "all" if any(link.standalone for link in links) else "touching" if links else "none"


def calibrate(
    rig: Rig,
    images: Callable[[str, str], np.ndarray] | None = None,
    method: str = "glc",
    frames: slice | None = None,
    matcher: str = "sift",
    **options: Any,
) -> tuple[Rig, dict]:
    """Calibrate the extrinsics (and focal lengths, AdjustConfig.refine_focal) of a rig over windows of its
    frames; returns the refined rig and its report.

    images(frame_id, camera) -> RGB image (default: the rig folder's files). Options: window (T, default
    7; a shorter last window, or a rig with fewer frames, is calibrated with what it has), loftr_weights,
    rules (AcceptanceRules; default beta per observation pair for the matcher and data set, see
    acceptance.default_beta, 200 iterations, alpha = 0.3 m), match_config, adjust_config, reference,
    timings, show_progress, match_cache (a dict shared between calls on the same images, e.g. to compare
    methods: features and matches are reused when window, matcher settings (same-camera links aside) and
    starting extrinsics agree), fuse_windows (default True: an accepted window that agrees with the calibration
    in effect is averaged with it, `fuse_calibrations`, instead of replacing it), partial (default True: with GLC, a
    window whose observed pairs do not link every camera is calibrated block by block, each block placed by its fit
    to the start, `blocks.place_blocks`; False rejects it, rule min_correspondences).
    """
    with torch_threads(1):
        setup = _setup(rig, images, method, frames, matcher, **options)
        return _calibrate(rig, setup)


@dataclass
class Setup:
    """The checked settings of one `calibrate` call."""

    method: str
    matcher: str
    frames: tuple[Frame, ...]
    window: int
    rules: AcceptanceRules
    match: MatchConfig
    adjust: AdjustConfig
    reference: str
    load: Callable[[str, str], np.ndarray]
    masks: dict[str, np.ndarray]
    timings: Timings
    show_progress: bool | None
    match_cache: dict | None
    pairs: list[tuple[str, str]]
    fuse_windows: bool = True
    partial: bool = True


def _check_match_config(cfg: MatchConfig) -> None:
    """InputError for matching settings outside what the pipeline runs."""
    if not 1 <= cfg.view_phases <= len(VIEW_PHASES):
        raise InputError(None, "view_phases", f"must be 1 to {len(VIEW_PHASES)}, got {cfg.view_phases}")
    if not 1 <= cfg.octave_layers <= 8:
        raise InputError(None, "octave_layers", f"must be 1 to 8, got {cfg.octave_layers}")


def _setup(
    rig: Rig,
    images: Callable[[str, str], np.ndarray] | None = None,
    method: str = "glc",
    frames: slice | None = None,
    matcher: str = "sift",
    *,
    window: int = DEFAULT_WINDOW,
    loftr_weights: str | None = None,
    rules: AcceptanceRules | None = None,
    match_config: MatchConfig | None = None,
    adjust_config: AdjustConfig | None = None,
    reference: str | None = None,
    timings: Timings | None = None,
    show_progress: bool | None = None,
    match_cache: dict | None = None,
    fuse_windows: bool = True,
    partial: bool = True,
) -> Setup:
    """Check the options (InputError for bad ones) and fill in the defaults."""
    if method not in METHODS:
        raise InputError(None, "method", f"unknown method {method!r} (expected one of {', '.join(METHODS)})")
    if matcher not in MATCHERS:
        raise InputError(None, "matcher", f"unknown matcher {matcher!r} (expected one of {', '.join(MATCHERS)})")
    if window < 1:
        raise InputError(None, "window", "must be at least 1 frame")
    if match_config is not None:
        _check_match_config(match_config)
    check_extrinsics(rig)
    selected = rig.frames if frames is None else rig.frames[frames]
    if not selected:
        raise InputError(rig.root, "frames", "the frame selection is empty")
    if not rig.pairs:
        raise InputError(rig.root, "ring/pairs", "the rig has no adjacent pairs to calibrate")
    ref = reference or reference_camera(rig)
    if ref not in rig.camera_names:
        raise InputError(None, "reference", f"camera {ref!r} does not exist")
    rules = rules or AcceptanceRules(min_correspondences=default_beta(rig, matcher))
    mcfg = replace(match_config or MatchConfig(), matcher=matcher)
    mcfg = replace(mcfg, refine=refines_keypoints(mcfg, rig.cameras))  # "auto" resolved for this rig
    if loftr_weights is not None:
        mcfg = replace(mcfg, loftr_weights=str(loftr_weights))
    acfg = replace(adjust_config or AdjustConfig(), max_iterations=rules.max_iterations)
    if mcfg.dense.enabled:  # dense same-frame matches made the focal refinement adopt wrong scales (issue #17, s. 10)
        acfg = replace(acfg, refine_focal=False)
    masks = {c: m for c in rig.camera_names if (m := rig.load_mask(c)) is not None}
    return Setup(method, matcher, tuple(selected), window, rules, mcfg, acfg, ref, images or rig.load_image, masks,
                 timings or Timings(), show_progress, match_cache, list(rig.pairs), bool(fuse_windows), bool(partial))


@dataclass
class WindowResult:
    """One window's outcome: verdict, extrinsics after it, and its report entry."""

    verdict: Verdict
    after: dict[str, np.ndarray]
    report: dict[str, Any]
    intrinsics: dict[str, CameraModel]  # after the window (refined focal lengths when accepted)
    pair_sigma_deg: dict[tuple[str, str], float] = field(default_factory=dict)  # of `after`


def window_ego_poses(rig: Rig, frames: Sequence[Frame], cameras: Sequence[str]) -> np.ndarray:
    """Ego poses of a window: (T, 4, 4) when every camera was taken at its frame's pose, else (T, M, 4, 4),
    each camera's own ego pose at its capture (in the order of `cameras`)."""
    per = np.stack([[np.asarray(f.capture_ego_to_world(c), dtype=np.float64) for c in cameras] for f in frames])
    if np.array_equal(per, np.broadcast_to(per[:, :1], per.shape)):
        return per[:, 0]
    return per


def _match_window(setup: Setup, cams: list[Camera], win: tuple[Frame, ...], ego: np.ndarray,
                  start: Mapping[str, np.ndarray]) -> list[PairMatches]:
    """Correspondences of a window; its features and matches come from the match cache when the same window
    was matched from the same start with settings that differ at most in the same-camera links."""
    ids = [f.id for f in win]
    unlinked = replace(setup.match, temporal_links=False, mono_links=False)
    key = (tuple(ids), repr(unlinked), tuple(start[n].tobytes() for n in sorted(start)),
           tuple(repr(c.intrinsics.to_dict()) for c in cams))
    window = None if setup.match_cache is None else setup.match_cache.get(key)
    if window is None:
        window = match_window(cams, setup.pairs, ego, lambda t, c: setup.load(ids[t], c), setup.masks or None,
                              setup.match, setup.timings, setup.show_progress)
        if setup.match_cache is not None:
            setup.match_cache[key] = window
    return with_links(window, setup.match, setup.timings)


@dataclass
class Judged:
    """What a window's calibration produced: verdict, method result (None when not run), matches before and
    after beta per observation pair."""

    verdict: Verdict
    result: MethodResult | None
    matches: list[PairMatches]
    used: list[PairMatches]
    links_for: list[str] = field(default_factory=list)  # why the window was redone with every same-camera link
    phases: list[dict] = field(default_factory=list)  # with more than one view phase: each run's outcome
    phases_for: list[str] = field(default_factory=list)  # why the window was redone at every view phase
    blocks: list[tuple[str, ...]] = field(default_factory=list)  # a partially linked window's blocks, else []
    not_linked: str | None = None  # why not every camera is linked (min_correspondences' reason)


def _judge(rig: Rig, setup: Setup, cams: list[Camera], win: tuple[Frame, ...], ego: np.ndarray,
           start: dict[str, np.ndarray]) -> Judged:
    """Match, apply beta per observation pair, check the ring is constrained, adjust, check the result; with
    `MatchConfig.auto_links`, once more with every same-camera link when a pair seen only across time came out
    weakly determined (`_weak_unseen_pairs`)."""
    if setup.method == "none":
        return Judged(Verdict(True), MethodResult(dict(start), message="input extrinsics kept"), [], [])
    if setup.match_cache is None:  # a second round reuses the first one's features and matches
        setup = replace(setup, match_cache={})
    judged = _judge_matches(setup, cams, win, ego, start)
    why = _weak_unseen_pairs(setup, judged, len(win))
    if not why:
        return judged
    linked = replace(setup, match=replace(setup.match, temporal_links=True, mono_links=True))
    return replace(_judge_matches(linked, cams, win, ego, start), links_for=why)


def _judge_phases(rig: Rig, setup: Setup, cams: list[Camera], win: tuple[Frame, ...], ego: np.ndarray,
                  start: dict[str, np.ndarray]) -> Judged:
    """`_judge` once per view phase (`MatchConfig.view_phases`, or all of them when `MatchConfig.auto_phases` finds
    the single run's pairs weakly determined, `_weak_pairs`); with more than one, the window is accepted when more
    than half of the runs are, with the mean of their extrinsics and focal scales; matches, sigmas and the rest of
    the report are the first accepted run's."""
    k = setup.match.view_phases
    phases = VIEW_PHASES[:k] if k > 1 else (setup.match.view_phase,)
    if setup.method == "none":
        return _judge(rig, setup, cams, win, ego, start)
    runs = [_judge(rig, replace(setup, match=replace(setup.match, view_phase=phases[0])), cams, win, ego, start)]
    why: list[str] = []
    if k == 1:
        why = _weak_pairs(setup, runs[0])
        if not why:
            return runs[0]
        phases = phases + tuple(p for p in VIEW_PHASES if p != phases[0])[: len(VIEW_PHASES) - 1]
    runs += [_judge(rig, replace(setup, match=replace(setup.match, view_phase=p)), cams, win, ego, start)
             for p in phases[1:]]
    accepted = [r for r in runs if r.verdict.accepted and r.result is not None]
    ok = _same_blocks(accepted)
    if 2 * len(ok) <= len(runs) < 2 * len(accepted):  # most runs accepted, linked differently
        ok = _common_blocks(accepted, start)
    rows = [{"phase": list(p), "accepted": r.verdict.accepted, "rule": r.verdict.rule,
             "blocks": [list(b) for b in r.blocks]} for p, r in zip(phases, runs)]
    if 2 * len(ok) <= len(runs):
        return replace(_phases_rejected(runs, len(ok)), phases=rows, phases_for=why)
    result = _mean_result([r.result for r in ok])
    centre = {**start, **result.sensor_to_ego}
    for row, r in zip(rows, runs):  # how far each averaged run's adjacent relative rotations are from the mean's
        if any(r is o for o in ok):
            after = {**start, **r.result.sensor_to_ego}
            turned = rotation_changes(centre, after, setup.pairs)
            row["pair_rotation_from_mean_deg"] = {f"{a}-{b}": round(v, 5) for (a, b), v in turned.items()}
    return replace(ok[0], result=result, phases=rows, phases_for=why)


def _phases_rejected(runs: list[Judged], n_ok: int) -> Judged:
    """The first rejected run of a window whose view phases did not agree (`n_ok` runs accepted with the same cameras
    linked), its reason saying so; when every run was accepted but linked differently, a `min_correspondences` one."""
    first = next((r for r in runs if not r.verdict.accepted), None)
    if first is None:
        first = replace(runs[0], verdict=Verdict(False, "min_correspondences", "the runs link the cameras into "
                                                 "different blocks, so no camera set is linked by most of them"))
    reason = (f"{n_ok} of {len(runs)} view phases accepted with the same cameras linked; the first rejected: "
              f"{first.verdict.reason}")
    return replace(first, verdict=replace(first.verdict, reason=reason))


def _common_blocks(runs: list[Judged], start: Mapping[str, np.ndarray]) -> list[Judged]:
    """Accepted runs that link the cameras into different blocks, each re-placed on the blocks all of them share
    (two cameras stay together only where every run links them; `_placed`), so that they can be averaged; [] when
    those blocks link no two cameras."""
    names = list(runs[0].result.sensor_to_ego)
    label = {n: tuple(next((k for k, b in enumerate(r.blocks) if n in b), -1) for r in runs) for n in names}
    common = [tuple(n for n in names if label[n] == key) for key in dict.fromkeys(label.values())]
    if all(len(b) == 1 for b in common):
        return []
    why = next((r.not_linked for r in runs if r.not_linked), None)
    return [replace(r, result=_placed(r.result, start, common), blocks=common,
                    not_linked=f"{why}; the view phases link the cameras differently, so only the cameras that every "
                               f"run links stay together") for r in runs]


def _same_blocks(runs: list[Judged]) -> list[Judged]:
    """The accepted runs to average: those linked into the blocks most of them have (the first run's on a tie); runs
    linked otherwise place their cameras differently and are left out."""
    keys = [tuple(r.blocks) for r in runs]
    if not keys:
        return []
    best = max(dict.fromkeys(keys), key=keys.count)
    return [r for r, k in zip(runs, keys) if k == best]


def _weak_pairs(setup: Setup, judged: Judged) -> list[str]:
    """The adjacent pairs of an accepted single-phase run whose relative rotation the adjustment determined to worse
    than `MatchConfig.auto_phases_sigma_deg` (empty when `MatchConfig.auto_phases` is off)."""
    cfg = setup.match
    if not cfg.auto_phases or not judged.verdict.accepted or judged.result is None:
        return []
    return [f"{a}-{b}: rotation sigma {s:.3f} deg" for (a, b), s in judged.result.pair_rotation_sigma_deg.items()
            if s > cfg.auto_phases_sigma_deg]


def _mean_result(results: list[MethodResult]) -> MethodResult:
    """The first result with the mean extrinsics (`mean_transform`) and mean focal scales of all of them."""
    mean = {n: mean_transform(np.stack([r.sensor_to_ego[n] for r in results])) for n in results[0].sensor_to_ego}
    names = {n for r in results for n in r.focal_scale}
    scales = {n: float(np.mean([r.focal_scale.get(n, 1.0) for r in results])) for n in names}
    return replace(results[0], sensor_to_ego=mean, focal_scale=scales)


def _weak_unseen_pairs(setup: Setup, judged: Judged, n_frames: int) -> list[str]:
    """The adjacent pairs that keep no same-frame observation pair passing beta and whose relative rotation the
    adjustment determined to worse than `MatchConfig.auto_links_sigma_deg` (empty when links do not apply)."""
    cfg = setup.match
    if (not cfg.auto_links or (cfg.temporal_links and cfg.mono_links) or cfg.matcher != "sift" or not cfg.cross_time
            or n_frames < 2 or judged.result is None):
        return []
    beta = setup.rules.min_correspondences
    sigma = judged.result.pair_rotation_sigma_deg
    return [f"{pm.cam_a}-{pm.cam_b}: no same-frame observation pair with {beta} inliers, rotation sigma "
            f"{sigma[(pm.cam_a, pm.cam_b)]:.3f} deg" for pm in judged.matches
            if pm.same_frame_views(beta) == 0 and sigma.get((pm.cam_a, pm.cam_b), 0.0) > cfg.auto_links_sigma_deg]


def _judge_matches(setup: Setup, cams: list[Camera], win: tuple[Frame, ...], ego: np.ndarray,
                   start: dict[str, np.ndarray]) -> Judged:
    """One round of `_judge`: match, beta, ring check (a window whose observed pairs do not link every camera is
    calibrated block by block, `_partial_blocks`), adjustment, result check."""
    matches = _match_window(setup, cams, win, ego, start)
    used = [pm.observed_with(setup.rules.min_correspondences) for pm in matches]
    observed = [(u.cam_a, u.cam_b) for u in used if u.view_pairs > 0]
    verdict = check_correspondences({(u.cam_a, u.cam_b): u.view_pairs for u in used}, setup.rules, setup.reference)
    blocks = [] if verdict.accepted else _partial_blocks(setup, cams, observed)
    not_linked = None if verdict.accepted else verdict.reason
    if not verdict.accepted and not blocks:
        return Judged(verdict, None, matches, used)
    t0 = time.perf_counter()
    result = run_method(setup.method, cams, setup.pairs, used, ego, setup.reference, setup.adjust)
    setup.timings.add("adjustment", t0)
    if blocks:
        result = _placed(result, start, blocks)
    verdict = check_result(result.converged, result.iterations, start, {**start, **result.sensor_to_ego}, observed,
                           setup.rules, result.pair_rotation_sigma_deg)
    return Judged(verdict, result, matches, used, blocks=blocks, not_linked=not_linked)


def _partial_blocks(setup: Setup, cams: list[Camera], observed: list[tuple[str, str]]) -> list[tuple[str, ...]]:
    """The blocks a window that does not link every camera is calibrated in (`Setup.partial`, GLC only), or [] when
    it is not (partial acceptance off, or no block of two cameras or more)."""
    if not setup.partial or setup.method != "glc":
        return []
    blocks = linked_blocks([c.name for c in cams], observed)
    return blocks if any(len(b) > 1 for b in blocks) else []


def _placed(result: MethodResult, start: Mapping[str, np.ndarray], blocks: list[tuple[str, ...]]) -> MethodResult:
    """A partially linked window's result with every block placed by its fit to the start (`place_blocks`) and no
    1-sigma for the pairs between blocks, which the images do not determine."""
    sigma = result.pair_rotation_sigma_deg
    between = set(between_blocks(list(sigma), blocks))
    return replace(result, sensor_to_ego=place_blocks(result.sensor_to_ego, start, blocks),
                   pair_rotation_sigma_deg={p: s for p, s in sigma.items() if p not in between})


def _focal_rows(start: Mapping[str, CameraModel], result: MethodResult | None) -> list[dict]:
    """Per camera: the focal-length change (%) adopted, the free estimate (%) with its 1-sigma (%), and
    whether it was significant enough to adopt (AdjustConfig.focal_min_sigmas)."""
    if result is None or not result.focal_scale:
        return []
    rows = []
    for name, s in result.focal_scale.items():
        K = getattr(start[name], "K", None)
        free = result.focal_scale_free.get(name, s)
        rows.append({"camera": name, "change_pct": 100.0 * (s - 1.0), "estimate_pct": 100.0 * (free - 1.0),
                     "sigma_pct": _num(100.0 * result.focal_scale_sigma.get(name, float("nan"))),
                     "adopted": bool(s != 1.0),
                     "fx_before": None if K is None else float(K[0, 0]),
                     "fx_after": None if K is None else float(K[0, 0] * s)})
    return rows


def ego_travel_m(ego: np.ndarray) -> float:
    """Largest distance (m) between two ego positions of a window (poses (T, 4, 4) or (T, M, 4, 4))."""
    pos = np.asarray(ego, dtype=np.float64)[..., :3, 3].reshape(-1, 3)
    return float(np.linalg.norm(pos[:, None] - pos[None], axis=-1).max()) if len(pos) else 0.0


def _still_explained(verdict: Verdict, travel_m: float) -> Verdict:
    """A rejection by the adjustment's rules, with the cause added when the car stood still over the window."""
    if verdict.accepted or travel_m >= STILL_EGO_M or verdict.rule not in ("not_converged", "weakly_constrained"):
        return verdict
    fired = verdict.fired_list()
    why = (f"{fired[0][1]}; the ego moved {travel_m:.3f} m over the window: with the car standing still no match "
           "across time measures depth, so a narrow overlap does not fix its pair; calibrate from frames where it "
           "moves")
    return Verdict.of([(fired[0][0], why), *fired[1:]])


def _against_in_effect(setup: Setup, verdict: Verdict, start: Mapping[str, np.ndarray],
                       in_effect_sigma: Mapping[tuple[str, str], float], after: Mapping[str, np.ndarray],
                       sigma: Mapping[tuple[str, str], float], travel_m: float
                       ) -> tuple[Verdict, Fused | None, float | None]:
    """An accepted window against the calibration in effect (`start`, with its pairs' 1-sigmas): rejected when
    less precise or taken standing still (`check_precision`), else averaged with it when the two agree
    (`setup.fuse_windows`), else adopted as it is; also how far they disagree (`disagreement_sigmas`, None when
    nothing is compared)."""
    if not verdict.accepted or not in_effect_sigma:
        return verdict, None, None
    turned = rotation_changes(start, after, setup.pairs)
    verdict = check_precision(in_effect_sigma, sigma, turned, setup.rules, still=travel_m < STILL_EGO_M)
    z = disagreement_sigmas(in_effect_sigma, sigma, turned)
    if verdict.accepted and setup.fuse_windows and z <= setup.rules.consistent_sigmas:
        return verdict, fuse_calibrations(start, in_effect_sigma, after, sigma), z
    return verdict, None, z


def _fused_fields(fused: Fused | None) -> dict[str, Any]:
    """A window's report fields on its averaging with the calibration in effect (None when it was not averaged)."""
    if fused is None:
        return {"fused_weights": None, "fused_pair_weights": None}
    return {"fused_weights": {"in_effect": fused.weights[0], "window": fused.weights[1]},
            "fused_pair_weights": _pair_weight_rows(fused)}


def _pair_weight_rows(fused: Fused) -> list[list]:
    """[a, b, the second calibration's share of the pair] per pair both calibrations have (report rows)."""
    return [[a, b, w] for (a, b), w in fused.pair_weights.items()]


def _change_confirmed(setup: Setup, res: WindowResult, pending: WindowResult | None
                      ) -> tuple[WindowResult, WindowResult | None]:
    """A window that disagrees with the calibration in effect beyond `consistent_sigmas` is adopted only when the
    next window agrees with it (then the two are averaged, `fuse_calibrations`, and adopted from the first one's
    frames); until then it is held back (rule `unconfirmed`) and the calibration in effect stays. A moved mount
    shows in every later window; a window whose 1-sigmas understate its error (one nuscenes window 0.098 deg off
    at a 0.012 deg 1-sigma) shows once. Returns the window's result and the window now awaiting confirmation."""
    z, limit = res.report["disagreement_sigmas"], setup.rules.consistent_sigmas
    if not (setup.fuse_windows and res.verdict.accepted and res.report["fused_weights"] is None
            and z is not None and z > limit):
        return res, None
    if pending is not None:
        turned = rotation_changes(pending.after, res.after, setup.pairs)
        z_pending = disagreement_sigmas(pending.pair_sigma_deg, res.pair_sigma_deg, turned)
        if z_pending <= limit:
            fused = fuse_calibrations(pending.after, pending.pair_sigma_deg, res.after, res.pair_sigma_deg)
            confirms = {"window": pending.report["index"], "timestamp_us": pending.report["timestamp_us"],
                        "disagreement_sigmas": _num(z_pending),
                        "pair_weights": _pair_weight_rows(fused)}
            return replace(res, after={**res.after, **fused.extrinsics}, pair_sigma_deg=fused.pair_sigma_deg,
                           report={**res.report, "confirms": confirms}), None
    why = (f"disagrees with the calibration in effect by {z:.1f} combined 1-sigmas (more than {limit:g}): a moved "
           f"mount or a window whose 1-sigmas understate its error; adopted only if the next window agrees with it "
           "(--no-fuse-windows: adopted at once)")
    fired = [*res.report["rules_fired"], {"rule": "unconfirmed", "reason": why}]
    report = {**res.report, "accepted": False, "rule": "unconfirmed", "reason": why, "rules_fired": fired}
    return replace(res, verdict=Verdict(False, "unconfirmed", why), report=report), res


def _calibrate_window(rig: Rig, setup: Setup, k: int, win: tuple[Frame, ...], start: dict[str, np.ndarray],
                      start_intr: dict[str, CameraModel],
                      in_effect_sigma: Mapping[tuple[str, str], float]) -> WindowResult:
    """Calibrate and judge one window (from the extrinsics and intrinsics in effect, whose pairs' rotation 1-sigmas
    are `in_effect_sigma`); its report entry."""
    involved = [c.name for c in rig.cameras if any(c.name in p for p in setup.pairs)]
    cams = [Camera(c.name, start_intr[c.name], start[c.name]) for c in rig.cameras if c.name in involved]
    ego = window_ego_poses(rig, win, involved)
    travel = ego_travel_m(ego)
    t_win = time.perf_counter()
    before = dict(setup.timings.seconds)
    j = _judge_phases(rig, setup, cams, win, ego, start)
    res = j.result or MethodResult(dict(start), iterations=0, converged=False)
    after = {**start, **res.sensor_to_ego}
    sigma = usable_sigmas(res.pair_rotation_sigma_deg)
    verdict, fused, z = _against_in_effect(setup, j.verdict, start, in_effect_sigma, after, sigma, travel)
    j = replace(j, verdict=_still_explained(verdict, travel))
    intr = dict(start_intr)
    if j.verdict.accepted:
        intr.update({n: start_intr[n].with_focal_scale(s) for n, s in res.focal_scale.items()})
    moved = translation_changes(start, after, setup.pairs)
    report = {
        "index": k, "frames": [f.id for f in win], "timestamp_us": int(win[0].timestamp_us),
        "accepted": j.verdict.accepted,
        "rule": j.verdict.rule,
        "reason": j.verdict.reason,
        "rules_fired": [{"rule": r, "reason": why} for r, why in j.verdict.fired_list()],
        "same_camera_links": _links_kept(j.matches),
        "links_because": j.links_for,
        "view_phases": j.phases,
        "view_phases_because": j.phases_for,
        "ego_travel_m": travel,
        **_fused_fields(fused),
        "disagreement_sigmas": _num(z),
        "confirms": None,
        "partial": bool(j.blocks),
        "blocks": [list(b) for b in j.blocks],
        "not_linked": j.not_linked if j.blocks else None,
        "pairs": _pair_rows(j.matches, j.used, j.result, moved, setup.rules.min_correspondences, j.blocks),
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "message": res.message,
        "rms_px_before": _num(res.rms_before_px),
        "rms_px_after": _num(res.rms_after_px),
        "max_rotation_change_deg": max(rotation_changes(start, after, setup.pairs).values(), default=0.0),
        "max_translation_change_m": max(moved.values(), default=0.0),
        "focal": _focal_rows(start_intr, j.result),
        "seconds": {s: round(setup.timings.seconds.get(s, 0.0) - before.get(s, 0.0), 3)
                    for s in setup.timings.seconds},
        "wall_seconds": round(time.perf_counter() - t_win, 3),
    }
    if fused is not None:
        return WindowResult(j.verdict, {**after, **fused.extrinsics}, report, intr, fused.pair_sigma_deg)
    return WindowResult(j.verdict, after, report, intr, sigma)


def _calibrate(rig: Rig, setup: Setup) -> tuple[Rig, dict]:
    old_block = rig.extra.get("calibration") if isinstance(rig.extra, Mapping) else None
    history: list[dict] = list(old_block.get("history", [])) if isinstance(old_block, Mapping) else []
    input_ext = {c.name: np.asarray(c.sensor_to_ego, dtype=np.float64) for c in rig.cameras}
    input_intr = {c.name: c.intrinsics for c in rig.cameras}
    current, current_intr = dict(input_ext), dict(input_intr)
    reports = []
    pending = None  # a window that disagreed with the calibration in effect, awaiting the next one's confirmation
    for k, win in enumerate(_windows(setup.frames, setup.window)):
        ts = int(win[0].timestamp_us)
        in_effect = calibration_at({"history": history}, ts)
        start = {**input_ext, **(in_effect or dict(current))}
        start_intr = {**input_intr, **(intrinsics_at({"history": history}, ts) if in_effect else current_intr)}
        sigma = pair_sigmas_at({"history": history}, ts, rig.root) if in_effect else {}
        res, pending = _change_confirmed(setup, _calibrate_window(rig, setup, k, win, start, start_intr, sigma),
                                         pending)
        if res.verdict.accepted:
            current, current_intr = res.after, res.intrinsics
            if setup.method != "none":
                since = res.report["confirms"]["timestamp_us"] if res.report["confirms"] else ts
                entry = {"from_timestamp_us": since, "window": k, "method": setup.method,
                         "sensor_to_ego": _matrix_dict(res.after)}
                if res.report["focal"]:
                    entry["intrinsics"] = {n: m.to_dict() for n, m in res.intrinsics.items()}
                entry["pair_rotation_sigma_deg"] = [[a, b, s] for (a, b), s in res.pair_sigma_deg.items()]
                if res.report["fused_weights"] is not None:
                    entry["fused_with_previous"] = True
                if res.report["confirms"]:
                    entry["confirms_window"] = res.report["confirms"]["window"]
                history.append(entry)
        reports.append(res.report)
    block = _block(setup, reports, history)
    final = calibration_at({"history": history}, int(1 << 62)) if setup.method != "none" else None
    final_intr = intrinsics_at({"history": history}, int(1 << 62)) if final is not None else current_intr
    final = {**input_ext, **(final or current)}
    return rig.with_extrinsics(final).with_intrinsics(final_intr).with_extra(calibration=block), block


def _block(setup: Setup, reports: list[dict], history: list[dict]) -> dict:
    """The calibration block of the output rig."""
    accepted_any = any(w["accepted"] for w in reports)
    first_rejected = next((w for w in reports if not w["accepted"]), None)
    return {
        "version": CALIB_VERSION,
        "method": setup.method,
        "matcher": setup.matcher,
        "reference": setup.reference,
        "window": setup.window,
        "rules": setup.rules.to_dict(),
        "keypoint_refinement": setup.match.refine and setup.matcher == "sift",
        "accepted": accepted_any,
        "rule": None if accepted_any or first_rejected is None else first_rejected["rule"],
        "reason": None if accepted_any or first_rejected is None else first_rejected["reason"],
        "rules_fired": [{"window": w["index"], **f} for w in reports for f in w["rules_fired"]],
        "partial_windows": [w["index"] for w in reports if w["accepted"] and w["partial"]],
        "windows": reports,
        "history": history,
        "seconds": {s: round(v, 3) for s, v in setup.timings.seconds.items()},
    }


def _num(x: float) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None
