"""Helpers shared by the scan readers: silencing native libraries and checking image files.

Open3D, libe57 and librealsense report failures as console messages rather than exceptions and
return empty or half-filled results. The readers therefore check files before handing them over
and judge what comes back; the helpers here do the parts every reader needs.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.errors import InputFileError, clipped

_NATIVE_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def captured_native_stderr() -> Iterator[list[str]]:
    """Collect what native code writes to file descriptor 2 while the block runs.

    Yields a list that receives the captured text when the block ends. Held under a lock and
    only around one file read, so other threads lose at most a few milliseconds of stderr.
    """
    captured: list[str] = []
    with _NATIVE_STDERR_LOCK, tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        try:
            os.dup2(sink.fileno(), 2)
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            captured.append(sink.read().decode("utf-8", errors="replace").strip())


#: The colour codes Open3D puts around its error messages.
_ANSI_ESCAPE = re.compile(r"\x1b\[[0-9;]*m")


def open3d_message(error: Exception, limit: int = 200) -> str:
    """An exception Open3D raised, as one line of plain text for a message (no colour codes,
    no line breaks, at most ``limit`` characters)."""
    return clipped(" ".join(_ANSI_ESCAPE.sub("", str(error)).split()), limit)


def quiet_open3d() -> Any:
    """Open3D at Error verbosity: its warnings would reach the terminal, not the caller."""
    import open3d as o3d  # here, not at the top: importing it takes 0.9 s

    return o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: PNG colour type -> channels (greyscale, RGB, palette, grey + alpha, RGBA).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


@dataclass(frozen=True)
class ImageInfo:
    """What an image file's header promises.

    Attributes
    ----------
    kind : {"png", "jpeg"}
    width, height : int or None
        Pixels (None for JPEG, whose size is only known after decoding).
    bit_depth : int
        Bits per channel.
    channels : int or None
    """

    kind: str
    width: int | None
    height: int | None
    bit_depth: int
    channels: int | None


def check_image_file(path: Path, label: str) -> ImageInfo:
    """Check that ``path`` is a complete PNG or JPEG file and return its header.

    Open3D reads a truncated PNG as a full-size image with made-up rows and says so only on the
    console, so the PNG's chunk structure and CRCs are walked here (cheap next to decoding), and a
    JPEG must end with its end-of-image marker.

    Raises
    ------
    InputFileError
        Missing, empty, truncated or corrupt file, or neither PNG nor JPEG.
    """
    if not path.is_file():
        raise InputFileError(f"{label} does not exist or is not a file")
    data = path.read_bytes()
    if not data:
        raise InputFileError(f"{label} is empty")
    if data.startswith(_PNG_SIGNATURE):
        return _check_png(data, label)
    if data.startswith(b"\xff\xd8"):
        # Some encoders pad after the end-of-image marker; a truncated file has none.
        if b"\xff\xd9" not in data[-64:]:
            raise InputFileError(f"{label} is a truncated JPEG (no end-of-image marker)")
        return ImageInfo("jpeg", None, None, 8, None)
    raise InputFileError(f"{label} is neither a PNG nor a JPEG image")


def _check_png(data: bytes, label: str) -> ImageInfo:
    position = len(_PNG_SIGNATURE)
    header: tuple[int, ...] | None = None
    while True:
        if position + 8 > len(data):
            raise InputFileError(f"{label} is a truncated PNG (it ends before its last chunk)")
        length, kind = struct.unpack(">I4s", data[position : position + 8])
        end = position + 12 + length
        if end > len(data):
            raise InputFileError(f"{label} is a truncated PNG (a chunk runs past its end)")
        body = data[position + 8 : position + 8 + length]
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(kind + body) != crc:
            raise InputFileError(
                f"{label} is a corrupt PNG (checksum of its {kind.decode('latin-1')} chunk "
                "does not match)"
            )
        if kind == b"IHDR":
            if length != 13:  # the PNG specification fixes IHDR at 13 bytes
                raise InputFileError(
                    f"{label} is a corrupt PNG (its IHDR header chunk has {length} bytes, not 13)"
                )
            header = struct.unpack(">IIBB", body[:10])
        if kind == b"IEND":
            break
        position = end
    if header is None:
        raise InputFileError(f"{label} is a corrupt PNG (no IHDR header chunk)")
    width, height, bit_depth, colour_type = header
    return ImageInfo("png", width, height, bit_depth, _PNG_CHANNELS.get(colour_type))


def read_image(path: Path, label: str) -> Any:
    """Read a checked PNG or JPEG with Open3D (an ``open3d.geometry.Image``), refusing the empty
    image it returns on failure."""
    import open3d as o3d

    check_image_file(path, label)
    with captured_native_stderr() as native, quiet_open3d():
        image = o3d.io.read_image(Path(path))
    detail = " ".join(native[0].split()) if native and native[0] else ""
    if image.is_empty():
        raise InputFileError(
            f"{label} could not be read as an image" + (f" ({detail})" if detail else "")
        )
    if detail:  # libpng / libjpeg complained: what was returned may be padded
        raise InputFileError(f"{label} could not be read cleanly: {detail}")
    return image
