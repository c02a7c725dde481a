"""The live NatNet feed on loopback, against our own NatNet replay server.

The server streams a synthetic recording at 360 Hz from its own process; NatNetSource receives it
in its own child process. Every test binds 127.0.0.1 on ports the system picks, so runs in
parallel do not collide.
"""

import socket
import struct
import sys
import threading
import time

import numpy as np
import pytest
from natnet import DataDescriptions, DataFrame, ServerInfo, Version
from natnet.packet_buffer import PacketBuffer
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from drivers.tracking import natnet_server as ns
from drivers.tracking.base import SOURCES, source_class
from drivers.tracking.canonical_csv import read_trace_csv
from drivers.tracking.natnet_server import NatNetReplayServer, RigidBodyPose
from drivers.tracking.natnet_source import (
    STARTUP_ALLOWANCE_S,
    NatNetConfig,
    NatNetSource,
    TrackerTimeoutError,
    UnknownRigidBodyError,
)
from drivers.tracking.record import record_natnet
from recon.inputs import Recording

RATE_HZ = 360.0
T0_S = 1234.5  # Motive's timestamps count from its start, not from zero


def synthetic(seconds: float, rate_hz: float = RATE_HZ) -> Recording:
    """A pen circling over a table while it turns and tilts, sampled at ``rate_hz``."""
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    angle = 2 * np.pi * t / 2.0
    points = np.column_stack(
        [0.4 + 0.1 * np.cos(angle), -0.2 + 0.1 * np.sin(angle), 0.05 + 0.01 * np.sin(3 * angle)]
    )
    euler = np.column_stack([angle, 0.3 * np.sin(angle), 0.2 * np.cos(2 * angle)])
    quats = Rotation.from_euler("zyx", euler).as_quat(scalar_first=False)
    return Recording(points_m=points, t_s=T0_S + t, orientations_xyzw=quats)


def config(server: NatNetReplayServer, **overrides) -> NatNetConfig:
    fields = {
        "rigid_body": "Pen",
        "command_port": server.command_port,
        "timeout_s": 3.0,
        "stall_timeout_s": 3.0,
    }
    return NatNetConfig(**(fields | overrides))


def collect(source: NatNetSource, last_frame: int) -> dict:
    """Every batch up to frame number ``last_frame`` (or until the stream stalls)."""
    batches = []
    try:
        for batch in source.batches():
            batches.append(batch)
            if source.stats.last_frame >= last_frame:
                break
    except TrackerTimeoutError:
        pass  # the stream ended short: the counts checked by the caller say by how much
    return {
        "frame": np.concatenate([b.frame_numbers for b in batches]),
        "t": np.concatenate([b.t_s for b in batches]),
        "p": np.concatenate([b.position_m for b in batches]),
        "q": np.concatenate([b.orientation_xyzw for b in batches]),
        "valid": np.concatenate([b.valid for b in batches]),
    }


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


# -- the packets, against the natnet client's own parsers --------------------------------------


def _payload(packet: bytes, message_id: int) -> PacketBuffer:
    buffer = PacketBuffer(packet)
    assert buffer.read_uint16() == message_id
    assert buffer.read_uint16() == len(packet) - 4
    return buffer


def test_the_packets_parse_with_the_natnet_client():
    version = Version(*ns.NATNET_VERSION)
    info = ServerInfo.read_from_buffer(_payload(ns.encode_server_info(), ns.NAT_SERVERINFO), None)
    assert info.application_name == ns.APPLICATION_NAME
    assert info.nat_net_protocol_version == version

    packet = ns.encode_model_definitions([("Wand", 4), ("Pen", 3)])
    buffer = _payload(packet, ns.NAT_MODELDEF)
    models = DataDescriptions.read_from_buffer(buffer, version)
    assert buffer.pointer == len(packet)  # every byte accounted for
    assert [(d.name, d.id_num) for d in models.rigid_bodies] == [("Wand", 4), ("Pen", 3)]
    assert [m.name for m in models.rigid_bodies[1].markers] == ["Pen_1", "Pen_2", "Pen_3"]

    bodies = [
        RigidBodyPose(4, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        RigidBodyPose(3, (0.25, -0.5, 1.0), (0.0, 0.6, 0.0, 0.8), valid=False, mean_error=1e-3),
    ]
    packet = ns.encode_frame(42, 12.345678901, bodies, stamps=(1, 2, 3))
    buffer = _payload(packet, ns.NAT_FRAMEOFDATA)
    frame = DataFrame.read_from_buffer(buffer, version)
    # natnet does not read the end-of-data tag: 4 bytes left.
    assert buffer.pointer == len(packet) - 4
    assert struct.unpack_from("<i", packet, buffer.pointer) == (0,)
    assert frame.prefix.frame_number == 42
    assert frame.suffix.timestamp == 12.345678901
    assert frame.suffix.stamp_transmit == 3
    pen = frame.rigid_bodies[1]
    assert pen.id_num == 3 and pen.tracking_valid is False
    np.testing.assert_allclose(pen.pos, (0.25, -0.5, 1.0))
    np.testing.assert_allclose(pen.rot, (0.0, 0.6, 0.0, 0.8), atol=1e-7)
    assert frame.rigid_bodies[0].tracking_valid is True


def test_the_replay_server_binds_loopback_only_and_checks_its_inputs():
    rec = synthetic(0.1)
    for host in ("0.0.0.0", "192.168.1.5", "localhost"):
        with pytest.raises(ValueError, match="loopback"):
            NatNetReplayServer(rec, host=host)
    with pytest.raises(ValueError, match="valid has shape"):
        NatNetReplayServer(rec, valid=np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match="distinct"):
        NatNetReplayServer(rec, rigid_body="Pen", other_rigid_bodies=["Pen"])
    with pytest.raises(ValueError, match="rate_hz"):
        NatNetReplayServer(Recording(points_m=rec.points_m))


@pytest.mark.timeout(60)
def test_the_server_speaks_natnet_to_a_plain_socket():
    """Connect, model definitions, frames to the requesting socket, disconnect: raw UDP."""
    rec = synthetic(1.0)
    with (
        NatNetReplayServer(rec, command_port=0, rigid_body_id=7) as server,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client,
    ):
        client.bind(("127.0.0.1", 0))
        client.settimeout(5.0)
        address = ("127.0.0.1", server.command_port)
        client.sendto(ns.encode_packet(ns.NAT_CONNECT, b"Ping\0"), address)
        reply = client.recv(65536)
        assert struct.unpack_from("<H", reply) == (ns.NAT_SERVERINFO,)
        client.sendto(ns.encode_packet(ns.NAT_REQUEST_MODELDEF, b"\0"), address)
        message_ids = set()
        first_frame = None
        while ns.NAT_MODELDEF not in message_ids or len(message_ids) < 2:
            packet = client.recv(65536)
            message_ids.add(struct.unpack_from("<H", packet)[0])
            if first_frame is None and packet[:2] == struct.pack("<H", ns.NAT_FRAMEOFDATA):
                first_frame = struct.unpack_from("<i", packet, 4)[0]
        assert message_ids == {ns.NAT_MODELDEF, ns.NAT_FRAMEOFDATA}
        assert first_frame == 1
        client.sendto(ns.encode_packet(ns.NAT_DISCONNECT, b"\0"), address)
        server.wait_done(timeout_s=10)
        stats = server.stop()
    assert stats.frames_sent == stats.frames_total == len(rec)
    assert stats.clients == 1
    # Disconnected mid-stream: the rest of the frames went to nobody.
    assert stats.packets_sent < stats.frames_sent


# -- the source ------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_every_frame_arrives_with_its_pose_and_lost_frames_are_flagged_invalid():
    rec = synthetic(3.0)
    n = len(rec)
    valid = np.ones(n, dtype=bool)
    valid[200:260] = False  # the pen out of view for a sixth of a second
    valid[900] = False
    with NatNetReplayServer(
        rec,
        rigid_body="Pen",
        rigid_body_id=3,
        other_rigid_bodies=["Wand", "Tray"],
        valid=valid,
        command_port=0,
    ) as server:
        source = NatNetSource(config(server))
        try:
            info = source.connect()
            got = collect(source, last_frame=n)
        finally:
            source.close()
        sent = server.stop()
    assert info.rigid_body_id == 3 and info.rigid_bodies == ("Wand", "Tray", "Pen")
    assert info.natnet_version == "4.0.0.0"
    assert sent.frames_sent == n
    stats = source.stats
    assert (stats.frames_received, stats.frames_dropped, stats.frames_out_of_order) == (n, 0, 0)
    assert stats.frames_invalid == int((~valid).sum())
    np.testing.assert_array_equal(got["frame"], np.arange(1, n + 1))
    np.testing.assert_array_equal(got["t"], rec.t_s)  # doubles on the wire
    np.testing.assert_array_equal(got["valid"], valid)
    # float32 on the wire: a few 1e-8 m at half a metre.
    np.testing.assert_allclose(got["p"][valid], rec.points_m[valid], rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["q"][valid], rec.orientations_xyzw[valid], rtol=0, atol=1e-6)
    assert np.isnan(got["p"][~valid]).all() and np.isnan(got["q"][~valid]).all()


@pytest.mark.timeout(60)
def test_dropped_frames_are_counted_by_frame_number_and_millimetres_converted():
    rec = synthetic(1.0)
    n = len(rec)
    dropped = [10, 11, 12, 200]
    with NatNetReplayServer(rec, drop_frames=dropped, units="mm", command_port=0) as server:
        source = NatNetSource(config(server, units="mm"))
        try:
            got = collect(source, last_frame=n)
        finally:
            source.close()
        sent = server.stop()
    assert sent.frames_sent == n - len(dropped)
    stats = source.stats
    assert (stats.frames_received, stats.frames_dropped) == (n - len(dropped), len(dropped))
    kept = np.setdiff1d(np.arange(n), dropped)
    np.testing.assert_array_equal(got["frame"], kept + 1)
    # Millimetres in float32 on the wire: a few 1e-5 mm.
    np.testing.assert_allclose(got["p"], rec.points_m[kept], rtol=0, atol=1e-6)


@pytest.mark.timeout(60)
def test_an_unknown_rigid_body_is_an_error_listing_the_names_streamed():
    with NatNetReplayServer(
        synthetic(1.0), rigid_body="Pen", other_rigid_bodies=["Wand"], command_port=0
    ) as server:
        source = NatNetSource(config(server, rigid_body="Stylus"))
        with pytest.raises(UnknownRigidBodyError, match="'Stylus'.*streams 'Wand', 'Pen'"):
            source.connect()
        assert source._process is None  # the receiver is gone with the error
        source.close()


@pytest.mark.timeout(60)
def test_no_server_is_a_timeout_within_the_bound():
    port = free_udp_port()  # nothing listens there
    source = NatNetSource(NatNetConfig(rigid_body="Pen", command_port=port, timeout_s=1.0))
    start = time.monotonic()
    with pytest.raises(TrackerTimeoutError, match=f"no NatNet server answered at 127.0.0.1:{port}"):
        list(source.batches())
    # The receiver's own timeout, plus its start-up: never the whole of the parent's bound.
    assert time.monotonic() - start < 1.0 + STARTUP_ALLOWANCE_S
    assert source._process is None
    source.close()


@pytest.mark.timeout(60)
def test_close_is_clean_idempotent_and_ends_a_running_iteration():
    never_connected = NatNetSource(NatNetConfig(rigid_body="Pen"))
    never_connected.close()
    never_connected.close()
    assert list(never_connected.batches()) == []

    with NatNetReplayServer(synthetic(5.0), command_port=0) as server:
        source = NatNetSource(config(server))
        source.connect()
        process = source._process
        received = []
        ended = threading.Event()

        def consume():
            for batch in source.batches():
                received.append(len(batch))
            ended.set()

        consumer = threading.Thread(target=consume, daemon=True)
        consumer.start()
        while sum(received) < 100:
            time.sleep(0.01)
        source.close()
        assert ended.wait(5.0)  # batches() returned instead of raising or hanging
        consumer.join()
        source.close()
        assert not process.is_alive() and process.exitcode == 0  # it stopped on request
        assert list(source.batches()) == []
        server.stop()


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_a_parent_holding_the_gil_for_2_s_loses_no_frame():
    rec = synthetic(4.0)
    n = len(rec)
    ticks = []
    ticking = threading.Event()
    ticking.set()

    def tick():
        while ticking.is_set():
            time.sleep(0.01)
            ticks.append(time.monotonic())  # after the sleep: it needs the GIL back first

    with NatNetReplayServer(rec, command_port=0) as server:
        source = NatNetSource(config(server))
        try:
            source.connect()
            batches = source.batches()
            first = next(batches)
            ticker = threading.Thread(target=tick, daemon=True)
            ticker.start()
            time.sleep(0.05)
            # No thread of this process runs while the main thread spins: the interpreter
            # would only hand the GIL over after the (raised) switch interval.
            interval = sys.getswitchinterval()
            sys.setswitchinterval(100.0)
            try:
                end = time.perf_counter() + 2.0
                spins = 0
                while time.perf_counter() < end:
                    spins += 1
            finally:
                sys.setswitchinterval(interval)
            ticking.clear()
            ticker.join()
            total = len(first)
            for batch in batches:
                total += len(batch)
                if source.stats.last_frame >= n:
                    break
        finally:
            source.close()
        sent = server.stop()
    gaps = np.diff(ticks)
    assert gaps.max() > 1.5  # the GIL really was held for the whole spin
    assert sent.frames_sent == n
    assert total == source.stats.frames_received == n
    assert source.stats.frames_dropped == 0


def test_the_config_refuses_typos_and_the_registry_is_not_needed_to_build_it():
    with pytest.raises(ValidationError):
        NatNetConfig(rigid_body="Pen", prot=1510)
    with pytest.raises(ValidationError, match="IPv4"):
        NatNetConfig(rigid_body="Pen", local="my-laptop")
    assert NatNetSource(NatNetConfig(rigid_body="Pen")).kind == "natnet"


@pytest.mark.skipif(
    "natnet" not in SOURCES,
    reason='"natnet" is not registered in drivers.tracking.base.SOURCES yet',
)
def test_the_source_is_registered():
    assert source_class("natnet") is NatNetSource


# -- recording to a file ---------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_record_writes_the_tracked_frames_until_the_stream_ends(tmp_path):
    rec = synthetic(1.5)
    n = len(rec)
    valid = np.ones(n, dtype=bool)
    valid[100:130] = False
    dropped = [300, 301]
    with NatNetReplayServer(rec, valid=valid, drop_frames=dropped, command_port=0) as server:
        summary = record_natnet(config(server, stall_timeout_s=0.5), tmp_path / "pen.csv")
        server.stop()
    written = valid.copy()
    written[dropped] = False
    assert summary.stop_reason == "stream_stalled"
    assert summary.frames_received == n - len(dropped)
    assert summary.frames_dropped == len(dropped)
    assert summary.frames_invalid == int((~valid).sum())
    assert summary.frames_written == int(written.sum())
    assert summary.t0_s == rec.t_s[0]
    back = read_trace_csv(tmp_path / "pen.csv")
    np.testing.assert_allclose(back.t_s, rec.t_s[written] - rec.t_s[0], atol=1e-8)
    np.testing.assert_allclose(back.points_m, rec.points_m[written], atol=1e-6)
    np.testing.assert_allclose(back.orientations_xyzw, rec.orientations_xyzw[written], atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["pen.csv"]  # no temporary left behind


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_record_stops_after_its_duration_or_on_the_stop_event(tmp_path):
    rec = synthetic(2.0)
    with NatNetReplayServer(rec, command_port=0) as server:
        summary = record_natnet(config(server), tmp_path / "half.csv", duration_s=0.5)
        server.stop()
    # The first client starts the replay: frame 1 is the first frame received.
    expected = int(np.sum(rec.t_s - rec.t_s[0] < 0.5))
    assert summary.stop_reason == "duration"
    assert summary.frames_written == summary.frames_received == expected
    assert len(read_trace_csv(tmp_path / "half.csv")) == expected

    with NatNetReplayServer(rec, command_port=0) as server:
        stop = threading.Event()

        def stop_when_streaming():
            while server.frames_sent < 200:
                time.sleep(0.01)
            stop.set()

        threading.Thread(target=stop_when_streaming, daemon=True).start()
        summary = record_natnet(config(server), tmp_path / "stopped.csv", stop_event=stop)
        server.stop()
    assert summary.stop_reason == "stop_event"
    assert 0 < summary.frames_written < len(rec)
    assert len(read_trace_csv(tmp_path / "stopped.csv")) == summary.frames_written
