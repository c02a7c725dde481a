"""Named failures of the drivers (files, trackers, scanners, robots).

Like ``recon.errors``, these are mapped one-to-one to HTTP statuses and stable codes by
``service/errors.py``, so each class is part of the public contract.
"""

from __future__ import annotations


class DriverError(Exception):
    """Base class of every failure to talk to the outside world."""


class InputFileError(DriverError):
    """A file that is missing, unreadable, or not what its format promises."""


class UnknownFormatError(DriverError):
    """No reader is registered for the file's suffix or the requested format."""
