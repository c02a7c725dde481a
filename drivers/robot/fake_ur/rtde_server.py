"""The RTDE port (TCP 30004): handshake, recipes, start/pause, data packages both ways.

One :class:`RTDEConnection` per client. Its reader thread answers requests and applies input
packages; the controller's tick calls :meth:`RTDEConnection.send_data` so data streams at the
rate the client asked for, continuously (ur_rtde treats 2.5 s of silence as a dead link).
"""

from __future__ import annotations

import logging
import socket
import struct
import threading

from drivers.robot.fake_ur import rtde_protocol as rp
from drivers.robot.fake_ur.controller import FakeController

log = logging.getLogger("fake_ur.rtde")

#: Protocol versions the fake accepts.
SUPPORTED_PROTOCOLS = (1, 2)


class RTDEConnection:
    """One RTDE client.

    Parameters
    ----------
    sock : socket.socket
    controller : FakeController
    version : tuple of 4 ints
        What ``get urcontrol version`` answers (major, minor, bugfix, build).
    """

    def __init__(self, sock: socket.socket, controller: FakeController, version) -> None:
        self.sock = sock
        self.controller = controller
        self.version = version
        self.output: rp.Recipe | None = None
        self.inputs: dict[int, rp.Recipe] = {}
        self.frequency_hz = controller.rate_hz
        self.streaming = False
        self.closed = False
        self._tick = 0
        self._send_lock = threading.Lock()
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
            self.sock.sendall(rp.packet(kind, payload))

    def _handle(self, kind: int, body: bytes) -> None:
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
            types = tuple(rp.input_type(n) or "NOT_FOUND" for n in names)
            if "NOT_FOUND" in types:
                log.warning("refused input recipe: %s", names)
                self._reply(kind, rp.setup_reply(0, types))
                return
            recipe_id = len(self.inputs) + 1  # numbered per connection from 1
            self.inputs[recipe_id] = rp.Recipe(recipe_id, names, types)
            self._reply(kind, rp.setup_reply(recipe_id, types))
        elif kind == rp.START:
            self.streaming = self.output is not None
            self._reply(kind, bytes([self.streaming]))
        elif kind == rp.PAUSE:
            self.streaming = False
            self._reply(kind, b"\x01")
        elif kind == rp.TEXT_MESSAGE:
            log.info("text message from client: %r", body)
        else:
            log.warning("unknown RTDE package type %d", kind)

    def send_data(self, values: dict[str, object]) -> None:
        """Called every control period: send a data package when one is due."""
        if not self.streaming or self.output is None or self.closed:
            return
        self._tick += 1
        every = max(1, round(self.controller.rate_hz / self.frequency_hz))
        if self._tick % every:
            return
        try:
            payload = self.output.pack(_with_defaults(self.output, values))
            with self._send_lock:
                self.sock.sendall(rp.packet(rp.DATA_PACKAGE, payload))
        except OSError:
            self.close()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.streaming = False
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
