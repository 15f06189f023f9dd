"""Scoped torch, OpenCV and BLAS thread counts."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import cv2
import torch
from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def _scoped(get: Callable[[], int], set_: Callable[[int], None], n: int) -> Iterator[None]:
    """Run a block with a library's thread count `n` (set only when it differs), then restore the previous one."""
    old = get()
    if old != n:
        set_(n)
    try:
        yield
    finally:
        if old != n:
            set_(old)


def torch_threads(n: int = 1) -> contextlib.AbstractContextManager[None]:
    """Run a block with `n` torch intra-op threads, then restore the previous count.

    The camera maths and the renderer are many medium-sized element-wise ops: threads gain little,
    and on a busy machine (or beside other worker processes) OpenMP threads spinning for each op
    can make them tens of times slower.
    """
    return _scoped(torch.get_num_threads, torch.set_num_threads, n)


def opencv_threads(n: int = 1) -> contextlib.AbstractContextManager[None]:
    """Run a block with OpenCV's thread count set to `n`, then restore the previous count.

    For work that is already spread over threads of its own: each OpenCV call then runs in its calling
    thread instead of handing stripes to OpenCV's pool (whose workers wait for the next call spinning,
    and whose stripes meet at a barrier). Results do not depend on it.
    """
    return _scoped(cv2.getNumThreads, cv2.setNumThreads, n)


def blas_threads(n: int = 1) -> contextlib.AbstractContextManager:
    """Run a block with the BLAS libraries (numpy's and scipy's OpenBLAS) at `n` threads, then restore them.

    For numpy work on small matrices or already spread over threads of its own (the adjustment: about 100
    unknowns), where BLAS threads spinning per call cost more than they gain; a fixed count also keeps
    results independent of the machine's core count (the summation order of a product depends on it). The count
    is the libraries' own, so it holds for the whole process while the block runs."""
    return threadpool_limits(n, user_api="blas")
