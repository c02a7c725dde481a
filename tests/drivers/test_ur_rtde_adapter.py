"""The ur_rtde adapter without a controller: unreachable and silent controllers.

The real client runs in a worker process, so a controller that never answers costs a timeout,
not a frozen process: a thread of the test keeps ticking while the adapter waits.
"""

import socket
import threading
import time

import pytest

from drivers.errors import ConnectionLostError, NotConnectedError, RobotTimeoutError
from drivers.robot.base import RobotState
from drivers.robot.ur_rtde import URRtdeBackend, URRtdeConfig

#: These tests drive ur_rtde, which waits up to 300 s for a command: bound them.
pytestmark = pytest.mark.timeout(60)


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
    gaps = [b - a for a, b in zip(ticks, ticks[1:], strict=False)]
    assert len(ticks) > 20 and max(gaps) < 0.5
    assert robot.state is RobotState.DISCONNECTED
    robot.close()
