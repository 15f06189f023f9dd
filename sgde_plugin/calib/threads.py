"""A context manager that runs small torch computations on one thread.

The NumPy faces of the camera models call torch on arrays of a few thousand elements; with several
threads on a busy 2-core machine each call waits on thread hand-offs (measured 20x slower for a
320x180 ray grid), so calibration runs them single-threaded and restores the setting afterwards.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def torch_threads(n: int = 1) -> Iterator[None]:
    """Temporarily set torch's intra-op thread count."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
