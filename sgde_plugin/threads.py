"""Scoped torch thread counts."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

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
