"""Scoped torch and OpenCV thread counts."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import cv2
import torch


@contextlib.contextmanager
def torch_threads(n: int = 1) -> Iterator[None]:
    """Run a block with `n` torch intra-op threads, then restore the previous count.

    The camera maths and the renderer are many medium-sized element-wise ops: threads gain little,
    and on a busy machine (or beside other worker processes) OpenMP threads spinning for each op
    can make them tens of times slower.
    """
    old = torch.get_num_threads()
    if old != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if old != n:
            torch.set_num_threads(old)


@contextlib.contextmanager
def opencv_threads(n: int = 1) -> Iterator[None]:
    """Run a block with OpenCV's thread count set to `n`, then restore the previous count.

    For work that is already spread over threads of its own: each OpenCV call then runs in its calling
    thread instead of handing stripes to OpenCV's pool (whose workers wait for the next call spinning,
    and whose stripes meet at a barrier). Results do not depend on it.
    """
    old = cv2.getNumThreads()
    if old != n:
        cv2.setNumThreads(n)
    try:
        yield
    finally:
        if old != n:
            cv2.setNumThreads(old)
