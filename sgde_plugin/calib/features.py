"""Features and tentative matches: SIFT (OpenCV, default) or LoFTR (kornia, weights from a local file)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from ..errors import InputError

if TYPE_CHECKING:  # kornia's feature zoo loads only for LoFTR
    from kornia.feature import LoFTR


@dataclass
class Keypoints:
    """Keypoint positions (N, 2) in native pixels, descriptors (N, D) float32, sizes (N,) in native pixels,
    each keypoint's index in its image's full list (kept through `subset`), `fixed`: True where the
    same keypoint sits at the same pixel in another frame of the camera (see `mark_fixed`), for
    keypoints found on a virtual view, their positions in the view's pixels (`view_uv`, else None), and
    what the camera's other frames say about it (`static_world.mark_static_evidence`): `moving` (no static
    point moves so), `inv_range` (1/m, NaN when unknown) with its 1-sigma `inv_range_sigma`."""

    uv: np.ndarray
    desc: np.ndarray
    size: np.ndarray | None = None
    index: np.ndarray | None = None
    fixed: np.ndarray | None = None
    view_uv: np.ndarray | None = None
    moving: np.ndarray | None = None
    inv_range: np.ndarray | None = None
    inv_range_sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.size is None:
            self.size = np.ones(self.uv.shape[0])
        if self.index is None:
            self.index = np.arange(self.uv.shape[0])
        if self.fixed is None:
            self.fixed = np.zeros(self.uv.shape[0], dtype=bool)
        if self.moving is None:
            self.moving = np.zeros(self.uv.shape[0], dtype=bool)
        if self.inv_range is None:
            self.inv_range = np.full(self.uv.shape[0], np.nan)
        if self.inv_range_sigma is None:
            self.inv_range_sigma = np.full(self.uv.shape[0], np.inf)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    def subset(self, keep: np.ndarray) -> Keypoints:
        """The keypoints selected by a boolean mask or index array."""
        view_uv = None if self.view_uv is None else self.view_uv[keep]
        return Keypoints(self.uv[keep], self.desc[keep], self.size[keep], self.index[keep], self.fixed[keep], view_uv,
                         self.moving[keep], self.inv_range[keep], self.inv_range_sigma[keep])

    @property
    def across_time(self) -> np.ndarray:
        """True where a keypoint may be matched across time: neither at one pixel (`fixed`) nor `moving`."""
        return ~(self.fixed | self.moving)


def mark_fixed(frames: list[Keypoints], radius_px: float = 1.0, min_cosine: float = 0.9) -> None:
    """Set `fixed` on the keypoints of one camera's frames that recur at the same pixel (within `radius_px`,
    descriptor cosine >= `min_cosine`) in another frame: texture that moves with the car (a near object
    driving along, the ego body) or lies at infinity. Across time such a match looks like a static point at
    a wrong depth, so cross-time matching leaves them out."""
    from scipy.spatial import cKDTree

    trees = [cKDTree(k.uv) if len(k) else None for k in frames]
    unit = [k.desc / np.maximum(np.linalg.norm(k.desc, axis=1, keepdims=True), 1e-12) for k in frames]
    for i, k in enumerate(frames):
        if trees[i] is None:
            continue
        for j, tree in enumerate(trees):
            if j == i or tree is None:
                continue
            near = trees[i].sparse_distance_matrix(tree, radius_px, output_type="ndarray")  # pairs within the radius
            a, b = near["i"], near["j"]
            cos = np.einsum("nd,nd->n", unit[i][a], unit[j][b])
            k.fixed[a[cos >= min_cosine]] = True


SIFT_UPSCALE_OFFSET_PX = 0.25


def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8 grey image of an RGB (or grey) image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def sift_features(
    image: np.ndarray, mask: np.ndarray | None = None, max_features: int = 4000, scale: float = 1.0,
    contrast_threshold: float = 0.04, octave_layers: int = 3,
) -> Keypoints:
    """SIFT keypoints of an image (optionally downscaled by `scale` for speed), positions in native pixels;
    `octave_layers`: scales sampled per octave (OpenCV's nOctaveLayers, Lowe's 3)."""
    gray = to_gray(image)
    if scale != 1.0:
        h, w = gray.shape
        size = (max(8, int(round(w * scale))), max(8, int(round(h * scale))))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    sift = cv2.SIFT_create(nfeatures=max_features, nOctaveLayers=octave_layers, contrastThreshold=contrast_threshold)
    kps, desc = sift.detectAndCompute(gray, mask)
    if desc is None or not kps:
        return Keypoints(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0))
    # OpenCV's 2x upscale of octave -1 maps pixel x to 2x + 0.5, so every keypoint is reported 0.25 px right of
    # and below where it is (blobs at known sub-pixel centres: +0.249 / +0.249 px, all octaves)
    uv = np.array([k.pt for k in kps], dtype=np.float64) - SIFT_UPSCALE_OFFSET_PX
    size = np.array([k.size for k in kps], dtype=np.float64) / scale
    if scale != 1.0:
        uv = (uv + 0.5) / scale - 0.5  # pixel-centre convention
    return Keypoints(uv, desc.astype(np.float32), size)


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours that pass Lowe's ratio test in both directions: index arrays (ia, ib)."""
    if desc_a.shape[0] < 2 or desc_b.shape[0] < 2:
        return np.zeros(0, int), np.zeros(0, int)

    def best(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
        """For each row of d1, the index of its ratio-test match in d2, or -1."""
        # brute force's two nearest neighbours as arrays (what BFMatcher.knnMatch computes, without its objects)
        dist, nn = cv2.batchDistance(d1, d2, cv2.CV_32F, normType=cv2.NORM_L2, K=2)
        return np.where(dist[:, 0] < ratio * dist[:, 1], nn[:, 0], -1).astype(int)

    ab = best(desc_a, desc_b)
    ba = best(desc_b, desc_a)
    ia = np.flatnonzero(ab >= 0)
    ib = ab[ia]
    mutual = ba[ib] == ia
    return ia[mutual], ib[mutual]


def load_loftr(weights: str | Path | None) -> LoFTR:
    """A kornia LoFTR built without downloading, weights from a local checkpoint (torch.load weights_only).

    The file may hold a plain state dict or a Lightning-style {"state_dict": ...}. A missing path or a
    file that does not fit the model is an InputError.
    """
    from kornia.feature import LoFTR  # kornia's feature zoo loads only for LoFTR

    if weights is None:
        raise InputError(None, "--loftr-weights", "LoFTR needs a local checkpoint path (nothing is downloaded)")
    path = Path(weights)
    if not path.is_file():
        raise InputError(path, None, "LoFTR checkpoint not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is bad input
        raise InputError(path, None, f"cannot load LoFTR checkpoint ({type(exc).__name__}: {exc})") from None
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    model = LoFTR(pretrained=None)
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as exc:
        raise InputError(path, None, f"checkpoint does not fit kornia's LoFTR ({str(exc).splitlines()[0]})") from None
    return model.eval()


def _box_crop(gray: np.ndarray, box: tuple[int, int, int, int] | None) -> tuple[np.ndarray, int, int]:
    """Crop to box (x0, y0, x1, y1) enlarged to multiples of 8 inside the image; returns crop and offset."""
    h, w = gray.shape
    x0, y0, x1, y1 = box if box is not None else (0, 0, w, h)
    x0, y0 = max(0, x0 - x0 % 8), max(0, y0 - y0 % 8)
    x1, y1 = min(w, x1), min(h, y1)
    x1 = x0 + max(8, ((x1 - x0) // 8) * 8)
    y1 = y0 + max(8, ((y1 - y0) // 8) * 8)
    return gray[y0:y1, x0:x1], x0, y0


def loftr_match(
    model: LoFTR, image_a: np.ndarray, image_b: np.ndarray, box_a: tuple[int, int, int, int] | None = None,
    box_b: tuple[int, int, int, int] | None = None, min_confidence: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """LoFTR matches between two images, optionally inside boxes (x0, y0, x1, y1): native pixels (N, 2) x 2."""
    ga, xa, ya = _box_crop(to_gray(image_a), box_a)
    gb, xb, yb = _box_crop(to_gray(image_b), box_b)
    if min(ga.shape) < 16 or min(gb.shape) < 16:
        return np.zeros((0, 2)), np.zeros((0, 2))
    with torch.inference_mode():
        out = model({
            "image0": torch.from_numpy(ga).float()[None, None] / 255.0,
            "image1": torch.from_numpy(gb).float()[None, None] / 255.0,
        })
    conf = out["confidence"].numpy()
    keep = conf >= min_confidence
    uv_a = out["keypoints0"].numpy()[keep].astype(np.float64) + [xa, ya]
    uv_b = out["keypoints1"].numpy()[keep].astype(np.float64) + [xb, yb]
    return uv_a, uv_b
