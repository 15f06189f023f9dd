"""Sub-pixel refinement of verified correspondences by patch alignment in the overlap views.

SIFT places a keypoint at the extremum of a difference of Gaussians, about 0.17 px from where the same
scene point lies in the other image of a pair (per axis, on the rendered worlds); through the rig's geometry
that noise is most of the fisheye preset's rotation error. Here each keypoint of a match track (the
connected component of the correspondence graph over (frame, camera, keypoint), as the adjustment merges
them) is aligned to one reference keypoint of its track: the reference keeps its SIFT position, every other
keypoint is moved to where its patch best matches its parent's patch along a breadth-first tree of the track's
verified correspondences (inverse-compositional Lucas-Kanade, an affine warp started from the starting rig's
rotation between the two views, on patches normalised for gain and offset). The track then holds one scene
point exactly, up to the alignment's own error. Keypoints whose alignment does not converge, moves more
than `max_shift_px`, leaves the usable pixels or ends with a weak correlation are dropped with their
correspondences. Everything is deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from scipy.ndimage import map_coordinates, spline_filter
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

if TYPE_CHECKING:
    from .correspondences import PairMatches


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the patch alignment (pixels are the overlap views' pixels)."""

    half_patch: int = 5
    window_sigma_px: float = 2.0
    blur_sigma_px: float = 0.0
    affine: bool = True
    max_iterations: int = 40
    tolerance_px: float = 0.01
    max_shift_px: float = 1.0
    min_ncc: float = 0.6
    max_affine_change: float = 1.0


@dataclass
class PatchImage:
    """A view prepared for alignment: cubic B-spline coefficients of its (blurred) grey values and of their x and
    y gradients, and where it is usable (float32 0/1)."""

    value: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    usable: np.ndarray


def patch_image(gray: np.ndarray, usable: np.ndarray | None = None, blur_sigma_px: float = 0.8) -> PatchImage:
    """A grey image prepared for alignment: Gaussian-blurred by `blur_sigma_px`, with central-difference gradients,
    as spline coefficients (sampling at arbitrary sub-pixel positions without the phase-dependent blur of
    bilinear interpolation or the 1/32-px position grid of cv2.remap)."""
    img = np.asarray(gray, np.float64)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=1, scale=0.5)
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=1, scale=0.5)
    ok = np.ones(img.shape, np.float32) if usable is None else np.asarray(usable, np.float32)
    if blur_sigma_px > 0:  # a pixel next to unusable ones is blurred with them
        k = 2 * int(np.ceil(2 * blur_sigma_px)) + 1
        ok = cv2.erode(ok, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return PatchImage(*(spline_filter(x, order=3, mode="mirror") for x in (img, gx, gy)), ok)


def _sample(images: Sequence[PatchImage], which: np.ndarray, pts: np.ndarray, fields: Sequence[str]) -> list:
    """Values of `fields` of images[which[n]] at points pts[n] (N, P, 2): cubic spline, nearest for `usable`
    (0 outside the image)."""
    out = [np.zeros(pts.shape[:2]) for _ in fields]
    for k in np.unique(which):
        rows = np.flatnonzero(which == k)
        coords = np.stack([pts[rows, :, 1], pts[rows, :, 0]])
        for o, name in zip(out, fields):
            order = 0 if name == "usable" else 3
            o[rows] = map_coordinates(getattr(images[k], name), coords, order=order, mode="constant", cval=0.0,
                                      prefilter=False)
    return out


def _normalised(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Patches (N, P) minus their weighted mean, divided by their weighted standard deviation; and that deviation."""
    m = v @ w
    c = v - m[:, None]
    s = np.sqrt(np.maximum((c * c) @ w, 1e-12))
    return c / s[:, None], s


def align_patches(templates: Sequence[PatchImage], t_which: np.ndarray, t_uv: np.ndarray,
                  images: Sequence[PatchImage], c_which: np.ndarray, c_uv: np.ndarray, A0: np.ndarray,
                  cfg: RefineConfig | None = None, facts: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the patches of templates[t_which[n]] around t_uv[n] (N, 2) lie in images[c_which[n]], starting at
    c_uv[n] with the local linear map A0[n] (2, 2; template offset -> image offset): (positions (N, 2),
    ok (N,)). Not ok: no convergence, a move beyond `max_shift_px`, unusable pixels, correlation below
    `min_ncc`, an affine part far from A0, or a flat template; `facts`, when given, receives how many failed
    each check."""
    cfg = cfg or RefineConfig()
    N = t_uv.shape[0]
    r = cfg.half_patch
    gy_, gx_ = np.mgrid[-r:r + 1, -r:r + 1]
    grid = np.stack([gx_.ravel(), gy_.ravel()], 1).astype(np.float64)  # (P, 2)
    w = np.exp(-(grid ** 2).sum(1) / (2 * cfg.window_sigma_px ** 2))
    w /= w.sum()
    if N == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    T, Tx, Ty, t_ok = _sample(templates, t_which, t_uv[:, None, :] + grid[None], ("value", "gx", "gy", "usable"))
    T, sT = _normalised(T.astype(np.float64), w)
    Tx, Ty = Tx / sT[:, None], Ty / sT[:, None]
    sd = [Tx, Ty] + ([Tx * grid[:, 0], Tx * grid[:, 1], Ty * grid[:, 0], Ty * grid[:, 1]] if cfg.affine else [])
    SD = np.stack(sd, axis=2)  # (N, P, k) steepest-descent images
    H = np.einsum("npi,npj,p->nij", SD, SD, w)
    flat = np.linalg.eigvalsh(H[:, :2, :2])[:, 0] < 1e-3  # no texture to align on
    Hinv = np.linalg.inv(H + np.eye(H.shape[1]) * 1e-9)
    SDw = SD * w[None, :, None]
    centre, A = np.array(c_uv, np.float64), np.array(A0, np.float64)
    done = np.zeros(N, bool)
    active = np.flatnonzero(~flat)
    for _ in range(cfg.max_iterations):
        if active.size == 0:
            break
        pts = centre[active, None, :] + grid[None] @ A[active].transpose(0, 2, 1)
        (I,) = _sample(images, c_which[active], pts, ("value",))
        I, _ = _normalised(I.astype(np.float64), w)
        res = I - T[active]
        dp = np.einsum("nij,nj->ni", Hinv[active], np.einsum("npk,np->nk", SDw[active], res))
        if cfg.affine:
            M = np.eye(2) + dp[:, 2:].reshape(-1, 2, 2)
            A[active] = A[active] @ np.linalg.inv(M)
        step = np.einsum("nij,nj->ni", A[active], dp[:, :2])
        centre[active] -= step
        small = np.linalg.norm(step, axis=1) < cfg.tolerance_px
        done[active[small]] = True
        active = active[~small]
    pts = centre[:, None, :] + grid[None] @ A.transpose(0, 2, 1)
    I, c_ok = _sample(images, c_which, pts, ("value", "usable"))
    I, _ = _normalised(I.astype(np.float64), w)
    ncc = (I * T) @ w
    # a warp that collapsed (a singular value 0) is as far from the template's as can be: log -> inf, rejected below
    change = np.maximum(np.linalg.svd(A @ np.linalg.inv(A0), compute_uv=False), np.finfo(float).tiny)
    checks = {"flat": ~flat, "converged": done, "shift": np.linalg.norm(centre - c_uv, axis=1) <= cfg.max_shift_px,
              "ncc": ncc >= cfg.min_ncc, "usable": (t_ok.min(1) > 0) & (c_ok.min(1) > 0),
              "affine": np.abs(np.log(change)).max(1) <= np.log1p(cfg.max_affine_change)}
    if facts is not None:
        for k, v in checks.items():
            facts[k] = facts.get(k, 0) + int((~v).sum())
    return centre, np.logical_and.reduce(list(checks.values()))


def _local_linear(K_p: np.ndarray, K_c: np.ndarray, R_cp: np.ndarray, uv_p: np.ndarray) -> np.ndarray:
    """The Jacobians (N, 2, 2) at view-p pixels uv_p (N, 2) of the homographies K_c R_cp K_p^-1 (N, 3, 3 each):
    how a rotation between two pinhole views maps a small patch."""
    Hm = K_c @ R_cp @ np.linalg.inv(K_p)
    x = np.c_[uv_p, np.ones(len(uv_p))]
    h = np.einsum("nij,nj->ni", Hm, x)
    q = h[:, :2] / h[:, 2:3]
    return (Hm[:, :2, :2] - q[:, :, None] * Hm[:, 2:3, :2]) / h[:, 2, None, None]


def _nodes(matches: Sequence[PairMatches], views: dict) -> tuple[dict, list, np.ndarray, np.ndarray]:
    """Keypoint nodes (frame, camera, keypoint) of the correspondences that lie on overlap views: node index per
    key, node keys with their view key, and per correspondence its two node indices (-1 off views)."""
    index: dict[tuple[int, str, int], int] = {}
    keys: list[tuple[tuple[int, str, int], tuple[int, str, str]]] = []
    ends_a, ends_b = [], []
    for pm in matches:
        for cam, other, frames, kps, ends in ((pm.cam_a, pm.cam_b, pm.frame_a, pm.kp_a, ends_a),
                                              (pm.cam_b, pm.cam_a, pm.frame_b, pm.kp_b, ends_b)):
            col = np.full(len(pm), -1)
            for i, (t, kp) in enumerate(zip(frames.tolist(), kps.tolist())):
                if kp < 0 or (t, cam, other) not in views:
                    continue
                key = (t, cam, kp)
                if key not in index:
                    index[key] = len(keys)
                    keys.append((key, (t, cam, other)))
                col[i] = index[key]
            ends.append(col)
    return index, keys, np.concatenate(ends_a) if ends_a else np.zeros(0, int), \
        np.concatenate(ends_b) if ends_b else np.zeros(0, int)


def _tree(n: int, na: np.ndarray, nb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first trees over the node graph, one per connected component rooted at its node of highest degree
    (ties: lowest index): (parent per node, -1 for roots; depth per node)."""
    e = (na >= 0) & (nb >= 0) & (na != nb)
    a, b = na[e], nb[e]
    deg = np.bincount(np.r_[a, b], minlength=n)
    order = np.lexsort((np.arange(n), -deg))
    _, comp = connected_components(coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)), directed=False)
    roots = np.full(comp.max() + 1 if n else 0, -1)
    for i in order[::-1]:  # the last written, i.e. the most preferred node of each component
        roots[comp[i]] = i
    # one breadth-first search from a super-root S joined to the roots only
    S = n
    ra = np.r_[a, np.full(roots.size, S)]
    rb = np.r_[b, roots]
    g2 = coo_matrix((np.ones(ra.size), (ra, rb)), shape=(n + 1, n + 1))
    bfs, pred = breadth_first_order(g2, S, directed=False, return_predecessors=True)
    parent = pred[:n].copy()
    parent[parent == S] = -1
    depth = np.zeros(n, int)
    for i in bfs[1:]:
        depth[i] = 0 if parent[i] < 0 else depth[parent[i]] + 1
    return parent, depth


def refine_matches(matches: Sequence[PairMatches], views: dict, cams: dict, poses: dict[str, np.ndarray],
                   cfg: RefineConfig | None = None) -> tuple[list[PairMatches], dict[str, Any]]:
    """The correspondences with their keypoints moved to the sub-pixel positions of patch alignment along each
    track, and without those whose alignment failed; plus `positions` (node key (frame, camera, keypoint) -> its
    ray in the camera's frame, or None for a dropped keypoint; for `apply_positions`) and counts.

    `views[(t, cam, other)]` holds the overlap view of camera `cam` at frame t aimed at `other` (`.view`: a
    VirtualView, `.gray`, `.usable`), `cams` the cameras by name; `poses[cam][t]` the starting camera-to-world
    poses (for the initial warp between two views). Keypoints on no view (raw images, LoFTR) are left as they
    are."""
    cfg = cfg or RefineConfig()
    _, keys, na, nb = _nodes(matches, views)
    n = len(keys)
    stats = {"keypoints": n, "refined": 0, "dropped": 0, "correspondences_dropped": 0, "median_shift_px": 0.0}
    if n == 0:
        return list(matches), {"positions": {}, **stats}
    vkeys = sorted({v for _, v in keys})
    vid = {v: i for i, v in enumerate(vkeys)}
    pimg = [patch_image(views[v].gray, views[v].usable, cfg.blur_sigma_px) for v in vkeys]
    node_view = np.array([vid[v] for _, v in keys])
    # each view's rotation to the world at the starting rig, and its pinhole matrix (for the initial warps)
    view_to_world = np.stack([poses[v[1]][v[0]][:3, :3] @ views[v].view.R for v in vkeys])
    K = np.stack([views[v].view.camera.intrinsics.K for v in vkeys])
    uv0 = _view_positions(matches, views, vkeys, node_view, na, nb, n)
    uv = uv0.copy()
    parent, depth = _tree(n, na, nb)
    ok, failed = _align_tree(uv, parent, depth, pimg, node_view, view_to_world, K, cfg)
    positions: dict = {}
    for k, v in enumerate(vkeys):
        rows = np.flatnonzero(node_view == k)
        cam_rays = views[v].view.rays_in_source(uv[rows])
        for r, ray in zip(rows, cam_rays):
            positions[keys[r][0]] = ray if ok[r] else None
    out = [apply_positions(pm, positions, cams) for pm in matches]
    moved = np.linalg.norm(uv - uv0, axis=1)[ok & (depth > 0)]
    stats.update(refined=int((ok & (depth > 0)).sum()), dropped=int((~ok).sum()),
                 correspondences_dropped=int(sum(len(a) - len(b) for a, b in zip(matches, out))),
                 median_shift_px=float(np.median(moved)) if moved.size else 0.0, failed=failed)
    return out, {"positions": positions, **stats}


def _view_positions(matches: Sequence[PairMatches], views: dict, vkeys: list, node_view: np.ndarray,
                    na: np.ndarray, nb: np.ndarray, n: int) -> np.ndarray:
    """Each node's position (n, 2) in its view, from its ray (exactly where the keypoint was detected)."""
    rays = np.zeros((n, 3))
    for pm, sl in _slices(matches):
        for col, rr in ((na[sl], pm.rays_a), (nb[sl], pm.rays_b)):
            m = col >= 0
            rays[col[m]] = rr[m]
    uv = np.zeros((n, 2))
    for k, v in enumerate(vkeys):
        rows = np.flatnonzero(node_view == k)
        view = views[v].view
        p, _ = view.camera.intrinsics.project(rays[rows] @ view.R)
        uv[rows] = p
    return uv


def _align_tree(uv: np.ndarray, parent: np.ndarray, depth: np.ndarray, pimg: list, node_view: np.ndarray,
                view_to_world: np.ndarray, K: np.ndarray, cfg: RefineConfig) -> tuple[np.ndarray, dict[str, int]]:
    """Align every node to its parent level by level (updates `uv` in place); which nodes held, failure counts."""
    n = len(uv)
    ok = np.ones(n, bool)
    failed: dict[str, int] = {}
    for level in range(1, int(depth.max()) + 1 if n else 1):
        child = np.flatnonzero((depth == level) & (parent >= 0))
        if child.size == 0:
            continue
        par = parent[child]
        R_cp = np.einsum("nji,njk->nik", view_to_world[node_view[child]], view_to_world[node_view[par]])
        A0 = _local_linear(K[node_view[par]], K[node_view[child]], R_cp, uv[par])
        pos, good = align_patches(pimg, node_view[par], uv[par], pimg, node_view[child], uv[child], A0, cfg, failed)
        uv[child[good]] = pos[good]
        ok[child[~good]] = False
    return ok, failed


def _slices(matches: Sequence[PairMatches]):
    """Each match set with its slice in the concatenated correspondences."""
    start = 0
    for pm in matches:
        yield pm, slice(start, start + len(pm))
        start += len(pm)


def apply_positions(pm: PairMatches, positions: dict, cameras: dict) -> PairMatches:
    """`pm` with its keypoints at the refined positions (rays, and pixels through the camera's model) and
    without the correspondences that touch a dropped keypoint; counts per observation pair follow."""
    n = len(pm)
    keep = np.ones(n, bool)
    uv_a, uv_b, ra, rb = pm.uv_a.copy(), pm.uv_b.copy(), pm.rays_a.copy(), pm.rays_b.copy()
    for cam, frames, kps, uvs, rays in ((pm.cam_a, pm.frame_a, pm.kp_a, uv_a, ra), (pm.cam_b, pm.frame_b, pm.kp_b,
                                                                                  uv_b, rb)):
        moved = []
        for i, (t, kp) in enumerate(zip(frames.tolist(), kps.tolist())):
            key = (t, cam, kp)
            if key not in positions:
                continue
            got = positions[key]
            if got is None:
                keep[i] = False
                continue
            rays[i] = got
            moved.append(i)
        if moved:  # as the keypoints of a view are mapped today: the camera's pixel, then its ray
            intr = cameras[cam].intrinsics
            p, _ = intr.project(rays[moved])
            uvs[moved] = p
            rays[moved], _ = intr.unproject(p)
    out = replace_arrays(pm, uv_a, uv_b, ra, rb).select(keep)
    out.inliers = pm.inliers
    counts = {}
    for t, t2 in zip(out.frame_a.tolist(), out.frame_b.tolist()):
        counts[(t, t2)] = counts.get((t, t2), 0) + 1
    out.observation_pairs = [replace(o, kept=counts.get((o.t, o.t2), 0)) if o.kept else o
                             for o in pm.observation_pairs]
    return out


def replace_arrays(pm: PairMatches, uv_a: np.ndarray, uv_b: np.ndarray, ra: np.ndarray, rb: np.ndarray
                   ) -> PairMatches:
    """A copy of `pm` with other pixels and rays."""
    return replace(pm, uv_a=uv_a, uv_b=uv_b, rays_a=ra, rays_b=rb)
