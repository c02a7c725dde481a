"""The RTDE port (TCP 30004): handshake, recipes, start/pause, data packages both ways.

One :class:`RTDEConnection` per client. Its reader thread answers requests and applies input
packages; the controller's tick calls :meth:`RTDEConnection.send_data` so data streams at the
rate the client asked for, continuously (ur_rtde treats 2.5 s of silence as a dead link).

The tick never blocks on a client: packets go out with non-blocking sends through a per-client
backlog, and a client that has not taken its data for :data:`SEND_STALL_S` is dropped, as a
real controller drops a client that cannot keep up -- one stalled reader must not stall the
physics or the other clients. An input field belongs to the connection that set it up until
that connection closes; another client's recipe naming it is answered ``IN_USE``, as UR's
controller does.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time

from drivers.robot.fake_ur import rtde_protocol as rp
from drivers.robot.fake_ur.controller import FakeController

log = logging.getLogger("fake_ur.rtde")

#: Protocol versions the fake accepts.
SUPPORTED_PROTOCOLS = (1, 2)
#: A client whose data has waited this long to be sent (its socket buffers full) is dropped
#: (s of wall time). Longer than a client stall on a busy machine, shorter than ur_rtde's own
#: 2.5 s dead-link limit.
SEND_STALL_S = 2.0
#: A client with more than this waiting to be sent is dropped at once (bytes).
SEND_BACKLOG_MAX = 8 << 20
#: Kernel send buffer of an RTDE socket (bytes): small, so a client that stops reading shows
#: as a backlog within a fraction of a second instead of after megabytes of autotuned buffer.
SOCKET_SEND_BUFFER = 64 << 10


class RTDEConnection:
    """One RTDE client.

    Parameters
    ----------
    sock : socket.socket
    controller : FakeController
    version : tuple of 4 ints
        What ``get urcontrol version`` answers (major, minor, bugfix, build).
    """

    def __init__(
        self, sock: socket.socket, controller: FakeController, version: tuple[int, int, int, int]
    ) -> None:
        self.sock = sock
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_SEND_BUFFER)
        self.controller = controller
        self.version = version
        self.output: rp.Recipe | None = None
        self.inputs: dict[int, rp.Recipe] = {}
        self.frequency_hz = controller.rate_hz
        self.streaming = False
        self.closed = False
        self._tick = 0
        self._send_lock = threading.Lock()
        self._backlog = bytearray()  # bytes not yet taken by the socket, in order
        self._stalled_since: float | None = None  # monotonic time the backlog began
        self.protocol = 1

    def serve(self) -> None:
        """Read packets until the client goes away."""
        buffer = bytearray()
        try:
            while not self.closed:
                data = self.sock.recv(65536)
                if not data:
                    break
                buffer += data
                for kind, body in rp.split_packets(buffer):
                    self._handle(kind, body)
        except OSError as exc:
            if not self.closed:
                log.info("RTDE client gone: %s", exc)
        except (ValueError, struct.error) as exc:
            # A malformed packet: drop this client (as a controller would), keep serving others.
            log.warning("malformed RTDE packet, closing the connection: %s", exc)
        finally:
            self.close()

    def _reply(self, kind: int, payload: bytes) -> None:
        if self.controller.frozen:
            return  # a controller that stopped answering
        with self._send_lock:
            self._send(rp.packet(kind, payload))

    def _send(self, data: bytes) -> None:
        """Queue ``data`` after what is waiting and send what the socket takes now, without
        blocking (call with the send lock held). Drops a client that stopped taking data."""
        self._backlog += data
        try:
            while self._backlog:
                sent = self.sock.send(self._backlog, socket.MSG_DONTWAIT)
                del self._backlog[:sent]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self.close()
            return
        if not self._backlog:
            self._stalled_since = None
            return
        now = time.monotonic()
        if self._stalled_since is None:
            self._stalled_since = now
        elif now - self._stalled_since > SEND_STALL_S or len(self._backlog) > SEND_BACKLOG_MAX:
            log.warning(
                "RTDE client took no data for %.1f s (%d bytes waiting): dropped",
                now - self._stalled_since,
                len(self._backlog),
            )
            self.close()

    def _handle(self, kind: int, body: bytes) -> None:  # noqa: C901
        c = self.controller
        if kind == rp.DATA_PACKAGE:
            recipe = self.inputs.get(body[0]) if body else None
            if recipe is None:
                log.warning("data package for unknown input recipe %s", body[:1].hex())
                return
            values = recipe.unpack(body[1:])
            with c.lock:
                if not c.frozen:
                    c.apply_inputs(values)
        elif kind == rp.REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", body[:2])
            accepted = version in SUPPORTED_PROTOCOLS
            if accepted:
                self.protocol = version
            self._reply(kind, bytes([accepted]))
        elif kind == rp.GET_URCONTROL_VERSION:
            self._reply(kind, struct.pack(">IIII", *self.version))
        elif kind == rp.SETUP_OUTPUTS:
            if self.protocol >= 2:
                (frequency,) = struct.unpack(">d", body[:8])
                names_text = body[8:]
            else:
                frequency, names_text = c.rate_hz, body
            # ur_rtde ends its name lists with a comma: empty names are not fields.
            names = tuple(n for n in names_text.decode().split(",") if n)
            types = tuple(rp.output_type(n) or "NOT_FOUND" for n in names)
            if "NOT_FOUND" in types or not (0 < frequency <= c.rate_hz):
                log.warning("refused output recipe (%s Hz): %s", frequency, names)
                self._reply(kind, rp.setup_reply(0, types))
                return
            self.output = rp.Recipe(1, names, types)
            self.frequency_hz = frequency
            self._reply(kind, rp.setup_reply(1, types))
        elif kind == rp.SETUP_INPUTS:
            names = tuple(n for n in body.decode().split(",") if n)
            with c.lock:
                types = tuple(
                    "IN_USE"
                    if c.input_owners.get(n, self) is not self
                    else (rp.input_type(n) or "NOT_FOUND")
                    for n in names
                )
                refused = "NOT_FOUND" in types or "IN_USE" in types
                if not refused:
                    for name in names:
                        c.input_owners[name] = self
            if refused:
                log.warning("refused input recipe: %s -> %s", names, types)
                self._reply(kind, rp.setup_reply(0, types))
                return
            recipe_id = len(self.inputs) + 1  # numbered per connection from 1
            self.inputs[recipe_id] = rp.Recipe(recipe_id, names, types)
            self._reply(kind, rp.setup_reply(recipe_id, types))
        elif kind == rp.START:
            if self.controller.frozen:
                return
            # The reply goes out before the first data package: both under the send lock.
            with self._send_lock:
                self._send(rp.packet(kind, bytes([self.output is not None])))
                self.streaming = self.output is not None
        elif kind == rp.PAUSE:
            self.streaming = False
            self._reply(kind, b"\x01")
        elif kind == rp.TEXT_MESSAGE:
            log.info("text message from client: %r", body)
        else:
            log.warning("unknown RTDE package type %d", kind)

    def send_data(self, values: dict[str, object]) -> None:
        """Called every control period: send a data package when one is due (never blocks)."""
        if self.closed:
            return
        with self._send_lock:
            if not self.streaming or self.output is None:
                if self._backlog:
                    self._send(b"")  # replies still waiting for room
                return
            self._tick += 1
            every = max(1, round(self.controller.rate_hz / self.frequency_hz))
            if self._tick % every:
                if self._backlog:
                    self._send(b"")
                return
            payload = self.output.pack(_with_defaults(self.output, values))
            self._send(rp.packet(rp.DATA_PACKAGE, payload))

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.streaming = False
            with self.controller.lock:  # its input fields are free for other clients
                owners = self.controller.input_owners
                for name in [n for n, owner in owners.items() if owner is self]:
                    del owners[name]
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self.sock.close()


_ZERO = {t: (0.0 if t == "DOUBLE" else 0) for t in rp.TYPE_FORMATS}


def _with_defaults(recipe: rp.Recipe, values: dict[str, object]) -> dict[str, object]:
    """``values`` completed with zeros for fields the fake does not model."""
    out = {}
    for name, kind in zip(recipe.names, recipe.types, strict=True):
        if name in values:
            out[name] = values[name]
        else:
            fmt = rp.TYPE_FORMATS[kind]
            out[name] = [0] * int(fmt[0]) if fmt[0].isdigit() else _ZERO[kind]
    return out
