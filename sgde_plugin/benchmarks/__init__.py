"""Benchmarks run by `sgde bench`; each module exposes `run(fast: bool) -> dict`."""
