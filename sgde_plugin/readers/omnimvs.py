"""Synthetic Urban / OmniMVS folders (`config.yaml`, `cam%d/%04d.png`, inverse-depth TIFFs) -> `Rig`.

Facts from the public OmniMVS code (hyu-cvlab/omnimvs-pytorch: `utils/ocam.py`, `utils/dbhelper.py`,
`utils/geometry.py`, `dataset.py`, and its `data/*/config.yaml`):

- `cameras[i]`: `cam_id`, `model: ocam`, `poly` / `inv_poly` whose FIRST entry is the number of
  coefficients that follow (ascending powers, OCamCalib's `ss` / `invpol`), `center` [row, col]
  (0-based), `affine` [c, d, e], `image_size` [H, W], `pose` [rx, ry, rz, tx, ty, tz] camera-to-rig
  (rotation vector, metres; X_rig = R X_cam + t), `max_fov` degrees. OmniMVS's pixel<->ray maths are
  exactly `cameras.Ocam`'s (same OCam frame and affine), and its camera frame is x right, y down,
  z forward, so the coefficients are used as they are, minus the leading count.
- The OmniMVS rig frame is camera 1's frame without translation: x right, y down, z forward.
  Ours is x forward, y left, z up, so sensor_to_ego = E @ cam_to_rig with E = CAMERA_TO_BODY; the
  rig centre is our ego origin (there is no ground-referenced vehicle frame).
- `dataset.img_fmt` (default `cam%d/%04d.png`, formatted with cam_id and frame index) and
  `dataset.start/step/end` give the frames; without them the first camera's folder is listed.
  Timestamps are the frame index (no times in the data) and ego poses are identity.
- Ground truth `omnidepth_gt_<W>/%05d.tiff` is an equirectangular INVERSE depth (1/m) around the rig
  centre, in a two-page TIFF (a uint8 thumbnail and the float32 map; we pick the float page). Its
  rays (OmniMVS `makeSphericalRays`): column c -> theta = (c - W/2)/(W/2)*pi + pi/2, row r -> phi =
  (r - (H-1)/2)/((H-1)/2)*phi_max, ray = (-cos(phi)cos(theta), sin(phi), cos(phi)sin(theta)) in the
  rig frame; phi_max is 45 degrees for 640x160 maps (Sunny/Cloudy/Sunset) and 90 for 640x320, i.e.
  180 * H / W degrees. Inverse depth below 1e-3 (beyond 1 km) is sky, as in OmniMVS.
- Per-camera depth for the contract (fisheye depth = range, 0 = none) is obtained by splatting the
  panorama's 3-D points into the camera with a z-buffer (`panorama_depth_to_camera`): sparse, like
  projected LiDAR. `Frame.depths[camera]` holds the TIFF path for every camera; `Rig.load_depth`
  reads it through `sgde_plugin.panorama` (below the readers, so the rig never imports a reader).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import yaml

from ..cameras import Camera
from ..errors import InputError
from ..geometry import CAMERA_TO_BODY, make_transform, rodrigues
from ..io import image_size
from ..panorama import (
    load_panorama_depth,
    panorama_depth_to_camera,
    panorama_rays,
    read_inverse_depth_tiff,
)
from ..rig import Frame, Rig, ring_pairs
from ..rigfile import intrinsics_from_dict

CONFIG = "config.yaml"
DEFAULT_IMG_FMT = "cam%d/%04d.png"
GT_DIR = re.compile(r"^omnidepth_gt_(\d+)$")
GT_NAME = "{:05d}.tiff"
_PLACEHOLDER = re.compile(r"%(0?\d*)d")
RIG_TO_EGO = make_transform(CAMERA_TO_BODY, np.zeros(3))  # OmniMVS rig (x right, y down, z fwd) -> ego


def is_omnimvs_folder(folder: Path) -> bool:
    """True if `folder` holds an OmniMVS-style `config.yaml`."""
    return (folder / CONFIG).is_file()


def read_config(path: Path) -> dict:
    """Parse `config.yaml`; InputError for bad YAML or a non-mapping top level."""
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(path, None, f"bad YAML{where} ({getattr(exc, 'problem', None) or exc})") from None
    if not isinstance(doc, dict):
        raise InputError(path, None, "top level is not a mapping")
    return doc


def _numbers(entry: dict, key: str, file: Path, where: str, length: int | None = None) -> list[float]:
    value = entry.get(key)
    if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                              for v in value):
        raise InputError(file, f"{where}.{key}", "missing or not a list of numbers")
    if length is not None and len(value) != length:
        raise InputError(file, f"{where}.{key}", f"has {len(value)} values, expected {length}")
    if not all(math.isfinite(v) for v in value):
        raise InputError(file, f"{where}.{key}", "contains NaN or infinity")
    return [float(v) for v in value]


def _counted(entry: dict, key: str, file: Path, where: str) -> list[float]:
    """An OCamCalib coefficient list whose first entry is the count of the rest."""
    value = _numbers(entry, key, file, where)
    if len(value) < 2 or value[0] != len(value) - 1:
        raise InputError(file, f"{where}.{key}", f"first entry must be the number of coefficients ({len(value) - 1})")
    return value[1:]


def ocam_camera(entry: dict, file: Path, where: str) -> tuple[str, int, Camera]:
    """(name, cam_id, Camera) of one `cameras[i]` entry: ocam intrinsics and sensor_to_ego in our ego frame."""
    cam_id = entry.get("cam_id")
    if not isinstance(cam_id, int) or isinstance(cam_id, bool):
        raise InputError(file, f"{where}.cam_id", "missing or not an integer")
    if entry.get("model", "ocam") != "ocam":
        raise InputError(file, f"{where}.model", f"unsupported model {entry.get('model')!r} (expected ocam)")
    h, w = _numbers(entry, "image_size", file, where, 2)
    if h != int(h) or w != int(w) or h <= 0 or w <= 0:
        raise InputError(file, f"{where}.image_size", "not two positive integers [H, W]")
    max_fov = entry.get("max_fov")
    if not isinstance(max_fov, (int, float)) or isinstance(max_fov, bool):
        raise InputError(file, f"{where}.max_fov", "missing or not a number")
    model = {
        "model": "ocam", "width": int(w), "height": int(h),
        "poly": _counted(entry, "poly", file, where), "inv_poly": _counted(entry, "inv_poly", file, where),
        "center": _numbers(entry, "center", file, where, 2), "affine": _numbers(entry, "affine", file, where, 3),
        "fov_deg": float(max_fov),
    }
    try:
        intrinsics = intrinsics_from_dict(model, where)
    except InputError as exc:
        raise InputError(file, exc.key.replace(".fov_deg", ".max_fov") if exc.key else None, exc.problem) from None
    pose = _numbers(entry, "pose", file, where, 6)
    cam_to_rig = make_transform(rodrigues(np.array(pose[:3])), np.array(pose[3:]))
    return f"cam{cam_id}", cam_id, Camera(f"cam{cam_id}", intrinsics, RIG_TO_EGO @ cam_to_rig)


def ring_by_azimuth(cameras: list[Camera]) -> tuple[str, ...]:
    """Camera names clockwise seen from above (front, right, back, left), starting at the first camera."""
    az = [math.atan2(c.sensor_to_ego[1, 2], c.sensor_to_ego[0, 2]) for c in cameras]
    order = sorted(range(len(cameras)), key=lambda i: (az[0] - az[i]) % (2 * math.pi))
    return tuple(cameras[i].name for i in order)


def _split_fmt(fmt: str, file: Path) -> tuple[str, str, str]:
    """(text before the frame placeholder with the camera one left in, frame spec, text after)."""
    marks = list(_PLACEHOLDER.finditer(fmt))
    if len(marks) != 2 or fmt.count("%") != 2:
        raise InputError(file, "dataset.img_fmt", f"{fmt!r} needs exactly two %d fields (camera, frame)")
    m = marks[1]
    return fmt[:m.start()], "%" + m.group(1) + "d", fmt[m.end():]


def _frame_indices(root: Path, fmt: str, first_cam: int, dataset: dict, file: Path) -> list[int]:
    keys = ("start", "step", "end")
    if all(k in dataset for k in keys):
        start, step, end = (dataset[k] for k in keys)
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (start, step, end)) or step <= 0:
            raise InputError(file, "dataset.start/step/end", "not integers with step > 0")
        return list(range(start, end + 1, step))
    head, _, tail = _split_fmt(fmt, file)
    head = head % first_cam
    pattern = re.compile(re.escape(head) + r"(\d+)" + re.escape(tail) + "$")
    found = sorted({int(m.group(1)) for p in root.glob(head + "*" + tail)
                    if (m := pattern.match(p.relative_to(root).as_posix()))})
    if not found:
        raise InputError(root / (head + "*" + tail), None, "no images found")
    return found


def _gt_folder(root: Path) -> Path | None:
    """The widest `omnidepth_gt_<W>` folder, if any."""
    best = None
    for p in root.iterdir():
        m = GT_DIR.match(p.name)
        if m and p.is_dir() and (best is None or int(m.group(1)) > best[0]):
            best = (int(m.group(1)), p)
    return None if best is None else best[1]


def load_omnimvs(root: str | Path, check_images: bool = False) -> Rig:
    """A Synthetic Urban / OmniMVS folder as a Rig of `ocam` cameras in a ring."""
    root = Path(root)
    file = root / CONFIG
    doc = read_config(file)
    cams_doc = doc.get("cameras")
    if not isinstance(cams_doc, list) or not cams_doc:
        raise InputError(file, "cameras", "missing or empty")
    dataset = doc.get("dataset") or {}
    if not isinstance(dataset, dict):
        raise InputError(file, "dataset", "not a mapping")
    fmt = dataset.get("img_fmt", DEFAULT_IMG_FMT)
    if not isinstance(fmt, str):
        raise InputError(file, "dataset.img_fmt", "not a string")
    _, frame_spec, _ = _split_fmt(fmt, file)

    cameras: list[Camera] = []
    ids: dict[str, int] = {}
    for i, entry in enumerate(cams_doc):
        if not isinstance(entry, dict):
            raise InputError(file, f"cameras[{i}]", "not a mapping")
        name, cam_id, cam = ocam_camera(entry, file, f"cameras[{i}]")
        if name in ids:
            raise InputError(file, f"cameras[{i}].cam_id", f"duplicate camera id {cam_id}")
        ids[name] = cam_id
        cameras.append(cam)
    ring = ring_by_azimuth(cameras)

    gt = _gt_folder(root)
    frames = []
    for idx in _frame_indices(root, fmt, ids[cameras[0].name], dataset, file):
        images = {c.name: root / (fmt % (ids[c.name], idx)) for c in cameras}
        if check_images:
            for cam in cameras:
                _check_image(images[cam.name], cam)
        depths: dict[str, Path] = {}
        if gt is not None and (gt / GT_NAME.format(idx)).is_file():
            depths = {c.name: gt / GT_NAME.format(idx) for c in cameras}
        frames.append(Frame(frame_spec % idx, idx, np.eye(4), images, depths))
    return Rig(tuple(cameras), ring_pairs(ring), tuple(frames), ring, root)


def _check_image(path: Path, cam: Camera) -> None:
    if not path.is_file():
        raise InputError(path, None, f"image of camera {cam.name} is missing")
    w, h = image_size(path)
    if (w, h) != (cam.width, cam.height):
        raise InputError(path, "size", f"image is {w}x{h}, camera {cam.name} is {cam.width}x{cam.height}")


__all__ = [
    "RIG_TO_EGO",
    "is_omnimvs_folder",
    "load_omnimvs",
    "load_panorama_depth",
    "ocam_camera",
    "panorama_depth_to_camera",
    "panorama_rays",
    "read_config",
    "read_inverse_depth_tiff",
    "ring_by_azimuth",
]
