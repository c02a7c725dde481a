"""Worker processes serving typed commands: :class:`WorkerClient` here, :class:`WorkerServer` there.

For device libraries that must not run in the caller's process (ur_rtde holds the GIL while it
waits on the network, which would freeze every thread of the service). The client starts a
child process (``multiprocessing`` spawn) that builds a server object and serves it:

* a command is a small frozen dataclass (a :class:`Command` subclass, one per command); the
  server maps each command class to the method that runs it (:meth:`WorkerServer.handlers`), so
  nothing is dispatched by a string name;
* every reply is awaited with a bound; a command that overruns it ends the worker (its state is
  then unknown) and raises :class:`~drivers.errors.WorkerTimeoutError`, a worker that dies
  raises :class:`~drivers.errors.WorkerLostError`; adapters re-raise both as their own kind;
* an error raised by the server comes back as its class name and message and is raised again
  as that class if the name is in an explicit table (:data:`drivers.errors.WIRE_ERRORS` by
  default), else as the client's ``fallback`` class -- never by importing a name;
* while a command runs, the server can report progress (:meth:`WorkerLink.progress`) and watch
  a stop event the client sets from any thread (:attr:`WorkerClient.stop_event`), so a stop
  reaches a server that is busy streaming;
* the worker ends when the client closes, and when the parent process dies: it then sets the
  stop event (a running command winds down, e.g. an arm decelerates) and exits shortly after.

Being ``multiprocessing``'s spawn method, the worker imports the parent's ``__main__`` module
again: a script that starts one needs the usual ``if __name__ == "__main__":`` guard.

The NatNet receiver (:mod:`drivers.tracking.natnet_source`) streams samples without being asked
and does not fit this request-and-reply shape; it shares only the error transport.
"""

from __future__ import annotations

import multiprocessing
import os
import re
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from drivers.errors import (
    DriverError,
    WorkerError,
    WorkerLostError,
    WorkerTimeoutError,
    error_from_wire,
    error_to_wire,
)
from drivers.registry import import_target

if TYPE_CHECKING:
    from ctypes import c_double
    from multiprocessing.synchronize import Event

#: How often the worker checks that its parent is alive (s).
PARENT_POLL_S = 0.5
#: How long an orphaned worker lets its running command wind down before it exits (s).
ORPHAN_GRACE_S = 2.0
#: What the client sends to end the worker's loop.
_SHUTDOWN = None


@dataclass(frozen=True)
class Command:
    """Base of the commands a worker serves: subclass it once per command, frozen, with fields
    for the arguments (they must pickle)."""

    @classmethod
    def label(cls) -> str:
        """The command's name in messages: its class name in snake case (``MoveJ`` -> move_j)."""
        return re.sub(r"(?<!^)(?=[A-Z])", "_", cls.__name__).lower()


ProgressCallback = Callable[[Any], None]


class WorkerClient:
    """A child process serving one :class:`WorkerServer`; send it commands with :meth:`call`.

    The process starts here. Calls are one at a time (a second thread waits for the first, within
    its own bound); :attr:`stop_event` may be set from any thread; :meth:`close` belongs to the
    thread that makes the calls.

    Parameters
    ----------
    server : str
        ``"module:Class"`` of the :class:`WorkerServer` subclass, built in the child as
        ``Class(link, *args)``.
    args : tuple
        Further arguments of its constructor (they must pickle).
    name : str
        The process's name, and the worker's name in messages ("the ur_rtde worker").
    fallback : DriverError subclass
        Raised for an error whose class is not in ``errors`` (its message names the class).
    errors : mapping of str to exception class, optional
        The classes an error may come back as, by name; default
        :data:`drivers.errors.WIRE_ERRORS`.

    Examples
    --------
    >>> client = WorkerClient("mypackage.device:DeviceServer", ("10.0.0.2",), name="the device")
    ... # doctest: +SKIP
    >>> client.call(ReadTemperature(), timeout_s=2.0)  # doctest: +SKIP
    21.5
    >>> client.close()  # doctest: +SKIP
    """

    def __init__(
        self,
        server: str,
        args: tuple[Any, ...] = (),
        *,
        name: str,
        fallback: type[DriverError] = DriverError,
        errors: Mapping[str, type[Exception]] | None = None,
    ) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.name = name
        self.fallback = fallback
        self.errors = dict(errors) if errors is not None else None
        #: Set to ask the running command to stop (the server decides what stopping means).
        self.stop_event = ctx.Event()
        #: A number the client sets at any time and a running command reads (a robot's speed
        #: override); one aligned double in shared memory, so a read is never torn.
        self.dial = ctx.RawValue("d", 1.0)
        parent, child = ctx.Pipe()
        self.process = ctx.Process(
            target=_serve,
            args=(child, self.stop_event, server, tuple(args), os.getpid(), self.dial),
            name=name,
            daemon=True,  # ended by multiprocessing when this interpreter exits
        )
        self.process.start()
        child.close()
        self._conn: Connection | None = parent
        self._seq = 0
        self._lock = threading.Lock()

    @property
    def alive(self) -> bool:
        """Whether the client is open and its process running."""
        return self._conn is not None and self.process.is_alive()

    def call(
        self,
        command: Command,
        *,
        timeout_s: float,
        on_progress: ProgressCallback | None = None,
        quiet_s: float | None = None,
    ) -> Any:
        """Run ``command`` in the worker and return what its handler returned.

        Parameters
        ----------
        command : Command
        timeout_s : float
            Bound on the reply.
        on_progress : callable, optional
            Called with each progress report of the command, in this thread.
        quiet_s : float, optional
            With it, each progress report extends the bound to at least ``quiet_s`` from then:
            for a command whose length is not known when it is sent (a motion that can be
            slowed or paused), the bound is on silence, not on the whole.

        Raises
        ------
        WorkerTimeoutError
            No reply within ``timeout_s``; the worker has been ended.
        WorkerLostError
            The worker is gone (died, or closed); it has been ended.
        WorkerError
            Another thread's command kept the worker busy for all of ``timeout_s``.
        Exception
            What the handler raised, as its class (see ``errors`` and ``fallback``).
        TypeError, ValueError
            Not a Command, or a bound that is not positive.
        """
        if not isinstance(command, Command):
            raise TypeError(f"a worker takes Command objects, not {type(command).__name__}")
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        deadline = time.monotonic() + timeout_s
        if not self._lock.acquire(timeout=timeout_s):
            raise WorkerError(
                f"{self.name} stayed busy with another command for {timeout_s:.1f} s; "
                f"{command.label()} was not sent"
            )
        try:
            return self._call(command, deadline, timeout_s, on_progress, quiet_s)
        finally:
            self._lock.release()

    def _call(
        self,
        command: Command,
        deadline: float,
        timeout_s: float,
        on_progress: ProgressCallback | None,
        quiet_s: float | None = None,
    ) -> Any:
        conn = self._conn
        if conn is None:
            raise WorkerLostError(f"{self.name} is closed")
        self._seq += 1
        seq = self._seq
        try:
            conn.send((seq, command))
        except (BrokenPipeError, OSError):
            self.close(grace_s=0)
            raise WorkerLostError(f"{self.name} is gone") from None
        while True:
            remaining = deadline - time.monotonic()
            try:
                answered = remaining > 0 and conn.poll(remaining)
            except (OSError, ValueError):  # closed under this call from another thread
                raise WorkerLostError(f"{self.name} was closed during {command.label()}") from None
            if not answered:
                self.close(grace_s=0)
                bound = f"{timeout_s:.1f} s" if quiet_s is None else f"{quiet_s:.1f} s of silence"
                raise WorkerTimeoutError(
                    f"{self.name} did not answer {command.label()} within {bound}"
                )
            try:
                reply_seq, kind, payload = conn.recv()
            except (EOFError, OSError):
                self.close(grace_s=0)
                raise WorkerLostError(
                    f"{self.name} stopped unexpectedly (exit code {self.process.exitcode})"
                ) from None
            if reply_seq != seq:
                continue  # about an earlier command (none is left unanswered; cheap to check)
            if kind == "progress":
                if quiet_s is not None:
                    deadline = max(deadline, time.monotonic() + quiet_s)
                if on_progress is not None:
                    on_progress(payload)
                continue
            if kind == "error":
                name, message = payload
                raise error_from_wire(name, message, fallback=self.fallback, table=self.errors)
            return payload

    def close(self, *, grace_s: float = 2.0) -> None:
        """End the worker: ask it to finish (its server's ``shutdown``), kill it after ``grace_s``.

        Idempotent. ``grace_s=0`` kills it at once (a worker in an unknown state).
        """
        conn, self._conn = self._conn, None
        process = self.process
        if conn is not None and grace_s > 0 and process.is_alive():
            try:
                conn.send(_SHUTDOWN)
            except (BrokenPipeError, OSError):
                pass
            process.join(grace_s)
        if process.is_alive():
            process.kill()
        process.join(5.0)
        if conn is not None:
            conn.close()

    def __enter__(self) -> WorkerClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WorkerLink:
    """What a server has of its client while it runs a command."""

    def __init__(self, conn: Connection, stop_event: Event, dial: c_double | None = None) -> None:
        self._conn = conn
        #: Set by the client (or by the worker when its parent died): stop what you are doing.
        self.stop_event = stop_event
        #: The client's dial (:attr:`WorkerClient.dial`): read ``dial.value``.
        self.dial = dial
        self._seq = 0

    def progress(self, payload: Any) -> None:
        """Report progress of the running command (the client's ``on_progress`` gets it)."""
        self._conn.send((self._seq, "progress", payload))


class WorkerServer(ABC):
    """The object a worker process serves; built there as ``Class(link, *args)``.

    Parameters
    ----------
    link : WorkerLink
        Progress reports and the stop event.
    """

    def __init__(self, link: WorkerLink) -> None:
        self.link = link

    @abstractmethod
    def handlers(self) -> Mapping[type[Command], Callable[[Any], Any]]:
        """Command class -> the method that runs it (it takes the command, returns the reply)."""

    def translate(self, error: Exception) -> Exception:
        """The error to send for ``error`` (e.g. a library's RuntimeError as a domain error)."""
        return error

    def shutdown(self) -> None:  # noqa: B027 - optional hook
        """Release what the server holds; called when the worker ends normally."""


# -- the child process ---------------------------------------------------------------------------


def _serve(  # pragma: no cover
    conn: Connection,
    stop_event: Event,
    server: str,
    args: tuple[Any, ...],
    parent_pid: int,
    dial: c_double | None = None,
) -> None:
    """Build the server and answer commands until the client closes or goes away."""
    # Ctrl-C reaches the whole process group: the parent decides when its worker stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _watch_parent(parent_pid, stop_event)
    link = WorkerLink(conn, stop_event, dial)
    instance: WorkerServer | None = None
    handlers: dict[type[Command], Callable[[Any], Any]] = {}
    failure: Exception | None = None
    try:
        instance = import_target(server)(link, *args)
        if not isinstance(instance, WorkerServer):
            raise TypeError(f"{server} is not a WorkerServer")
        handlers = dict(instance.handlers())
    except Exception as exc:  # noqa: BLE001 - reported as the answer to the first command
        failure = exc
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            break
        if message is _SHUTDOWN:
            break
        seq, command = message
        link._seq = seq
        try:
            if failure is not None:
                raise failure
            handler = handlers.get(type(command))
            if handler is None:
                raise TypeError(f"{server} does not serve {type(command).__name__}")
            reply = (seq, "ok", handler(command))
        except Exception as exc:  # noqa: BLE001 - every failure goes back, by class name
            if instance is not None and exc is not failure:
                exc = instance.translate(exc)
            reply = (seq, "error", error_to_wire(exc))
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            break
    if instance is not None:
        instance.shutdown()


def _watch_parent(parent_pid: int, stop_event: Event) -> None:  # pragma: no cover - child process
    """End this worker if its parent dies (a parent killed outright cannot close it)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        stop_event.set()  # a running command winds down (an arm decelerates)
        time.sleep(ORPHAN_GRACE_S)
        os._exit(1)

    threading.Thread(target=watch, name="parent watch", daemon=True).start()
