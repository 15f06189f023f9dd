"""Blocks of a rig that a window's observed pairs link, and how a partially linked window is placed.

When the pairs that passed beta do not link every camera (a camera whose overlaps are blocked, two rear cameras
with nothing in common), the adjustment still determines the relative poses inside each group of cameras that
chains of observed pairs link (a block), but nothing the images measure says where one block sits against
another. Partial acceptance (`calibrate(..., partial=True)`, the default) keeps each block's relative poses and
places the block by the least-squares fit of its cameras to the extrinsics the window started from: what the
images do not measure stays as it was, averaged over the block's cameras. A camera alone in its block keeps its
starting extrinsics exactly.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..geometry import make_transform, mean_transform


def linked_blocks(cameras: Sequence[str], observed: Sequence[tuple[str, str]]) -> list[tuple[str, ...]]:
    """Groups of cameras that chains of `observed` pairs link, each in the order of `cameras`, ordered by their
    first camera."""
    nbrs: dict[str, set[str]] = {c: set() for c in cameras}
    for a, b in observed:
        nbrs.setdefault(a, set()).add(b)
        nbrs.setdefault(b, set()).add(a)
    order = list(dict.fromkeys([*cameras, *nbrs]))
    blocks: list[tuple[str, ...]] = []
    seen: set[str] = set()
    for c in order:
        if c in seen:
            continue
        block, stack = {c}, [c]
        while stack:
            for n in nbrs[stack.pop()] - block:
                block.add(n)
                stack.append(n)
        seen |= block
        blocks.append(tuple(n for n in order if n in block))
    return blocks


def between_blocks(pairs: Sequence[tuple[str, str]], blocks: Sequence[Sequence[str]]) -> list[tuple[str, str]]:
    """The pairs whose two cameras lie in different blocks."""
    block_of = {c: k for k, block in enumerate(blocks) for c in block}
    return [(a, b) for a, b in pairs if block_of.get(a) != block_of.get(b)]


def fit_block(adjusted: Mapping[str, np.ndarray], start: Mapping[str, np.ndarray], block: Sequence[str]) -> np.ndarray:
    """The rigid transform C (4, 4), applied on the ego side (C @ sensor_to_ego), that brings a block's adjusted
    extrinsics nearest to its starting ones: the chordal mean of the rotations that map each adjusted orientation
    onto its start, then the mean offset of the camera positions under it."""
    R = mean_transform(np.stack([make_transform(start[m][:3, :3] @ adjusted[m][:3, :3].T, np.zeros(3))
                                 for m in block]))[:3, :3]
    t = np.mean([start[m][:3, 3] - R @ adjusted[m][:3, 3] for m in block], axis=0)
    return make_transform(R, t)


def place_blocks(adjusted: Mapping[str, np.ndarray], start: Mapping[str, np.ndarray],
                 blocks: Sequence[Sequence[str]]) -> dict[str, np.ndarray]:
    """Every block of `adjusted` moved rigidly onto its fit to `start` (`fit_block`); relative poses inside a block
    are kept, a one-camera block gets its start back."""
    out = dict(adjusted)
    for block in blocks:
        if len(block) == 1:
            out[block[0]] = np.array(start[block[0]], dtype=np.float64)
            continue
        C = fit_block(adjusted, start, block)
        out.update({m: C @ adjusted[m] for m in block})
    return out
