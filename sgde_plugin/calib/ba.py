"""Bundle adjustment of a surround rig with the geometric loop constraint (GLC).

Unknowns (the paper's parametrisation): the pose of the reference camera in every frame of the window,
X^1_t, one relative pose per other camera, X^m_rel, fixed over the window, so the pose of camera m in
frame t is X^m_t = X^m_rel X^1_t; and one 3-D point per correspondence. Every adjacent pair of the ring
(last-to-first included) observes the same unknowns, so the ring of relative poses closes by
construction. Residuals are angular errors of the observed unit rays (the stereographic projection
of the predicted direction onto the ray's tangent plane, 2 tan(angle / 2), which grows without bound
towards the antipode, so no point can settle behind its camera) times the camera's pixels per
radian, divided by each observation's sigma, so pinholes and fisheyes share one model.

Solver (`schur.py`; this module holds the model and the passes): Levenberg-Marquardt on the normal
equations with the points eliminated per point (Schur complement, the standard bundle-adjustment
reduction), analytic Jacobians, the soft-L1 loss by
iteratively reweighted least squares, and a safeguarded Gauss-Newton step per point after each pose
step. SciPy's `least_squares(jac_sparsity=...)` with its LSMR trust-region solver was tried first: on
5,000 points it used its 200 evaluations in 180 s without converging; this solver needs seconds.

Gauge and metric scale (the choice made here):
* The adjustment's world frame is the reference camera in the first frame of the window: X^1_0 is
  fixed. The ego trajectory is known in metres; it enters through a rotation G (3 unknowns) that
  maps ego-world directions into this frame, with priors
    c_t - c_0 = G (e_t - e_0)                 (sigma_centre_m = 2 cm), e_t = ego_to_world[t] applied
                                               to the reference camera's initial mounting position;
    R^1_t (R^1_0)^T = G (ego rotation 0->t) G^T  (sigma_ego_rot_deg = 0.05 deg).
  The mount is rigid, so these hold whatever the mount error, while G absorbs the unknown orientation
  of the reference camera on the car. Correspondences between camera A in frame t and camera B in
  frame t' span the ego motion, whose length is known in metres: the relative translations come out
  metric (tests prove it). G has a weak prior (5 deg) towards identity: on a straight drive its roll
  about the direction of travel is not observable, and through G it moves no point and no camera.
* Relative translations have a prior towards their initial values, the mount (sigma 0.1 m per axis: a
  mount known to about 10 cm, as from a drawing or a tape measure), and relative rotations a very weak
  one (10 deg). They hold what the images do not measure: on a random rig whose pair was seen only on
  far points and on cars driving alongside, the images let a translation wander by 0.5 m with a 0.5 m
  prior (and bend the rotation 0.7 deg); with 5 cm it stayed within 2 cm. The price: on a light data
  set (3 points per image pair) the prior pulls towards the input's error (2.6 cm with 0.1 m, 3.6 cm
  with 0.05 m, 0.3 cm with 0.5 m; tests/test_calib_ba.py).
* The reference camera keeps its initial sensor_to_ego; the other cameras' sensor_to_ego are
  S_m = S_1 (X^m_rel)^-1. Calibration refines the relative geometry, which is what stereo needs.
* Focal lengths (`refine_focal`, `focal.py`): one scale s_m per camera, the reference camera's included,
  multiplies fx and fy (principal point and distortion kept; a fisheye's image radius), with a Gaussian
  prior of `sigma_focal` = 1 % around the rig's value. What determines them: in an overlap two cameras see
  the same points at different distances from their principal points, so the spread of the matches
  (across the strip and up and down it) measures the ratio of the two focal lengths; a common scale of
  all of them turns every pair's relative yaw the same way, and the ring's yaws must add up to a full
  turn (all six of DDAD's scaled by 0.5 % open its ring by 1.2-1.6 deg), so the loop measures the common
  scale; the metric scale (ego motion) and the gauge (reference camera in frame 0, G) are lengths and
  poses, which a focal length does not touch. Weakly determined: a camera whose overlaps are thin strips
  at one image radius, where a focal change looks like a yaw; the prior holds it and its 1-sigma says so.
  The formal sigmas ignore correlated keypoint errors (on the rendered presets, whose intrinsics are
  exact, free estimates reach 3-4.6 sigma, 0.14 %), so `robust_adjust` adopts a scale only at
  `focal_min_sigmas` = 10 sigmas and otherwise returns the fixed-intrinsics result unchanged.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry import invert_transform, make_transform, rodrigues, rotation_vector, skew
from ..threads import blas_threads
from .focal import FocalMap
from .schur import covariance, lm_step, point_blocks, view_layout

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class AdjustConfig:
    """Settings of the loop-constrained bundle adjustment (see the module docstring for the priors)."""

    loss: str = "soft_l1"
    f_scale: float = 2.0
    max_iterations: int = 200
    sigma_centre_m: float = 0.02
    sigma_ego_rot_deg: float = 0.05
    sigma_gauge_rot_deg: float = 5.0
    sigma_rel_t_m: float = 0.1
    sigma_rel_rot_deg: float = 10.0
    ftol: float = 1e-7
    pose_tol: float = 1e-5
    initial_damping: float = 1e-3
    point_iterations: int = 1
    consensus_deg: float = 3.0
    refine_focal: bool = True
    sigma_focal: float = 0.01
    focal_min_sigmas: float = 10.0
    threads: int = 2  # with focal scales: the fixed-intrinsics passes run beside the free ones (same result)


@dataclass
class Observations:
    """One row per observation: camera, window frame, 3-D point, unit ray, and its noise sigma in pixels."""

    camera: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    ray: np.ndarray
    sigma_px: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.camera.shape[0])


@dataclass
class _State:
    R_t: np.ndarray  # (T, 3, 3) reference camera -> adjustment world
    c_t: np.ndarray  # (T, 3)
    R_m: np.ndarray  # (M, 3, 3) camera m -> reference camera
    p_m: np.ndarray  # (M, 3)
    G: np.ndarray  # (3, 3) ego-world directions -> adjustment world
    anchor: np.ndarray  # (K, 3) fixed anchor of each point (a camera centre that sees it, initial)
    m: np.ndarray  # (K, 3) unit direction from the anchor
    rho: np.ndarray  # (K,) inverse distance from the anchor (0 = at infinity, < 0 beyond it)
    s: np.ndarray | None = None  # (M,) focal-length scale of each camera (None: not refined)

    @property
    def P(self) -> np.ndarray:
        """Points in the adjustment world (K, 3) (very far for points at infinity)."""
        return self.anchor + self.m / np.maximum(np.abs(self.rho), 1e-9)[:, None]

    def set_points(self, points: np.ndarray, anchor: np.ndarray) -> None:
        """Parametrise world points (K, 3) by inverse distance from the given anchors."""
        v = np.asarray(points, dtype=np.float64) - anchor
        dist = np.maximum(np.linalg.norm(v, axis=1), 1e-6)
        self.anchor, self.m, self.rho = anchor.copy(), v / dist[:, None], 1.0 / dist

    def subset(self, ids: np.ndarray) -> None:
        """Keep only the points `ids` (in that order)."""
        self.anchor, self.m, self.rho = self.anchor[ids], self.m[ids], self.rho[ids]

    def copy(self) -> _State:
        """A deep copy."""
        return _State(self.R_t.copy(), self.c_t.copy(), self.R_m.copy(), self.p_m.copy(), self.G.copy(),
                      self.anchor.copy(), self.m.copy(), self.rho.copy(), None if self.s is None else self.s.copy())


@dataclass
class AdjustResult:
    """Outcome of `adjust`: refined extrinsics, points, residuals (pixels) and solver facts."""

    sensor_to_ego: np.ndarray
    points: np.ndarray
    residual_px: np.ndarray
    iterations: int
    converged: bool
    message: str
    initial_rms_px: float
    final_rms_px: float
    state: _State | None = field(default=None, repr=False)
    rotation_cov: np.ndarray | None = field(default=None, repr=False)  # (M, M, 3, 3), see relative_rotation_sigma_deg
    focal_scale: np.ndarray | None = None  # (M,) with `AdjustConfig.refine_focal`
    focal_scale_sigma: np.ndarray | None = None  # (M,) 1-sigma of the free estimates (robust_adjust)
    focal_scale_free: np.ndarray | None = None  # (M,) free estimates, before the significance test (robust_adjust)


def triangulate_midpoint(
    centre_a: np.ndarray, dir_a: np.ndarray, centre_b: np.ndarray, dir_b: np.ndarray, fallback_m: float = 20.0
) -> np.ndarray:
    """Midpoints of the closest approach of ray pairs (N, 3); `fallback_m` along ray a when ill-posed."""
    w0 = centre_a - centre_b
    a = np.sum(dir_a * dir_a, axis=1)
    b = np.sum(dir_a * dir_b, axis=1)
    c = np.sum(dir_b * dir_b, axis=1)
    d = np.sum(dir_a * w0, axis=1)
    e = np.sum(dir_b * w0, axis=1)
    den = a * c - b * b
    ok = den > 1e-9
    den = np.where(ok, den, 1.0)
    s = (b * e - c * d) / den
    u = (a * e - b * d) / den
    ok &= (s > 0.5) & (u > 0.5) & (s < 1e4)
    s = np.where(ok, s, fallback_m)
    u = np.where(ok, u, 0.0)
    pa = centre_a + s[:, None] * dir_a
    pb = centre_b + u[:, None] * dir_b
    return np.where(ok[:, None], 0.5 * (pa + pb), pa)


def view_poses(sensor_to_ego: np.ndarray, ego_to_world: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (T, M, 4, 4) of every camera in every frame; `ego_to_world` (T, 4, 4), or
    (T, M, 4, 4) with each camera's own ego pose at its capture."""
    if np.ndim(ego_to_world) == 4:
        return np.einsum("tmij,mjk->tmik", ego_to_world, sensor_to_ego)
    return np.einsum("tij,mjk->tmik", ego_to_world, sensor_to_ego)


def capture_offsets(sensor_to_ego: np.ndarray, ego_to_world: np.ndarray, reference: int) -> np.ndarray:
    """Per frame and camera (T, M, 4, 4): the reference camera at camera m's capture, in the reference camera's
    frame at its own capture (identity for a synchronous rig), from the ego poses and its initial mount.

    With per-camera capture the pose of camera m in frame t is X^1_t E_tm X^m_rel: the ego motion between
    two captures is known, so the cameras keep one relative pose each (the paper's parametrisation).
    """
    ego = np.asarray(ego_to_world, dtype=np.float64)
    M = sensor_to_ego.shape[0]
    if ego.ndim == 3:
        return np.broadcast_to(np.eye(4), (ego.shape[0], M, 4, 4)).copy()
    W = np.einsum("tmij,jk->tmik", ego, sensor_to_ego[reference])  # reference camera at each capture
    return np.einsum("tij,tmjk->tmik", invert_transform(W[:, reference]), W)


def initial_points(
    sensor_to_ego: np.ndarray, ego_to_world: np.ndarray, obs: Observations, n_points: int,
    consensus_deg: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate every point by consensus over its observations with the given poses.

    Each pair of a track's observations proposes a point (midpoint of the two rays); the proposal
    that the most observations agree with (ray within `consensus_deg`, in front of the camera) wins,
    so one mismatched keypoint in a long track neither misplaces the point nor hides the others.
    Returns the points, each point's anchor (centre of its first agreeing camera) and, per
    observation, whether it agrees with its point.
    """
    poses = view_poses(sensor_to_ego, ego_to_world)
    P = poses[obs.frame, obs.camera]
    centre = P[:, :3, 3]
    direction = np.einsum("nij,nj->ni", P[:, :3, :3], obs.ray)
    points = np.zeros((n_points, 3))
    anchors = np.zeros((n_points, 3))
    agree = np.zeros(len(obs), dtype=bool)
    if not len(obs):
        return points, anchors, agree
    cos_tol = np.cos(np.radians(consensus_deg))
    order = np.argsort(obs.point, kind="stable")
    counts = np.bincount(obs.point, minlength=n_points)
    for n in np.unique(counts[counts > 0]):
        pts = np.flatnonzero(counts == n)
        starts = np.searchsorted(obs.point[order], pts)
        groups = order[starts[:, None] + np.arange(n)[None, :]]  # (G, n) observation indices
        C, D = centre[groups], direction[groups]
        if n == 1:
            points[pts] = C[:, 0] + 20.0 * D[:, 0]
            anchors[pts] = C[:, 0]
            agree[groups[:, 0]] = True
            continue
        a, b = np.triu_indices(n, 1)
        G, m = pts.size, a.size
        X = triangulate_midpoint(C[:, a].reshape(-1, 3), D[:, a].reshape(-1, 3),
                                 C[:, b].reshape(-1, 3), D[:, b].reshape(-1, 3)).reshape(G, m, 3)
        v = X[:, :, None, :] - C[:, None, :, :]  # (G, m, n, 3)
        cos = np.sum(v * D[:, None, :, :], axis=-1) / np.maximum(np.linalg.norm(v, axis=-1), 1e-12)
        ok = cos >= cos_tol
        score = ok.sum(-1) + 1e-3 * np.where(ok, cos, 0.0).sum(-1)
        best = np.argmax(score, axis=1)
        rows = np.arange(G)
        points[pts] = X[rows, best]
        good = ok[rows, best]  # (G, n)
        agree[groups[good]] = True
        first = np.argmax(good, axis=1)
        anchors[pts] = C[rows, first]
    return points, anchors, agree


def soft_l1(sq: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Soft-L1 cost c^2 * 2 (sqrt(1 + s / c^2) - 1) of squared residual norms, and its IRLS weight."""
    z = 1.0 + sq / (c * c)
    return 2.0 * c * c * (np.sqrt(z) - 1.0), 1.0 / np.sqrt(z)


def cauchy(sq: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Cauchy cost c^2 log(1 + s / c^2) of squared residual norms, and its IRLS weight."""
    z = 1.0 + sq / (c * c)
    return c * c * np.log(z), 1.0 / z


def geman_mcclure(sq: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Geman-McClure cost c^2 s / (c^2 + s) (bounded: far outliers have no pull), and its IRLS weight."""
    c2 = c * c
    return c2 * sq / (c2 + sq), (c2 / (c2 + sq)) ** 2


LOSSES = {"soft_l1": soft_l1, "cauchy": cauchy, "geman_mcclure": geman_mcclure}


def tangent_basis(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each unit ray (N, 3) and to each other: (N, 3), (N, 3)."""
    rays = np.asarray(rays, dtype=np.float64)
    helper = np.where(np.abs(rays[:, 1:2]) < 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(helper, rays)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(rays, e1)
    return e1, e2


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Matrix times vector per observation, observations last: (i, j, N), (j, N) -> (i, N)."""
    return np.einsum("ijn,jn->in", M, x)


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Matrix product per observation, observations last: (i, j, N), (j, k, N) -> (i, k, N)."""
    return np.einsum("ijn,jkn->ikn", A, B)


def _cross_rows(A: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Each row of A (r, 3, N) crossed with w (3, N): (r, 3, N), the rows of A @ skew(w)."""
    return np.stack([A[:, 1] * w[2] - A[:, 2] * w[1], A[:, 2] * w[0] - A[:, 0] * w[2],
                     A[:, 0] * w[1] - A[:, 1] * w[0]], axis=1)


def _focal_groups(maps: Sequence[FocalMap | None], camera: np.ndarray) -> list[tuple[FocalMap, np.ndarray]]:
    """The observations (indices) per focal map: one group for the plain pinholes' maps (all alike), one per
    other camera with a map; cameras without a map or observations have none."""
    plain = [m for m, fm in enumerate(maps) if fm is not None and fm.theta is None]
    groups = [(FocalMap(), plain)] if plain else []
    groups += [(fm, [m]) for m, fm in enumerate(maps) if fm is not None and fm.theta is not None]
    members = [(fm, np.flatnonzero(np.isin(camera, ms))) for fm, ms in groups]
    return [(fm, idx) for fm, idx in members if idx.size]


class _Problem:
    """Residuals, Jacobians and priors of one loop-constrained adjustment.

    Pose unknowns (left-multiplied rotation increments, additive translations): 6 per frame (frame 0
    is fixed), 6 per non-reference camera, 3 for G; the reference camera maps to a discarded slot. With
    `config.refine_focal` and `focal_maps`, one focal-length scale per camera follows (every camera's,
    the reference's included; a camera whose map is None keeps 1 through its prior).
    """

    def __init__(self, sensor_to_ego, ego_to_world, obs, focal, reference, config: AdjustConfig,
                 capture_mount: np.ndarray | None = None, focal_maps: Sequence[FocalMap | None] | None = None):
        self.M, self.T = sensor_to_ego.shape[0], ego_to_world.shape[0]
        self.ref, self.cfg, self.obs = reference, config, obs
        mounts = sensor_to_ego.copy()
        if capture_mount is not None:
            mounts[reference] = capture_mount
        cap = capture_offsets(mounts, ego_to_world, reference)  # (T, M, 4, 4)
        self.cap_RT = np.swapaxes(cap[:, :, :3, :3], 2, 3)  # per frame and camera
        self.cap_RT_t = np.einsum("tmij,tmj->tmi", self.cap_RT, cap[:, :, :3, 3])
        self.view = obs.frame * self.M + obs.camera  # each observation's (frame, camera)
        if ego_to_world.ndim == 4:
            ego_to_world = ego_to_world[:, reference]
        self.loss = LOSSES[config.loss]
        self.sigma = np.ones(len(obs)) if obs.sigma_px is None else np.asarray(obs.sigma_px, dtype=np.float64)
        # residuals are in units of each observation's sigma
        self.focal = np.asarray(focal, dtype=np.float64)[obs.camera] / self.sigma
        S_ref = sensor_to_ego[reference]
        W = np.einsum("tij,jk->tik", ego_to_world, S_ref)  # reference camera -> ego world, initial mount
        self.W = W
        to_local = invert_transform(W[0])  # the adjustment world is the reference camera in frame 0
        self.W_local = np.einsum("ij,tjk->tik", to_local, W)
        self.R_local = to_local[:3, :3]
        self.d_t = W[:, :3, 3] - W[0, :3, 3]  # ego-world displacement of the reference camera
        self.dR_t = np.einsum("tij,kj->tik", W[:, :3, :3], W[0, :3, :3])  # ego-world rotation 0 -> t
        Q0 = np.einsum("ij,mjk->mik", invert_transform(S_ref), sensor_to_ego)
        Q0[reference] = np.eye(4)
        self.Q0 = Q0
        self.others = [m for m in range(self.M) if m != reference]
        n_o = len(self.others)
        slot = np.full(self.M, n_o)  # the reference camera maps to the discarded slot
        for s_, m in enumerate(self.others):
            slot[m] = s_
        self.g_idx = 6 * self.T + 6 * n_o
        self.n_full = self.g_idx + 3 + 6
        self.solve_idx = np.arange(6, self.g_idx + 3)  # frame 0 fixed, discarded slot excluded
        fi = 6 * obs.frame[:, None] + np.arange(6)[None, :]
        ci = np.where(slot[obs.camera] < n_o, 6 * self.T + 6 * slot[obs.camera], self.g_idx + 3)
        self.pose_idx = np.concatenate([fi, ci[:, None] + np.arange(6)[None, :]], axis=1)  # (N, 12)
        self.is_ref = obs.camera == reference
        ray = np.asarray(obs.ray, dtype=np.float64)
        self.ray = np.ascontiguousarray(ray.T)  # (3, N)
        self.E = np.ascontiguousarray(np.stack(tangent_basis(ray), axis=0).transpose(0, 2, 1))  # (2, 3, N)
        n = self.n_full
        self.maps = list(focal_maps) if config.refine_focal and focal_maps is not None else None
        if self.maps is not None:
            self.f_idx = n
            self.n_full = n = n + self.M
            self.solve_idx = np.concatenate([self.solve_idx, self.f_idx + np.arange(self.M)])
            self.pose_idx = np.concatenate([self.pose_idx, (self.f_idx + obs.camera)[:, None]], axis=1)  # (N, 13)
            self.focal_groups = _focal_groups(self.maps, obs.camera)
        self.views = view_layout(self.view, self.pose_idx)
        self.point_blocks = point_blocks(self.pose_idx, obs.point, n, int(obs.point.max()) + 1 if len(obs) else 0)

    def initial_state(self, n_points: int) -> _State:
        """Poses from the initial extrinsics and ego poses; points still to be triangulated."""
        z = np.zeros((n_points, 3))
        return _State(self.W_local[:, :3, :3].copy(), self.W_local[:, :3, 3].copy(), self.Q0[:, :3, :3].copy(),
                      self.Q0[:, :3, 3].copy(), self.R_local.copy(), z, z + [0.0, 0.0, 1.0], np.ones(n_points),
                      None if self.maps is None else np.ones(self.M))

    def focal_scales(self, st: _State) -> np.ndarray:
        """The state's focal scales (ones when it has none, e.g. a warm start from a run without them)."""
        return np.ones(self.M) if st.s is None else st.s

    def map_focal(self, q: np.ndarray, st: _State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame directions (3, N) -> the directions the rig's intrinsics see (focal_scale), d/dq
        (3, 3, N), d/ds (3, N)."""
        n = q.shape[1]
        out, ds = q.copy(), np.zeros_like(q)
        dq = np.zeros((3, 3, n))
        dq[[0, 1, 2], [0, 1, 2]] = 1.0
        s = self.focal_scales(st)[self.obs.camera]
        for fm, idx in self.focal_groups:
            v, J, d = fm.apply(q[:, idx].T, s[idx])
            out[:, idx], dq[:, :, idx], ds[:, idx] = v.T, np.moveaxis(J, 0, 2), d.T
        return out, dq, ds

    def extrinsics(self, st: _State, S_ref: np.ndarray) -> np.ndarray:
        """sensor_to_ego (M, 4, 4) of a state, the reference camera at `S_ref`."""
        S = np.einsum("ij,mjk->mik", S_ref, make_transform(st.R_m, st.p_m))
        S[self.ref] = S_ref
        return S

    def obs_terms(self, st: _State, jacobians: bool, poses: bool = True) -> np.ndarray | tuple:
        """Residuals (N, 2); with `jacobians` also d r / d pose (N, 2, 12; None without `poses`) and
        d r / d point (N, 2, 3): `terms` with the observations first."""
        out = self.terms(st, jacobians, poses)
        if not jacobians:
            return out.T
        r, Jp, Jl = out
        return r.T, None if Jp is None else np.moveaxis(Jp, 2, 0), np.moveaxis(Jl, 2, 0)

    def terms(self, st: _State, jacobians: bool, poses: bool = True) -> np.ndarray | tuple:
        """Residuals (2, N); with `jacobians` also d r / d pose (2, 12, N; None without `poses`) and
        d r / d point (2, 3, N). The observations are the last axis: numpy's products of many tiny matrices
        are an order of magnitude faster component by component over a long axis than as stacked matrices.

        With P = anchor + m / rho the direction to the point is that of q = rho * (camera-frame P), which
        stays finite for points at infinity: q = R_m^T (R_t^T (rho (anchor - c_t) + m) - rho p_m).
        """
        o = self.obs
        # the rotations and offsets depend on (frame, camera) only: composed once per pair, then gathered
        RmT_all = np.swapaxes(st.R_m, 1, 2)  # (M, 3, 3)
        RtT_all = np.einsum("tmij,tkj->tmik", self.cap_RT, st.R_t)  # E_R^T R_t^T, (T, M, 3, 3)
        C_all = np.einsum("mij,tmjk->tmik", RmT_all, RtT_all).reshape(-1, 9)  # R_m^T E_R^T R_t^T
        d_all = np.einsum("mij,tmj->tmi", RmT_all, self.cap_RT_t + st.p_m[None]).reshape(-1, 3)
        C = np.take(C_all.T, self.view, axis=1).reshape(3, 3, -1)
        d, ct = np.take(d_all.T, self.view, axis=1), np.take(st.c_t.T, o.frame, axis=1)
        rho, m, a = np.take(st.rho, o.point), np.take(st.m.T, o.point, axis=1), np.take(st.anchor.T, o.point, axis=1)
        h = rho * (a - ct) + m
        q = q_cam = _mv(C, h) - rho * d  # R_m^T (E_R^T R_t^T h - rho (E_R^T E_t + p_m))
        if self.maps is not None:
            q, dq_dq, dq_ds = self.map_focal(q, st)
        nq = np.maximum(np.sqrt(np.sum(q * q, axis=0)), 1e-12)
        u = q / nq
        # stereographic residual 2 f E u / (1 + ray . u): f * angle near the ray, no minimum at the antipode
        Eu = _mv(self.E, u)
        s = np.maximum(1.0 + np.sum(self.ray * u, axis=0), 1e-9)
        gain = 2.0 * self.focal / s
        r = gain * Eu
        if not jacobians:
            return r
        # dr/du = (2 f / s) (E - E u ray^T / s); du/dq = (I - u u^T) / |q|
        dr_du = gain * (self.E - Eu[:, None, :] * (self.ray / s)[None])
        A = (dr_du - _mv(dr_du, u)[:, None, :] * u[None]) / nq
        extra = []
        if self.maps is not None:
            extra = [_mv(A, dq_ds)[:, None, :]]  # d r / d s of the observation's camera
            A = _mm(A, dq_dq)
        A_C = _mm(A, C)  # A R_m^T E_R^T R_t^T
        J_pose = None
        if poses:
            RmT = np.take(RmT_all.reshape(-1, 9).T, o.camera, axis=1).reshape(3, 3, -1)
            A_RmT = _mm(A, RmT)
            v = np.einsum("jin,jn->in", RmT, q_cam)  # R_m q: the point before the camera's rotation
            # a @ skew(w) for each row a is the cross product a x w
            J_pose = np.concatenate([_cross_rows(A_C, h), -rho * A_C, _cross_rows(A_RmT, v), -rho * A_RmT] + extra,
                                    axis=1)  # (2, 12, N), (2, 13, N) with the focal scale
            J_pose[:, 6:12, self.is_ref] = 0.0
        e1, e2 = tangent_basis(st.m)
        B = np.take(np.stack([e1, e2], axis=2).reshape(-1, 6).T, o.point, axis=1).reshape(3, 2, -1)  # basis of m
        d_rho = _mv(C, a - ct) - d  # R_m^T (E_R^T R_t^T (a - c_t) - E_R^T E_t - p_m)
        J_pt = np.concatenate([_mm(A_C, B), _mv(A, d_rho)[:, None, :]], axis=1)  # (2, 3, N)
        return r, J_pose, J_pt

    def prior_terms(self, st: _State) -> list[tuple[np.ndarray, list[tuple[int, np.ndarray]]]]:
        """Prior residuals (k,) with their Jacobian blocks [(first pose column, k x width)], small-angle form."""
        cfg = self.cfg
        out: list[tuple[np.ndarray, list[tuple[int, np.ndarray]]]] = []
        eye = np.eye(3)
        s_c, s_e = 1.0 / cfg.sigma_centre_m, 1.0 / np.radians(cfg.sigma_ego_rot_deg)
        s_g = 1.0 / np.radians(cfg.sigma_gauge_rot_deg)
        s_rr, s_rt = 1.0 / np.radians(cfg.sigma_rel_rot_deg), 1.0 / cfg.sigma_rel_t_m
        G, gi = st.G, self.g_idx
        out.append((rotation_vector(G @ self.R_local.T) * s_g, [(gi, s_g * eye)]))
        for t in range(1, self.T):
            Gd = G @ self.d_t[t]
            out.append(((st.c_t[t] - st.c_t[0] - Gd) * s_c, [(6 * t + 3, s_c * eye), (gi, s_c * skew(Gd))]))
            A = st.R_t[t] @ st.R_t[0].T
            B = G @ self.dR_t[t] @ G.T
            out.append((rotation_vector(A @ B.T) * s_e, [(6 * t, s_e * eye), (gi, s_e * (A - eye))]))
        for s_, m in enumerate(self.others):
            base = 6 * self.T + 6 * s_
            out.append((rotation_vector(st.R_m[m] @ self.Q0[m, :3, :3].T) * s_rr, [(base, s_rr * eye)]))
            out.append(((st.p_m[m] - self.Q0[m, :3, 3]) * s_rt, [(base + 3, s_rt * eye)]))
        if self.maps is not None:
            s_f = 1.0 / cfg.sigma_focal
            out.append(((self.focal_scales(st) - 1.0) * s_f, [(self.f_idx, s_f * np.eye(self.M))]))
        return out

    def cost(self, st: _State, r: np.ndarray | None = None) -> float:
        """Robust observation cost plus the priors; `r`: the state's residuals (2, N) when already evaluated."""
        if r is None:
            r = self.terms(st, jacobians=False)
        rho, _ = self.loss(np.sum(r * r, axis=0), self.cfg.f_scale)
        return float(np.sum(rho) + sum(float(x @ x) for x, _ in self.prior_terms(st)))

    def focal_scale_sigma(self, cov: np.ndarray) -> np.ndarray | None:
        """1-sigma (M,) of each camera's focal scale from `covariance`; None when they are not refined."""
        if self.maps is None:
            return None
        d = np.diag(cov)[self.f_idx : self.f_idx + self.M]
        return np.sqrt(np.maximum(d, 0.0))

    def camera_rotation_covariance(self, cov: np.ndarray) -> np.ndarray:
        """The cameras' rotation blocks (M, M, 3, 3) of a covariance of the increments (`schur.covariance`):
        rad^2, zero for the reference camera."""
        out = np.zeros((self.M, self.M, 3, 3))
        idx = {m: 6 * self.T + 6 * s_ for s_, m in enumerate(self.others)}
        for a, ia in idx.items():
            for b, ib in idx.items():
                out[a, b] = cov[ia : ia + 3, ib : ib + 3]
        return out

    @staticmethod
    def move_points(st: _State, dl: np.ndarray) -> None:
        """Apply point increments (K, 3): two tangent components of the direction, then inverse distance."""
        e1, e2 = tangent_basis(st.m)
        m = st.m + dl[:, :1] * e1 + dl[:, 1:2] * e2
        st.m = m / np.linalg.norm(m, axis=1, keepdims=True)
        # no clamp at 0: the model uses the direction of rho * P, continuous through infinity (homogeneous
        # coordinates); a far point may end slightly "beyond infinity" within its noise
        st.rho = st.rho + dl[:, 2]

    def apply(self, st: _State, dp: np.ndarray, dl: np.ndarray) -> _State:
        """A new state moved by pose increments `dp` and point increments `dl`."""
        T = self.T
        new = st.copy()
        ft = dp[: 6 * T].reshape(T, 6)
        new.R_t = rodrigues(ft[:, :3]) @ st.R_t
        new.c_t = st.c_t + ft[:, 3:]
        for s_, m in enumerate(self.others):
            b = 6 * T + 6 * s_
            new.R_m[m] = rodrigues(dp[b : b + 3]) @ st.R_m[m]
            new.p_m[m] = st.p_m[m] + dp[b + 3 : b + 6]
        new.G = rodrigues(dp[self.g_idx : self.g_idx + 3]) @ st.G
        if self.maps is not None:
            new.s = self.focal_scales(st) + dp[self.f_idx : self.f_idx + self.M]
        self.move_points(new, dl)
        return new


def adjust(
    sensor_to_ego: np.ndarray,
    ego_to_world: np.ndarray,
    obs: Observations,
    focal: np.ndarray,
    reference: int = 0,
    config: AdjustConfig | None = None,
    start: AdjustResult | None = None,
    start_points: np.ndarray | None = None,
    focal_maps: Sequence[FocalMap | None] | None = None,
) -> AdjustResult:
    """Loop-constrained bundle adjustment over one window; see the module docstring.

    sensor_to_ego: (M, 4, 4) initial extrinsics (the priors refer to them); ego_to_world: (T, 4, 4) ego
    poses of the window, or (T, M, 4, 4) each camera's own ego pose at its capture (see capture_offsets);
    obs: observations (camera, frame, point, unit ray, sigma); focal: (M,) pixels
    per radian; reference: index of the camera that carries the gauge. `start` (a previous result of
    the same problem) with `start_points` (which of its points `obs` numbers 0, 1, ...) warm-starts.
    `focal_maps` (one per camera, `focal.focal_map`) with `config.refine_focal` adds a focal-length scale per
    camera with a Gaussian prior of `config.sigma_focal` around 1 (`AdjustResult.focal_scale`).
    The iteration count includes rejected (re-damped) steps and is at most `config.max_iterations`.
    """
    cfg = config or AdjustConfig()
    sensor_to_ego = np.asarray(sensor_to_ego, dtype=np.float64)
    ego_to_world = np.asarray(ego_to_world, dtype=np.float64)
    if ego_to_world.ndim == 4 and (start is None or start.state is None) and cfg.max_iterations > 1:
        return _adjust_captured(sensor_to_ego, ego_to_world, obs, focal, reference, cfg, focal_maps)
    prob, st = _problem_and_start(sensor_to_ego, ego_to_world, obs, focal, reference, cfg, start, start_points,
                                  focal_maps)
    r0 = prob.obs_terms(st, jacobians=False) * prob.sigma[:, None]
    initial_rms = float(np.sqrt(np.mean(np.sum(r0 * r0, axis=1)))) if len(obs) else 0.0
    cost = prob.cost(st)
    lam = cfg.initial_damping
    converged, message, it = False, "iteration limit reached", 0
    while it < cfg.max_iterations:
        it += 1
        trial, step_size, r_trial = lm_step(prob, st, lam)
        new_cost = prob.cost(trial, r_trial)
        if np.isfinite(new_cost) and new_cost <= cost:
            decrease = cost - new_cost
            st, cost = trial, new_cost
            lam = max(lam / 3.0, 1e-10)
            if decrease <= cfg.ftol * max(cost, 1e-12):
                converged, message = True, f"converged (relative cost decrease {decrease / max(cost, 1e-12):.1e})"
                break
            if step_size < cfg.pose_tol:
                converged, message = True, f"converged (largest pose step {step_size:.1e})"
                break
        else:
            lam *= 8.0
            if lam > 1e10:
                converged, message = True, "converged (no further decrease at any damping)"
                break
    res = prob.obs_terms(st, jacobians=False) * prob.sigma[:, None]
    final_rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1)))) if len(obs) else 0.0
    return AdjustResult(
        sensor_to_ego=prob.extrinsics(st, sensor_to_ego[reference]),
        points=st.P,
        residual_px=res,
        iterations=it,
        converged=converged,
        message=message,
        initial_rms_px=initial_rms,
        final_rms_px=final_rms,
        state=st,
        focal_scale=None if prob.maps is None else prob.focal_scales(st).copy(),
    )


def _problem_and_start(sensor_to_ego, ego_to_world, obs, focal, reference, cfg, start, start_points,
                       focal_maps=None):
    """The problem and its starting state: a previous result's (warm start), else the initial poses with
    points triangulated from them. With per-camera capture, a warm start's G gives the reference mount's
    orientation for the capture offsets."""
    warm = start is not None and start.state is not None
    mount = None
    if ego_to_world.ndim == 4 and warm:
        mount = sensor_to_ego[reference].copy()
        mount[:3, :3] = ego_to_world[0, reference, :3, :3].T @ start.state.G.T  # ego-world -> camera at frame 0
    prob = _Problem(sensor_to_ego, ego_to_world, obs, focal, reference, cfg, capture_mount=mount,
                    focal_maps=focal_maps)
    if warm:
        st = start.state.copy()
        if start_points is not None:
            st.subset(start_points)
        return prob, st
    n_points = int(obs.point.max()) + 1 if len(obs) else 0
    st = prob.initial_state(n_points)
    cap = capture_offsets(sensor_to_ego, ego_to_world, reference)
    ego_local = np.einsum("tij,tmjk,kl->tmil", make_transform(st.R_t, st.c_t), cap,
                          invert_transform(sensor_to_ego[reference]))
    points, anchors, _ = initial_points(sensor_to_ego, ego_local, obs, n_points, cfg.consensus_deg)
    st.set_points(points, anchors)
    return prob, st


def _adjust_captured(sensor_to_ego: np.ndarray, ego_to_world: np.ndarray, obs: Observations, focal: np.ndarray,
                     reference: int, cfg: AdjustConfig,
                     focal_maps: Sequence[FocalMap | None] | None = None) -> AdjustResult:
    """Per-camera capture: the ego motion between captures is turned into the reference camera's frame with its
    mount; a first solve estimates the mount's orientation (through G), a second one uses it."""
    first = adjust(sensor_to_ego, ego_to_world, obs, focal, reference,
                   replace(cfg, max_iterations=cfg.max_iterations // 2), focal_maps=focal_maps)
    again = adjust(sensor_to_ego, ego_to_world, obs, focal, reference,
                   replace(cfg, max_iterations=cfg.max_iterations - first.iterations), start=first,
                   focal_maps=focal_maps)
    again.iterations += first.iterations
    again.initial_rms_px = first.initial_rms_px
    return again


def relative_rotation_sigma_deg(rotation_cov: np.ndarray, a: int, b: int) -> float:
    """1-sigma (largest axis, degrees) of the relative rotation of cameras a and b from `AdjustResult.rotation_cov`:
    how well the images and priors determine it (large when a camera hangs on degenerate observations)."""
    C = rotation_cov[a, a] + rotation_cov[b, b] - rotation_cov[a, b] - rotation_cov[b, a]
    return float(np.degrees(np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (C + C.T)).max()), 0.0))))


def select_observations(obs: Observations, keep_obs: np.ndarray) -> tuple[Observations, np.ndarray, np.ndarray]:
    """Keep some observations, then drop points left with fewer than two; renumber points 0, 1, ...

    Returns the new observations, the mask of kept input observations and the kept points' old ids.
    """
    keep = np.asarray(keep_obs, dtype=bool).copy()
    counts = np.bincount(obs.point[keep], minlength=int(obs.point.max()) + 1 if len(obs) else 0)
    keep &= counts[obs.point] >= 2
    old_ids, new_ids = np.unique(obs.point[keep], return_inverse=True)
    sigma = None if obs.sigma_px is None else obs.sigma_px[keep]
    sub = Observations(obs.camera[keep], obs.frame[keep], new_ids.astype(np.int64), obs.ray[keep], sigma)
    return sub, keep, old_ids


@dataclass(frozen=True)
class RobustSchedule:
    """Passes of `robust_adjust`: graduated coarse fit, reject, weighted fit, reject, final fit."""

    coarse_scales_px: tuple[float, ...] = (1.0,)
    coarse_loss: str = "cauchy"
    coarse_iterations_per_scale: int = 40
    coarse_ftol: float = 1e-4
    coarse_pose_tol: float = 1e-4
    coarse_reject_px: float = 3.0
    fine_reject_sigma: float = 5.0


def robust_adjust(
    sensor_to_ego: np.ndarray,
    ego_to_world: np.ndarray,
    obs: Observations,
    focal: np.ndarray,
    reference: int = 0,
    config: AdjustConfig | None = None,
    schedule: RobustSchedule | None = None,
    focal_maps: Sequence[FocalMap | None] | None = None,
) -> tuple[AdjustResult, np.ndarray]:
    """Adjustment in passes with outlier rejection between them; returns the result and the kept observations.

    First, observations that disagree by more than `config.consensus_deg` with their track's consensus
    point at the input poses are dropped (mismatched keypoints joined to a good track). Pass 1 weighs
    every observation as 1 px under a Cauchy loss (scale 1 px), whose pull fades for far
    outliers that RANSAC leaves (e.g. tracks on moving cars), where they would bend a soft-L1 fit; a
    schedule of shrinking scales (graduated non-convexity) or the bounded Geman-McClure loss can be
    chosen instead, but measured worse on the synthetic sequences. Observations with a residual above
    `coarse_reject_px` are then dropped (and points left with one observation). Pass 2 weighs each
    observation by its own sigma (SIFT keypoints are less precise at coarse scales), still under the
    Cauchy loss: an outlier 100 sigmas off would weigh like 100 inliers under soft-L1, and a handful
    of them (two-view points on a passing car) was measured to bend the ring by 0.4 deg. Observations
    above `fine_reject_sigma` sigmas are dropped and pass 3, the final adjustment, uses the configured
    loss (soft-L1 by default, the paper's near-L1). Passes warm-start from the previous one and share
    one iteration budget.

    Focal lengths (`config.refine_focal` with `focal_maps`): the passes run first with every camera's
    focal-length scale free (prior `config.sigma_focal`), which estimates each with its 1-sigma. A scale
    that differs from 1 by at least `config.focal_min_sigmas` sigmas is adopted. When all are, that is
    the result; when none is, the result is that of the passes with the rig's intrinsics (the
    fixed-intrinsics one, unchanged; with `config.threads` > 1 they run beside the free ones); otherwise
    the passes run again with the adopted cameras' scales free and the others at 1. `focal_scale_free` /
    `focal_scale_sigma` report the free estimates either way; `iterations` counts the passes of the result
    only (each run has the full iteration limit).
    """
    cfg = config or AdjustConfig()
    sch = schedule or RobustSchedule()
    args = (sensor_to_ego, ego_to_world, obs, focal, reference, cfg, sch)
    # one BLAS thread: the matrices are small (threads spinning per call cost more than they gain), and the
    # result does not depend on how many passes run side by side
    with blas_threads(1), ThreadPoolExecutor(max(1, cfg.threads)) as pool:
        if not (cfg.refine_focal and focal_maps is not None and any(fm is not None for fm in focal_maps)):
            return _robust_passes(*args, None)[:2]
        # the fixed-intrinsics passes, the answer when no scale is adopted, run beside the free ones
        fixed = pool.submit(_robust_passes, *args, None) if cfg.threads > 1 else None
        res, kept, _ = _robust_passes(*args, focal_maps)
        if res.focal_scale is None or res.focal_scale_sigma is None:
            return res, kept
        free, sigma = res.focal_scale.copy(), res.focal_scale_sigma.copy()
        adopt = np.array([fm is not None for fm in focal_maps]) & (np.abs(free - 1.0) >= cfg.focal_min_sigmas * sigma)
        _LOG.debug("focal scales: free %s, sigma %s, adopted %s", free, sigma, adopt)
        if not adopt.any():
            res, kept, _ = fixed.result() if fixed is not None else _robust_passes(*args, None)
            res.focal_scale = np.ones_like(free)
        elif not adopt.all():
            res, kept, _ = _robust_passes(*args, [fm if adopt[m] else None for m, fm in enumerate(focal_maps)])
    res.focal_scale_free, res.focal_scale_sigma = free, sigma
    return res, kept


def _robust_passes(sensor_to_ego, ego_to_world, obs, focal, reference, cfg, sch, focal_maps):
    """The passes of `robust_adjust` (focal scales free for the cameras whose map is given): the result, the
    kept input observations and the final observations."""
    budget = cfg.max_iterations
    n_input = len(obs)
    # observations that disagree with their track's consensus point at the initial poses are mismatches
    n_points = int(obs.point.max()) + 1 if len(obs) else 0
    _, _, agree = initial_points(sensor_to_ego, ego_to_world, obs, n_points, cfg.consensus_deg)
    obs, mask, _ = select_observations(obs, agree)
    kept_idx = np.flatnonzero(mask)
    if len(obs) == 0:  # nothing to adjust (every match disagreed with its track): the start, not converged
        start = np.array(sensor_to_ego, dtype=np.float64)
        res = AdjustResult(start, np.zeros((0, 3)), np.zeros((0, 2)), 0, False, "no observation to adjust", 0.0, 0.0,
                           focal_scale=None if focal_maps is None else np.ones(len(start)))
        return res, np.zeros(n_input, dtype=bool), obs
    plain = Observations(obs.camera, obs.frame, obs.point, obs.ray)
    res, used = None, 0
    for scale in sch.coarse_scales_px:  # graduated non-convexity: a wide basin first, then sharper
        stage = replace(cfg, loss=sch.coarse_loss, f_scale=scale, pose_tol=max(cfg.pose_tol, sch.coarse_pose_tol),
                        ftol=max(cfg.ftol, sch.coarse_ftol),
                        max_iterations=max(1, min(sch.coarse_iterations_per_scale, budget - used)))
        res = adjust(sensor_to_ego, ego_to_world, plain, focal, reference, config=stage, start=res,
                     focal_maps=focal_maps)
        used += res.iterations
        _LOG.debug("coarse pass: scale %s, %d iterations, %s", scale, res.iterations, res.message)
    cur_obs = obs
    # pass 2 (weighted, Cauchy) after rejecting in pixels, pass 3 (weighted, configured loss) after
    # rejecting in sigmas
    stages = ((sch.coarse_reject_px, False, replace(cfg, loss=sch.coarse_loss)), (sch.fine_reject_sigma, True, cfg))
    for limit, in_sigmas, stage_cfg in stages:
        if budget - used <= 0 or len(cur_obs) == 0:
            break
        err = np.linalg.norm(res.residual_px, axis=1)
        if in_sigmas and cur_obs.sigma_px is not None:
            err = err / cur_obs.sigma_px
        sub, mask, old_ids = select_observations(cur_obs, err <= limit)
        if len(sub) == 0:
            break
        cur_obs, kept_idx = sub, kept_idx[mask]
        res = adjust(sensor_to_ego, ego_to_world, cur_obs, focal, reference,
                     config=replace(stage_cfg, max_iterations=budget - used), start=res, start_points=old_ids,
                     focal_maps=focal_maps)
        used += res.iterations
        _LOG.debug("pass: limit %s, loss %s, %d iterations, %s, %d observations", limit, stage_cfg.loss,
                   res.iterations, res.message, len(cur_obs))
    res.iterations = used
    if len(cur_obs):
        prob, st = _problem_and_start(sensor_to_ego, ego_to_world, cur_obs, focal, reference, cfg, res, None,
                                      focal_maps)
        cov = covariance(prob, st)
        res.rotation_cov = prob.camera_rotation_covariance(cov)
        res.focal_scale_sigma = prob.focal_scale_sigma(cov)
    kept = np.zeros(n_input, dtype=bool)
    kept[kept_idx] = True
    return res, kept, cur_obs
