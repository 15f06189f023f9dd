"""Where the prior's errors on real frames come from: `sgde bench real`'s breakdown tables.

Every LiDAR point that gets a prior is kept with its true depth, the prior's depth and confidence and its
image row; the errors are then split by depth range, by image row band (the car body fills the bottom
rows of side and rear cameras), by confidence band, and into large errors (off by more than 25 %). Per
pair, the median disparity error (rectified pixels at the matching scale, f B (1 / prior - 1 / LiDAR)) over
the pair's overlap points separates a calibration residual (a constant offset per pair) from matching noise.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..tables import format_table

DEPTH_BANDS_M = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, 200.0)
ROW_BANDS = (0.0, 0.25, 0.5, 0.75, 1.0)  # fractions of the image height, top to bottom
CONFIDENCE_BANDS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0001)
LARGE_ERROR_RATIO = 1.25


class ErrorBreakdown:
    """Per-point samples of one pose source; `result()` gives the tables."""

    def __init__(self) -> None:
        self._cols: dict[str, list[np.ndarray]] = {"gt": [], "pred": [], "conf": [], "row": []}

    def add(self, depth: Mapping[str, np.ndarray], confidence: Mapping[str, np.ndarray],
            gts: Mapping[str, np.ndarray | None], max_depth: float) -> None:
        """One frame: prior depth and confidence per camera, LiDAR depth per camera (None = none)."""
        for name, gt in gts.items():
            if gt is None or name not in depth:
                continue
            ys, xs = np.nonzero((gt > 0) & (gt <= max_depth) & (depth[name] > 0))
            for key, values in (("gt", gt[ys, xs]), ("pred", depth[name][ys, xs]),
                                ("conf", confidence[name][ys, xs]), ("row", ys / gt.shape[0])):
                self._cols[key].append(np.asarray(values, np.float64))

    def result(self, pair_samples: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
               pair_fb: Mapping[str, float] | None = None) -> dict[str, Any]:
        """Tables by depth, row and confidence band, the large errors, and per pair the median disparity
        error from `pair_samples` {pair: (prior, LiDAR)} and `pair_fb` {pair: focal x baseline, px m}."""
        c = {k: np.concatenate(v) if v else np.zeros(0) for k, v in self._cols.items()}
        rel = np.abs(c["pred"] - c["gt"]) / np.maximum(c["gt"], 1e-9)
        total = float(rel.sum()) or 1.0
        ratio = np.maximum(c["pred"], 1e-9) / np.maximum(c["gt"], 1e-9)
        large = np.maximum(ratio, 1 / ratio) > LARGE_ERROR_RATIO

        def band(key: str, edges: tuple[float, ...], label: str) -> list[dict[str, Any]]:
            rows = []
            for lo, hi in zip(edges[:-1], edges[1:]):
                sel = (c[key] >= lo) & (c[key] < hi) if key != "gt" else (c[key] > lo) & (c[key] <= hi)
                n = int(sel.sum())
                rows.append({label: f"{lo:g}-{min(hi, 1.0) if key == 'conf' else hi:g}", "n": n,
                             "share": n / max(1, rel.size), "abs_rel": float(rel[sel].mean()) if n else float("nan"),
                             "a1": float((~large[sel]).mean()) if n else float("nan"),
                             "share_of_abs_rel": float(rel[sel].sum()) / total})
            return rows

        out: dict[str, Any] = {
            "n": int(rel.size),
            "depth_m": band("gt", DEPTH_BANDS_M, "depth_m"),
            "image_rows": band("row", ROW_BANDS, "rows"),
            "confidence": band("conf", CONFIDENCE_BANDS, "confidence"),
            "large_errors": {"share": float(large.mean()) if rel.size else float("nan"),
                             "share_of_abs_rel": float(rel[large].sum()) / total,
                             "prior_nearer": float((c["pred"][large] < c["gt"][large]).mean()) if large.any()
                             else float("nan")},
            "pair_disparity_error_px": {},
        }
        for pair, (pred, gt) in (pair_samples or {}).items():
            fb = (pair_fb or {}).get(pair)
            ok = (pred > 0) & (gt > 0)
            if fb is None or not ok.any():
                continue
            err = fb * (1 / pred[ok] - 1 / gt[ok])
            out["pair_disparity_error_px"][pair] = {"median": float(np.median(err)), "n": int(ok.sum()),
                                                    "median_beyond_20m": float(np.median(err[gt[ok] > 20]))
                                                    if (gt[ok] > 20).any() else float("nan")}
        return out


def breakdown_tables(breakdown: Mapping[str, Any]) -> str:
    """The printed form of `ErrorBreakdown.result()`."""
    big = breakdown["large_errors"]
    parts = [format_table(breakdown["depth_m"]), format_table(breakdown["image_rows"]),
             format_table(breakdown["confidence"]),
             f"off by more than 25 %: {big['share']:.3f} of the points, {big['share_of_abs_rel']:.3f} of the Abs Rel "
             f"sum, prior nearer than LiDAR on {big['prior_nearer']:.3f} of them"]
    pairs = breakdown["pair_disparity_error_px"]
    if pairs:
        parts.append(format_table([{"pair": p, "median_disp_error_px": v["median"],
                                    "beyond_20m": v["median_beyond_20m"], "n": v["n"]} for p, v in pairs.items()]))
    return "\n\n".join(parts)


__all__ = ["ErrorBreakdown", "breakdown_tables"]
