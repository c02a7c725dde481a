"""A scan's size is checked when it is read: millimetres read as metres, the reverse, and scans
of a site (not of a workpiece) are refused there, not at the first reconstruction."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.scanning.base import MAX_SCAN_EXTENT_M, check_scan_units
from drivers.scanning.pointcloud import read_scan
from recon.errors import UnitsMismatchError
from tests.corpus import require_corpus


def _cylinder(height: float, radius: float) -> np.ndarray:
    angle, z = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0, height, 40))
    return np.c_[radius * np.cos(angle).ravel(), radius * np.sin(angle).ravel(), z.ravel()]


def _xyz(points: np.ndarray) -> bytes:
    return "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points).encode()


def test_millimetres_read_as_metres_are_refused_with_the_unit_to_give():
    part_mm = _xyz(_cylinder(170.0, 30.0))
    with pytest.raises(
        UnitsMismatchError, match=r"spans 190 m .* look like millimetres .*190 mm.*units=mm"
    ):
        read_scan(part_mm, name="part.xyz", units="m")
    scan = read_scan(part_mm, name="part.xyz", units="mm").scan
    assert np.ptp(scan.points_m[:, 2]) == pytest.approx(0.17)


def test_metres_read_as_millimetres_are_refused_with_the_unit_to_give():
    part_m = _xyz(_cylinder(0.00017, 0.00003))  # a 170 mm part in metres... read as mm: 0.17 mm
    with pytest.raises(UnitsMismatchError, match=r"read as millimetres, spans only .*units=m"):
        read_scan(part_m, name="part.xyz", units="mm")


@pytest.mark.parametrize(
    "points, words",
    [
        (np.array([[0, 0, 0], [MAX_SCAN_EXTENT_M * 1e3 * 2, 0, 0]]), "a scan of a site"),
        (np.array([[6.4e5, 8.5e5, 120.0], [6.4e5 + 300, 8.5e5 + 100, 130.0]]), "a scan of a site"),
        (np.array([[0, 0, 0], [1e300, 0, 0]]), "a scan of a site"),
    ],
    ids=["kilometres", "geographic", "huge"],
)
def test_scans_of_sites_are_refused_in_either_unit(points, words):
    for units in ("m", "mm"):
        with pytest.raises(UnitsMismatchError, match=words):
            check_scan_units(points * (1e-3 if units == "mm" else 1.0), units, "site.xyz")


def test_real_scans_of_rooms_parts_and_a_plant_pass_and_aerial_lidar_is_refused():
    """The corpus's files written by real scanners and tools: every scan of a part or a room
    (2-7.5 m) reads; PDAL's Autzen aerial LiDAR (386 m wide, geographic coordinates) is refused
    as a site, not as wrong units."""
    corpus = require_corpus() / "real-inputs"
    readable = [
        "e57/libe57org_bunny_double.e57",
        "e57/libe57org_pumpA_visual_reference_155k_rgb_intensity.e57",
        "pcd/pcl_office1_organized_rgbfloat.pcd",
        "pcd/pcl_table_scene_mug_stereo_organized_bincompressed.pcd",
        "ply/open3d_coloredicp_frag_115.ply",
    ]
    for name in readable:
        assert len(read_scan(corpus / name).scan.points_m) > 1000, name
    with pytest.raises(UnitsMismatchError, match=r"spans 386\.\d m .* a scan of a site"):
        read_scan(corpus / "pts/pdal_autzen_lidar_10pts.pts")


def test_a_few_stray_points_far_out_do_not_refuse_a_workpiece_scan():
    """One stray return 40 m away in a 2,400-point scan of a 170 mm part (a reflection): the
    bulk decides, the scan reads."""
    part = _cylinder(0.17, 0.03)
    stray = np.vstack([part, [[40.0, 0.0, 0.0]]])
    check_scan_units(stray, "m", "part.ply")  # no refusal
    with pytest.raises(UnitsMismatchError, match="look like millimetres"):
        check_scan_units(stray * 1000, "m", "part.ply")
