"""C3D marker files: known trajectories in and out, long takes, and every kind of bad file --
including files that crash or hang ezc3d, which must not take the process down."""

import struct

import numpy as np
import pytest

from drivers.errors import InputFileError
from drivers.tracking import c3d as c3d_module
from drivers.tracking.c3d import read_c3d
from tests.drivers.tracking_fixtures import helix, write_c3d

LABELS = ["tip", "back", "left", "right"]
# C3D stores float32: about 6e-8 relative, so 3e-8 m at 0.5 m.
ATOL_M = 1e-7


def markers(n, rate_hz=240.0):
    t, p, _ = helix(n, rate_hz)
    offsets = np.array([[0, 0, 0], [0, 0, 0.12], [0.03, 0, 0.1], [-0.03, 0, 0.1]])
    return t, p[:, None, :] + offsets[None]


@pytest.mark.parametrize("units", ["mm", "m"])
def test_round_trip_with_lost_samples(tmp_path, units):
    t, pos = markers(500)
    lost = np.zeros((500, 4), bool)
    lost[100:130, 0] = True
    lost[0, 0] = lost[-1, 0] = True
    lost[200:300, 1] = True
    path = write_c3d(tmp_path / "take.c3d", LABELS, pos, 240.0, units=units, lost=lost)
    trace = read_c3d(path, marker="tip")
    batch = trace.batch
    np.testing.assert_array_equal(batch.valid, ~lost[:, 0])
    np.testing.assert_allclose(batch.position_m[~lost[:, 0]], pos[~lost[:, 0], 0], atol=ATOL_M)
    assert np.isnan(batch.position_m[lost[:, 0]]).all()
    np.testing.assert_allclose(batch.t_s, t, atol=1e-12)
    assert batch.orientation_xyzw is None
    assert trace.units == units and trace.rate_hz == 240.0 and trace.marker == "tip"
    assert trace.available == tuple(LABELS)
    np.testing.assert_array_equal(np.isnan(trace.residual_m), lost[:, 0])
    back = read_c3d(path, marker="back")
    np.testing.assert_array_equal(back.batch.valid, ~lost[:, 1])
    rec = trace.to_recording()
    assert len(rec) == int((~lost[:, 0]).sum())


def test_single_marker_is_chosen_and_bytes_are_accepted(tmp_path):
    _t, pos = markers(50)
    path = write_c3d(tmp_path / "one.c3d", ["pen"], pos[:, :1], 100.0)
    trace = read_c3d(path.read_bytes(), name="upload.c3d")
    assert trace.marker == "pen"
    np.testing.assert_allclose(trace.batch.position_m, pos[:, 0], atol=ATOL_M)
    np.testing.assert_allclose(trace.batch.t_s, np.arange(50) / 100.0)


def test_take_longer_than_65535_frames(tmp_path):
    # 200 s at 360 Hz: past the header's 16-bit frame numbers and ezc3d's own limit.
    n = 72_000
    _t, pos = markers(n, 360.0)
    lost = np.zeros((n, 2), bool)
    lost[[10, 65_534, 65_535, 70_000], 0] = True
    path = write_c3d(tmp_path / "long.c3d", LABELS[:2], pos[:, :2], 360.0, lost=lost)
    trace = read_c3d(path, marker="tip")
    assert len(trace) == n
    np.testing.assert_array_equal(trace.batch.valid, ~lost[:, 0])
    np.testing.assert_allclose(
        trace.batch.position_m[~lost[:, 0]], pos[~lost[:, 0], 0], atol=ATOL_M
    )
    np.testing.assert_allclose(trace.batch.t_s[-1], (n - 1) / 360.0)


def test_marker_choice_errors(tmp_path):
    _, pos = markers(20)
    path = write_c3d(tmp_path / "m.c3d", LABELS, pos, 100.0)
    with pytest.raises(InputFileError, match=r"4 markers \('tip', 'back', 'left', 'right'\)"):
        read_c3d(path)
    with pytest.raises(InputFileError, match="no marker named 'Tip'; it has 'tip', 'back'"):
        read_c3d(path, marker="Tip")
    with pytest.raises(ValueError, match="empty string"):
        read_c3d(path, marker="")


def test_units_come_from_the_file_or_the_argument(tmp_path):
    _, pos = markers(20)
    path = write_c3d(tmp_path / "u.c3d", ["tip"], pos[:, :1], 100.0, units="")
    with pytest.raises(InputFileError, match="POINT:UNITS is empty.*units='mm'"):
        read_c3d(path)
    trace = read_c3d(path, units="m")
    np.testing.assert_allclose(trace.batch.position_m, pos[:, 0], atol=ATOL_M)
    with pytest.raises(ValueError, match="unknown length unit"):
        read_c3d(path, units="furlong")
    # A unit in the file wins over the argument.
    in_mm = write_c3d(tmp_path / "mm.c3d", ["tip"], pos[:, :1], 100.0, units="mm")
    np.testing.assert_allclose(read_c3d(in_mm, units="m").batch.position_m, pos[:, 0], atol=ATOL_M)


def test_unknown_unit_in_the_file(tmp_path):
    _, pos = markers(20)
    path = write_c3d(tmp_path / "in.c3d", ["tip"], pos[:, :1], 100.0, units="mm")
    content = path.read_bytes()
    # POINT:UNITS is a two-character string in the parameter section.
    assert content.count(b"mm") == 1
    with pytest.raises(InputFileError, match="unknown length unit 'in'"):
        read_c3d(content.replace(b"mm", b"in"))


@pytest.fixture
def small_c3d(tmp_path):
    _, pos = markers(200)
    return write_c3d(tmp_path / "s.c3d", ["tip", "m1"], pos[:, :2], 100.0).read_bytes()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda b: b"", "is empty"),
        (lambda b: b"x,y,z\n1,2,3\n" * 200, "not a C3D file"),
        (lambda b: b[:300], "not a C3D file"),
        (lambda b: b[: len(b) // 2], "truncated: it declares 200 frames but holds \\d+"),
        (lambda b: b[:-600], "truncated: it declares 200 frames but holds 1\\d\\d"),
        (lambda b: b[:1100], "truncated|not a readable C3D file"),
        # Processor type byte of the parameter section.
        (lambda b: b[:515] + b"\x07" + b[516:], "not a readable C3D file.*processor type"),
    ],
)
def test_bad_files_are_refused_with_a_reason(small_c3d, edit, message):
    with pytest.raises(InputFileError, match=message):
        read_c3d(edit(small_c3d), name="take.c3d", marker="tip")


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_c3d(tmp_path / "nope.c3d")
    with pytest.raises(InputFileError, match="directory"):
        read_c3d(tmp_path)


# Single bytes of the parameter section that make ezc3d 1.7.2 crash (SIGSEGV) or loop for ever,
# found by mutating the file written above. A later ezc3d may refuse them politely instead.
@pytest.mark.parametrize("offset, value", [(535, 255), (534, 255), (525, 254)])
def test_files_that_crash_or_hang_ezc3d_do_not_take_the_process_down(
    small_c3d, monkeypatch, offset, value
):
    monkeypatch.setattr(c3d_module, "CHILD_TIMEOUT_S", 3.0)
    damaged = bytearray(small_c3d)
    damaged[offset] = value
    with pytest.raises(InputFileError, match="damaged|did not finish|not a readable C3D"):
        read_c3d(bytes(damaged), name="take.c3d", marker="tip")


def test_a_crash_of_the_parser_becomes_an_input_file_error(small_c3d, monkeypatch):
    # Whatever ezc3d's version does with the files above, a segmentation fault is reported.
    monkeypatch.setattr(c3d_module, "_CHILD_TARGET", "tests.drivers.isolation_targets:segfault")
    with pytest.raises(InputFileError, match=r"damaged: it made the C3D reader crash \(SIGSEGV\)"):
        read_c3d(small_c3d, name="take.c3d")


def test_a_hanging_parser_is_stopped(small_c3d, monkeypatch):
    monkeypatch.setattr(c3d_module, "_CHILD_TARGET", "tests.drivers.isolation_targets:hang")
    monkeypatch.setattr(c3d_module, "CHILD_TIMEOUT_S", 1.0)
    with pytest.raises(InputFileError, match="did not finish within 1 s"):
        read_c3d(small_c3d, name="take.c3d")


def test_to_recording_needs_two_valid_samples(tmp_path):
    _, pos = markers(5)
    lost = np.ones((5, 1), bool)
    lost[2] = False
    trace = read_c3d(write_c3d(tmp_path / "r.c3d", ["tip"], pos[:, :1], 100.0, lost=lost))
    with pytest.raises(InputFileError, match="seen in 1 of 5 frames"):
        trace.to_recording()


def _header_frames(content: bytes, first: int, last: int) -> bytes:
    # Words 4 and 5 of the 512-byte header (bytes 6-9, little-endian for Intel files): the
    # first and last frame numbers.
    return content[:6] + struct.pack("<2H", first, last) + content[10:]


def test_a_header_frame_range_that_disagrees_with_point_frames(tmp_path):
    # NDI's Optotrak software writes the take's range (1-1149) in the header of a 29-frame file
    # whose POINT:FRAMES is 29 and whose data section holds 29 frames.
    t, pos = markers(29, 100.0)
    content = write_c3d(tmp_path / "ndi.c3d", ["tip"], pos[:, :1], 100.0).read_bytes()
    assert struct.unpack("<2H", content[6:10]) == (1, 29)
    ndi = _header_frames(content, 1, 1149)
    trace = read_c3d(ndi, name="ndi.c3d")
    assert len(trace) == 29 and trace.batch.valid.all()
    np.testing.assert_allclose(trace.batch.position_m, pos[:, 0], atol=ATOL_M)
    np.testing.assert_allclose(trace.batch.t_s, t, atol=1e-12)
    # Real truncation stays detected: cut mid-frame (20 of the 29 frames, 16 bytes each, and a
    # few bytes of the next), or on a 512-byte block as a buffered copy stops.
    data_start = (struct.unpack("<H", content[16:18])[0] - 1) * 512
    with pytest.raises(
        InputFileError,
        match=r"ndi.c3d is truncated: it declares 29 frames \(POINT:FRAMES; its header says "
        r"1149\) but holds 20",
    ):
        read_c3d(ndi[: data_start + 20 * 16 + 7], name="ndi.c3d")
    with pytest.raises(InputFileError, match="truncated: it declares 29 frames but holds 20"):
        read_c3d(content[: data_start + 20 * 16 + 7], name="ndi.c3d")
    # Ending exactly after a frame, off a block, is how NDI writes a short export: the frames
    # held are read, and the note says what to do if the take was longer.
    short = read_c3d(content[: data_start + 20 * 16], name="ndi.c3d")
    assert len(short) == 20 and "holds 20 complete frames" in short.notes[0]
