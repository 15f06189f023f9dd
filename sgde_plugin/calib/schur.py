"""The solver half of the loop-constrained adjustment (`ba.py` holds the model): damped Gauss-Newton
(Levenberg-Marquardt) steps on the normal equations with the points eliminated per point (Schur complement,
the standard bundle-adjustment reduction), a safeguarded Gauss-Newton step per point with the poses held,
and the covariance of the pose (and focal-scale) unknowns. Each function takes the problem (`ba._Problem`:
residuals, Jacobians, priors, unknown layout) and a state. Per-observation arrays have the observations on their
last axis (`_Problem.terms`); per-point ones on their first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .ba import _Problem, _State


def lm_step(prob: _Problem, st: _State, lam: float) -> tuple[_State, float, np.ndarray | None]:
    """One damped Gauss-Newton step (Schur complement on the points); returns the trial state, the largest pose
    step and the trial's residuals (None when no point step ran)."""
    o, n = prob.obs, prob.n_full
    K = st.P.shape[0]
    S, rhs, Hlp, Hll_inv, gl = reduced_system(prob, st, lam)
    keep = prob.solve_idx
    dp = np.zeros(n)
    dp[keep] = np.linalg.solve(S[np.ix_(keep, keep)], rhs[keep])
    back = point_sums(o.point, np.einsum("icn,cn->in", Hlp, dp[prob.pose_idx.T]), K)
    dl = -(Hll_inv @ (gl + back)[:, :, None])[:, :, 0]
    trial = prob.apply(st, dp, dl)
    r = None
    for _ in range(prob.cfg.point_iterations):
        r = refine_points(prob, trial)
    return trial, float(np.abs(dp[keep]).max(initial=0.0)), r


def reduced_system(prob: _Problem, st: _State, lam: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The damped normal equations of the poses with the points eliminated (Schur complement): S, the
    right-hand side, and what the point back-substitution needs (Hlp, Hll^-1, gl)."""
    o, n = prob.obs, prob.n_full
    K = st.P.shape[0]
    r, Jp, Jl = prob.terms(st, jacobians=True)  # observations last
    _, w = prob.loss(np.sum(r * r, axis=0), prob.cfg.f_scale)
    Jl_w = Jl * w
    Hll = point_sums(o.point, np.einsum("ain,ajn->ijn", Jl_w, Jl), K)
    gl = point_sums(o.point, np.einsum("ain,an->in", Jl_w, r), K)
    Hpp, gp = pose_terms(prob.views, Jp, r, w, n)
    for x, blocks in prob.prior_terms(st):
        for ia, Ja in blocks:
            gp[ia : ia + Ja.shape[1]] += Ja.T @ x
            for ib, Jb in blocks:
                Hpp[ia : ia + Ja.shape[1], ib : ib + Jb.shape[1]] += Ja.T @ Jb
    Hll_d = Hll + lam * np.einsum("kii->ki", Hll)[:, :, None] * np.eye(3)[None] + 1e-12 * np.eye(3)[None]
    Hpp_d = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-12 * np.eye(n)
    L_inv = inverse_cholesky(Hll_d)
    Hll_inv = np.swapaxes(L_inv, 1, 2) @ L_inv
    Hlp = np.einsum("ain,acn->icn", Jl_w, Jp)  # (3, 12, N)
    z = (L_inv @ gl[:, :, None])[:, :, 0]
    reduce_S, reduce_g = point_terms(prob.point_blocks, Hlp, L_inv, z, n)
    return Hpp_d - reduce_S, reduce_g - gp, Hlp, Hll_inv, gl


def inverse_cholesky(H: np.ndarray) -> np.ndarray:
    """L^-1 (K, 3, 3), lower triangular, of symmetric positive definite H = L L^T (K, 3, 3), component by
    component. Pivots below 1e-12 (the damping's floor: only rounding puts one there) are raised to it."""
    pivot = lambda x: np.sqrt(np.maximum(x, 1e-12))  # noqa: E731
    l00 = pivot(H[:, 0, 0])
    l10, l20 = H[:, 1, 0] / l00, H[:, 2, 0] / l00
    l11 = pivot(H[:, 1, 1] - l10 * l10)
    l21 = (H[:, 2, 1] - l20 * l10) / l11
    l22 = pivot(H[:, 2, 2] - l20 * l20 - l21 * l21)
    out = np.zeros_like(H)
    out[:, 0, 0], out[:, 1, 1], out[:, 2, 2] = 1.0 / l00, 1.0 / l11, 1.0 / l22
    out[:, 1, 0] = -l10 * out[:, 0, 0] * out[:, 1, 1]
    out[:, 2, 1] = -l21 * out[:, 1, 1] * out[:, 2, 2]
    out[:, 2, 0] = -(l20 * out[:, 0, 0] + l21 * out[:, 1, 0]) * out[:, 2, 2]
    return out


@dataclass(frozen=True)
class ViewLayout:
    """The observations grouped by (frame, camera): all of a group's residuals depend on the same pose unknowns."""

    order: np.ndarray  # observation indices, group by group
    cuts: np.ndarray  # group g is order[cuts[g]:cuts[g + 1]]
    pose_idx: np.ndarray  # (groups, unknowns per observation)


def view_layout(view: np.ndarray, pose_idx: np.ndarray) -> ViewLayout:
    """Group observations by their (frame, camera) index `view` (N,), pose unknowns `pose_idx` (N, c)."""
    order = np.argsort(view, kind="stable")
    cuts = np.flatnonzero(np.diff(view[order], prepend=-1, append=-2) != 0)
    return ViewLayout(order, cuts, pose_idx[order[cuts[:-1]]])


def pose_terms(views: ViewLayout, Jp: np.ndarray, r: np.ndarray, w: np.ndarray,
               n: int) -> tuple[np.ndarray, np.ndarray]:
    """The observations' pose block of the normal equations (n, n) and gradient (n,) from the pose Jacobians
    Jp (2, c, N), residuals r (2, N) and weights w (N,): one product per group of observations that share their
    pose unknowns (a sum over observations would scatter c^2 numbers each)."""
    X = np.take(np.concatenate([Jp, r[:, None, :]], axis=1), views.order, axis=2)  # (2, c + 1, N)
    Xw = X * np.take(w, views.order)
    c = X.shape[1]
    blocks = np.stack([Xw[0, :, a:b] @ X[0, :, a:b].T + Xw[1, :, a:b] @ X[1, :, a:b].T
                       for a, b in zip(views.cuts[:-1], views.cuts[1:])]) if X.shape[2] else np.zeros((0, c, c))
    idx = views.pose_idx
    flat = (idx[:, :, None] * n + idx[:, None, :]).ravel()
    Hpp = np.bincount(flat, weights=blocks[:, :-1, :-1].ravel(), minlength=n * n).reshape(n, n)
    gp = np.bincount(idx.ravel(), weights=blocks[:, :-1, -1].ravel(), minlength=n)
    return Hpp, gp


@dataclass(frozen=True)
class PointBlock:
    """One chunk of points of the Schur complement: its observations (point by point), first point, count, and
    where each entry of their (3, c) per-observation products lands in the chunk's dense (points * 3, n) matrix."""

    obs: np.ndarray
    points: np.ndarray  # the point of each of `obs`
    first: int
    count: int
    flat: np.ndarray


def point_blocks(pose_idx: np.ndarray, point: np.ndarray, n: int, K: int, chunk: int = 8192) -> list[PointBlock]:
    """The chunks of `point_terms` for observations with pose unknowns `pose_idx` (N, c) of points `point`."""
    out = []
    for k0 in range(0, K, chunk):
        sel = np.flatnonzero((point >= k0) & (point < k0 + chunk))
        sel = sel[np.argsort(point[sel], kind="stable")]  # in memory order: the scatter below stays in cache
        rows = 3 * (point[sel] - k0)[:, None, None] + np.arange(3)[None, :, None]  # (N, 3, 1)
        flat = (rows * n + pose_idx[sel, None, :]).ravel()  # in (N, 3, c) order
        out.append(PointBlock(sel, point[sel], k0, min(chunk, K - k0), flat))
    return out


def point_terms(blocks: Sequence[PointBlock], Hlp: np.ndarray, L_inv: np.ndarray, z: np.ndarray,
                n: int) -> tuple[np.ndarray, np.ndarray]:
    """sum over points k of B_k Hll_k^-1 B_k^T (n, n) and of B_k Hll_k^-1 gl_k (n,), B_k^T the sum of the
    Hlp (3, n) of k's observations (Hlp: (3, c, N)); `L_inv` (K, 3, 3) from `inverse_cholesky(Hll)`,
    z_k = L_k^-1 gl_k.

    With Y_k = L_k^-1 B_k^T both are sums of Y_k^T Y_k and Y_k^T z_k. Per chunk of points, Y as a dense
    (3 * points, n) matrix and one symmetric product: a sum over the pairs of observations of each point
    would cost (track length)^2 blocks per point."""
    out, g = np.zeros((n, n)), np.zeros(n)
    L_obs = L_inv.reshape(-1, 9).T  # (9, K)
    for blk in blocks:
        k = slice(blk.first, blk.first + blk.count)
        L = np.take(L_obs, blk.points, axis=1).reshape(3, 3, -1)
        Y = np.einsum("ijn,jcn->nic", L, np.take(Hlp, blk.obs, axis=2))  # (N, 3, c): the scatter's order
        Y = np.bincount(blk.flat, weights=Y.ravel(), minlength=3 * blk.count * n).reshape(-1, n)
        out += Y.T @ Y
        g += Y.T @ z[k].ravel()
    return out, g


def refine_points(prob: _Problem, st: _State) -> np.ndarray:
    """One Gauss-Newton step per point with the poses held, kept only where it lowers that point's cost;
    returns the residuals (2, N) of the state it leaves."""
    o = prob.obs
    K = st.P.shape[0]
    r, _, Jl = prob.terms(st, jacobians=True, poses=False)
    _, w = prob.loss(np.sum(r * r, axis=0), prob.cfg.f_scale)
    Jl_w = Jl * w
    H = point_sums(o.point, np.einsum("ain,ajn->ijn", Jl_w, Jl), K)
    g = point_sums(o.point, np.einsum("ain,an->in", Jl_w, r), K)
    H += 1e-9 * np.einsum("kii->k", H)[:, None, None] * np.eye(3)[None] + 1e-12 * np.eye(3)[None]
    before = point_costs(prob, r, K)
    old_m, old_rho = st.m, st.rho
    prob.move_points(st, -np.linalg.solve(H, g[:, :, None])[:, :, 0])
    r_new = prob.terms(st, jacobians=False)
    worse = point_costs(prob, r_new, K) > before
    st.m[worse], st.rho[worse] = old_m[worse], old_rho[worse]
    back = worse[o.point]
    r_new[:, back] = r[:, back]  # the same numbers an evaluation at the restored points gives
    return r_new


def point_sums(point: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """Sum of per-observation arrays (..., N), observations last, over each point's observations:
    (n_points, ...). The same sums in the same order as `np.add.at` (bit for bit), in a fraction of its time."""
    width = int(np.prod(values.shape[:-1], dtype=int))
    flat = (point[None, :] * width + np.arange(width)[:, None]).ravel()
    out = np.bincount(flat, weights=values.reshape(-1), minlength=n_points * width)
    return out.reshape((n_points, *values.shape[:-1]))


def point_costs(prob: _Problem, r: np.ndarray, n_points: int) -> np.ndarray:
    """Robust cost of each point's observations from their residuals (2, N)."""
    rho, _ = prob.loss(np.sum(r * r, axis=0), prob.cfg.f_scale)
    return np.bincount(prob.obs.point, weights=rho, minlength=n_points)


def covariance(prob: _Problem, st: _State) -> np.ndarray:
    """Covariance (n_full, n_full) of the pose (and focal-scale) increments at `st`, from the Gauss-Newton
    information with the points eliminated and the priors included (zero for fixed unknowns)."""
    S, *_ = reduced_system(prob, st, 1e-9)  # a trace of damping keeps points at infinity invertible
    keep = prob.solve_idx
    cov = np.zeros((prob.n_full, prob.n_full))
    cov[np.ix_(keep, keep)] = np.linalg.pinv(S[np.ix_(keep, keep)])
    return cov
