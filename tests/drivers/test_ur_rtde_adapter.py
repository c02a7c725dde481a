"""The ur_rtde adapter without a controller: unreachable and silent controllers.

The real client runs in a worker process, so a controller that never answers costs a timeout,
not a frozen process: a thread of the test keeps ticking while the adapter waits.
"""

import itertools
import socket
import threading
import time

import pytest

from drivers.errors import (
    ConnectionLostError,
    NotConnectedError,
    ProtectiveStopError,
    RobotTimeoutError,
)
from drivers.robot.base import RobotState
from drivers.robot.ur_rtde import URRtdeBackend, URRtdeConfig

#: These tests drive ur_rtde, which waits up to 300 s for a command: bound them.
# Against the fake controller in real time: make test-fast leaves them out.
pytestmark = [pytest.mark.timeout(60), pytest.mark.slow]


def test_an_unreachable_controller_is_a_clear_error():
    robot = URRtdeBackend(URRtdeConfig(host="127.0.0.9", connect_timeout_s=10))
    with pytest.raises(ConnectionLostError, match="cannot connect to the controller at 127.0.0.9"):
        robot.connect()
    assert robot.state is RobotState.DISCONNECTED
    with pytest.raises(NotConnectedError):
        robot.status()
    robot.close()


@pytest.fixture
def silent_controller():
    """Accepts connections on the RTDE port of 127.0.0.11 and never says a word."""
    server = socket.create_server(("127.0.0.11", 30004))
    accepted = []
    stop = threading.Event()

    def accept():
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                accepted.append(server.accept()[0])
            except TimeoutError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield "127.0.0.11"
    stop.set()
    thread.join()
    for conn in accepted:
        conn.close()
    server.close()


def test_a_silent_controller_times_out_without_freezing_the_caller(silent_controller):
    ticks = []
    running = threading.Event()
    running.set()

    def tick():
        while running.is_set():
            ticks.append(time.monotonic())
            time.sleep(0.05)

    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    robot = URRtdeBackend(URRtdeConfig(host=silent_controller, connect_timeout_s=2.0))
    with pytest.raises(RobotTimeoutError, match="did not answer connect"):
        robot.connect()
    running.clear()
    ticker.join()
    # The process stayed responsive while ur_rtde blocked in the worker.
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert len(ticks) > 20 and max(gaps) < 0.5
    assert robot.state is RobotState.DISCONNECTED
    robot.close()


# -- against the fake controller -------------------------------------------------------------------

from tests.drivers import fake_ur_fixture  # noqa: E402 - the fixtures below use it

fake_ur_process = fake_ur_fixture.fake_ur_process
fake_ur = fake_ur_fixture.fake_ur


def test_a_lost_link_ends_its_worker_so_a_reconnect_starts_clean(fake_ur):
    robot = URRtdeBackend(URRtdeConfig(host=fake_ur.host, connect_timeout_s=5.0))
    robot.connect()
    robot.enable()
    worker = robot._worker.process
    fake_ur.control("freeze")
    time.sleep(0.3)  # packages already on their way reach the client first
    with pytest.raises(ConnectionLostError, match="no new data"):
        robot.status()
    # The old worker (and the RTDE input registers its ur_rtde held) is gone at once.
    worker.join(timeout=5)
    assert not worker.is_alive() and robot.state is RobotState.DISCONNECTED
    fake_ur.control("unfreeze")
    robot.connect()
    robot.enable()
    assert robot.status().q_rad.shape == (6,)
    robot.close()


def test_a_protective_stop_while_settling_on_the_last_sample_is_not_a_success(fake_ur):
    from dataclasses import replace

    from drivers.robot.ur_rtde import PROGRESS_EVERY
    from tests.motion_fixtures import line_process

    full = line_process("ur5e", 0.1)
    # Cut so that the streaming loop's last progress report comes with its last sample: a stop
    # injected then lands while the adapter holds the last target for the arm (a lookahead
    # behind, still moving) to arrive.
    m = (len(full) - 1) // PROGRESS_EVERY * PROGRESS_EVERY + 1
    fields = (
        "t_s",
        "q_rad",
        "qd_rad_s",
        "qdd_rad_s2",
        "tcp_m",
        "tcp_rotvec",
        "arc_length_m",
        "phase",
    )
    trajectory = replace(full, **{name: getattr(full, name)[:m] for name in fields})
    fake_ur.control("reset", q_rad=trajectory.q_rad[0].tolist())
    robot = URRtdeBackend(URRtdeConfig(host=fake_ur.host, connect_timeout_s=5.0))
    robot.connect()
    robot.enable()
    stopped = []

    def stop_at_the_end(fraction):
        if fraction >= 1.0 and not stopped:
            stopped.append(fake_ur.control("protective_stop"))

    try:
        with pytest.raises(ProtectiveStopError):
            robot.execute(trajectory, on_progress=stop_at_the_end)
        assert stopped and robot.state is RobotState.PROTECTIVE_STOP
    finally:
        robot.close()


def test_enable_powers_on_and_releases_the_brakes_only_when_told(tmp_path):
    from drivers.errors import NotEnabledError

    fake = fake_ur_fixture.FakeURProcess(tmp_path / "fake.log", extra_args=["--powered-off"])
    fake.start()
    try:
        robot = URRtdeBackend(URRtdeConfig(host=fake.host, connect_timeout_s=5.0))
        robot.connect()
        with pytest.raises(NotEnabledError, match="power it on"):
            robot.enable()
        robot.close()
        assert fake.control("status")["robot_mode"] == 3  # still powered off
        robot = URRtdeBackend(URRtdeConfig(host=fake.host, connect_timeout_s=5.0, power_on=True))
        robot.connect()
        robot.enable()
        assert robot.state is RobotState.ENABLED
        assert fake.control("status")["robot_mode"] == 7  # running
        robot.close()
    finally:
        fake.stop()
