"""The writer lock of a prior cache: one build at a time writes into a cache folder.

On a local folder the lock is `flock` on the cache folder itself (nothing is added to the folder);
the kernel releases it when the holder exits, even by kill -9, so a stale lock never blocks a
resume. Object stores (s3://, gs://, memory://...) have no lock: there, run one build per cache at
a time; every frame write still re-checks the scene's fingerprint, so a build never writes into a
scene that another build (re)created with other inputs.
"""

from __future__ import annotations

import fcntl
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager

from ..errors import InputError
from .backends import Location, local_path, location_name


@contextmanager
def writer_lock(location: Location, wait_s: float = 0.0) -> Iterator[bool]:
    """Hold the cache's writer lock for the block (yields True), or yield False where there is no lock
    (object stores). Waits up to `wait_s` seconds for another writer, then refuses with InputError."""
    path = local_path(location)
    if path is None:
        yield False
        return
    if path.exists() and not path.is_dir():
        raise InputError(path, None, "exists and is not a folder (a prior cache is a folder)")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise InputError(path, None, f"cannot create or open the cache folder ({exc.strerror or exc})") from None
    try:
        deadline = time.monotonic() + max(0.0, float(wait_s))
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise InputError(
                        location_name(location), None,
                        "another build is writing this cache (its writer lock is held): wait for it to end "
                        "or build into another --out",
                    ) from None
                time.sleep(0.1)
        yield True
    finally:
        os.close(fd)  # releases the lock


__all__ = ["writer_lock"]
