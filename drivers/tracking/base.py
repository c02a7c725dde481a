"""Tracker sources: something that yields timestamped pen samples.

A source yields batches of :class:`Sample` (tip position in metres, orientation as a scalar-last
quaternion, a flag for missing or low-quality frames). File replays pair a reader with a separate
:class:`Pacer` (as fast as possible, or real time times a factor); live feeds pace themselves.

Sources are registered by name in :data:`SOURCES` (a :class:`~drivers.registry.Registry`) and
imported lazily; each has a pydantic config (a :class:`SourceConfig` with a literal ``kind``), and
:func:`create_source` builds the source a config names.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from drivers.errors import UnknownBackendError
from drivers.registry import Registry
from drivers.robot.clock import Clock, RealClock
from recon.arrays import FloatArray

if TYPE_CHECKING:
    from recon.inputs import Recording


@dataclass(frozen=True)
class SampleBatch:
    """Consecutive samples of a source.

    Attributes
    ----------
    t_s : ndarray of shape (B,), or None
        Sample times (s); None for a recording that has none (a canonical CSV without ``t``).
    position_m : ndarray of shape (B, 3)
        Pen-tip positions (tracker frame).
    orientation_xyzw : ndarray of shape (B, 4), or None
    valid : ndarray of shape (B,), bool
        False for missing or low-quality frames.
    """

    t_s: FloatArray | None
    position_m: FloatArray
    orientation_xyzw: FloatArray | None
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.position_m)

    def times_s(self) -> FloatArray:
        """The sample times (s), of samples that carry them (a source's batches always do).

        Raises
        ------
        ValueError
            Samples read from a trace file without times (a canonical CSV without ``t``).
        """
        if self.t_s is None:
            raise ValueError("these samples carry no times (a trace file without a t column)")
        return self.t_s


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


#: Names a message quotes at most: a recorder's header can hold hundreds of columns (an RTDE
#: recording's is 2.7 KB), and a message that echoes it all hides what it says.
EXCERPT_NAMES = 8


def name_excerpt(names: Iterable[object], limit: int = EXCERPT_NAMES, *, quote: bool = True) -> str:
    """The first ``limit`` of ``names``, comma-separated, and how many more there are.

    Parameters
    ----------
    names : iterable of str
    limit : int
    quote : bool
        Quote each name (``repr``), as messages quote names taken from a file.

    Returns
    -------
    str
        ``"'a', 'b', 'c' … and 12 more"``; "none" for no names.
    """
    names = list(names)
    if not names:
        return "none"
    shown = [repr(n) if quote else str(n) for n in names[:limit]]
    more = len(names) - len(shown)
    return ", ".join(shown) + (f" … and {more} more" if more else "")


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


class SourceConfig(BaseModel):
    """Settings of a source; each source subclasses it with a literal ``kind``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str


class TrackerSource(ABC):
    """A stream of pen samples; iterate :meth:`batches` until it ends or :meth:`close`."""

    kind: ClassVar[str]
    #: Its config model (what :func:`create_source` takes for it).
    config_class: ClassVar[type[SourceConfig]]

    @classmethod
    def from_config(
        cls,
        config: SourceConfig,
        *,
        recording: Recording | SampleBatch | None = None,
        clock: Clock | None = None,
    ) -> TrackerSource:
        """The source for ``config`` (see :func:`create_source`).

        Sources that replay stored samples take ``recording`` and pace with ``clock``; live
        sources take neither, and refuse them rather than ignore them.
        """
        if recording is not None or clock is not None:
            raise ValueError(
                f"the {cls.kind} source takes neither a recording nor a clock: it streams live"
            )
        return cls(config)  # type: ignore[call-arg]

    @abstractmethod
    def batches(self) -> Iterator[SampleBatch]: ...

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the source (a network socket, a file)."""


#: Tracker sources by name, imported on first use; packages add more through the entry-point
#: group ``teachpath.tracker_sources``.
SOURCES: Registry[type[TrackerSource]] = Registry(
    "tracker source",
    {
        "replay": "drivers.tracking.replay:ReplaySource",
        "natnet": "drivers.tracking.natnet_source:NatNetSource",
    },
    group="teachpath.tracker_sources",
    unknown_error=UnknownBackendError,
    base=TrackerSource,
)


def source_class(kind: str) -> type[TrackerSource]:
    """The source class registered as ``kind``.

    Raises
    ------
    UnknownBackendError
        Unknown name (the message lists the known ones).
    MissingDependencyError
        The source needs a package that is not installed (a subclass of UnknownBackendError).
    """
    return SOURCES.load(kind)


def create_source(
    config: SourceConfig,
    *,
    recording: Recording | SampleBatch | None = None,
    clock: Clock | None = None,
) -> TrackerSource:
    """The source for ``config``, chosen by its ``kind`` field.

    Parameters
    ----------
    config : SourceConfig
        E.g. :class:`~drivers.tracking.replay.ReplayConfig` or
        :class:`~drivers.tracking.natnet_source.NatNetConfig`.
    recording : Recording or SampleBatch, optional
        The samples a replay streams (replay sources only).
    clock : Clock, optional
        What a replay is paced by (replay sources only); real time by default.

    Raises
    ------
    UnknownBackendError, MissingDependencyError
        See :func:`source_class`.
    ValueError
        A config of another source than its ``kind`` names, or a recording or clock given to a
        source that takes none (or none given to one that needs it).
    """
    cls = source_class(config.kind)
    if not isinstance(config, cls.config_class):
        raise ValueError(
            f"the {cls.kind} source takes {cls.config_class.__name__}, got {type(config).__name__}"
        )
    return cls.from_config(config, recording=recording, clock=clock)
