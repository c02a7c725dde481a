"""Property-based fuzzing of every reader (project issue "Robustness", point 8): random bytes
and mutated sound files of each format are read or refused with an input error, never another
exception, never a crash, within the parse memory limit.

The readers run in one child process (:mod:`tests.drivers.reader_fuzz_runner`) under the
service's parse memory limit (``TEACHPATH_MAX_PARSE_MEMORY_MB``'s default): a crash of native code
fails this test naming the reader (its input kept), instead of killing the test run; so does
memory past the limit (a MemoryError), a crash of a reader's own child process, or a package
the reader needs that is not installed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
#: Inputs per reader (readers that parse in a child of their own get an eighth).
EXAMPLES = 120


@pytest.mark.slow
def test_every_reader_reads_or_refuses_fuzzed_input_within_the_memory_limit(tmp_path):
    memory_mb = Settings.model_fields["max_parse_memory_mb"].default
    run = subprocess.run(
        [sys.executable, "-m", "tests.drivers.reader_fuzz_runner", str(tmp_path), str(memory_mb),
         str(EXAMPLES)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=900,
    )  # fmt: skip
    results, started = {}, None
    peak_mb = None
    for line in run.stdout.splitlines():
        record = json.loads(line)
        if "start" in record:
            started = record["start"]
        elif "peak_rss_mb" in record:
            peak_mb = record["peak_rss_mb"]
        else:
            results[record["reader"]] = record
            started = None
    assert started is None, (
        f"reading fuzzed {started} input killed the process (exit {run.returncode}); the input "
        f"is {tmp_path / ('current-' + started)}\n{run.stderr[-3000:]}"
    )
    assert run.returncode == 0, run.stderr[-3000:]
    failures = {name: r["failure"] for name, r in results.items() if "failure" in r}
    assert not failures, json.dumps(failures, indent=1)
    expected = {
        "canonical_csv", "motive_csv", "rtde_csv", "c3d", "calibration", "tip_calibration",
        "ply", "pcd", "xyz", "xyzn", "pts", "e57", "rgbd_zip", "bag",
    }  # fmt: skip
    assert set(results) == expected
    for name, r in results.items():
        # Every reader saw inputs, and the damage was real: most of them refused.
        refused = r["refused"] + r["crashed in its child"]
        total = r["read"] + refused
        assert total >= 4 and refused >= total // 3, (name, r)
    # Shown with `pytest -s`; a reader past the limit failed above with its MemoryError.
    print(f"fuzz child peak resident memory {peak_mb:.0f} MB (limit {memory_mb:.0f} MB)")
