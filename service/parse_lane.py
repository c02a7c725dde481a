"""Where uploads are parsed: each in a limited child process of its own, waited on from a
thread of this process, at most a few at once, never queued behind reconstruction jobs.

The parse tasks of :mod:`service.tasks` do their work in a fresh child
(:func:`service.tasks.parse_in_child`: bounded memory and time, Open3D's GIL-holding readers out
of this process); what runs here is the wait and a few checks on the summary. Handing them to
the job pool as well (as before) only made an upload wait for the reconstructions queued ahead
of it: 8.8 s behind six.
"""

from __future__ import annotations

from typing import Any, Protocol

import anyio
import anyio.to_thread


class ParseTask(Protocol):
    def run(self) -> Any: ...


class ParseLane:
    """Runs parse tasks, at most ``concurrency`` at once (each holds a child process of up to
    ``max_parse_memory_mb``); more wait their turn in the event loop, holding no thread (the
    web server's thread pool serves every plain route, a Stop among them: uploads waiting in it
    could take all its threads).

    Parameters
    ----------
    concurrency : int
        Parses at once.
    """

    def __init__(self, concurrency: int) -> None:
        if concurrency < 1:
            raise ValueError(f"concurrency must be at least 1, got {concurrency}")
        self.concurrency = concurrency
        self._limiter: anyio.CapacityLimiter | None = None

    async def run(self, task: ParseTask) -> Any:
        """``task.run()``'s result, or what it raised (the child's errors, see
        :func:`service.tasks.parse_in_child`). A request cancelled meanwhile still waits for
        its parse to end, so that the caller's clean-up comes after the child's last write."""
        if self._limiter is None:  # made in the event loop that uses it
            self._limiter = anyio.CapacityLimiter(self.concurrency)
        return await anyio.to_thread.run_sync(task.run, limiter=self._limiter)
