"""`PriorDataset`: a torch Dataset joining a rig's images, its cached priors and optional ground truth.

Every sample is resized (or augmented with a BEVDepth-style image-augmentation matrix) to the
network's input size with one pixel affine shared by image, prior, confidence and ground truth:
the image bilinearly, the depth maps without inventing depths (min-pool of valid values, then
nearest; see `resample`). Safe with `DataLoader(num_workers > 0)`: the cache is opened lazily in
each worker process.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ..errors import InputError
from ..rig import Rig
from .backends import Location
from .resample import as_affine, resize_matrix, warp_depth_affine, warp_image
from .store import PriorCache, check_size

IdaSpec = np.ndarray | Callable[[str, str, tuple[int, int], tuple[int, int]], np.ndarray] | None


class PriorDataset(Dataset):
    """Samples of (frame, camera) — or of whole frames with `group_cameras=True` — as tensors:
    image (3,h,w) float in [0,1], prior (1,h,w) metres, valid (1,h,w) bool, confidence (1,h,w),
    gt (1,h,w) metres when `with_gt` (0 = none), ida (3,3) the pixel affine used, frame_id, camera.

    `ida` is None (plain resize to `size`), one matrix (3x3 or BEVDepth 4x4 `ida_mat`, mapping
    source pixels to network-input pixels) or a callable (frame_id, camera, (H, W), (h, w)) -> matrix
    for per-sample random augmentation. The cache must have been built for this rig's calibration
    (checked by fingerprint unless `check_rig=False`).
    """

    def __init__(
        self,
        rig: Rig,
        cache: PriorCache | Location,
        size: tuple[int, int],
        *,
        cameras: Sequence[str] | None = None,
        frames: Sequence[str] | None = None,
        ida: IdaSpec = None,
        with_gt: bool = False,
        group_cameras: bool = False,
        check_rig: bool = True,
        scene: str | None = None,
    ):
        self.size = check_size(size)  # (0, 0) and the like: a clear ValueError before any work
        self.rig = rig
        self.cache = cache if isinstance(cache, PriorCache) else PriorCache(cache, scene=scene)
        if check_rig:
            self.cache.check(rig=rig)
        self.cameras = list(cameras) if cameras is not None else list(rig.camera_names)
        missing = [c for c in self.cameras if c not in self.cache.cameras()]
        if missing:
            raise InputError(str(self.cache.location), "cameras", f"no priors for {missing}")
        cached = set(self.cache.frames())
        if frames is None:
            self.frames = [f.id for f in rig.frames if f.id in cached]
        else:
            absent = [f for f in frames if f not in cached]
            if absent:
                where = str(self.cache.location)
                raise InputError(where, "frames", f"{len(absent)} frames not in the cache, e.g. {absent[0]!r}")
            self.frames = list(frames)
        self.ida = ida
        self.with_gt = with_gt
        self.group_cameras = group_cameras

    def __len__(self) -> int:
        return len(self.frames) if self.group_cameras else len(self.frames) * len(self.cameras)

    def matrix(self, frame_id: str, camera: str) -> np.ndarray:
        """The 3x3 pixel affine (native camera pixels -> network input) of one sample."""
        cam = self.rig.camera(camera)
        src = (int(cam.height), int(cam.width))
        if self.ida is None:
            return resize_matrix(src, self.size)
        if callable(self.ida):
            return as_affine(self.ida(frame_id, camera, src, self.size))
        return as_affine(self.ida)

    def sample(self, frame_id: str, camera: str) -> dict[str, Any]:
        """One camera image of one frame, as tensors at the network input size."""
        m = self.matrix(frame_id, camera)
        image = self.rig.load_image(frame_id, camera)
        img = warp_image(image, m, self.size).astype(np.float32) / 255.0
        depth, _, conf = self.cache.get_prior(frame_id, camera)
        prior, confidence = warp_depth_affine(depth, m, self.size, conf)
        out = {
            "image": torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))),
            "prior": torch.from_numpy(prior[None]),
            "valid": torch.from_numpy(prior[None] > 0),
            "confidence": torch.from_numpy(confidence[None].astype(np.float32)),
            "ida": torch.from_numpy(m.astype(np.float32)),
            "frame_id": frame_id,
            "camera": camera,
        }
        if self.with_gt:
            gt = self.rig.load_depth(frame_id, camera)
            gt_out = np.zeros(self.size, np.float32) if gt is None else warp_depth_affine(gt, m, self.size)[0]
            out["gt"] = torch.from_numpy(gt_out[None])
        return out

    def __getitem__(self, index: int) -> dict[str, Any]:
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(index)
        if not self.group_cameras:
            fi, ci = divmod(index, len(self.cameras))
            return self.sample(self.frames[fi], self.cameras[ci])
        fid = self.frames[index]
        samples = [self.sample(fid, cam) for cam in self.cameras]
        keys = [k for k in samples[0] if k not in ("frame_id", "camera")]
        out: dict[str, Any] = {k: torch.stack([s[k] for s in samples]) for k in keys}
        out["frame_id"] = fid
        out["camera"] = list(self.cameras)
        return out


__all__ = ["PriorDataset"]
