"""Running a frame's pairs on a thread pool and consuming each camera's results as soon as they are complete.

A frame's pairs differ in cost by 2-3x (SGBM's cost grows with canvas area times search range), and
each camera's map needs only its own two pairs. `run_pairs` starts the costliest pairs first (the
last ones to finish are then short, so the threads end together) and fuses a camera in the calling
thread as soon as its pairs are done, while the pool still works on the others. The results, and
the order in which each camera's values are fused, are those of a sequential run.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
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


__all__ = ["longest_first", "run_pairs"]
