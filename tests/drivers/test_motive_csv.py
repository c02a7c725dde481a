"""Motive CSV exports: known trajectories in and out, and every kind of bad file."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from drivers.tracking.motive_csv import read_motive_csv
from tests.drivers.tracking_fixtures import EULER_ORDERS, PEN_MARKERS_M, helix, write_motive_csv

# Motive writes six decimals: 1e-6 of the unit, and quaternion components to 5e-7.
POSITION_ATOL = {"mm": 1e-9, "cm": 1e-8, "m": 1e-6}


def same_rotation(q1, q2):
    """Largest angle (rad) between two sets of orientations (q and -q are the same)."""
    dot = np.abs(np.sum(q1 * q2, axis=1))
    return float(np.max(2 * np.arccos(np.clip(dot, -1.0, 1.0))))


@pytest.fixture
def pen():
    return helix(300, 240.0)


@pytest.mark.parametrize("units", ["mm", "cm", "m"])
@pytest.mark.parametrize("rotation", ["quaternion", *EULER_ORDERS])
def test_round_trip(tmp_path, pen, units, rotation):
    t, p, q = pen
    path = write_motive_csv(tmp_path / "take.csv", t, p, q, units=units, rotation=rotation)
    trace = read_motive_csv(path)
    batch = trace.batch
    np.testing.assert_allclose(batch.t_s, t, atol=5e-7)
    np.testing.assert_allclose(batch.position_m, p, atol=POSITION_ATOL[units])
    # Six decimals of a quaternion or of an angle in degrees: a few microradians.
    assert same_rotation(batch.orientation_xyzw, q) < 1e-5
    np.testing.assert_allclose(np.linalg.norm(batch.orientation_xyzw, axis=1), 1.0, atol=1e-12)
    assert batch.valid.all()
    assert trace.rigid_body == "Pen" and trace.marker is None
    assert trace.rotation_type == ("Quaternion" if rotation == "quaternion" else rotation)
    assert trace.rate_hz == 240.0
    assert trace.length_units == {"mm": "Millimeters", "cm": "Centimeters", "m": "Meters"}[units]
    assert trace.available == ("Pen",)
    assert trace.available_markers == tuple(f"Pen:Marker{k}" for k in range(1, 5))
    np.testing.assert_allclose(trace.mean_marker_error_m, 1e-4, atol=POSITION_ATOL[units])


def test_euler_angles_follow_motives_relative_convention(tmp_path):
    # X 90 degrees, then 90 about the moved Y: the body's z axis ends up along world +x (about
    # the fixed axes it would end along -y).
    t = np.arange(3) / 100.0
    path = write_motive_csv(
        tmp_path / "e.csv", t, np.zeros((3, 3)), np.tile([0, 0, 0, 1.0], (3, 1)), rotation="XYZ"
    )
    text = path.read_bytes().decode()
    assert "Rotation Type,XYZ" in text
    for line in (8, 9, 10):
        text = _set_cell(_set_cell(text, line, 2, "90.000000"), line, 3, "90.000000")
    trace = read_motive_csv(text.encode())
    z_axis = Rotation.from_quat(trace.batch.orientation_xyzw).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(z_axis, np.tile([1.0, 0.0, 0.0], (3, 1)), atol=1e-12)


def test_lost_frames_are_nan_and_not_valid(tmp_path, pen):
    t, p, q = pen
    lost = np.zeros(len(t), bool)
    lost[[0, 50, 51, 52, 299]] = True
    trace = read_motive_csv(write_motive_csv(tmp_path / "l.csv", t, p, q, lost=lost))
    batch = trace.batch
    np.testing.assert_array_equal(batch.valid, ~lost)
    assert np.isnan(batch.position_m[lost]).all() and np.isnan(batch.orientation_xyzw[lost]).all()
    assert np.isnan(trace.mean_marker_error_m[lost]).all()
    np.testing.assert_allclose(batch.position_m[~lost], p[~lost], atol=1e-9)
    rec = trace.to_recording()
    assert len(rec) == len(t) - lost.sum()
    np.testing.assert_allclose(rec.t_s, t[~lost], atol=5e-7)


def test_high_marker_error_rows_are_flagged_but_kept(tmp_path, pen):
    t, p, q = pen
    error = np.full(len(t), 2e-4)
    error[10:20] = 3e-3
    path = write_motive_csv(tmp_path / "q.csv", t, p, q, marker_error_m=error)
    assert read_motive_csv(path).batch.valid.all()
    trace = read_motive_csv(path, max_marker_error_m=1e-3)
    assert not trace.batch.valid[10:20].any() and trace.batch.valid[20:].all()
    np.testing.assert_allclose(trace.batch.position_m[10:20], p[10:20], atol=1e-9)
    np.testing.assert_allclose(trace.mean_marker_error_m[10:20], 3e-3, atol=1e-9)


def test_several_rigid_bodies_picked_by_name(tmp_path, pen):
    t, p, q = pen
    other_q = Rotation.from_rotvec([0.3, 0.0, 0.0]).as_quat()
    pos = np.stack([p + [0.5, 0.0, 0.0], p, p - [0.0, 0.2, 0.0]])
    quat = np.stack([np.tile(other_q, (len(t), 1)), q, q])
    lost = np.zeros((3, len(t)), bool)
    lost[0, :100] = True  # the other bodies' gaps must not leak into the pen's
    path = write_motive_csv(
        tmp_path / "s.csv", t, pos, quat, rigid_bodies=["Workpiece", "Pen", "Probe"], lost=lost
    )
    with pytest.raises(InputFileError, match=r"several rigid bodies \(Workpiece, Pen, Probe\)"):
        read_motive_csv(path)
    trace = read_motive_csv(path, rigid_body="Pen")
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert same_rotation(trace.batch.orientation_xyzw, q) < 1e-5 and trace.batch.valid.all()
    assert trace.available == ("Workpiece", "Pen", "Probe")
    work = read_motive_csv(path, rigid_body="Workpiece")
    assert not work.batch.valid[:100].any() and work.batch.valid[100:].all()
    with pytest.raises(InputFileError, match="no rigid body named 'pen'; it has 'Workpiece'"):
        read_motive_csv(path, rigid_body="pen")


def test_a_marker_instead_of_a_rigid_body(tmp_path, pen):
    t, p, q = pen
    lost = np.zeros(len(t), bool)
    lost[5:9] = True
    path = write_motive_csv(tmp_path / "m.csv", t, p, q, lost=lost)
    trace = read_motive_csv(path, marker="Pen:Marker2")
    expected = p + Rotation.from_quat(q).apply(PEN_MARKERS_M[1])
    np.testing.assert_allclose(trace.batch.position_m[~lost], expected[~lost], atol=1e-8)
    assert trace.batch.orientation_xyzw is None and trace.rotation_type is None
    np.testing.assert_array_equal(trace.batch.valid, ~lost)
    assert trace.marker == "Pen:Marker2" and trace.rigid_body is None
    with pytest.raises(InputFileError, match="no marker named 'Tip'; it has 'Pen:Marker1'"):
        read_motive_csv(path, marker="Tip")
    with pytest.raises(ValueError, match="not both"):
        read_motive_csv(path, marker="Pen:Marker2", rigid_body="Pen")


def test_bytes_and_a_file_without_quality_columns_or_markers(tmp_path, pen):
    t, p, q = pen
    path = write_motive_csv(tmp_path / "b.csv", t, p, q, quality=False, markers_per_body=0)
    trace = read_motive_csv(path.read_bytes(), name="upload.csv")
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert trace.mean_marker_error_m is None and trace.available_markers == ()


def test_a_real_motive_1_23_header_with_quoted_ids_and_lost_rows():
    # The shape of a Motive 2.x export (three rows of it): quoted IDs, trailing empty error cell
    # name, a lost body leaving all its cells empty, metres.
    content = (
        b"Format Version,1.23,Take Name,sept-18,Take Notes,,Capture Frame Rate,100.000000,"
        b"Export Frame Rate,100.000000,Capture Start Time,2019-09-18 04.30.02.695 PM,"
        b"Total Frames in Take,3,Total Exported Frames,3,Rotation Type,Quaternion,"
        b"Length Units,Meters,Coordinate Space,Global\r\n\r\n"
        b",Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,"
        b"Rigid Body\r\n"
        b",Name,device02,device02,device02,device02,device02,device02,device02,device02\r\n"
        b',ID,"9E20","9E20","9E20","9E20","9E20","9E20","9E20","9E20"\r\n'
        b",,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error\r\n"
        b"Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,\r\n"
        b"72210,722.1,0.134648,-0.97705,-0.111668,0.121543,0.142319,0.160392,2.000101,0.000113\r\n"
        b"72211,722.11,,,,,,,,\r\n"
        b"72212,722.12,0.210628,-0.972549,-0.093882,0.031141,0.124554,0.166018,1.945209,0.000115"
    )
    trace = read_motive_csv(content)
    np.testing.assert_allclose(trace.batch.t_s, [722.1, 722.11, 722.12])
    np.testing.assert_array_equal(trace.batch.valid, [True, False, True])
    np.testing.assert_allclose(trace.batch.position_m[2], [0.124554, 0.166018, 1.945209])
    assert trace.take_name == "sept-18" and trace.rigid_body == "device02"
    np.testing.assert_allclose(trace.mean_marker_error_m[[0, 2]], [0.000113, 0.000115])


def test_units_argument_only_fills_a_missing_declaration(tmp_path, pen):
    t, p, q = pen
    path = write_motive_csv(tmp_path / "u.csv", t, p, q, units="mm")
    # The header says Millimeters: the argument does not override it.
    np.testing.assert_allclose(read_motive_csv(path, units="m").batch.position_m, p, atol=1e-9)
    no_units = path.read_bytes().decode().replace(",Length Units,Millimeters", "")
    with pytest.raises(InputFileError, match="does not say its length unit.*units='mm'"):
        read_motive_csv(no_units.encode())
    trace = read_motive_csv(no_units.encode(), units="mm")
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert trace.length_units == "mm"
    with pytest.raises(ValueError, match="unknown length unit"):
        read_motive_csv(path, units="inch")


def _text(tmp_path, **options):
    t, p, q = helix(20, 100.0)
    return write_motive_csv(tmp_path / "x.csv", t, p, q, **options).read_bytes().decode()


def _lines(text):
    return text.split("\r\n")


BODY = 7  # index of the first data row among the lines of a written file


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: "", "is empty"),
        (lambda s: "\r\n\r\n  \r\n", "is empty"),
        (lambda s: "x,y,z\n1,2,3\n", "not a Motive CSV export.*'Format Version'"),
        # What Motive writes with "Header information" unchecked.
        (lambda s: "\r\n".join(_lines(s)[BODY:]), "no header.*'Header information' checked"),
        (lambda s: "\r\n".join(_lines(s)[:2]), "no 'Frame,Time.*'Header information'"),
        (lambda s: s.rstrip()[:-30], r"truncated: its last row \(line 27\) has 3\d of 38 cells"),
        (lambda s: "\r\n".join(_lines(s)[:20]), "truncated: its header promises 20 frames but"),
        (
            lambda s: s.replace("Length Units,Millimeters", "Length Units,Inches"),
            "unknown length unit 'Inches'",
        ),
        (
            lambda s: s.replace("Rotation Type,Quaternion", "Rotation Type,Matrix"),
            "unknown rotation type 'Matrix'",
        ),
        (lambda s: _set_cell(s, 12, 6, "nan"), r"line 12, column 7 \(Pen Position X\).*'nan'"),
        (lambda s: _set_cell(s, 9, 2, "inf"), "line 9, column 3 .*NaN or infinite"),
        (lambda s: _set_cell(s, 9, 7, "12,5"), "line 9 has 39 cells where line 8 has 38"),
        (lambda s: _set_cell(s, 10, 3, "0.1.2"), "line 10, column 4 .*'0.1.2' is not a number"),
        (lambda s: _set_cell(s, 10, 3, "-"), "line 10, column 4 .*'-' is not a number"),
        (lambda s: _set_cell(s, 11, 1, "0.4x"), r"line 11, column Time \(Seconds\).*not a number"),
        (lambda s: _set_cell(s, 11, 1, ""), "line 11 has no time"),
        (lambda s: _set_cell(s, 15, 1, "0.05"), r"do not increase \(line 15\)"),
        (lambda s: _drop_column(s, 8), "no Position Z column for rigid body 'Pen'"),
        (lambda s: _drop_column(s, 5), "no 'Rotation W' column .*rotation type is Quaternion"),
        (
            lambda s: _edit_line(s, 3, lambda c: "" if c == "Rigid Body" else c),
            r"no rigid body and 4 markers \(Pen:Marker1, Pen:Marker2",
        ),
        (
            lambda s: _edit_line(s, 3, lambda c: "Bone" if c == "Rigid Body" else c),
            r"holds a skeleton and no rigid body.*bones 'Pen'; markers 'Pen:Marker1', 'Pen:Mar",
        ),
        (lambda s: _edit_line(s, 4, lambda c: "Species" if c == "Name" else c), "rows Name"),
        (
            lambda s: "\r\n".join(_lines(s)[: BODY + 1]).replace("Total Exported Frames,20,", ""),
            "1 data rows; a trace needs at least two",
        ),
    ],
)
def test_bad_files_are_refused_with_a_reason(tmp_path, edit, message):
    with pytest.raises(InputFileError, match=message):
        read_motive_csv(edit(_text(tmp_path)).encode(), name="take.csv")


def _set_cell(text, line, column, value):
    return _edit_line(text, line, lambda cell: cell, {column: value})


def _edit_line(text, line, change, cells_at=None):
    lines = _lines(text)
    cells = [change(cell) for cell in lines[line - 1].split(",")]
    for column, value in (cells_at or {}).items():
        cells[column] = value
    lines[line - 1] = ",".join(cells)
    return "\r\n".join(lines)


def _drop_column(text, column):
    lines = _lines(text)
    for i in range(2, len(lines)):
        if lines[i]:
            cells = lines[i].split(",")
            del cells[column]
            lines[i] = ",".join(cells)
    return "\r\n".join(lines)


def test_motive_3_parent_row_and_trailing_empty_columns(tmp_path):
    t, p, q = helix(20, 100.0)
    lines = _lines(write_motive_csv(tmp_path / "3.csv", t, p, q).read_bytes().decode())
    # Motive 3 adds a Parent row; some exports pad every row with empty cells.
    lines.insert(5, ",Parent," + ",".join(["Root"] * 36))
    padded = [line + ",,,," if i >= 2 and line else line for i, line in enumerate(lines)]
    trace = read_motive_csv("\r\n".join(padded).encode())
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert same_rotation(trace.batch.orientation_xyzw, q) < 1e-5


def test_duplicate_rigid_body_names_are_refused(tmp_path):
    t, p, q = helix(10, 100.0)
    path = write_motive_csv(
        tmp_path / "d.csv", t, np.stack([p, p]), np.stack([q, q]), rigid_bodies=["Pen", "Pen"]
    )
    with pytest.raises(InputFileError, match="two 'Rotation X' columns for 'Pen'"):
        read_motive_csv(path)


def test_zero_quaternion_and_binary_and_missing_files(tmp_path):
    text = _text(tmp_path)
    zero = _set_cell(_set_cell(text, 10, 5, "0.0"), 10, 2, "0.0")
    zero = _set_cell(_set_cell(zero, 10, 3, "0.0"), 10, 4, "0.0")
    with pytest.raises(InputFileError, match="line 10 has a zero quaternion"):
        read_motive_csv(zero.encode())
    with pytest.raises(InputFileError, match="binary"):
        read_motive_csv(b"\x00\x01\x02PK")
    with pytest.raises(InputFileError, match="does not exist"):
        read_motive_csv(tmp_path / "nope.csv")
    with pytest.raises(InputFileError, match="directory"):
        read_motive_csv(tmp_path)
    with pytest.raises(ValueError, match="max_marker_error_m"):
        read_motive_csv(text.encode(), max_marker_error_m=-1.0)


def test_to_recording_needs_two_valid_samples(tmp_path):
    t, p, q = helix(5, 100.0)
    lost = np.array([True, True, True, True, False])
    trace = read_motive_csv(write_motive_csv(tmp_path / "r.csv", t, p, q, lost=lost))
    with pytest.raises(InputFileError, match="tracked in 1 of 5 frames"):
        trace.to_recording()


# --- real exports that were refused or misread (issue "Robustness", point 7) -----------------


@pytest.mark.parametrize("version", ["1.21", "1.22"])
@pytest.mark.parametrize("units, rotation", [("m", "quaternion"), ("mm", "XYZ"), ("cm", "ZYX")])
def test_motive_1x_exports_without_row_labels_are_read(tmp_path, pen, version, units, rotation):
    t, p, q = pen
    error = np.linspace(1e-4, 3e-4, len(t))
    path = write_motive_csv(
        tmp_path / "take.csv",
        t,
        p,
        q,
        units=units,
        rotation=rotation,
        format_version=version,
        marker_error_m=error,
    )
    lines = _lines(path.read_bytes().decode())
    # The layout of Motive 1.x: no Type/Name/ID labels, "Time", the 1.x quality columns.
    assert lines[0].startswith(f"Format Version,{version},")
    assert lines[2].startswith(",,Rigid Body,Rigid Body,") and lines[3].startswith(",,Pen,Pen,")
    assert lines[4].startswith(",,1,1,")
    assert "Error Per Marker" in lines[5] and "Marker Quality" in lines[5]
    assert lines[6].startswith("Frame,Time,X,Y,Z,")
    trace = read_motive_csv(path)
    np.testing.assert_allclose(trace.batch.t_s, t, atol=5e-7)
    np.testing.assert_allclose(trace.batch.position_m, p, atol=POSITION_ATOL[units])
    assert same_rotation(trace.batch.orientation_xyzw, q) < 1e-5
    assert trace.rigid_body == "Pen" and trace.available_markers[0] == "Pen:Marker1"
    assert trace.rotation_type == ("Quaternion" if rotation == "quaternion" else rotation)
    assert trace.length_units == {"mm": "Millimeters", "cm": "Centimeters", "m": "Meters"}[units]
    np.testing.assert_allclose(trace.mean_marker_error_m, error, atol=POSITION_ATOL[units])
    marker = read_motive_csv(path, marker="Pen:Marker2")
    expected = p + Rotation.from_quat(q).apply(PEN_MARKERS_M[1])
    np.testing.assert_allclose(marker.batch.position_m, expected, atol=1e-5)


def test_a_motive_1_21_export_as_written():
    # Byte for byte the shape of a Motive 1.9 export with quality statistics: no row labels,
    # "Time", "Error Per Marker" after the body and "Marker Quality" after its marker.
    content = (
        b"Format Version,1.21,Take Name,Take 2016-03-02 02.12.36 PM,Capture Frame Rate,"
        b"120.000000,Export Frame Rate,120.000000,Capture Start Time,2016-03-02 02.12.36 PM,"
        b"Total Frames in Take,3,Total Exported Frames,3,Rotation Type,Quaternion,"
        b"Length Units,Meters,Coordinate Space,Global\r\n\r\n"
        b",,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,"
        b"Rigid Body,Rigid Body Marker,Rigid Body Marker,Rigid Body Marker,Rigid Body Marker\r\n"
        b",,Pen,Pen,Pen,Pen,Pen,Pen,Pen,Pen,Pen:Marker1,Pen:Marker1,Pen:Marker1,Pen:Marker1\r\n"
        b",,1,1,1,1,1,1,1,1,1,1,1,1\r\n"
        b",,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Error Per Marker,"
        b"Position,Position,Position,Marker Quality\r\n"
        b"Frame,Time,X,Y,Z,W,X,Y,Z,,X,Y,Z,\r\n"
        b"0,0.000000,0.000000,0.000000,0.000000,1.000000,0.412000,0.087000,-0.153000,0.000210,"
        b"0.412000,0.087000,-0.033000,1.000000\r\n"
        b"1,0.008333,,,,,,,,,,,,\r\n"
        b"2,0.016667,0.000000,0.707107,0.000000,0.707107,0.416000,0.087500,-0.151000,0.000190,"
        b"0.536000,0.087500,-0.151000,0.990000\r\n"
    )
    trace = read_motive_csv(content, name="take.csv")
    np.testing.assert_allclose(trace.batch.t_s, [0.0, 0.008333, 0.016667])
    np.testing.assert_array_equal(trace.batch.valid, [True, False, True])
    np.testing.assert_allclose(
        trace.batch.position_m[[0, 2]], [[0.412, 0.087, -0.153], [0.416, 0.0875, -0.151]]
    )
    np.testing.assert_allclose(
        trace.batch.orientation_xyzw[2], [0, np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-6
    )
    np.testing.assert_allclose(trace.mean_marker_error_m[[0, 2]], [0.00021, 0.00019])
    assert trace.rate_hz == 120.0 and trace.length_units == "Meters"
    # A lost frame's empty time column would be named as the file names it.
    with pytest.raises(InputFileError, match="line 9 has no time; every row needs its Time$"):
        read_motive_csv(content.replace(b"1,0.008333,", b"1,,"), name="take.csv")


def _spreadsheet_resave(text, drop=()):
    """What a spreadsheet writes back: numbers as it shows them (120 for 120.000000), every row
    padded with commas to the widest, blank rows as commas only (two at the end)."""
    for key in drop:
        text = re.sub(rf",{key},[^,\r\n]*", "", text)
    rows = [
        [
            re.sub(r"^(-?\d+)\.(\d*?)0+$", lambda m: m[1] + ("." + m[2] if m[2] else ""), c)
            for c in line.split(",")
        ]
        for line in _lines(text.rstrip("\r\n")) + ["", ""]
    ]
    width = max(len(row) for row in rows)
    return "\r\n".join(",".join(row + [""] * (width - len(row))) for row in rows) + "\r\n"


def test_a_spreadsheet_resave_is_read(tmp_path, pen):
    t, p, q = pen
    text = write_motive_csv(tmp_path / "s.csv", t, p, q).read_bytes().decode()
    resaved = _spreadsheet_resave(text)
    lines = _lines(resaved)
    assert ",Export Frame Rate,240," in lines[0] and set(lines[1]) == {","}
    assert lines[-2] and set(lines[-2]) == {","} and lines[7].startswith("0,0,")
    trace = read_motive_csv(resaved.encode(), name="s.csv")
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert same_rotation(trace.batch.orientation_xyzw, q) < 1e-5 and trace.rate_hz == 240.0
    assert len(trace) == len(t)


def test_a_spreadsheet_resave_without_units_or_rotation_type_says_what_is_missing(tmp_path, pen):
    t, p, q = pen
    text = write_motive_csv(tmp_path / "s.csv", t, p, q).read_bytes().decode()
    resaved = _spreadsheet_resave(text, drop=("Rotation Type", "Length Units")).encode()
    with pytest.raises(InputFileError) as error:
        read_motive_csv(resaved, name="s.csv")
    message = str(error.value)
    assert "no 'Length Units' in its first row" in message
    assert "--units mm (or m) on the command line, units='mm' (or 'm') in an upload" in message
    assert "'Rotation Type' is missing too" in message and "quaternions" in message
    # Given the unit, the quaternions are read as such: their W column says what they are.
    trace = read_motive_csv(resaved, name="s.csv", units="mm")
    np.testing.assert_allclose(trace.batch.position_m, p, atol=1e-9)
    assert (
        trace.rotation_type == "Quaternion"
        and same_rotation(trace.batch.orientation_xyzw, q) < 1e-5
    )
    # Euler angles of an unknown order cannot be read, and no option gives the order.
    euler = write_motive_csv(tmp_path / "e.csv", t, p, q, rotation="ZXY").read_bytes().decode()
    resaved = _spreadsheet_resave(euler, drop=("Rotation Type",)).encode()
    with pytest.raises(
        InputFileError,
        match=r"no 'Rotation Type' in its first row\), and the rotation columns of 'Pen' "
        r"\(X, Y, Z, no W\) are Euler angles of an unknown order; no option supplies it",
    ):
        read_motive_csv(resaved, name="e.csv")


NO_ASSET_HEADER = (
    b"Format Version,1.23,Take Name,empty,Take Notes,,Capture Frame Rate,120.000000,"
    b"Export Frame Rate,120.000000,Capture Start Time,2024-05-14 10.21.07.512 AM,"
    b"Capture Start Frame,0,Total Frames in Take,3,Total Exported Frames,3,"
    b"Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global\r\n\r\n"
)


@pytest.mark.parametrize(
    "rows", [b",Type\r\n,Name\r\n,ID\r\n,\r\n", b""], ids=["empty-rows", "no-rows"]
)
def test_an_export_without_assets_says_so(rows):
    content = NO_ASSET_HEADER + rows + b"Frame,Time (Seconds)\r\n0,0.000000\r\n1,0.008333\r\n"
    with pytest.raises(InputFileError) as error:
        read_motive_csv(content, name="take.csv")
    message = str(error.value)
    assert "holds no rigid body or marker: its only columns are Frame and Time" in message
    assert "the take exported no assets" in message and "'Rigid Bodies'" in message
    assert "Header information" not in message


def _skeleton_export(n_bones=3, n=60):
    """A Motive 3 export of a skeleton only: Bone and Bone Marker columns, a Parent row; each
    bone's position is a known helix shifted by its index."""
    t, p, q = helix(n, 120.0)
    bones = ["Skel:Hip", "Skel:Ab", "Skel:Chest"] + [f"Skel:Bone{k}" for k in range(3, n_bones)]
    bones = bones[:n_bones]
    markers = ["Skel:WaistLFront", "Skel:WaistRFront", "Skel:BackTop"]
    types, names, parents, kinds, axes, columns = [], [], [], [], [], []
    for b, bone in enumerate(bones):
        for kind, axis, values in [("Rotation", a, q[:, i] * 1.0) for i, a in enumerate("XYZW")] + [
            ("Position", a, (p[:, i] + 0.1 * b) * 1e3) for i, a in enumerate("XYZ")
        ]:
            types.append("Bone"), names.append(bone), parents.append("Skel:Hip" if b else "")
            kinds.append(kind), axes.append(axis), columns.append(values)
    for k, marker in enumerate(markers):
        for i, axis in enumerate("XYZ"):
            types.append("Bone Marker"), names.append(marker), parents.append("Skel:Hip")
            kinds.append("Position"), axes.append(axis), columns.append((p[:, i] - 0.01 * k) * 1e3)
    data = np.column_stack(columns)
    lines = [
        "Format Version,1.24,Take Name,walk,Take Notes,,Capture Frame Rate,120.000000,Export "
        "Frame Rate,120.000000,Capture Start Time,2024-05-14 10.21.07.512 AM,Capture Start "
        f"Frame,0,Total Frames in Take,{n},Total Exported Frames,{n},Rotation Type,Quaternion,"
        "Length Units,Millimeters,Coordinate Space,Global",
        "",
        ",Type," + ",".join(types),
        ",Name," + ",".join(names),
        ",ID," + ",".join(["1"] * len(types)),
        ",Parent," + ",".join(parents),
        ",," + ",".join(kinds),
        "Frame,Time (Seconds)," + ",".join(axes),
    ]
    lines += [f"{i},{t[i]:.6f}," + ",".join(f"{v:.6f}" for v in data[i]) for i in range(n)]
    return ("\r\n".join(lines) + "\r\n").encode(), t, p, q


def test_a_skeleton_only_export_lists_bones_and_markers_and_a_bone_can_be_read():
    content, _t, p, q = _skeleton_export()
    with pytest.raises(InputFileError) as error:
        read_motive_csv(content, name="walk.csv")
    message = str(error.value)
    assert "walk.csv holds a skeleton (Skel) and no rigid body" in message
    assert "(rigid_body=... or --rigid-body)" in message and "(marker=... or --marker)" in message
    assert "bones 'Skel:Hip', 'Skel:Ab', 'Skel:Chest'" in message
    assert "markers 'Skel:WaistLFront', 'Skel:WaistRFront', 'Skel:BackTop'" in message
    bone = read_motive_csv(content, rigid_body="Skel:Ab")
    np.testing.assert_allclose(bone.batch.position_m, p + 0.1, atol=1e-9)
    assert same_rotation(bone.batch.orientation_xyzw, q) < 1e-5 and bone.rigid_body == "Skel:Ab"
    marker = read_motive_csv(content, marker="Skel:BackTop")
    np.testing.assert_allclose(marker.batch.position_m, p - 0.02, atol=1e-9)
    with pytest.raises(InputFileError, match="no rigid body named 'Pen'; it has none; bones 'Skel"):
        read_motive_csv(content, rigid_body="Pen")
    # A full skeleton has dozens of bones: the message names a few and counts the rest.
    many, *_ = _skeleton_export(n_bones=21, n=5)
    with pytest.raises(InputFileError, match=r"'Skel:Bone7' … and 13 more; markers") as error:
        read_motive_csv(many, name="walk.csv")
    assert len(str(error.value)) < 600


LEGACY_1_1 = (
    b"comment,Tracking Tools 2.3.2 Exported Data\r\n"
    b"info,version,1.1\r\n"
    b"info,framecount,2\r\n"
    b"info,rigidbodycount,1\r\n"
    b"rigidbody,Pen,1,3,0.000000,0.000000,0.120000,0.030000,0.000000,0.100000,-0.020000,"
    b"0.025000,0.090000\r\n"
    b"righthanded\r\n"
    b"frame,0,0.000000,1,1,0.412000,0.087000,-0.153000,0.000000,0.000000,0.000000,1.000000,"
    b"0.000000,0.000000,0.000000,1,0.412000,0.087000,-0.033000,1,Pen-1\r\n"
    b"frame,1,0.008333,1,1,0.413000,0.087000,-0.153000,0.000000,0.000000,0.000000,1.000000,"
    b"0.000000,0.000000,0.000000,0\r\n"
)
TRACKABLE_EXPORT = (
    b"comment,Trackable Export Data\r\n"
    b"info,framecount,2\r\n"
    b"info,trackablecount,1\r\n"
    b"trackable,Pen,1,3,0.000000,0.000000,0.120000,0.030000,0.000000,0.100000,-0.020000,"
    b"0.025000,0.090000\r\n"
    b"frame,0,0.000000,1,1,0.412000,0.087000,-0.153000,0.000000,0.000000,0.000000,1.000000,"
    b"0.000000,0.000000,0.000000,0\r\n"
)


@pytest.mark.parametrize(
    "content, what",
    [(LEGACY_1_1, "format 1.1"), (TRACKABLE_EXPORT, "'comment', 'info' and 'frame' rows")],
    ids=["format-1.1", "trackable-export"],
)
def test_legacy_optitrack_csv_is_named_with_what_to_export_instead(content, what):
    with pytest.raises(InputFileError) as error:
        read_motive_csv(content, name="take.csv")
    message = str(error.value)
    assert f"take.csv is a legacy OptiTrack CSV (Tracking Tools or early Motive, {what})" in message
    assert "export the take from Motive as CSV with 'Header information' checked" in message
    assert "canonical t,x,y,z,qx,qy,qz,qw CSV" in message


def test_several_rigid_bodies_are_listed_in_part(tmp_path):
    t, p, q = helix(5, 100.0)
    bodies = [f"Body {k}" for k in range(12)]
    path = write_motive_csv(
        tmp_path / "m.csv",
        t,
        np.stack([p] * 12),
        np.stack([q] * 12),
        rigid_bodies=bodies,
        markers_per_body=0,
    )
    with pytest.raises(
        InputFileError, match=r"several rigid bodies \(Body 0, .*Body 7 … and 4 more\); say"
    ):
        read_motive_csv(path)
