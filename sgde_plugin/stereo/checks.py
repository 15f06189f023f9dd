"""The checks a matched pair goes through (refinement, left-right, photometric, islands), on the box of its matches.

`check_pair` takes the matcher's left- and right-referenced disparities and confidences over the core
columns of a rectified pair and returns them refined and filtered. Every check is local (windows of at
most 7x7 px, a gradient, a search along the row), so it runs only on the smallest box holding every
pixel that still has a match, grown by `HALO` px and clipped to the core: outside the box the
confidence is 0 whatever the checks say, inside it each value is the one the whole core would give
(the windows of the matched pixels lie inside the box, or meet the core's own edge there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import PriorConfig
from .filters import (
    discontinuity_factor,
    grey_float,
    lr_check,
    photometric_scores,
    refine_disparity,
    remove_islands,
)

HALO = 8  # px around the matched pixels: covers refinement's 5x5 and the photometric 7x7 windows + gradient


@dataclass(frozen=True)
class MatchedPair:
    """A pair's canvases and the matcher's core-column answers, both references (the right one un-mirrored)."""

    left: np.ndarray  # whole rectified canvases as matched (uint8)
    right: np.ndarray
    x0: int  # first core column of the canvas
    disp_l: np.ndarray  # (H, Wc) core columns
    conf_l: np.ndarray
    disp_r: np.ndarray
    conf_r: np.ndarray


def match_box(*confs: np.ndarray, halo: int = HALO) -> tuple[slice, slice] | None:
    """(rows, cols) of the box holding every pixel with confidence > 0 in any of `confs`, grown by `halo`
    and clipped to the maps; None if there is none."""
    ok = confs[0] > 0
    for conf in confs[1:]:
        ok = ok | (conf > 0)
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    if rows.size == 0:
        return None
    h, w = ok.shape
    return (slice(max(0, rows[0] - halo), min(h, rows[-1] + 1 + halo)),
            slice(max(0, cols[0] - halo), min(w, cols[-1] + 1 + halo)))


def hull(*boxes: tuple[slice, slice] | None) -> tuple[slice, slice] | None:
    """The smallest box holding every box given (`match_box` boxes; None = empty); None if all are empty."""
    given = [b for b in boxes if b is not None]
    if not given:
        return None
    return (slice(min(b[0].start for b in given), max(b[0].stop for b in given)),
            slice(min(b[1].start for b in given), max(b[1].stop for b in given)))


def check_pair(m: MatchedPair, config: PriorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Refined and checked (disp_l, conf_l, disp_r, conf_r) over the core columns; confidence 0 = rejected.

    Refinement and the photometric checks of each reference run on the box of its own matches, the
    left-right check on the box of both. Outside its box a disparity is 0 when refinement is on (as
    refinement leaves it) and the matcher's otherwise.
    """
    cfg = config
    boxes = (match_box(m.conf_l), match_box(m.conf_r))
    both = hull(*boxes)  # = match_box(m.conf_l, m.conf_r): the box of a union holds the boxes of its parts
    if both is None:
        return m.disp_l.copy(), np.zeros_like(m.conf_l), m.disp_r.copy(), np.zeros_like(m.conf_r)
    rows = both[0]  # the canvases' rows that any box needs, as float32 grey
    canvases = (grey_float(m.left[rows]), grey_float(m.right[rows]))
    sides = ((m.disp_l, m.conf_l, -1), (m.disp_r, m.conf_r, +1))
    disps = []
    for k, (disp, conf, sign) in enumerate(sides):
        if cfg.filters.refine_iterations <= 0:
            disps.append(disp)
            continue
        out = np.zeros_like(disp)
        box = boxes[k]
        if box is not None:
            a, b, x0, (d, c) = _box_view(canvases[k], canvases[1 - k], m.x0, box, rows.start, disp, conf)
            out[box] = refine_disparity(a, b, d, c > 0, sign, x0, cfg.filters.refine_iterations)
        disps.append(out)
    confs = [np.zeros_like(m.conf_l), np.zeros_like(m.conf_r)]
    dl, cl, dr, cr = (x[both] for x in (disps[0], m.conf_l, disps[1], m.conf_r))
    confs[0][both] = lr_check(dl, cl, dr, cr, -1, cfg.filters.lr_max_diff)
    confs[1][both] = lr_check(dr, cr, dl, cl, +1, cfg.filters.lr_max_diff)
    for k, (_, _, sign) in enumerate(sides):
        box = boxes[k]
        if box is not None:
            a, b, x0, (d, c) = _box_view(canvases[k], canvases[1 - k], m.x0, box, rows.start, disps[k], confs[k])
            _photometric(a, b, x0, d, c, sign, cfg, (box[0].start, box[1].start))  # c: a view, scaled in place
    return disps[0], confs[0], disps[1], confs[1]


def _box_view(
    own: np.ndarray, other: np.ndarray, x0: int, box: tuple[slice, slice], row0: int, *maps: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int, list[np.ndarray]]:
    """(reference pixels of the box, the other canvas' rows of the box (whole width), the box's first canvas
    column, `maps` cut to the box); `own` and `other` hold canvas rows from `row0` on."""
    rows, cols = box
    local = slice(rows.start - row0, rows.stop - row0)
    x = x0 + cols.start
    return own[local, x : x + cols.stop - cols.start], other[local], x, [mp[box] for mp in maps]


def _photometric(
    a: np.ndarray, b: np.ndarray, x0: int, disp: np.ndarray, conf: np.ndarray, sign: int, config: PriorConfig,
    origin: tuple[int, int] = (0, 0),
) -> None:
    """Scale `conf` in place by the photometric checks after the per-pixel shift (they catch consistent but
    wrong matches, e.g. of points whose true match has left the other image), the small-disparity factor,
    the optional discontinuity factor, and drop small islands."""
    cfg = config
    t, mad_max = cfg.filters.min_zncc, cfg.filters.max_abs_diff
    ncc, mad, texture = photometric_scores(a, b, disp, conf > 0, sign, x0, origin=origin)
    conf *= np.clip((ncc - t) / (1 - t), 0, 1) * np.clip(1 - mad / mad_max, 0, 1)
    if cfg.filters.min_texture > 0:  # rows without x-structure are ambiguous
        conf *= np.clip(texture / cfg.filters.min_texture - 1, 0, 1)
    conf *= disp / (disp + cfg.confidence.disparity_px)  # small disparities give uncertain depth
    if cfg.confidence.edge_jump_px > 0:
        conf *= discontinuity_factor(disp, conf > 0, cfg.confidence.edge_jump_px)
    remove_islands(disp, conf, cfg.filters.min_region_px)  # isolated islands are mostly wrong matches


__all__ = ["HALO", "MatchedPair", "check_pair", "hull", "match_box"]
