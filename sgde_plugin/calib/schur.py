"""The solver half of the loop-constrained adjustment (`ba.py` holds the model): damped Gauss-Newton
(Levenberg-Marquardt) steps on the normal equations with the points eliminated per point (Schur complement,
the standard bundle-adjustment reduction), a safeguarded Gauss-Newton step per point with the poses held,
and the covariance of the pose (and focal-scale) unknowns. Each function takes the problem (`ba._Problem`:
residuals, Jacobians, priors, unknown layout) and a state.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .ba import _Problem, _State


def lm_step(prob: _Problem, st: _State, lam: float) -> tuple[_State, float]:
    """One damped Gauss-Newton step (Schur complement on the points); returns the trial state."""
    o, n = prob.obs, prob.n_full
    K = st.P.shape[0]
    S, rhs, Hpl, Hll_inv, gl = reduced_system(prob, st, lam)
    keep = prob.solve_idx
    dp = np.zeros(n)
    dp[keep] = np.linalg.solve(S[np.ix_(keep, keep)], rhs[keep])
    back = per_point_sum(o.point, (np.swapaxes(Hpl, 1, 2) @ dp[prob.pose_idx][:, :, None])[:, :, 0], K)
    dl = -(Hll_inv @ (gl + back)[:, :, None])[:, :, 0]
    trial = prob.apply(st, dp, dl)
    for _ in range(prob.cfg.point_iterations):
        refine_points(prob, trial)
    return trial, float(np.abs(dp[keep]).max(initial=0.0))


def reduced_system(prob: _Problem, st: _State, lam: float):
    """The damped normal equations of the poses with the points eliminated (Schur complement): S, the
    right-hand side, and what the point back-substitution needs (Hpl, Hll^-1, gl)."""
    o, n = prob.obs, prob.n_full
    K = st.P.shape[0]
    r, Jp, Jl = prob.obs_terms(st, jacobians=True)
    _, w = prob.loss(np.sum(r * r, axis=1), prob.cfg.f_scale)
    Jl_wT = np.swapaxes(Jl * w[:, None, None], 1, 2)
    Jp_wT = np.swapaxes(Jp * w[:, None, None], 1, 2)
    Hll = per_point_sum(o.point, Jl_wT @ Jl, K)
    gl = per_point_sum(o.point, (Jl_wT @ r[:, :, None])[:, :, 0], K)
    Hpp = np.bincount(prob.flat_pp, weights=(Jp_wT @ Jp).ravel(), minlength=n * n).reshape(n, n).astype(float)
    gp = np.bincount(prob.pose_idx.ravel(), weights=(Jp_wT @ r[:, :, None]).ravel(), minlength=n).astype(float)
    for x, blocks in prob.prior_terms(st):
        for ia, Ja in blocks:
            gp[ia : ia + Ja.shape[1]] += Ja.T @ x
            for ib, Jb in blocks:
                Hpp[ia : ia + Ja.shape[1], ib : ib + Jb.shape[1]] += Ja.T @ Jb
    Hll_d = Hll + lam * np.einsum("kii->ki", Hll)[:, :, None] * np.eye(3)[None] + 1e-12 * np.eye(3)[None]
    Hpp_d = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-12 * np.eye(n)
    Hll_inv = np.linalg.inv(Hll_d)
    Hpl = Jp_wT @ Jl  # (N, 12, 3)
    S = Hpp_d - _point_terms(prob.pose_idx, o.point, Hpl, Hpl @ Hll_inv[o.point], n, K)
    v = (Hll_inv @ gl[:, :, None])[:, :, 0]
    rhs = -gp + np.bincount(prob.pose_idx.ravel(), weights=(Hpl @ v[o.point][:, :, None]).ravel(), minlength=n)
    return S, rhs, Hpl, Hll_inv, gl


def _point_terms(pose_idx: np.ndarray, point: np.ndarray, Hpl: np.ndarray, HplHinv: np.ndarray, n: int, K: int,
                 chunk: int = 8192) -> np.ndarray:
    """sum over points k of B_k Hll_k^-1 B_k^T (n, n), B_k the sum of the Hpl of k's observations (n, 3).

    Per chunk of points, B and B Hll^-1 as dense (n, 3 * chunk) matrices and one product: a sum over the pairs
    of observations of each point would cost (track length)^2 blocks per point."""
    out = np.zeros((n, n))
    for k0 in range(0, K, chunk):
        sel = np.flatnonzero((point >= k0) & (point < k0 + chunk))
        width = 3 * min(chunk, K - k0)
        flat = (pose_idx[sel, :, None] * width + 3 * (point[sel] - k0)[:, None, None] + np.arange(3)).ravel()
        B = np.bincount(flat, weights=Hpl[sel].ravel(), minlength=n * width).reshape(n, width)
        BH = np.bincount(flat, weights=HplHinv[sel].ravel(), minlength=n * width).reshape(n, width)
        out += BH @ B.T
    return out


def refine_points(prob: _Problem, st: _State) -> None:
    """One Gauss-Newton step per point with the poses held, kept only where it lowers that point's cost."""
    o = prob.obs
    K = st.P.shape[0]
    r, _, Jl = prob.obs_terms(st, jacobians=True, poses=False)
    _, w = prob.loss(np.sum(r * r, axis=1), prob.cfg.f_scale)
    Jl_wT = np.swapaxes(Jl * w[:, None, None], 1, 2)
    H = per_point_sum(o.point, Jl_wT @ Jl, K)
    g = per_point_sum(o.point, (Jl_wT @ r[:, :, None])[:, :, 0], K)
    H += 1e-9 * np.einsum("kii->k", H)[:, None, None] * np.eye(3)[None] + 1e-12 * np.eye(3)[None]
    before = point_costs(prob, r, K)
    old_m, old_rho = st.m, st.rho
    prob.move_points(st, -np.linalg.solve(H, g[:, :, None])[:, :, 0])
    worse = point_costs(prob, prob.obs_terms(st, jacobians=False), K) > before
    st.m[worse], st.rho[worse] = old_m[worse], old_rho[worse]


def per_point_sum(point: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """Sum of per-observation arrays (N, ...) over each point's observations: (n_points, ...). The same sums in
    the same order as `np.add.at` (bit for bit), in a fraction of its time."""
    width = int(np.prod(values.shape[1:], dtype=int))
    flat = (point[:, None] * width + np.arange(width)).ravel()
    out = np.bincount(flat, weights=values.reshape(-1), minlength=n_points * width)
    return out.reshape((n_points, *values.shape[1:]))


def point_costs(prob: _Problem, r: np.ndarray, n_points: int) -> np.ndarray:
    """Robust cost of each point's observations."""
    rho, _ = prob.loss(np.sum(r * r, axis=1), prob.cfg.f_scale)
    return np.bincount(prob.obs.point, weights=rho, minlength=n_points)


def covariance(prob: _Problem, st: _State) -> np.ndarray:
    """Covariance (n_full, n_full) of the pose (and focal-scale) increments at `st`, from the Gauss-Newton
    information with the points eliminated and the priors included (zero for fixed unknowns)."""
    S, *_ = reduced_system(prob, st, 1e-9)  # a trace of damping keeps points at infinity invertible
    keep = prob.solve_idx
    cov = np.zeros((prob.n_full, prob.n_full))
    cov[np.ix_(keep, keep)] = np.linalg.pinv(S[np.ix_(keep, keep)])
    return cov
