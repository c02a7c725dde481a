"""Scan readers beyond plain point clouds: the registry, E57, RGB-D frames and RealSense bags.

Ground truth is generated here: a plane z = 0 with a half-cylinder ridge of radius 40 mm along x,
ray-cast analytically (numpy, no Open3D) into 16-bit depth PNGs with known intrinsics and poses.
Depth is quantised to whole raw units (1 mm at the default scale), so a back-projected point
lies up to half a unit along its ray from the true surface: at most 0.5 mm x the ray's length per
unit depth (1.26 at the corner of a 640 x 480 image with f = 525 px), plus float rounding.
TSDF fusion adds the voxel's discretisation on top: points within one voxel (2 mm) of the
surface and 99 % within 1 mm are required (measured 1.5 mm and 0.7 mm).

Nothing is downloaded. Not testable here: decoding a real RealSense recording (nothing on this
machine can write one; see the bag tests for what is covered instead).
"""

from __future__ import annotations

import json
import shutil
import struct
import uuid
import zipfile
import zlib
from pathlib import Path

import numpy as np
import open3d as o3d
import pye57
import pytest
from pye57 import libe57
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError, MissingDependencyError, UnknownFormatError
from drivers.scanning import bag as bag_module
from drivers.scanning import base
from drivers.scanning.bag import BagOptions, BagReadError, extract_frames, frames_to_scan
from drivers.scanning.base import SCAN_READERS, format_for, make_reader, read_scan
from drivers.scanning.pointcloud import read_scan as pointcloud_read_scan
from drivers.scanning.pointcloud import write_scan
from drivers.scanning.rgbd import Intrinsics
from recon.inputs import Scan

MM = 1e-3
RIDGE_RADIUS_M = 0.04
INTRINSICS = Intrinsics(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)


# --------------------------------------------------------------------------- the synthetic scene


def look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_world_camera of a camera at ``eye`` looking at ``target`` (x right, y down, z ahead)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def render_depth(T_world_camera: np.ndarray, intr: Intrinsics = INTRINSICS) -> np.ndarray:
    """Depth along the optical axis (m) of every pixel, by analytic ray casting; inf for misses.

    The surface: the plane z = 0 where |y| >= R, and the cylinder y^2 + z^2 = R^2 above it.
    """
    u, v = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height, dtype=float))
    # Ray directions with unit z in the camera frame, so a ray parameter is the depth itself.
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    d = d_cam @ T_world_camera[:3, :3].T
    o = T_world_camera[:3, 3]
    t = np.full(u.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = -o[2] / d[..., 2]
        hit = (t_plane > 0) & (np.abs(o[1] + t_plane * d[..., 1]) >= RIDGE_RADIUS_M)
        t = np.where(hit, t_plane, t)
        a = d[..., 1] ** 2 + d[..., 2] ** 2
        b = 2 * (o[1] * d[..., 1] + o[2] * d[..., 2])
        c = o[1] ** 2 + o[2] ** 2 - RIDGE_RADIUS_M**2
        disc = b * b - 4 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        for t_cyl in ((-b - root) / (2 * a), (-b + root) / (2 * a)):
            on_top = o[2] + t_cyl * d[..., 2] >= 0
            hit = (disc >= 0) & (t_cyl > 0) & on_top & (t_cyl < t)
            t = np.where(hit, t_cyl, t)
    return t


def surface_distance(points: np.ndarray) -> np.ndarray:
    """Exact distance of each point (N, 3) to the plane-with-ridge surface, metres."""
    y, z = np.abs(points[:, 1]), points[:, 2]
    to_plane = np.where(y >= RIDGE_RADIUS_M, np.abs(z), np.hypot(y - RIDGE_RADIUS_M, z))
    to_cylinder = np.where(
        z >= 0, np.abs(np.hypot(y, z) - RIDGE_RADIUS_M), np.hypot(y - RIDGE_RADIUS_M, z)
    )
    return np.minimum(to_plane, to_cylinder)


def surface_samples(half_width_m: float = 0.1, step_m: float = 0.002) -> np.ndarray:
    """Points on the analytic surface over |x|, |y| <= half_width_m."""
    s = np.arange(-half_width_m, half_width_m + 1e-12, step_m)
    x, y = np.meshgrid(s, s)
    z = np.where(np.abs(y) < RIDGE_RADIUS_M, np.sqrt(np.maximum(RIDGE_RADIUS_M**2 - y**2, 0)), 0)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def max_quantisation_error_m(intr: Intrinsics, depth_scale: float) -> float:
    """Largest distance a half-unit depth rounding moves a back-projected point."""
    corner = np.hypot(
        max(intr.cx, intr.width - intr.cx) / intr.fx, max(intr.cy, intr.height - intr.cy) / intr.fy
    )
    return 0.5 / depth_scale * np.sqrt(1 + corner**2) + 1e-6


def to_raw(depth_m: np.ndarray, depth_scale: float = 1000.0) -> np.ndarray:
    raw = np.where(np.isfinite(depth_m), np.rint(depth_m * depth_scale), 0)
    return np.where(raw < 65535, raw, 0).astype(np.uint16)


def write_png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert o3d.io.write_image(str(path), o3d.geometry.Image(np.ascontiguousarray(array)))


def intrinsics_json(intr: Intrinsics = INTRINSICS, *, layout: str = "plain") -> dict:
    if layout == "open3d":
        pinhole = o3d.camera.PinholeCameraIntrinsic(
            intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy
        )
        return {
            "width": intr.width,
            "height": intr.height,
            "intrinsic_matrix": pinhole.intrinsic_matrix.T.ravel().tolist(),  # column-major
        }
    return {
        "fx": intr.fx,
        "fy": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "width": intr.width,
        "height": intr.height,
    }


def sequence_poses(n_frames: int) -> list[np.ndarray]:
    """Cameras on a circle 0.3 m around the ridge, 0.55 m up, all looking at it."""
    poses = []
    for i in range(n_frames):
        a = 2 * np.pi * i / n_frames
        eye = [0.3 * np.cos(a), 0.3 * np.sin(a), 0.55]
        poses.append(look_at(eye, target=[0.02 * np.cos(3 * a), 0.0, 0.0]))
    return poses


def write_open3d_log(path: Path, poses, indices=None) -> None:
    lines = []
    for i, T in zip(indices if indices is not None else range(len(poses)), poses, strict=True):
        lines.append(f"{i} {i} {i + 1}")
        lines += [" ".join(f"{v:.12f}" for v in row) for row in T]
    path.write_text("\n".join(lines) + "\n")


def make_sequence(root: Path, n_frames: int, *, poses: str = "log") -> list[np.ndarray]:
    """An RGB-D folder: intrinsics.json, depth/NNNNNN.png and the poses in the named format."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    Ts = sequence_poses(n_frames)
    stamps = [1305031102.0 + 0.1 * i for i in range(n_frames)]
    for i, T in enumerate(Ts):
        name = f"{stamps[i]:.6f}.png" if poses == "tum" else f"{i:06d}.png"
        write_png(root / "depth" / name, to_raw(render_depth(T)))
    if poses == "log":
        write_open3d_log(root / "trajectory.log", Ts)
    elif poses == "tum":
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        for stamp, T in zip(stamps, Ts, strict=True):
            q = Rotation.from_matrix(T[:3, :3]).as_quat(scalar_first=False)
            lines.append(f"{stamp + 0.004:.6f} " + " ".join(f"{v:.12f}" for v in [*T[:3, 3], *q]))
        (root / "poses.txt").write_text("\n".join(lines) + "\n")
    elif poses == "json":
        (root / "poses.json").write_text(
            json.dumps({f"{i:06d}": T.tolist() for i, T in enumerate(Ts)})
        )
    return Ts


def zip_folder(folder: Path, target: Path, *, nest: bool = True) -> Path:
    """A zip of ``folder`` as a file manager makes it (inside a top folder when ``nest``)."""
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                relative = path.relative_to(folder.parent if nest else folder)
                archive.write(path, relative.as_posix())
    return target


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> tuple[Path, list[np.ndarray]]:
    root = tmp_path_factory.mktemp("rgbd") / "scan"
    return root, make_sequence(root, 12)


@pytest.fixture(scope="module")
def fused(sequence):
    return read_scan(sequence[0])


# --------------------------------------------------------------------------- registry


def test_formats_are_chosen_by_suffix_folder_or_name(tmp_path):
    assert format_for("a.E57") == "e57"
    assert format_for("scan.rgbd.json") == "rgbd"
    assert format_for("frames.zip") == "rgbd"
    assert format_for("rec.bag") == "bag"
    assert format_for("cloud.ply") == "ply"
    assert format_for("anything", "E57") == "e57"
    with pytest.raises(UnknownFormatError, match="cannot tell the scan format"):
        format_for("settings.json")
    with pytest.raises(UnknownFormatError, match="unknown scan format 'las'"):
        format_for("x.ply", "las")
    with pytest.raises(InputFileError, match="no intrinsics.json"):
        read_scan(tmp_path)  # an (empty) folder is read as RGB-D frames


def test_options_are_checked_against_the_reader():
    with pytest.raises(ValueError, match="options of kind 'e57'"):
        make_reader("rgbd", {"kind": "e57"})
    with pytest.raises(ValueError, match="depth_trunk_m"):
        make_reader("rgbd", {"depth_trunk_m": 2.0})  # a typo is refused, not ignored
    with pytest.raises(ValueError, match="greater than or equal to 0.0005"):
        make_reader("rgbd", {"voxel_m": 1e-5})  # a million times the voxels of 1 mm
    with pytest.raises(ValueError, match="takes RGBDOptions"):
        make_reader("rgbd", BagOptions())
    assert make_reader("bag", {"n_frames": 3}).options.n_frames == 3


def test_resource_limits_lower_defaults_and_refuse_larger_requests():
    limits = {"max_unpacked_mb": 100.0, "timeout_s": 30.0}
    assert make_reader("rgbd", None, limits).options.max_unpacked_mb == 100.0
    assert make_reader("rgbd", {"fusion": "points"}, limits).options.max_unpacked_mb == 100.0
    assert make_reader("bag", {"n_frames": 3}, limits).options.timeout_s == 30.0
    assert make_reader("bag", {"timeout_s": 10}, limits).options.timeout_s == 10.0  # lower: fine
    with pytest.raises(ValueError, match="max_unpacked_mb=5000 exceeds the limit of 100"):
        make_reader("rgbd", {"max_unpacked_mb": 5000}, limits)
    with pytest.raises(ValueError, match="timeout_s=3600 exceeds the limit of 30"):
        make_reader("bag", {"timeout_s": 3600}, limits)
    make_reader("ply", None, limits)  # readers without those options are unaffected


def test_a_missing_dependency_names_the_package(monkeypatch):
    monkeypatch.setitem(SCAN_READERS.builtins, "e57", "pye57_is_not_installed_here:Reader")
    with pytest.raises(UnknownFormatError, match="pip install pye57_is_not_installed_here") as err:
        base.reader_class("e57")
    assert isinstance(err.value, MissingDependencyError)


def test_fixed_unit_formats_refuse_other_units(tmp_path):
    for name in ("a.e57", "a.bag", "a.zip"):
        (tmp_path / name).write_bytes(b"x")
        with pytest.raises(ValueError, match="leave units at 'm'"):
            read_scan(tmp_path / name, units="mm")


def test_write_scan_refuses_formats_it_cannot_write(tmp_path):
    with pytest.raises(UnknownFormatError, match="cannot write"):
        write_scan(tmp_path / "s.e57", Scan(points_m=np.eye(3)))


def test_pointcloud_read_scan_dispatches_to_every_reader(tmp_path):
    """The service's and CLI's entry point reads the new formats too, same signature."""
    frame = tmp_path / "frame"
    write_png(frame / "depth.png", to_raw(render_depth(look_at([0.05, -0.1, 0.5]))))
    (frame / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    archive = zip_folder(frame, tmp_path / "frame.zip")
    via_path = pointcloud_read_scan(archive)
    via_upload = pointcloud_read_scan(archive.read_bytes(), name="frame.zip", units="m")
    assert via_path.format == via_upload.format == "rgbd"
    np.testing.assert_array_equal(via_path.scan.points_m, via_upload.scan.points_m)


# --------------------------------------------------------------------------- E57


def write_e57(path: Path, scans) -> None:
    """scans: (points (N, 3), rotation wxyz, translation, invalid flags or None)."""
    with pye57.E57(str(path), mode="w") as e57:
        for points, wxyz, t, invalid in scans:
            data = {
                "cartesianX": points[:, 0],
                "cartesianY": points[:, 1],
                "cartesianZ": points[:, 2],
            }
            if invalid is not None:
                data["cartesianInvalidState"] = invalid.astype(np.int8)
            e57.write_scan_raw(data, rotation=np.asarray(wxyz), translation=np.asarray(t))


def write_spherical_e57(path: Path, rae: np.ndarray, wxyz, translation) -> None:
    """An E57 scan with only range/azimuth/elevation fields (pye57 writes cartesian only)."""
    with pye57.E57(str(path), mode="w") as e57:
        imf = e57.image_file
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
        pose, rot, trans = (libe57.StructureNode(imf) for _ in range(3))
        # Children in x, y, z, w order: the standard names them, it does not order them.
        for key, value in zip("xyzw", [*wxyz[1:], wxyz[0]], strict=True):
            rot.set(key, libe57.FloatNode(imf, float(value)))
        for key, value in zip("xyz", translation, strict=True):
            trans.set(key, libe57.FloatNode(imf, float(value)))
        pose.set("rotation", rot)
        pose.set("translation", trans)
        scan.set("pose", pose)
        names = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
        prototype = libe57.StructureNode(imf)
        for name, column in zip(names, rae.T, strict=True):
            low, high = float(column.min()), float(column.max())
            prototype.set(name, libe57.FloatNode(imf, low, libe57.E57_DOUBLE, low, high))
        points = libe57.CompressedVectorNode(imf, prototype, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e57.data3d.append(scan)
        arrays, buffers = e57.make_buffers(list(names), len(rae))
        for name, column in zip(names, rae.T, strict=True):
            arrays[name][:] = column
        writer = points.writer(buffers)
        writer.write(len(rae))
        writer.close()


def posed(points, wxyz, t):
    R = Rotation.from_quat([*wxyz[1:], wxyz[0]], scalar_first=False).as_matrix()
    return points @ R.T + np.asarray(t)


def test_e57_round_trip_merges_every_scan_by_its_pose(tmp_path):
    rng = np.random.default_rng(2)
    a, b = rng.uniform(-1, 1, (500, 3)), rng.uniform(-1, 1, (300, 3))
    qa = Rotation.from_rotvec([0.1, -0.4, 0.9]).as_quat(scalar_first=True)
    qb = np.array([1.0, 0.0, 0.0, 0.0])
    write_e57(tmp_path / "s.e57", [(a, qa, [1.0, -2.0, 0.5], None), (b, qb, [0.0, 0.0, 3.0], None)])
    result = read_scan(tmp_path / "s.e57")
    assert result.format == "e57" and result.n_dropped == 0 and len(result.scan) == 800
    expected = np.concatenate([posed(a, qa, [1.0, -2.0, 0.5]), posed(b, qb, [0, 0, 3.0])])
    # pye57 stores coordinates as float32: 1e-6 m is their resolution at 1 m.
    np.testing.assert_allclose(result.scan.points_m, expected, atol=1e-6)
    upload = read_scan((tmp_path / "s.e57").read_bytes(), name="site.e57")
    np.testing.assert_array_equal(upload.scan.points_m, result.scan.points_m)


def test_e57_points_flagged_invalid_are_dropped_and_counted(tmp_path):
    points = np.random.default_rng(3).uniform(-1, 1, (100, 3))
    invalid = np.zeros(100, bool)
    invalid[::10] = True
    write_e57(tmp_path / "s.e57", [(points, [1, 0, 0, 0], [0, 0, 0], invalid)])
    result = read_scan(tmp_path / "s.e57")
    assert len(result.scan) == 90 and result.n_dropped == 10
    assert "flagged invalid" in result.dropped_because
    np.testing.assert_allclose(result.scan.points_m, points[~invalid], atol=1e-6)


def test_e57_spherical_only_scans_are_converted(tmp_path):
    rng = np.random.default_rng(4)
    rae = np.column_stack(
        [rng.uniform(1, 5, 200), rng.uniform(-np.pi, np.pi, 200), rng.uniform(-1.2, 1.2, 200)]
    )
    wxyz = Rotation.from_rotvec([0.0, 0.3, 0.2]).as_quat(scalar_first=True)
    write_spherical_e57(tmp_path / "s.e57", rae, wxyz, [1.0, 2.0, 3.0])
    result = read_scan(tmp_path / "s.e57")
    r, azimuth, elevation = rae.T  # the standard's convention (ASTM E2807, 8.4.11)
    local = np.column_stack(
        [
            r * np.cos(elevation) * np.cos(azimuth),
            r * np.cos(elevation) * np.sin(azimuth),
            r * np.sin(elevation),
        ]
    )
    np.testing.assert_allclose(result.scan.points_m, posed(local, wxyz, [1, 2, 3]), atol=1e-9)


def test_bad_e57_files_are_refused_with_a_reason(tmp_path, capfd):
    write_e57(tmp_path / "good.e57", [(np.eye(3), [1, 0, 0, 0], [0, 0, 0], None)])
    content = (tmp_path / "good.e57").read_bytes()
    cases = {
        "empty.e57": (b"", "is empty"),
        "text.e57": (b"ply\nformat ascii 1.0\n", "not an E57 file"),
        "truncated.e57": (content[: len(content) // 2], "truncated or corrupt"),
        "flipped.e57": (content[:2000] + b"\xff" * 64 + content[2064:], "corrupt|not a readable"),
    }
    for name, (data, message) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputFileError, match=message):
            read_scan(tmp_path / name)
    with pytest.raises(InputFileError, match="does not exist"):
        read_scan(tmp_path / "missing.e57")
    with pytest.raises(ValueError, match="metres by the ASTM E2807 standard"):
        read_scan(tmp_path / "good.e57", units="mm")
    with pye57.E57(str(tmp_path / "void.e57"), mode="w"):
        pass  # pye57 cannot write a scan without valid points; a file without scans it can
    with pytest.raises(InputFileError, match="holds no scans"):
        read_scan(tmp_path / "void.e57")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


# --------------------------------------------------------------------------- one RGB-D frame


def numpy_backprojection(raw, intr, depth_scale, T_world_camera=None):
    """The pinhole model written out, independent of Open3D."""
    T_world_camera = np.eye(4) if T_world_camera is None else T_world_camera
    v, u = np.nonzero(raw)
    z = raw[v, u] / depth_scale
    cam = np.column_stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z])
    return cam @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


def test_one_frame_folder_matches_the_analytic_surface(tmp_path):
    T = look_at([0.08, -0.25, 0.5])
    raw = to_raw(render_depth(T))
    folder = tmp_path / "frame"
    write_png(folder / "depth.png", raw)
    (folder / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    result = read_scan(folder)
    assert result.format == "rgbd" and result.n_dropped == 0
    assert len(result.scan) == np.count_nonzero(raw)
    # Without a pose the cloud is in the camera frame: move it to the world to compare.
    world = result.scan.points_m @ T[:3, :3].T + T[:3, 3]
    assert surface_distance(world).max() < max_quantisation_error_m(INTRINSICS, 1000.0)
    np.testing.assert_allclose(
        np.sort(result.scan.points_m, axis=0),
        np.sort(numpy_backprojection(raw, INTRINSICS, 1000.0), axis=0),
        atol=1e-6,
    )


def test_manifest_frame_with_pose_colour_scale_and_open3d_intrinsics(tmp_path):
    T = look_at([-0.1, 0.2, 0.45])
    raw = to_raw(render_depth(T), depth_scale=5000.0)  # the TUM data sets' scale
    write_png(tmp_path / "d" / "depth.png", raw)
    write_png(tmp_path / "d" / "color.png", np.zeros((480, 640, 3), np.uint8))
    manifest = {
        "intrinsics": intrinsics_json(layout="open3d"),
        "depth_scale": 5000,
        "depth": "d/depth.png",
        "color": "d/color.png",
        "T_world_camera": T.tolist(),
    }
    (tmp_path / "frame.rgbd.json").write_text(json.dumps(manifest))
    result = read_scan(tmp_path / "frame.rgbd.json")
    assert surface_distance(result.scan.points_m).max() < max_quantisation_error_m(
        INTRINSICS, 5000.0
    )
    assert any("5000" in note and "manifest" in note for note in result.notes)


def test_depth_beyond_the_truncation_is_left_out_and_counted(tmp_path):
    T = look_at([0.0, -0.6, 0.35])  # a grazing view: the plane runs far away
    raw = to_raw(render_depth(T))
    folder = tmp_path / "frame"
    write_png(folder / "depth.png", raw)
    (folder / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    result = read_scan(folder, options={"depth_trunc_m": 1.0})
    far = int(np.count_nonzero(raw > 1000))
    assert far > 0 and result.n_dropped == far
    # The reader's reason, not "without finite coordinates" (the finding).
    assert "depth_trunc_m" in result.dropped_because
    assert len(result.scan) == np.count_nonzero(raw) - far
    assert np.all(result.scan.points_m[:, 2] <= 1.0 + 1e-9)


# --------------------------------------------------------------------------- several frames


def test_fused_frames_cover_the_surface_within_a_voxel(sequence, fused):
    points = fused.scan.points_m
    distance = surface_distance(points)
    assert distance.max() < 2 * MM  # one TSDF voxel
    assert np.percentile(distance, 99) < 1 * MM
    # Every part of the ridge and the plane around it that all cameras see is covered. The TSDF
    # rounds the concave crease where the ridge meets the plane (measured gaps up to 1.9 mm
    # there, 1.2 mm elsewhere).
    samples = surface_samples(0.1)
    gaps, _ = cKDTree(points).query(samples)
    crease = np.abs(np.abs(samples[:, 1]) - RIDGE_RADIUS_M) < 3 * MM
    assert gaps[~crease].max() < 1.5 * MM
    assert gaps[crease].max() < 3 * MM
    # TSDF normals are unit and, on the flat part, vertical.
    normals = fused.scan.normals
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    flat = (np.abs(points[:, 1]) > RIDGE_RADIUS_M + 0.01) & (np.abs(points[:, 1]) < 0.1)
    assert np.median(np.abs(normals[flat, 2])) > 0.99
    assert any("TSDF" in note for note in fused.notes)


@pytest.mark.slow
def test_points_fusion_is_exact_to_the_quantisation(sequence):
    result = read_scan(sequence[0], options={"fusion": "points", "voxel_m": 0.001})
    assert surface_distance(result.scan.points_m).max() < max_quantisation_error_m(
        INTRINSICS, 1000.0
    )
    gaps, _ = cKDTree(result.scan.points_m).query(surface_samples(0.1))
    assert gaps.max() < 2 * MM
    assert result.scan.normals is None


@pytest.mark.slow
def test_a_zip_of_the_folder_reads_like_the_folder(sequence, fused, tmp_path):
    archive = zip_folder(sequence[0], tmp_path / "scan.zip")
    via_path = read_scan(archive)
    via_upload = read_scan(archive.read_bytes(), name="upload.zip")
    np.testing.assert_array_equal(via_path.scan.points_m, fused.scan.points_m)
    np.testing.assert_array_equal(via_upload.scan.points_m, fused.scan.points_m)
    flat = zip_folder(sequence[0], tmp_path / "flat.zip", nest=False)
    np.testing.assert_array_equal(read_scan(flat).scan.points_m, fused.scan.points_m)


@pytest.mark.parametrize("poses", ["tum", "json"])
def test_tum_and_json_poses_give_the_log_result(tmp_path, poses):
    make_sequence(tmp_path / "log", 3)
    make_sequence(tmp_path / poses, 3, poses=poses)
    options = {"fusion": "points"}
    expected = read_scan(tmp_path / "log", options=options).scan.points_m
    np.testing.assert_allclose(
        read_scan(tmp_path / poses, options=options).scan.points_m, expected, atol=1e-9
    )


def test_manifest_lists_frames_with_poses(tmp_path):
    Ts = make_sequence(tmp_path / "seq", 3)
    frames = [
        {"depth": f"seq/depth/{i:06d}.png", "T_world_camera": T.tolist()} for i, T in enumerate(Ts)
    ]
    (tmp_path / "all.rgbd.json").write_text(
        json.dumps({"intrinsics": "seq/intrinsics.json", "frames": frames})
    )
    options = {"fusion": "points"}
    np.testing.assert_allclose(
        read_scan(tmp_path / "all.rgbd.json", options=options).scan.points_m,
        read_scan(tmp_path / "seq", options=options).scan.points_m,
        atol=1e-12,
    )


# --------------------------------------------------------------------------- bad RGB-D input


@pytest.fixture()
def frame_folder(tmp_path) -> Path:
    folder = tmp_path / "frame"
    write_png(folder / "depth.png", to_raw(render_depth(look_at([0.05, -0.1, 0.5]))))
    (folder / "intrinsics.json").write_text(json.dumps(intrinsics_json()))
    return folder


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _flip_bytes(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 8] = b"\x00\xff" * 4
    path.write_bytes(bytes(data))


def _short_ihdr(path: Path) -> None:
    """A PNG whose header chunk is cut to 4 bytes, with a valid checksum (a crafted file)."""
    body = b"\x00\x00\x02\x80"
    chunk = struct.pack(">I4s", len(body), b"IHDR") + body
    chunk += struct.pack(">I", zlib.crc32(b"IHDR" + body))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + struct.pack(">I4sI", 0, b"IEND", 0xAE426082))


def _intrinsics(**changes):
    def edit(folder: Path) -> None:
        values = intrinsics_json()
        for key, value in changes.items():
            if value is None:
                values.pop(key)
            else:
                values[key] = value
        (folder / "intrinsics.json").write_text(json.dumps(values))

    return edit


BAD_FRAMES = {
    "truncated depth": (lambda f: _truncate(f / "depth.png"), "truncated PNG"),
    "corrupt depth": (lambda f: _flip_bytes(f / "depth.png"), "corrupt PNG"),
    "short PNG header": (lambda f: _short_ihdr(f / "depth.png"), "IHDR header chunk has 4 bytes"),
    "empty depth": (lambda f: (f / "depth.png").write_bytes(b""), "is empty"),
    "not an image": (lambda f: (f / "depth.png").write_text("depth"), "neither a PNG nor"),
    "8-bit depth": (
        lambda f: write_png(f / "depth.png", np.full((480, 640), 100, np.uint8)),
        "8-bit PNG with 1 channel.*16-bit greyscale",
    ),
    "colour as depth": (
        lambda f: write_png(f / "depth.png", np.zeros((480, 640, 3), np.uint8)),
        "16-bit greyscale",
    ),
    "size mismatch": (
        lambda f: write_png(f / "depth.png", np.full((240, 320), 500, np.uint16)),
        "320 x 240 pixels but the intrinsics are for 640 x 480",
    ),
    "no depth at all": (
        lambda f: write_png(f / "depth.png", np.zeros((480, 640), np.uint16)),
        "no depth measurement",
    ),
    "metres read as millimetres": (
        lambda f: write_png(f / "depth.png", np.full((480, 640), 1, np.uint16)),
        "median depth is 1 mm, closer than depth cameras measure",
    ),
    "no depth png": (lambda f: (f / "depth.png").unlink(), "no depth.png and no depth/ folder"),
    "no intrinsics": (lambda f: (f / "intrinsics.json").unlink(), "no intrinsics.json"),
    "intrinsics lack fields": (_intrinsics(fy=None, cx=None), "lacks fy, cx"),
    "NaN focal length": (_intrinsics(fx=float("nan")), "fx is nan"),
    "negative focal length": (_intrinsics(fx=-525.0), "focal lengths must be positive"),
    "text focal length": (_intrinsics(fx="525"), "fx must be a number"),
    "principal point outside": (_intrinsics(cx=900.0), "outside the 640 x 480 image"),
    "fractional width": (_intrinsics(width=640.5), "whole pixels"),
    "intrinsics not JSON": (
        lambda f: (f / "intrinsics.json").write_text("fx: 525"),
        "not valid JSON",
    ),
    "intrinsics empty": (lambda f: (f / "intrinsics.json").write_text(""), "is empty"),
    "intrinsics a list": (
        lambda f: (f / "intrinsics.json").write_text("[525, 525]"),
        "must be a JSON object",
    ),
    "bad intrinsic matrix": (
        lambda f: (f / "intrinsics.json").write_text(
            json.dumps({"width": 640, "height": 480, "intrinsic_matrix": [1] * 9})
        ),
        "not a pinhole camera matrix",
    ),
    "two intrinsics files": (
        lambda f: shutil.copy(f / "intrinsics.json", f / "intrinsic.json"),
        "both intrinsics.json and intrinsic.json",
    ),
}


@pytest.mark.parametrize("case", list(BAD_FRAMES))
def test_bad_rgbd_frames_are_refused_with_a_reason(frame_folder, capfd, case):
    spoil, message = BAD_FRAMES[case]
    spoil(frame_folder)
    with pytest.raises(InputFileError, match=message):
        read_scan(frame_folder)
    out, err = capfd.readouterr()  # nothing of Open3D's complaints reaches the terminal
    assert out == "" and err == ""


@pytest.mark.parametrize(
    "depth_scale, message",
    [
        (
            1.0,
            r"depth_scale 1 .*median depth is \d{3} m, beyond depth_trunc_m 3.*"
            r"use depth_scale 1000",
        ),
        (1e6, r"median depth is 0\.\d+ mm.*perhaps 1000"),
    ],
)
def test_a_depth_scale_off_by_1000_is_named(frame_folder, depth_scale, message):
    with pytest.raises(InputFileError, match=message):
        read_scan(frame_folder, options={"depth_scale": depth_scale})


def test_units_other_than_metres_are_refused_for_depth_images(frame_folder):
    with pytest.raises(ValueError, match="depth_scale"):
        read_scan(frame_folder, units="mm")


def _log_without_frame_1(root: Path) -> None:
    poses = sequence_poses(3)
    write_open3d_log(root / "trajectory.log", [poses[0], poses[2]], indices=[0, 2])


def _nan_pose(root: Path) -> None:
    poses = sequence_poses(3)
    poses[1][0, 3] = np.nan
    write_open3d_log(root / "trajectory.log", poses)


def _scaled_pose(root: Path) -> None:
    poses = sequence_poses(3)
    poses[2][:3, :3] *= 1000.0  # a pose exported in millimetres as a scaled matrix
    write_open3d_log(root / "trajectory.log", poses)


def _shifted_tum(root: Path) -> None:
    (root / "trajectory.log").unlink()
    for path in (root / "depth").iterdir():
        path.rename(path.with_name(f"frame{path.name}"))
    lines = [f"{1.0 + i * 0.1:.6f} 0 0 0.5 0 0 0 1" for i in range(3)]
    (root / "poses.txt").write_text("\n".join(lines))


def _json_missing(root: Path) -> None:
    (root / "trajectory.log").unlink()
    (root / "poses.json").write_text(json.dumps({"000000": np.eye(4).tolist()}))


BAD_SEQUENCES = {
    "missing pose": (_log_without_frame_1, r"no pose for frame depth/000001.png \(index 1\)"),
    "no pose file": (lambda r: (r / "trajectory.log").unlink(), "3 depth images but no camera"),
    "NaN pose": (_nan_pose, "frame 1 has NaN"),
    "scaled pose": (_scaled_pose, "not a rotation"),
    "truncated log": (
        lambda r: (r / "trajectory.log").write_text(
            "\n".join((r / "trajectory.log").read_text().splitlines()[:-2])
        ),
        "truncated or not a trajectory log",
    ),
    "log for too many frames": (
        lambda r: write_open3d_log(r / "trajectory.log", sequence_poses(4)),
        "pose for frame 3, but there are 3 depth images",
    ),
    "TUM names without timestamps": (_shifted_tum, "frame000000.png has none; rename"),
    "JSON pose missing": (_json_missing, "no pose for frame depth/000001.png in poses.json"),
    "two pose files": (
        lambda r: (r / "poses.json").write_text("{}"),
        "several pose files",
    ),
    "empty depth folder": (
        lambda r: [p.unlink() for p in (r / "depth").iterdir()],
        "depth holds no .png",
    ),
}


@pytest.mark.parametrize("case", list(BAD_SEQUENCES))
def test_bad_sequences_are_refused_with_a_reason(tmp_path, case):
    root = tmp_path / "seq"
    make_sequence(root, 3)
    spoil, message = BAD_SEQUENCES[case]
    spoil(root)
    with pytest.raises(InputFileError, match=message):
        read_scan(root, options={"fusion": "points"})


def test_tum_timestamps_too_far_from_a_frame(tmp_path):
    root = tmp_path / "seq"
    make_sequence(root, 3, poses="tum")
    lines = (root / "poses.txt").read_text().splitlines()
    (root / "poses.txt").write_text("\n".join(lines[:2] + lines[3:]))  # drop frame 1's pose
    with pytest.raises(InputFileError, match=r"no pose for frame depth/1305031102.100000.png"):
        read_scan(root)


def test_a_sequence_whose_frames_are_all_empty(tmp_path):
    root = tmp_path / "seq"
    make_sequence(root, 3)
    for path in (root / "depth").iterdir():
        write_png(path, np.zeros((480, 640), np.uint16))
    with pytest.raises(InputFileError, match="none of the 3 depth images"):
        read_scan(root)


BAD_MANIFESTS = {
    "unknown key": ({"intrinsics": {}, "depth": "d.png", "depht_scale": 1000}, "depht_scale"),
    "frames and depth": (
        {"intrinsics": {}, "depth": "d.png", "frames": [{"depth": "d.png"}]},
        "not both",
    ),
    "no frames": ({"intrinsics": {}, "frames": []}, "lists no frames"),
    "climbs out": ({"intrinsics": intrinsics_json(), "depth": "../d.png"}, "outside its folder"),
    "missing depth": ({"intrinsics": intrinsics_json(), "depth": "d.png"}, "does not exist"),
    "missing intrinsics file": ({"intrinsics": "k.json", "depth": "d.png"}, "does not exist"),
    "missing colour": (
        {"intrinsics": intrinsics_json(), "depth": "frame/depth.png", "color": "c.png"},
        "colour image c.png does not exist",
    ),
    "two frames, one pose": (
        {
            "intrinsics": intrinsics_json(),
            "frames": [
                {"depth": "frame/depth.png", "T_world_camera": np.eye(4).tolist()},
                {"depth": "frame/depth.png"},
            ],
        },
        "no camera pose for frame frame/depth.png",
    ),
    "pose not 4x4": (
        {"intrinsics": intrinsics_json(), "depth": "frame/depth.png", "T_world_camera": [[1]]},
        "must be a 4x4 matrix",
    ),
}


@pytest.mark.parametrize("case", list(BAD_MANIFESTS))
def test_bad_manifests_are_refused_with_a_reason(frame_folder, case):
    content, message = BAD_MANIFESTS[case]
    path = frame_folder.parent / "m.rgbd.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputFileError, match=message):
        read_scan(path)


def test_bad_uploads_and_zips_are_refused_with_a_reason(frame_folder, tmp_path):
    manifest = json.dumps({"intrinsics": "intrinsics.json", "depth": "depth.png"}).encode()
    with pytest.raises(InputFileError, match="must be a .zip of the folder"):
        read_scan(manifest, name="frame.rgbd.json")
    with pytest.raises(InputFileError, match="is empty"):
        read_scan(b"", name="frame.zip")
    good = zip_folder(frame_folder, tmp_path / "good.zip").read_bytes()
    with pytest.raises(InputFileError, match="not a zip archive, or it is truncated"):
        read_scan(good[: len(good) // 2], name="frame.zip")
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("scan/cloud.ply", "ply\n")
    with pytest.raises(InputFileError, match="holds no RGB-D frames"):
        read_scan(tmp_path / "other.zip")
    with zipfile.ZipFile(tmp_path / "evil.zip", "w") as archive:
        archive.writestr("intrinsics.json", "{}")
        archive.writestr("../../escape.png", "x")
    with pytest.raises(InputFileError, match="unsafe member name"):
        read_scan(tmp_path / "evil.zip")
    with pytest.raises(InputFileError, match="unpacks to .* more than"):
        read_scan(tmp_path / "good.zip", options={"max_unpacked_mb": 0.01})
    with zipfile.ZipFile(tmp_path / "empty.zip", "w"):
        pass
    with pytest.raises(InputFileError, match="empty zip"):
        read_scan(tmp_path / "empty.zip")


# --------------------------------------------------------------------------- RealSense bags


def ros_bag_without_streams() -> bytes:
    """A well-formed ROS bag v2.0 with no connections: a recording of nothing."""

    def field(name: str, value: bytes) -> bytes:
        item = name.encode() + b"=" + value
        return struct.pack("<I", len(item)) + item

    magic = b"#ROSBAG V2.0\n"
    header = (
        field("op", b"\x03")
        + field("index_pos", struct.pack("<Q", len(magic) + 4096))
        + field("conn_count", struct.pack("<I", 0))
        + field("chunk_count", struct.pack("<I", 0))
    )
    padding = 4096 - (4 + len(header) + 4)  # the bag header record is padded to 4 KiB
    return (
        magic
        + struct.pack("<I", len(header))
        + header
        + struct.pack("<I", padding)
        + b" " * padding
    )


BAD_BAGS = {
    "empty": (b"", "is empty"),
    "not a bag": (b"PK\x03\x04 a zip, say", "not a RealSense recording"),
    "signature only": (b"#ROSBAG V2.0\n", "librealsense cannot play"),
    "truncated header": (ros_bag_without_streams()[:100], "librealsense cannot play"),
    "no streams": (ros_bag_without_streams(), "lacks a depth \\(Z16\\) and a colour"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BAD_BAGS))
def test_bad_bags_are_refused_with_a_reason(tmp_path, capfd, case):
    content, message = BAD_BAGS[case]
    (tmp_path / "rec.bag").write_bytes(content)
    with pytest.raises(InputFileError, match=message):
        read_scan(tmp_path / "rec.bag")
    with pytest.raises(InputFileError, match=message):
        read_scan(content, name="rec.bag")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_missing_bag(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_scan(tmp_path / "rec.bag")
    with pytest.raises(ValueError, match="depth units"):
        read_scan(tmp_path / "rec.bag", units="mm")


class FakeBagReader:
    """Stands in for o3d.t.io.RSBagReader: the same calls, frames from the synthetic scene."""

    def __init__(self, frames, *, opens=True, depth_scale=1000.0):
        self.frames, self.opens, self.position = list(frames), opens, 0
        self.metadata = o3d.t.io.RGBDVideoMetadata()
        self.metadata.intrinsics = INTRINSICS.to_open3d()
        self.metadata.depth_scale = depth_scale
        self.closed = False

    def open(self, path):
        return self.opens

    def is_eof(self):
        return self.position >= len(self.frames)

    def next_frame(self):
        if self.is_eof():
            return o3d.t.geometry.RGBDImage()
        raw = self.frames[self.position]
        self.position += 1
        colour = np.zeros((*raw.shape, 3), np.uint8)
        return o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(o3d.core.Tensor(colour)),
            o3d.t.geometry.Image(o3d.core.Tensor(raw[..., None])),
        )

    def close(self):
        self.closed = True


def test_bag_frames_become_the_median_depth_of_a_static_camera():
    """What the child process does with Open3D's reader, with the reader faked."""
    T = look_at([0.05, -0.2, 0.5])
    truth = render_depth(T)
    rng = np.random.default_rng(5)
    noisy = [to_raw(truth + rng.normal(0, 0.002, truth.shape)) for _ in range(9)]
    noisy.insert(0, np.full_like(noisy[0], 7))  # a first frame before exposure settled
    fake = FakeBagReader(noisy)
    frames = extract_frames("rec.bag", 1, 9, reader_factory=lambda: fake)
    assert fake.closed and frames["depth"].shape == (9, 480, 640)
    result = frames_to_scan(frames, BagOptions(first_frame=1, n_frames=9), label="rec.bag")
    world = result.scan.points_m @ T[:3, :3].T + T[:3, 3]
    # The median of 9 frames with 2 mm noise: about 0.8 mm, well under one frame's noise.
    assert np.sqrt(np.mean(surface_distance(world) ** 2)) < 1.2 * MM
    assert any("median of 9 frame(s)" in note for note in result.notes)


def test_bag_reader_failures_map_to_exit_statuses():
    with pytest.raises(BagReadError) as cannot_open:
        extract_frames("rec.bag", 0, 3, reader_factory=lambda: FakeBagReader([], opens=False))
    with pytest.raises(BagReadError) as no_frames:
        extract_frames(
            "rec.bag", 5, 3, reader_factory=lambda: FakeBagReader([np.ones((480, 640), np.uint16)])
        )
    assert cannot_open.value.status == bag_module._EXIT_CANNOT_OPEN
    assert no_frames.value.status == bag_module._EXIT_NO_FRAMES


def test_bag_depth_scale_and_flicker_checks():
    raw = to_raw(render_depth(look_at([0.0, -0.1, 0.5])))
    frames = {"depth": raw[None], "K": INTRINSICS.matrix, "size": np.array([640, 480])}
    with pytest.raises(InputFileError, match="use depth_scale 1000"):
        frames_to_scan({**frames, "depth_scale": 1.0}, BagOptions(), label="rec.bag")
    assert (
        frames_to_scan({**frames, "depth_scale": 0.0}, BagOptions(), label="rec.bag")
        .notes[0]
        .endswith("the bag gave none)")
    )
    flicker = np.stack([raw, np.zeros_like(raw), np.zeros_like(raw)])
    with pytest.raises(InputFileError, match="no pixel has depth in at least 50%"):
        frames_to_scan({**frames, "depth": flicker}, BagOptions(), label="rec.bag")
    with pytest.raises(InputFileError, match="do not match the colour camera"):
        frames_to_scan({**frames, "depth": raw[None, :240]}, BagOptions(), label="rec.bag")
