"""File helpers: atomic writes, depth PNGs (KITTI convention), images and their sizes."""

from __future__ import annotations

import io
import os
import struct
import tempfile
import warnings
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from .errors import InputError

DEPTH_PNG_SCALE = 256.0
DEPTH_PNG_PROBLEM = "not a single-channel uint16 depth PNG"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def is_plain_name(name: str) -> bool:
    """True for a name usable as one file name: not empty, not '.' or '..', no path separator, no control
    character, no surrounding spaces, at most 200 characters."""
    return (
        isinstance(name, str) and 0 < len(name) <= 200 and name not in (".", "..") and name == name.strip()
        and not any(c in "/\\" or not c.isprintable() for c in name)
    )


def _temp_sibling(path: Path) -> Path:
    """A new empty file next to `path` (its folder created); InputError when `path` cannot be written there."""
    if path.is_dir():
        raise InputError(path, None, "is a folder; expected a file path")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    except OSError as exc:
        raise InputError(path, None, f"cannot write ({exc.strerror or exc})") from None
    os.close(fd)
    return Path(tmp)


def check_writable(path: str | Path | None) -> None:
    """Raise now the InputError a later write of `path` would raise (for commands that work long before they
    write); `path` itself is not touched. None: nothing to check."""
    if path is not None:
        _temp_sibling(Path(path)).unlink()


def make_folder(path: str | Path) -> Path:
    """Create the output folder `path` with its parents (it may exist); InputError naming it when it cannot be."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, None, "exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(path, None, f"cannot create the folder ({exc.strerror or exc})") from None
    return path


@contextmanager
def output_folder(path: str | Path) -> Iterator[Path]:
    """`make_folder` for a block that fills it: a folder the block created is removed again when the block
    fails before writing anything into it (no empty output left behind a one-line error)."""
    path = Path(path)
    existed = path.exists()
    folder = make_folder(path)
    try:
        yield folder
    except BaseException:
        if not existed and not any(folder.iterdir()):
            folder.rmdir()
        raise


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path; rename it onto `path` only if the block succeeds. A path that
    cannot be written (a folder, a read-only file system, a parent that is a file) is an InputError."""
    path = Path(path)
    tmp_path = _temp_sibling(path)
    # mkstemp creates 0600; give the file the mode a plain open() would
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as exc:  # a full disk, say: nothing half-written is left behind
        raise InputError(path, None, f"cannot write ({exc.strerror or exc})") from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write bytes to `path` through a temporary name and a rename."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write text (UTF-8) to `path` through a temporary name and a rename."""
    atomic_write_bytes(path, text.encode("utf-8"))


def encode_png(array: np.ndarray) -> bytes:
    """PNG bytes of a uint8 (HxW or HxWx3 RGB) or uint16 (HxW) array."""
    if array.ndim == 3:
        array = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", array)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write an 8-bit RGB (or grey) image atomically; format from the suffix (.png or .jpg)."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        atomic_write_bytes(path, encode_png(rgb))
        return
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(path.suffix, bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise RuntimeError(f"encoding {path} failed")
    atomic_write_bytes(path, buf.tobytes())


def _read_file(path: str | Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise InputError(path, None, f"cannot read ({exc.strerror or exc})") from None


def check_complete(data: bytes, path: str | Path) -> None:
    """InputError when PNG or JPEG bytes are cut short (no IEND chunk / no end-of-image marker) or a PNG
    chunk fails its CRC, which decoders would otherwise fill with grey or report only on stderr."""
    if data[:8] == PNG_SIGNATURE:
        if b"IEND" not in data[-32:]:
            raise InputError(path, None, "truncated PNG (no IEND chunk)")
        _check_png_chunks(data, path)
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-1024:]:
        raise InputError(path, None, "truncated JPEG (no end-of-image marker)")


def _check_png_chunks(data: bytes, path: str | Path) -> None:
    """Every PNG chunk's CRC-32 (type + data) must match the one stored after it."""
    pos = 8
    while pos + 12 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        end = pos + 8 + length
        if end + 4 > len(data):
            raise InputError(path, None, "truncated PNG (a chunk runs past the end)")
        (crc,) = struct.unpack(">I", data[end : end + 4])
        if zlib.crc32(data[pos + 4 : end]) != crc:
            kind = data[pos + 4 : pos + 8].decode("latin-1")
            raise InputError(path, None, f"corrupted PNG ({kind} chunk at byte {pos} fails its CRC)")
        pos = end + 4


def _decode(path: str | Path, flags: int) -> np.ndarray | None:
    """OpenCV decode of a complete file (a truncated one is refused before the decoder sees it)."""
    data = _read_file(path)
    check_complete(data, path)
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8-bit colour image as HxWx3 RGB uint8; InputError if unreadable or truncated."""
    img = _decode(path, cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(path, None, "cannot read image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_check(path: str | Path) -> None:
    """Decode an image file completely (not only its header); InputError naming the file when it is
    truncated or corrupted. Uses Pillow, which reports problems as exceptions, not on stderr."""
    data = _read_file(path)
    check_complete(data, path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with Image.open(io.BytesIO(data)) as im:
                im.load()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
        raise InputError(path, None, f"cannot decode image ({first})") from None


def depth_to_png_array(depth_m: np.ndarray) -> np.ndarray:
    """Metres -> uint16 depth-PNG values (round(d * 256), 0 = no value, clipped at 255.99 m)."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    d = np.where(d > 0, d, 0.0)
    return np.clip(np.round(d * DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)


def write_depth_png(path: str | Path, depth_m: np.ndarray) -> None:
    """Write metric depth as a KITTI-convention uint16 PNG, atomically."""
    atomic_write_bytes(path, encode_png(depth_to_png_array(depth_m)))


def read_depth_png(path: str | Path) -> np.ndarray:
    """Read a KITTI-convention depth PNG to float32 metres (0 = no value)."""
    raw = _decode(path, cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
        raise InputError(path, None, DEPTH_PNG_PROBLEM)
    return raw.astype(np.float32) / DEPTH_PNG_SCALE


def read_mask(path: str | Path) -> np.ndarray:
    """Read a static mask PNG as bool HxW (True = use, 0 in the file = ignore)."""
    raw = _decode(path, cv2.IMREAD_GRAYSCALE)
    if raw is None:
        raise InputError(path, None, "cannot read mask")
    return raw > 0


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG from its header, without decoding the pixels."""
    return image_header(path)[:2]


def image_header(path: str | Path) -> tuple[int, int, int, int | None]:
    """(width, height, bits per channel, PNG colour type; None for a JPEG, taken as 8-bit) of a PNG or JPEG from
    its header, without decoding the pixels."""
    path = Path(path)
    try:
        return _header(path)
    except OSError as exc:  # a folder where an image belongs, no permission, ...
        raise InputError(path, None, f"cannot read ({exc.strerror or exc})") from None
    except struct.error:  # cut short inside the header
        raise InputError(path, None, "not a readable PNG or JPEG image (header cut short)") from None


def check_pixel_format(path: str | Path, header: tuple[int, int, int, int | None], depth: bool = False) -> None:
    """InputError unless an `image_header` holds what a rig folder asks for (sgde-rig/1): a colour image of 8
    bits per channel, or with `depth` a single-channel 16-bit PNG."""
    _, _, bits, colour_type = header
    if depth and (bits, colour_type) != (16, 0):
        raise InputError(path, None, DEPTH_PNG_PROBLEM)
    if not depth and bits > 8:
        raise InputError(path, None, f"not an 8-bit colour image ({bits} bits per channel)")


def _header(path: Path) -> tuple[int, int, int, int | None]:
    with open(path, "rb") as f:
        head = f.read(32)
        if head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
            w, h, bits, colour_type = struct.unpack(">IIBB", head[16:26])
            return int(w), int(h), int(bits), int(colour_type)
        if head[:2] == b"\xff\xd8":
            f.seek(2)
            while True:
                marker = f.read(2)
                if len(marker) < 2 or marker[0] != 0xFF:
                    break
                if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
                    continue
                (length,) = struct.unpack(">H", f.read(2))
                if 0xC0 <= marker[1] <= 0xCF and marker[1] not in (0xC4, 0xC8, 0xCC):
                    _, h, w = struct.unpack(">BHH", f.read(5))
                    return int(w), int(h), 8, None
                f.seek(length - 2, os.SEEK_CUR)
    raise InputError(path, None, "not a readable PNG or JPEG image")
