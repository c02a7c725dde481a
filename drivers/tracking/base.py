"""Tracker sources: something that yields timestamped pen samples.

A source yields batches of :class:`Sample` (tip position in metres, orientation as a scalar-last
quaternion, a flag for missing or low-quality frames). File replays pair a reader with a separate
:class:`Pacer` (as fast as possible, or real time times a factor); live feeds pace themselves.
Sources are registered by name (:data:`SOURCES`) and imported lazily.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from drivers.errors import UnknownBackendError
from drivers.robot.clock import Clock, RealClock
from recon.types import FloatArray


@dataclass(frozen=True)
class SampleBatch:
    """Consecutive samples of a source.

    Attributes
    ----------
    t_s : ndarray of shape (B,)
    position_m : ndarray of shape (B, 3)
        Pen-tip positions (tracker frame).
    orientation_xyzw : ndarray of shape (B, 4), or None
    valid : ndarray of shape (B,), bool
        False for missing or low-quality frames.
    """

    t_s: FloatArray
    position_m: FloatArray
    orientation_xyzw: FloatArray | None
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


def increasing_times(t_s: FloatArray) -> np.ndarray:
    """Which samples come later than every sample before them.

    A restarted stream (a looped take, a restarted tracker) starts its clock again; keeping
    only samples past the running maximum drops the repeated stretch instead of making the
    whole recording unreadable.

    Parameters
    ----------
    t_s : ndarray of shape (N,)

    Returns
    -------
    ndarray of shape (N,), bool
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    keep = np.ones(len(t_s), dtype=bool)
    if len(t_s) > 1:
        keep[1:] = t_s[1:] > np.maximum.accumulate(t_s)[:-1]
    return keep


class Pacer:
    """Releases samples no faster than their timestamps allow, scaled by ``speed``.

    ``speed=None`` releases them as fast as they can be consumed.
    """

    def __init__(self, speed: float | None = 1.0, *, clock: Clock | None = None) -> None:
        if speed is not None and not speed > 0:
            raise ValueError(f"speed must be > 0 (or None for as fast as possible), got {speed}")
        self.speed = speed
        self.clock = clock or RealClock()
        self._origin: tuple[float, float] | None = None

    def wait_for(self, t_s: float) -> None:
        if self.speed is None:
            return
        if self._origin is None:
            self._origin = (self.clock.now(), t_s)
        start, t0 = self._origin
        self.clock.sleep_until(start + (t_s - t0) / self.speed)


class TrackerSource(ABC):
    """A stream of pen samples; iterate :meth:`batches` until it ends or :meth:`close`."""

    kind: str

    @abstractmethod
    def batches(self) -> Iterator[SampleBatch]: ...

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the source (a network socket, a file)."""


#: Source name -> "module:Class".
SOURCES: dict[str, str] = {
    "replay": "drivers.tracking.replay:ReplaySource",
    "natnet": "drivers.tracking.natnet_source:NatNetSource",
}


def source_class(kind: str) -> type[TrackerSource]:
    """The source class registered as ``kind``.

    Raises
    ------
    UnknownBackendError
        Unknown name, or a missing optional dependency.
    """
    if kind not in SOURCES:
        raise UnknownBackendError(
            f"unknown tracker source {kind!r}; available: {', '.join(sorted(SOURCES))}"
        )
    module_name, class_name = SOURCES[kind].split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UnknownBackendError(
            f"the {kind} source needs {exc.name}, which is not installed"
        ) from None
    return getattr(module, class_name)
