"""The four calibration methods of the ablation, run on one window's correspondences.

* `none`: the input (data-set) extrinsics.
* `pairwise`: each adjacent pair alone, from its same-frame correspondences only (a stereo pair):
  the essential matrix of the pooled matches gives the relative rotation and the direction of the
  baseline, whose length is kept from the input extrinsics (when the essential matrix disagrees with
  the input by more than 5 deg in rotation or 30 deg in baseline direction, a sign of a degenerate
  planar or distant scene, the input pose is the start instead); a two-view adjustment (the
  adjustment of `ba.py` restricted to the two cameras and to same-frame matches, so the ego motion
  adds nothing and the baseline length stays at its input value through the translation prior)
  refines it.
* `wo-glc` (the paper's "w/o GLC", two cameras only): each adjacent pair alone, with all T x T frame
  pairs and the ego-anchored adjustment of `ba.py`, so the same metric bundle adjustment as `glc`
  but without the other cameras and without the ring.
* `glc`: one adjustment over all cameras and all adjacent pairs including last-to-first.

The per-pair methods produce relative poses that do not close around the ring, so the extrinsics
are chained from the reference camera along a breadth-first spanning tree of the adjacency graph;
the pair(s) outside the tree (for a ring: the one opposite the reference) are not used and inherit
the accumulated chain error. That open loop is what the geometric loop constraint removes.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..cameras import Camera
from ..geometry import rotation_angle_deg
from .ba import (
    AdjustConfig,
    AdjustResult,
    Observations,
    relative_rotation_sigma_deg,
    robust_adjust,
    select_observations,
)
from .correspondences import PairMatches
from .focal import focal_map
from .outliers import rotation_to_z
from .overlap import pixels_per_radian

METHODS = ("none", "pairwise", "wo-glc", "glc")
# the pairwise essential-matrix start is used only when it agrees this well with the input extrinsics
MAX_INIT_ROTATION_DEG = 5.0
MAX_INIT_DIRECTION_DEG = 30.0
# a per-pair method keeps the input relative pose of a pair with fewer usable correspondences
MIN_PAIR_MATCHES = 8


@dataclass
class MethodResult:
    """Refined extrinsics and solver facts of one method on one window."""

    sensor_to_ego: dict[str, np.ndarray]
    iterations: int = 0
    converged: bool = True
    message: str = ""
    used_pairs: list[tuple[str, str]] = field(default_factory=list)
    pair_rms_px: dict[tuple[str, str], float] = field(default_factory=dict)
    pair_used_matches: dict[tuple[str, str], int] = field(default_factory=dict)
    rms_before_px: float = float("nan")
    rms_after_px: float = float("nan")
    pair_rotation_sigma_deg: dict[tuple[str, str], float] = field(default_factory=dict)
    focal_scale: dict[str, float] = field(default_factory=dict)  # with AdjustConfig.refine_focal (glc only)
    focal_scale_sigma: dict[str, float] = field(default_factory=dict)  # of the free estimates
    focal_scale_free: dict[str, float] = field(default_factory=dict)  # before the significance test


def spanning_tree(names: Sequence[str], pairs: Sequence[tuple[str, str]], root: str) -> list[tuple[str, str]]:
    """Edges (parent, child) of a breadth-first spanning tree of the adjacency graph from `root`."""
    nbrs: dict[str, list[str]] = {n: [] for n in names}
    for a, b in pairs:
        nbrs[a].append(b)
        nbrs[b].append(a)
    seen, edges, queue = {root}, [], deque([root])
    while queue:
        p = queue.popleft()
        for c in nbrs[p]:
            if c not in seen:
                seen.add(c)
                edges.append((p, c))
                queue.append(c)
    return edges


@dataclass
class TrackObservations:
    """Observations of merged tracks plus, per correspondence (edge), its two observation indices and pair."""

    obs: Observations
    edge_obs: np.ndarray  # (E, 2), -1 where the observation was dropped
    edge_pair: np.ndarray  # (E,)


@dataclass(frozen=True)
class _Endpoints:
    """Both ends of every correspondence: ids (`key_a`, `key_b`: view * 2^32 + keypoint, negative without an
    id), and per end (first all a-ends, then all b-ends) frame, camera, ray and sigma; `pair` is the match
    set each correspondence came from."""

    key_a: np.ndarray
    key_b: np.ndarray
    frame: np.ndarray
    cam: np.ndarray
    ray: np.ndarray
    sig: np.ndarray
    pair: np.ndarray


def _endpoints(matches: Sequence[PairMatches], index: dict[str, int], M: int) -> _Endpoints | None:
    """The correspondences of all match sets as flat arrays of their two ends; None when there are none."""
    keys_a, keys_b, fa, fb, ca, cb, ra, rb, sa, sb, pair = [], [], [], [], [], [], [], [], [], [], []
    fresh = -1
    for k, pm in enumerate(matches):
        n = len(pm)
        if n == 0:
            continue
        ia, ib = index[pm.cam_a], index[pm.cam_b]
        for keys, frame, cam, kp in ((keys_a, pm.frame_a, ia, pm.kp_a), (keys_b, pm.frame_b, ib, pm.kp_b)):
            view = frame.astype(np.int64) * M + cam
            key = view * (1 << 32) + kp
            no_id = kp < 0
            key[no_id] = fresh - np.arange(int(no_id.sum()))
            fresh -= int(no_id.sum())
            keys.append(key)
        fa.append(pm.frame_a), fb.append(pm.frame_b)
        ca.append(np.full(n, ia)), cb.append(np.full(n, ib))
        ra.append(pm.rays_a), rb.append(pm.rays_b)
        sa.append(pm.sigma_a), sb.append(pm.sigma_b)
        pair.append(np.full(n, k))
    if not pair:
        return None
    return _Endpoints(
        np.concatenate(keys_a), np.concatenate(keys_b),
        np.concatenate([np.concatenate(fa), np.concatenate(fb)]),
        np.concatenate([np.concatenate(ca), np.concatenate(cb)]),
        np.concatenate([np.concatenate(ra), np.concatenate(rb)]),
        np.concatenate([np.concatenate(sa), np.concatenate(sb)]),
        np.concatenate(pair),
    )


def _merge_tracks(ends: _Endpoints, M: int) -> tuple[Observations, np.ndarray]:
    """(observations, edge_obs): one point per consistent connected component of the match graph, one
    two-view point per correspondence of an inconsistent one (two keypoints of one image)."""
    frame, cam, ray, sig = ends.frame, ends.cam, ends.ray, ends.sig
    E = ends.key_a.shape[0]
    nodes, node_of = np.unique(np.concatenate([ends.key_a, ends.key_b]), return_inverse=True)
    na, nb = node_of[:E], node_of[E:]
    graph = coo_matrix((np.ones(E), (na, nb)), shape=(nodes.size, nodes.size))
    _, comp = connected_components(graph, directed=False)
    # one observation per node: the first endpoint that carries it
    first = np.full(nodes.size, -1)
    order = np.arange(2 * E)[::-1]
    first[node_of[order]] = order
    view = frame[first] * M + cam[first]
    # a component with two nodes in the same image is inconsistent
    nodes_per_cv = np.bincount(np.ravel_multi_index((comp, view), (comp.max() + 1, view.max() + 1)))
    bad_comp = np.zeros(comp.max() + 1, dtype=bool)
    bad_comp[np.unravel_index(np.flatnonzero(nodes_per_cv > 1), (comp.max() + 1, view.max() + 1))[0]] = True
    good_edge = ~bad_comp[comp[na]]
    # observations: good nodes (one each), then both endpoints of every edge in a bad component
    good_nodes = np.flatnonzero(~bad_comp[comp])
    _, point_of_comp = np.unique(comp[good_nodes], return_inverse=True)
    n_good_points = int(point_of_comp.max()) + 1 if good_nodes.size else 0
    bad_edges = np.flatnonzero(~good_edge)
    src = np.concatenate([first[good_nodes], bad_edges, bad_edges + E])
    point = np.concatenate([point_of_comp, n_good_points + np.arange(bad_edges.size),
                            n_good_points + np.arange(bad_edges.size)]).astype(np.int64)
    obs = Observations(cam[src].astype(np.int64), frame[src].astype(np.int64), point, ray[src], sig[src])
    obs_of_node = np.full(nodes.size, -1)
    obs_of_node[good_nodes] = np.arange(good_nodes.size)
    edge_obs = np.stack([obs_of_node[na], obs_of_node[nb]], axis=1)
    edge_obs[bad_edges, 0] = good_nodes.size + np.arange(bad_edges.size)
    edge_obs[bad_edges, 1] = good_nodes.size + bad_edges.size + np.arange(bad_edges.size)
    return obs, edge_obs


def _drop_weak_cross_time(obs: Observations, edge_obs: np.ndarray,
                          min_views: int) -> tuple[Observations, np.ndarray]:
    """Drop points seen at two times by fewer than `min_views` images (a car driving parallel to us looks
    the same as a static point); edges that lose an observation get -1."""
    counts = np.bincount(obs.point)
    first = np.full(counts.size, np.iinfo(np.int64).max)
    last = np.full(counts.size, -1)
    np.minimum.at(first, obs.point, obs.frame)
    np.maximum.at(last, obs.point, obs.frame)
    weak = (first != last) & (counts < min_views)
    obs, keep, _ = select_observations(obs, ~weak[obs.point])
    new_index = np.full(keep.size + 1, -1)
    new_index[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
    return obs, new_index[edge_obs]


def observations(matches: Sequence[PairMatches], index: dict[str, int],
                 min_cross_time_views: int = 3) -> TrackObservations:
    """Observations for the adjustment, with correspondences merged into tracks.

    A keypoint matched in several image pairs (e.g. camera A at frame t against camera B at frames
    t', t'', ...) is one 3-D point seen in all those images: its depth is then fixed by the ego
    motion as well as by the baseline. Tracks are the connected components of the match graph over
    (frame, camera, keypoint) nodes; a component holding two different keypoints of one image is
    inconsistent and falls back to one two-view point per correspondence. Matches without keypoint
    ids (LoFTR) stay two-view points.

    A point whose observations span two frames needs `min_cross_time_views` observations: a single
    match between camera A at frame t and camera B at frame t' is consistent with the epipolar
    geometry even on a car driving parallel to the ego (it only lands at a wrong depth), yet a few
    such two-view points bent the ring by 0.4 deg on the synthetic street; with a third image the
    track is checked. Edges whose observations were dropped get -1 in `edge_obs`.
    """
    M = max(index.values()) + 1 if index else 1
    ends = _endpoints(matches, index, M)
    if ends is None:
        z = np.zeros(0, dtype=np.int64)
        return TrackObservations(Observations(z, z, z, np.zeros((0, 3)), np.zeros(0)), np.zeros((0, 2), int), z)
    obs, edge_obs = _merge_tracks(ends, M)
    if min_cross_time_views > 2 and len(obs):
        obs, edge_obs = _drop_weak_cross_time(obs, edge_obs, min_cross_time_views)
    return TrackObservations(obs, edge_obs, ends.pair)


def _pair_rms(res: AdjustResult, kept: np.ndarray, tracks: TrackObservations, n_pairs: int) -> tuple[list, list]:
    """Per pair: RMS residual (px) over the correspondences whose two observations survived, and their count."""
    pos = np.cumsum(kept) - 1  # index into the final residuals of each kept observation
    e2 = np.sum(res.residual_px**2, axis=1)
    kept_pad = np.append(kept, False)  # edge_obs == -1 looks up the False at the end
    ok = kept_pad[tracks.edge_obs[:, 0]] & kept_pad[tracks.edge_obs[:, 1]]
    val = np.zeros(ok.shape[0])
    val[ok] = 0.5 * (e2[pos[tracks.edge_obs[ok, 0]]] + e2[pos[tracks.edge_obs[ok, 1]]])
    rms, used = [], []
    for k in range(n_pairs):
        m = ok & (tracks.edge_pair == k)
        rms.append(float(np.sqrt(val[m].mean())) if m.any() else float("nan"))
        used.append(int(m.sum()))
    return rms, used


def _adjust_cameras(
    cameras: Sequence[Camera], matches: Sequence[PairMatches], ego_to_world: np.ndarray, reference: str,
    config: AdjustConfig,
) -> tuple[dict[str, np.ndarray], AdjustResult, list[float], list[int]]:
    names = [c.name for c in cameras]
    index = {n: i for i, n in enumerate(names)}
    tracks = observations([*matches, *(link for pm in matches for link in pm.links)], index)
    S0 = np.stack([c.sensor_to_ego for c in cameras])
    focal = np.array([pixels_per_radian(c.intrinsics) for c in cameras])
    maps = [focal_map(c.intrinsics) for c in cameras] if config.refine_focal else None
    res, kept = robust_adjust(S0, ego_to_world, tracks.obs, focal, index[reference], config, focal_maps=maps)
    rms, used = _pair_rms(res, kept, tracks, len(matches))
    return {n: res.sensor_to_ego[i] for i, n in enumerate(names)}, res, rms, used


def run_glc(
    cameras: Sequence[Camera], matches: Sequence[PairMatches], ego_to_world: np.ndarray, reference: str,
    config: AdjustConfig | None = None,
) -> MethodResult:
    """One loop-constrained adjustment over all cameras and all adjacent pairs."""
    cfg = config or AdjustConfig()
    ext, res, rms, used = _adjust_cameras(cameras, matches, ego_to_world, reference, cfg)
    pairs = [(m.cam_a, m.cam_b) for m in matches]
    index = {c.name: i for i, c in enumerate(cameras)}
    sigma = {} if res.rotation_cov is None else {
        (a, b): relative_rotation_sigma_deg(res.rotation_cov, index[a], index[b]) for a, b in pairs}
    scales = {} if res.focal_scale is None else {c.name: float(res.focal_scale[i]) for i, c in enumerate(cameras)}
    per_camera = {key: {} if v is None else {c.name: float(v[i]) for i, c in enumerate(cameras)}
                  for key, v in (("sigma", res.focal_scale_sigma), ("free", res.focal_scale_free))}
    return MethodResult(ext, res.iterations, res.converged, res.message, pairs, dict(zip(pairs, rms)),
                        dict(zip(pairs, used)), res.initial_rms_px, res.final_rms_px, sigma, scales,
                        per_camera["sigma"], per_camera["free"])


def relative_pose_from_rays(rays_a: np.ndarray, rays_b: np.ndarray, focal_px: float,
                            threshold_px: float = 1.0) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t_unit) with X_b = R X_a + t from ray matches: essential matrix (USAC) and its decomposition."""
    if rays_a.shape[0] < 8:
        return None
    Ra, Rb = rotation_to_z(rays_a.mean(axis=0)), rotation_to_z(rays_b.mean(axis=0))
    va, vb = rays_a @ Ra.T, rays_b @ Rb.T
    ok = (va[:, 2] > 0.2) & (vb[:, 2] > 0.2)
    if ok.sum() < 8:
        return None
    pa = va[ok, :2] / va[ok, 2:3]
    pb = vb[ok, :2] / vb[ok, 2:3]
    E, mask = cv2.findEssentialMat(pa, pb, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999,
                                   threshold=threshold_px / focal_px)
    if E is None or E.shape != (3, 3):
        return None
    _, R, t, _ = cv2.recoverPose(E, pa, pb, np.eye(3), mask=mask)
    # back from the rotated frames: X_b' = R X_a' + t with X' = R_x X
    return Rb.T @ R @ Ra, Rb.T @ t.ravel()


def _chain(
    cameras: Sequence[Camera], pairs: Sequence[tuple[str, str]], matches: Sequence[PairMatches],
    ego_to_world: np.ndarray, reference: str, config: AdjustConfig, same_time: bool,
) -> MethodResult:
    cams = {c.name: c for c in cameras}
    names = list(cams)
    by_pair = {frozenset((m.cam_a, m.cam_b)): m for m in matches}
    # chain along observed pairs first; a camera they do not reach keeps its input pose relative to its parent
    observed = [p for p in pairs if len(by_pair[frozenset(p)]) >= MIN_PAIR_MATCHES]
    tree = spanning_tree(list(cams), observed, reference)
    reached = {reference} | {c for _, c in tree}
    tree += [e for e in spanning_tree(list(cams), pairs, reference) if e[1] not in reached]
    out = {reference: cams[reference].sensor_to_ego.copy()}
    result = MethodResult(out)
    iterations, converged, msgs, rms_b, rms_a = 0, True, [], [], []
    for p, c in tree:
        pm = by_pair[frozenset((p, c))]
        if same_time:
            pm = pm.same_time()
        cp, cc = cams[p], cams[c]
        key = (pm.cam_a, pm.cam_b)
        if len(pm) < MIN_PAIR_MATCHES:
            out[c] = out[p] @ np.linalg.inv(cp.sensor_to_ego) @ cc.sensor_to_ego
            msgs.append(f"{p}-{c}: {len(pm)} usable correspondences, input relative pose kept")
            continue
        if same_time:
            cc = cc.with_pose(_essential_init(cp, cc, pm))
        ego = ego_to_world if ego_to_world.ndim == 3 else ego_to_world[:, [names.index(p), names.index(c)]]
        ext, res, rms, used = _adjust_cameras([cp, cc], [pm], ego, p, config)
        Q = np.linalg.inv(cp.sensor_to_ego) @ ext[c]  # child in the parent's frame
        out[c] = out[p] @ Q
        result.used_pairs.append(key)
        result.pair_rms_px[key] = rms[0]
        result.pair_used_matches[key] = used[0]
        iterations = max(iterations, res.iterations)
        converged &= res.converged
        msgs.append(f"{p}-{c}: {res.message}")
        rms_b.append(res.initial_rms_px)
        rms_a.append(res.final_rms_px)
    for name, cam in cams.items():
        out.setdefault(name, cam.sensor_to_ego.copy())
    result.iterations, result.converged, result.message = iterations, converged, "; ".join(msgs)
    result.rms_before_px = float(np.nanmean(rms_b)) if rms_b else float("nan")
    result.rms_after_px = float(np.nanmean(rms_a)) if rms_a else float("nan")
    return result


def _essential_init(cp: Camera, cc: Camera, pm: PairMatches) -> np.ndarray:
    """Child extrinsic from the essential matrix of same-frame matches, baseline length kept from the input."""
    flip = pm.cam_a != cp.name
    ra, rb = (pm.rays_b, pm.rays_a) if flip else (pm.rays_a, pm.rays_b)
    focal = min(pixels_per_radian(cp.intrinsics), pixels_per_radian(cc.intrinsics))
    est = relative_pose_from_rays(ra, rb, focal)
    if est is None:
        return cc.sensor_to_ego
    R, t = est  # X_c = R X_p + t
    rel0 = np.linalg.inv(cc.sensor_to_ego) @ cp.sensor_to_ego  # parent -> child, input
    length = np.linalg.norm(rel0[:3, 3])
    if t @ rel0[:3, 3] < 0:
        t = -t
    # A planar or distant scene makes the essential matrix degenerate; then the input pose is the better start.
    cos_dir = float(t @ rel0[:3, 3]) / max(np.linalg.norm(t) * length, 1e-12)
    direction_deg = np.degrees(np.arccos(min(1.0, cos_dir)))
    if rotation_angle_deg(R @ rel0[:3, :3].T) > MAX_INIT_ROTATION_DEG or direction_deg > MAX_INIT_DIRECTION_DEG:
        return cc.sensor_to_ego
    rel = np.eye(4)
    rel[:3, :3], rel[:3, 3] = R, t / max(np.linalg.norm(t), 1e-12) * length
    return cp.sensor_to_ego @ np.linalg.inv(rel)


def run_method(
    method: str, cameras: Sequence[Camera], pairs: Sequence[tuple[str, str]], matches: Sequence[PairMatches],
    ego_to_world: np.ndarray, reference: str, config: AdjustConfig | None = None,
) -> MethodResult:
    """Run one of METHODS on one window's correspondences; `ego_to_world` (T, 4, 4), or (T, M, 4, 4) with
    each camera's own ego pose at its capture (cameras in the order of `cameras`)."""
    cfg = config or AdjustConfig()
    if method == "none":
        return MethodResult({c.name: c.sensor_to_ego.copy() for c in cameras}, message="input extrinsics kept")
    if method == "glc":
        return run_glc(cameras, matches, ego_to_world, reference, cfg)
    if method in ("wo-glc", "pairwise"):  # a pair alone cannot place a focal error: intrinsics stay fixed
        return _chain(cameras, pairs, matches, ego_to_world, reference, replace(cfg, refine_focal=False),
                      same_time=method == "pairwise")
    raise ValueError(f"unknown method {method!r} (expected one of {', '.join(METHODS)})")
