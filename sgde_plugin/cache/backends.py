"""Where a prior cache lives: local folders, fsspec URLs or zarr stores; opening them and raw key access."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zarr
import zarr.storage
from zarr.abc.store import Store
from zarr.core.buffer import default_buffer_prototype
from zarr.core.sync import sync

from ..errors import InputError

Location = str | Path | Store  # a local folder, an fsspec URL (memory://, s3://, ...) or an open zarr store


def is_url(location: Location) -> bool:
    """True for fsspec URLs such as memory://..., s3://..., gs://..."""
    return isinstance(location, str) and "://" in location and not location.startswith("file://")


def location_name(location: Location) -> str:
    """The cache location as shown to the user."""
    return str(location) if not isinstance(location, Store) else repr(location)


def local_path(location: Location) -> Path | None:
    """The folder of a local cache (None for URLs and zarr stores)."""
    if isinstance(location, Store) or is_url(location):
        return None
    return Path(str(location).removeprefix("file://"))


def open_store(location: Location, read_only: bool, storage_options: Mapping[str, Any] | None = None) -> Store:
    """A zarr store for a local folder, an fsspec URL or an existing zarr Store; InputError for a location
    that cannot hold a cache (an unknown URL protocol, a file, a missing folder when reading)."""
    if isinstance(location, Store):
        return location.with_read_only(read_only) if location.read_only != read_only else location
    if is_url(location):
        try:
            return zarr.storage.FsspecStore.from_url(
                location, read_only=read_only, storage_options=dict(storage_options or {})
            )
        except (ValueError, ImportError, OSError, TypeError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise InputError(location, None, f"unsupported cache location ({first})") from None
    path = local_path(location)
    assert path is not None
    if path.exists() and not path.is_dir():
        raise InputError(path, None, "exists and is not a folder (a prior cache is a folder)")
    if read_only and not path.exists():
        raise InputError(path, None, "prior cache does not exist")
    return zarr.storage.LocalStore(path, read_only=read_only)


def open_root(store: Store, location: Location, mode: str) -> zarr.Group:
    """The cache's root group; InputError when the location is not a zarr v3 group."""
    try:
        root = zarr.open_group(store, mode=mode, zarr_format=3)
    except (FileNotFoundError, KeyError, ValueError, TypeError, zarr.errors.GroupNotFoundError) as exc:
        raise InputError(location_name(location), "zarr.json", f"not a prior cache ({type(exc).__name__})") from None
    return root


def store_keys(location: Location, storage_options: Mapping[str, Any] | None = None) -> dict[str, int]:
    """Every key of the store with its size in bytes."""
    store = open_store(location, read_only=True, storage_options=storage_options)

    async def _collect() -> dict[str, int]:
        out = {}
        async for key in store.list():
            out[key] = await store.getsize(key)
        return out

    return sync(_collect())


def list_prefix(store: Store, prefix: str) -> set[str]:
    """The keys of a store under `prefix` (e.g. every shard of one array)."""

    async def _collect() -> set[str]:
        return {key async for key in store.list_prefix(prefix)}

    return sync(_collect())


def get_bytes(store: Store, key: str) -> bytes | None:
    """Raw bytes of one key of an open store (None when absent)."""
    buf = sync(store.get(key, prototype=default_buffer_prototype()))
    return None if buf is None else buf.to_bytes()


def read_key(location: Location, key: str, storage_options: Mapping[str, Any] | None = None) -> bytes | None:
    """Raw bytes of one store key (None when absent)."""
    return get_bytes(open_store(location, read_only=True, storage_options=storage_options), key)


__all__ = [
    "get_bytes",
    "is_url",
    "list_prefix",
    "local_path",
    "location_name",
    "open_root",
    "open_store",
    "read_key",
    "store_keys",
]
