"""Figures for reports: per-camera prior panels and a bird's-eye view of the ring's priors."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cameras import Camera, pixel_grid
from .geometry import transform_points
from .io import atomic_path


@dataclass(frozen=True)
class CameraPanel:
    """One row of the prior figure: a camera's image, prior, ground truth (metres, 0 = none)."""

    camera: str
    image: np.ndarray
    prior: np.ndarray
    gt: np.ndarray | None = None


def _figure():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _masked(depth: np.ndarray) -> np.ma.MaskedArray:
    return np.ma.masked_where(~(depth > 0), depth)


def save_prior_panels(path: str | Path, panels: Sequence[CameraPanel], max_depth: float = 80.0) -> None:
    """Image | prior | ground truth | relative error, one row per camera, saved as PNG (atomically)."""
    plt = _figure()
    rows = len(panels)
    fig, axes = plt.subplots(rows, 4, figsize=(16, 2.6 * rows), squeeze=False)
    for r, p in enumerate(panels):
        ax = axes[r]
        ax[0].imshow(p.image)
        ax[0].set_ylabel(p.camera, fontsize=9)
        ax[1].imshow(_masked(p.prior), cmap="turbo", vmin=0, vmax=max_depth, interpolation="nearest")
        ax[1].set_facecolor("black")
        if p.gt is not None:
            ax[2].imshow(_masked(p.gt), cmap="turbo", vmin=0, vmax=max_depth, interpolation="nearest")
            both = (p.prior > 0) & (p.gt > 0)
            err = np.zeros_like(p.prior)
            err[both] = np.abs(p.prior[both] - p.gt[both]) / p.gt[both]
            im = ax[3].imshow(np.ma.masked_where(~both, err), cmap="magma", vmin=0, vmax=0.3, interpolation="nearest")
            ax[3].set_facecolor("black")
            if r == 0:
                fig.colorbar(im, ax=ax[3], fraction=0.03, label="|prior - gt| / gt")
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
        if r == 0:
            for a, title in zip(ax, ["image", f"prior (0-{max_depth:.0f} m)", "ground truth", "relative error"]):
                a.set_title(title, fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def prior_points_ego(camera: Camera, depth: np.ndarray, stride: int = 2) -> np.ndarray:
    """Ego-frame 3-D points of a prior map (every `stride`-th pixel with a value), (N, 3)."""
    sub = depth[::stride, ::stride]
    uv = pixel_grid(camera.width, camera.height).numpy()[::stride, ::stride]
    keep = sub > 0
    pts, valid = camera.intrinsics.points_from_depth(uv[keep], sub[keep])
    return transform_points(camera.sensor_to_ego, pts[valid])


def save_bev_points(
    path: str | Path,
    views: Mapping[str, tuple[Sequence[Camera], Mapping[str, np.ndarray]]],
    extent_m: float = 30.0,
) -> None:
    """Side-by-side bird's-eye views (x forward up, y left) of priors as points coloured by camera."""
    plt = _figure()
    fig, axes = plt.subplots(1, len(views), figsize=(6.5 * len(views), 6.8), squeeze=False)
    cmap = plt.get_cmap("tab10")
    for ax, (title, (cameras, priors)) in zip(axes[0], views.items()):
        for i, cam in enumerate(cameras):
            if cam.name not in priors:
                continue
            pts = prior_points_ego(cam, priors[cam.name])
            near = (np.abs(pts[:, 0]) < extent_m) & (np.abs(pts[:, 1]) < extent_m)
            pts = pts[near]
            ax.scatter(-pts[:, 1], pts[:, 0], s=0.3, color=cmap(i % 10), label=cam.name, rasterized=True)
            ax.plot(-cam.sensor_to_ego[1, 3], cam.sensor_to_ego[0, 3], "k^", ms=4)
        ax.set_xlim(-extent_m, extent_m)
        ax.set_ylim(-extent_m, extent_m)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=11)
        ax.set_xlabel("-y: lateral offset (m), right positive")
        ax.set_ylabel("x forward (m)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=min(6, len(labels)), markerscale=12, fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    _save(fig, path)


def _save(fig, path: str | Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
