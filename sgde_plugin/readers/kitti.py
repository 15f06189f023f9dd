"""KITTI odometry / SemanticKITTI / SSCBench-KITTI calibration: ``calib.txt``, ``poses.txt`` -> cameras.

Facts (KITTI odometry devkit; VoxFormer's ``preprocess/utils/kitti_util.py`` and its datasets):

- ``calib.txt`` lines ``P0:`` .. ``P3:`` (3x4 row-major projection matrices of the rectified cameras,
  pixel ~ P @ X for X in the rectified camera-0 frame) and ``Tr:`` (3x4, LiDAR -> camera 0). The odometry
  set is already rectified: there is no ``R0_rect`` (VoxFormer uses identity).
- ``P = K [I | t]``: camera i sits at -t in the camera-0 frame with camera-0's axes, so a point
  X0 has X_i = X0 + t in camera i, and its depth there is z0 + t_z (= the third row of P @ X0).
  For P2 on sequence 00 |t| = 6.0 cm (t_z = 3.8 mm).
- ``poses.txt``: one 3x4 row-major camera-0 pose per frame in the first frame's camera-0 frame;
  VoxFormer turns them into LiDAR poses as inv(Tr) @ pose @ Tr.

The offset is folded into ``sensor_to_ego`` (ego = the LiDAR frame), which is exact: a pinhole with
K and pose inv(Tr) @ [I | -t] projects every LiDAR point to P @ Tr @ X and unprojects pixel + depth
back to it (``tests/test_readers_kitti.py``). So no camera model of the project needs an offset.

``convention="voxformer"`` reproduces VoxFormer's stage-1 ``depth2lidar.py`` instead, which places a
pixel with depth d at ((u - c_u) d / f_u - P[0,3] / f_u, (v - c_v) d / f_v - P[1,3] / f_v, d) in the
camera-0 frame: it ignores P[2,3], i.e. t' = (P[0,3] / f_u, P[1,3] / f_v, 0), about 3 mm off t on
x and 4 mm on z for P2. Use it to reproduce VoxFormer's ``.pseudo`` voxels bit for bit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera, Pinhole
from ..errors import InputError
from ..geometry import invert_transform, make_transform
from ..rigfile import MAX_WORLD_M

CONVENTIONS = ("exact", "voxformer")
KITTI_LIDAR_HEIGHT_M = 1.73  # Velodyne above the road on the KITTI car


def _check_finite(values: np.ndarray, path: Path, where: str) -> None:
    """InputError for NaN, infinity or a value beyond MAX_WORLD_M (no calibration or pose entry is that large)."""
    if not np.all(np.isfinite(values)):
        raise InputError(path, where, "contains NaN or infinity")
    if np.abs(values).max(initial=0.0) > MAX_WORLD_M:
        raise InputError(path, where, f"has a value beyond {MAX_WORLD_M:g}")


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> {"P0".."P3": 3x4, "Tr": 4x4 LiDAR -> camera 0}; InputError names a bad line."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise InputError(path, None, f"cannot read: {exc.strerror or exc}") from None
    out: dict[str, np.ndarray] = {}
    for line in lines:
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep:
            raise InputError(path, key, "line has no 'KEY:' prefix")
        try:
            values = np.array([float(v) for v in value.split()])
        except ValueError:
            raise InputError(path, key, "values are not numbers") from None
        _check_finite(values, path, key)
        if key in ("P0", "P1", "P2", "P3", "Tr"):
            if values.size != 12:
                raise InputError(path, key, f"has {values.size} values, expected 12 (3x4 row-major)")
            out[key] = values.reshape(3, 4)
    for key in ("P2", "Tr"):
        if key not in out:
            raise InputError(path, key, "missing")
    out["Tr"] = np.vstack([out["Tr"], [0.0, 0.0, 0.0, 1.0]])
    return out


def projection_offset(P: np.ndarray, convention: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    """Split a rectified 3x4 projection ``P = K [I | t]`` into K (3x3) and t (3,), camera-0 frame, metres."""
    P = np.asarray(P, dtype=np.float64)
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    K = P[:, :3].copy()
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"P[:, :3] is not a rectified pinhole K (upper triangular, K[2] = (0, 0, 1)): {K.tolist()}")
    if convention == "exact":
        t = np.linalg.solve(K, P[:, 3])
    else:
        t = np.array([P[0, 3] / K[0, 0], P[1, 3] / K[1, 1], 0.0])
    return K, t


def kitti_camera(P: np.ndarray, Tr: np.ndarray, width: int, height: int, name: str = "image_2",
                 convention: str = "exact") -> Camera:
    """A KITTI rectified camera as a pinhole with its offset folded into ``sensor_to_ego`` (ego = LiDAR frame).

    ``P``: the camera's 3x4 projection (P2 for ``image_2``); ``Tr``: 3x4 or 4x4 LiDAR -> camera 0.
    """
    K, t = projection_offset(P, convention)
    Tr = np.asarray(Tr, dtype=np.float64)
    if Tr.shape == (3, 4):
        Tr = np.vstack([Tr, [0.0, 0.0, 0.0, 1.0]])
    cam_to_cam0 = make_transform(np.eye(3), -t)
    return Camera(name, Pinhole(int(width), int(height), K, None), invert_transform(Tr) @ cam_to_cam0)


def read_kitti_poses(path: str | Path, Tr: np.ndarray) -> np.ndarray:
    """``poses.txt`` -> LiDAR poses [F, 4, 4] (LiDAR of frame f -> LiDAR of frame 0): inv(Tr) @ pose @ Tr."""
    path = Path(path)
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    except OSError as exc:
        raise InputError(path, None, f"cannot read: {exc.strerror or exc}") from None
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for i, row in enumerate(rows):
        if len(row) != 12:
            raise InputError(path, f"line {i + 1}", f"has {len(row)} values, expected 12 (3x4 row-major)")
        try:
            poses[i, :3] = np.array([float(v) for v in row]).reshape(3, 4)
        except ValueError:
            raise InputError(path, f"line {i + 1}", "values are not numbers") from None
        _check_finite(poses[i], path, f"line {i + 1}")
    Tr = np.asarray(Tr, dtype=np.float64)
    return invert_transform(Tr) @ poses @ Tr
