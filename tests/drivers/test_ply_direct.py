"""Binary PLY vertices read straight into numpy, checked against Open3D's reader.

The direct path (:func:`drivers.scanning.pointcloud._binary_ply_vertices`) replaced Open3D for the
common case: it spares the command the 0.9 s Open3D import and reads faster; every layout
it takes must give what Open3D gives, and every layout it does not take must still be read (by
Open3D) or refused with a reason.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import InputFileError
from drivers.scanning import pointcloud
from drivers.scanning.pointcloud import read_scan

RNG = np.random.default_rng(7)
POINTS = RNG.normal(scale=0.2, size=(500, 3))
NORMALS = RNG.normal(size=(500, 3))
NORMALS /= np.linalg.norm(NORMALS, axis=1, keepdims=True)


def _ply(fmt: str, elements: list[tuple[str, int, list[tuple[str, str]], bytes]]) -> bytes:
    """A PLY file: header from (name, count, [(property, type)], body bytes) per element."""
    head = [b"ply", f"format {fmt} 1.0".encode(), b"comment written by the test"]
    for name, count, props, _ in elements:
        head.append(f"element {name} {count}".encode())
        head += [f"property {kind} {prop}".encode() for prop, kind in props]
    head.append(b"end_header")
    return b"\n".join(head) + b"\n" + b"".join(body for *_, body in elements)


def _vertex_body(fmt: str, props: list[tuple[str, str]], columns: dict[str, np.ndarray]) -> bytes:
    order = "<" if fmt == "binary_little_endian" else ">"
    kinds = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4", "short": "i2"}
    record = np.dtype([(name, order + kinds[kind]) for name, kind in props])
    data = np.zeros(len(next(iter(columns.values()))), dtype=record)
    for name, values in columns.items():
        data[name] = values
    return data.tobytes()


def _vertices(fmt="binary_little_endian", kind="double", normals=False, colours=False):
    props = [(axis, kind) for axis in "xyz"]
    columns = dict(zip("xyz", POINTS.T, strict=True))
    if normals:
        props += [(n, "float") for n in ("nx", "ny", "nz")]
        columns |= dict(zip(("nx", "ny", "nz"), NORMALS.T, strict=True))
    if colours:
        props += [(c, "uchar") for c in ("red", "green", "blue")]
        columns |= {c: np.full(len(POINTS), 200) for c in ("red", "green", "blue")}
    return ("vertex", len(POINTS), props, _vertex_body(fmt, props, columns))


def _faces(fmt="binary_little_endian", n=40) -> tuple:
    order = "<" if fmt == "binary_little_endian" else ">"
    row = np.dtype([("n", "u1"), ("v", order + "i4", (3,))])
    data = np.zeros(n, dtype=row)
    data["n"] = 3
    data["v"] = np.arange(3 * n).reshape(n, 3) % len(POINTS)
    return ("face", n, [("vertex_indices", "list uchar int")], data.tobytes())


def _open3d_read(path):
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(path), format="ply")
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    return np.asarray(cloud.points), normals


CASES = {
    "doubles": {},
    "floats": {"kind": "float"},
    "big-endian": {"fmt": "binary_big_endian"},
    "normals and colours": {"normals": True, "colours": True},
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_binary_vertices_read_directly_match_open3d(tmp_path, case, monkeypatch):
    options = CASES[case]
    fmt = options.get("fmt", "binary_little_endian")
    path = tmp_path / "scan.ply"
    path.write_bytes(_ply(fmt, [_vertices(**options), _faces(fmt)]))
    expected_points, expected_normals = _open3d_read(path)
    # The direct path must be the one taken: Open3D's reader is made to fail if it is called.
    monkeypatch.setattr(pointcloud, "_read_with_open3d", _refuse)
    scan = read_scan(path).scan
    np.testing.assert_array_equal(scan.points_m, expected_points)
    if options.get("normals"):
        np.testing.assert_allclose(scan.normals, expected_normals, atol=1e-7)
    else:
        assert scan.normals is None


def _refuse(*args, **kwargs):
    raise AssertionError("Open3D's reader was used for a layout the direct path takes")


def test_an_element_before_the_vertices_is_skipped_by_its_size(tmp_path, monkeypatch):
    camera = ("camera", 2, [("fx", "float"), ("fy", "float")], np.ones(4, "<f4").tobytes())
    path = tmp_path / "scan.ply"
    path.write_bytes(_ply("binary_little_endian", [camera, _vertices()]))
    monkeypatch.setattr(pointcloud, "_read_with_open3d", _refuse)
    np.testing.assert_array_equal(read_scan(path).scan.points_m, POINTS)


def _open3d_calls(monkeypatch) -> list[str]:
    """The names of the files read through Open3D from now on (it still reads them)."""
    calls: list[str] = []
    read_with_open3d = pointcloud._read_with_open3d
    monkeypatch.setattr(
        pointcloud,
        "_read_with_open3d",
        lambda *args: calls.append(args[0].name) or read_with_open3d(*args),
    )
    return calls


def test_layouts_the_direct_path_does_not_take_are_read_by_open3d(tmp_path, monkeypatch):
    calls = _open3d_calls(monkeypatch)
    ascii_path = tmp_path / "ascii.ply"
    rows = "\n".join(" ".join(f"{v:.17g}" for v in p) for p in POINTS)
    ascii_path.write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(POINTS)}\nproperty double x\n"
        f"property double y\nproperty double z\nend_header\n{rows}\n"
    )
    faces_first = tmp_path / "faces_first.ply"
    faces_first.write_bytes(_ply("binary_little_endian", [_faces(), _vertices()]))
    for path in (ascii_path, faces_first):
        np.testing.assert_allclose(read_scan(path).scan.points_m, POINTS, atol=1e-12)
    assert calls == ["ascii.ply", "faces_first.ply"]


def test_a_ply_without_coordinates_or_truncated_is_refused(tmp_path):
    no_xyz = ("vertex", 3, [("u", "float"), ("v", "float")], np.zeros(6, "<f4").tobytes())
    path = tmp_path / "no_xyz.ply"
    path.write_bytes(_ply("binary_little_endian", [no_xyz]))
    with pytest.raises(InputFileError, match="no x, y and z coordinates .*: u, v"):
        read_scan(path)
    short = tmp_path / "short.ply"
    short.write_bytes(_ply("binary_little_endian", [_vertices()])[:-100])
    with pytest.raises(InputFileError, match="declares 500 vertices"):
        read_scan(short)


def test_non_finite_vertices_are_dropped_and_counted(tmp_path):
    points = POINTS.copy()
    points[[3, 9]] = np.nan
    points[11, 0] = np.inf
    props = [(axis, "double") for axis in "xyz"]
    body = _vertex_body("binary_little_endian", props, dict(zip("xyz", points.T, strict=True)))
    path = tmp_path / "nan.ply"
    path.write_bytes(_ply("binary_little_endian", [("vertex", len(points), props, body)]))
    read = read_scan(path)
    assert read.n_dropped == 3
    assert len(read.scan.points_m) == len(points) - 3


def test_a_ply_with_no_vertices_is_refused_as_holding_no_points(tmp_path):
    for props in ([("x", "float"), ("y", "float"), ("z", "float")], [("u", "float")], []):
        path = tmp_path / "empty.ply"
        path.write_bytes(_ply("binary_little_endian", [("vertex", 0, props, b"")]))
        with pytest.raises(InputFileError, match="holds no points"):
            read_scan(path)


def test_a_property_named_twice_is_left_to_open3d(tmp_path, monkeypatch):
    props = [("x", "double"), ("y", "double"), ("z", "double"), ("x", "double")]
    body = np.column_stack([POINTS, POINTS[:, 0]]).astype("<f8").tobytes()
    path = tmp_path / "twice.ply"
    path.write_bytes(_ply("binary_little_endian", [("vertex", len(POINTS), props, body)]))
    calls = _open3d_calls(monkeypatch)
    # Open3D takes the first x (as the direct path would have): the same points.
    np.testing.assert_array_equal(read_scan(path).scan.points_m, POINTS)
    assert calls == ["twice.ply"]
