"""Correspondences between adjacent cameras over a window: all T x T frame pairs of each adjacent pair,
restricted to the predicted overlap, as unit rays, with outliers removed per image pair."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, is_dataclass, replace

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..errors import InputError
from ..progress import progress
from ..threads import opencv_threads
from .dense_pairs import DenseConfig, frame_matches, same_orientation_view
from .features import Keypoints, load_loftr, loftr_match, mark_fixed, match_descriptors, sift_features, to_gray
from .guided import GuidedConfig, guided_search
from .outliers import epipolar_angle_deg, essential_inliers, mount_consensus
from .overlap import OverlapGrid, overlap_grid, pixels_per_radian
from .refine import RefineConfig, apply_positions, refine_matches
from .static_world import StaticConfig, mark_window, static_consistent
from .views import VIEW_INTERPOLATIONS, VirtualView, overlap_view

MATCHERS = ("sift", "loftr")
STAGES = ("features", "matching", "ransac", "adjustment")
# sub-pixel phases of the overlap views (x, y), in the order `MatchConfig.view_phases` takes them: the second is
# the farthest from the first, the four together a half-pixel lattice
VIEW_PHASES = ((0.0, 0.0), (0.5, 0.5), (0.5, 0.0), (0.0, 0.5))


@dataclass(frozen=True)
class MatchConfig:
    """Settings of correspondence search and outlier removal."""

    matcher: str = "sift"
    loftr_weights: str | None = None
    max_features: int = 4000
    contrast_threshold: float = 0.02
    # SIFT's scales per octave (Lowe's 3); 5 lowered the worst pair on the development seeds but not on the
    # report seeds (session 17, docs/results/issue-17-calibration.md): opt-in
    octave_layers: int = 3
    feature_scale: float = 1.0
    ratio: float = 0.8
    margin_px: float = 24.0
    epipolar_gate_deg: float = 5.0
    ransac_threshold_px: float = 1.0
    ransac_prob: float = 0.999
    max_per_view_pair: int = 150
    min_per_view_pair: int = 8
    sigma_per_size: float = 1.0 / 32.0
    sigma_floor_px: float = 0.1
    loftr_sigma_px: float = 0.5
    fisheye_views: bool = True
    pinhole_views: bool = True
    view_upsample: float = 1.0
    view_pair_scale: str = "min"
    level_views: bool = False
    antialias_views: bool = False
    view_interpolation: str = "lanczos"  # how views sample their camera: views.VIEW_INTERPOLATIONS
    # calibrate: each window matched and adjusted this many times (1-4), the views' pixel grids moved by the first
    # VIEW_PHASES, the accepted runs' extrinsics averaged (SIFT's positions on a resampled view vary with the
    # grid's sub-pixel phase; averaging lowers that part of the error, at that many times the work)
    view_phases: int = 1
    view_phase: tuple[float, float] = (0.0, 0.0)  # the phase of this matching run (set by calibrate per run)
    # calibrate, with view_phases = 1: an accepted window whose adjacent pair comes out with a rotation 1-sigma above
    # auto_phases_sigma_deg is matched and adjusted again at the other VIEW_PHASES and the mean kept, as with
    # view_phases = 4 (the same reasoning as auto_links_sigma_deg below; windows whose pairs are better determined
    # than that, e.g. every preset and the real DDAD sample, run once)
    auto_phases: bool = True
    auto_phases_sigma_deg: float = 0.02
    cross_time: bool = True
    guided_below: int = 0  # > 0: guided matching on camera pairs whose best observation pair has fewer inliers
    consensus_px: float = 1.5
    mount_check_px: float = 0.0  # > 0: every observation pair keeps only matches within this of the pair's one mount
    guided_cross_time: bool = True
    temporal_links: bool = False  # same-camera matches between consecutive frames that extend the pairs' tracks
    mono_links: bool = False  # with temporal_links: keep every verified same-camera match, not only the pairs' tracks
    # calibrate: a window whose adjacent pair keeps no same-frame observation pair passing beta and comes out of the
    # adjustment with a rotation 1-sigma above auto_links_sigma_deg is matched and adjusted again with both of the
    # above (errors run 1.4-4 sigmas, the target bound is 0.05 deg: a pair beyond 0.02 deg is likely out of it)
    auto_links: bool = True
    auto_links_sigma_deg: float = 0.02
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    static: StaticConfig = field(default_factory=StaticConfig)  # matches across time on static points only
    # sub-pixel patch alignment of the verified keypoints along their tracks (`refine.py`): True, False, or "auto",
    # on when the rig has a non-pinhole camera (`refines_keypoints`)
    refine: bool | str = "auto"
    refinement: RefineConfig = field(default_factory=RefineConfig)
    # dense same-frame correspondences in each pair's overlap (`dense_pairs.py`; off by default)
    dense: DenseConfig = field(default_factory=DenseConfig)
    seed: int = 0
    threads: int = 2  # images whose features are detected, observation pairs matched at once (same results)

    def to_dict(self) -> dict:
        """JSON-able settings (for the calibration block)."""
        return {k: (asdict(v) if is_dataclass(v := getattr(self, k)) else v) for k in self.__dataclass_fields__}


def refines_keypoints(cfg: MatchConfig, cameras: Sequence[Camera]) -> bool:
    """Whether the keypoint refinement runs on a rig of `cameras`: `cfg.refine`, where "auto" means on exactly when
    a camera is not a pinhole. SIFT keypoints on the pinhole views resampled from fisheye images are what the
    alignment fixes; on pinhole rigs it costs nuScenes' noisy-start median (README, issue #17, sessions 7-8)."""
    if cfg.refine == "auto":
        return any(not isinstance(c.intrinsics, Pinhole) for c in cameras)
    if not isinstance(cfg.refine, bool):
        raise InputError(None, "refine", f"unknown refine setting {cfg.refine!r} (expected True, False or 'auto')")
    return cfg.refine


@dataclass(frozen=True)
class ObservationPair:
    """One observation pair (two images: camera a at window frame t, camera b at t2) and its match counts.

    `inliers` is what the verification kept, `kept` how many of them the pair's PairMatches holds (0 when
    fewer than the matcher's floor, at most `max_per_view_pair`)."""

    t: int
    t2: int
    tentative: int
    gated: int
    inliers: int
    kept: int

    def to_dict(self) -> dict:
        """JSON-able counts."""
        return {"t": self.t, "t2": self.t2, "tentative": self.tentative, "after_gate": self.gated,
                "inliers": self.inliers}


@dataclass
class PairMatches:
    """Inlier correspondences of one adjacent camera pair (a, b) over a window (frames are window indices)."""

    cam_a: str
    cam_b: str
    frame_a: np.ndarray
    frame_b: np.ndarray
    uv_a: np.ndarray
    uv_b: np.ndarray
    rays_a: np.ndarray
    rays_b: np.ndarray
    sigma_a: np.ndarray
    sigma_b: np.ndarray
    kp_a: np.ndarray  # keypoint index in image (frame_a, cam_a), -1 when the matcher has no keypoints
    kp_b: np.ndarray
    tentative: int = 0
    gated: int = 0
    inliers: int = 0
    view_pairs: int = 0
    observation_pairs: list[ObservationPair] = field(default_factory=list)
    links: list[PairMatches] = field(default_factory=list)  # same-camera track links (`temporal_links`)
    standalone: bool = False  # a link set kept whole (`mono_links`), not only where it touches the pair's tracks

    def __len__(self) -> int:
        return int(self.frame_a.shape[0])

    def select(self, keep: np.ndarray) -> PairMatches:
        """A copy restricted to some correspondences (counts kept)."""
        n = int(np.count_nonzero(keep)) if keep.dtype == bool else int(keep.size)
        return PairMatches(self.cam_a, self.cam_b, self.frame_a[keep], self.frame_b[keep], self.uv_a[keep],
                           self.uv_b[keep], self.rays_a[keep], self.rays_b[keep], self.sigma_a[keep],
                           self.sigma_b[keep], self.kp_a[keep], self.kp_b[keep], self.tentative, self.gated, n,
                           self.view_pairs, list(self.observation_pairs), list(self.links))

    def observed_with(self, beta: int) -> PairMatches:
        """Only the correspondences of observation pairs with at least `beta` inliers (the paper's beta)."""
        good = {(o.t, o.t2) for o in self.observation_pairs if o.inliers >= beta and o.kept > 0}
        keep = np.array([(int(x), int(y)) in good for x, y in zip(self.frame_a, self.frame_b)], dtype=bool)
        out = self.select(keep)
        out.inliers = int(sum(o.inliers for o in self.observation_pairs if (o.t, o.t2) in good))
        out.view_pairs = len(good)
        out.links = [_touching(link, out) for link in self.links]
        return out

    def same_frame_views(self, beta: int) -> int:
        """How many same-frame observation pairs (camera a and b at one frame) pass `beta`."""
        return sum(o.t == o.t2 and o.inliers >= beta and o.kept > 0 for o in self.observation_pairs)

    def same_time(self) -> PairMatches:
        """Only the correspondences between images of the same frame."""
        return self.select(self.frame_a == self.frame_b)


def _touching(link: PairMatches, pm: PairMatches) -> PairMatches:
    """The same-camera links of `link` that touch a keypoint of `pm`'s correspondences."""
    if link.standalone:
        return link
    ends = set()
    for cam, frames, kps in ((pm.cam_a, pm.frame_a, pm.kp_a), (pm.cam_b, pm.frame_b, pm.kp_b)):
        if cam == link.cam_a:
            ends.update(zip(frames.tolist(), kps.tolist()))
    keep = np.array([(fa, ka) in ends or (fb, kb) in ends for fa, ka, fb, kb in
                     zip(link.frame_a.tolist(), link.kp_a.tolist(), link.frame_b.tolist(), link.kp_b.tolist())], bool)
    return link.select(keep.reshape(-1))


@dataclass
class Timings:
    """Seconds spent per stage."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    def add(self, stage: str, t0: float) -> None:
        """Add the time since `t0` (time.perf_counter) to a stage."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0

    def share(self, t0: float, busy: dict[str, float]) -> None:
        """Add the time since `t0` to stages that ran side by side in threads, split in proportion to each
        stage's summed thread time `busy` (so the stages still add up to the wall time)."""
        total = sum(busy.values())
        wall = time.perf_counter() - t0
        for stage, s in busy.items():
            self.seconds[stage] = self.seconds.get(stage, 0.0) + (wall * s / total if total > 0 else 0.0)


def _empty(a: str, b: str) -> PairMatches:
    z2, z3, zi, z = np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0)
    return PairMatches(a, b, zi, zi, z2, z2, z3, z3, z, z, zi, zi)


@dataclass
class Tentative:
    """Tentative matches of one observation pair (camera a at frame t, camera b at frame t2)."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    sigma_a: np.ndarray
    sigma_b: np.ndarray
    kp_a: np.ndarray
    kp_b: np.ndarray


@dataclass
class Verified:
    """The verified correspondences of one observation pair and its counts (`part` is None when none);
    `guided`: guided matches were added (`guided.py`)."""

    pair: ObservationPair
    part: dict[str, np.ndarray] | None
    guided: bool = False


def find_correspondences(
    cameras: Sequence[Camera],
    pairs: Sequence[tuple[str, str]],
    ego_to_world: np.ndarray,
    image: Callable[[int, str], np.ndarray],
    masks: dict[str, np.ndarray] | None = None,
    config: MatchConfig | None = None,
    timings: Timings | None = None,
    show_progress: bool | None = None,
) -> list[PairMatches]:
    """Correspondences of every adjacent pair over the window whose ego poses are `ego_to_world` (T, 4, 4).

    `image(t, camera)` returns the RGB image of a camera at window frame t; `masks` (True = use) hides the
    ego body. The initial extrinsics of `cameras` predict the overlaps and the loose epipolar gate.
    `ego_to_world` may also be (T, M, 4, 4): each camera's own ego pose at its capture (cameras in the
    order of `cameras`). Stages: overlap prediction, features, tentative matches and verification per
    observation pair (two images), assembly per camera pair, then the same-camera links (`temporal_links`).
    """
    cfg = config or MatchConfig()
    window = match_window(cameras, pairs, ego_to_world, image, masks, cfg, timings, show_progress)
    return with_links(window, cfg, timings)


@dataclass
class WindowMatches:
    """A window's correspondences without same-camera links, and what `with_links` needs to add them later
    without detecting and matching again: the features, the cameras, their poses per frame, the keypoints'
    refined positions (None without the refinement)."""

    pairs: list[PairMatches]
    feats: dict[tuple[int, str, str], Keypoints] | None
    cams: dict[str, Camera]
    poses: dict[str, np.ndarray]
    positions: dict | None
    frames: int


def match_window(
    cameras: Sequence[Camera], pairs: Sequence[tuple[str, str]], ego_to_world: np.ndarray,
    image: Callable[[int, str], np.ndarray], masks: dict[str, np.ndarray] | None = None,
    config: MatchConfig | None = None, timings: Timings | None = None, show_progress: bool | None = None,
) -> WindowMatches:
    """`find_correspondences` up to the same-camera links (which `config`'s link settings do not change)."""
    cfg = _checked(config or MatchConfig())
    cfg = replace(cfg, refine=refines_keypoints(cfg, cameras))
    timings = timings or Timings()
    cams = {c.name: c for c in cameras}
    ego = capture_poses(ego_to_world, len(cameras))
    T = ego.shape[0]
    ego_of = {c.name: ego[:, i] for i, c in enumerate(cameras)}
    grids = predict_overlaps(cams, pairs, ego_of, cfg, timings)
    poses = {n: np.einsum("tij,jk->tik", ego_of[n], cams[n].sensor_to_ego) for n in ego_of}
    images = _ImageCache(image)
    loftr = load_loftr(cfg.loftr_weights) if cfg.matcher == "loftr" else None
    feats, view_images = None, {}
    if loftr is None:
        feats = _window_features(cameras, cams, pairs, grids, T, images, masks, poses, cfg, timings, show_progress,
                                 view_images)

        def match(a: str, b: str, t: int, t2: int) -> Tentative:
            return _static_only(_sift_tentative(feats, grids, a, b, t, t2, cfg), feats, cams, a, b, t, t2,
                                _rel(poses, a, b, t, t2), cfg)
    else:
        def match(a: str, b: str, t: int, t2: int) -> Tentative:
            return _loftr_tentative(loftr, images, grids, cams, masks, a, b, t, t2, cfg)
    densify = _guided_densifier(feats, view_images, grids, cams, cfg) if loftr is None else None
    verified = _verify_all(cams, pairs, T, poses, match, cfg, timings, show_progress, densify)
    if densify is not None or (feats is not None and cfg.mount_check_px > 0):
        t0 = time.perf_counter()
        verified = {(a, b): _consistent(cams[a], cams[b], verified[(a, b)], poses[a], poses[b], cfg)
                    for a, b in pairs}
        timings.add("ransac", t0)
    if feats is not None and cfg.dense.enabled:
        verified = _with_dense(cams, pairs, poses, verified, view_images, images, masks, cfg, timings)
    out = [assemble_pair(a, b, verified[(a, b)]) for a, b in pairs]
    positions = None
    if feats is not None and cfg.refine:
        t0 = time.perf_counter()
        out, facts = refine_matches(out, view_images, cams, poses, cfg.refinement)
        positions = facts["positions"]
        timings.add("refine", t0)
    return WindowMatches(out, feats, cams, poses, positions, T)


def with_links(window: WindowMatches, config: MatchConfig, timings: Timings | None = None) -> list[PairMatches]:
    """The window's pairs, each with its same-camera links when `config.temporal_links` asks for them (SIFT
    only); the pairs of `window` are left as they are (a new PairMatches per pair carries the links)."""
    if not (config.temporal_links and config.cross_time and window.frames > 1 and window.feats is not None):
        return window.pairs
    timings = timings or Timings()
    t0 = time.perf_counter()
    out = []
    for pm in window.pairs:
        links = temporal_links(window.cams, pm, window.feats, window.poses, config, window.frames)
        if window.positions is not None:  # links share keypoints with the tracks: the same refined positions
            links = [apply_positions(link, window.positions, window.cams) for link in links]
        out.append(replace(pm, links=links))
    timings.add("matching", t0)
    return out


def _with_dense(cams: dict[str, Camera], pairs: Sequence[tuple[str, str]], poses: dict[str, np.ndarray],
                verified: dict[tuple[str, str], list[Verified]], view_images: dict, images: _ImageCache,
                masks: dict[str, np.ndarray] | None, cfg: MatchConfig, timings: Timings
                ) -> dict[tuple[str, str], list[Verified]]:
    """Each same-frame observation pair with the verified dense matches of its overlap added (`dense_pairs`)."""
    rng = np.random.default_rng(cfg.seed + 1)
    vcfg = replace(cfg, max_per_view_pair=cfg.dense.max_per_frame, ransac_threshold_px=cfg.dense.ransac_threshold_px)
    interpolation = VIEW_INTERPOLATIONS[cfg.view_interpolation]
    out = dict(verified)
    for a, b in pairs:
        first = view_images.get((0, a, b))
        if first is None:
            continue
        t0 = time.perf_counter()
        view_b = same_orientation_view(first.view, cams[b])
        mask_b = None if masks is None or b not in masks else np.asarray(masks[b], bool)
        merged = []
        for v in verified[(a, b)]:
            t = v.pair.t
            if t != v.pair.t2 or (t, a, b) not in view_images:
                merged.append(v)
                continue
            va = view_images[(t, a, b)]
            uv_a, uv_b = frame_matches(cams[a], cams[b], va.view, va.gray, va.usable, view_b, images(t, b), mask_b,
                                       interpolation, cfg.dense)
            timings.add("matching", t0)
            t0 = time.perf_counter()
            sig, kp = np.full(len(uv_a), cfg.dense.sigma_px), np.full(len(uv_a), -1)
            dense = verify_observation_pair(cams[a], cams[b], t, t, Tentative(uv_a, uv_b, sig, sig, kp, kp),
                                            _rel(poses, a, b, t, t), vcfg, rng)
            merged.append(_merged(v, dense))
            timings.add("ransac", t0)
            t0 = time.perf_counter()
        out[(a, b)] = merged
    return out


def _merged(v: Verified, dense: Verified) -> Verified:
    """One observation pair's verified matches with its dense ones added (counts summed)."""
    if dense.part is None:
        return v
    p, d = v.pair, dense.pair
    counts = replace(p, tentative=p.tentative + d.tentative, gated=p.gated + d.gated, inliers=p.inliers + d.inliers,
                     kept=p.kept + d.kept)
    part = dense.part if v.part is None else {k: np.concatenate([v.part[k], dense.part[k]]) for k in v.part}
    return Verified(counts, part, v.guided)


def _window_features(cameras: Sequence[Camera], cams: dict[str, Camera], pairs: Sequence[tuple[str, str]],
                     grids: dict, T: int, images: _ImageCache, masks: dict[str, np.ndarray] | None,
                     poses: dict[str, np.ndarray], cfg: MatchConfig, timings: Timings, show_progress: bool | None,
                     view_images: dict) -> dict:
    """SIFT features of every involved camera over the window, marked static or moving when asked."""
    involved = sorted({n for p in pairs for n in p}, key=[c.name for c in cameras].index)
    feats = detect_features(cams, involved, grids, T, images, masks, cfg, timings, show_progress, view_images)
    if cfg.cross_time and cfg.static.enabled and T > 1:
        t0 = time.perf_counter()
        mark_window(feats, {n: c.intrinsics for n, c in cams.items()}, poses, cfg.static)
        timings.add("features", t0)
    return feats


def _guided_densifier(feats: dict, view_images: dict, grids: dict, cams: dict[str, Camera], cfg: MatchConfig
                      ) -> Callable[[str, str, int, int, np.ndarray, Tentative], Tentative | None] | None:
    """Guided matching along the starting rig's epipolar band for sparse observation pairs (None when off)."""
    if cfg.guided_below <= 0:
        return None

    def densify(a: str, b: str, t: int, t2: int, rel: np.ndarray, tent: Tentative) -> Tentative | None:
        return _guided_tentative(feats, view_images, grids, cams, a, b, t, t2, rel, tent, cfg)
    return densify


def _checked(cfg: MatchConfig) -> MatchConfig:
    """The config, after checking its named choices (one clear error for an unknown one)."""
    if cfg.matcher not in MATCHERS:
        raise InputError(None, "matcher", f"unknown matcher {cfg.matcher!r} (expected {', '.join(MATCHERS)})")
    if cfg.view_interpolation not in VIEW_INTERPOLATIONS:
        raise InputError(None, "view_interpolation", f"unknown interpolation {cfg.view_interpolation!r} "
                         f"(expected {', '.join(VIEW_INTERPOLATIONS)})")
    return cfg


def temporal_links(cams: dict[str, Camera], pm: PairMatches, feats: dict, poses: dict[str, np.ndarray],
                   cfg: MatchConfig, T: int) -> list[PairMatches]:
    """For each camera of pair `pm`, matches of its overlap view's keypoints between consecutive frames
    (verified against the known ego motion) that touch a keypoint of the pair's verified correspondences.

    They join a correspondence's keypoint to the same point in the camera's next frame, so the adjustment's
    tracks see a point from both cameras at several frames: its depth is then fixed by the ego motion (a
    baseline of metres) instead of by the mount's baseline alone, which separates a narrow pair's rotation
    from its translation. Keypoints that stay at one pixel (`mark_fixed`: at infinity or moving with the
    car) or move unlike a static point are left out, and so are the ends of same-frame correspondences whose
    range disagrees with what their cameras' frames say (`static_world`: an object that drives along).
    With `cfg.mono_links` every verified match is kept, as a `standalone` link set."""
    rng = np.random.default_rng(cfg.seed)
    unlimited = replace(cfg, max_per_view_pair=1 << 30)
    links = []
    static = None if cfg.mono_links else _static_correspondences(pm, feats, poses, cfg)
    ends = ((pm.cam_a, pm.cam_b, pm.frame_a, pm.kp_a), (pm.cam_b, pm.cam_a, pm.frame_b, pm.kp_b))
    for cam, other, frames, kps in ends:
        used = None if static is None else {t: set(kps[(frames == t) & static].tolist()) for t in range(T)}
        verified = []
        for t in range(T - 1):
            if used is not None and not (used[t] or used[t + 1]):
                continue
            fa, fb = feats[(t, cam, other)], feats[(t + 1, cam, other)]
            tent = _descriptor_matches(fa.subset(fa.across_time), fb.subset(fb.across_time), cfg)
            rel = _rel(poses, cam, cam, t, t + 1)
            v = verify_observation_pair(cams[cam], cams[cam], t, t + 1, tent, rel, unlimited, rng)
            if v.part is None:
                continue
            if used is None:
                touch = np.ones(len(v.part["ka"]), dtype=bool)
            else:
                touch = np.isin(v.part["ka"], list(used[t])) | np.isin(v.part["kb"], list(used[t + 1]))
            if touch.any():
                part = {k: x[touch] for k, x in v.part.items()}
                verified.append(Verified(replace(v.pair, kept=int(touch.sum())), part))
        if verified:
            link = assemble_pair(cam, cam, verified)
            link.standalone = cfg.mono_links
            links.append(link)
    return links


def _static_correspondences(pm: PairMatches, feats: dict, poses: dict[str, np.ndarray], cfg: MatchConfig
                            ) -> np.ndarray:
    """Per correspondence of `pm`: consistent with a static point (cross-time ones passed the gate already;
    same-frame ones on an object that drives along are valid matches but no static point)."""
    ok = np.ones(len(pm), dtype=bool)
    if not cfg.static.enabled:
        return ok
    for t in np.unique(pm.frame_a[pm.frame_a == pm.frame_b]):
        sel = np.flatnonzero((pm.frame_a == t) & (pm.frame_b == t))
        ok[sel] = static_consistent(pm.kp_a[sel], pm.kp_b[sel], pm.rays_a[sel], pm.rays_b[sel],
                                  feats[(int(t), pm.cam_a, pm.cam_b)], feats[(int(t), pm.cam_b, pm.cam_a)],
                                  _rel(poses, pm.cam_a, pm.cam_b, int(t), int(t)), cfg.static)
    return ok


def _verify_all(cams: dict[str, Camera], pairs: Sequence[tuple[str, str]], T: int, poses: dict[str, np.ndarray],
                match: Callable[[str, str, int, int], Tentative], cfg: MatchConfig, timings: Timings,
                show_progress: bool | None, densify: Callable | None = None) -> dict[tuple[str, str], list[Verified]]:
    """Tentative matches and verification of every observation pair (all T x T, or same-frame only). A camera
    pair none of whose observation pairs reached `cfg.guided_below` inliers (a narrow overlap) is matched
    again with `densify` added to every observation pair."""
    rng = np.random.default_rng(cfg.seed)
    verified: dict[tuple[str, str], list[Verified]] = {(a, b): [] for a, b in pairs}
    tentative: dict[tuple[str, str], list[Tentative]] = {(a, b): [] for a, b in pairs}
    jobs = [(a, b, t, t2) for a, b in pairs for t in range(T) for t2 in range(T) if cfg.cross_time or t == t2]

    def screen(a: str, b: str, t: int, t2: int) -> tuple[Tentative, _Screened, float, float]:
        t0 = time.perf_counter()
        tent = match(a, b, t, t2)
        t1 = time.perf_counter()
        scr = screen_observation_pair(cams[a], cams[b], tent, _rel(poses, a, b, t, t2), cfg)
        return tent, scr, t1 - t0, time.perf_counter() - t1

    # matching and RANSAC of the observation pairs side by side; the random subsets are drawn in job order
    busy = {"matching": 0.0, "ransac": 0.0}
    t_pool = time.perf_counter()
    with opencv_threads(1), ThreadPoolExecutor(max(1, cfg.threads)) as pool:
        futures = [pool.submit(screen, *job) for job in jobs]
        for (a, b, t, t2), fut in progress(list(zip(jobs, futures)), desc="calibrate: matching", total=len(jobs),
                                           enabled=show_progress):
            tent, scr, dm, dr = fut.result()
            busy["matching"] += dm
            busy["ransac"] += dr
            verified[(a, b)].append(verify_observation_pair(cams[a], cams[b], t, t2, tent, None, cfg, rng, scr))
            tentative[(a, b)].append(tent)
    timings.share(t_pool, busy)
    if densify is None:
        return verified
    for a, b in pairs:
        if max((v.pair.inliers for v in verified[(a, b)]), default=0) >= cfg.guided_below:
            continue
        for k, (v, tent) in enumerate(zip(verified[(a, b)], tentative[(a, b)])):
            t, t2 = v.pair.t, v.pair.t2
            if not (cfg.guided_cross_time or t == t2):
                continue
            t0 = time.perf_counter()
            more = densify(a, b, t, t2, _rel(poses, a, b, t, t2), tent)
            timings.add("matching", t0)
            if more is not None and len(more.uv_a):
                t0 = time.perf_counter()
                verified[(a, b)][k] = verify_observation_pair(cams[a], cams[b], t, t2, _joined(tent, more),
                                                              _rel(poses, a, b, t, t2), cfg, rng)
                verified[(a, b)][k].guided = True
                timings.add("ransac", t0)
    return verified


def _rel(poses: dict[str, np.ndarray], a: str, b: str, t: int, t2: int) -> np.ndarray:
    """Starting relative pose: camera a at frame t -> camera b at frame t2."""
    return np.linalg.inv(poses[b][t2]) @ poses[a][t]


def capture_poses(ego_to_world: np.ndarray, n_cameras: int) -> np.ndarray:
    """Ego poses per frame and camera (T, M, 4, 4) from (T, 4, 4) (synchronous) or (T, M, 4, 4)."""
    ego = np.asarray(ego_to_world, dtype=np.float64)
    if ego.ndim == 3:
        return np.repeat(ego[:, None], n_cameras, axis=1)
    if ego.ndim != 4 or ego.shape[1] != n_cameras:
        raise ValueError(f"ego poses must be (T, 4, 4) or (T, {n_cameras}, 4, 4), got {ego.shape}")
    return ego


class _ImageCache:
    """Each image is read once."""

    def __init__(self, image: Callable[[int, str], np.ndarray]) -> None:
        self.image, self.cache = image, {}

    def __call__(self, t: int, name: str) -> np.ndarray:
        if (t, name) not in self.cache:
            self.cache[(t, name)] = self.image(t, name)
        return self.cache[(t, name)]


def predict_overlaps(cams: dict[str, Camera], pairs: Sequence[tuple[str, str]], ego_of: dict[str, np.ndarray],
                     cfg: MatchConfig, timings: Timings) -> dict[tuple[str, str], OverlapGrid]:
    """Overlap grids of every adjacent pair in both directions, from the initial extrinsics."""
    t0 = time.perf_counter()
    grids: dict[tuple[str, str], OverlapGrid] = {}
    for a, b in pairs:
        grids[(a, b)] = overlap_grid(cams[a], cams[b], ego_of[a], cfg.margin_px, ego_to_world_b=ego_of[b])
        grids[(b, a)] = overlap_grid(cams[b], cams[a], ego_of[b], cfg.margin_px, ego_to_world_b=ego_of[a])
    timings.add("matching", t0)
    return grids


def detect_features(
    cams: dict[str, Camera], involved: Sequence[str], grids: dict[tuple[str, str], OverlapGrid], T: int,
    images: Callable[[int, str], np.ndarray], masks: dict[str, np.ndarray] | None, cfg: MatchConfig,
    timings: Timings, show_progress: bool | None, view_images: dict | None = None,
) -> dict[tuple[int, str, str], Keypoints]:
    """SIFT keypoints per (frame, camera, neighbour): on the raw image inside the predicted overlaps, or on a
    virtual pinhole view aimed at the overlap; `view_images`, when given, receives each view's ViewImage."""
    t0 = time.perf_counter()
    feats: dict[tuple[int, str, str], Keypoints] = {}
    # one image per thread, each OpenCV call in its own thread (SIFT's own stripes gain 1.3x on 2 cores, this 1.8x)
    with opencv_threads(1), ThreadPoolExecutor(max(1, cfg.threads)) as pool:
        jobs = {}
        for name in involved:
            raw, views, static, det = _detection_plan(cams, name, grids, masks, cfg)
            jobs[name] = (raw, views, [pool.submit(_image_features, cams[name], images(t, name), det, views, static,
                                                   cfg) for t in range(T)])
        for name in progress(involved, desc="calibrate: features", enabled=show_progress):
            raw, views, per_frame = jobs[name]
            for t, job in enumerate(per_frame):
                kp, per_view = job.result()
                for o in raw:
                    feats[(t, name, o)] = kp
                for o, (kv, vim) in per_view.items():
                    feats[(t, name, o)] = kv
                    if view_images is not None:
                        view_images[(t, name, o)] = vim
            if cfg.cross_time and T > 1:
                for o in [*views, *raw[:1]]:
                    mark_fixed([feats[(t, name, o)] for t in range(T)])
    timings.add("features", t0)
    return feats


def _detection_plan(cams: dict[str, Camera], name: str, grids: dict[tuple[str, str], OverlapGrid],
                    masks: dict[str, np.ndarray] | None, cfg: MatchConfig) -> tuple[list[str], dict, np.ndarray | None,
                                                                                    np.ndarray | None]:
    """Where camera `name`'s features are detected: the neighbours seen on the raw image, the virtual view per
    other neighbour, its static mask, and the raw image's detection mask (None when no neighbour uses it)."""
    cam = cams[name]
    neighbours = [o for (x, o) in grids if x == name]
    views = _overlap_views(cams, name, neighbours, grids, cfg)
    static = None if masks is None or name not in masks else np.asarray(masks[name], bool)
    raw = [o for o in neighbours if o not in views]
    if not raw:
        return raw, views, static, None
    det = np.zeros((cam.height, cam.width), np.uint8)
    for o in raw:
        det |= grids[(name, o)].any_mask(cam.width, cam.height)
    if static is not None:
        det[~static] = 0
    return raw, views, static, det


def _image_features(cam: Camera, picture: np.ndarray, det: np.ndarray | None, views: dict[str, VirtualView],
                    static: np.ndarray | None, cfg: MatchConfig) -> tuple[Keypoints | None, dict]:
    """SIFT of one image: on the raw image inside `det` (None: not asked) and on each neighbour's view."""
    kp = None if det is None else sift_features(picture, det, cfg.max_features, cfg.feature_scale,
                                                 cfg.contrast_threshold, cfg.octave_layers)
    return kp, {o: _view_features(cam, view, picture, static, slot, cfg)
                for slot, (o, view) in enumerate(views.items())}


def _overlap_views(cams: dict[str, Camera], name: str, neighbours: Sequence[str],
                   grids: dict[tuple[str, str], OverlapGrid], cfg: MatchConfig) -> dict[str, VirtualView]:
    """Per neighbour, the virtual pinhole view of camera `name` aimed at their overlap (fisheyes: at the
    fisheye's own resolution; pinholes: at the pair's common one, cropped), where the settings ask for one."""
    cam = cams[name]
    fisheye = not isinstance(cam.intrinsics, Pinhole)
    if (fisheye and not cfg.fisheye_views) or (not fisheye and not cfg.pinhole_views):
        return {}
    views = {}
    for o in neighbours:
        view = (overlap_view(cam, grids[(name, o)], upsample=cfg.view_upsample, phase=cfg.view_phase) if fisheye else
                overlap_view(cam, grids[(name, o)], other=cams[o], crop=True, upsample=cfg.view_upsample,
                             pair_scale=cfg.view_pair_scale, level=cfg.level_views, phase=cfg.view_phase))
        if view is not None:
            views[o] = view
    return views


def _sift_tentative(feats: dict, grids: dict, a: str, b: str, t: int, t2: int, cfg: MatchConfig) -> Tentative:
    """Mutual ratio-test matches of the keypoints inside each other's predicted overlap; across time without
    the keypoints that stay at one pixel (`mark_fixed`) or move unlike a static point (`static_world`)."""
    fa, fb = feats[(t, a, b)], feats[(t2, b, a)]
    sa = fa.subset(grids[(a, b)].lookup(t, t2, fa.uv) & ((t == t2) | fa.across_time))
    sb = fb.subset(grids[(b, a)].lookup(t2, t, fb.uv) & ((t == t2) | fb.across_time))
    return _descriptor_matches(sa, sb, cfg)


def _static_only(tent: Tentative, feats: dict, cams: dict[str, Camera], a: str, b: str, t: int, t2: int,
                 rel: np.ndarray, cfg: MatchConfig) -> Tentative:
    """Across time, only the tentative matches whose triangulated range agrees with what each keypoint's own
    camera says over time (`static_world.static_consistent`; rel: a at t -> b at t2, starting rig)."""
    if t == t2 or not cfg.static.enabled or not len(tent.uv_a):
        return tent
    ra, _ = cams[a].intrinsics.unproject(tent.uv_a)
    rb, _ = cams[b].intrinsics.unproject(tent.uv_b)
    keep = static_consistent(tent.kp_a, tent.kp_b, ra, rb, feats[(t, a, b)], feats[(t2, b, a)], rel, cfg.static)
    return Tentative(*(getattr(tent, k)[keep] for k in ("uv_a", "uv_b", "sigma_a", "sigma_b", "kp_a", "kp_b")))


def _descriptor_matches(sa: Keypoints, sb: Keypoints, cfg: MatchConfig) -> Tentative:
    """Mutual ratio-test matches between two keypoint sets, with their sigmas from the keypoint sizes."""
    ia, ib = match_descriptors(sa.desc, sb.desc, cfg.ratio)
    return Tentative(sa.uv[ia], sb.uv[ib], np.maximum(cfg.sigma_floor_px, sa.size[ia] * cfg.sigma_per_size),
                     np.maximum(cfg.sigma_floor_px, sb.size[ib] * cfg.sigma_per_size), sa.index[ia], sb.index[ib])


def _loftr_tentative(loftr, images, grids: dict, cams: dict, masks, a: str, b: str, t: int, t2: int,
                     cfg: MatchConfig) -> Tentative:
    """LoFTR matches inside the boxes of the predicted overlaps, outside the static masks."""
    uva, uvb = loftr_match(loftr, images(t, a), images(t2, b), _box(grids[(a, b)], t, t2, cams[a]),
                           _box(grids[(b, a)], t2, t, cams[b]))
    keep = grids[(a, b)].lookup(t, t2, uva) & grids[(b, a)].lookup(t2, t, uvb)
    if masks is not None:
        keep &= _in_mask(masks.get(a), uva) & _in_mask(masks.get(b), uvb)
    n = int(keep.sum())
    sig, kp = np.full(n, cfg.loftr_sigma_px), np.full(n, -1)
    return Tentative(uva[keep], uvb[keep], sig, sig, kp, kp)


@dataclass
class _Screened:
    """An observation pair's matches through the epipolar gate and RANSAC: their rays, the tentative and gated
    counts, and the indices of the inliers."""

    ra: np.ndarray
    rb: np.ndarray
    tentative: int
    gated: int
    inliers: np.ndarray


def screen_observation_pair(ca: Camera, cb: Camera, tent: Tentative, rel: np.ndarray, cfg: MatchConfig) -> _Screened:
    """Loose epipolar gate from the initial relative pose `rel` (a at t -> b at t2), then USAC on the essential
    matrix (no random state of ours: safe in threads)."""
    ra, va = ca.intrinsics.unproject(tent.uv_a)
    rb, vb = cb.intrinsics.unproject(tent.uv_b)
    sel = np.flatnonzero(va & vb)
    tentative = int(sel.size)
    gate = epipolar_angle_deg(ra[sel], rb[sel], rel[:3, :3], rel[:3, 3]) <= cfg.epipolar_gate_deg
    sel = sel[gate]
    focal = min(pixels_per_radian(ca.intrinsics), pixels_per_radian(cb.intrinsics))
    inl = essential_inliers(ra[sel], rb[sel], cfg.ransac_threshold_px, focal, cfg.ransac_prob, seed=cfg.seed)
    return _Screened(ra, rb, tentative, int(sel.size), sel[inl])


def verify_observation_pair(ca: Camera, cb: Camera, t: int, t2: int, tent: Tentative, rel: np.ndarray | None,
                            cfg: MatchConfig, rng: np.random.Generator, screened: _Screened | None = None) -> Verified:
    """Loose epipolar gate from the initial relative pose `rel` (a at t -> b at t2), then USAC on the
    essential matrix (or their outcome `screened`); at most `max_per_view_pair` inliers are kept (a random
    subset)."""
    scr = screened if screened is not None else screen_observation_pair(ca, cb, tent, rel, cfg)
    idx, n_inl = scr.inliers, int(scr.inliers.size)
    if n_inl < cfg.min_per_view_pair:  # a handful of matches fits a spurious essential matrix
        return Verified(ObservationPair(t, t2, scr.tentative, scr.gated, n_inl, 0), None)
    if idx.size > cfg.max_per_view_pair:
        idx = np.sort(rng.choice(idx, cfg.max_per_view_pair, replace=False))
    part = {"uva": tent.uv_a[idx], "uvb": tent.uv_b[idx], "ra": scr.ra[idx], "rb": scr.rb[idx],
            "siga": tent.sigma_a[idx], "sigb": tent.sigma_b[idx], "ka": tent.kp_a[idx], "kb": tent.kp_b[idx]}
    return Verified(ObservationPair(t, t2, scr.tentative, scr.gated, n_inl, int(idx.size)), part)


def _consistent(ca: Camera, cb: Camera, verified: list[Verified], poses_a: np.ndarray, poses_b: np.ndarray,
                cfg: MatchConfig) -> list[Verified]:
    """Guided observation pairs (with `cfg.mount_check_px` > 0 every one) keep only the matches that agree with
    one mount of the camera pair fitted to all its verified matches (`outliers.mount_consensus`), within
    `consensus_px` (guided) or `mount_check_px`; their counts become those matches. A free essential matrix per
    observation pair also fits wrong matches of a narrow, wide-baseline strip that no rigid mount explains."""
    parts = [v for v in verified if v.part is not None]
    check_all = cfg.mount_check_px > 0
    if not parts or not (check_all or any(v.guided for v in parts)):
        return verified
    rel0 = np.concatenate([np.repeat((np.linalg.inv(poses_b[v.pair.t2]) @ poses_a[v.pair.t])[None],
                                     v.part["ra"].shape[0], axis=0) for v in parts])
    focal = min(pixels_per_radian(ca.intrinsics), pixels_per_radian(cb.intrinsics))
    _, err = mount_consensus(rel0, np.concatenate([v.part["ra"] for v in parts]),
                             np.concatenate([v.part["rb"] for v in parts]), focal)
    out, start = [], 0
    ends = {id(v): (start := start + v.part["ra"].shape[0]) for v in parts}
    for v in verified:
        if v.part is None or not (v.guided or check_all):
            out.append(v)
            continue
        n = v.part["ra"].shape[0]
        ok = np.abs(err[ends[id(v)] - n:ends[id(v)]]) <= (cfg.consensus_px if v.guided else cfg.mount_check_px)
        k = int(ok.sum())
        inliers = k if v.pair.inliers <= n else int(round(v.pair.inliers * k / n))
        counts = replace(v.pair, inliers=inliers, kept=k if k >= cfg.min_per_view_pair else 0)
        part = {key: val[ok] for key, val in v.part.items()} if k >= cfg.min_per_view_pair else None
        out.append(Verified(counts, part, v.guided))
    return out


def assemble_pair(a: str, b: str, verified: Sequence[Verified]) -> PairMatches:
    """One PairMatches from the verified observation pairs of camera pair (a, b)."""
    parts = [(v.pair, v.part) for v in verified if v.part is not None]
    if not parts:
        pm = _empty(a, b)
    else:
        cat = {k: np.concatenate([p[k] for _, p in parts]) for k in parts[0][1]}
        pm = PairMatches(
            a, b,
            np.concatenate([np.full(p["uva"].shape[0], o.t) for o, p in parts]).astype(np.int64),
            np.concatenate([np.full(p["uva"].shape[0], o.t2) for o, p in parts]).astype(np.int64),
            cat["uva"], cat["uvb"], cat["ra"], cat["rb"], cat["siga"], cat["sigb"],
            cat["ka"].astype(np.int64), cat["kb"].astype(np.int64),
        )
        pm.inliers = int(sum(o.inliers for o, _ in parts))
    pm.tentative = int(sum(v.pair.tentative for v in verified))
    pm.gated = int(sum(v.pair.gated for v in verified))
    pm.view_pairs = len(parts)
    pm.observation_pairs = [v.pair for v in verified]
    return pm


_VIEW_INDEX_OFFSET = 1_000_000  # keypoint ids of the n-th virtual view of an image start at (n + 1) * this


@dataclass
class ViewImage:
    """A virtual view of one image: the view, its grey pixels and where they are usable (data, not masked)."""

    view: VirtualView
    gray: np.ndarray
    usable: np.ndarray


def _view_features(cam: Camera, view: VirtualView, image: np.ndarray, static: np.ndarray | None, slot: int,
                   cfg: MatchConfig) -> tuple[Keypoints, ViewImage]:
    """SIFT on a virtual pinhole view, mapped back to the camera's pixels (sizes in its centre's pixels)."""
    mask = view.valid.copy()
    if static is not None:
        mask &= view.warp(static.astype(np.uint8), cv2.INTER_NEAREST) > 0
    # colour resampled, then grey: resampling grey costs a third but moved nuscenes' seeds 0-3 (half size) from
    # 0.0124 / 0.0228 deg mean median / max to 0.0135 / 0.0268 (session 15)
    gray = to_gray(view.warp(image, VIEW_INTERPOLATIONS[cfg.view_interpolation], antialias=cfg.antialias_views))
    kv = sift_features(gray, mask.astype(np.uint8) * 255, cfg.max_features, 1.0, cfg.contrast_threshold,
                       cfg.octave_layers)
    uv, ok = cam.intrinsics.project(view.rays_in_source(kv.uv))
    scale = pixels_per_radian(cam.intrinsics) / float(view.camera.intrinsics.K[0, 0])
    return Keypoints(uv[ok], kv.desc[ok], kv.size[ok] * scale, kv.index[ok] + (slot + 1) * _VIEW_INDEX_OFFSET,
                     kv.fixed[ok], kv.uv[ok]), ViewImage(view, gray, mask)


def _rotation4(R: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = R
    return out


def _guided_tentative(feats: dict, view_images: dict, grids: dict, cams: dict[str, Camera], a: str, b: str, t: int,
                      t2: int, rel: np.ndarray, tent: Tentative, cfg: MatchConfig) -> Tentative | None:
    """Guided matches of a's keypoints not matched in `tent`, searched in b's view along the epipolar band of
    the starting relative pose `rel` (a at t -> b at t2); None without views on both sides."""
    va, vb = view_images.get((t, a, b)), view_images.get((t2, b, a))
    if va is None or vb is None:
        return None
    fa = feats[(t, a, b)]
    keep = grids[(a, b)].lookup(t, t2, fa.uv) & ((t == t2) | fa.across_time) & ~np.isin(fa.index, tent.kp_a)
    keep[np.flatnonzero(keep)[~_first_at_position(fa.view_uv[keep])]] = False
    sa = fa.subset(keep)
    rel_view = _rotation4(vb.view.R).T @ rel @ _rotation4(va.view.R)
    idx, uv_view_b = guided_search(va.gray, va.usable, vb.gray, vb.usable, sa.view_uv,
                                   va.view.camera.intrinsics.K, vb.view.camera.intrinsics.K, rel_view, cfg.guided)
    uv_b, ok = cams[b].intrinsics.project(vb.view.rays_in_source(uv_view_b))
    ok &= grids[(b, a)].lookup(t2, t, uv_b)
    idx, uv_b = idx[ok], uv_b[ok]
    sig = np.maximum(cfg.sigma_floor_px, sa.size[idx] * cfg.sigma_per_size)
    return Tentative(sa.uv[idx], uv_b, sig, sig.copy(), sa.index[idx], np.full(idx.size, -1))


def _first_at_position(uv: np.ndarray) -> np.ndarray:
    """True for the first of keypoints at one position (SIFT repeats a keypoint for each of its orientations)."""
    _, first = np.unique(np.round(uv, 2), axis=0, return_index=True)
    out = np.zeros(len(uv), dtype=bool)
    out[first] = True
    return out


def _joined(x: Tentative, y: Tentative) -> Tentative:
    """Two sets of tentative matches as one."""
    return Tentative(*(np.concatenate([getattr(x, k), getattr(y, k)]) for k in
                       ("uv_a", "uv_b", "sigma_a", "sigma_b", "kp_a", "kp_b")))


def _box(grid: OverlapGrid, t: int, t2: int, cam: Camera) -> tuple[int, int, int, int] | None:
    """Bounding box (x0, y0, x1, y1) of a coarse overlap mask, in native pixels; None when empty."""
    m = grid.mask[t, t2]
    if not m.any():
        return None
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    s = grid.stride
    return (max(0, int(cols[0]) * s - s), max(0, int(rows[0]) * s - s),
            min(cam.width, int(cols[-1]) * s + s), min(cam.height, int(rows[-1]) * s + s))


def _in_mask(mask: np.ndarray | None, uv: np.ndarray) -> np.ndarray:
    if mask is None or uv.shape[0] == 0:
        return np.ones(uv.shape[0], dtype=bool)
    h, w = mask.shape
    col = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    return np.asarray(mask, bool)[row, col]
