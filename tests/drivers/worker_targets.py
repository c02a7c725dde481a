"""A small worker server for the WorkerClient tests (imported by name in the worker process)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from drivers.errors import InputFileError, ProtectiveStopError
from drivers.worker import Command, WorkerLink, WorkerServer


@dataclass(frozen=True)
class Echo(Command):
    value: object


@dataclass(frozen=True)
class Count(Command):
    """Reports 1..n as progress, then returns n."""

    n: int


@dataclass(frozen=True)
class Fail(Command):
    """Raises ``kind`` ("protective_stop", "vendor", "runtime") with ``message``."""

    kind: str
    message: str


@dataclass(frozen=True)
class Sleep(Command):
    seconds: float


@dataclass(frozen=True)
class WaitForStop(Command):
    """Returns True once the client's stop event is set (False after ``timeout_s``)."""

    timeout_s: float


@dataclass(frozen=True)
class Pid(Command):
    pass


@dataclass(frozen=True)
class Unserved(Command):
    pass


class VendorError(Exception):
    """A library's own exception: not among the classes that may cross."""


class EchoServer(WorkerServer):
    def __init__(self, link: WorkerLink, shutdown_marker: str | None = None) -> None:
        super().__init__(link)
        self.shutdown_marker = shutdown_marker

    def handlers(self):
        return {
            Echo: lambda c: c.value,
            Count: self.count,
            Fail: self.fail,
            Sleep: lambda c: time.sleep(c.seconds),
            WaitForStop: self.wait_for_stop,
            Pid: lambda c: os.getpid(),
        }

    def count(self, command: Count) -> int:
        for i in range(1, command.n + 1):
            self.link.progress(i)
        return command.n

    def fail(self, command: Fail) -> None:
        if command.kind == "protective_stop":
            raise ProtectiveStopError(command.message)
        if command.kind == "runtime":
            raise RuntimeError(command.message)
        raise VendorError(command.message)

    def wait_for_stop(self, command: WaitForStop) -> bool:
        return self.link.stop_event.wait(command.timeout_s)

    def translate(self, error: Exception) -> Exception:
        if isinstance(error, RuntimeError):
            return InputFileError(f"translated: {error}")
        return error

    def shutdown(self) -> None:
        if self.shutdown_marker:
            Path(self.shutdown_marker).write_text("shut down")


class BrokenServer(WorkerServer):
    def __init__(self, link: WorkerLink) -> None:
        raise InputFileError("the device library would not start")

    def handlers(self):
        return {}
