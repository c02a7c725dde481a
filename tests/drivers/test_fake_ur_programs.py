"""Standalone URScript programs on the fake UR controller, and the TCP / payload it keeps.

In-process tests step a :class:`~drivers.robot.fake_ur.controller.FakeController` directly
(fast, exact timing); the others send programs to a fake in its own process on its script port,
as teachpath's exported programs would reach a controller, and watch them through the control
channel and the dashboard. Expected poses come from ``recon.kinematics`` (FK composed with the
TCP), not from the fake.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.robot.fake_ur import controller as ctl
from drivers.robot.fake_ur import server, urscript
from drivers.robot.fake_ur.server import DASHBOARD_PORT, FakeUR
from drivers.robot.sim import HOME_RAD
from recon import kinematics
from recon.transforms import invert_transform, pose_from_transform, transform_from_pose
from tests.drivers import fake_ur_fixture

fake_ur_process = fake_ur_fixture.fake_ur_process
fake_ur = fake_ur_fixture.fake_ur

# The fake controller runs in real time: seconds per test (make test-fast leaves them out).
pytestmark = pytest.mark.slow

ARM = kinematics.model("ur5e")
HOME = np.array(HOME_RAD)
TCP = np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.0])  # a 12 cm tool along the flange's z


def tcp_of(q, tcp=TCP) -> np.ndarray:
    """The TCP pose at ``q``: recon's FK composed with the TCP."""
    return pose_from_transform(kinematics.forward(ARM, np.asarray(q)) @ transform_from_pose(tcp))


def ik_near(pose, q_near, tcp=TCP) -> np.ndarray:
    """recon's IK of a TCP pose, the solution nearest ``q_near``."""
    T = transform_from_pose(np.asarray(pose)[None]) @ invert_transform(transform_from_pose(tcp))
    solutions = kinematics.inverse(ARM, T)
    candidates = solutions.q_rad[0][solutions.valid[0]]
    assert len(candidates), "unreachable test pose"
    candidates = candidates + 2 * np.pi * np.round((q_near - candidates) / (2 * np.pi))
    return candidates[np.argmin(np.abs(candidates - q_near).max(axis=1))]


def rotation_error(a, b) -> float:
    return float((Rotation.from_rotvec(a[3:6]).inv() * Rotation.from_rotvec(b[3:6])).magnitude())


def fmt(values) -> str:
    return ", ".join(f"{v:.10g}" for v in values)


def run(c: ctl.FakeController, max_s: float = 30.0) -> urscript.RunState:
    """Step ``c`` until its program is over."""
    for _ in range(int(max_s * c.rate_hz)):
        if c.run is None or c.run.state != "running":
            break
        c.step()
    for _ in range(int(ctl.TRACE_TAIL_S * c.rate_hz)):  # the trace's tail (the arm at rest)
        if c._trace_until is None:
            break
        c.step()
    assert c.run is not None
    return c.run


def started(text: str, **kwargs) -> ctl.FakeController:
    c = ctl.FakeController("ur5e", **kwargs)
    assert c.load_program(text), c.run
    return c


# -- compiling -----------------------------------------------------------------------------------


def test_arguments_bind_as_urscript_binds_them_in_any_float_notation():
    program = urscript.compile_program(
        "def p1():\n"
        "  # set up\n"
        "  movej([0, -1.5708, 1.5708, -1.5708, -1.5708, 0], 1.2, v=0.5)  # positional a\n"
        "  movel(p[.5, -2.5E-1, 3., 0, 3.14, +0], r=1e-3, v=0.1)\n"
        "  servoj([1,2,3,4,5,6], t=0.008, gain=500)\n"
        '  textmsg("a # is not a comment", 2)\n'
        "  local target = p[0.1, 0.2, 0.3, 0, 0, 0]\n"
        "  movep(target)\n"
        "end\n"
        "p1()\n"
    )
    movej, movel, servoj, textmsg, assign, movep = program.statements
    assert program.name == "p1" and [s.line for s in program.statements] == [3, 4, 5, 6, 7, 8]
    assert movej.args[1:] == (1.2, 0.5, 0.0, 0.0)  # q, a, v, t, r
    assert isinstance(movel.args[0], urscript.Pose)
    assert movel.args[0].values == pytest.approx([0.5, -0.25, 3.0, 0, 3.14, 0])
    assert movel.args[1:] == (1.2, 0.1, 0.0, 1e-3)
    assert servoj.args[3:] == (0.008, 0.1, 500.0)  # t, lookahead_time (default), gain
    assert textmsg.args == ("a # is not a comment", 2.0)
    assert assign.target == "target" and movep.args[0] == urscript.Name("target")


def test_a_bare_sequence_is_a_program_too():
    program = urscript.compile_program('textmsg("hello")\nsleep(0.1)\n')
    assert program.name == "<script>" and len(program.statements) == 2


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("def a():\n  movej([0,0,0,0,0,0])\n  frobnicate(1)\nend\n", 3, "unknown function"),
        ("def a():\n  while True:\n    sync()\n  end\nend\n", 2, "'while' blocks"),
        ("def a():\n  x = 1 + 2\nend\n", 2, "unexpected"),
        ("def a():\n  movel(p[0,0,0,0,0,0], v=0.1, 1.2)\nend\n", 2, "positional argument after"),
        ("def a():\n  movel(p[0,0,0,0,0,0], speed=0.1)\nend\n", 2, "no parameter 'speed'"),
        ("def a():\n  sleep()\nend\n", 2, "needs its argument 't'"),
        ("def a():\n  sync()\n", 2, "no 'end'"),
        ("def a():\n  sync()\nend\nb()\n", 4, "only the call a()"),
    ],
)
def test_what_is_outside_the_subset_is_refused_with_its_line(text, line, words):
    with pytest.raises(urscript.CompileError, match=words) as caught:
        urscript.compile_program(text)
    assert caught.value.line == line


def test_a_long_servoj_program_compiles_quickly():
    lines = "".join(
        f"  servoj([{fmt(HOME + 1e-5 * k)}], t=0.002, lookahead_time=0.1, gain=300)\n"
        for k in range(10_000)
    )
    started_at = time.perf_counter()
    program = urscript.compile_program(f"def long():\n{lines}end\nlong()\n")
    took = time.perf_counter() - started_at
    assert len(program.statements) == 10_000
    print(f"compiled 10 000 servoj lines in {took:.3f} s")  # measured 0.16 s; not asserted


# -- running, in process ---------------------------------------------------------------------------


def test_moves_sleep_and_servoj_take_the_time_they_ask_for():
    goal = HOME + [0.3, 0, 0, 0, 0, 0]
    servo = "".join(
        f"  servoj([{fmt(goal + [0.001 * k, 0, 0, 0, 0, 0])}], t=0.01)\n" for k in range(10)
    )
    c = started(f"def timing():\n  movej([{fmt(goal)}], t=2.0)\n  sleep(0.25)\n{servo}end\n")
    assert run(c).state == "finished"
    rows = c.trace.rows()
    t, line = rows[:, 0], rows[:, 13]
    begins = {int(k): float(t[line == k][0]) for k in np.unique(line) if k}
    # movej's t takes priority over v and a: the profile lasts 2 s; the move ends once settled.
    assert 2.0 <= begins[3] - begins[2] < 2.0 + ctl.SETTLE_MAX_S
    assert begins[4] - begins[3] == pytest.approx(0.25, abs=c.dt_s)
    for k in range(4, 13):  # each servoj call occupies its t of controller time
        assert begins[k + 1] - begins[k] == pytest.approx(0.01, abs=1e-9)
    assert np.abs(c.q - (goal + [0.009, 0, 0, 0, 0, 0])).max() < 1e-4


def test_blended_movel_and_movej_runs_do_not_stop_at_their_waypoints():
    c = ctl.FakeController("ur5e")
    start = np.array(c.tcp_pose())
    a = np.concatenate([start[:3] + [0.05, 0, 0], start[3:]])
    b = np.concatenate([start[:3] + [0.05, 0.05, 0], start[3:]])
    q1, q2 = HOME + [0.2, 0, 0, 0, 0, 0], HOME + [0.2, 0.1, 0, 0, 0, 0]
    assert c.load_program(
        f"movel(p[{fmt(a)}], v=0.1, r=0.005)\nmovel(p[{fmt(b)}], v=0.1)\n"
        f"movej([{fmt(q1)}], v=0.5, r=0.01)\nmovej([{fmt(q2)}], v=0.5)\n"
    )
    assert run(c).state == "finished"
    rows = c.trace.rows()
    speed = np.linalg.norm(np.diff(rows[:, 7:10], axis=0), axis=1) / c.dt_s
    near_a = np.argmin(np.linalg.norm(rows[:, 7:10] - a[:3], axis=1))
    assert speed[near_a] > 0.05  # through the corner at speed
    qd = np.abs(np.diff(rows[:, 1:7], axis=0)).max(axis=1) / c.dt_s
    near_q1 = np.argmin(np.abs(rows[:, 1:7] - q1).max(axis=1))
    assert qd[near_q1] > 0.1
    assert np.abs(c.q - q2).max() < 1e-3


def test_variables_halt_and_stopj_after_servoj():
    q1 = HOME + [0.1, 0, 0, 0, 0, 0]
    c = started(
        f"def v():\n  global q1 = [{fmt(q1)}]\n  movej(q1, v=1.0)\n"
        f"  servoj([{fmt(q1 + [0.01, 0, 0, 0, 0, 0])}], t=0.1)\n  stopj(2.0)\n"
        '  textmsg("stopped at ", q1)\n  halt()\n  textmsg("never")\nend\n'
    )
    status = run(c)
    assert status.state == "finished" and status.line == 7
    assert any(m.startswith("stopped at [0.1, -1.5708") for m in c.messages)
    assert "never" not in c.messages
    assert np.abs(c.qd).max() < ctl.SETTLED_RAD_S


def test_a_runtime_error_stops_the_program_at_its_line_after_what_ran():
    q1 = HOME + [0.1, 0, 0, 0, 0, 0]
    c = started(f"def bad():\n  movej([{fmt(q1)}])\n  movel(p[3, 0, 0.3, 0, 3.14, 0])\nend\n")
    status = run(c)
    assert status.state == "error" and status.line == 3
    assert "no inverse kinematics solution" in status.message
    assert any(m.startswith("line 3: movel: no inverse") for m in c.messages)
    assert c.runtime_state == ctl.RUNTIME_STOPPED
    assert np.abs(c.q - q1).max() < 2e-3  # the movej ran, the movel did not


@pytest.mark.parametrize(
    ("statement", "words"),
    [
        ("movej([0, 0, 0])", "needs 6 values"),
        ("movel(p[0, 0, 0, 0, 0, 0], v=0)", "speed and acceleration must be > 0"),
        ("servoj([0, -1.57, 1.57, -1.57, -1.57, 0], gain=50)", "gain 50"),
        ("sleep(missing)", "variable 'missing' is not defined"),
        ("set_tcp([0, 0, 0.1, 0, 0, 0])", "must be a pose"),
    ],
)
def test_invalid_arguments_are_runtime_errors(statement, words):
    c = started(f"def bad():\n  sync()\n  {statement}\nend\n")
    status = run(c)
    assert status.state == "error" and status.line == 3 and words in status.message


def test_a_program_refused_for_local_control_or_a_safety_stop_does_not_start():
    c = ctl.FakeController("ur5e")
    c.remote_control = False
    assert not c.load_program("sync()\n")
    assert c.run.state == "refused" and "local control" in c.run.message
    c.remote_control = True
    c.protective_stop()
    assert not c.load_program("sync()\n")
    assert c.run.state == "refused"


def test_the_trace_is_bounded():
    trace = ctl.Trace(max_samples=2 * ctl.TRACE_BLOCK)
    for k in range(5 * ctl.TRACE_BLOCK + 7):
        trace.append(k * 0.002, np.full(6, k), np.zeros(6), k % 3)
    assert len(trace) <= 2 * ctl.TRACE_BLOCK + 7 and trace.dropped % ctl.TRACE_BLOCK == 0
    rows = trace.rows(trace.dropped)
    assert rows[0, 1] == trace.dropped and rows[-1, 1] == 5 * ctl.TRACE_BLOCK + 6


# -- TCP and payload in process ----------------------------------------------------------------


def test_the_tcp_moves_every_reported_pose_and_the_payload_is_kept():
    c = ctl.FakeController("ur5e")
    assert c.outputs()["actual_TCP_pose"] == pytest.approx(tcp_of(HOME, np.zeros(6)))
    c.set_tcp(TCP)
    c.set_payload(2.0, [0, 0, 0.05], None)
    outputs = c.outputs()
    assert outputs["actual_TCP_pose"] == pytest.approx(tcp_of(HOME), abs=1e-12)
    assert outputs["target_TCP_pose"] == pytest.approx(tcp_of(HOME), abs=1e-12)
    assert outputs["payload"] == 2.0 and outputs["payload_cog"] == [0, 0, 0.05]
    c.set_payload(2.5, None, None)  # the cog is kept
    assert c.payload_cog_m.tolist() == [0, 0, 0.05]
    # IK takes TCP poses.
    q = HOME + [0.2, 0.1, -0.1, 0.1, 0.1, -0.1]
    assert c._ik(tcp_of(q), HOME) == pytest.approx(q, abs=1e-9)


def test_a_program_sets_the_payload_every_way_urscript_has():
    c = started(
        "set_target_payload(1.0, [0, 0, 0.1], [0.01, 0.02, 0.03, 0, 0, 0])\n"
        "set_payload_mass(1.25)\n"
        "set_payload_cog([0.01, 0, 0.1])\n"
        f"set_tcp(p[{fmt(TCP)}])\n"
    )
    assert run(c).state == "finished"
    assert c.payload_kg == 1.25 and c.payload_cog_m.tolist() == [0.01, 0, 0.1]
    assert c.payload_inertia.tolist() == [0.01, 0.02, 0.03, 0, 0, 0]
    assert c.tcp_offset.tolist() == TCP.tolist()
    assert np.array(c.tcp_pose()) == pytest.approx(tcp_of(HOME), abs=1e-12)


def test_the_control_channel_pages_the_trace_and_reset_clears_the_tool(monkeypatch):
    fake = FakeUR("127.0.0.1")  # never started: no ports bound
    c = fake.controller
    c.set_tcp(TCP)
    assert c.load_program(f"movej([{fmt(HOME + [0.05, 0, 0, 0, 0, 0])}])\n")
    run(c)
    status = fake.handle_control({"cmd": "program_status"})
    assert (status["state"], status["kind"], status["line"]) == ("finished", "urscript", 1)
    monkeypatch.setattr(server, "TRACE_REPLY_MAX", 7)
    rows, start = [], 0
    while True:
        page = fake.handle_control({"cmd": "program_trace", "start": start, "every": 3})
        assert len(page["t_s"]) <= 7
        rows += [
            [t, *q, *p, line]
            for t, q, p, line in zip(
                page["t_s"], page["q_rad"], page["tcp_pose"], page["line"], strict=True
            )
        ]
        if page["complete"]:
            break
        start = page["next"]
    assert np.array(rows) == pytest.approx(c.trace.rows(every=3))
    assert status["trace_samples"] == len(c.trace) > 100
    with pytest.raises(ValueError, match="unknown options"):
        fake.handle_control({"cmd": "program_trace", "from": 0})
    fake.handle_control({"cmd": "reset"})
    assert fake.handle_control({"cmd": "program_status"})["state"] == "none"
    assert not c.tcp_offset.any() and c.payload_kg == 0.0


# -- on the wire -------------------------------------------------------------------------------


def _dashboard(host: str, *commands: str) -> list[str]:
    with socket.create_connection((host, DASHBOARD_PORT), timeout=5) as sock:
        lines = sock.makefile("rb")
        lines.readline()  # greeting
        replies = []
        for command in commands:
            sock.sendall((command + "\n").encode())
            replies.append(lines.readline().decode().strip())
    return replies


STATE_QUERIES = ("robotmode", "safetystatus", "safetymode", "programState", "running")


@pytest.mark.timeout(120)
def test_an_exported_program_runs_where_it_is_planned(fake_ur):
    """set_tcp / set_payload, a movej, a movel down 5 cm, 200 servoj along an arc, a movel up:
    the arm ends on the analytic target and the movel is a straight line."""
    q_a = HOME + [0.2, -0.1, 0.2, -0.1, 0.0, 0.3]
    a = tcp_of(q_a)
    b = a + [0, 0, -0.05, 0, 0, 0]
    q_b = ik_near(b, q_a)
    radius = 0.02
    center = b[:3] - [radius, 0, 0]
    angles = np.linspace(0, np.pi / 2, 201)[1:]
    arc = [
        np.concatenate([center + radius * np.array([np.cos(t), np.sin(t), 0]), b[3:]])
        for t in angles
    ]
    q_arc = [q_b]
    for pose in arc:
        q_arc.append(ik_near(pose, q_arc[-1]))
    d = arc[-1] + [0, 0, 0.05, 0, 0, 0]
    q_d = ik_near(d, q_arc[-1])
    servo = "".join(
        f"  servoj([{fmt(q)}], 0, 0, 0.008, lookahead_time=0.1, gain=300)\n" for q in q_arc[1:]
    )
    text = (
        "def exported():\n"
        f"  set_tcp(p[{fmt(TCP)}])\n"
        "  set_payload(1.5, [0, 0, 0.06])\n"
        f"  movej([{fmt(q_a)}], a=1.4, v=1.05)\n"
        f"  movel(p[{fmt(b)}], a=1.2, v=0.1)\n"
        f"{servo}"
        f"  movel(p[{fmt(d)}], a=1.2, v=0.1)\n"
        "end\n"
        "exported()\n"
    )
    before = fake_ur.send_program(text)
    status = fake_ur.wait_program(before, running=True)
    assert _dashboard(fake_ur.host, "programState", "running") == [
        "PLAYING exported",
        "Program running: true",
    ]
    status = fake_ur.wait_program(before, timeout_s=60)
    assert status["state"] == "finished", status
    assert status["statements"] == status["executed"] == 205
    assert np.abs(np.array(status["q_rad"]) - q_d).max() < 1e-3
    final = np.array(status["tcp_pose"])
    assert np.linalg.norm(final[:3] - d[:3]) < 5e-4 and rotation_error(final, d) < 1e-3
    assert final == pytest.approx(tcp_of(status["q_rad"]), abs=1e-9)  # the TCP is reported
    fake_status = fake_ur.control("status")
    assert fake_status["tcp_offset"] == pytest.approx(TCP)
    assert fake_status["payload_kg"] == 1.5 and fake_status["payload_cog_m"] == [0, 0, 0.06]
    assert _dashboard(fake_ur.host, "programState", "running") == [
        "STOPPED exported",
        "Program running: false",
    ]
    trace = fake_ur.program_trace()
    # The movel down (line 5) is a straight TCP line from a to b.
    down = trace["tcp_pose"][trace["line"] == 5][:, :3]
    direction = (b[:3] - a[:3]) / np.linalg.norm(b[:3] - a[:3])
    off_line = np.linalg.norm(np.cross(down - a[:3], direction), axis=1)
    assert len(down) > 100 and off_line.max() < 2e-4, off_line.max()
    # The arc (lines 6-205) is followed through the servo lookahead, on the circle.
    on_arc = trace["tcp_pose"][(trace["line"] >= 6) & (trace["line"] <= 205)][:, :3]
    radial = np.abs(np.linalg.norm(on_arc[:, :2] - center[:2], axis=1) - radius)
    assert radial.max() < 5e-4 and np.abs(on_arc[:, 2] - b[2]).max() < 5e-4
    assert trace["q_rad"][-1] == pytest.approx(status["q_rad"], abs=1e-9)
    print(
        f"movel off its line {off_line.max() * 1e3:.3f} mm; arc radial {radial.max() * 1e3:.3f} mm"
    )


@pytest.mark.timeout(60)
def test_movep_keeps_its_speed_and_passes_within_the_blend_radius_of_each_pose(fake_ur):
    start = tcp_of(HOME, np.zeros(6))
    r, v = 0.01, 0.1
    offsets = [
        (0.08, 0, 0),
        (0.08, 0.08, 0),
        (0.16, 0.08, -0.03),
        (0.16, 0.0, -0.03),
        (0.1, -0.05, 0),
    ]
    poses = [np.concatenate([start[:3] + o, start[3:]]) for o in offsets]
    moves = "".join(f"  movep(p[{fmt(p)}], a=1.2, v={v}, r={r})\n" for p in poses)
    status = fake_ur.wait_program(fake_ur.send_program(f"def corners():\n{moves}end\n"))
    assert status["state"] == "finished", status
    trace = fake_ur.program_trace()
    xyz = trace["tcp_pose"][:, :3]
    for k, pose in enumerate(poses[:-1]):
        passed = np.linalg.norm(xyz - pose[:3], axis=1).min()
        assert passed <= r + 5e-4, (k, passed)
        assert passed > 1e-3  # blended: the corner is cut, not visited
    assert np.linalg.norm(xyz[-1] - poses[-1][:3]) < 5e-4  # the last move stops on its pose
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=1) / np.diff(trace["t_s"])
    assert speed.max() < 1.03 * v
    cruising = speed[speed > 0.5 * v]
    assert np.median(cruising) == pytest.approx(v, rel=0.01)
    assert np.mean(np.abs(cruising - v) < 0.03 * v) > 0.8  # constant speed through the blends


@pytest.mark.timeout(60)
def test_an_unknown_function_stops_the_program_with_its_line_and_nothing_moves(fake_ur):
    q1 = HOME + [0.3, 0, 0, 0, 0, 0]
    before = fake_ur.send_program(
        f"def oops():\n  movej([{fmt(q1)}])\n  # next\n  socket_open(1)\nend\n"
    )
    status = fake_ur.wait_program(before)
    assert status["state"] == "error" and status["line"] == 4
    assert "socket_open" in status["message"]
    assert any("Compile error: line 4" in m for m in status["messages"])
    time.sleep(0.1)
    assert np.array(fake_ur.control("status")["q_rad"]) == pytest.approx(HOME, abs=1e-9)
    assert _dashboard(fake_ur.host, "programState", "running") == [
        "STOPPED oops",
        "Program running: false",
    ]


@pytest.mark.timeout(60)
def test_a_protective_stop_or_an_emergency_stop_stops_a_running_program(fake_ur):
    fake_ur.control("configure", unlock_wait_s=0.0)
    far = HOME + [1.5, 0, 0, 0, 0, 0]
    program = f"def slow():\n  movej([{fmt(far)}], v=0.3)\nend\n"
    before = fake_ur.send_program(program)
    fake_ur.wait_program(before, running=True)
    assert _dashboard(fake_ur.host, *STATE_QUERIES) == [
        "Robotmode: RUNNING",
        "Safetystatus: NORMAL",
        "Safetymode: NORMAL",
        "PLAYING slow",
        "Program running: true",
    ]
    time.sleep(0.5)
    fake_ur.control("protective_stop")
    status = fake_ur.wait_program(before)
    assert status["state"] == "stopped" and status["line"] == 2
    assert status["message"].startswith("protective stop")
    q_stopped = np.array(status["q_rad"])
    assert 0.01 < q_stopped[0] < 1.0  # it had moved, and did not go on
    assert _dashboard(fake_ur.host, *STATE_QUERIES) == [
        "Robotmode: RUNNING",
        "Safetystatus: PROTECTIVE_STOP",
        "Safetymode: PROTECTIVE_STOP",
        "STOPPED slow",
        "Program running: false",
    ]
    time.sleep(0.2)
    assert np.array(fake_ur.control("status")["q_rad"]) == pytest.approx(q_stopped, abs=1e-9)
    # Refused while stopped; runs again once unlocked.
    assert fake_ur.wait_program(fake_ur.send_program(program))["state"] == "refused"
    assert _dashboard(fake_ur.host, "unlock protective stop") == ["Protective stop releasing"]
    before = fake_ur.send_program(program)
    fake_ur.wait_program(before, running=True)
    for source, name in (("robot", "ROBOT_EMERGENCY_STOP"), ("system", "SYSTEM_EMERGENCY_STOP")):
        fake_ur.control("emergency_stop", source=source)
        status = fake_ur.wait_program(before)
        assert status["state"] == "stopped" and status["message"] == f"{source} emergency stop"
        assert _dashboard(fake_ur.host, *STATE_QUERIES)[:3] == [
            "Robotmode: POWER_OFF",
            f"Safetystatus: {name}",
            f"Safetymode: {name}",
        ]
        fake_ur.control("release_emergency_stop")
        assert _dashboard(fake_ur.host, "power on", "brake release", "robotmode") == [
            "Powering on",
            "Brake releasing",
            "Robotmode: RUNNING",
        ]
        before = fake_ur.send_program(program)
        fake_ur.wait_program(before, running=True)
    assert _dashboard(fake_ur.host, "stop", "programState") == ["Stopped", "STOPPED slow"]
    assert fake_ur.control("program_status")["message"] == "stopped from the dashboard"


@pytest.mark.timeout(60)
def test_remote_control_can_be_switched_off(fake_ur):
    assert _dashboard(fake_ur.host, "is in remote control") == ["true"]
    fake_ur.control("configure", remote_control=False)
    assert _dashboard(fake_ur.host, "is in remote control") == ["false"]
    status = fake_ur.wait_program(fake_ur.send_program("sync()\n"))
    assert status["state"] == "refused" and "local control" in status["message"]
    assert _dashboard(fake_ur.host, "play") == ["Failed to execute: play"]
    fake_ur.control("configure", remote_control=True)
    assert fake_ur.wait_program(fake_ur.send_program("sync()\n"))["state"] == "finished"
    assert _dashboard(fake_ur.host, "play") == ["Starting program"]  # runs it again
    with pytest.raises(RuntimeError, match="remote_control is true or false"):
        fake_ur.control("configure", remote_control="no")


@pytest.mark.timeout(60)
def test_ur_rtde_set_tcp_and_set_payload_are_honoured(fake_ur):
    import rtde_control
    import rtde_receive

    flags = (
        rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        | rtde_control.RTDEControlInterface.FLAG_DISABLE_REMOTE_CONTROL_CHECK
    )
    receive = rtde_receive.RTDEReceiveInterface(fake_ur.host)
    control = rtde_control.RTDEControlInterface(fake_ur.host, -1.0, flags)
    try:
        flange = np.array(receive.getActualTCPPose())
        assert flange == pytest.approx(tcp_of(HOME, np.zeros(6)), abs=1e-9)
        assert control.setTcp(list(TCP))
        assert control.setPayload(1.2, [0.0, 0.01, 0.05])
        time.sleep(0.05)
        assert np.array(receive.getActualTCPPose()) == pytest.approx(tcp_of(HOME), abs=1e-9)
        assert np.array(receive.getTargetTCPPose()) == pytest.approx(tcp_of(HOME), abs=1e-9)
        assert np.array(control.getTCPOffset()) == pytest.approx(TCP)
        assert np.array(control.getForwardKinematics()) == pytest.approx(tcp_of(HOME), abs=1e-9)
        assert receive.getPayload() == pytest.approx(1.2)
        assert np.array(receive.getPayloadCog()) == pytest.approx([0.0, 0.01, 0.05])
        status = fake_ur.control("status")
        assert status["tcp_offset"] == pytest.approx(TCP) and status["payload_kg"] == 1.2
        # moveL takes TCP poses: 3 cm down with the tool, a straight TCP line.
        goal = tcp_of(HOME) + [0, 0, -0.03, 0, 0, 0]
        assert control.moveL(list(goal), 0.1, 1.2)
        reached = np.array(receive.getActualTCPPose())
        # (a half-turn's rotation vector has two spellings, r and -r: compare rotations)
        assert reached[:3] == pytest.approx(goal[:3], abs=1e-4)
        assert rotation_error(reached, goal) < 1e-4
        assert np.array(receive.getActualQ()) == pytest.approx(ik_near(goal, HOME), abs=1e-3)
        assert np.array(control.getInverseKinematics(list(goal))) == pytest.approx(
            ik_near(goal, HOME), abs=1e-6
        )
        # setPayload with a zero cog keeps the one set before, as the pinned script does.
        assert control.setPayload(0.8, [0.0, 0.0, 0.0])
        time.sleep(0.05)
        assert receive.getPayload() == pytest.approx(0.8)
        assert np.array(receive.getPayloadCog()) == pytest.approx([0.0, 0.01, 0.05])
        # The recorded trace covers ur_rtde's control script too.
        trace = fake_ur.program_trace()
        assert trace["tcp_pose"][-1] == pytest.approx(goal, abs=1e-4)
    finally:
        control.stopScript()
        control.disconnect()
        receive.disconnect()


def test_a_transit_in_two_joint_moves_is_exported_as_two_movej_and_followed():
    """The plan turns the base first, then unfolds the arm (a direct joint move would sweep low):
    the program must follow both moves, not one movej that cuts the corner the check passed."""
    from drivers.robot.urscript import joint_stops, urscript_program
    from recon import motion
    from recon.transforms import transform_from_pose as T_of

    turned = HOME + [1.5, 0, 0, 0, 0, 0]
    goal = turned + [0, -0.4, 0.6, -0.3, 0.2, 0.5]
    rates = {"speed_scale": 0.5, "acceleration_scale": 0.5}
    moves = [
        motion.joint_move(ARM, HOME, turned, **rates),
        motion.joint_move(ARM, turned, goal, **rates),
    ]
    plan = motion.assemble(ARM, moves, T_flange_tcp=T_of(TCP), requested_speed_m_s=0.05)
    stops = joint_stops(plan)
    assert len(stops) == 3 and np.abs(plan.q_rad[stops[1]] - turned).max() < 1e-9
    text = urscript_program(plan, tcp_pose=TCP)
    assert text.count("movej(") == 2
    c = started(text)
    assert run(c, max_s=60).state == "finished"
    q_run = c.trace.rows()[:, 1:7]
    assert np.abs(q_run[-1] - goal).max() < 1e-3
    # Every controller sample lies on the planned joint path: two straight joint segments.
    off_rad = np.minimum(_off_segment(q_run, HOME, turned), _off_segment(q_run, turned, goal))
    assert off_rad.max() < 2e-3, off_rad.max()
    # A single movej would have passed far from the turned pose.
    assert _off_segment(turned[None], HOME, goal)[0] > 0.5


def _off_segment(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Joint-space distance (rad) of each row of ``q`` (n, 6) from the segment a-b."""
    u = np.clip((q - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(q - (a + u[:, None] * (b - a)), axis=1)


def test_an_exported_motion_over_two_pieces_runs_both_with_the_lift_between():
    from drivers.robot.urscript import urscript_program
    from recon.metrics import distance_to_curve
    from recon.plan import PlanParams, plan_path

    s = np.linspace(0.0, 0.08, 81)
    first = np.column_stack([0.4 + 0 * s, -0.12 + s, np.full_like(s, 0.1)])
    second = np.column_stack([0.4 + 0 * s, 0.04 + s, np.full_like(s, 0.1)])
    plan = plan_path(
        np.vstack([first, second]),
        params=PlanParams(speed_m_s=0.05, tcp_pose=tuple(TCP)),
        piece=np.repeat([0, 1], 81),
    )
    traj = plan.trajectory
    text = urscript_program(traj, tcp_pose=TCP, mode="movep")
    assert text.count("movel(") == 4 and text.count("# transit") == 2
    c = ctl.FakeController("ur5e")
    c.reset_arm(traj.q_rad[0])
    assert c.load_program(text), c.run
    assert run(c, max_s=120).state == "finished"
    rows = c.trace.rows()
    tcp_run = rows[:, 7:10]
    assert np.abs(rows[-1, 1:7] - traj.q_rad[-1]).max() < 2e-3
    # On the plan throughout (movep: its tolerance and blends), both pieces traced.
    off = distance_to_curve(tcp_run, traj.tcp_m)
    assert off.max() < 3e-3, off.max()
    for piece in (first, second):
        assert distance_to_curve(piece, tcp_run).max() < 1e-3


def test_an_exported_program_sets_the_payload_given_and_never_a_silent_zero():
    """Every exported program had `set_payload(0.0000, ...)`: it overrode the installation's
    payload (a gripper's kilograms) with nothing. A plan without a payload sets none (the
    installation's stays, and the program says so); one with a payload sets it."""
    from drivers.robot.urscript import urscript_program
    from recon import motion
    from recon.transforms import transform_from_pose as T_of

    plan = motion.assemble(
        ARM,
        [
            motion.joint_move(
                ARM, HOME, HOME + [0.3, 0, 0, 0, 0, 0], speed_scale=0.5, acceleration_scale=0.5
            )
        ],
        T_flange_tcp=T_of(TCP),
        requested_speed_m_s=0.05,
    )
    kept = urscript_program(plan, tcp_pose=TCP)
    assert "set_payload(" not in kept and "installation's is kept" in kept
    c = started(kept)
    c.set_payload(2.0, [0, 0, 0.05], None)  # the installation's
    assert run(c, max_s=60).state == "finished"
    assert c.payload_kg == 2.0 and c.payload_cog_m.tolist() == [0, 0, 0.05]
    given = urscript_program(plan, tcp_pose=TCP, payload_kg=1.2, payload_cog_m=(0, 0, 0.04))
    assert "set_payload(1.2000, [0.000000, 0.000000, 0.040000])" in given
    c = started(given)
    assert run(c, max_s=60).state == "finished"
    assert c.payload_kg == 1.2
