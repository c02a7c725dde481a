"""Functions the isolation and worker tests run in child processes (importable by name there)."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError, UnknownRigidBodyError
from recon.errors import DegenerateInputError


def arrays(seed: int) -> dict:
    """Arrays of several kinds, reproducible from ``seed``, and a few plain values."""
    rng = np.random.default_rng(seed)
    return {
        "float64": rng.normal(size=(4, 3)),
        "float32_fortran": np.asfortranarray(rng.normal(size=(5, 2)).astype(np.float32)),
        "int16": rng.integers(-500, 500, size=7).astype(np.int16),
        "uint16_image": rng.integers(0, 65535, size=(3, 4, 5)).astype(np.uint16),
        "bool": rng.random(6) > 0.5,
        "nan_inf": np.array([np.nan, np.inf, -np.inf, 0.0]),
        "empty": np.zeros((0, 3)),
        "labels": np.array(["tip", "tail", "Pen:Marker1"]),
        "count": 42,
        "unit": "mm",
    }


def nothing() -> None:
    return None


def zeros(n_bytes: int) -> dict:
    return {"zeros": np.zeros(n_bytes, dtype=np.uint8)}


def scaled(values, *, factor: float) -> dict:
    return {"values": np.asarray(values) * factor}


def raise_input_file_error(message: str) -> None:
    raise InputFileError(message)


def raise_unknown_rigid_body(message: str) -> None:
    raise UnknownRigidBodyError(message)


def raise_degenerate_input(message: str) -> None:
    raise DegenerateInputError(message)


def raise_value_error(message: str) -> None:
    raise ValueError(message)


def raise_key_error() -> None:
    raise KeyError("frames")


def import_missing_module() -> None:
    import teachpath_test_module_that_is_not_installed  # noqa: F401


def allocate(n_bytes: int) -> dict:
    block = np.ones(n_bytes, dtype=np.uint8)
    return {"sum": block.sum()}


def allocate_in_a_child(n_bytes: int, memory_bytes: int) -> dict:
    """``allocate`` in a child of this (isolated) process that asks for ``memory_bytes``."""
    from drivers.isolation import Limits, run_isolated

    limits = Limits(memory_bytes=memory_bytes, memory_setting="inner")
    return run_isolated(
        "tests.drivers.isolation_targets:allocate", (n_bytes,), limits=limits, what="the inner"
    )


def sleep(seconds: float) -> None:
    time.sleep(seconds)


def sleep_recording_pid(pid_file: str, seconds: float) -> None:
    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(seconds)


def kill_self() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def segfault(*_reader_args) -> None:
    """Dies as a native parser does on a bad pointer (takes a reader's arguments, if given)."""
    print("about to read address 0", file=sys.stderr, flush=True)
    ctypes.string_at(0)


def hang(*_reader_args) -> None:
    """Loops as a native parser does on some damaged files (takes a reader's arguments)."""
    time.sleep(3600)


def exit_quietly() -> None:
    os._exit(7)


def noisy() -> dict:
    """Writes to stdout and stderr, from Python and below it (as native libraries do)."""
    print("hello from the child")
    print("a warning", file=sys.stderr)
    os.write(1, b"native stdout\n")
    os.write(2, b"native stderr\n")
    return {"ok": True}


def thread_settings() -> dict:
    return {"openblas": os.environ.get("OPENBLAS_NUM_THREADS", ""), "path": np.array(sys.path)}
