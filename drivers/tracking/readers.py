"""Trace files, read by format (from the suffix or given): the readers of drivers/tracking."""

from __future__ import annotations

from pathlib import Path

from drivers.errors import UnknownFormatError
from drivers.tracking.canonical_csv import read_trace_csv
from recon.types import Recording

#: Format name -> reader(source, units=..., **options) -> Recording.
TRACE_READERS = {"csv": read_trace_csv}
#: File suffix -> format name.
TRACE_SUFFIXES = {".csv": "csv"}


def read_trace(
    source: str | Path | bytes,
    *,
    name: str | None = None,
    fmt: str | None = None,
    units: str = "m",
    **options,
) -> tuple[Recording, str]:
    """Read a trace in any supported format. Returns (recording, format used).

    Raises
    ------
    UnknownFormatError
        No reader for the format or suffix.
    InputFileError
        The file is wrong for its format.
    """
    label = name or ("upload" if isinstance(source, bytes) else str(source))
    if fmt is None:
        suffix = Path(label).suffix.lower()
        fmt = TRACE_SUFFIXES.get(suffix)
        if fmt is None:
            raise UnknownFormatError(
                f"cannot tell the trace format of {label!r} from its suffix; use one of "
                f"{', '.join(sorted(TRACE_SUFFIXES))} or give the format "
                f"({', '.join(sorted(TRACE_READERS))})"
            )
    reader = TRACE_READERS.get(fmt.lower())
    if reader is None:
        raise UnknownFormatError(
            f"unknown trace format {fmt!r}; use one of {', '.join(sorted(TRACE_READERS))}"
        )
    return reader(source, units=units, name=label, **options), fmt.lower()
