"""`rig.json` field validation: numeric matrices and vectors, image sizes, camera intrinsics, 4x4 poses.

Every check raises `InputError` naming the key (`cameras[front].K`) and the problem; the camera maths
lives in `sgde_plugin.cameras`, the rig document itself in `sgde_plugin.rig`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import MODELS, CameraModel, KannalaBrandt, Ocam, Pinhole
from .errors import InputError
from .geometry import ORTHONORMAL_TOL, rotation_error, vector_norm

MAX_MOUNT_M = 1e3  # a camera mounted farther than this from the ego origin is a unit or typing error
MAX_WORLD_M = 1e8  # ego positions beyond this are not on Earth (UTM-sized coordinates are ~1e7 m)


def matrix_field(entry: dict, key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    """The finite float64 array of exactly `shape` at `entry[key]`."""
    if key not in entry or entry[key] is None:
        raise InputError(None, f"{where}.{key}", "missing")
    try:
        arr = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(None, f"{where}.{key}", "not a numeric array") from None
    if arr.shape != shape:
        raise InputError(None, f"{where}.{key}", f"has shape {list(arr.shape)}, expected {list(shape)}")
    if not np.all(np.isfinite(arr)):
        raise InputError(None, f"{where}.{key}", "contains NaN or infinity")
    return arr


def vector_field(entry: dict, key: str, where: str, lengths: tuple[int, ...] | None = None) -> np.ndarray:
    """The non-empty finite float64 vector at `entry[key]`, of one of `lengths` values when given."""
    value = entry.get(key)
    if value is None:
        raise InputError(None, f"{where}.{key}", "missing")
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(None, f"{where}.{key}", "not a numeric list") from None
    if lengths is not None and arr.shape[0] not in lengths:
        expected = " or ".join(map(str, lengths))
        raise InputError(None, f"{where}.{key}", f"has {arr.shape[0]} values, expected {expected}")
    if arr.shape[0] == 0 or not np.all(np.isfinite(arr)):
        raise InputError(None, f"{where}.{key}", "empty or not finite")
    return arr


MAX_PIXELS = 1e6  # no focal length or principal point of a real camera is this large
MAX_IMAGE_SIDE = 65535  # the largest PNG/JPEG side OpenCV writes


def _intrinsic_matrix(entry: dict, where: str) -> np.ndarray:
    if "K" not in entry or entry["K"] is None:
        raise InputError(None, f"{where}.K", "missing")
    try:
        K = np.asarray(entry["K"], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(None, f"{where}.K", "not a numeric matrix") from None
    if K.shape != (3, 3):
        raise InputError(None, f"{where}.K", f"is not a square 3x3 matrix (shape {list(K.shape)})")
    if not np.all(np.isfinite(K)):
        raise InputError(None, f"{where}.K", "contains NaN or infinity")
    if np.abs(K).max() > MAX_PIXELS:
        raise InputError(None, f"{where}.K", f"has an absurd value ({np.abs(K).max():.3g} > {MAX_PIXELS:g} pixels)")
    if abs(np.linalg.det(K)) < 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(None, f"{where}.K", "is singular (focal lengths must be positive)")
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise InputError(None, f"{where}.K", "last row must be [0, 0, 1] and K[1][0] must be 0")
    return K


def _size(entry: dict, key: str, where: str) -> int:
    value = entry.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
        raise InputError(None, f"{where}.{key}", "missing or not a positive integer")
    if value > MAX_IMAGE_SIDE:
        raise InputError(None, f"{where}.{key}", f"{value} is absurd (more than {MAX_IMAGE_SIDE} pixels)")
    return value


def _fov(entry: dict, where: str) -> float:
    value = entry.get("fov_deg")
    if not isinstance(value, (int, float)) or not (0 < value < 360):
        raise InputError(None, f"{where}.fov_deg", "missing or not in (0, 360) degrees")
    return float(value)


def intrinsics_from_dict(entry: dict, where: str = "camera") -> CameraModel:
    """Build and check a camera model from its `rig.json` fields; InputError names the bad key."""
    model = entry.get("model")
    if not isinstance(model, str) or model not in MODELS:
        raise InputError(None, f"{where}.model", f"unknown camera model {model!r} (expected {', '.join(MODELS)})")
    w, h = _size(entry, "width", where), _size(entry, "height", where)
    if model == "pinhole":
        dist = entry.get("dist")
        d = None
        if dist is not None:
            d = vector_field(entry, "dist", where, (4, 5))
            d = np.pad(d, (0, 5 - d.shape[0]))
        return Pinhole(w, h, _intrinsic_matrix(entry, where), d)
    if model == "kannala_brandt":
        d = np.zeros(4) if entry.get("dist") is None else vector_field(entry, "dist", where, (4,))
        return KannalaBrandt(w, h, _intrinsic_matrix(entry, where), d, _fov(entry, where))
    affine = vector_field(entry, "affine", where, (3,))
    if abs(affine[0] - affine[1] * affine[2]) < 1e-9:
        raise InputError(None, f"{where}.affine", "is singular (c - d * e = 0)")
    return Ocam(
        w, h,
        poly=vector_field(entry, "poly", where),
        inv_poly=vector_field(entry, "inv_poly", where),
        center=vector_field(entry, "center", where, (2,)),
        affine=affine,
        fov_deg=_fov(entry, where),
    )


def transform_field(entry: dict, key: str, where: str, required: bool = True,
                    max_m: float = MAX_WORLD_M) -> np.ndarray:
    """A checked 4x4 rigid transform at `entry[key]` (identity when absent and not required)."""
    if key not in entry and not required:
        return np.eye(4)
    T = matrix_field(entry, key, (4, 4), where)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(None, f"{where}.{key}", "last row must be [0, 0, 0, 1]")
    det = float(np.linalg.det(T[:3, :3]))
    if det < 0:  # rotation_error is inf for it: say what it is
        raise InputError(None, f"{where}.{key}", f"rotation has determinant {det:.3g} (a reflection)")
    err = rotation_error(T[:3, :3])
    if err > ORTHONORMAL_TOL:
        raise InputError(None, f"{where}.{key}", f"rotation is not orthonormal (error {err:.2g} > 1e-6)")
    check_translation(T[:3, 3], None, f"{where}.{key}", max_m)
    return T


def check_translation(t: np.ndarray, file: Path | str | None, where: str, max_m: float) -> None:
    """InputError naming `where` when the translation `t` is farther than `max_m` metres."""
    norm = vector_norm(t)
    if norm > max_m:
        raise InputError(file, where, f"translation of {norm:.3g} m is absurd (more than {max_m:g} m)")


__all__ = ["MAX_IMAGE_SIDE", "MAX_MOUNT_M", "MAX_PIXELS", "MAX_WORLD_M", "check_translation", "intrinsics_from_dict",
           "matrix_field", "transform_field", "vector_field"]
