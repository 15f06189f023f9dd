"""Camera models (contracts section 2): pinhole (+OpenCV distortion), Kannala-Brandt, ocam.

The maths of each model is written once, in torch (batched, differentiable, any device and float
dtype). The NumPy methods `project` / `unproject` run the same code on float64 CPU tensors.
Conventions: camera frame x right, y down, z forward; the centre of the top-left pixel is (0, 0);
an image covers [-0.5, W - 0.5] x [-0.5, H - 0.5]. Checking `rig.json` fields: `sgde_plugin.rigfile`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

_EPS = 1e-12
Device = torch.device | str | None  # where torch tensors are made (None: the default device)


def _param(value: np.ndarray, like: Tensor) -> Tensor:
    return torch.as_tensor(np.ascontiguousarray(value), dtype=like.dtype, device=like.device)


def _polyval(coeffs: Tensor, x: Tensor) -> Tensor:
    """sum_i coeffs[i] * x**i (ascending powers), Horner."""
    # in place unless autograd needs each step's result: a fisheye's maps spent most of their time allocating them
    in_place = not (torch.is_grad_enabled() and (coeffs.requires_grad or x.requires_grad))
    out = torch.zeros_like(x).add_(coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out.mul_(x).add_(c) if in_place else out * x + c
    return out


def _polyder(coeffs: Tensor) -> Tensor:
    n = coeffs.shape[0]
    if n == 1:
        return torch.zeros_like(coeffs)
    return coeffs[1:] * torch.arange(1, n, dtype=coeffs.dtype, device=coeffs.device)


def _tol(t: Tensor) -> float:
    """Residual below which an iterative solve counts as converged, by dtype."""
    return 1e3 * torch.finfo(t.dtype).eps


def _safe_norm2(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """sqrt(x^2 + y^2) with a finite gradient at 0, and the mask of where it is ~0."""
    r2 = x * x + y * y
    small = r2 < _EPS * _EPS
    r = torch.sqrt(torch.where(small, torch.ones_like(r2), r2))
    return torch.where(small, torch.zeros_like(r), r), small


def pixel_grid(width: int, height: int, dtype: torch.dtype = torch.float64, device: Device = None) -> Tensor:
    """Pixel centres (u, v) of an image, shape (H, W, 2)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def _float_list(values: np.ndarray | Sequence[float]) -> list:
    """An array as nested lists of Python floats (as `rig.json` holds it)."""
    return np.asarray(values, dtype=np.float64).tolist()


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera: image size plus a projection model."""

    width: int
    height: int

    model: ClassVar[str] = ""
    depth_is_range: ClassVar[bool] = False  # fisheye depth = range, pinhole depth = z

    # --- the maths, torch only -------------------------------------------------------------
    def project_torch(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame points (..., 3) -> pixels (..., 2) and validity (...)."""
        raise NotImplementedError

    def unproject_torch(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """Pixels (..., 2) -> unit rays (..., 3) in the camera frame and validity (...)."""
        raise NotImplementedError

    def in_image(self, uv: Tensor) -> Tensor:
        """True where a pixel position lies inside the image area."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def depth_torch(self, points: Tensor) -> Tensor:
        """Depth of camera-frame points in this camera's convention (z, or range for fisheyes)."""
        return torch.linalg.norm(points, dim=-1) if self.depth_is_range else points[..., 2]

    def points_from_depth_torch(self, uv: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
        """Pixels and depths (in this camera's convention) -> camera-frame points, validity."""
        rays, valid = self.unproject_torch(uv)
        if self.depth_is_range:
            scale = depth
        else:
            z = rays[..., 2]
            valid = valid & (z > 1e-9)
            scale = depth / torch.where(valid, z, torch.ones_like(z))
        return rays * scale[..., None], valid

    # --- NumPy faces of the same maths -----------------------------------------------------
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NumPy: camera-frame points (..., 3) -> pixels (..., 2), validity (...)."""
        uv, valid = self.project_torch(torch.as_tensor(np.asarray(points, dtype=np.float64)))
        return uv.numpy(), valid.numpy()

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NumPy: pixels (..., 2) -> unit rays (..., 3), validity (...)."""
        rays, valid = self.unproject_torch(torch.as_tensor(np.asarray(uv, dtype=np.float64)))
        return rays.numpy(), valid.numpy()

    def depth(self, points: np.ndarray) -> np.ndarray:
        """NumPy: depth of camera-frame points in this camera's convention."""
        return self.depth_torch(torch.as_tensor(np.asarray(points, dtype=np.float64))).numpy()

    def points_from_depth(self, uv: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """NumPy: pixels and depths -> camera-frame points, validity."""
        pts, valid = self.points_from_depth_torch(
            torch.as_tensor(np.asarray(uv, dtype=np.float64)), torch.as_tensor(np.asarray(depth, np.float64))
        )
        return pts.numpy(), valid.numpy()

    def ray_grid(self, dtype: torch.dtype = torch.float64, device: Device = None) -> tuple[Tensor, Tensor]:
        """Unit rays of every pixel centre, (H, W, 3), and their validity (H, W)."""
        return self.unproject_torch(pixel_grid(self.width, self.height, dtype, device))

    def valid_mask(self) -> np.ndarray:
        """Bool (H, W): pixels that see the scene (inside the image circle for fisheyes)."""
        return self.ray_grid()[1].numpy()

    # --- description ------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The `rig.json` fields of this model (without name and pose)."""
        return {"model": self.model, "width": self.width, "height": self.height, **self._parameters()}

    def _parameters(self) -> dict[str, Any]:
        """The model's own `rig.json` fields (after model, width and height)."""
        raise NotImplementedError

    def resized(self, width: int, height: int) -> CameraModel:
        """The same camera for the image resized to (width, height)."""
        raise NotImplementedError

    def with_focal_scale(self, scale: float) -> CameraModel:
        """The same camera with its focal length times `scale`: every pixel's offset from the principal point
        grows by `scale`, the principal point and the distortion profile stay."""
        raise NotImplementedError

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CameraModel) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(repr(self.to_dict()))


def _resize_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsic matrix for an image scaled by (sx, sy) with the pixel-centre convention."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, :] *= sx
    K2[1, :] *= sy
    K2[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
    K2[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
    K2[2] = [0.0, 0.0, 1.0]
    return K2


def _focal_scaled_K(K: np.ndarray, scale: float) -> np.ndarray:
    """K with fx, fy and the skew times `scale` (principal point kept)."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, :2] *= scale
    K2[1, 1] *= scale
    return K2


def _apply_K(K: Tensor, x: Tensor, y: Tensor) -> Tensor:
    return torch.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], dim=-1)


def _apply_K_inv(K: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return x, y


@dataclass(frozen=True, eq=False)
class Pinhole(CameraModel):
    """Pinhole with optional OpenCV distortion [k1, k2, p1, p2, k3]."""

    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    dist: np.ndarray | None = None

    model: ClassVar[str] = "pinhole"
    depth_is_range: ClassVar[bool] = False
    newton_iterations: ClassVar[int] = 12

    def _distort(self, x: Tensor, y: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        k1, k2, p1, p2, k3 = d
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def project_torch(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Perspective division, the OpenCV distortion when set, then K; points behind the camera are invalid."""
        K = _param(self.K, points)
        z = points[..., 2]
        front = z > 1e-9
        zs = torch.where(front, z, torch.ones_like(z))
        x, y = points[..., 0] / zs, points[..., 1] / zs
        if self.dist is not None:
            x, y = self._distort(x, y, _param(self.dist, points))
        uv = _apply_K(K, x, y)
        return uv, front & self.in_image(uv)

    def unproject_torch(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """K^-1, then the distortion inverted by Newton steps; rays at z = 1, normalised."""
        K = _param(self.K, uv)
        xd, yd = _apply_K_inv(K, uv)
        x, y = xd, yd
        if self.dist is not None:
            k1, k2, p1, p2, k3 = d = _param(self.dist, uv)
            for _ in range(self.newton_iterations):  # Newton on the 2-D distortion map
                fx, fy = self._distort(x, y, d)
                r2 = x * x + y * y
                radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                dR = k1 + r2 * (2 * k2 + 3 * k3 * r2)
                a = radial + 2 * x * x * dR + 2 * p1 * y + 6 * p2 * x
                b = 2 * x * y * dR + 2 * p1 * x + 2 * p2 * y
                c = 2 * x * y * dR + 2 * p1 * x + 2 * p2 * y
                e = radial + 2 * y * y * dR + 6 * p1 * y + 2 * p2 * x
                det = a * e - b * c
                det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
                rx, ry = fx - xd, fy - yd
                x = x - (e * rx - b * ry) / det
                y = y - (-c * rx + a * ry) / det
            fx, fy = self._distort(x, y, d)
            converged = ((fx - xd).abs() < _tol(x)) & ((fy - yd).abs() < _tol(x))
        else:
            converged = torch.ones_like(x, dtype=torch.bool)
        rays = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        rays = rays / torch.linalg.norm(rays, dim=-1, keepdim=True)
        return rays, converged & self.in_image(uv)

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view through the principal point, degrees (the fisheyes' `fov_deg` is a cone angle)."""
        rays, _ = self.unproject(np.array([[-0.5, self.K[1, 2]], [self.width - 0.5, self.K[1, 2]]]))
        return float(np.degrees(np.arctan2(-rays[0, 0], rays[0, 2]) + np.arctan2(rays[1, 0], rays[1, 2])))

    def _parameters(self) -> dict[str, Any]:
        return {"K": _float_list(self.K), "dist": None if self.dist is None else _float_list(self.dist)}

    def resized(self, width: int, height: int) -> Pinhole:
        """K scaled to the new size (pixel centres kept); the distortion is unchanged."""
        return Pinhole(width, height, _resize_K(self.K, width / self.width, height / self.height), self.dist)

    def with_focal_scale(self, scale: float) -> Pinhole:
        """fx, fy times `scale`; principal point and distortion unchanged."""
        return Pinhole(self.width, self.height, _focal_scaled_K(self.K, scale), self.dist)


@dataclass(frozen=True, eq=False)
class KannalaBrandt(CameraModel):
    """Kannala-Brandt fisheye: r = f * theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8), up to fov_deg."""

    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    dist: np.ndarray = field(default_factory=lambda: np.zeros(4))
    fov_deg: float = 180.0

    model: ClassVar[str] = "kannala_brandt"
    depth_is_range: ClassVar[bool] = True
    newton_iterations: ClassVar[int] = 12

    def _theta_d(self, theta: Tensor, k: Tensor) -> Tensor:
        t2 = theta * theta
        return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))

    def project_torch(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """theta -> theta_d by the polynomial, then K; valid inside fov_deg and the image."""
        K, k = _param(self.K, points), _param(self.dist, points)
        r, on_axis = _safe_norm2(points[..., 0], points[..., 1])
        theta = torch.atan2(r, points[..., 2])
        theta_d = self._theta_d(theta, k)
        # on the axis theta_d / r -> 1 / z
        z = points[..., 2]
        scale = torch.where(on_axis, 1 / torch.where(z.abs() > _EPS, z, torch.ones_like(z)),
                            theta_d / torch.where(on_axis, torch.ones_like(r), r))
        uv = _apply_K(K, points[..., 0] * scale, points[..., 1] * scale)
        norm = torch.linalg.norm(points, dim=-1)
        valid = (theta <= math.radians(self.fov_deg) / 2 + 1e-9) & (norm > 1e-9) & self.in_image(uv)
        return uv, valid

    def unproject_torch(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """K^-1, then theta from theta_d by Newton steps; valid inside fov_deg and the image."""
        K, k = _param(self.K, uv), _param(self.dist, uv)
        xd, yd = _apply_K_inv(K, uv)
        theta_d, on_axis = _safe_norm2(xd, yd)
        theta = theta_d.clone()
        for _ in range(self.newton_iterations):
            t2 = theta * theta
            f = self._theta_d(theta, k) - theta_d
            df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
            theta = (theta - f / torch.where(df.abs() < 1e-12, torch.ones_like(df), df)).clamp(0, math.pi)
        converged = (self._theta_d(theta, k) - theta_d).abs() < _tol(theta)
        s = torch.where(on_axis, torch.ones_like(theta), torch.sin(theta) / torch.where(on_axis, 1, theta_d))
        rays = torch.stack([xd * s, yd * s, torch.cos(theta)], dim=-1)
        valid = converged & (theta <= math.radians(self.fov_deg) / 2 + 1e-9) & self.in_image(uv)
        return rays, valid

    def _parameters(self) -> dict[str, Any]:
        return {"K": _float_list(self.K), "dist": _float_list(self.dist), "fov_deg": float(self.fov_deg)}

    def resized(self, width: int, height: int) -> KannalaBrandt:
        """K scaled to the new size (pixel centres kept); the polynomial is unchanged."""
        K = _resize_K(self.K, width / self.width, height / self.height)
        return KannalaBrandt(width, height, K, self.dist, self.fov_deg)

    def with_focal_scale(self, scale: float) -> KannalaBrandt:
        """fx, fy times `scale`; principal point and polynomial unchanged."""
        return KannalaBrandt(self.width, self.height, _focal_scaled_K(self.K, scale), self.dist, self.fov_deg)


@dataclass(frozen=True, eq=False)
class Ocam(CameraModel):
    """Scaramuzza's omnidirectional model as in OCamCalib and the OmniMVS / Synthetic Urban data.

    `poly` maps the sensor radius rho to the OCam z (cam2world, ascending powers), `inv_poly` maps
    theta = atan(z / rho) to rho (world2cam). `center` is (row, col) and `affine` is (c, d, e):
    row = c * xs + d * ys + row_c, col = e * xs + ys + col_c. The OCam frame is x down (rows),
    y right (columns), z backward; we convert to the OpenCV camera frame. Projection starts from
    `inv_poly` and refines on `poly` with Newton steps, so project and unproject are exact inverses.
    """

    poly: np.ndarray = field(default_factory=lambda: np.array([-1.0]))
    inv_poly: np.ndarray = field(default_factory=lambda: np.array([1.0]))
    center: np.ndarray = field(default_factory=lambda: np.zeros(2))
    affine: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    fov_deg: float = 180.0

    model: ClassVar[str] = "ocam"
    depth_is_range: ClassVar[bool] = True
    newton_iterations: ClassVar[int] = 6

    def project_torch(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """The ray's elevation to a sensor radius (inverse polynomial, refined on poly), then the affine map."""
        poly, inv_poly = _param(self.poly, points), _param(self.inv_poly, points)
        dpoly = _polyder(poly)
        c, d, e = _param(self.affine, points)
        row_c, col_c = _param(self.center, points)
        xo, yo, zo = points[..., 1], points[..., 0], -points[..., 2]
        norm, on_axis = _safe_norm2(xo, yo)
        full = torch.sqrt(norm * norm + zo * zo).clamp_min(_EPS)
        n, z = norm / full, zo / full  # unit (radial, axial) direction
        rho = _polyval(inv_poly, torch.atan2(z, n)).detach().clamp_min(0)
        for _ in range(self.newton_iterations):  # solve poly(rho) * n - z * rho = 0
            g = _polyval(poly, rho) * n - z * rho
            dg = _polyval(dpoly, rho) * n - z
            step = g / torch.where(dg.abs() < 1e-12, torch.ones_like(dg), dg)
            rho = (rho - step).clamp_min(0)
            # steps at rounding level everywhere: the next ones would only move rho by its last bits
            if bool((step.abs() <= 16 * torch.finfo(rho.dtype).eps * (1 + rho)).all()):
                break
        ns = torch.where(on_axis, torch.ones_like(norm), norm)
        xs = torch.where(on_axis, torch.zeros_like(rho), rho * xo / ns)
        ys = torch.where(on_axis, torch.zeros_like(rho), rho * yo / ns)
        row = c * xs + d * ys + row_c
        col = e * xs + ys + col_c
        uv = torch.stack([col, row], dim=-1)
        angle = torch.atan2(norm, points[..., 2])
        converged = (_polyval(poly, rho) * n - z * rho).abs() < _tol(rho) * (1 + rho)
        valid = converged & (angle <= math.radians(self.fov_deg) / 2 + 1e-9) & (full > 1e-9) & self.in_image(uv)
        return uv, valid

    def unproject_torch(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """The inverse affine map, then poly(rho) gives the ray; valid inside fov_deg and the image."""
        poly = _param(self.poly, uv)
        c, d, e = _param(self.affine, uv)
        row_c, col_c = _param(self.center, uv)
        dr, dc = uv[..., 1] - row_c, uv[..., 0] - col_c
        inv_det = 1 / (c - d * e)
        xs = inv_det * (dr - d * dc)
        ys = inv_det * (-e * dr + c * dc)
        rho, _ = _safe_norm2(xs, ys)
        zs = _polyval(poly, rho)
        ray = torch.stack([ys, xs, -zs], dim=-1)  # OCam (x down, y right, z back) -> OpenCV
        ray = ray / torch.linalg.norm(ray, dim=-1, keepdim=True)
        angle = torch.acos(ray[..., 2].clamp(-1, 1))
        valid = (angle <= math.radians(self.fov_deg) / 2 + 1e-9) & self.in_image(uv)
        return ray, valid

    def _parameters(self) -> dict[str, Any]:
        arrays = {name: _float_list(getattr(self, name)) for name in ("poly", "inv_poly", "center", "affine")}
        return {**arrays, "fov_deg": float(self.fov_deg)}

    def resized(self, width: int, height: int) -> Ocam:
        """Polynomials and centre scaled for a uniform resize (ValueError otherwise)."""
        s = width / self.width
        if abs(height / self.height - s) > 1e-3 * s:
            raise ValueError("an ocam camera can only be resized uniformly")
        powers = np.arange(len(self.poly))
        return Ocam(
            width, height,
            poly=np.asarray(self.poly) * s ** (1.0 - powers),
            inv_poly=np.asarray(self.inv_poly) * s,
            center=s * (np.asarray(self.center) + 0.5) - 0.5,
            affine=np.asarray(self.affine),
            fov_deg=self.fov_deg,
        )

    def with_focal_scale(self, scale: float) -> Ocam:
        """Sensor radii times `scale` for the same rays: inv_poly times s, poly(rho) -> s poly(rho / s)."""
        powers = np.arange(len(self.poly))
        return Ocam(self.width, self.height, poly=np.asarray(self.poly) * scale ** (1.0 - powers),
                    inv_poly=np.asarray(self.inv_poly) * scale, center=np.asarray(self.center),
                    affine=np.asarray(self.affine), fov_deg=self.fov_deg)


MODELS: dict[str, type[CameraModel]] = {m.model: m for m in (Pinhole, KannalaBrandt, Ocam)}


@dataclass(frozen=True, eq=False)
class Camera:
    """A named camera of a rig: intrinsics model plus sensor_to_ego (4x4, camera -> ego)."""

    name: str
    intrinsics: CameraModel
    sensor_to_ego: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self.intrinsics.width

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self.intrinsics.height

    @property
    def model(self) -> str:
        """Model name as in rig.json."""
        return self.intrinsics.model

    def with_pose(self, sensor_to_ego: np.ndarray) -> Camera:
        """The same camera with another extrinsic."""
        return Camera(self.name, self.intrinsics, np.asarray(sensor_to_ego, dtype=np.float64))

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for a resized image."""
        return Camera(self.name, self.intrinsics.resized(width, height), self.sensor_to_ego)

    def to_dict(self) -> dict[str, Any]:
        """The camera's `rig.json` entry."""
        d = {"name": self.name, **self.intrinsics.to_dict()}
        d["sensor_to_ego"] = np.asarray(self.sensor_to_ego, dtype=np.float64).tolist()
        return d

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Camera) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(self.name)
