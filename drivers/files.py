"""Writing files so that a reader never sees half of one."""

from __future__ import annotations

import contextlib
import csv
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from drivers.errors import InputFileError


@contextlib.contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """A temporary path next to ``target`` that replaces it only if the block succeeds.

    The file is fsynced before the rename (and the directory after it), so after a crash the
    target holds either its old content or the complete new one, never a partial file; on an
    exception the temporary file is removed and the target is untouched.

    Parameters
    ----------
    target : path
        The final file. Its folder must exist.

    Yields
    ------
    Path
        Where to write. It keeps the target's suffix, for writers that pick a format by it.
    """
    target = Path(target)
    folder = target.parent if str(target.parent) else Path(".")
    handle, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=target.suffix, dir=folder)
    os.close(handle)
    tmp = Path(tmp_name)
    # mkstemp makes the file private (0600); give it the mode a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        with tmp.open("rb+") as written:
            os.fsync(written.fileno())
        os.replace(tmp, target)
        with contextlib.suppress(OSError):  # not every file system lets a folder be fsynced
            dir_fd = os.open(folder, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def csv_rows(lines: Iterable[str], label: str) -> list[list[str]]:
    """Every row of CSV text (``lines``: a text stream or a list of lines).

    Raises
    ------
    InputFileError
        Text the csv module cannot parse (a carriage return inside an unquoted field, a field
        past its size limit): the message names the line.
    """
    reader = csv.reader(lines)
    try:
        return list(reader)
    except csv.Error as exc:
        raise InputFileError(
            f"{label} is not a CSV file that can be parsed (line {reader.line_num}: {exc}); "
            "export it again, or save it as plain CSV"
        ) from None
