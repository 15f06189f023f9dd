"""Correspondences between adjacent cameras over a window: all T x T frame pairs of each adjacent pair,
restricted to the predicted overlap, as unit rays, with outliers removed per image pair."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..cameras import Camera, Pinhole
from ..errors import InputError
from ..progress import progress
from .features import Keypoints, load_loftr, loftr_match, match_descriptors, sift_features
from .outliers import epipolar_angle_deg, essential_inliers
from .overlap import OverlapGrid, overlap_grid, pixels_per_radian
from .views import VirtualView, overlap_view

MATCHERS = ("sift", "loftr")
STAGES = ("features", "matching", "ransac", "adjustment")


@dataclass(frozen=True)
class MatchConfig:
    """Settings of correspondence search and outlier removal."""

    matcher: str = "sift"
    loftr_weights: str | None = None
    max_features: int = 4000
    contrast_threshold: float = 0.02
    feature_scale: float = 1.0
    ratio: float = 0.8
    margin_px: float = 24.0
    epipolar_gate_deg: float = 5.0
    ransac_threshold_px: float = 1.0
    ransac_prob: float = 0.999
    max_per_view_pair: int = 150
    min_per_view_pair: int = 15
    sigma_per_size: float = 1.0 / 32.0
    sigma_floor_px: float = 0.1
    loftr_sigma_px: float = 0.5
    fisheye_views: bool = True
    cross_time: bool = True
    seed: int = 0

    def to_dict(self) -> dict:
        """JSON-able settings (for the calibration block)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


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

    def __len__(self) -> int:
        return int(self.frame_a.shape[0])

    def select(self, keep: np.ndarray) -> PairMatches:
        """A copy restricted to some correspondences (counts kept)."""
        n = int(np.count_nonzero(keep)) if keep.dtype == bool else int(keep.size)
        return PairMatches(self.cam_a, self.cam_b, self.frame_a[keep], self.frame_b[keep], self.uv_a[keep],
                           self.uv_b[keep], self.rays_a[keep], self.rays_b[keep], self.sigma_a[keep],
                           self.sigma_b[keep], self.kp_a[keep], self.kp_b[keep], self.tentative, self.gated, n,
                           self.view_pairs)

    def same_time(self) -> PairMatches:
        """Only the correspondences between images of the same frame."""
        return self.select(self.frame_a == self.frame_b)


@dataclass
class Timings:
    """Seconds spent per stage."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    def add(self, stage: str, t0: float) -> None:
        """Add the time since `t0` (time.perf_counter) to a stage."""
        self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


def _empty(a: str, b: str) -> PairMatches:
    z2, z3, zi, z = np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0)
    return PairMatches(a, b, zi, zi, z2, z2, z3, z3, z, z, zi, zi)


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
    """
    cfg = config or MatchConfig()
    if cfg.matcher not in MATCHERS:
        raise InputError(None, "matcher", f"unknown matcher {cfg.matcher!r} (expected {', '.join(MATCHERS)})")
    timings = timings or Timings()
    cams = {c.name: c for c in cameras}
    T = ego_to_world.shape[0]
    rng = np.random.default_rng(cfg.seed)
    loftr = load_loftr(cfg.loftr_weights) if cfg.matcher == "loftr" else None

    t0 = time.perf_counter()
    grids: dict[tuple[str, str], OverlapGrid] = {}
    for a, b in pairs:
        grids[(a, b)] = overlap_grid(cams[a], cams[b], ego_to_world, cfg.margin_px)
        grids[(b, a)] = overlap_grid(cams[b], cams[a], ego_to_world, cfg.margin_px)
    timings.add("matching", t0)

    involved = sorted({n for p in pairs for n in p}, key=[c.name for c in cameras].index)
    cache: dict[tuple[int, str], np.ndarray] = {}

    def img(t: int, name: str) -> np.ndarray:
        """Each image is read once."""
        if (t, name) not in cache:
            cache[(t, name)] = image(t, name)
        return cache[(t, name)]

    feats: dict[tuple[int, str, str], Keypoints] = {}  # (frame, camera, neighbour)
    if loftr is None:
        t0 = time.perf_counter()
        for name in progress(involved, desc="calibrate: features", enabled=show_progress):
            cam = cams[name]
            neighbours = [o for (x, o) in grids if x == name]
            views = {}
            if cfg.fisheye_views and not isinstance(cam.intrinsics, Pinhole):
                views = {o: v for o in neighbours if (v := overlap_view(cam, grids[(name, o)])) is not None}
            static = None if masks is None or name not in masks else np.asarray(masks[name], bool)
            raw = [o for o in neighbours if o not in views]
            det = np.zeros((cam.height, cam.width), np.uint8)
            for o in raw:
                det |= grids[(name, o)].any_mask(cam.width, cam.height)
            if static is not None:
                det[~static] = 0
            for t in range(T):
                picture = img(t, name)
                if raw:
                    kp = sift_features(picture, det, cfg.max_features, cfg.feature_scale, cfg.contrast_threshold)
                    for o in raw:
                        feats[(t, name, o)] = kp
                for slot, (o, view) in enumerate(views.items()):
                    feats[(t, name, o)] = _view_features(cam, view, picture, static, slot, cfg)
        timings.add("features", t0)

    out = []
    jobs = [(a, b, t, t2) for a, b in pairs for t in range(T) for t2 in range(T) if cfg.cross_time or t == t2]
    collected: dict[tuple[str, str], list] = {(a, b): [] for a, b in pairs}
    counts = {(a, b): [0, 0, 0] for a, b in pairs}
    poses = {n: np.einsum("tij,jk->tik", ego_to_world, cams[n].sensor_to_ego) for n in involved}
    for a, b, t, t2 in progress(jobs, desc="calibrate: matching", total=len(jobs), enabled=show_progress):
        ca, cb = cams[a], cams[b]
        t0 = time.perf_counter()
        if loftr is None:
            fa, fb = feats[(t, a, b)], feats[(t2, b, a)]
            sa = fa.subset(grids[(a, b)].lookup(t, t2, fa.uv))
            sb = fb.subset(grids[(b, a)].lookup(t2, t, fb.uv))
            ia, ib = match_descriptors(sa.desc, sb.desc, cfg.ratio)
            uva, uvb = sa.uv[ia], sb.uv[ib]
            ka, kb = sa.index[ia], sb.index[ib]
            siga = np.maximum(cfg.sigma_floor_px, sa.size[ia] * cfg.sigma_per_size)
            sigb = np.maximum(cfg.sigma_floor_px, sb.size[ib] * cfg.sigma_per_size)
        else:
            uva, uvb = loftr_match(loftr, img(t, a), img(t2, b), _box(grids[(a, b)], t, t2, ca),
                                   _box(grids[(b, a)], t2, t, cb))
            keep = grids[(a, b)].lookup(t, t2, uva) & grids[(b, a)].lookup(t2, t, uvb)
            if masks is not None:
                keep &= _in_mask(masks.get(a), uva) & _in_mask(masks.get(b), uvb)
            uva, uvb = uva[keep], uvb[keep]
            siga = sigb = np.full(uva.shape[0], cfg.loftr_sigma_px)
            ka = kb = np.full(uva.shape[0], -1)
        timings.add("matching", t0)
        t0 = time.perf_counter()
        ra, va = ca.intrinsics.unproject(uva)
        rb, vb = cb.intrinsics.unproject(uvb)
        ok = va & vb
        counts[(a, b)][0] += int(ok.sum())
        sel = np.flatnonzero(ok)
        rel = np.linalg.inv(poses[b][t2]) @ poses[a][t]  # cam a at t -> cam b at t2 (initial)
        gate = epipolar_angle_deg(ra[sel], rb[sel], rel[:3, :3], rel[:3, 3]) <= cfg.epipolar_gate_deg
        sel = sel[gate]
        counts[(a, b)][1] += int(gate.sum())
        focal = min(pixels_per_radian(ca.intrinsics), pixels_per_radian(cb.intrinsics))
        inl = essential_inliers(ra[sel], rb[sel], cfg.ransac_threshold_px, focal, cfg.ransac_prob, seed=cfg.seed)
        if inl.sum() < cfg.min_per_view_pair:  # a handful of matches fits a spurious essential matrix
            inl[:] = False
        idx = sel[inl]
        if idx.size:
            counts[(a, b)][2] += 1
        if idx.size > cfg.max_per_view_pair:
            idx = np.sort(rng.choice(idx, cfg.max_per_view_pair, replace=False))
        if idx.size:
            collected[(a, b)].append({
                "t": t, "t2": t2, "uva": uva[idx], "uvb": uvb[idx], "ra": ra[idx], "rb": rb[idx],
                "siga": siga[idx], "sigb": sigb[idx], "ka": ka[idx], "kb": kb[idx], "inliers": int(inl.sum()),
            })
        timings.add("ransac", t0)

    for a, b in pairs:
        parts = collected[(a, b)]
        if not parts:
            pm = _empty(a, b)
        else:
            cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k not in ("t", "t2", "inliers")}
            pm = PairMatches(
                a, b,
                np.concatenate([np.full(p["uva"].shape[0], p["t"]) for p in parts]).astype(np.int64),
                np.concatenate([np.full(p["uva"].shape[0], p["t2"]) for p in parts]).astype(np.int64),
                cat["uva"], cat["uvb"], cat["ra"], cat["rb"], cat["siga"], cat["sigb"],
                cat["ka"].astype(np.int64), cat["kb"].astype(np.int64),
            )
            pm.inliers = int(sum(p["inliers"] for p in parts))
        pm.tentative, pm.gated, pm.view_pairs = counts[(a, b)]
        out.append(pm)
    return out


_VIEW_INDEX_OFFSET = 1_000_000  # keypoint ids of the n-th virtual view of an image start at (n + 1) * this


def _view_features(cam: Camera, view: VirtualView, image: np.ndarray, static: np.ndarray | None, slot: int,
                   cfg: MatchConfig) -> Keypoints:
    """SIFT on a virtual pinhole view, mapped back to the fisheye's pixels (sizes in its centre's pixels)."""
    mask = view.valid.copy()
    if static is not None:
        mask &= view.warp(static.astype(np.uint8), cv2.INTER_NEAREST) > 0
    kv = sift_features(view.warp(image), mask.astype(np.uint8) * 255, cfg.max_features, 1.0, cfg.contrast_threshold)
    uv, ok = cam.intrinsics.project(view.rays_in_source(kv.uv))
    scale = pixels_per_radian(cam.intrinsics) / float(view.camera.intrinsics.K[0, 0])
    return Keypoints(uv[ok], kv.desc[ok], kv.size[ok] * scale, kv.index[ok] + (slot + 1) * _VIEW_INDEX_OFFSET)


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
