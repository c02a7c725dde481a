"""Tasks for the job-manager tests, imported by name in the worker processes."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Sleep:
    """Write the worker's pid to ``pid_file`` (when given), sleep, write ``marker`` (when
    given) after the sleep, return the worker's pid."""

    seconds: float
    marker: str | None = None
    pid_file: str | None = None

    def run(self) -> dict:
        if self.pid_file:
            Path(self.pid_file).write_text(str(os.getpid()))
        time.sleep(self.seconds)
        if self.marker:
            Path(self.marker).write_text("written after the sleep")
        return {"pid": os.getpid()}


@dataclass(frozen=True)
class Pid:
    """The worker's pid, at once."""

    def run(self) -> dict:
        return {"pid": os.getpid()}


@dataclass(frozen=True)
class LoadedModules:
    """Which of ``names`` the worker had imported before this task ran (this module imports
    none of them)."""

    names: tuple[str, ...]

    def run(self) -> dict:
        return {"loaded": [name for name in self.names if name in sys.modules]}
