"""A NatNet server of our own that replays a recording, for tests, benches and dry runs.

It speaks the part of OptiTrack's NatNet protocol (version :data:`NATNET_VERSION`, Motive 3.0's
bitstream) that a rigid-body client uses, over UDP on a loopback address:

- a client's ``NAT_CONNECT`` (0) on the command port is answered with ``NAT_SERVERINFO`` (1) and
  makes the client a unicast subscriber; the first subscriber starts the replay;
- ``NAT_REQUEST_MODELDEF`` (4) is answered with ``NAT_MODELDEF`` (5): one rigid-body
  description (name, streaming id, markers) per body;
- ``NAT_KEEPALIVE`` (10) refreshes a subscriber, ``NAT_DISCONNECT`` (9) removes it,
  ``NAT_REQUEST_FRAMEOFDATA`` (6) is answered with the last frame sent and any ``NAT_REQUEST``
  command string (2) with ``NAT_UNRECOGNIZED_REQUEST`` (100);
- every sample of the recording goes out as one ``NAT_FRAMEOFDATA`` (7) packet (frame number,
  every rigid body's pose with its tracking-valid flag, the timestamp) to each subscriber, at the
  address its requests came from: in unicast mode Motive sends frames to the client's command
  socket, not to the data port (which is only advertised in the server info, for multicast).

Every packet is ``uint16 message id, uint16 payload bytes, payload``, little-endian, with no
padding. Frames are sent on absolute deadlines (start + sample time), so pacing does not drift
and a late wake-up is caught up at once instead of stretching the stream. The server runs in
its own process (``multiprocessing`` spawn), so the pacing does not depend on what the process
that started it is doing, and it binds loopback addresses (127.0.0.0/8) only.
"""

from __future__ import annotations

import ipaddress
import multiprocessing
import multiprocessing.process
import os
import select
import signal
import socket
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.errors import DriverError
from drivers.units import metres_per
from recon.inputs import Recording

if TYPE_CHECKING:
    from ctypes import c_longlong
    from multiprocessing.synchronize import Event

#: The NatNet bitstream version served (Motive 3.0). natnet 0.3.0 parses all of it; its frames
#: have the 3.x layout, its rigid-body descriptions add marker names.
NATNET_VERSION = (4, 0, 0, 0)
#: This server's own version, reported as the "server version" (Motive's would be 3.0.x).
SERVER_VERSION = (0, 1, 0, 0)
APPLICATION_NAME = "teachpath NatNet replay"
#: Ticks per second of the high-resolution stamps in each frame (we use monotonic nanoseconds).
CLOCK_HZ = 1_000_000_000
DEFAULT_MULTICAST_GROUP = "239.255.42.99"

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

#: Data-description types in NAT_MODELDEF.
DATASET_RIGID_BODY = 1

_HEADER = struct.Struct("<HH")
_INT = struct.Struct("<i")
# id, x, y, z, qx, qy, qz, qw, mean marker error (m), params (bit 0: tracking valid).
_RIGID_BODY = struct.Struct("<i3f4ffH")
# timecode, timecode subframe, timestamp (s), camera mid-exposure / data received / transmit
# stamps (CLOCK_HZ ticks), params (bit 0 recording, bit 1 tracked models changed), end of data.
_SUFFIX = struct.Struct("<IIdQQQHi")
_SERVER_INFO = struct.Struct("<256s4B4BQHB4s")
#: Largest payload the 16-bit size field can describe.
MAX_PAYLOAD = 0xFFFF

#: Marker layout of the replayed pen (metres, rigid-body frame): three markers on a 60 mm stem.
PEN_MARKERS_M = ((0.0, 0.06, 0.0), (0.03, 0.09, 0.0), (-0.02, 0.11, 0.015))


@dataclass(frozen=True)
class RigidBodyPose:
    """One rigid body in one frame (the server's units, Motive's default being metres)."""

    id: int
    position: tuple[float, float, float]
    orientation_xyzw: tuple[float, float, float, float]
    valid: bool = True
    mean_error: float = 0.0


def encode_packet(message_id: int, payload: bytes) -> bytes:
    """A NatNet packet: message id and payload size (both uint16), then the payload.

    Raises
    ------
    ValueError
        A payload longer than the 16-bit size field allows.
    """
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"NatNet payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return _HEADER.pack(message_id, len(payload)) + payload


def encode_server_info(
    *,
    application: str = APPLICATION_NAME,
    server_version: Sequence[int] = SERVER_VERSION,
    natnet_version: Sequence[int] = NATNET_VERSION,
    data_port: int = 1511,
    multicast: bool = False,
    multicast_group: str = DEFAULT_MULTICAST_GROUP,
) -> bytes:
    """The ``NAT_SERVERINFO`` packet (Motive's ``sServerDescription``).

    Name (256 bytes, NUL padded), server and NatNet versions (4 bytes each), then what NatNet 3+
    servers append: the high-resolution clock frequency (uint64), the data port (uint16), a
    multicast flag (uint8) and the multicast group (4 bytes).
    """
    payload = _SERVER_INFO.pack(
        application.encode("utf-8")[:255],
        *server_version,
        *natnet_version,
        CLOCK_HZ,
        data_port,
        int(multicast),
        socket.inet_aton(multicast_group),
    )
    return encode_packet(NAT_SERVERINFO, payload)


def encode_model_definitions(
    bodies: Sequence[tuple[str, int]], *, markers_m: Sequence[Sequence[float]] = PEN_MARKERS_M
) -> bytes:
    """The ``NAT_MODELDEF`` packet describing rigid bodies ``(name, streaming id)``.

    Per body (NatNet 4.0): dataset type 1, name (NUL terminated), id, parent id (-1), pivot
    offset (3 float32), marker count, the marker positions, their active labels (0: passive),
    then their names (new in 4.0).
    """
    parts = [_INT.pack(len(bodies))]
    for name, body_id in bodies:
        parts.append(_INT.pack(DATASET_RIGID_BODY))
        parts.append(name.encode("utf-8") + b"\0")
        parts.append(struct.pack("<ii3f", body_id, -1, 0.0, 0.0, 0.0))
        parts.append(_INT.pack(len(markers_m)))
        parts.extend(struct.pack("<3f", *m) for m in markers_m)
        parts.extend(_INT.pack(0) for _ in markers_m)
        parts.extend(f"{name}_{k + 1}".encode() + b"\0" for k in range(len(markers_m)))
    return encode_packet(NAT_MODELDEF, b"".join(parts))


def encode_frame(
    frame_number: int,
    timestamp_s: float,
    bodies: Sequence[RigidBodyPose],
    *,
    stamps: tuple[int, int, int] = (0, 0, 0),
) -> bytes:
    """A ``NAT_FRAMEOFDATA`` packet with rigid bodies only (NatNet 3.0-4.0 layout).

    Frame number; marker sets, unlabeled markers (both empty); the rigid bodies (id, position,
    quaternion x y z w, mean marker error, params with bit 0 = tracking valid); skeletons,
    labeled markers, force plates, devices (all empty); the suffix (timecode, timestamp as a
    double, three high-resolution stamps, params) and the end-of-data tag 0.
    """
    parts = [_INT.pack(frame_number), _INT.pack(0), _INT.pack(0), _INT.pack(len(bodies))]
    for body in bodies:
        parts.append(
            _RIGID_BODY.pack(
                body.id,
                *body.position,
                *body.orientation_xyzw,
                body.mean_error,
                1 if body.valid else 0,
            )
        )
    parts.append(b"\0" * 16)  # no skeletons, labeled markers, force plates, devices
    parts.append(_SUFFIX.pack(0, 0, timestamp_s, *stamps, 0, 0))
    return encode_packet(NAT_FRAMEOFDATA, b"".join(parts))


@dataclass(frozen=True)
class ReplayStats:
    """What a replay server did.

    Attributes
    ----------
    frames_sent : int
        Frames of the recording streamed (frames dropped on purpose are not sent).
    frames_total : int
        Frames in the recording.
    packets_sent : int
        Frame packets over all subscribers.
    clients : int
        Subscribers that connected.
    max_late_s : float
        Worst delay of a frame behind its deadline, seconds.
    """

    frames_sent: int
    frames_total: int
    packets_sent: int
    clients: int
    max_late_s: float


class ReplayServerError(DriverError):
    """The replay server process could not start (its port in use, its address not local)."""


class NatNetReplayServer:
    """Streams a recording as a NatNet server would, from a process of its own.

    Parameters
    ----------
    recording : Recording
        Positions (metres, tracker frame), times (seconds; strictly increasing) and orientations
        (x, y, z, w; identity if absent). Times are the frames' timestamps and their schedule.
    rigid_body : str
        The replayed body's name.
    rigid_body_id : int
        Its streaming id.
    valid : ndarray of shape (N,), bool, optional
        False for frames where the body was not tracked: those are sent flagged not valid, with
        a zero position and identity orientation. All valid if not given.
    other_rigid_bodies : sequence of str
        More bodies to describe and stream (ids ``rigid_body_id + 1, ...``, listed before the
        replayed one), at rest at the origin, so clients have to pick theirs by name.
    drop_frames : sequence of int
        Indices of frames not to send at all (a lossy network): their frame numbers are skipped.
    host : str
        A loopback address to bind, 127.0.0.1 by default.
    command_port : int
        The command port; 0 picks a free one (read :attr:`command_port` after :meth:`start`).
    data_port : int
        The data port advertised in the server info (unicast frames do not use it).
    rate_hz : float, optional
        Stream at this rate instead of the recording's times (frame ``i`` at ``t0 + i/rate``);
        needed for a recording without times.
    first_frame : int
        Frame number of the first sample.
    units : {"m", "mm"}
        Length unit of the streamed positions (Motive streams metres).

    Examples
    --------
    >>> with NatNetReplayServer(recording, rigid_body="Pen", command_port=0) as server:
    ...     source = NatNetSource(NatNetConfig(rigid_body="Pen", command_port=server.command_port))
    """

    def __init__(
        self,
        recording: Recording,
        *,
        rigid_body: str = "Pen",
        rigid_body_id: int = 1,
        valid: np.ndarray | None = None,
        other_rigid_bodies: Sequence[str] = (),
        drop_frames: Sequence[int] = (),
        host: str = "127.0.0.1",
        command_port: int = 1510,
        data_port: int = 1511,
        rate_hz: float | None = None,
        first_frame: int = 1,
        units: str = "m",
    ) -> None:
        try:
            loopback = ipaddress.IPv4Address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"the replay server binds loopback addresses only, not {host!r}")
        n = len(recording)
        if rate_hz is not None:
            if not rate_hz > 0:
                raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
            t0 = 0.0 if recording.t_s is None else float(recording.t_s[0])
            times = t0 + np.arange(n) / rate_hz
        elif recording.t_s is None:
            raise ValueError("the recording has no times: give rate_hz")
        else:
            times = np.asarray(recording.t_s, dtype=np.float64)
        valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        if valid.shape != (n,):
            raise ValueError(f"valid has shape {valid.shape}; expected ({n},)")
        drops = np.zeros(n, dtype=bool)
        drop_index = np.asarray(list(drop_frames), dtype=np.int64)
        if drop_index.size and (drop_index.min() < 0 or drop_index.max() >= n):
            raise ValueError(f"drop_frames must be frame indices in [0, {n})")
        drops[drop_index] = True
        names = [rigid_body, *other_rigid_bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"rigid body names must be distinct, got {names}")
        quats = recording.orientations_xyzw
        if quats is None:
            quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        scale = 1.0 / metres_per(units)
        self.n_frames = n
        self.host = host
        self._plan = {
            "host": host,
            "command_port": int(command_port),
            "data_port": int(data_port),
            "times": times,
            "positions": np.asarray(recording.points_m, dtype=np.float64) * scale,
            "quats": np.asarray(quats, dtype=np.float64),
            "valid": valid,
            "drops": drops,
            # The other bodies come first, so a client has to pick its body by id.
            "bodies": [(name, rigid_body_id + 1 + k) for k, name in enumerate(other_rigid_bodies)]
            + [(rigid_body, rigid_body_id)],
            "first_frame": int(first_frame),
        }
        self._ctx = multiprocessing.get_context("spawn")
        self._process: multiprocessing.process.BaseProcess | None = None
        self._pipe: Connection | None = None
        self._stop = self._ctx.Event()
        self._done = self._ctx.Event()
        self._sent = self._ctx.Value("q", 0, lock=False)
        self._port: int | None = None
        self._stats: ReplayStats | None = None

    @property
    def command_port(self) -> int:
        """The bound command port (after :meth:`start`)."""
        if self._port is None:
            raise ReplayServerError("the server is not started")
        return self._port

    @property
    def frames_sent(self) -> int:
        """Frames streamed so far."""
        return int(self._sent.value)

    def start(self, *, timeout_s: float = 20.0) -> NatNetReplayServer:
        """Start the server process and wait until it listens.

        Raises
        ------
        ReplayServerError
            The process could not bind its port or did not start within ``timeout_s``.
        """
        if self._process is not None:
            return self
        parent, child = self._ctx.Pipe()
        self._process = self._ctx.Process(
            target=_serve,
            args=(self._plan, child, self._stop, self._done, self._sent),
            name=f"natnet replay {self.host}",
            daemon=True,
        )
        self._process.start()
        child.close()
        self._pipe = parent
        if not parent.poll(timeout_s):
            self._kill()
            raise ReplayServerError(f"the replay server did not start within {timeout_s} s")
        kind, payload = parent.recv()
        if kind == "error":
            self._kill()
            raise ReplayServerError(payload)
        self._port = payload
        return self

    def wait_done(self, timeout_s: float | None = None) -> bool:
        """Wait until every frame was streamed; False on timeout."""
        return self._done.wait(timeout_s)

    def stop(self, *, timeout_s: float = 10.0) -> ReplayStats:
        """Stop the server and return what it did (idempotent)."""
        if self._stats is not None:
            return self._stats
        stats = ReplayStats(self.frames_sent, self.n_frames, 0, 0, 0.0)
        if self._process is not None:
            self._stop.set()
            if self._pipe is not None and self._pipe.poll(timeout_s):
                try:
                    kind, payload = self._pipe.recv()
                    if kind == "stats":
                        stats = ReplayStats(**payload)
                except (EOFError, OSError):
                    pass
            self._process.join(timeout=timeout_s)
            self._kill()
        self._stats = stats
        return stats

    def _kill(self) -> None:
        if self._process is not None and self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=5)
        if self._pipe is not None:
            self._pipe.close()
        self._pipe = None

    def __enter__(self) -> NatNetReplayServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- the server process ------------------------------------------------------------------------

#: Longest wait in the loop, so a stop request is seen promptly while idle.
_IDLE_POLL_S = 0.05


def _serve(  # pragma: no cover - child
    plan: dict[str, Any],
    pipe: Connection,
    stop_event: Event,
    done_event: Event,
    sent: c_longlong,
) -> None:
    # Ctrl-C reaches the whole process group: the parent decides when the server stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        sock.bind((plan["host"], plan["command_port"]))
    except OSError as exc:
        pipe.send(("error", f"cannot bind {plan['host']}:{plan['command_port']}: {exc.strerror}"))
        return
    # A burst after a late wake-up must not block on a full send buffer.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
    sock.setblocking(False)
    server = _Streamer(plan, sock, sent)
    pipe.send(("listening", sock.getsockname()[1]))
    try:
        server.run(stop_event, done_event)
    finally:
        sock.close()
        try:
            pipe.send(("stats", server.stats()))
        except OSError:
            pass  # the parent is gone


class _Streamer:  # pragma: no cover - runs in the server process
    def __init__(self, plan: dict[str, Any], sock: socket.socket, sent: c_longlong) -> None:
        self.plan, self.sock, self.sent = plan, sock, sent
        self.clients: dict[tuple[str, int], float] = {}
        self.n_clients = 0
        self.index = 0
        self.start: float | None = None
        self.frames_sent = self.packets_sent = 0
        self.max_late_s = 0.0
        self.last_packet: bytes | None = None
        self.offsets = plan["times"] - plan["times"][0] if len(plan["times"]) else plan["times"]
        self.server_info = encode_server_info(data_port=plan["data_port"])
        self.model_defs = encode_model_definitions(plan["bodies"])
        # The bodies other than the replayed one (the last) rest at the origin.
        self.target_id = plan["bodies"][-1][1]
        self.others = [
            RigidBodyPose(body_id, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), True, 0.0)
            for _, body_id in plan["bodies"][:-1]
        ]

    def stats(self) -> dict[str, Any]:
        return {
            "frames_sent": self.frames_sent,
            "frames_total": len(self.offsets),
            "packets_sent": self.packets_sent,
            "clients": self.n_clients,
            "max_late_s": self.max_late_s,
        }

    def run(self, stop_event: Event, done_event: Event) -> None:
        n = len(self.offsets)
        if n == 0:
            done_event.set()
        parent = os.getppid()
        # A parent killed without stopping us leaves this process to init: stop then too.
        while not stop_event.is_set() and os.getppid() == parent:
            now = time.monotonic()
            wait = _IDLE_POLL_S
            if self.start is not None and self.index < n:
                wait = min(wait, max(0.0, self.start + self.offsets[self.index] - now))
            readable, _, _ = select.select([self.sock], [], [], wait)
            if readable:
                self.handle_requests()
            if self.start is None or self.index >= n:
                continue
            now = time.monotonic()
            # Absolute deadlines: every frame whose time has come goes now, so a late wake-up
            # is caught up at once and the stream never drifts.
            while self.index < n and self.start + self.offsets[self.index] <= now:
                self.max_late_s = max(
                    self.max_late_s, float(now - self.start - self.offsets[self.index])
                )
                if not self.plan["drops"][self.index]:
                    self.send_frame(self.index)
                self.index += 1
            if self.index >= n:
                done_event.set()

    def handle_requests(self) -> None:
        while True:
            try:
                data, address = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue  # an ICMP error from a client that went away
            if len(data) < 4:
                continue
            message_id, _ = _HEADER.unpack_from(data)
            if message_id == NAT_CONNECT:
                if address not in self.clients:
                    self.n_clients += 1
                self.clients[address] = time.monotonic()
                self.reply(self.server_info, address)
                if self.start is None:
                    self.start = time.monotonic()
            elif message_id == NAT_KEEPALIVE:
                if address in self.clients:
                    self.clients[address] = time.monotonic()
            elif message_id == NAT_REQUEST_MODELDEF:
                self.reply(self.model_defs, address)
            elif message_id == NAT_REQUEST_FRAMEOFDATA:
                if self.last_packet is not None:
                    self.reply(self.last_packet, address)
            elif message_id == NAT_DISCONNECT:
                self.clients.pop(address, None)
            elif message_id == NAT_REQUEST:
                self.reply(encode_packet(NAT_UNRECOGNIZED_REQUEST, b""), address)

    def reply(self, packet: bytes, address: tuple[str, int]) -> None:
        try:
            self.sock.sendto(packet, address)
        except OSError:
            pass  # the client is gone; UDP has nobody to tell

    def send_frame(self, i: int) -> None:
        plan = self.plan
        valid = bool(plan["valid"][i])
        if valid:
            position = tuple(plan["positions"][i])
            quat = tuple(plan["quats"][i])
        else:
            position, quat = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)
        body = RigidBodyPose(self.target_id, position, quat, valid, 2e-4 if valid else 0.0)
        stamp = time.monotonic_ns()
        packet = encode_frame(
            plan["first_frame"] + i,
            float(plan["times"][i]),
            [*self.others, body],
            stamps=(stamp, stamp, stamp),
        )
        self.last_packet = packet
        for address in self.clients:
            self.reply(packet, address)
            self.packets_sent += 1
        self.frames_sent += 1
        self.sent.value = self.frames_sent
