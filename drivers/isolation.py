"""Run a function in a fresh child process under a time and a memory limit: :func:`run_isolated`.

For parsers of untrusted or damaged input, above all native ones (ezc3d, librealsense, Open3D):
a crash, an endless loop or a runaway allocation there must cost an error message, not the
calling process. The child is a fresh interpreter (``python -I -c``) that takes the parent's
``sys.path`` from the call it reads on its stdin (so it imports exactly what the parent would,
without rewriting ``PYTHONPATH``), and

* runs with an address-space limit (``RLIMIT_AS``; its file writes are bounded the same), no core
  dumps, one BLAS/OpenMP thread (per-thread buffers would eat the memory limit) and SIGINT
  ignored (the parent decides);
* dies with the parent (``PR_SET_PDEATHSIG`` on Linux), and is killed when it runs out of time;
* writes its stdout and stderr to a file, so native libraries do not write to the caller's
  terminal or log; the last lines are kept on the error when the child crashes;
* hands its result back as an ``.npz`` file read with ``allow_pickle=False``, and its errors as a
  class name and a message (:func:`drivers.errors.error_from_wire`): nothing the child sends is
  unpickled, so even a child taken over through a parser bug cannot run code in the parent;
* reports what it used (:class:`Usage`: its peak resident memory and address space) to a caller
  that asks (``on_usage``), so a test can show that a parse stayed within its bound.

A child started from a process that is itself under a lower address-space limit (a parse that
runs the bag reader, which isolates itself again) cannot raise it: it runs under the lower one,
and the memory error names that one.

Why not ``multiprocessing``'s spawn method: its children run the parent's ``__main__`` module
again, so a script without an ``if __name__ == "__main__":`` guard could not read a C3D file any
more, and a service's main module would be imported into every parse; its environment cannot be
set per child either. The worker processes of :mod:`drivers.worker`, long-lived and talking both
ways, do use it.

Errors in the parent:

========================================== =================================================
in the child                               in the parent
========================================== =================================================
a DriverError, ReconError or ValueError    the same class, the same message
a third-party module not installed         :class:`~drivers.errors.MissingDependencyError`
MemoryError (over ``memory_bytes``)        :class:`~drivers.errors.ResourceLimitError`
still running after ``time_s``             :class:`~drivers.errors.ResourceLimitError`
killed by a signal, or exited silently     :class:`~drivers.errors.ReaderCrashError`
any other exception                        :class:`~drivers.errors.InputFileError`
========================================== =================================================

A call costs one interpreter start plus the imports of the target's module: measured on the
2-core development machine, 0.12 s for a target that imports nothing, 0.23 s for one that imports
numpy, 0.6 s to hand back a 200 MB array (``tests/bench/test_bench_isolation.py``).
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from drivers.errors import (
    InputFileError,
    ReaderCrashError,
    ResourceLimitError,
    error_from_wire,
    error_to_wire,
)

#: Default bound on the child's wall time (s): generous for a parse, short enough that a hung
#: parser is noticed.
DEFAULT_TIME_S = 60.0
#: Default bound on the child's address space (bytes). Address space, not resident memory: an
#: interpreter with numpy maps about 150 MB, with Open3D about 450 MB.
DEFAULT_MEMORY_BYTES = 2 << 30
#: Environment variables that make numerical libraries use one thread in the child.
_ONE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
#: Largest status the parent reads (a class name and a message).
_STATUS_MAX_BYTES = 1 << 16
#: Lines of the child's output kept on a crash error.
_OUTPUT_TAIL_LINES = 5


@dataclass(frozen=True)
class Limits:
    """What a child may use, and the names of the settings that set it (for messages).

    Attributes
    ----------
    time_s : float
        Wall time from the start of the child (interpreter start-up included), seconds.
    memory_bytes : int or None
        Address space of the child (``RLIMIT_AS``); None: no limit.
    time_setting, memory_setting : str
        What a user changes to raise the limit, named in the error message.
    background : bool
        Run the child below the caller's priority (:func:`lower_priority`): for a server, whose
        requests (a Stop among them) must not wait for a parse.
    """

    time_s: float = DEFAULT_TIME_S
    memory_bytes: int | None = DEFAULT_MEMORY_BYTES
    time_setting: str = "time_s"
    memory_setting: str = "memory_bytes"
    background: bool = False

    def __post_init__(self) -> None:
        if not self.time_s > 0:
            raise ValueError(f"time_s must be positive, got {self.time_s}")
        if self.memory_bytes is not None and self.memory_bytes <= 0:
            raise ValueError(f"memory_bytes must be positive or None, got {self.memory_bytes}")


@dataclass(frozen=True)
class Usage:
    """What a child used, as it reported it before it ended.

    Attributes
    ----------
    wall_s : float
        From its start to its end (or its kill), measured by the parent.
    peak_rss_bytes : int or None
        Its largest resident set (``getrusage``; its own children included); None when it wrote
        no report (killed, crashed).
    peak_address_space_bytes : int or None
        Its largest address space (``VmPeak``, what ``RLIMIT_AS`` bounds); None where the
        platform does not say, or without a report.
    memory_limit_bytes : int or None
        The address-space limit it ran under (lower than asked for if its parent had a lower
        one); None: no limit.
    """

    wall_s: float
    peak_rss_bytes: int | None = None
    peak_address_space_bytes: int | None = None
    memory_limit_bytes: int | None = None


def run_isolated(
    target: str,
    args: tuple[Any, ...] = (),
    kwargs: Mapping[str, Any] | None = None,
    *,
    limits: Limits | None = None,
    what: str | None = None,
    on_usage: Callable[[Usage], None] | None = None,
) -> dict[str, Any]:
    """Call ``target(*args, **kwargs)`` in a fresh child process and return its arrays.

    Parameters
    ----------
    target : str
        ``"module:function"``; the module is imported in the child (only there).
    args, kwargs
        Its arguments; they must pickle (paths as strings, numbers, small arrays).
    limits : Limits, optional
        Time and memory bounds; default :class:`Limits` ().
    what : str, optional
        What runs, for messages ("the C3D reader"); default ``target``.
    on_usage : callable, optional
        Called with the child's :class:`Usage` once it has ended, whatever the outcome (before
        an error is raised).

    Returns
    -------
    dict of str to ndarray
        What the function returned: a mapping of names to arrays (or values ``np.asarray``
        turns into arrays without objects: numbers, strings, lists of them), or None for an
        empty dict. Arrays come back with their dtype, shape and values.

    Raises
    ------
    DriverError, ReconError, ValueError
        The same class and message the function raised in the child.
    MissingDependencyError
        The function (or its module) needs a package that is not installed.
    ResourceLimitError
        The child needed more memory or time than ``limits`` allows (the message names the
        limit and its setting; ``limit``, ``value`` and ``setting`` say it too).
    ReaderCrashError
        The child died without an answer: killed by a signal (a crash of native code, or the
        kernel's out-of-memory killer), or exited.
    InputFileError
        The function raised an exception of another class (its name is in the message).
    """
    from drivers.npz import read_npz

    limits = limits or Limits()
    what = what or target
    call = pickle.dumps((target, tuple(args), dict(kwargs or {})))
    with tempfile.TemporaryDirectory(prefix="teachpath-isolated-") as tmp:
        spec = pickle.dumps(
            {
                "path": list(sys.path),
                "call": call,
                "dir": tmp,
                "memory_bytes": limits.memory_bytes,
                "background": limits.background,
                "what": what,
                "parent_pid": os.getpid(),
            }
        )
        output_path = Path(tmp) / _OUTPUT
        env = {**os.environ, **dict.fromkeys(_ONE_THREAD, "1")}
        started = time.monotonic()
        with output_path.open("wb") as output:
            process = subprocess.Popen(
                [sys.executable, "-I", "-c", _BOOTSTRAP],
                stdin=subprocess.PIPE,
                stdout=output,
                stderr=output,
                env=env,
                close_fds=True,
            )
        timed_out = False
        try:
            process.communicate(spec, timeout=limits.time_s)
        except subprocess.TimeoutExpired:
            timed_out = True
        finally:
            if process.poll() is None:  # over time, or interrupted here (KeyboardInterrupt)
                process.kill()
                process.wait()
        status = _read_status(Path(tmp) / _STATUS)
        if on_usage is not None:
            on_usage(_usage(status, time.monotonic() - started, limits.memory_bytes))
        memory_limit = (status or {}).get("limit_bytes", limits.memory_bytes)
        if status is None and timed_out:
            raise ResourceLimitError(
                f"{what} did not finish within {limits.time_s:g} s, its time limit "
                f"({limits.time_setting})",
                limit="time",
                value=limits.time_s,
                setting=limits.time_setting,
            )
        if status is None:
            raise _crash(what, process.returncode, output_path)
        if "error" in status:
            name, message = status["error"]
            raise error_from_wire(
                name,
                message,
                fallback=lambda text: InputFileError(f"{what} failed unexpectedly ({text})"),
            )
        if status.get("memory"):
            mb = (memory_limit or 0) / 2**20
            raise ResourceLimitError(
                f"{what} needed more memory than its limit of {mb:.0f} MB "
                f"({limits.memory_setting})",
                limit="memory",
                value=memory_limit,
                setting=limits.memory_setting,
            )
        if not (Path(tmp) / _RESULT).is_file():
            return {}
        return read_npz(Path(tmp) / _RESULT)


def _usage(status: dict[str, Any] | None, wall_s: float, asked_bytes: int | None) -> Usage:
    """The child's report (in its status) as a :class:`Usage`."""
    report = (status or {}).get("usage") or {}

    def number(key: str) -> int | None:
        value = report.get(key)
        return int(value) if isinstance(value, (int, float)) else None

    limit = (status or {}).get("limit_bytes", asked_bytes)
    return Usage(
        wall_s=wall_s,
        peak_rss_bytes=number("rss"),
        peak_address_space_bytes=number("vm"),
        memory_limit_bytes=int(limit) if isinstance(limit, (int, float)) else None,
    )


def _read_status(path: Path) -> dict[str, Any] | None:
    """The child's status, or None if it wrote none (or no sensible one)."""
    try:
        with path.open("rb") as handle:
            data = handle.read(_STATUS_MAX_BYTES + 1)
        status = json.loads(data) if len(data) <= _STATUS_MAX_BYTES else None
    except (OSError, ValueError):
        return None
    return status if isinstance(status, dict) else None


def _crash(what: str, returncode: int | None, output_path: Path) -> ReaderCrashError:
    tail = _tail(output_path)
    if returncode is not None and returncode < 0:
        try:
            signal_name = signal.Signals(-returncode).name
        except ValueError:
            signal_name = f"signal {-returncode}"
        cause = ""
        if -returncode == signal.SIGKILL:
            # Nobody here sent it: the kernel's out-of-memory killer is the usual sender.
            cause = ", which the system's out-of-memory killer sends when memory runs out"
        return ReaderCrashError(
            f"{what} crashed ({signal_name}{cause})",
            signal_name=signal_name,
            output_tail=tail,
        )
    return ReaderCrashError(
        f"{what} exited (status {returncode}) without an answer"
        + (f": {tail.splitlines()[-1]}" if tail else ""),
        exit_code=returncode,
        output_tail=tail,
    )


def _tail(path: Path) -> str:
    try:
        with path.open("rb") as handle:
            handle.seek(0, os.SEEK_END)
            handle.seek(max(handle.tell() - 4096, 0))
            text = handle.read().decode("utf-8", errors="replace")
    except OSError:
        return ""
    lines = [line.rstrip() for line in text.splitlines() if line.strip()]
    return "\n".join(lines[-_OUTPUT_TAIL_LINES:])


# -- the child process ---------------------------------------------------------------------------

#: Files in the call's temporary folder: the child's output, its status, its arrays.
_OUTPUT, _STATUS, _RESULT = "output.txt", "status.json", "result.npz"

#: What the child interpreter runs: it takes the parent's sys.path from the spec on stdin (only
#: plain values; the call itself is unpickled after the limits are set), then this module.
_BOOTSTRAP = (
    "import pickle, sys; spec = pickle.load(sys.stdin.buffer); sys.path[:] = spec['path']; "
    "from drivers.isolation import _child_main; _child_main(spec)"
)

#: Statuses made in advance: a child out of memory may have none left to make them.
_OK: dict[str, Any] = {"ok": True}
_MEMORY: dict[str, Any] = {"memory": True}
_OK_STATUS = json.dumps(_OK).encode()


#: Niceness of background processes where the idle scheduling class is not available: CPU work
#: yields to the API (50 pollers during a 1M-point reconstruction on 2 cores: without it, p99
#: status latency was over a second).
BACKGROUND_NICENESS = 10


def lower_priority() -> None:
    """Run this process (and the threads and processes it starts later) below normal priority.

    Linux's SCHED_IDLE runs it only on CPU time nothing else wants: with 50 clients polling
    every 0.5 s during a 1M-point reconstruction, p99 status latency was 19-34 ms with niceness
    10 alone and 10-16 ms with the idle class (tests/bench/test_bench_api.py, two and four
    runs). Where either is not permitted, the priority stays.
    """
    try:
        os.nice(BACKGROUND_NICENESS)
    except OSError:  # not permitted here: run at normal priority
        pass
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or not permitted: the niceness stays
        pass


def _child_main(spec: dict[str, Any]) -> None:  # pragma: no cover - runs in the child process
    """Set the limits, run the call, write its arrays and its status (see the module docstring)."""
    folder = Path(spec["dir"])
    if spec.get("background"):
        lower_priority()
    limit = _confine(spec["memory_bytes"], spec["parent_pid"])
    memory_status = json.dumps({**_MEMORY, "limit_bytes": limit}).encode()
    try:
        target, args, kwargs = pickle.loads(spec["call"])
        from drivers.registry import import_target

        function = import_target(target)
        result = function(*args, **kwargs)
        _save(result, folder / _RESULT)
        status = _OK
    except MemoryError:
        status = _MEMORY
    except BaseException as exc:  # noqa: BLE001 - every failure is reported, by class name
        try:
            status = {"error": error_to_wire(_named(exc, spec["what"]))}
        except MemoryError:
            status = _MEMORY
    try:
        # The failed allocation was not made, so there is memory for the report again.
        encoded = json.dumps({**status, "limit_bytes": limit, "usage": _own_usage()}).encode()
    except MemoryError:
        encoded = _OK_STATUS if status.get("ok") else memory_status
    # Written whole and then renamed: the parent reads a status or none, never half of one.
    partial = folder / (_STATUS + ".partial")
    partial.write_bytes(encoded)
    partial.rename(folder / _STATUS)


def _named(error: BaseException, what: str) -> BaseException:  # pragma: no cover - child
    """A third-party module that is not installed, as the error that says what to install."""
    if isinstance(error, ModuleNotFoundError) and error.name:
        from drivers.registry import OWN_PACKAGES, missing_dependency

        if error.name.split(".")[0] not in OWN_PACKAGES:
            return missing_dependency(error, what)
    return error


def _own_usage() -> dict[str, int]:  # pragma: no cover - runs in the child process
    """Peak resident set (its own children's included) and peak address space, bytes.

    The process's own peak is ``VmHWM``, not ``getrusage``: Linux carries ``ru_maxrss`` across
    ``exec``, so it would include the parent's size at the fork.
    """
    usage: dict[str, int] = {}
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                if key in ("VmHWM", "VmPeak"):
                    usage["rss" if key == "VmHWM" else "vm"] = int(value.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource

        # ru_maxrss is in KiB on Linux, bytes on macOS.
        scale = 1 if sys.platform == "darwin" else 1024
        if "rss" not in usage:
            usage["rss"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale
        children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * scale
        usage["rss"] = max(usage["rss"], children)
    except (ImportError, OSError):
        pass
    return usage


def _confine(memory_bytes: int | None, parent_pid: int) -> int | None:  # pragma: no cover - child
    """Signals and limits of the child, set before the call is unpickled and its module loaded.

    Returns the address-space limit in force: ``memory_bytes``, or the lower one this process
    inherited (which it cannot raise), or None.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group; the parent decides
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: die with the parent
        except (OSError, AttributeError):
            pass
        if os.getppid() != parent_pid:  # the parent died before the line above
            os._exit(1)
    try:
        import resource
    except ImportError:
        return None  # no limit where the platform does not offer one
    try:
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a crash leaves no core file behind
    except (ValueError, OSError):
        pass
    inherited = _hard_limit(resource, resource.RLIMIT_AS)
    if memory_bytes is None:
        return inherited
    memory_bytes = memory_bytes if inherited is None else min(memory_bytes, inherited)
    try:
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    except (ValueError, OSError):
        return inherited
    try:
        # Nor can it fill the disk: what it writes (its arrays) fits in its memory.
        written = _hard_limit(resource, resource.RLIMIT_FSIZE)
        cap = memory_bytes if written is None else min(memory_bytes, written)
        resource.setrlimit(resource.RLIMIT_FSIZE, (cap, cap))
    except (ValueError, OSError):
        pass
    return memory_bytes


def _hard_limit(resource: ModuleType, which: int) -> int | None:  # pragma: no cover - child
    """The hard limit ``which`` of this process, None if unlimited."""
    try:
        hard = resource.getrlimit(which)[1]
    except (ValueError, OSError):
        return None
    return None if hard == resource.RLIM_INFINITY else int(hard)


def _save(result: object, path: Path) -> None:  # pragma: no cover - runs in the child process
    if result is None:
        result = {}
    if not isinstance(result, Mapping):
        raise TypeError(f"an isolated function returns a mapping of arrays, not {type(result)}")
    if not result:
        return  # no file: nothing to read (and numpy need not load for it)
    from drivers.npz import write_npz  # numpy loads only for a result to write

    write_npz(path, {str(key): value for key, value in result.items()})
