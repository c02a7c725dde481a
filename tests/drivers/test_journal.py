"""The execution journal: what a killed writer leaves is read back; what no writer left is
refused."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from drivers.errors import InputFileError
from drivers.robot.journal import (
    COLUMNS,
    CSV_HEADER,
    HEADER_BYTES,
    MAGIC,
    MAGIC_V1,
    MAX_SAMPLES,
    ROW_BYTES,
    JournalWriter,
    read_journal,
    read_journal_with_plan,
)


def _samples(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    data = rng.normal(size=(n, 13))
    data[:, 0] = np.arange(n) * 0.002
    return data


def _write(path, data, capacity=None):
    with JournalWriter(path, capacity_samples=capacity or len(data)) as writer:
        for row in data:
            writer.add(row[0], row[1:7], list(row[7:13]))
        assert len(writer) == len(data)


def test_samples_come_back_bit_for_bit_and_the_file_is_private(tmp_path):
    data = _samples(1000)
    path = tmp_path / "j.journal"
    _write(path, data)
    t, q, tcp = read_journal(path)
    assert np.array_equal(np.column_stack([t, q, tcp]), data)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_a_journal_outgrowing_its_capacity_keeps_every_sample(tmp_path):
    data = _samples(37)
    path = tmp_path / "j.journal"
    _write(path, data, capacity=2)  # remapped at 2, 4, 8, 16, 32
    t, q, tcp = read_journal(path)
    assert np.array_equal(np.column_stack([t, q, tcp]), data)


def test_an_empty_journal_has_no_samples(tmp_path):
    path = tmp_path / "j.journal"
    JournalWriter(path).close()
    t, q, tcp = read_journal(path)
    assert t.shape == (0,) and q.shape == (0, 6) and tcp.shape == (0, 6)


def test_a_writer_killed_mid_motion_leaves_every_sample_it_stored(tmp_path):
    """The crash the journal is for: the process dies (SIGKILL, nothing closed or flushed);
    what it stored before is in the file."""
    path = tmp_path / "killed.journal"
    script = textwrap.dedent(
        f"""
        import os, signal
        from drivers.robot.journal import JournalWriter
        writer = JournalWriter({str(path)!r}, capacity_samples=100)
        for i in range(1234):  # past the capacity: remapped on the way
            writer.add(i * 0.002, [i] * 6, [-i] * 6)
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=os.getcwd(), timeout=60)
    assert done.returncode == -signal.SIGKILL
    t, q, tcp = read_journal(path)
    assert len(t) == 1234
    assert np.array_equal(q[:, 0], np.arange(1234)) and np.array_equal(tcp[-1], [-1233] * 6)


def test_a_row_written_but_not_counted_is_not_read(tmp_path):
    """A writer killed between a row and its count: the row is not a sample."""
    path = tmp_path / "j.journal"
    _write(path, _samples(10))
    raw = bytearray(path.read_bytes())
    raw[24:32] = np.uint64(9).tobytes()  # the count, as before the last row's store
    path.write_bytes(bytes(raw))
    assert len(read_journal(path)[0]) == 9


def _header(count: int, capacity: int, columns: int = COLUMNS, magic: bytes = MAGIC) -> bytes:
    head = magic + np.uint32(columns).tobytes() + bytes(4)
    head += np.uint64(capacity).tobytes() + np.uint64(count).tobytes()
    return head.ljust(HEADER_BYTES, b"\0")


def test_the_plan_clock_of_a_slowed_run_comes_back(tmp_path):
    """A run slowed or paused: each sample keeps where on the plan's clock the arm was sent."""
    data = _samples(50)
    plan_s = np.concatenate([np.arange(25) * 0.002, np.full(25, 24 * 0.002)])  # then paused
    path = tmp_path / "j.journal"
    with JournalWriter(path, capacity_samples=10) as writer:
        for row, plan in zip(data, plan_s, strict=True):
            writer.add(row[0], row[1:7], row[7:13], plan_s=plan)
    t, q, tcp, plan_back = read_journal_with_plan(path)
    assert np.array_equal(np.column_stack([t, q, tcp]), data)
    assert np.array_equal(plan_back, plan_s)


def test_a_journal_of_the_version_before_reads_with_the_plan_at_its_own_pace(tmp_path):
    """13 columns and the first magic: written before speed override existed."""
    data = _samples(6)
    path = tmp_path / "old.journal"
    path.write_bytes(_header(6, 8, columns=13, magic=MAGIC_V1) + data.tobytes() + bytes(2 * 104))
    t, q, tcp, plan_s = read_journal_with_plan(path)
    assert np.array_equal(np.column_stack([t, q, tcp]), data)
    assert np.array_equal(plan_s, t)


def test_a_plan_clock_going_backwards_is_refused_naming_the_sample(tmp_path):
    data = _samples(10)
    path = tmp_path / "j.journal"
    with JournalWriter(path) as writer:
        for i, row in enumerate(data):
            writer.add(row[0], row[1:7], row[7:13], plan_s=0.1 if i == 6 else i * 0.002)
    with pytest.raises(InputFileError, match="sample 8"):
        read_journal(path)


@pytest.mark.parametrize(
    "content, words",
    [
        (b"\x89PNG\r\n\x1a\n" + bytes(100), "not a teachpath journal"),
        (MAGIC + bytes(10), "not a teachpath journal"),  # the header itself cut
        (_header(5, 5) + bytes(2 * ROW_BYTES), "declares 5 samples"),  # cut after two rows
        (_header(5, 3) + bytes(5 * ROW_BYTES), "in room for 3"),  # more than its capacity
        (_header(2**63, 2**64 - 1), "declares 9,223,372,036,854,775,808 samples"),
        (_header(MAX_SAMPLES + 1, MAX_SAMPLES + 1), "at most 4,000,000"),  # no 430 MB+ read
        (_header(1, 1, columns=12) + bytes(ROW_BYTES), "of 12 numbers"),
        (_header(1, 1, columns=14, magic=MAGIC_V1) + bytes(ROW_BYTES), "of 14 numbers"),
    ],
    ids=["png", "cut-header", "cut-rows", "over-capacity", "huge", "too-many", "columns", "v1-14"],
)
def test_files_no_writer_left_are_refused_with_what_is_wrong(tmp_path, content, words):
    path = tmp_path / "bad.journal"
    path.write_bytes(content)
    with pytest.raises(InputFileError, match=words) as error:
        read_journal(path)
    assert "bad.journal" in str(error.value)


@pytest.mark.parametrize("poison", ["nan", "inf", "backwards"])
def test_samples_no_arm_reported_are_refused_naming_the_sample(tmp_path, poison):
    data = _samples(20)
    if poison == "backwards":
        data[7, 0] = data[5, 0]
    else:
        data[7, 3] = float(poison)
    path = tmp_path / "j.journal"
    _write(path, data)
    with pytest.raises(InputFileError, match="sample 8"):
        read_journal(path)


def test_a_missing_journal_or_a_folder_is_an_input_error(tmp_path):
    with pytest.raises(InputFileError, match="cannot be read"):
        read_journal(tmp_path / "absent.journal")
    with pytest.raises(InputFileError, match="cannot be read"):
        read_journal(tmp_path)


def _csv(data: np.ndarray) -> str:
    return CSV_HEADER + "".join(",".join(f"{v:.9g}" for v in row) + "\n" for row in data)


def test_text_journals_of_earlier_versions_are_still_read(tmp_path):
    data = _samples(30)
    path = tmp_path / "exe_old.csv"
    path.write_text(_csv(data) + "0.06,1,2")  # a torn last line: the writer died mid-line
    t, q, _tcp = read_journal(path)
    assert len(t) == 30
    np.testing.assert_allclose(np.column_stack([t, q]), data[:, :7], rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize(
    "body, words",
    [
        ("1,2,3\n", "line 2: 3 fields"),
        ("0," + ",".join(["x"] * 12) + "\n", "line 2"),
        ("0.1" + ",0" * 12 + "\n" + "0.0" + ",0" * 12 + "\n", "sample 2"),  # time backwards
    ],
    ids=["fields", "text", "backwards"],
)
def test_bad_text_journals_are_refused(tmp_path, body, words):
    path = tmp_path / "exe_old.csv"
    path.write_text(CSV_HEADER + body)
    with pytest.raises(InputFileError, match=words):
        read_journal(path)
    path.write_bytes(CSV_HEADER.encode() + b"\xff\xfe\n")
    with pytest.raises(InputFileError, match="cannot be read"):
        read_journal(path)


@pytest.mark.parametrize(
    "content", [b"", bytes(HEADER_BYTES + 3 * ROW_BYTES)], ids=["0 bytes", "zeros"]
)
def test_a_journal_nothing_was_written_to_has_no_samples(tmp_path, content):
    """The writer died before anything reached the file (a text journal before its first flush,
    a header never written back): the arm never moved under it. It was refused before."""
    for name in ("exe_x.journal", "exe_x.csv"):
        path = tmp_path / name
        path.write_bytes(content)
        t, q, tcp = read_journal(path)
        assert len(t) == 0 and q.shape == (0, 6) and tcp.shape == (0, 6)


def test_rows_counted_but_never_written_back_keep_the_samples_before_them(tmp_path):
    """A power loss can write the count's page back and not the last rows': they read as zeros
    at the end. The samples before them are kept (the whole journal was refused)."""
    path = tmp_path / "j.journal"
    data = _samples(50)
    _write(path, data)
    raw = bytearray(path.read_bytes())
    raw[HEADER_BYTES + 40 * ROW_BYTES : HEADER_BYTES + 50 * ROW_BYTES] = bytes(10 * ROW_BYTES)
    path.write_bytes(bytes(raw))
    t, q, tcp = read_journal(path)
    assert np.array_equal(np.column_stack([t, q, tcp]), data[:40])
