"""The execution journal's cost inside the servo loop, per sample (``make bench``).

The loop writes one sample per 2 ms controller period. Against today's memory-mapped journal,
the text journal of earlier versions (a formatted CSV line, flushed every 50 samples), written
here as it was, in the same run. Printed, never asserted: the machines are shared and noisy.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.robot.journal import CSV_HEADER, JournalWriter

pytestmark = [pytest.mark.bench, pytest.mark.timeout(300)]

SAMPLES = 30_000  # a minute at 500 Hz


def _time_adds(add, samples: int) -> np.ndarray:
    """Seconds per call of ``add(t, q, tcp)``, shape (samples,), with the arguments a
    ur_rtde getter returns (lists of floats)."""
    rng = np.random.default_rng(0)
    q_rows, tcp_rows = (
        rng.normal(size=(samples, 6)).tolist(),
        rng.normal(size=(samples, 6)).tolist(),
    )
    spent = np.zeros(samples)
    for i in range(samples):
        start = time.perf_counter()
        add(i * 0.002, q_rows[i], tcp_rows[i])
        spent[i] = time.perf_counter() - start
    return spent


class _TextJournal:
    """The text journal as earlier versions wrote it (the baseline)."""

    def __init__(self, path) -> None:
        self.file = open(path, "w", buffering=1 << 16)  # noqa: SIM115
        self.file.write(CSV_HEADER)
        self.pending = 0

    def add(self, t_s, q_rad, tcp_pose) -> None:
        self.file.write(",".join(f"{v:.9g}" for v in (t_s, *q_rad, *tcp_pose)) + "\n")
        self.pending += 1
        if self.pending >= 50:
            self.file.flush()
            self.pending = 0


def test_journal_cost_per_sample(tmp_path):
    print(f"\n## The journal's cost per sample in the servo loop ({SAMPLES:,} samples)\n")
    print("| journal | median us | p99 us | max us | samples over 100 us |")
    print("|---|---:|---:|---:|---:|")
    results = {}
    for rounds in range(3):  # alternated, so that both see the same machine
        text = _TextJournal(tmp_path / f"text{rounds}.csv")
        results.setdefault("text, flushed every 50 (earlier)", []).append(
            _time_adds(text.add, SAMPLES)
        )
        text.file.close()
        with JournalWriter(tmp_path / f"mapped{rounds}.journal", SAMPLES) as mapped:
            results.setdefault("memory-mapped (now)", []).append(_time_adds(mapped.add, SAMPLES))
    for name, runs in results.items():
        spent_us = np.concatenate(runs) * 1e6
        p50, p99 = np.percentile(spent_us, [50, 99])
        print(
            f"| {name} | {p50:.2f} | {p99:.2f} | {spent_us.max():.1f} | "
            f"{int((spent_us > 100).sum())} of {len(spent_us):,} |"
        )
