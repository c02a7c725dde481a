"""run_isolated: a function in a child process with limits; arrays and errors come back intact.

The targets live in ``tests/drivers/isolation_targets.py``, imported by name in the child.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from drivers.errors import (
    DriverError,
    InputFileError,
    MissingDependencyError,
    ReaderCrashError,
    ResourceLimitError,
    UnknownRigidBodyError,
)
from drivers.isolation import Limits, run_isolated
from recon.errors import DegenerateInputError
from tests.drivers import isolation_targets

T = "tests.drivers.isolation_targets:"

#: Each test starts one or two interpreters; none should come near this.
pytestmark = pytest.mark.timeout(60)


def test_arrays_come_back_intact():
    got = run_isolated(T + "arrays", (7,))
    want = isolation_targets.arrays(7)
    assert sorted(got) == sorted(want)
    for key, value in want.items():
        value = np.asarray(value)
        assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
        np.testing.assert_array_equal(got[key], value, err_msg=key)
    assert got["count"].item() == 42 and str(got["unit"]) == "mm"


def test_arguments_reach_the_child():
    got = run_isolated(T + "scaled", ([1.0, 2.0],), {"factor": 3.0})
    np.testing.assert_array_equal(got["values"], [3.0, 6.0])


@pytest.mark.parametrize(
    "target, cls",
    [
        ("raise_input_file_error", InputFileError),
        ("raise_unknown_rigid_body", UnknownRigidBodyError),
        ("raise_degenerate_input", DegenerateInputError),
        ("raise_value_error", ValueError),
    ],
)
def test_errors_come_back_as_their_class_with_their_message(target, cls):
    with pytest.raises(cls) as raised:
        run_isolated(T + target, ("what the child said",))
    assert type(raised.value) is cls
    assert str(raised.value) == "what the child said"


def test_other_exceptions_are_an_input_file_error_naming_them():
    expected = r"the reader failed unexpectedly \(KeyError: 'frames'\)"
    with pytest.raises(InputFileError, match=expected):
        run_isolated(T + "raise_key_error", what="the reader")


def test_a_missing_module_names_what_to_install():
    with pytest.raises(MissingDependencyError, match="teachpath_test_module_that_is_not_installed"):
        run_isolated(T + "import_missing_module", what="the reader")


def test_a_child_over_its_memory_limit_is_the_memory_limit_error():
    limits = Limits(memory_bytes=400 << 20, memory_setting="TEACHPATH_PARSE_MEMORY_MB")
    with pytest.raises(ResourceLimitError) as raised:
        run_isolated(T + "allocate", (2 << 30,), limits=limits, what="the parser")
    error = raised.value
    assert error.limit == "memory" and error.value == 400 << 20
    assert error.setting == "TEACHPATH_PARSE_MEMORY_MB"
    assert str(error) == (
        "the parser needed more memory than its limit of 400 MB (TEACHPATH_PARSE_MEMORY_MB)"
    )
    # Within the limit, the same function runs.
    assert run_isolated(T + "allocate", (1 << 20,), limits=limits)["sum"] == 1 << 20


def test_the_child_reports_its_peak_memory_within_its_limit():
    limits = Limits(memory_bytes=600 << 20)
    seen = []
    assert run_isolated(T + "allocate", (200 << 20,), limits=limits, on_usage=seen.append)
    (usage,) = seen
    # The 200 MB it filled, and not the caller's own size (Linux keeps ru_maxrss across exec).
    assert 200 << 20 <= usage.peak_rss_bytes <= usage.peak_address_space_bytes <= 600 << 20
    assert usage.memory_limit_bytes == 600 << 20 and usage.wall_s > 0
    # Over its limit, the report still comes, and stays within the limit.
    with pytest.raises(ResourceLimitError):
        run_isolated(T + "allocate", (2 << 30,), limits=limits, on_usage=seen.append)
    assert seen[1].peak_address_space_bytes <= 600 << 20


def test_a_child_under_a_lower_inherited_limit_names_that_limit():
    """A child of an isolated process cannot raise the limit it inherited: the error says the
    limit it ran under, not the one asked for."""
    outer = Limits(memory_bytes=700 << 20)
    with pytest.raises(ResourceLimitError) as raised:
        run_isolated(T + "allocate_in_a_child", (1 << 30, 4 << 30), limits=outer)
    assert str(raised.value) == "the inner needed more memory than its limit of 700 MB (inner)"


def test_a_child_over_its_time_limit_is_the_time_limit_error():
    started = time.monotonic()
    expected = r"did not finish within 1 s, its time limit \(t\)"
    with pytest.raises(ResourceLimitError, match=expected) as raised:
        run_isolated(T + "sleep", (3600,), limits=Limits(time_s=1.0, time_setting="t"))
    assert raised.value.limit == "time" and raised.value.setting == "t"
    assert time.monotonic() - started < 30  # killed, not waited for (the sleep is an hour)


def test_a_child_killed_by_sigkill_is_a_crash_error():
    with pytest.raises(ReaderCrashError, match=r"the parser crashed \(SIGKILL, which the sys") as e:
        run_isolated(T + "kill_self", what="the parser")
    assert e.value.signal_name == "SIGKILL"
    assert isinstance(e.value, InputFileError)  # what callers of the readers catch


def test_a_segfault_is_a_crash_error_with_the_child_s_last_words(capfd):
    with pytest.raises(ReaderCrashError, match=r"the parser crashed \(SIGSEGV\)") as raised:
        run_isolated(T + "segfault", what="the parser")
    assert "about to read address 0" in raised.value.output_tail
    assert capfd.readouterr() == ("", "")  # nor did the crash reach this process's stderr


def test_a_child_that_exits_without_an_answer_is_a_crash_error():
    with pytest.raises(ReaderCrashError, match=r"exited \(status 7\) without an answer") as e:
        run_isolated(T + "exit_quietly")
    assert e.value.exit_code == 7 and e.value.signal_name is None


def test_the_child_s_output_does_not_reach_the_caller(capfd):
    assert run_isolated(T + "noisy")["ok"]
    assert capfd.readouterr() == ("", "")


def test_the_child_gets_the_parent_s_path_and_one_thread():
    got = run_isolated(T + "thread_settings")
    assert str(got["openblas"]) == "1"
    assert list(got["path"]) == sys.path


def test_bad_limits_are_refused():
    with pytest.raises(ValueError, match="time_s"):
        Limits(time_s=0)
    with pytest.raises(ValueError, match="memory_bytes"):
        Limits(memory_bytes=-1)


def test_the_child_dies_with_its_parent(tmp_path):
    pid_file = tmp_path / "child.pid"
    code = (
        "from drivers.isolation import run_isolated; "
        f"run_isolated({T + 'sleep_recording_pid'!r}, ({str(pid_file)!r}, 3600))"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=os.getcwd())
    try:
        deadline = time.monotonic() + 30
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline and parent.poll() is None
            time.sleep(0.05)
        child = int(pid_file.read_text())
    finally:
        parent.send_signal(signal.SIGKILL)  # no chance to clean up: the kernel ends the child
        parent.wait()
    deadline = time.monotonic() + 10
    while _running(child):
        assert time.monotonic() < deadline, "the child outlived its parent"
        time.sleep(0.05)


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as handle:
            state = handle.read().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")  # a zombie has ended; whoever adopted it reaps it


def test_errors_that_cross_are_listed_once_each():
    from drivers import errors
    from drivers.errors import WIRE_ERRORS
    from recon import errors as recon_errors

    for module, base in ((errors, DriverError), (recon_errors, recon_errors.ReconError)):
        for name, value in vars(module).items():
            if isinstance(value, type) and issubclass(value, base):
                assert WIRE_ERRORS.get(name) is value, name
