"""A camera's focal-length scale inside the adjustment: how it moves the rays the rig's intrinsics give.

A camera whose focal length is s times the rig's images a direction at s times the pixel offset from the
principal point that the rig predicts (`CameraModel.with_focal_scale`). The adjustment's observed rays
come from the rig's intrinsics, so it maps each predicted direction (true geometry) to the ray that the
rig's intrinsics assign to the pixel where a camera with focal scale s images it: the azimuth about the
optical axis stays, the angle theta from the axis becomes theta_n with rho(theta_n) = s rho(theta), rho
the model's radial profile (image radius over focal length). A pinhole without distortion has
rho = tan(theta), i.e. exactly v = diag(s, s, 1) q on an unnormalised direction q. Fisheye models
(Kannala-Brandt, ocam) and pinholes with radial distortion use a dense table of rho(theta) from the model's
own projection, interpolated linearly (8,193 samples: well under 1e-6 px). A pinhole with tangential
distortion is not radially symmetric: it gets no focal unknown (`focal_map` returns None).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import CameraModel, Pinhole

TABLE_SAMPLES = 8193
_SMALL = 1e-9


@dataclass(frozen=True)
class FocalMap:
    """Ray map of one camera for a focal scale s; `theta`/`rho` tabulate its radial profile (None: pinhole)."""

    theta: np.ndarray | None = None
    rho: np.ndarray | None = None

    def apply(self, q: np.ndarray, s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Directions q (N, 3) -> mapped directions v (N, 3), dv/dq (N, 3, 3) and dv/ds (N, 3); the scale `s` is
        one number or one per direction (N,)."""
        if self.theta is None:
            d = np.ones((q.shape[0], 3))
            d[:, :2] = np.reshape(s, (-1, 1))
            J = np.zeros((q.shape[0], 3, 3))
            J[:, [0, 1, 2], [0, 1, 2]] = d
            return q * d, J, np.concatenate([q[:, :2], np.zeros((q.shape[0], 1))], axis=1)
        return _radial_apply(self.theta, self.rho, q, s)


def _interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear interpolation with linear extrapolation past both ends: values and slopes."""
    i = np.clip(np.searchsorted(xp, x) - 1, 0, xp.size - 2)
    slope = (fp[i + 1] - fp[i]) / (xp[i + 1] - xp[i])
    return fp[i] + slope * (x - xp[i]), slope


def _radial_apply(T: np.ndarray, R: np.ndarray, q: np.ndarray, s: float):
    """`FocalMap.apply` for a tabulated profile rho(theta) (see the module docstring)."""
    nq = np.maximum(np.linalg.norm(q, axis=1), 1e-12)
    u = q / nq[:, None]
    rxy = np.hypot(u[:, 0], u[:, 1])
    theta = np.arctan2(rxy, u[:, 2])
    r, slope_a = _interp(theta, T, R)
    theta_n, inv_slope_b = _interp(s * r, R, T)
    h_theta = s * slope_a * inv_slope_b  # d theta_n / d theta
    h_s = r * inv_slope_b  # d theta_n / d s
    sn, cn = np.sin(theta_n), np.cos(theta_n)
    small = rxy < _SMALL
    rc = np.where(small, 1.0, rxy)
    k = np.where(small, h_theta, sn / rc)
    e = np.where(small[:, None], 0.0, u[:, :2] / rc[:, None])
    v = np.stack([k * u[:, 0], k * u[:, 1], cn], axis=1)
    n = q.shape[0]
    d_theta = np.concatenate([u[:, 2:3] * e, -rxy[:, None]], axis=1)  # (N, 3), on the unit sphere
    d_rxy = np.concatenate([e, np.zeros((n, 1))], axis=1)
    d_theta_n = h_theta[:, None] * d_theta
    d_k = np.where(small[:, None], 0.0, (cn[:, None] * d_theta_n - k[:, None] * d_rxy) / rc[:, None])
    Jn = np.zeros((n, 3, 3))
    Jn[:, :2, :] = u[:, :2, None] * d_k[:, None, :]
    Jn[:, 0, 0] += k
    Jn[:, 1, 1] += k
    Jn[:, 2, :] = -sn[:, None] * d_theta_n
    P = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / nq[:, None, None]  # du/dq
    dk_ds = np.where(small, 0.0, cn * h_s / rc)
    dv_ds = np.stack([dk_ds * u[:, 0], dk_ds * u[:, 1], -sn * h_s], axis=1)
    return v, Jn @ P, dv_ds


def _max_angle(model: CameraModel) -> float:
    """Largest angle from the optical axis the table must cover (radians)."""
    fov = getattr(model, "fov_deg", None)
    if model.depth_is_range and fov is not None:
        return float(np.radians(fov) / 2)
    corners = np.array([[-0.5, -0.5], [model.width - 0.5, -0.5], [-0.5, model.height - 0.5],
                        [model.width - 0.5, model.height - 0.5]])
    rays, _ = model.unproject(corners)
    return float(min(np.arccos(np.clip(rays[:, 2], -1.0, 1.0)).max() * 1.1, np.radians(89.0)))


def focal_map(model: CameraModel) -> FocalMap | None:
    """The focal-scale ray map of a camera model, or None when the model is not radially symmetric."""
    if isinstance(model, Pinhole):
        dist = None if model.dist is None else np.asarray(model.dist, dtype=np.float64)
        if dist is None or not np.any(dist):
            return FocalMap()
        if np.any(dist[2:4]):
            return None  # tangential distortion
    theta = np.linspace(0.0, _max_angle(model), TABLE_SAMPLES)
    dirs = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    with torch.no_grad():
        uv, _ = model.project_torch(torch.as_tensor(dirs))
    rho = uv[:, 0].numpy() - float(uv[0, 0])
    rho = rho / max(float(np.abs(rho).max()), 1e-12)
    grows = np.diff(rho) > 0
    n = int(np.argmin(grows)) + 1 if not grows.all() else theta.size
    if n < 16:
        return None
    return FocalMap(theta[:n].copy(), rho[:n].copy())
