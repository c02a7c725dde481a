"""WorkerClient: typed commands to a worker process, bounded replies, errors back by class."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from drivers.errors import (
    DriverError,
    InputFileError,
    ProtectiveStopError,
    RobotError,
    WorkerError,
    WorkerLostError,
    WorkerTimeoutError,
)
from drivers.worker import Command, WorkerClient
from tests.drivers.worker_targets import (
    Count,
    Echo,
    Fail,
    Pid,
    Sleep,
    Unserved,
    WaitForStop,
)

SERVER = "tests.drivers.worker_targets:EchoServer"

#: Each test starts a worker process or two; none should come near this.
pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def client():
    """One worker for the tests that leave it running."""
    worker = WorkerClient(SERVER, name="the test worker")
    yield worker
    worker.close()


def test_a_typed_command_round_trip(client):
    assert client.call(Echo("hello"), timeout_s=30) == "hello"
    q = np.linspace(0, 1, 6)
    np.testing.assert_array_equal(client.call(Echo(q), timeout_s=5), q)
    assert client.call(Pid(), timeout_s=5) == client.process.pid != os.getpid()


def test_progress_reports_reach_the_caller(client):
    seen = []
    assert client.call(Count(3), timeout_s=5, on_progress=seen.append) == 3
    assert seen == [1, 2, 3]


def test_an_error_comes_back_as_its_class(client):
    with pytest.raises(ProtectiveStopError) as raised:
        client.call(Fail("protective_stop", "the arm is in a protective stop"), timeout_s=5)
    assert type(raised.value) is ProtectiveStopError
    assert str(raised.value) == "the arm is in a protective stop"
    assert client.alive  # an error is an answer: the worker serves on


def test_a_class_outside_the_table_is_the_generic_error(client):
    with pytest.raises(DriverError, match="^VendorError: no such register$") as raised:
        client.call(Fail("vendor", "no such register"), timeout_s=5)
    assert type(raised.value) is DriverError


def test_the_server_translates_library_errors(client):
    with pytest.raises(InputFileError, match="translated: socket closed"):
        client.call(Fail("runtime", "socket closed"), timeout_s=5)


def test_commands_must_be_typed_and_served(client):
    with pytest.raises(TypeError, match="Command objects"):
        client.call("read_q", timeout_s=5)  # type: ignore[arg-type]
    with pytest.raises(DriverError, match="does not serve Unserved"):
        client.call(Unserved(), timeout_s=5)
    with pytest.raises(ValueError, match="timeout_s"):
        client.call(Echo(1), timeout_s=0)


def test_labels_name_commands_in_snake_case():
    class MoveJ(Command):
        pass

    assert MoveJ.label() == "move_j" and WaitForStop.label() == "wait_for_stop"


def test_the_fallback_class_is_the_client_s_choice():
    with (
        WorkerClient(SERVER, name="the arm's worker", fallback=RobotError) as worker,
        pytest.raises(RobotError, match="VendorError: boom"),
    ):
        worker.call(Fail("vendor", "boom"), timeout_s=30)


def test_a_command_that_overruns_its_bound_ends_the_worker():
    worker = WorkerClient(SERVER, name="the test worker")
    assert worker.call(Echo(1), timeout_s=30) == 1  # started and serving
    started = time.monotonic()
    with pytest.raises(
        WorkerTimeoutError, match="the test worker did not answer sleep within 0.5 s"
    ):
        worker.call(Sleep(3600), timeout_s=0.5)
    assert time.monotonic() - started < 30  # not the hour the command wanted
    assert not worker.process.is_alive() and not worker.alive
    with pytest.raises(WorkerLostError, match="closed"):
        worker.call(Echo(1), timeout_s=5)
    worker.close()  # idempotent


def test_close_ends_the_process_after_the_server_s_shutdown(tmp_path):
    marker = tmp_path / "shutdown"
    worker = WorkerClient(SERVER, (str(marker),), name="the test worker")
    assert worker.call(Echo(1), timeout_s=30) == 1
    worker.close()
    assert not worker.process.is_alive() and worker.process.exitcode == 0
    assert marker.read_text() == "shut down"
    worker.close()


def test_a_worker_that_dies_is_a_lost_worker():
    worker = WorkerClient(SERVER, name="the test worker")
    assert worker.call(Echo(1), timeout_s=30) == 1
    worker.process.kill()
    worker.process.join(5)
    with pytest.raises(WorkerLostError, match="the test worker"):
        worker.call(Echo(2), timeout_s=5)
    worker.close()


def test_a_server_that_cannot_start_answers_with_its_error():
    with (
        WorkerClient("tests.drivers.worker_targets:BrokenServer", name="w") as worker,
        pytest.raises(InputFileError, match="would not start"),
    ):
        worker.call(Echo(1), timeout_s=30)


def test_the_stop_event_reaches_a_busy_server(client):
    threading.Timer(0.3, client.stop_event.set).start()
    try:
        assert client.call(WaitForStop(20), timeout_s=30) is True
    finally:
        client.stop_event.clear()


@pytest.mark.slow
def test_a_second_caller_waits_within_its_own_bound(client):
    busy = threading.Thread(target=client.call, args=(Sleep(2.0),), kwargs={"timeout_s": 30})
    busy.start()
    deadline = time.monotonic() + 10
    while not client._lock.locked():
        assert time.monotonic() < deadline
        time.sleep(0.01)
    with pytest.raises(WorkerError, match="busy with another command") as raised:
        client.call(Echo(1), timeout_s=0.2)
    assert type(raised.value) is WorkerError  # the worker was not ended for it
    busy.join()
    assert client.call(Echo(2), timeout_s=5) == 2


def test_the_worker_ends_when_its_parent_dies(tmp_path):
    pid_file = tmp_path / "worker.pid"
    code = (
        "import time; from drivers.worker import WorkerClient; "
        "from tests.drivers.worker_targets import Pid; "
        f"w = WorkerClient({SERVER!r}, name='w'); "
        f"open({str(pid_file)!r}, 'w').write(str(w.call(Pid(), timeout_s=30))); "
        "time.sleep(3600)"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=os.getcwd())
    try:
        deadline = time.monotonic() + 40
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline and parent.poll() is None
            time.sleep(0.05)
        worker = int(pid_file.read_text())
    finally:
        parent.send_signal(signal.SIGKILL)  # no atexit, no close(): the worker notices alone
        parent.wait()
    deadline = time.monotonic() + 20
    while _running(worker):
        assert time.monotonic() < deadline, "the worker outlived its parent"
        time.sleep(0.1)


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as handle:
            state = handle.read().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")
