"""Trace and scan readers: round trips, units, and every kind of bad file."""

import numpy as np
import pytest

from drivers.errors import InputFileError, UnknownFormatError
from drivers.files import atomic_path
from drivers.scanning.pointcloud import read_scan, write_scan
from drivers.tracking.canonical_csv import read_trace_csv, write_trace_csv
from recon.inputs import Recording, Scan


def test_trace_round_trip_with_times_and_orientations(tmp_path):
    rng = np.random.default_rng(0)
    q = rng.standard_normal((20, 4))
    rec = Recording(
        points_m=rng.uniform(-1, 1, (20, 3)),
        t_s=np.arange(20) * 0.004,
        orientations_xyzw=q / np.linalg.norm(q, axis=1)[:, None],
    )
    write_trace_csv(tmp_path / "t.csv", rec)
    back = read_trace_csv(tmp_path / "t.csv")
    np.testing.assert_allclose(back.points_m, rec.points_m, atol=1e-8)
    np.testing.assert_allclose(back.t_s, rec.t_s, atol=1e-9)
    np.testing.assert_allclose(back.orientations_xyzw, rec.orientations_xyzw, atol=1e-8)


def test_trace_in_millimetres_any_column_order_and_bytes():
    data = b"z,y,x\n1,2,3\n4,5,6\n"
    rec = read_trace_csv(data, units="mm")
    np.testing.assert_allclose(rec.points_m, [[0.003, 0.002, 0.001], [0.006, 0.005, 0.004]])
    assert rec.t_s is None and rec.orientations_xyzw is None


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"a,b,c\n1,2,3\n4,5,6\n", "no column x, y, z"),
        (b"x,y,z\n1,2,3\n", "at least two"),
        (b"x,y,z\n1,2,3\n4,5\n", "line 3 has 2 cells"),
        (b"x,y,z\n1,2,3\n4,five,6\n", "not a number"),
        (b"x,y,z\n1,2,3\nnan,5,6\n", "NaN or infinite"),
        (b"x,y,z\n1,2,3\ninf,5,6\n", "NaN or infinite"),
        (b"t,x,y,z\n0,1,2,3\n0,4,5,6\n", "do not increase"),
        (b"x,y,z,qx,qy,qz,qw\n1,2,3,0,0,0,0\n4,5,6,0,0,0,1\n", "zero quaternion"),
        (b"\xff\xfe\x00x", "not a text"),
    ],
)
def test_bad_trace_files_are_refused_with_a_reason(content, message):
    with pytest.raises(InputFileError, match=message):
        read_trace_csv(content)


def test_missing_trace_file(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_trace_csv(tmp_path / "nope.csv")
    with pytest.raises(InputFileError, match="directory"):
        read_trace_csv(tmp_path)


def test_unknown_unit():
    with pytest.raises(ValueError, match="unknown length unit"):
        read_trace_csv(b"x,y,z\n1,2,3\n4,5,6\n", units="inch")


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_scan_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(1)
    scan = Scan(points_m=rng.uniform(-1, 1, (500, 3)))
    write_scan(tmp_path / f"s{suffix}", scan)
    back = read_scan(tmp_path / f"s{suffix}")
    np.testing.assert_allclose(back.scan.points_m, scan.points_m, atol=1e-6)
    assert back.n_dropped == 0


def test_scan_upload_bytes_in_millimetres(tmp_path):
    write_scan(tmp_path / "s.ply", Scan(points_m=np.eye(3)))
    back = read_scan((tmp_path / "s.ply").read_bytes(), name="upload.ply", units="mm")
    np.testing.assert_allclose(back.scan.points_m, np.eye(3) * 1e-3)


def test_non_finite_scan_points_are_dropped_and_counted(tmp_path):
    (tmp_path / "s.xyz").write_text("0 0 0\nnan nan nan\n1 1 1\n")
    back = read_scan(tmp_path / "s.xyz")
    assert len(back.scan) == 2 and back.n_dropped == 1


PLY_HEADER = (
    b"ply\nformat ascii 1.0\nelement vertex 10\n"
    b"property float x\nproperty float y\nproperty float z\nend_header\n"
)


@pytest.mark.parametrize(
    "name, content, error, message",
    [
        ("s.ply", b"garbage", InputFileError, "not a PLY"),
        ("s.ply", PLY_HEADER + b"1 2 3\n", InputFileError, "could not be read|truncated"),
        ("s.pcd", b"garbage", InputFileError, "not a PCD"),
        (
            "s.pcd",
            b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 5\n"
            b"HEIGHT 1\nPOINTS 5\nDATA ascii\n1 2 3\n",
            InputFileError,
            "truncated",
        ),
        ("s.xyz", b"", InputFileError, "empty"),
        ("s.xyz", bytes(range(256)), InputFileError, "binary"),
        ("s.xyz", b"nan nan nan\n", InputFileError, "no point with finite"),
        ("s.obj", b"v 1 2 3\n", UnknownFormatError, "cannot tell the scan format"),
    ],
)
def test_bad_scan_files_are_refused_with_a_reason(tmp_path, capfd, name, content, error, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(error, match=message):
        read_scan(tmp_path / name)
    # Nothing of Open3D's own complaints reaches the terminal.
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_missing_scan_file(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_scan(tmp_path / "nope.ply")


def test_explicit_format_overrides_the_suffix(tmp_path):
    (tmp_path / "scan.txt").write_text("0 0 0\n1 1 1\n")
    assert len(read_scan(tmp_path / "scan.txt", fmt="xyz").scan) == 2
    with pytest.raises(UnknownFormatError):
        read_scan(tmp_path / "scan.txt", fmt="stl")


def test_atomic_path_leaves_the_old_file_when_writing_fails(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer failed")
    assert target.read_text() == "old"
    assert list(tmp_path.iterdir()) == [target]
    with atomic_path(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"


# --- the registry: every trace format through read_trace ---------------------------------------


def test_read_trace_tells_motive_from_canonical_csv_and_cleans_lost_frames(tmp_path):
    from drivers.tracking.readers import read_trace
    from tests.drivers.tracking_fixtures import helix, write_motive_csv

    t, position, quat = helix(960)
    lost = np.zeros(len(t), bool)
    lost[300:310] = True  # 42 ms: bridged
    write_motive_csv(
        tmp_path / "take.csv",
        t,
        np.stack([position, position + 0.5]),
        np.stack([quat, quat]),
        rigid_bodies=["pen", "table"],
        lost=np.stack([lost, np.zeros_like(lost)]),
    )
    trace = read_trace(tmp_path / "take.csv", rigid_body="pen")
    assert trace.format == "motive" and trace.raw.meta["rigid_body"] == "pen"
    assert trace.raw.rate_hz == pytest.approx(240.0)
    assert len(trace.recording) == len(t) and trace.clean.report.n_bridged == 10
    # mm in the file, metres out; the bridged frames close to the truth (a smooth helix).
    assert np.abs(trace.recording.points_m - position).max() < 1e-3
    with pytest.raises(InputFileError, match="pen.*table|table.*pen"):
        read_trace(tmp_path / "take.csv")  # two rigid bodies: which one?
    with pytest.raises(ValueError, match="Motive CSV exports only"):
        read_trace(tmp_path / "take.csv", fmt="csv", rigid_body="pen")


def test_headerless_motive_exports_get_the_motive_readers_advice(tmp_path):
    from drivers.tracking.readers import read_trace
    from tests.drivers.tracking_fixtures import helix, write_motive_csv

    t, position, quat = helix(50)
    full = write_motive_csv(tmp_path / "full.csv", t, position, quat).read_text()
    lines = full.split("\n")
    bare = write_motive_csv(tmp_path / "bare.csv", t, position, quat, header=False).read_bytes()
    from_type_row = "\n".join(lines[2:]).encode()  # the metadata line cut off: ",Type,..."
    for content in (bare, from_type_row):
        with pytest.raises(InputFileError, match="'Header information'"):
            read_trace(content, name="take.csv")
    # Bare numbers that fit a canonical row still get the canonical reader's advice.
    with pytest.raises(InputFileError, match="must name the columns"):
        read_trace(b"0,0.1,0.2,0.3\n1,0.2,0.2,0.3\n", name="trace.csv")


def test_read_trace_reads_a_c3d_marker(tmp_path):
    from drivers.tracking.readers import read_trace
    from tests.drivers.tracking_fixtures import helix, write_c3d

    _t, position, _ = helix(480)
    markers = np.stack([position, position + 0.1], axis=1)
    write_c3d(tmp_path / "take.c3d", ["tip", "tail"], markers, 240.0)
    trace = read_trace(tmp_path / "take.c3d", marker="tip")
    assert trace.format == "c3d" and trace.recording.orientations_xyzw is None
    np.testing.assert_allclose(trace.recording.points_m, position, atol=1e-6)
    with pytest.raises(InputFileError, match="tip"):
        read_trace(tmp_path / "take.c3d")  # two markers: which one?


# --- exports that were refused or misreported, and a pen that did not move --------------------


def _still_pen(n=2400, extent_m=4e-5, seed=3):
    """A rigid body that never moved: samples jittering in a box whose diagonal is extent_m."""
    rng = np.random.default_rng(seed)
    jitter = rng.uniform(-1.0, 1.0, (n, 3))
    jitter -= jitter.min(axis=0)
    jitter *= extent_m / np.linalg.norm(np.ptp(jitter, axis=0))
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    return np.arange(n) / 240.0, np.array([0.41, 0.12, 0.05]) + jitter, quat


def test_a_still_pen_is_refused_from_a_file_and_from_a_capture(tmp_path):
    from drivers.tracking.readers import MIN_TRACE_EXTENT_M, RawTrace, read_trace, trace_from_raw
    from tests.drivers.tracking_fixtures import write_motive_csv

    t, position, quat = _still_pen()
    path = write_motive_csv(tmp_path / "still.csv", t, position, quat)
    message = r"the pen did not move \(extent 0\.04 mm\); record a trace .* at least 3 mm"
    with pytest.raises(InputFileError, match=message):
        read_trace(path)
    from drivers.tracking.base import SampleBatch

    batch = SampleBatch(t, position, quat, np.ones(len(t), dtype=bool))
    for piece in (None, "all"):
        with pytest.raises(InputFileError, match=message):
            trace_from_raw(RawTrace(batch, "capture"), piece=piece)
    # Just above the threshold it is a (short) trace.
    stroke = SampleBatch(
        t,
        np.outer(np.linspace(0, 1.2 * MIN_TRACE_EXTENT_M, len(t)), [1.0, 0, 0]),
        quat,
        batch.valid,
    )
    assert len(trace_from_raw(RawTrace(stroke, "capture")).recording) == len(t)
    assert 2e-3 < MIN_TRACE_EXTENT_M < 1e-2


def test_exports_of_other_layouts_reach_their_reader_through_the_suffix(tmp_path):
    from drivers.tracking.readers import read_trace
    from tests.drivers.tracking_fixtures import helix, write_motive_csv

    t, position, quat = helix(240)
    old = write_motive_csv(tmp_path / "v121.csv", t, position, quat, format_version="1.21")
    trace = read_trace(old)
    assert trace.format == "motive" and trace.raw.meta["rigid_body"] == "Pen"
    np.testing.assert_allclose(trace.recording.points_m, position, atol=1e-9)
    legacy = b"comment,Tracking Tools 2.3.2 Exported Data\r\ninfo,version,1.1\r\n"
    legacy += b"frame,0,0.000000,0,0\r\nframe,1,0.008333,0,0\r\n"
    with pytest.raises(InputFileError, match=r"legacy OptiTrack CSV .*format 1\.1"):
        read_trace(legacy, name="old.csv")


def test_a_long_header_is_quoted_in_part():
    from drivers.tracking.readers import read_trace

    names = [f"channel_{k}" for k in range(300)]
    content = (",".join(names) + "\n" + ",".join(["0"] * 300) + "\n").encode()
    with pytest.raises(InputFileError) as error:
        read_trace(content, name="log.csv")
    message = str(error.value)
    assert "in its header ('channel_0', 'channel_1'" in message
    assert "'channel_7' … and 292 more)" in message and len(message) < 300


def test_a_csv_with_200k_columns_is_refused_at_once_naming_the_limit():
    """The quadratic column lookup held a parse slot for 300 s on this file (2.7 MB)."""
    import time

    from drivers.tracking.canonical_csv import MAX_COLUMNS

    header = ",".join(["x", "y", "z"] + [f"c{i}" for i in range(200_000)])
    row = ",".join(["0.1"] * 200_003)
    content = f"{header}\n{row}\n{row}\n".encode()
    start = time.process_time()
    with pytest.raises(
        InputFileError, match=f"200003 columns; a trace file has at most {MAX_COLUMNS}"
    ):
        read_trace_csv(content)
    print(f"refused in {time.process_time() - start:.2f} s of CPU")


def test_many_extra_columns_within_the_limit_are_read_and_the_first_of_a_repeated_name_wins():
    header = ",".join(["x", "y", "z", "t", "x"] + [f"extra{i}" for i in range(200)])
    rows = [",".join(["1", "2", "3", str(i), "9"] + ["0"] * 200) for i in range(3)]
    recording = read_trace_csv(("\n".join([header, *rows]) + "\n").encode(), units="m")
    assert recording.points_m.tolist() == [[1.0, 2.0, 3.0]] * 3
    assert recording.t_s.tolist() == [0.0, 1.0, 2.0]
