"""The live OptiTrack feed: a rigid body's pose from Motive over NatNet.

The NatNet client (PyPI ``natnet``, pinned to 0.3.0) runs in a child process of its own
(``multiprocessing`` spawn) that does nothing else: it receives, parses and forwards samples in
batches over a queue. UDP does not wait: a receiver that is not scheduled for a while loses
frames once its socket buffer is full, and in the same process any long call holding the GIL
(a 1.9 s Open3D call lost 161 of 720 frames at 360 Hz) would starve it. In its own process the
receiver keeps up whatever the parent does; the parent takes the batches when it is ready.

What the child does, in order:

1. sends ``NAT_CONNECT`` and waits for the server info (``timeout_s``);
2. requests the model definitions until they come (``timeout_s``) and resolves the rigid
   body's name to its streaming id (an unknown name is an error listing the names streamed);
3. from then on, keeps the rigid body's pose from every ``NAT_FRAMEOFDATA`` (frames that came
   before the definitions are kept and converted once the id is known) and sends them every
   ``batch_s`` with their frame numbers, timestamps and tracking-valid flags.

A failure in the child (no server, an unknown rigid body, a socket that cannot be opened) is
raised there as its :mod:`drivers.errors` class and sent as the class's name and message, which
the parent raises again as that class (:func:`~drivers.errors.error_from_wire`). The receiver is
not a :class:`drivers.worker.WorkerClient`: it streams without being asked, and a request and
reply per batch would only add latency and a second thread in the child.

Unicast (the default here) needs keep-alives, which natnet sends on every poll of its command
socket; Motive sends unicast frames to that socket. Two socket details differ from natnet's
defaults (natnet 0.3.0 only offers them as private methods, hence the name-mangled overrides):
its unicast data socket is bound to the local address instead of every interface (in unicast
it receives nothing, so nothing needs to listen beyond ``local``), and both sockets get a
larger receive buffer (:data:`RECEIVE_BUFFER_BYTES`) to ride out a busy machine.

Positions: NatNet streams metres (Motive's default); ``units="mm"`` converts a server set to
stream millimetres. The position is the rigid body's pivot point: set it at the pen tip in
Motive. Frame numbers count frames: a gap is a dropped frame, reported in :attr:`stats`.
"""

from __future__ import annotations

import ipaddress
import multiprocessing
import os
import queue as queue_module
import select
import signal
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from natnet import NatNetClient, NatNetNetworkError
from numpy.typing import ArrayLike
from pydantic import Field, field_validator

from drivers.errors import (
    DriverError,
    TrackerError,
    TrackerTimeoutError,
    UnknownRigidBodyError,
    error_from_wire,
    error_to_wire,
)
from drivers.tracking.base import SampleBatch, SourceConfig, TrackerSource
from drivers.units import metres_per

if TYPE_CHECKING:
    from multiprocessing.synchronize import Event

#: Receive buffer asked for on the client's sockets (the kernel caps it at net.core.rmem_max;
#: 4 MiB holds many seconds of rigid-body frames).
RECEIVE_BUFFER_BYTES = 4 << 20
#: Time allowed on top of the protocol timeouts for the child process to start (imports).
STARTUP_ALLOWANCE_S = 15.0
#: How often the child re-sends the model-definition request while waiting for it.
MODELDEF_RETRY_S = 0.5
#: Longest wait of the child's poll: keep-alives go out at least this often while idle.
POLL_S = 0.1
#: How long close() lets the receiver flush its last frames to a running batches() loop.
DRAIN_S = 3.0
#: How long a stopping receiver may take to flush and exit before it is killed (s).
FLUSH_S = 5.0
#: How long a receiver that never connected gets to exit by itself before it is killed (s).
UNCONNECTED_GRACE_S = 0.2

#: After a frame number this many frames below the last one, the stream counts as restarted
#: (Motive looping a take, or restarted), not as a late packet.
RESTART_BACKSTEP = 1000


class NatNetConfig(SourceConfig):
    """Settings of the NatNet source.

    Attributes
    ----------
    server : str
        Address of the NatNet server (the Motive PC).
    local : str
        Address of this machine on the tracker's network (sockets bind here).
    rigid_body : str
        Name of the pen's rigid body in Motive.
    multicast : bool
        Multicast instead of unicast (Motive's Transmission Type must match).
    """

    kind: Literal["natnet"] = "natnet"
    server: str = Field("127.0.0.1", description="NatNet server (Motive) address")
    local: str = Field("127.0.0.1", description="this machine's address on that network")
    rigid_body: str = Field(..., min_length=1, description="the pen's rigid-body name in Motive")
    multicast: bool = Field(False, description="multicast instead of unicast")
    multicast_group: str = Field("239.255.42.99", description="Motive's multicast address")
    command_port: int = Field(1510, ge=1, le=65535)
    data_port: int = Field(1511, ge=1, le=65535, description="multicast data port")
    timeout_s: float = Field(5.0, gt=0, description="bound on each answer while connecting")
    stall_timeout_s: float | None = Field(
        5.0, gt=0, description="a stream silent this long is an error (None: wait forever)"
    )
    units: Literal["m", "mm"] = Field("m", description="length unit the server streams")
    batch_s: float = Field(0.02, gt=0, le=1.0, description="how often the child sends samples")

    @field_validator("local")
    @classmethod
    def _interface(cls, value: str) -> str:
        return check_interface_address(value)

    @field_validator("multicast_group")
    @classmethod
    def _group(cls, value: str) -> str:
        if not _ipv4(value).is_multicast:
            raise ValueError(
                f"{value!r} is not a multicast address (224.0.0.0 to 239.255.255.255); Motive's "
                "default is 239.255.42.99"
            )
        return value

    @field_validator("server")
    @classmethod
    def _server(cls, value: str) -> str:
        return check_server_address(value)


def _ipv4(value: str) -> ipaddress.IPv4Address:
    try:
        return ipaddress.IPv4Address(value)
    except ValueError:
        raise ValueError(f"{value!r} is not an IPv4 address") from None


def check_interface_address(value: str) -> str:
    """``value`` if it can name one interface of this machine: an IPv4 address that is not the
    wildcard 0.0.0.0 (sockets bound there listen on every interface), a multicast or the
    broadcast address.

    Raises
    ------
    ValueError
        Saying which address to give instead.
    """
    address = _ipv4(value)
    if address.is_unspecified:
        raise ValueError(
            f"{value!r} is the wildcard address, which binds every interface; give the address "
            "of this machine on the tracker's network (or 127.0.0.1 for a server on this machine)"
        )
    if address.is_multicast or address == ipaddress.IPv4Address("255.255.255.255"):
        raise ValueError(
            f"{value!r} is a multicast or broadcast address, not an interface's; give the "
            "address of this machine on the tracker's network (the multicast group is separate)"
        )
    return value


def check_server_address(value: str) -> str:
    """``value`` unless it is an IP address no server can have (the wildcard, multicast,
    broadcast); host names are left to the resolver.

    Raises
    ------
    ValueError
    """
    try:
        address = ipaddress.ip_address(value)
    except ValueError:
        return value
    if (
        address.is_unspecified
        or address.is_multicast
        or address == ipaddress.IPv4Address("255.255.255.255")
    ):
        raise ValueError(
            f"{value!r} cannot be a NatNet server's address (a wildcard, multicast or broadcast "
            "address); give the address of the PC that runs Motive"
        )
    return value


@dataclass(frozen=True)
class NatNetServerInfo:
    """Who answered.

    Attributes
    ----------
    application : str
        The server's name ("Motive").
    server_version, natnet_version : str
    rigid_body_id : int
        Streaming id of the requested rigid body.
    rigid_bodies : tuple of str
        Every rigid body the server describes.
    """

    application: str
    server_version: str
    natnet_version: str
    rigid_body_id: int
    rigid_bodies: tuple[str, ...]


@dataclass(frozen=True)
class NatNetStats:
    """Frames seen by the source so far.

    Attributes
    ----------
    frames_received : int
        Frames delivered in batches (valid or not).
    frames_dropped : int
        Frame numbers skipped between received frames (lost on the way, or never sent).
    frames_invalid : int
        Delivered frames in which the rigid body was not tracked.
    frames_out_of_order : int
        Frames older than one already delivered (discarded).
    restarts : int
        Times the frame numbers started again (a looped take, a restarted server).
    first_frame, last_frame : int or None
        Frame numbers of the first and last delivered frames.
    """

    frames_received: int = 0
    frames_dropped: int = 0
    frames_invalid: int = 0
    frames_out_of_order: int = 0
    restarts: int = 0
    first_frame: int | None = None
    last_frame: int | None = None


@dataclass(frozen=True)
class NatNetBatch(SampleBatch):
    """A :class:`~drivers.tracking.base.SampleBatch` that also carries the frame numbers.

    Attributes
    ----------
    frame_numbers : ndarray of shape (B,), int64
        The server's frame numbers, increasing within a stream.
    """

    frame_numbers: np.ndarray


class NatNetSource(TrackerSource):
    """A rigid body's pose from a NatNet server, received in a child process.

    :meth:`connect` (or the first :meth:`batches`) starts the receiver and waits until it has
    resolved the rigid body; :meth:`batches` then yields what arrived since the last batch,
    until :meth:`close`. Samples in which the body was not tracked have ``valid`` False and NaN
    position and orientation (the server's numbers for an untracked body mean nothing).

    Parameters
    ----------
    config : NatNetConfig
    """

    kind = "natnet"
    config_class = NatNetConfig

    def __init__(self, config: NatNetConfig) -> None:
        self.config = config
        self._ctx = multiprocessing.get_context("spawn")
        self._process: multiprocessing.process.BaseProcess | None = None
        self._queue: multiprocessing.queues.Queue[tuple[str, Any]] | None = None
        self._stop = self._ctx.Event()
        self._lock = threading.Lock()
        self._closed = False
        # Set while batches() runs (by its thread's id), so close() lets it drain the last
        # frames instead of discarding them; _drained is set when it has.
        self._consumer: int | None = None
        self._drained = threading.Event()
        self._server: NatNetServerInfo | None = None
        self._stats = NatNetStats()
        self._scale = metres_per(config.units)

    @property
    def server(self) -> NatNetServerInfo | None:
        """The server that answered, once connected."""
        return self._server

    @property
    def stats(self) -> NatNetStats:
        """Frames received, dropped, invalid so far."""
        return self._stats

    @property
    def address(self) -> str:
        return f"{self.config.server}:{self.config.command_port}"

    def connect(self) -> NatNetServerInfo:
        """Start the receiver and wait until it streams the rigid body.

        Returns
        -------
        NatNetServerInfo

        Raises
        ------
        TrackerTimeoutError
            No server info or no model definitions within ``timeout_s`` each.
        UnknownRigidBodyError
            The server does not describe a rigid body of that name (the message lists those
            it does).
        TrackerError
            A socket could not be opened (``local`` not an address of this machine), the
            receiver failed, or the source is closed.
        """
        if self._server is not None:
            return self._server
        if self._closed:
            raise TrackerError(f"the NatNet source for {self.address} is closed")
        cfg = self.config
        q = self._ctx.Queue()
        self._stop.clear()
        process = self._ctx.Process(
            target=_receiver_main,
            args=(cfg.model_dump(), q, self._stop),
            name=f"natnet {self.address}",
            daemon=True,
        )
        process.start()
        self._process, self._queue = process, q
        bound_s = 2 * cfg.timeout_s + STARTUP_ALLOWANCE_S
        deadline = time.monotonic() + bound_s
        while True:
            try:
                kind, payload = q.get(timeout=0.1)
            except queue_module.Empty:
                failure = None
                if self._closed:
                    failure = TrackerError(f"the NatNet source for {self.address} was closed")
                elif not process.is_alive():
                    failure = TrackerError(
                        f"the NatNet receiver for {self.address} exited (code "
                        f"{process.exitcode}) before connecting"
                    )
                elif time.monotonic() > deadline:
                    failure = TrackerTimeoutError(
                        f"the NatNet receiver for {self.address} did not connect within "
                        f"{bound_s:.0f} s"
                    )
                if failure is None:
                    continue
                self._shutdown()
                raise failure from None
            except (EOFError, OSError, ValueError):  # closed from another thread
                self._shutdown()
                raise TrackerError(f"the NatNet source for {self.address} was closed") from None
            if kind == "ready":
                self._server = NatNetServerInfo(**payload)
                return self._server
            if kind == "error":
                self._shutdown()
                raise error_from_wire(*payload, fallback=TrackerError)

    def batches(self) -> Iterator[NatNetBatch]:
        """Samples as they arrive, until :meth:`close` (see :class:`NatNetSource`).

        Yields
        ------
        NatNetBatch
            ``t_s`` the frames' timestamps (seconds, the server's clock), ``position_m`` (B, 3)
            in metres, ``orientation_xyzw`` (B, 4), ``valid`` (B,), ``frame_numbers`` (B,).

        Raises
        ------
        TrackerTimeoutError
            Connecting timed out, or no frame arrived for ``stall_timeout_s``.
        UnknownRigidBodyError, TrackerError
            See :meth:`connect`; or the receiver failed while streaming.
        """
        if self._closed:
            return
        self._drained.clear()
        self._consumer = threading.get_ident()
        try:
            yield from self._receive()
        finally:
            self._consumer = None
            self._shutdown()
            self._drained.set()

    def _receive(self) -> Iterator[NatNetBatch]:
        self.connect()
        # Locals: _shutdown() clears the attributes.
        process, q = self._process, self._queue
        if process is None or q is None:
            return
        stall = self.config.stall_timeout_s
        last_data = time.monotonic()
        drain_until = None
        while True:
            try:
                kind, payload = q.get(timeout=0.1)
            except queue_module.Empty:
                if self._closed:
                    # close() told the receiver to flush and exit: done once it has exited
                    # and its last batches are read (or it takes too long).
                    drain_until = drain_until or time.monotonic() + DRAIN_S
                    if not process.is_alive() or time.monotonic() > drain_until:
                        return
                    continue
                if not process.is_alive():
                    self._shutdown()
                    raise TrackerError(
                        f"the NatNet receiver for {self.address} stopped (exit code "
                        f"{process.exitcode})"
                    ) from None
                if stall is not None and time.monotonic() - last_data > stall:
                    self._shutdown()
                    raise TrackerTimeoutError(
                        f"no frame from the NatNet server at {self.address} for {stall:.1f} s "
                        f"(after {self._stats.frames_received} frames); is Motive still "
                        "streaming (live mode or playing, streaming enabled)?"
                    ) from None
                continue
            except (EOFError, OSError, ValueError):
                if self._closed:
                    return
                raise
            if kind == "batch":
                last_data = time.monotonic()
                batch = self._accept(*payload)
                if len(batch):
                    yield batch
            elif kind == "error":
                self._shutdown()
                raise error_from_wire(*payload, fallback=TrackerError)

    def close(self) -> None:
        """Stop the receiver (idempotent; safe from another thread while :meth:`batches` runs).

        While another thread iterates :meth:`batches`, the receiver flushes what it holds and
        :meth:`batches` yields those last samples before it ends; this waits for that (at most
        ``DRAIN_S`` and a little). Otherwise samples not taken are discarded.
        """
        self._closed = True
        self._stop.set()  # the receiver flushes its last frames and exits
        consumer = self._consumer
        if (
            consumer is not None
            and consumer != threading.get_ident()
            and self._drained.wait(DRAIN_S + 1.0)
        ):
            return
        self._shutdown()

    def __enter__(self) -> NatNetSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _shutdown(self) -> None:
        with self._lock:
            process, q = self._process, self._queue
            self._process = self._queue = None
        if process is None or q is None:
            return
        self._stop.set()
        # Drain while the child flushes and exits: its queue feeder must not block on a pipe
        # nobody reads. A receiver that never connected holds no frames, and it may sit in
        # its connect (up to timeout_s, deaf to the stop): end it at once.
        connected = self._server is not None
        deadline = time.monotonic() + (FLUSH_S if connected else UNCONNECTED_GRACE_S)
        while process.is_alive() and time.monotonic() < deadline:
            try:
                q.get(timeout=0.05)
            except (queue_module.Empty, EOFError, OSError, ValueError):
                pass
        if process.is_alive():
            process.kill()
        process.join(timeout=5)
        # The queue is not closed here: batches() may still be polling it from another thread
        # (closing its descriptor under it could even hand the number to another file). It is
        # closed when the last reference goes.

    def _accept(
        self,
        frames: ArrayLike,
        t: ArrayLike,
        position: ArrayLike,
        orientation: ArrayLike,
        valid: ArrayLike,
    ) -> NatNetBatch:
        """Count drops, discard late frames, convert units."""
        s = self._stats
        frames = np.asarray(frames, dtype=np.int64)
        keep = np.ones(len(frames), dtype=bool)
        dropped = out_of_order = restarts = 0
        last = s.last_frame
        for i, f in enumerate(frames.tolist()):
            if last is None:
                pass
            elif f > last:
                dropped += f - last - 1
            elif last - f >= RESTART_BACKSTEP:
                restarts += 1
            else:
                keep[i] = False
                out_of_order += 1
                continue
            last = f
        valid = np.asarray(valid, dtype=bool)[keep]
        first = s.first_frame
        if first is None and keep.any():
            first = int(frames[keep][0])
        self._stats = NatNetStats(
            frames_received=s.frames_received + int(keep.sum()),
            frames_dropped=s.frames_dropped + dropped,
            frames_invalid=s.frames_invalid + int((~valid).sum()),
            frames_out_of_order=s.frames_out_of_order + out_of_order,
            restarts=s.restarts + restarts,
            first_frame=first,
            last_frame=last,
        )
        return NatNetBatch(
            t_s=np.asarray(t, dtype=np.float64)[keep],
            position_m=np.asarray(position, dtype=np.float64)[keep] * self._scale,
            orientation_xyzw=np.asarray(orientation, dtype=np.float64)[keep],
            valid=valid,
            frame_numbers=frames[keep],
        )


# -- the receiver process ------------------------------------------------------------------------


class _Client(NatNetClient):  # type: ignore[misc]  # natnet ships no types: its client is Any
    """natnet's client with our socket set-up (see the module docstring).

    natnet 0.3.0 creates its sockets in private methods; these overrides use their mangled
    names, which the pinned version guarantees.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.sockets: list[socket.socket] = []

    def _NatNetClient__create_command_socket(  # noqa: N802 - natnet's private name
        self,
    ) -> socket.socket:
        sock = NatNetClient._NatNetClient__create_command_socket(self)
        return self._keep(sock)

    def _NatNetClient__create_data_socket(  # noqa: N802 - natnet's private name
        self, port: int
    ) -> socket.socket:
        if self.use_multicast:
            return self._keep(NatNetClient._NatNetClient__create_data_socket(self, port))
        # Unicast frames come to the command socket; this one only has to exist.
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            sock.bind((self.local_ip_address, 0))
        except OSError:
            sock.close()
            raise
        sock.settimeout(0.0)
        return self._keep(sock)

    def _keep(self, sock: socket.socket) -> socket.socket:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        self.sockets.append(sock)
        return sock


def _receiver_main(  # pragma: no cover - child process
    config: dict[str, Any], out: multiprocessing.queues.Queue[tuple[str, Any]], stop_event: Event
) -> None:
    # Ctrl-C reaches the whole process group: the parent decides when this receiver stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    receiver = None
    try:
        receiver = _Receiver(config, out)
        receiver.run(stop_event)
    except DriverError as error:  # by class name: the parent raises the same class
        out.put(("error", error_to_wire(error)))
    except Exception as exc:  # the parent must hear of it, not find a dead process
        failure = TrackerError(f"the NatNet receiver failed: {type(exc).__name__}: {exc}")
        out.put(("error", error_to_wire(failure)))
    finally:
        if receiver is not None:
            receiver.shutdown()


class _Receiver:  # pragma: no cover - runs in the child process
    def __init__(
        self, config: dict[str, Any], out: multiprocessing.queues.Queue[tuple[str, Any]]
    ) -> None:
        self.config = config
        self.out = out
        self.address = f"{config['server']}:{config['command_port']}"
        self.client: _Client | None = None
        # natnet's model definitions (an untyped library's object) once the server sent them.
        self.descriptions: Any = None
        self.target_id: int | None = None
        self.pending: list[Any] = []  # frames received before the id was known
        self.rows: list[tuple[Any, ...]] = []
        self.last_modeldef_request = -np.inf

    def run(self, stop_event: Event) -> None:
        cfg = self.config
        client = self.open()
        info = client.server_info
        self.resolve(cfg["timeout_s"])
        names = tuple(d.name for d in self.descriptions.rigid_bodies)
        self.out.put(
            (
                "ready",
                {
                    "application": info.application_name,
                    "server_version": str(info.server_version),
                    "natnet_version": str(info.nat_net_protocol_version),
                    "rigid_body_id": self.target_id,
                    "rigid_bodies": names,
                },
            )
        )
        for frame in self.pending:
            self.on_frame(frame)
        self.pending = []
        last_flush = time.monotonic()
        parent = os.getppid()
        # A parent killed without closing us leaves this process to init: stop then too.
        while not stop_event.is_set() and os.getppid() == parent:
            readable, _, _ = select.select(client.sockets, [], [], POLL_S)
            if readable:
                client.update_sync()  # drains both sockets, keep-alive per packet
            elif not cfg["multicast"]:
                client.send_request(NatNetClient.NAT_KEEPALIVE)
            now = time.monotonic()
            if self.rows and now - last_flush >= cfg["batch_s"]:
                self.flush()
                last_flush = now
        if os.getppid() != parent:
            # Nobody reads the queue any more: exit without waiting to flush it.
            self.out.cancel_join_thread()
            return
        self.flush()

    def open(self) -> _Client:
        """Connect to the server; the connected client (also kept as ``client``)."""
        cfg = self.config
        client = self.client = _Client(
            server_ip_address=cfg["server"],
            local_ip_address=cfg["local"],
            multicast_address=cfg["multicast_group"],
            command_port=cfg["command_port"],
            data_port=cfg["data_port"],
            use_multicast=cfg["multicast"],
        )
        client.on_data_description_received_event.handlers.append(self.on_descriptions)
        client.on_data_frame_received_event.handlers.append(self.on_frame)
        mode = "multicast" if cfg["multicast"] else "unicast"
        try:
            client.connect(timeout=cfg["timeout_s"])
        except TimeoutError:
            raise TrackerTimeoutError(
                f"no NatNet server answered at {self.address} within {cfg['timeout_s']:.1f} s; "
                f"check that Motive streams (Settings > Streaming > Enable) in {mode} on that "
                "address and command port",
            ) from None
        except (OSError, NatNetNetworkError) as exc:
            reason = getattr(exc, "inner_error", exc)
            raise TrackerError(
                f"cannot open a {mode} socket on {cfg['local']} for {self.address}: {reason}; "
                "'local' must be an address of this machine on the tracker's network",
            ) from None
        return client

    def resolve(self, timeout_s: float) -> None:
        """Wait for the model definitions and find the rigid body's id."""
        client = self.connected()
        deadline = time.monotonic() + timeout_s
        last_request = -np.inf
        while self.descriptions is None:
            now = time.monotonic()
            if now > deadline:
                raise TrackerTimeoutError(
                    f"the NatNet server at {self.address} answered but sent no model "
                    f"definitions within {timeout_s:.1f} s",
                )
            if now - last_request >= MODELDEF_RETRY_S:
                client.request_modeldef()
                last_request = now
            readable, _, _ = select.select(client.sockets, [], [], 0.05)
            if readable:
                client.update_sync()
        self.target_id = self.find_id()
        if self.target_id is None:
            names = [d.name for d in self.descriptions.rigid_bodies]
            streamed = (
                "it streams " + ", ".join(repr(n) for n in names)
                if names
                else "it streams no rigid bodies (enable Rigid Bodies in Motive's streaming "
                "settings)"
            )
            raise UnknownRigidBodyError(
                f"no rigid body named {self.config['rigid_body']!r} at the NatNet server "
                f"{self.address}; {streamed}",
            )

    def connected(self) -> _Client:
        """The client, once :meth:`open` made it."""
        if self.client is None:
            raise TrackerError(f"the NatNet receiver for {self.address} is not connected")
        return self.client

    def find_id(self) -> int | None:
        for description in self.descriptions.rigid_bodies:
            if description.name == self.config["rigid_body"]:
                return int(description.id_num)
        return None

    def on_descriptions(self, descriptions: Any) -> None:
        self.descriptions = descriptions
        if self.target_id is not None:
            # Motive re-numbers bodies when assets change: follow the name.
            found = self.find_id()
            if found is not None:
                self.target_id = found

    def on_frame(self, frame: Any) -> None:
        if self.target_id is None:
            self.pending.append(frame)
            return
        # At most once a second: natnet 0.3.0 does not know NatNet 4.1's precision timestamps
        # and reads this flag from them when Motive streams 4.1.
        now = time.monotonic()
        if frame.suffix.tracked_models_changed and now - self.last_modeldef_request > 1.0:
            self.connected().request_modeldef()
            self.last_modeldef_request = now
        for body in frame.rigid_bodies:
            if body.id_num == self.target_id:
                valid = body.tracking_valid is not False
                pos, rot = (body.pos, body.rot) if valid else (_NAN3, _NAN4)
                self.rows.append(
                    (frame.prefix.frame_number, frame.suffix.timestamp, *pos, *rot, valid)
                )
                return
        # The body is missing from this frame: a frame without it is a frame not tracked.
        self.rows.append((frame.prefix.frame_number, frame.suffix.timestamp, *_NAN3, *_NAN4, False))

    def flush(self) -> None:
        if not self.rows:
            return
        rows, self.rows = self.rows, []
        data = np.array(rows, dtype=np.float64)
        self.out.put(
            (
                "batch",
                (
                    data[:, 0].astype(np.int64),
                    data[:, 1],
                    data[:, 2:5],
                    data[:, 5:9],
                    data[:, 9] > 0.5,
                ),
            )
        )

    def shutdown(self) -> None:
        if self.client is None:
            return
        try:
            if not self.config["multicast"] and self.client.connected:
                self.client.send_request(NatNetClient.NAT_DISCONNECT)
        except OSError:
            pass
        self.client.shutdown()
        self.client = None


_NAN3 = (float("nan"),) * 3
_NAN4 = (float("nan"),) * 4
