"""The fake UR controller: its protocol pieces, the canary on ur_rtde's private protocol, and
the ur_rtde adapter's fault handling end to end against it.

Unit tests run in-process; everything that touches ur_rtde talks to a fake in its own process
(``tests/drivers/fake_ur_fixture.py``) and carries a timeout, since ur_rtde waits up to 300 s for
a command.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
import time
from importlib.metadata import version

import numpy as np
import pytest
from scipy.spatial import cKDTree

from drivers.errors import (
    ConnectionLostError,
    EmergencyStopError,
    MotionStoppedError,
    ProtectiveStopError,
    RobotTimeoutError,
)
from drivers.robot.base import RobotState
from drivers.robot.clock import FakeClock
from drivers.robot.fake_ur import control_script as cs
from drivers.robot.fake_ur import controller as ctl
from drivers.robot.fake_ur import dashboard, rtde_server, watchdog
from drivers.robot.fake_ur import rtde_protocol as rp
from drivers.robot.sim import HOME_RAD, SimBackend, SimConfig
from drivers.robot.ur_rtde import URRtdeBackend, URRtdeConfig
from recon import kinematics
from recon.transforms import pose_from_transform
from tests.drivers import fake_ur_fixture
from tests.motion_fixtures import base_from_tracker, line_process

# The fake controller's fixtures, used by name.
fake_ur_process = fake_ur_fixture.fake_ur_process
fake_ur = fake_ur_fixture.fake_ur

# The fake controller runs in real time: seconds per test (make test-fast leaves them out).
pytestmark = pytest.mark.slow

UR_RTDE_VERSION = "1.6.5"

# A stand-in control script with the markers and layout the fake relies on (written for these
# tests; the canary checks the real upload has the same markers).
SCRIPT = """def rtde_control():
# HEADER_BEGIN
    global reg_offset_float = # float register offset
{offset}    global reg_offset_int = # int register offset
{offset}    global is_servoing = 0
    def write_output_integer_reg(register_index, value):
        write_output_integer_register(register_index + reg_offset_int, value)
    end
    def exec_move_path():
        textmsg("exec_move_path")
        # inject move path
{moves}    end
    def rtde_cmd():
      cmd = read_input_integer_reg(0)
      return cmd
    end
    def signal_ready():
        write_output_integer_reg(0, 1)
    end
    def signal_done_with_cmd():
        write_output_integer_reg(0, 2)
    end
    def write_async_progress_register(value):
        write_output_integer_reg(2, reg_value)
    end
# HEADER_END
# NODE_CONTROL_LOOP_BEGINS
    signal_ready()
# NODE_CONTROL_LOOP_ENDS
end
"""


def _script(offset=0, moves=""):
    return SCRIPT.format(offset=offset, moves=moves)


# -- RTDE wire format ----------------------------------------------------------------------------


def test_field_types_follow_the_rtde_table():
    assert rp.output_type("actual_q") == "VECTOR6D"
    assert rp.output_type("runtime_state") == "UINT32"
    assert rp.output_type("robot_mode") == "INT32"
    assert rp.output_type("output_int_register_47") == "INT32"
    assert rp.output_type("output_int_register_48") is None
    assert rp.output_type("output_bit_register_64") == "BOOL"
    assert rp.output_type("no_such_field") is None
    assert rp.input_type("input_double_register_24") == "DOUBLE"
    assert rp.input_type("external_force_torque") == "VECTOR6D"
    assert rp.input_type("actual_q") is None  # outputs are not writable


def test_recipe_round_trip_and_packet_framing():
    recipe = rp.Recipe(3, ("timestamp", "actual_q", "robot_mode"), ("DOUBLE", "VECTOR6D", "INT32"))
    values = {"timestamp": 1.5, "actual_q": tuple(range(6)), "robot_mode": 7}
    body = recipe.pack(values)
    assert body[0] == 3 and len(body) == 1 + 8 + 48 + 4
    assert recipe.unpack(body[1:]) == {**values, "actual_q": tuple(float(v) for v in range(6))}
    stream = bytearray(rp.packet(rp.DATA_PACKAGE, body) + rp.packet(rp.START)[:2])
    packets = rp.split_packets(stream)
    assert packets == [(rp.DATA_PACKAGE, body)] and len(stream) == 2  # partial packet kept


# -- the control script ----------------------------------------------------------------------------


def test_script_markers_offset_and_injected_path_are_read():
    moves = (
        "\tsignal_async_progress(0)\n"
        "\tmovej([0.1,-1.5,1.5,-1.5,-1.5,0],a=1.2,v=0.5,r=0.01)\n"
        "\tsignal_async_progress(1)\n"
        "\tmovej([0.2,-1.5,1.5,-1.5,-1.5,1e-3],a=1.2,v=0.4,r=0)\n"
    )
    info = cs.inspect(_script(24, moves))
    assert info.is_rtde_control and info.int_offset == 24 and info.float_offset == 24
    assert [m.speed for m in info.path] == [0.5, 0.4]
    assert info.path[0].blend_m == 0.01 and info.path[1].target[5] == pytest.approx(1e-3)
    assert cs.program_complete(_script()) and not cs.program_complete(_script()[:-5])
    assert not cs.inspect("def other():\n  textmsg(1)\nend\n").is_rtde_control


def test_protocol_differences_name_missing_command_branches_and_real_time_changes():
    assert "command 45 branch" in cs.protocol_differences(_script())
    realtime = " or ".join(f"cmd == {c}" for c in sorted(cs.REALTIME_COMMANDS))
    branches = "".join(
        f"        elif cmd == {c}:\n            x = 1\n"
        + "".join(f"            {marker}\n" for marker in cs.BRANCH_MARKERS.get(c, ()))
        for c in cs.EMULATED_COMMANDS
    )
    arguments = "".join(f"    {marker}\n" for marker in cs.ARGUMENT_MARKERS.values())
    complete = _script().replace(
        "# NODE_CONTROL_LOOP_BEGINS",
        f"{arguments}{branches}        if {realtime}:\n# NODE_CONTROL_LOOP_BEGINS",
    )
    assert cs.protocol_differences(complete) == []
    renumbered = complete.replace("cmd == 45:", "cmd == 46:", 1)
    assert cs.protocol_differences(renumbered)[0] == "command 45 branch"
    fewer = complete.replace(" or cmd == 71", "")
    assert cs.protocol_differences(fewer)[0].startswith("real-time command list")
    # An upgrade that renumbers setTcp and setPayload keeps branches with those ids, but
    # their calls move: the branch markers catch it.
    swapped = (
        complete.replace(f"cmd == {cs.CMD_SET_TCP}:", "cmd == 999:")
        .replace(f"cmd == {cs.CMD_SET_PAYLOAD}:", f"cmd == {cs.CMD_SET_TCP}:")
        .replace("cmd == 999:", f"cmd == {cs.CMD_SET_PAYLOAD}:")
    )
    differences = cs.protocol_differences(swapped)
    assert f"command {cs.CMD_SET_TCP} branch lacks 'set_tcp(pose)'" in differences
    assert f"command {cs.CMD_SET_PAYLOAD} branch lacks 'set_payload(mass, cog)'" in differences


def _run_until(controller, condition, max_s=10.0):
    for _ in range(int(max_s * controller.rate_hz)):
        controller.step()
        if condition():
            return
    raise AssertionError("the fake controller never got there")


def test_the_emulated_script_runs_a_synchronous_move_j():
    c = ctl.FakeController("ur5e")
    assert c.load_program(_script(24))
    assert c.out_int[24] == 1  # ready
    goal = np.array(HOME_RAD) + [0.2, 0, 0, 0, 0, 0]
    c.in_double[24:32] = [*goal, 1.0, 2.0]  # q, speed, acceleration
    c.in_int[25] = 0  # not async
    c.in_int[24] = cs.CMD_MOVEJ
    _run_until(c, lambda: c.out_int[24] == 2)
    assert np.abs(c.q - goal).max() < 2e-3
    c.in_int[24] = 0
    c.step()
    assert c.out_int[24] == 1


def _move_j_ticks(c, goal, slider_at=()):
    """Run a synchronous moveJ to ``goal`` from where the arm is; ``slider_at``: (tick,
    fraction) pairs written to the speed slider as a client would. Returns the joints of every
    tick until the move is done, shape (T, 6)."""
    c.in_double[24:32] = [*goal, 1.0, 2.0]
    c.in_int[25] = 0
    c.in_int[24] = cs.CMD_MOVEJ
    changes = dict(slider_at)
    q = []
    for tick in range(int(30 * c.rate_hz)):
        if tick in changes:
            c.apply_inputs({"speed_slider_mask": 1, "speed_slider_fraction": changes[tick]})
        c.step()
        q.append(c.q.copy())
        if c.out_int[24] == 2:
            c.in_int[24] = 0
            c.step()
            return np.array(q)
    raise AssertionError("the move never ended")


def test_the_speed_slider_scales_a_timed_move_along_the_same_way_and_holds_it_at_zero():
    """UR's speed slider (RTDE speed_slider_fraction): a moveJ at half the slider takes twice
    as long along the same joint path; at 0 the arm comes to rest on that path and waits, and
    goes on to the goal when the slider is raised. The scaling ramps, never jumps; a package
    without the mask, or a value that is not a number, changes nothing; one outside 0..1 takes
    the nearest end."""
    goal = np.array(HOME_RAD) + [0.6, -0.3, 0.4, 0.0, 0.0, 0.5]
    full = ctl.FakeController("ur5e")
    assert full.load_program(_script(24))
    at_full = _move_j_ticks(full, goal)
    half = ctl.FakeController("ur5e")
    assert half.load_program(_script(24))
    at_half = _move_j_ticks(half, goal, slider_at=[(0, 0.5)])
    assert half.outputs()["target_speed_fraction"] == 0.5
    assert half.outputs()["speed_scaling"] == 0.5

    def crossing(q, share):  # the tick the lead joint passes ``share`` of its way
        return int(np.argmax(np.abs(q[:, 0] - q[0, 0]) >= share * abs(goal[0] - q[0, 0])))

    span_full = crossing(at_full, 0.9) - crossing(at_full, 0.1)
    span_half = crossing(at_half, 0.9) - crossing(at_half, 0.1)
    assert 1.95 < span_half / span_full < 2.05, (span_half, span_full)
    # The same way: every joint position of the slow move lies on the full-speed one.
    gap = cKDTree(at_full).query(at_half)[0]
    assert gap.max() < 2e-3, gap.max()
    np.testing.assert_allclose(at_half[-1], goal, atol=2e-3)

    # Held at 0 halfway, then released: at rest on the way, then on to the goal.
    held = ctl.FakeController("ur5e")
    assert held.load_program(_script(24))
    middle = crossing(at_full, 0.4)
    stop_at = middle + int(2.0 * held.rate_hz)
    path = _move_j_ticks(held, goal, slider_at=[(middle, 0.0), (stop_at, 1.0)])
    resting = path[stop_at - int(0.5 * held.rate_hz) : stop_at]
    assert np.abs(resting - resting[-1]).max() < 1e-6, "the arm did not wait at slider 0"
    assert cKDTree(at_full).query(resting[-1])[0] < 2e-3  # on the way, not off it
    assert 0.1 < np.abs(resting[-1] - at_full[0]).max() < np.abs(goal - at_full[0]).max() - 0.05
    np.testing.assert_allclose(path[-1], goal, atol=2e-3)
    # The scaling ramped: no jump of joint speed bigger than a ramp step allows.
    speed = np.abs(np.diff(path, axis=0)).max(axis=1) * held.rate_hz
    assert np.abs(np.diff(speed)).max() < 0.05, np.abs(np.diff(speed)).max()

    c = ctl.FakeController("ur5e")
    c.apply_inputs({"speed_slider_mask": 0, "speed_slider_fraction": 0.3})
    c.apply_inputs({"speed_slider_mask": 1, "speed_slider_fraction": float("nan")})
    assert c.speed_slider == 1.0
    c.apply_inputs({"speed_slider_mask": 1, "speed_slider_fraction": 2.0})
    assert c.speed_slider == 1.0
    c.apply_inputs({"speed_slider_mask": 1, "speed_slider_fraction": -1.0})
    assert c.speed_slider == 0.0


def _command(c, cmd, doubles=(), ints=()):
    """Write a command's arguments and id the way the client does (one data package)."""
    c.in_double[: len(doubles)] = list(doubles)
    c.in_int[1 : 1 + len(ints)] = list(ints)
    c.in_int[0] = cmd


def test_speed_j_then_speed_stop_and_unknown_commands_are_answered():
    c = ctl.FakeController("ur5e")
    c.load_program(_script())
    _command(c, cs.CMD_SPEEDJ, [0.5, 0, 0, 0, 0, 0, 2.0, 0.002])
    for _ in range(250):  # 0.5 s
        c.step()
    assert c.out_int[0] == 1  # real-time commands answer "ready", never "done"
    assert c.qd[0] == pytest.approx(0.5, abs=0.05)
    _command(c, 0)
    c.step()
    _command(c, cs.CMD_SPEED_STOP, [4.0])
    _run_until(c, lambda: np.abs(c.qd).max() < 1e-4)
    _command(c, 0)
    c.step()
    _command(c, 17)  # set_payload: not emulated, still answered
    c.step()
    assert c.out_int[0] == 2


def test_move_l_fk_runs_a_straight_tcp_line():
    c = ctl.FakeController("ur5e")
    c.load_program(_script())
    start = np.array(c.tcp_pose())
    goal_q = np.array(HOME_RAD) + [0.3, 0.1, -0.1, 0, 0, 0]
    goal = np.array(c.tcp_pose(goal_q))
    _command(c, cs.CMD_MOVEL_FK, [*goal_q, 0.25, 1.2], [0])
    poses = []

    def arrived():
        poses.append(c.tcp_pose())
        return c.out_int[0] == 2

    _run_until(c, arrived)
    xyz = np.array(poses)[:, :3]
    direction = (goal[:3] - start[:3]) / np.linalg.norm(goal[:3] - start[:3])
    off_line = np.linalg.norm(np.cross(xyz - start[:3], direction), axis=1)
    assert off_line.max() < 2e-3  # the servo law's lag rounds the ends a little
    assert np.linalg.norm(xyz[-1] - goal[:3]) < 1e-3


def test_the_watchdog_logs_a_command_that_never_finishes(caplog):
    c = ctl.FakeController("ur5e")
    c.load_program(_script())
    _command(c, cs.CMD_MOVEJ, [*(np.array(HOME_RAD) + [1.0, 0, 0, 0, 0, 0]), 1.0, 2.0], [0])
    c.step()
    c.t_s += watchdog.GRACE_S + 10.0  # the move "ran" far longer than planned
    stop = threading.Event()
    thread = threading.Thread(target=watchdog.watch, args=(c, stop), kwargs={"period_s": 0.01})
    with caplog.at_level("WARNING", logger="fake_ur.watchdog"):
        thread.start()
        # Until the watchdog has looked (a busy machine may not run its thread for a while):
        # no fixed sleep, only a bound on waiting for the warning.
        deadline = time.monotonic() + 30.0
        while "stuck command" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.01)
        stop.set()
        thread.join()
    assert "stuck command: move" in caplog.text


def test_async_progress_is_encoded_like_the_script():
    c = ctl.FakeController("ur5e")
    c.load_program(_script())
    c._write_async_progress(0)
    reg = c.out_int[2]
    assert reg & 0x8000 and reg & 0x7FFF == 0  # running, progress 0
    c._write_async_progress(-1)
    assert not c.out_int[2] & 0x8000  # finished
    assert (c.out_int[2] >> 24) & 0x7F == (reg >> 24) & 0x7F  # same operation


def test_a_protective_stop_stops_the_program_until_unlocked():
    c = ctl.FakeController("ur5e")
    c.load_program(_script())
    c.protective_stop()
    assert c.runtime_state == ctl.RUNTIME_STOPPED
    assert not c.load_program(_script())  # programs do not start in a protective stop
    say = lambda line: dashboard.reply(c, line, polyscope="x", serial="1", model="UR5")  # noqa: E731
    assert say("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    # UR's controllers refuse to unlock within 5 s of the stop.
    assert say("unlock protective stop") == dashboard.UNLOCK_TOO_EARLY
    c.t_s += 4.9
    assert say("unlock protective stop") == dashboard.UNLOCK_TOO_EARLY
    c.t_s += 0.2
    assert say("unlock protective stop") == "Protective stop releasing"
    assert c.load_program(_script())
    assert say("programState") == "PLAYING rtde_control"
    assert say("robotmode") == "Robotmode: RUNNING"
    assert say("frobnicate").startswith("Could not understand")


# -- on the wire, against the fake process -----------------------------------------------------


def _request(sock, kind, payload=b""):
    sock.sendall(rp.packet(kind, payload))
    buffer = bytearray()
    while True:
        buffer += sock.recv(65536)
        for got, body in rp.split_packets(buffer):
            if got == kind:
                return body


@pytest.mark.timeout(30)
def test_rtde_handshake_recipes_and_stream(fake_ur):
    with socket.create_connection((fake_ur.host, 30004), timeout=5) as sock:
        assert _request(sock, rp.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        major, *_ = struct.unpack(">IIII", _request(sock, rp.GET_URCONTROL_VERSION))
        assert major == 5  # e-series
        # Input recipe ids are numbered per connection from 1.
        ids = [_request(sock, rp.SETUP_INPUTS, b"input_int_register_0,")[0] for _ in range(2)]
        assert ids == [1, 2]
        reply = _request(sock, rp.SETUP_OUTPUTS, struct.pack(">d", 500.0) + b"actual_q,nope,")
        assert reply[1:] == b"VECTOR6D,NOT_FOUND"
        reply = _request(sock, rp.SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,")
        assert reply[1:] == b"DOUBLE"
        assert _request(sock, rp.START) == b"\x01"
        stamps, buffer, start = [], bytearray(), time.monotonic()
        while time.monotonic() - start < 0.4:
            buffer += sock.recv(65536)
            for kind, body in rp.split_packets(buffer):
                if kind == rp.DATA_PACKAGE:
                    stamps.append(struct.unpack(">d", body[1:9])[0])
        # 125 Hz requested of a 500 Hz controller: every fourth period.
        assert np.diff(stamps) == pytest.approx(0.008, abs=1e-9)
        assert 25 <= len(stamps) <= 75
    with socket.create_connection((fake_ur.host, 30004), timeout=5) as sock:
        assert _request(sock, rp.SETUP_INPUTS, b"input_int_register_1,")[0] == 1


def _closed_by_peer(sock) -> bool:
    try:
        return sock.recv(65536) == b""
    except ConnectionResetError:
        return True


@pytest.mark.timeout(30)
def test_bad_input_on_every_port_is_answered_or_dropped_and_the_fake_lives_on(fake_ur):
    from drivers.robot.fake_ur.server import CONTROL_PORT

    # RTDE: a request too short for its fields, an impossible packet size, a recipe that is
    # not text -- each drops that client only.
    for garbage in (
        rp.packet(rp.REQUEST_PROTOCOL_VERSION, b""),
        struct.pack(">HB", 1, rp.START),
        rp.packet(rp.SETUP_INPUTS, b"\xff\xfe,"),
    ):
        with socket.create_connection((fake_ur.host, 30004), timeout=5) as sock:
            sock.sendall(garbage)
            assert _closed_by_peer(sock)
    # An input package for a recipe never set up is ignored; the connection stays usable.
    with socket.create_connection((fake_ur.host, 30004), timeout=5) as sock:
        sock.sendall(rp.packet(rp.DATA_PACKAGE, b"\x07" + bytes(8)))
        assert _request(sock, rp.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"
        assert _request(sock, rp.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 9)) == b"\x00"
    # Dashboard: what it does not know, it says so, as UR's does.
    with socket.create_connection((fake_ur.host, 29999), timeout=5) as sock:
        board = sock.makefile("rb")
        board.readline()  # the greeting
        sock.sendall(b"make coffee\n\xff\xfe\n")
        assert board.readline().startswith(b"Could not understand")
        assert board.readline().startswith(b"Could not understand")
    # The control channel: a reason for every bad request, and the next one still works.
    with socket.create_connection((fake_ur.host, CONTROL_PORT), timeout=5) as sock:
        channel = sock.makefile("rb")
        for line, reason in (
            (b"{not json\n", b"JSONDecodeError"),
            (b"[1, 2]\n", b"a request is a JSON object"),
            (b'{"cmd": "dance"}\n', b"unknown control command 'dance'"),
            (b'{"cmd": "reset", "q_rad": "home"}\n', b'"ok": false'),
        ):
            sock.sendall(line)
            assert reason in channel.readline()
    assert fake_ur.control("status")["robot"] == "ur5e"


def _protocol_2(sock):
    assert _request(sock, rp.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) == b"\x01"


@pytest.mark.timeout(30)
def test_input_fields_belong_to_one_connection_and_start_is_answered_first(fake_ur):
    with socket.create_connection((fake_ur.host, 30004), timeout=5) as first:
        assert _request(first, rp.SETUP_INPUTS, b"input_int_register_40,")[0] == 1
        with socket.create_connection((fake_ur.host, 30004), timeout=5) as second:
            reply = _request(
                second, rp.SETUP_INPUTS, b"input_double_register_40,input_int_register_40,"
            )
            assert reply == b"\x00DOUBLE,IN_USE"  # as UR's controller answers
            # The reply to START comes before the first data package, at any rate.
            _protocol_2(second)
            setup = struct.pack(">d", 500.0) + b"timestamp,"
            assert _request(second, rp.SETUP_OUTPUTS, setup)[0] == 1
            second.sendall(rp.packet(rp.START))
            buffer = bytearray()
            while not (packets := rp.split_packets(buffer)):
                buffer += second.recv(65536)
            assert packets[0] == (rp.START, b"\x01")
    # The first connection closed: its fields are free again.
    with socket.create_connection((fake_ur.host, 30004), timeout=5) as third:
        deadline = time.monotonic() + 5
        while _request(third, rp.SETUP_INPUTS, b"input_int_register_40,")[0] != 1:
            assert time.monotonic() < deadline, "the closed connection kept its input fields"
            time.sleep(0.05)


@pytest.mark.timeout(30)
def test_a_client_that_stops_reading_is_dropped_without_stalling_the_others(fake_ur):
    fields = b"".join(
        name.encode() + b"," for name, kind in rp._OUTPUTS_FIXED.items() if kind == "VECTOR6D"
    )
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fills in milliseconds
    stalled.settimeout(5)
    stalled.connect((fake_ur.host, 30004))
    with stalled, socket.create_connection((fake_ur.host, 30004), timeout=5) as reader:
        _protocol_2(stalled)
        _protocol_2(reader)
        assert _request(stalled, rp.SETUP_OUTPUTS, struct.pack(">d", 500.0) + fields)[0] == 1
        assert _request(reader, rp.SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"timestamp,")
        stalled.sendall(rp.packet(rp.START))  # and never reads again
        assert _request(reader, rp.START) == b"\x01"
        stamps, buffer, start = [], bytearray(), time.monotonic()
        clients, checked = 2, start
        while clients > 1 and time.monotonic() - start < rtde_server.SEND_STALL_S + 3.0:
            buffer += reader.recv(65536)
            for kind, body in rp.split_packets(buffer):
                if kind == rp.DATA_PACKAGE:
                    stamps.append(struct.unpack(">d", body[1:9])[0])
            if time.monotonic() - checked > 0.2:
                clients, checked = fake_ur.control("status")["rtde_clients"], time.monotonic()
        wall_s = time.monotonic() - start
        assert clients == 1, "the client that stopped reading was not dropped"
        # The controller's clock kept up with the wall clock: a blocking send to the stalled
        # client stopped it (12 s of controller time in 20 s measured).
        assert stamps[-1] - stamps[0] > 0.8 * wall_s - 0.2, (stamps[-1] - stamps[0], wall_s)


@pytest.mark.timeout(60)
def test_canary_the_pinned_ur_rtde_script_still_has_the_markers(fake_ur):
    """Fails when ur_rtde's uploaded control script changes under the fake."""
    import rtde_control

    installed = version("ur-rtde")
    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
    )

    def check_uploaded_script(offset):
        script = fake_ur.control("last_script")["script"]
        differences = cs.protocol_differences(script)
        assert not differences, (
            f"ur-rtde {installed}'s control script differs in {differences}: the fake controller "
            f"(drivers/robot/fake_ur) speaks the private register protocol of ur-rtde "
            f"{UR_RTDE_VERSION}; re-record the uploaded script and update control_script.py, "
            "or pin ur-rtde back"
        )
        assert cs.register_offset(script) == offset, (
            f"ur-rtde {installed} declares its register offset differently"
        )

    for upper, offset in ((False, 0), (True, 24)):
        extra = rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS if upper else 0
        try:
            control = rtde_control.RTDEControlInterface(fake_ur.host, -1.0, flags | extra)
        except RuntimeError:
            # The fake does not run a script it does not recognise, so the constructor fails
            # first ("Failed to start control script"): say why, from the upload itself.
            check_uploaded_script(offset)
            raise
        try:
            check_uploaded_script(offset)
            assert control.isProgramRunning()
            assert len(control.getForwardKinematics()) == 6  # a round trip through the loop
        finally:
            control.stopScript()
            control.disconnect()
    assert installed == UR_RTDE_VERSION, (
        f"ur-rtde {installed} is installed, the fake was checked against {UR_RTDE_VERSION}"
    )


@pytest.mark.timeout(60)
def test_moves_are_refused_in_a_protective_stop_until_unlocked(fake_ur):
    """At the ur_rtde level: the controller stops the script; moves return False."""
    import dashboard_client
    import rtde_control
    import rtde_receive

    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
    )
    receive = rtde_receive.RTDEReceiveInterface(fake_ur.host)
    control = rtde_control.RTDEControlInterface(fake_ur.host, -1.0, flags)
    board = dashboard_client.DashboardClient(fake_ur.host)
    board.connect()
    try:
        goal = list(np.array(HOME_RAD) + [0.1, 0, 0, 0, 0, 0])
        fake_ur.control("configure", unlock_wait_s=0.0)  # UR's 5 s wait is tested in-process
        fake_ur.control("protective_stop")
        time.sleep(0.05)
        assert receive.isProtectiveStopped()
        assert control.moveJ(goal, 1.0, 2.0) is False
        board.unlockProtectiveStop()
        time.sleep(0.05)
        assert not receive.isProtectiveStopped()
        assert control.reuploadScript()
        time.sleep(0.05)
        assert control.moveJ(goal, 1.0, 2.0) is True
        assert np.abs(np.array(receive.getActualQ()) - goal).max() < 2e-3
    finally:
        control.disconnect()
        receive.disconnect()
        board.disconnect()


@pytest.mark.timeout(60)
def test_ur_rtde_commands_fail_or_succeed_as_on_a_controller(fake_ur):
    """moveJ / moveJ_IK / moveL / getInverseKinematics / speedJ + speedStop / stopL through
    ur_rtde: what cannot be done stops the script and returns False (or an empty IK answer)
    at once, instead of a false success or ur_rtde's 300 s wait."""
    import rtde_control
    import rtde_receive

    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
    )
    receive = rtde_receive.RTDEReceiveInterface(fake_ur.host)
    control = rtde_control.RTDEControlInterface(fake_ur.host, -1.0, flags)

    def restart():
        assert not control.isProgramRunning()
        assert control.reuploadScript()
        deadline = time.monotonic() + 5
        while not control.isProgramRunning():
            assert time.monotonic() < deadline
            time.sleep(0.01)

    try:
        home = np.array(HOME_RAD)
        pose = np.array(control.getForwardKinematics())
        far = pose + [3.0, 0, 0, 0, 0, 0]
        started = time.monotonic()
        assert control.moveJ(list(home), 1.0, 0.0) is False  # ur_rtde lets a = 0 through
        restart()
        assert control.moveJ_IK(list(far), 1.0, 1.0) is False
        restart()
        assert control.moveL(list(far), 0.25, 1.2) is False
        restart()
        assert control.getInverseKinematics(list(far)) == []
        restart()
        assert time.monotonic() - started < 5  # refusals are prompt
        near = home + [0.2, 0.1, -0.1, 0.1, 0.1, -0.1]
        # The pose comes from recon's FK: ur_rtde's getForwardKinematics(q) leaves the script's
        # TCP registers as the last command wrote them (test_fake_ur_programs pins that quirk).
        near_pose = pose_from_transform(kinematics.forward(kinematics.model("ur5e"), near))
        solution = control.getInverseKinematics(list(near_pose), list(near))
        assert np.array(solution) == pytest.approx(near, abs=1e-6)
        goal = pose + [0, 0, -0.05, 0, 0, 0]
        assert control.moveL(list(goal), 0.25, 1.2) is True
        assert np.array(receive.getActualTCPPose()) == pytest.approx(goal, abs=1e-4)
        assert control.moveJ_IK(list(pose), 1.0, 2.0) is True
        assert np.abs(np.array(receive.getActualQ()) - home).max() < 2e-3
        # speedJ, then speedStop at 1 rad/s^2: answered once the arm has stopped.
        assert control.speedJ([0.3, 0, 0, 0, 0, 0], 2.0, 0.002)
        time.sleep(0.4)
        asked_at_s = receive.getTimestamp()  # the controller's clock
        control.speedStop(1.0)
        # The receive interface holds the last 2 ms sample: read one from after the answer (one
        # taken while the last millisecond of braking ran showed 0.0015 rad/s once).
        stamp, deadline = receive.getTimestamp(), time.monotonic() + 1.0
        while receive.getTimestamp() == stamp:
            assert time.monotonic() < deadline, "no new sample from the controller"
            time.sleep(0.001)
        assert abs(receive.getActualQd()[0]) < 1e-3
        # Answered only once braked: 0.3 s of braking from 0.3 rad/s at 1 rad/s^2 passed on the
        # controller's clock (less a sample's age at each end; no bound above: a loaded machine
        # adds round trips, not braking).
        assert receive.getTimestamp() - asked_at_s > 0.3 - 0.02
        # stopL ends an async moveL early.
        start_q = np.array(receive.getActualQ())
        assert control.moveL(list(goal), 0.1, 1.0, True)
        time.sleep(0.2)
        control.stopL(2.0)
        assert np.abs(receive.getActualQd()).max() < 1e-3
        assert not control.getAsyncOperationProgressEx().isAsyncOperationRunning()
        travelled = np.abs(np.array(receive.getActualQ()) - start_q).max()
        assert (
            0
            < travelled
            < np.abs(np.array(control.getInverseKinematics(list(goal))) - start_q).max()
        )
    finally:
        control.stopScript()
        control.disconnect()
        receive.disconnect()


# -- the adapter's faults, end to end ------------------------------------------------------------


@pytest.fixture
def robot(fake_ur):
    start = line_process("ur5e", 0.1).q_rad[0]
    fake_ur.control("reset", q_rad=start.tolist())
    backend = URRtdeBackend(
        URRtdeConfig(host=fake_ur.host, connect_timeout_s=5.0, motion_margin_s=3.0)
    )
    backend.connect()
    backend.enable()
    yield backend
    backend.close()


def _inject_at(fake, fraction_wanted, command, **arguments):
    done = []

    def on_progress(fraction):
        if fraction > fraction_wanted and not done:
            done.append(fake.control(command, **arguments))

    return on_progress


@pytest.mark.timeout(60)
def test_a_stop_while_the_waypoints_are_computed_sends_no_move_path(fake_ur, robot, monkeypatch):
    """The stop race of movePath: a stop acknowledged while the waypoints are being computed
    (before the fix, movePath followed 100-580 ms later and the arm moved before it stopped).
    The stop is requested from inside the waypoint computation, so the race is certain."""
    import drivers.robot.base as base

    trajectory = line_process("ur5e", 0.1)
    real_waypoints = base.coarse_waypoints

    def stopped_meanwhile(*args, **kwargs):
        path = real_waypoints(*args, **kwargs)
        robot.stop()  # the operator's Stop, acknowledged while this runs
        return path

    monkeypatch.setattr(base, "coarse_waypoints", stopped_meanwhile)
    q_before = np.array(fake_ur.control("status")["q_rad"])
    with pytest.raises(MotionStoppedError):
        robot.execute_path(trajectory, tolerance_m=5e-4)
    status = fake_ur.control("status")
    assert status["path_moves"] == 0  # no movePath reached the controller
    assert np.abs(np.array(status["q_rad"]) - q_before).max() == 0.0  # not a microradian


@pytest.mark.timeout(60)
def test_the_worker_checks_the_latched_stop_right_before_it_sends_move_path(fake_ur, robot):
    """The last check is in the process that talks to the arm: with the stop already latched
    there, the worker never sends the path, whatever the caller did before."""
    from drivers.robot.ur_rtde import MovePath

    trajectory = line_process("ur5e", 0.1)
    robot._worker.stop_event.set()  # latched in the worker, not yet seen by the caller
    times, _actual, completed, fault = robot._call(
        MovePath(
            trajectory.q_rad[::200].tolist(),
            [0.5] * len(trajectory.q_rad[::200]),
            1.0,
            [0.0] * len(trajectory.q_rad[::200]),
            None,
        ),
        timeout_s=10.0,
    )
    assert (times, completed, fault) == ([], False, "stopped on request")
    assert fake_ur.control("status")["path_moves"] == 0


@pytest.mark.timeout(60)
def test_a_protective_stop_during_execution_is_reported_and_unlocked(fake_ur, robot):
    trajectory = line_process("ur5e", 0.1)
    fake_ur.control("configure", unlock_wait_s=0.0)  # not what this test is about
    with pytest.raises(ProtectiveStopError):
        robot.execute(trajectory, on_progress=_inject_at(fake_ur, 0.3, "protective_stop"))
    assert robot.state is RobotState.PROTECTIVE_STOP
    with pytest.raises(ProtectiveStopError):
        robot.move_joints(trajectory.q_rad[0])
    robot.unlock_protective_stop()
    assert robot.state is RobotState.ENABLED
    robot.move_joints(trajectory.q_rad[0], speed_rad_s=1.0, acceleration_rad_s2=2.0)
    assert np.abs(robot.status().q_rad - trajectory.q_rad[0]).max() < 2e-3


@pytest.mark.timeout(60)
def test_an_emergency_stop_is_reported(fake_ur, robot):
    fake_ur.control("emergency_stop")
    time.sleep(0.05)
    with pytest.raises(EmergencyStopError):
        robot.status()
    assert robot.state is RobotState.EMERGENCY_STOP


@pytest.mark.timeout(60)
def test_a_dropped_connection_is_reported_and_reconnecting_works(fake_ur, robot):
    trajectory = line_process("ur5e", 0.1)
    # The link stays down for 2 s: ur_rtde's own reconnection (which would bridge a short
    # drop) fails, and the adapter reports the loss. Usually as a lost connection ("End of
    # file", 0.52 s after the start); but a timeout is genuinely possible: measured once in
    # three runs (after 4.6 s, the execute bound), when ur_rtde's call blocks in its own
    # reconnection attempts against the refusing controller before it sees the end of file --
    # the adapter then kills the worker. Either way it ends within the execute bound.
    drop = _inject_at(fake_ur, 0.3, "drop_connections", refuse_s=2.0)
    started = time.monotonic()
    with pytest.raises((ConnectionLostError, RobotTimeoutError)):
        robot.execute(trajectory, on_progress=drop)
    assert time.monotonic() - started < robot._motion_bound_s(trajectory.duration_s) + 2
    assert robot.state is RobotState.DISCONNECTED
    time.sleep(2.0)
    robot.connect()
    robot.enable()
    assert robot.status().q_rad.shape == (6,)


@pytest.mark.timeout(60)
def test_a_silent_controller_is_lost_and_the_event_loop_keeps_running(fake_ur, robot):
    """The service's loop keeps ticking while the controller stops answering: reading the arm
    fails as a lost link, and connecting to the silent controller times out."""

    async def scenario():
        loop = asyncio.get_running_loop()
        ticks = []

        async def ticker():
            while True:
                ticks.append(loop.time())
                await asyncio.sleep(0.02)

        task = asyncio.create_task(ticker())
        fake_ur.control("freeze")
        # Packages sent just before the freeze may still be on their way to a busy client.
        await asyncio.sleep(0.3)
        with pytest.raises(ConnectionLostError, match="no new data"):
            await loop.run_in_executor(None, robot.status)
        robot.close()
        other = URRtdeBackend(URRtdeConfig(host=fake_ur.host, connect_timeout_s=3.0))
        with pytest.raises((RobotTimeoutError, ConnectionLostError)):
            await loop.run_in_executor(None, other.connect)
        other.close()
        task.cancel()
        return np.diff(ticks)

    gaps = asyncio.run(scenario())
    assert len(gaps) > 50 and gaps.max() < 0.5


@pytest.mark.timeout(120)
def test_a_dry_run_sized_trajectory_streams_with_servoj_and_runs_as_a_path(fake_ur, robot):
    from recon import scenes
    from recon.plan import PlanParams, approach_in, normals_from_scan, plan_path
    from recon.reconstruct import reconstruct

    T = base_from_tracker()
    scene = scenes.SCENES["cylinder_edge"](0)
    recon = reconstruct(scene.recording, scene.scan)
    normals = normals_from_scan(
        recon.points_m,
        recon.mode,
        recon.scan_model,
        T_scan_tracker=recon.T_scan_tracker,
        approach_tracker=approach_in(T, (0, 0, 1)),
    )
    trajectory = plan_path(
        recon.points_m, T_base_tracker=T, normals=normals, params=PlanParams(speed_m_s=0.1)
    ).trajectory
    assert len(trajectory) > 1000
    fake_ur.control("reset", q_rad=trajectory.q_rad[0].tolist())
    robot.close()  # the reset stopped the control script: connect afresh
    robot.connect()
    robot.enable()
    record = robot.execute(trajectory)
    assert record.completed and len(record) == len(trajectory)
    # The fake integrates the sim backend's model: through ur_rtde, in real time, the arm takes
    # the simulated arm's joint-space path (its wrist lags the plan by 0.27 rad in both). The
    # client's loop runs a few per cent slower than the controller's clock, so the samples are
    # compared along the path, not in time.
    sim = SimBackend(SimConfig(q_start_rad=tuple(trajectory.q_rad[0])), clock=FakeClock())
    sim.connect()
    sim.enable()
    simulated = sim.execute(trajectory)
    distance, _ = cKDTree(simulated.q_actual_rad).query(record.q_actual_rad)
    # Measured 0.01-0.04 rad; a client stall on a busy machine holds the target for its length
    # (0.14 rad once, with a fresh-clone suite and other work sharing the two cores; p99 0.085
    # once in a fresh-clone suite, the browser tests' servers beside it). Nearly all samples stay
    # on the simulated path, within a third of the plan's 0.27 rad lag, and none strays as far.
    print(
        f"off the simulated path: p99 {np.percentile(distance, 99):.3f}, max {distance.max():.3f}"
    )
    assert np.percentile(distance, 99) < 0.1
    assert distance.max() < 0.2
    assert np.abs(robot.status().q_rad - trajectory.q_rad[-1]).max() < 2e-3
    robot.move_joints(trajectory.q_rad[0], speed_rad_s=2.0, acceleration_rad_s2=4.0)
    record = robot.execute_path(trajectory, tolerance_m=5e-4)
    assert record.completed
    assert np.abs(robot.status().q_rad - trajectory.q_rad[-1]).max() < 2e-3


@pytest.mark.timeout(120)
def test_a_path_run_is_slowed_paused_and_resumed_by_the_speed_slider_then_put_back(fake_ur, robot):
    """A movePath run takes the speed override and the pause through the controller's speed
    slider: set to 30 % the slider says so; paused, the arm comes to rest on its way and the
    run waits; resumed, it ends at its last waypoint, and the slider is back as it was found."""
    trajectory = line_process("ur5e", 0.02)
    fake_ur.control("reset", q_rad=trajectory.q_rad[0].tolist())
    robot.close()  # the reset stopped the control script: connect afresh
    robot.connect()
    robot.enable()
    assert robot.speed_override_paths
    progress: list[float] = []
    outcome: dict = {}

    def run() -> None:
        try:
            outcome["record"] = robot.execute_path(
                trajectory, tolerance_m=5e-4, on_progress=progress.append
            )
        except Exception as error:  # reported below
            outcome["error"] = error

    def status() -> dict:
        return fake_ur.control("status")

    def wait_for(condition, what: str, timeout_s: float = 60.0) -> None:
        # A ceiling that catches a hang, not a timing: a fresh clone's busy run once took more
        # than 20 s to start the path.
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, what
            time.sleep(0.02)

    runner = threading.Thread(target=run)
    runner.start()
    wait_for(lambda: progress, "the path did not start")
    robot.set_speed(0.3)
    wait_for(lambda: status()["speed_slider"] == 0.3, "the slider did not follow the speed")
    wait_for(lambda: status()["speed_scaling"] == 0.3, "the scaling did not ramp to the slider")
    robot.pause()
    wait_for(lambda: status()["speed_scaling"] == 0.0, "the pause did not reach the slider")
    time.sleep(0.3)  # the arm settles on its way
    q_paused = np.array(status()["q_rad"])
    time.sleep(1.0)
    assert np.abs(np.array(status()["q_rad"]) - q_paused).max() < 1e-6, "it moved while paused"
    assert runner.is_alive() and robot.paused
    assert np.abs(q_paused - trajectory.q_rad[-1]).max() > 1e-3  # not at its end yet
    assert robot.speed_now == 0.0  # the worker reports the controller's scaling, paused too
    robot.resume()
    runner.join(timeout=60)
    assert not runner.is_alive() and "error" not in outcome, outcome
    assert outcome["record"].completed
    assert np.abs(robot.status().q_rad - trajectory.q_rad[-1]).max() < 2e-3
    assert status()["speed_slider"] == 1.0  # put back as the run found it


def test_the_speed_slider_never_goes_above_where_the_run_found_it():
    """The teach pendant's slider turned down to 50 % before a movePath run: the run's override
    stays within it, the pause sets 0, and the end puts 50 % back; a slider left untouched is
    not written again at the end."""
    from drivers.robot.ur_rtde import _SpeedSlider

    class IO:
        def __init__(self) -> None:
            self.sent: list[float] = []

        def setSpeedSlider(self, value: float) -> bool:  # noqa: N802 - ur_rtde's name
            self.sent.append(value)
            return True

    io = IO()
    slider = _SpeedSlider(io, 0.5)
    for override in (1.0, 0.3, 0.0, 1.0):
        slider.follow(override)
    slider.restore()
    assert io.sent == [0.5, 0.3, 0.0, 0.5]  # the last follow already put 50 % back

    class Receive:
        def getSpeedScaling(self) -> float:  # noqa: N802 - ur_rtde's name
            return 0.25

    assert slider.share(Receive()) == 0.5  # the override's view: half of the found 50 %
    untouched = IO()
    full = _SpeedSlider(untouched, float("nan"))  # not read: taken as 100 %
    full.follow(1.0)
    full.restore()
    assert untouched.sent == [1.0]


# -- the controller's RTDE watchdog ------------------------------------------------------------


@pytest.mark.timeout(60)
def test_the_controllers_rtde_watchdog_stops_a_move_its_client_went_quiet_on(fake_ur):
    """ur_rtde's setWatchdog: the control script's rtde_set_watchdog(..., "stop"). A moveJ the
    controller runs on its own, from a client that then sends nothing (a hung worker): the
    program stops within the watchdog's period and the arm brakes short of the goal."""
    import rtde_control

    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
    )
    control = rtde_control.RTDEControlInterface(fake_ur.host, -1.0, flags)
    try:
        goal = np.array(HOME_RAD) + [0.6, 0, 0, 0, 0, 0]
        assert control.setWatchdog(20.0)
        started = fake_ur.control("program_status")["t_s"]
        assert control.moveJ(goal.tolist(), 0.5, 1.0, True)  # async: the controller runs it
        deadline = time.monotonic() + 10.0
        while fake_ur.control("program_status")["state"] == "running":
            assert time.monotonic() < deadline, "the watchdog never fired"
            time.sleep(0.01)
        status = fake_ur.control("program_status")
        assert any("RTDE watchdog" in m for m in status["messages"]), status["messages"]
        # Stopped within a few watchdog periods of controller time after the last write, far
        # short of the 1.2 s the move takes.
        assert status["ended_s"] - started < 0.3
        assert np.abs(np.array(status["q_rad"]) - goal).max() > 0.3
        assert not control.isProgramRunning()
    finally:
        control.disconnect()


@pytest.mark.timeout(60)
def test_the_adapter_arms_the_watchdog_for_a_path_and_keeps_it_fed(fake_ur, robot):
    """execute_path (movePath: the controller runs the path alone) with the watchdog at its
    2 Hz: the adapter kicks it while it samples the arm, so the path completes; after it the
    watchdog is relaxed and the script still runs."""
    trajectory = line_process("ur5e", 0.1)
    log_before = len(fake_ur.log_text())
    record = robot.execute_path(trajectory, tolerance_m=5e-4)
    assert record.completed
    time.sleep(0.6)  # more than the 2 Hz watchdog's period, were it not relaxed
    status = fake_ur.control("program_status")
    assert status["state"] == "running", status
    log = fake_ur.log_text()[log_before:]
    armed, relaxed = log.find("RTDE watchdog set: 2 Hz"), log.find("RTDE watchdog set: 0.01 Hz")
    assert 0 <= armed < relaxed, log  # armed for the path, relaxed after it
    assert "RTDE watchdog:" not in log  # it never fired
