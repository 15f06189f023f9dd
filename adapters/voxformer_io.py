"""VoxFormer's packed voxel files: stage-1 occupancy (``.pseudo``) and query proposals (``.query*``).

Both are VoxFormer's ``pack`` of a {0, 1} grid: the [X, Y, Z] array flattened in C order, eight voxels
per byte, the first voxel in the most significant bit (``np.packbits(..., bitorder="big")``), no header.
``.pseudo`` files hold the 256 x 256 x 32 occupancy (``voxels/<frame>.pseudo`` under
``sequences_<depthmodel>_sweep<n>/<sequence>/``); query files the 128 x 128 x 16 proposals of the
query-proposal network (``queries/<frame>.<query_tag>``; the stage-2 dataset globs that tag).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from torch import Tensor

from sgde_plugin.errors import InputError
from sgde_plugin.io import atomic_write_bytes

PSEUDO_SHAPE = (256, 256, 32)
QUERY_SHAPE = (128, 128, 16)
QUERY_TAG = "query_iou5203_pre7712_rec6153"  # the tag of VoxFormer's released configs


def _as_grid(grid: Tensor | np.ndarray, shape: tuple[int, int, int] | None) -> np.ndarray:
    """One [X, Y, Z] grid as a NumPy bool array (CPU, any dtype in); refuses a batch."""
    arr = grid.detach().cpu().numpy() if isinstance(grid, Tensor) else np.asarray(grid)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 3:
        raise ValueError(f"one [X, Y, Z] grid per file, got shape {arr.shape} (write a batch sample by sample)")
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise ValueError(f"grid shape {arr.shape} is not the {shape} that VoxFormer reads")
    if arr.size % 8:
        raise ValueError(f"{arr.size} voxels cannot be packed eight per byte")
    return arr > 0


def pack_voxels(grid: Tensor | np.ndarray) -> bytes:
    """A {0, 1} [X, Y, Z] grid -> VoxFormer's packed bytes (C order, most significant bit first)."""
    return np.packbits(_as_grid(grid, None).reshape(-1), bitorder="big").tobytes()


def unpack_voxels(data: bytes, shape: tuple[int, int, int]) -> np.ndarray:
    """Packed bytes -> uint8 {0, 1} grid of ``shape`` (ValueError when the size does not fit)."""
    n = int(np.prod(shape))
    if len(data) * 8 != n:
        raise ValueError(f"{len(data)} bytes hold {len(data) * 8} voxels, not the {n} of shape {tuple(shape)}")
    return np.unpackbits(np.frombuffer(data, np.uint8), bitorder="big").reshape(shape)


def write_pseudo(path: str | Path, occupancy: Tensor | np.ndarray) -> None:
    """Write a 256 x 256 x 32 occupancy as VoxFormer's ``.pseudo`` file (atomically)."""
    atomic_write_bytes(path, np.packbits(_as_grid(occupancy, PSEUDO_SHAPE).reshape(-1), bitorder="big").tobytes())


def write_query(path: str | Path, proposals: Tensor | np.ndarray) -> None:
    """Write 128 x 128 x 16 query proposals as VoxFormer's query file (atomically)."""
    atomic_write_bytes(path, np.packbits(_as_grid(proposals, QUERY_SHAPE).reshape(-1), bitorder="big").tobytes())


def read_packed(path: str | Path, shape: tuple[int, int, int]) -> np.ndarray:
    """Read a packed VoxFormer file into a uint8 {0, 1} grid; InputError names a file of the wrong size."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, None, f"cannot read: {exc.strerror or exc}") from None
    try:
        return unpack_voxels(data, shape)
    except ValueError as exc:
        raise InputError(path, None, str(exc)) from None


def voxformer_paths(root: str | Path, sequence: str, frame: str, depthmodel: str = "msnet3d", nsweep: int = 10,
                    query_tag: str = QUERY_TAG) -> dict[str, Path]:
    """Where VoxFormer's stage 2 looks for a frame's ``.pseudo`` and query file under ``root`` (``kitti/dataset``)."""
    base = Path(root) / f"sequences_{depthmodel}_sweep{nsweep}" / sequence
    return {"pseudo": base / "voxels" / f"{frame}.pseudo", "query": base / "queries" / f"{frame}.{query_tag}"}
