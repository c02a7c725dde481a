"""What running a reader in a child process costs (``make bench``): drivers.isolation; prints only.

A call of :func:`drivers.isolation.run_isolated` starts an interpreter, imports the target's
module there and hands its arrays back through an ``.npz`` file.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest

from drivers.isolation import run_isolated

pytestmark = pytest.mark.bench

T = "tests.drivers.isolation_targets:"


def _median(fn, repeats=7):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def test_spawn_overhead():
    cases = [
        ("time.sleep(0): interpreter start only", "time:sleep", (0,)),
        ("a module that imports numpy, nothing returned", T + "nothing", ()),
        ("1 KB array", T + "zeros", (1 << 10,)),
        ("10 MB array", T + "zeros", (10 << 20,)),
        ("200 MB array", T + "zeros", (200 << 20,)),
    ]
    print("\n## drivers.isolation.run_isolated: cost of one call (median of 7)\n")
    print("| call | s |")
    print("|---|---:|")
    for label, target, args in cases:
        seconds = _median(lambda target=target, args=args: run_isolated(target, args))
        print(f"| {label} | {seconds:.3f} |")
    got = run_isolated(T + "zeros", (10 << 20,))
    assert got["zeros"].shape == (10 << 20,) and not np.any(got["zeros"])
