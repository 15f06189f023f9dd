"""JSON helpers for the readers: whole files and streamed top-level arrays, errors as InputError."""

from __future__ import annotations

import gc
import json
import re
from collections.abc import Callable, Iterator
from collections.abc import Set as AbstractSet
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from ..errors import InputError
from ..geometry import vector_norm

QUATERNION_TOL = 1e-3  # |q| must be 1 within this; the rotation uses the normalised q

_SEPARATOR = re.compile(r"\s*,?\s*")
_BOUNDARY = re.compile(r"\}\s*,\s*\{")
_CHUNK = 1 << 23  # characters read per step when streaming a table


@contextmanager
def paused_gc() -> Iterator[None]:
    """Python's cyclic garbage collector off for the block, then as it was.

    Millions of parsed rows are container objects that live on, and each full collection walks all of them:
    a third of loading nuScenes trainval's tables went to collections that found nothing to free (parsed rows
    hold no reference cycles; memory without cycles is freed by reference counting as before). The collector is
    process-wide: cycles that other threads make meanwhile are collected after the block.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def read_json(path: Path) -> Any:
    """A whole JSON file; InputError for a missing file or bad JSON."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except json.JSONDecodeError as exc:
        what = "truncated JSON" if exc.pos >= len(exc.doc.rstrip()) else "bad JSON"
        raise InputError(path, None, f"{what} ({exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, None, f"not UTF-8 text ({exc.reason})") from None


def iter_json_array(
    path: Path, object_pairs_hook: Callable[[list[tuple[str, Any]]], Any] | None = None
) -> Iterator[Any]:
    """Stream the elements of a file holding one JSON array, without holding the whole text.

    `object_pairs_hook` (as in `json.loads`) turns each object into something smaller while it
    is parsed. A truncated file or bad JSON is an InputError naming the element index.
    """
    decoder = json.JSONDecoder(object_pairs_hook=object_pairs_hook)
    with _open_text(path) as f:
        buf = _read(f, path)
        eof = len(buf) < _CHUNK
        pos = _SEPARATOR.match(buf, 0).end()
        while not buf[pos:pos + 1] and not eof:
            more = _read(f, path)
            eof = len(more) < _CHUNK
            buf += more
            pos = _SEPARATOR.match(buf, 0).end()
        if buf[pos:pos + 1] != "[":
            raise InputError(path, None, "bad JSON (expected a top-level array)")
        pos += 1
        index = 0
        while True:
            pos = _SEPARATOR.match(buf, pos).end()
            if pos < len(buf) and buf[pos] == "]":
                if buf[pos + 1:].strip() or (not eof and f.read().strip()):
                    raise InputError(path, None, "bad JSON (extra data after the array)")
                return
            try:
                if pos >= len(buf):
                    raise json.JSONDecodeError("end of buffer", buf, pos)
                value, end = decoder.raw_decode(buf, pos)
            except json.JSONDecodeError as exc:
                if eof:
                    what = "truncated" if not buf.rstrip().endswith("]") else "bad JSON"
                    raise InputError(path, f"element {index}", f"{what} ({exc.msg})") from None
                more = _read(f, path)
                eof = len(more) < _CHUNK
                buf = buf[pos:] + more
                pos = 0
                continue
            pos = end
            index += 1
            yield value


def _open_text(path: Path) -> TextIO:
    """A UTF-8 text file opened for reading; InputError when it does not exist."""
    try:
        return open(path, encoding="utf-8")  # noqa: SIM115 - the caller closes it (with)
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None


def _read(f: TextIO, path: Path) -> str:
    try:
        return f.read(_CHUNK)
    except UnicodeDecodeError as exc:
        raise InputError(path, None, f"not UTF-8 text ({exc.reason})") from None


class _NotFlat(Exception):
    """The fast splitter met something other than flat objects (a nested object, a '{' in a string)."""


def _object_chunks(path: Path) -> Iterator[tuple[str, list[str]]]:
    """(text, elements) of consecutive elements of a top-level array of FLAT objects, each text without its '}'.

    Splits whole chunks at '}' in C, so it is only valid when no element holds a nested object or
    a brace inside a string; a chunk where some '}' is not followed by `, {` (or the counts of
    braces differ) raises `_NotFlat`, so the caller can use the exact parser.
    """
    with _open_text(path) as f:
        buf = _read(f, path)
        eof = len(buf) < _CHUNK
        start = _SEPARATOR.match(buf, 0).end()
        if buf[start:start + 1] != "[":
            raise _NotFlat
        buf = buf[start + 1:]
        index = 0
        while True:
            cut = buf.rfind("}")
            if cut >= 0:
                part, buf = buf[:cut], buf[cut + 1:]
                pieces = part.split("}")
                if part.count("{") != len(pieces) or len(_BOUNDARY.findall(part)) != len(pieces) - 1:
                    raise _NotFlat  # a brace inside a string, or a nested object
                index += len(pieces)
                yield part, pieces
            if eof:
                rest = buf.strip().lstrip(",").strip()
                if rest.startswith("]") and not rest[1:].strip():
                    return
                if rest.startswith("{"):
                    raise InputError(path, f"element {index}", "truncated (the file ends inside it)")
                raise InputError(path, f"element {index}", "truncated or bad JSON (no closing ']')")
            more = _read(f, path)
            eof = len(more) < _CHUNK
            buf += more


# (pattern whose group 1 is a row's value, a set of values, keep rows whose value IS in the set?)
Select = tuple[re.Pattern, AbstractSet[str], bool]


def scan_table(path: Path, reduce: Callable[[dict], Any], select: list[Select] = ()) -> list:
    """`reduce(row)` of every row of a JSON array of objects, keeping the results that are not None.

    Streams the file. `select` names rows that `reduce` would drop, so they are never parsed (such
    rows are checked for structure only): a row is skipped when its text holds `pattern` with a
    value whose membership in the set differs from `keep_if_in`. Falls back to the exact streaming
    parser when the rows are not flat objects.
    """
    out = []
    select = [s for s in select if s[1] or s[2]]  # an empty set whose rows are dropped drops nothing: no scan
    try:
        index = 0
        for part, pieces in _object_chunks(path):
            kept = _selected(part, pieces, select)
            for row in _parse_rows(path, pieces, kept, index):
                result = reduce(row)
                if result is not None:
                    out.append(result)
            index += len(pieces)
        return out
    except _NotFlat:
        pass
    out = []
    for index, row in enumerate(iter_json_array(path)):
        if not isinstance(row, dict):
            raise InputError(path, f"element {index}", "not an object")
        result = reduce(row)
        if result is not None:
            out.append(result)
    return out


def _parse_rows(path: Path, pieces: list[str], kept: list[int], first: int) -> list:
    """Parse the kept pieces of a chunk (`_object_chunks`) in one call; on an error, one by one to name the bad
    element (`first` is the chunk's first element index)."""
    # each piece is its separator (checked by _object_chunks: whitespace, a comma, whitespace) and its object
    # without the '}', so joined at '}' they are the objects and their separators, the first one's to strip
    text = "}".join(pieces) if len(kept) == len(pieces) else "}".join([pieces[i] for i in kept])
    try:
        rows = json.loads("[" + text.lstrip(" \t\r\n,") + "}]") if kept else []
        if len(rows) == len(kept):
            return rows
    except json.JSONDecodeError:
        pass
    rows = []
    for i in kept:
        try:
            rows.append(json.loads(pieces[i][pieces[i].index("{"):] + "}"))
        except json.JSONDecodeError as exc:
            raise InputError(path, f"element {first + i}", f"bad JSON ({exc.msg})") from None
    return rows


def _selected(part: str, pieces: list[str], select: list[Select]) -> list[int]:
    """Indices of the rows of a chunk that pass every selection (rows without the pattern pass)."""
    rows = list(range(len(pieces)))
    for pattern, values, keep_if_in in select:
        if 4 * len(rows) > len(pieces):  # most rows left: one findall over the chunk, if aligned
            found = pattern.findall(part)
            if len(found) == len(pieces):
                rows = [i for i in rows if (found[i] in values) == keep_if_in]
                continue
        rows = [i for i in rows if (m := pattern.search(pieces[i])) is None or (m.group(1) in values) == keep_if_in]
    return rows


# --- field access with errors that name file and key ------------------------------------------
def get(row: dict, key: str, file: Path | str | None, where: str, kinds: type | tuple[type, ...] | None = None,
        alt: str | None = None, default: Any = ...) -> Any:
    """`row[key]` (or `row[alt]`), checked against `kinds`; InputError naming `where.key` otherwise."""
    if key in row:
        value = row[key]
    elif alt is not None and alt in row:
        value = row[alt]
    elif default is not ...:
        return default
    else:
        raise InputError(file, f"{where}.{key}", "missing")
    if kinds is not None:
        bad_bool = isinstance(value, bool) and bool not in (kinds if isinstance(kinds, tuple) else (kinds,))
        if bad_bool or not isinstance(value, kinds):
            raise InputError(file, f"{where}.{key}", f"has the wrong type ({type(value).__name__})")
    return value


def number_list(row: dict, key: str, length: int, file: Path | str | None, where: str) -> np.ndarray:
    """A list of `length` finite numbers as float64; InputError otherwise."""
    value = get(row, key, file, where, list)
    if len(value) != length or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InputError(file, f"{where}.{key}", f"expected {length} numbers")
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(file, f"{where}.{key}", "contains NaN or infinity")
    return arr


def unit_quaternion(q: np.ndarray, file: Path | str | None, where: str, zero_is_identity: bool = False
                    ) -> np.ndarray:
    """q (w, x, y, z) when its length is 1 within QUATERNION_TOL (a zero q as the identity when allowed)."""
    norm = vector_norm(q)
    if norm == 0.0 and zero_is_identity:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if abs(norm - 1.0) > QUATERNION_TOL:
        raise InputError(file, f"{where}.rotation", f"quaternion is not unit length (norm {norm:.6g})")
    return q


__all__ = ["QUATERNION_TOL", "get", "iter_json_array", "number_list", "paused_gc", "read_json", "scan_table",
           "unit_quaternion"]
