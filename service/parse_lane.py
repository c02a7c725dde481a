"""Where uploads are parsed: each in a limited child process of its own, waited on from a
thread of this process, at most a few at once, never queued behind reconstruction jobs.

The parse tasks of :mod:`service.tasks` do their work in a fresh child
(:func:`service.tasks.parse_in_child`: bounded memory and time, Open3D's GIL-holding readers out
of this process); what runs here is the wait and a few checks on the summary. Handing them to
the job pool as well (as before) only made an upload wait for the reconstructions queued ahead
of it: 8.8 s behind six.
"""

from __future__ import annotations

import threading
from typing import Any, Protocol

from starlette.concurrency import run_in_threadpool


class ParseTask(Protocol):
    def run(self) -> Any: ...


class ParseLane:
    """Runs parse tasks, at most ``concurrency`` at once (each holds a child process of up to
    ``max_parse_memory_mb``); more wait their turn in a thread.

    Parameters
    ----------
    concurrency : int
        Parses at once.
    """

    def __init__(self, concurrency: int) -> None:
        if concurrency < 1:
            raise ValueError(f"concurrency must be at least 1, got {concurrency}")
        self.concurrency = concurrency
        self._slots = threading.BoundedSemaphore(concurrency)

    async def run(self, task: ParseTask) -> Any:
        """``task.run()``'s result, or what it raised (the child's errors, see
        :func:`service.tasks.parse_in_child`)."""
        return await run_in_threadpool(self._run, task)

    def _run(self, task: ParseTask) -> Any:
        with self._slots:
            return task.run()
