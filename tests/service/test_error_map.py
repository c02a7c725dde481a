"""How the drivers' newer error classes map to HTTP statuses and codes (service/errors.py)."""

from drivers.errors import (
    MissingDependencyError,
    ReaderCrashError,
    ResourceLimitError,
    UnknownBackendError,
    UnknownFormatError,
)
from service.errors import classify


def test_a_missing_package_is_the_server_s_fault_whatever_registry_raised_it():
    error = MissingDependencyError("the 'e57' scan format needs ...", module="pye57")
    assert classify(error) == (501, "missing_dependency")
    assert classify(UnknownFormatError("unknown scan format 'las'")) == (422, "unknown_format")
    assert classify(UnknownBackendError("unknown robot backend 'kuka'")) == (422, "unknown_backend")


def test_reader_limits_and_crashes_are_invalid_files():
    assert classify(ResourceLimitError("took longer than 1 s", limit="time")) == (
        422,
        "invalid_file",
    )
    assert classify(ReaderCrashError("crashed (SIGSEGV)")) == (422, "invalid_file")
