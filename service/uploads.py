"""Uploads as they arrive: a bounded, harmless name, and a cap on the bytes in flight.

A client names its file as it likes: 300 characters, 200 ``é`` (400 bytes, past the 255 a file
system allows in a name), path separators, NUL, or nothing. The name is kept for messages and
for the artifact's ``source_name``, so it is cleaned first (:func:`clean_filename`: the last path
component, no control characters, at most :data:`MAX_NAME_CHARS`, its suffix kept since it tells
the format), and the copy of the bytes kept on disk gets an ASCII version of it
(:func:`storage_name`).

Every upload is held in this process while it is parsed and stored (the bytes, and their copy to
the parse's worker). :class:`UploadBudget` counts the bytes of the uploads in flight and refuses
one that would take them past ``max_uploads_in_flight_mb`` with a 503 and ``Retry-After``, before
its bytes are read into memory.
"""

from __future__ import annotations

import contextlib
import threading
import unicodedata
from collections.abc import Iterator
from pathlib import PurePosixPath

from service.errors import ApiError

#: Longest name kept, characters: every real file name fits, and it stays well under the
#: database column (300) and the 255 bytes a file system allows (as ASCII on disk).
MAX_NAME_CHARS = 120
#: Longest suffix kept whole when a name is shortened (".rgbd.json" is the longest we read).
MAX_SUFFIX_CHARS = 16
#: The name of an upload that came without a usable one.
DEFAULT_NAME = "upload"
#: Seconds a client is told to wait before retrying when the uploads in flight are at their cap:
#: about what parsing an upload of typical size takes.
RETRY_AFTER_S = 5


def clean_filename(raw: str | None) -> str:
    """The name an upload is known by: bounded and harmless, its suffix kept.

    Parameters
    ----------
    raw : str or None
        The file name the client sent.

    Returns
    -------
    str
        Its last path component (``/`` or ``\\``), Unicode-normalised (NFC), without control
        characters (NUL, line breaks) or surrounding blanks, at most :data:`MAX_NAME_CHARS`
        characters (shortened in its stem); :data:`DEFAULT_NAME` if nothing is left.
    """
    name = unicodedata.normalize("NFC", raw or "")
    name = name.replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(c for c in name if unicodedata.category(c)[0] != "C").strip()
    if name in ("", ".", ".."):
        return DEFAULT_NAME
    return _shortened(name, MAX_NAME_CHARS)


def storage_name(name: str) -> str:
    """An ASCII file name for the kept bytes of an upload named ``name`` (see
    :func:`clean_filename`): other characters become ``_``; :data:`DEFAULT_NAME` if none is
    left."""
    safe = "".join(c if c.isascii() and (c.isalnum() or c in "._-") else "_" for c in name)
    if safe.strip("._") == "":
        return DEFAULT_NAME
    return _shortened(safe, MAX_NAME_CHARS)


def _shortened(name: str, limit: int) -> str:
    if len(name) <= limit:
        return name
    path = PurePosixPath(name)
    suffix = "".join(path.suffixes[-2:])
    if len(suffix) > MAX_SUFFIX_CHARS:
        suffix = path.suffix if len(path.suffix) <= MAX_SUFFIX_CHARS else ""
    return name[: limit - len(suffix)] + suffix


class UploadBudget:
    """The bytes of uploads in flight, and the cap they may not pass.

    Parameters
    ----------
    cap_mb : float
        ``max_uploads_in_flight_mb``.
    """

    def __init__(self, cap_mb: float) -> None:
        self.cap_mb = cap_mb
        self._cap = int(cap_mb * 2**20)
        self._held = 0
        self._lock = threading.Lock()

    @property
    def held_bytes(self) -> int:
        """Bytes of the uploads in flight now."""
        with self._lock:
            return self._held

    @contextlib.contextmanager
    def hold(self, size: int) -> Iterator[None]:
        """Count ``size`` bytes as in flight for the duration of the block.

        Raises
        ------
        ApiError
            503 ``uploads_busy`` with ``Retry-After``, if they would pass the cap.
        """
        with self._lock:
            if self._held + size > self._cap:
                held = self._held
                raise ApiError(
                    503,
                    "uploads_busy",
                    f"the server is handling {held / 2**20:.1f} MB of uploads already, and this "
                    f"one ({size / 2**20:.1f} MB) would take them past the limit of "
                    f"{self.cap_mb:g} MB (TEACHPATH_MAX_UPLOADS_IN_FLIGHT_MB); retry in "
                    f"{RETRY_AFTER_S} s",
                    detail={"in_flight_bytes": held, "limit_bytes": self._cap},
                    headers={"Retry-After": str(RETRY_AFTER_S)},
                )
            self._held += size
        try:
            yield
        finally:
            with self._lock:
                self._held -= size
