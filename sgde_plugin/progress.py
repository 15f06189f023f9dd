"""Progress bars that show on a terminal and stay quiet in logs."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, enabled: bool | None = None) -> tqdm:
    """Wrap an iterable in a tqdm bar that is shown only when stderr is a terminal."""
    show = sys.stderr.isatty() if enabled is None else enabled
    return tqdm(iterable, desc=desc, total=total, disable=not show, leave=False, dynamic_ncols=True)
