"""Clocks the robot backends wait on: the real one, and a fake one that makes tests fast."""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic time in seconds, and a way to wait for it."""

    def now(self) -> float: ...

    def sleep_until(self, t_s: float) -> None: ...


class RealClock:
    """``time.monotonic`` and real sleeping."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)


class FakeClock:
    """A clock that jumps instead of waiting: simulated seconds cost no real time.

    Thread-safe, so a test can read it while a backend advances it.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = start_s
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep_until(self, t_s: float) -> None:
        with self._lock:
            self._t = max(self._t, t_s)

    def advance(self, dt_s: float) -> None:
        with self._lock:
            self._t += dt_s
