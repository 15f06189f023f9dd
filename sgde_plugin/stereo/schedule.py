"""Running a frame's pairs on a thread pool and consuming each camera's results as soon as they are complete.

A frame's pairs differ in cost by 2-3x (SGBM's cost grows with canvas area times search range), and
each camera's map needs only its own two pairs. `run_pairs` starts the costliest pairs first (the
last ones to finish are then short, so the threads end together) and fuses a camera in the calling
thread as soon as its pairs are done, while the pool still works on the others. The results, and
the order in which each camera's values are fused, are those of a sequential run. (Fusing in the
pool instead cost about three times the CPU in a measurement under load, probably fresh pages for the
camera-sized maps in the pool threads' malloc arenas.) `OnDemand` computes per-camera inputs (the grey images) in
the pair thread that first needs them, once, so the pairs start at once.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Executor, Future, as_completed
from typing import TypeVar

P = TypeVar("P")
R = TypeVar("R")
V = TypeVar("V")


def longest_first(costs: Sequence[float]) -> list[int]:
    """Indices ordered by decreasing cost (stable: equal costs keep their order)."""
    return sorted(range(len(costs)), key=lambda i: -costs[i])


def run_pairs(
    items: Sequence[P], work: Callable[[P], R], needs: Mapping[str, Sequence[int]],
    consume: Callable[[str, list[R]], V], pool: Executor | None = None, costs: Sequence[float] | None = None,
) -> tuple[list[R], dict[str, V]]:
    """(`work(item)` for every item in order, {key: `consume(key, [results of needs[key]] in item order)`}).

    With a `pool`, items are submitted costliest first (`costs`) and each key is consumed in the calling
    thread as soon as every item it needs is done; keys are returned in the order of `needs`. Without a
    pool everything runs in order in the calling thread.
    """
    keys = list(needs)
    if pool is None:
        results = [work(item) for item in items]
        return results, {k: consume(k, [results[i] for i in sorted(needs[k])]) for k in keys}
    order = longest_first(costs if costs is not None else [0.0] * len(items))
    futures: dict[Future, int] = {pool.submit(work, items[i]): i for i in order}
    done: dict[int, R] = {}
    consumed: dict[str, V] = {}
    for key in keys:  # keys that need nothing (cameras without a pair)
        if not needs[key]:
            consumed[key] = consume(key, [])
    for fut in as_completed(futures):
        done[futures[fut]] = fut.result()
        for key in keys:
            if key not in consumed and all(i in done for i in needs[key]):
                consumed[key] = consume(key, [done[i] for i in sorted(needs[key])])
    return [done[i] for i in range(len(items))], {k: consumed[k] for k in keys}


class OnDemand(Mapping[str, V]):
    """A mapping whose value for a key is `make(key)`, computed on first access (once, thread-safe)."""

    def __init__(self, keys: Sequence[str], make: Callable[[str], V]):
        self._make = make
        self._locks = {k: threading.Lock() for k in keys}
        self._values: dict[str, V] = {}

    def __getitem__(self, key: str) -> V:
        """The value of `key`, made now if no thread has made it yet."""
        if key not in self._values:
            with self._locks[key]:  # KeyError for an unknown key, as a dict
                if key not in self._values:
                    self._values[key] = self._make(key)
        return self._values[key]

    def __iter__(self) -> Iterator[str]:
        """The keys, made or not."""
        return iter(self._locks)

    def __len__(self) -> int:
        """Number of keys."""
        return len(self._locks)


__all__ = ["OnDemand", "longest_first", "run_pairs"]
