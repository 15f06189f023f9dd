"""Overlap rectification of one adjacent camera pair, built from the camera models directly.

The rectified frame has x along the baseline (left -> right camera centre), z the mean viewing
direction with its baseline component removed and y = z x x. Both rectified cameras share this
rotation and one K, so a scene point has the same row in both and disparity = f * B / z.
The canvas covers only the shared sector (directions seen by both cameras) plus a margin, and is
padded by the disparity search range on both sides so that left- and right-referenced disparities
can be computed. Every source image is warped with one `cv2.remap` whose maps come straight from
the source camera model (pinhole, Kannala-Brandt or ocam), so there is no double interpolation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ..cameras import Camera, Pinhole
from ..pairs import left_right
from ..threads import torch_threads  # noqa: F401 - re-exported

DISPARITY_STEP = 16  # SGBM wants a multiple of 16


@dataclass(frozen=True, eq=False)
class RectifiedPair:
    """Geometry of one rectified pair: the two source cameras, the two rectified pinholes, the canvas."""

    left: Camera
    right: Camera
    rect_left: Camera  # pinhole, rectified rotation, left camera centre
    rect_right: Camera  # same K and rotation, right camera centre
    baseline_m: float
    max_disparity: int  # search range in rectified pixels (a multiple of 16)
    core_x: tuple[int, int]  # columns [x0, x1) of the shared sector inside the padded canvas

    @property
    def focal_px(self) -> float:
        """Focal length of both rectified cameras, pixels."""
        return float(self.rect_left.intrinsics.K[0, 0])

    @property
    def size(self) -> tuple[int, int]:
        """Canvas (width, height)."""
        return self.rect_left.width, self.rect_left.height

    @property
    def rotation(self) -> np.ndarray:
        """Rectified rotation (columns x, y, z of the rectified frame in ego coordinates)."""
        return self.rect_left.sensor_to_ego[:3, :3]

    @property
    def name(self) -> str:
        """`left|right`."""
        return f"{self.left.name}|{self.right.name}"


def rectified_rotation(left: Camera, right: Camera) -> np.ndarray:
    """Rectified rotation in ego coordinates: x along the baseline, z the mean view minus its x part."""
    x = right.sensor_to_ego[:3, 3] - left.sensor_to_ego[:3, 3]
    norm = np.linalg.norm(x)
    if norm < 1e-6:
        raise ValueError(f"cameras {left.name} and {right.name} share a centre: no stereo baseline")
    x = x / norm
    view = left.sensor_to_ego[:3, 2] + right.sensor_to_ego[:3, 2]
    z = view - (view @ x) * x
    if np.linalg.norm(z) < 1e-6:
        raise ValueError(f"cameras {left.name} and {right.name} look along their baseline: cannot rectify")
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _rotation_into(cam: Camera, rotation: np.ndarray) -> np.ndarray:
    """Matrix taking directions in the frame `rotation` (ego columns) into `cam`'s camera frame."""
    return cam.sensor_to_ego[:3, :3].T @ rotation


def angular_resolution(cam: Camera, direction_ego: np.ndarray) -> float | None:
    """Pixels per radian of `cam` around an ego direction (sqrt of the Jacobian area), None if unseen."""
    R = cam.sensor_to_ego[:3, :3].T
    d = R @ (direction_ego / np.linalg.norm(direction_ego))
    t1 = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(d, t1)
    eps = 1e-4
    pts = np.stack([d, d + eps * t1, d + eps * t2])
    uv, valid = cam.intrinsics.project(pts)
    if not valid.all():
        return None
    J = np.stack([uv[1] - uv[0], uv[2] - uv[0]], axis=1) / eps
    return float(math.sqrt(abs(np.linalg.det(J))))


def _camera_resolution(cam: Camera, rotation: np.ndarray) -> float:
    """Angular resolution at the rectified z direction, else at the camera's own axis."""
    res = angular_resolution(cam, rotation[:, 2])
    if res is None:
        res = angular_resolution(cam, cam.sensor_to_ego[:3, 2])
    if res is None:
        raise ValueError(f"camera {cam.name}: cannot measure its angular resolution")
    return res


def _rows(samples: int, max_az: float, max_el: float) -> int:
    """Number of elevation samples for `samples` azimuth samples (same tangent-plane spacing)."""
    return max(8, int(samples * math.tan(max_el) / math.tan(max_az)))


def _shared_sector(
    left: Camera, right: Camera, rotation: np.ndarray, max_az: float, max_el: float, samples: int
) -> tuple[float, float, float, float, float] | None:
    """Tangent-plane box (a0, a1, b0, b1) of directions seen by both cameras, and the widest disparity.

    Directions are taken at infinity (rotation only). The disparity bound is, over the rows, the
    largest horizontal distance from a right-visible direction to a left-visible one on its right.
    """
    a = np.linspace(-math.tan(max_az), math.tan(max_az), samples)
    b = np.linspace(-math.tan(max_el), math.tan(max_el), _rows(samples, max_az, max_el))
    seen = []
    for cam in (left, right):  # projection is scale-free: the directions (a, b, 1) need no normalising
        with torch_threads(1):
            _, valid = cam.intrinsics.project_torch(_plane_directions(_rotation_into(cam, rotation), a, b))
        seen.append(valid.numpy())
    both = seen[0] & seen[1]
    if not both.any():
        return None
    rows = np.nonzero(both.any(axis=1))[0]
    cols = np.nonzero(both.any(axis=0))[0]
    widest = 0.0
    r = np.nonzero(seen[0].any(axis=1) & seen[1].any(axis=1))[0]
    if r.size:  # per row: the last direction the left camera sees minus the first one the right camera sees
        last_left = a.size - 1 - np.argmax(seen[0][r, ::-1], axis=1)
        first_right = np.argmax(seen[1][r], axis=1)
        widest = max(widest, float((a[last_left] - a[first_right]).max()))
    return float(a[cols[0]]), float(a[cols[-1]]), float(b[rows[0]]), float(b[rows[-1]]), widest


def turned(vectors: np.ndarray, R: np.ndarray) -> np.ndarray:
    """float64 (N, 3) `vectors` @ R.T, by OpenCV's per-element transform (about 4x BLAS on one thread, 20x torch's
    (N, 3) @ (3, 3), and no BLAS thread pool to spin)."""
    return cv2.transform(np.ascontiguousarray(vectors, np.float64).reshape(-1, 1, 3), R).reshape(-1, 3)


def _plane_directions(M: np.ndarray, xs: np.ndarray, ys: np.ndarray, dtype: torch.dtype = torch.float64
                      ) -> torch.Tensor:
    """M @ (x, y, 1) for every (x, y) of the grid ys x xs: (len(ys), len(xs), 3), applied row by column (no (N, 3)
    grid is built and turned)."""
    M = torch.as_tensor(M, dtype=dtype)
    x = torch.as_tensor(xs, dtype=dtype)
    y = torch.as_tensor(ys, dtype=dtype)
    return (y[:, None] * M[:, 1] + M[:, 2])[:, None, :] + x[None, :, None] * M[:, 0]


def rectify_pair(
    cam_a: Camera,
    cam_b: Camera,
    scale: float = 0.5,
    min_depth: float = 1.5,
    margin_px: int = 8,
    max_azimuth_deg: float = 60.0,
    max_elevation_deg: float = 50.0,
    samples: int = 241,
) -> RectifiedPair | None:
    """Rectified geometry of an adjacent pair (order-free), or None if the pair cannot give stereo.

    None when the cameras share no sector, share a centre, or look along their baseline.
    The focal length is `scale` times the mean angular resolution (px/rad) of the two source
    cameras at the rectified viewing direction; the search range is min(f B / min_depth, widest
    possible disparity of the shared sector), rounded up to a multiple of 16.
    """
    with torch_threads(1):
        return _rectify_pair(cam_a, cam_b, scale, min_depth, margin_px, math.radians(max_azimuth_deg),
                             math.radians(max_elevation_deg), samples)


def tile_pair(
    cam_a: Camera, cam_b: Camera, turn: float, half_angle: float, scale: float, min_depth: float, margin_px: int,
    max_azimuth_deg: float, samples: int = 241, name: str = "",
) -> RectifiedPair | None:
    """`rectify_pair` with the rectified frame turned by `turn` (radians, + down) about the baseline and the
    canvas holding the shared field within `half_angle` (radians) of that direction; None if there is none.
    Its cameras are named `L|R@name#L` and `#R`."""
    with torch_threads(1):
        return _rectify_pair(cam_a, cam_b, scale, min_depth, margin_px, math.radians(max_azimuth_deg), half_angle,
                             samples, turn, f"@{name}")


def _turn_about_x(angle: float) -> np.ndarray:
    """Columns of a frame turned by `angle` about x (the baseline), in the old frame: z turns towards +y (down)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def _rectify_pair(
    cam_a: Camera, cam_b: Camera, scale: float, min_depth: float, margin_px: int, az: float, el: float,
    samples: int, turn: float | None = None, tag: str = "",
) -> RectifiedPair | None:
    left, right = left_right(cam_a, cam_b)
    try:
        R = rectified_rotation(left, right)
    except ValueError:  # co-located, or looking along the baseline: no stereo from this pair
        return None
    if turn is not None:
        R = R @ _turn_about_x(turn)
    baseline = float(np.linalg.norm(right.sensor_to_ego[:3, 3] - left.sensor_to_ego[:3, 3]))
    box = _shared_sector(left, right, R, az, el, samples)
    if box is None:
        return None
    a0, a1, b0, b1, widest = box
    step_a = 2 * math.tan(az) / (samples - 1)
    step_b = 2 * math.tan(el) / (_rows(samples, az, el) - 1)
    a0, a1 = a0 - step_a, a1 + step_a  # the sampled box is one sample short of the true edge
    b0, b1 = b0 - step_b, b1 + step_b
    f = scale * 0.5 * (_camera_resolution(left, R) + _camera_resolution(right, R))
    d_depth = f * baseline / min_depth
    d_geom = f * (widest + 2 * step_a) + margin_px
    max_disp = int(math.ceil(max(min(d_depth, d_geom), 1.0) / DISPARITY_STEP) * DISPARITY_STEP)
    core_w = int(math.ceil(f * (a1 - a0))) + 2 * margin_px
    height = int(math.ceil(f * (b1 - b0))) + 2 * margin_px
    width = core_w + 2 * max_disp
    cx = max_disp + margin_px - f * a0
    cy = margin_px - f * b0
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    model = Pinhole(width, height, K, None)

    def pose(cam: Camera) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = cam.sensor_to_ego[:3, 3]
        return T

    return RectifiedPair(
        left=left,
        right=right,
        rect_left=Camera(f"{left.name}|{right.name}{tag}#L", model, pose(left)),
        rect_right=Camera(f"{left.name}|{right.name}{tag}#R", model, pose(right)),
        baseline_m=baseline,
        max_disparity=max_disp,
        core_x=(max_disp, max_disp + core_w),
    )


def rim_inner(src: Camera, rim_px: int) -> np.ndarray | None:
    """uint8 (H, W) of `src`: its valid area eroded by `rim_px` (the fisheye rim left out); None if rim_px <= 0."""
    if rim_px <= 0:
        return None
    with torch_threads(1):
        src_valid = src.intrinsics.valid_mask().astype(np.uint8)
    kernel = np.ones((2 * rim_px + 1, 2 * rim_px + 1), np.uint8)
    return cv2.erode(src_valid, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)


def camera_maps(
    src: Camera, dst: Camera, rim_px: int = 0, dtype: torch.dtype = torch.float64, inner: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remap maps (float32 x, y) sampling `src` for every pixel of `dst`, and their validity.

    Both cameras are taken to share an optical centre (rectified or virtual cameras): only the
    rotation between them matters. With `rim_px` > 0, source pixels closer than that to the
    border of the source's valid area (the fisheye rim) count as invalid; `inner` may pass
    `rim_inner(src, rim_px)` computed once for several warps of the same source.
    """
    R = src.sensor_to_ego[:3, :3].T @ dst.sensor_to_ego[:3, :3]
    with torch_threads(1):
        points, ok = _turned_rays(dst, R, dtype)
        uv, valid = src.intrinsics.project_torch(points)
    valid = valid & ok
    map_x = uv[..., 0].numpy().astype(np.float32)
    map_y = uv[..., 1].numpy().astype(np.float32)
    valid = valid.numpy()
    if rim_px > 0:
        if inner is None:
            inner = rim_inner(src, rim_px)
        iu = np.clip(np.rint(map_x), 0, src.width - 1).astype(np.intp)
        iv = np.clip(np.rint(map_y), 0, src.height - 1).astype(np.intp)
        valid &= inner[iv, iu] > 0
    map_x[~valid] = -1e4
    map_y[~valid] = -1e4
    return map_x, map_y, valid


def _turned_rays(dst: Camera, R: np.ndarray, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions (H, W, 3; not unit) of `dst`'s pixel centres turned by R into the source frame, and validity."""
    intr = dst.intrinsics
    if isinstance(intr, Pinhole) and intr.dist is None:
        # an undistorted pinhole (every canvas and virtual view): pixel -> direction is one matrix, applied
        # row by column instead of building the (H, W, 3) ray grid and turning it
        points = _plane_directions(R @ np.linalg.inv(intr.K), np.arange(intr.width), np.arange(intr.height), dtype)
        return points, torch.ones(points.shape[:2], dtype=torch.bool)
    rays, ok = intr.ray_grid(dtype)
    return torch.from_numpy(turned(rays.numpy(), R).reshape(rays.shape)).to(dtype), ok


@dataclass(frozen=True, eq=False)
class WarpMaps:
    """Precomputed fixed-point maps of one source -> target warp plus the target's validity.

    The maps cover only `box`, the smallest box of the target holding every valid pixel (a rectified
    canvas is about 60 % valid and its box about 65 %): the rest of the target is 0 without a remap."""

    map1: np.ndarray  # (box rows, box columns, 2) int16
    map2: np.ndarray  # (box rows, box columns) uint16
    valid: np.ndarray  # bool (H, W) of the target
    box: tuple[slice, slice] = (slice(0, 0), slice(0, 0))

    @classmethod
    def between(cls, src: Camera, dst: Camera, rim_px: int = 0, inner: np.ndarray | None = None) -> WarpMaps:
        """Maps sampling `src` for every pixel of `dst` (shared optical centre; `inner`: see `camera_maps`)."""
        map_x, map_y, valid = camera_maps(src, dst, rim_px, inner=inner)
        rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
        box = (slice(0, 0), slice(0, 0)) if rows.size == 0 else (
            slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
        map1, map2 = cv2.convertMaps(np.ascontiguousarray(map_x[box]), np.ascontiguousarray(map_y[box]),
                                     cv2.CV_16SC2)
        return cls(map1, map2, valid, box)

    def warp(self, image: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Warp one image (any channels, uint8 or float) into the target; 0 outside the source.

        The maps send every pixel outside `valid` far outside the source (`camera_maps`), so the
        constant border already makes it 0: no mask pass is needed."""
        out = np.zeros(self.valid.shape + image.shape[2:], image.dtype)
        if self.map1.size:
            part = cv2.remap(image, self.map1, self.map2, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            out[self.box] = part.reshape(out[self.box].shape)
        return out


def default_rim_px(cam: Camera) -> int:
    """Pixels of the image-circle rim discarded for fisheye models (none for pinholes)."""
    return 3 if cam.intrinsics.depth_is_range else 0
