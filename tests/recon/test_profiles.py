"""The scan's cross-sections (recon.profiles), one-face fits (recon.faces), the edge a segment
follows (recon.classify) and the lift-off checks (recon.methods.anchored), on analytic profiles
with known answers: dihedral edges, a chamfer, a thin wall, a step."""

from __future__ import annotations

import itertools
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from recon.faces import fit_faces
from recon.inputs import Scan
from recon.methods import anchored
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.results import PointMode
from recon.scan_model import build_scan_model
from recon.transforms import apply_transform

MM = 1e-3


def extruded(profile_yz, rng, *, sigma_m, length_m=0.06, spacing_m=0.0007):
    """A surface whose cross-section (y, z) is the polyline ``profile_yz`` (K, 2), extruded
    along x over ``length_m``, sampled at random about every ``spacing_m`` with noise along each
    face's normal. Returns (points (M, 3), unit normals (M, 3))."""
    profile = np.asarray(profile_yz, dtype=np.float64)
    points, normals = [], []
    for a, b in itertools.pairwise(profile):
        width = float(np.linalg.norm(b - a))
        n = int(length_m * width / spacing_m**2)
        t = rng.uniform(0.0, 1.0, n)
        x = rng.uniform(-length_m / 2, length_m / 2, n)
        yz = a + t[:, None] * (b - a)
        direction = (b - a) / width
        normal = np.array([0.0, -direction[1], direction[0]])
        face = np.column_stack([x, yz]) + rng.normal(0.0, sigma_m, n)[:, None] * normal
        points.append(face)
        normals.append(np.repeat(normal[None], n, axis=0))
    return np.concatenate(points), np.concatenate(normals)


def along_x(y_m, z_m, *, length_m=0.04, spacing_m=0.001):
    """A straight path along x at (y, z)."""
    x = np.arange(-length_m / 2, length_m / 2 + 1e-12, spacing_m)
    return np.column_stack([x, np.full_like(x, y_m), np.full_like(x, z_m)])


def model_for(points, path):
    return build_scan_model(Scan(points_m=points), path, ReconParams())


def corners_near(model, where_yz, reach_m=1.5 * MM):
    """The supported slice corners within ``reach_m`` of (y, z) in the middle stations
    (away from the scan's ends), as (C, 3) scan-frame points."""
    profiles = model.profiles
    middle = np.abs(profiles.origin_m[:, 0]) < 0.012
    corners = profiles.corners_world_m[middle][profiles.corner_ok[middle]]
    near = np.linalg.norm(corners[:, 1:] - np.asarray(where_yz), axis=1) <= reach_m
    return corners[near]


# -- slices ----------------------------------------------------------------------------------


@pytest.mark.parametrize("angle_deg", [90, 135])
@pytest.mark.parametrize("concave", [False, True])
def test_a_dihedral_edge_is_a_corner_of_every_slice_on_the_true_edge(angle_deg, concave):
    """Two faces meeting along the x axis at ``angle_deg`` with 0.3 mm noise: every slice's
    corner lies on the axis to a fraction of the noise."""
    rng = np.random.default_rng(angle_deg + concave)
    a = np.radians(angle_deg)
    down = 1.0 if concave else -1.0
    far = 0.012 * np.array([np.cos(a), down * np.sin(a)])
    scan, _ = extruded([(0.015, 0.0), (0.0, 0.0), tuple(far)], rng, sigma_m=0.3 * MM)
    path = along_x(0.0008, 0.0008 * down)  # the hand's error off the edge
    model = model_for(scan, path)
    corners = corners_near(model, (0.0, 0.0))
    stations = np.count_nonzero(np.abs(model.profiles.origin_m[:, 0]) < 0.012)
    assert len(corners) >= stations  # one corner per slice (at least)
    off = np.linalg.norm(corners[:, 1:], axis=1)
    assert np.median(off) < 0.15 * MM and off.max() < 0.35 * MM


def test_a_chamfer_is_two_corners_and_its_faces_meeting_in_the_air_is_none():
    """A box edge with a 4 mm chamfer: the slices show its two corners, not the corner where
    the box's two faces would meet (in the air, cut off by the chamfer)."""
    rng = np.random.default_rng(7)
    leg = 0.004 / np.sqrt(2)
    profile = [(0.015, 0.0), (leg, 0.0), (0.0, -leg), (0.0, -0.012)]
    scan, _ = extruded(profile, rng, sigma_m=0.1 * MM, spacing_m=0.0005)
    model = model_for(scan, along_x(0.0, 0.0))
    for corner in [(leg, 0.0), (0.0, -leg)]:
        found = corners_near(model, corner, reach_m=0.5 * MM)
        assert len(found) >= 8, corner  # most of the 11 middle slices
        off = np.linalg.norm(found[:, 1:] - corner, axis=1)
        assert np.median(off) < 0.2 * MM, corner
    # The faces' meeting survives in a slice or two where the chamfer's line is too short.
    assert len(corners_near(model, (0.0, 0.0), reach_m=1.0 * MM)) <= 2


def test_a_narrow_chamfer_is_one_edge_where_its_faces_meet():
    """A 2 mm chamfer is narrower than a slice can hold as a face of its own: one edge, where
    the two faces meet (1 mm off the chamfer's middle; a documented limit)."""
    rng = np.random.default_rng(7)
    leg = 0.002 / np.sqrt(2)
    profile = [(0.015, 0.0), (leg, 0.0), (0.0, -leg), (0.0, -0.012)]
    scan, _ = extruded(profile, rng, sigma_m=0.1 * MM, spacing_m=0.0005)
    model = model_for(scan, along_x(0.0, 0.0))
    found = corners_near(model, (0.0, 0.0), reach_m=0.5 * MM)
    assert len(found) >= 10
    assert len(corners_near(model, (leg, 0.0), reach_m=0.4 * MM)) == 0


def test_the_slices_move_with_the_part():
    """A rigid motion of the scan and the path moves every corner with it (the slices' axes
    come from the points, not the frame)."""
    rng = np.random.default_rng(8)
    scan, _ = extruded([(0.015, 0.0), (0.0, 0.0), (0.0, -0.012)], rng, sigma_m=0.2 * MM)
    path = along_x(0.0005, -0.0005)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.4, -0.9, 0.3]).as_matrix()
    T[:3, 3] = [0.3, -0.1, 0.6]
    params = replace(ReconParams(), voxel_m=0.0)
    here = build_scan_model(Scan(points_m=scan), path, params).profiles
    there = build_scan_model(
        Scan(points_m=apply_transform(T, scan)), apply_transform(T, path), params
    ).profiles
    assert np.array_equal(here.corner_ok, there.corner_ok)
    moved = apply_transform(T, here.corners_world_m[here.corner_ok])
    assert np.abs(moved - there.corners_world_m[there.corner_ok]).max() < 1e-6


# -- the edge a segment follows: a thin wall ---------------------------------------------------


def thin_wall(rng, thickness_m=0.003, height_m=0.010):
    """A wall standing on a floor, its top's two convex edges ``thickness_m`` apart, at
    y = 0 and y = thickness_m, z = height_m."""
    t, h = thickness_m, height_m
    profile = [(-0.015, 0.0), (0.0, 0.0), (0.0, h), (t, h), (t, 0.0), (t + 0.015, 0.0)]
    # Longer than the path by more than the slices reach past its ends (12 mm): the scan's own
    # end is not what is tested here.
    return extruded(profile, rng, sigma_m=0.25 * MM, spacing_m=0.0006, length_m=0.08)


@pytest.mark.parametrize("edge_y", [0.0, 0.003])
def test_on_a_thin_wall_the_whole_segment_follows_the_edge_the_trace_is_on(edge_y):
    """Two edges 3 mm apart; the trace follows one with the hand's drift taking it 1.2 mm
    towards the other: every point ends on the traced edge, none hops to the other one.

    The wall's top is 3 mm wide, so its direction in each slice is known only so well: the
    corners sit up to 0.4 mm off along the wall (measured), within the 0.5 mm aim."""
    rng = np.random.default_rng(11)
    scan, _ = thin_wall(rng)
    path = along_x(edge_y, 0.010)
    x = path[:, 0]
    towards = 0.0015 - edge_y  # towards the wall's middle, and past it a little
    drift = 1.2 * MM * np.sign(towards) * (0.5 + 0.5 * np.sin(x / 0.008))
    traced = path + np.column_stack([np.zeros_like(x), drift, np.zeros_like(x)])
    traced += rng.normal(0.0, 0.1 * MM, traced.shape)
    out = reconstruct(traced, Scan(points_m=scan), params=replace(ReconParams(), register=False))
    error = np.linalg.norm(out.points_m[:, 1:] - [edge_y, 0.010], axis=1)
    assert np.all(out.mode == PointMode.EDGE)
    assert np.median(error) < 0.35 * MM and error.max() < 0.5 * MM
    # Across the wall (towards the other edge), to a tenth of a millimetre.
    assert np.abs(out.points_m[:, 1] - edge_y).max() < 0.15 * MM


# -- one face ---------------------------------------------------------------------------------


def step(rng):
    """A floor at z = 0 and a 3 mm step up at y = 0 (0.3 mm noise)."""
    profile = [(-0.015, 0.0), (0.0, 0.0), (0.0, 0.003), (0.015, 0.003)]
    scan, _ = extruded(profile, rng, sigma_m=0.3 * MM)
    return scan


@pytest.mark.parametrize("seed", [12, 13, 14])
@pytest.mark.parametrize("offset_m", [0.0025, 0.004])
def test_beside_a_step_s_foot_the_height_comes_from_the_floor(seed, offset_m):
    """Points on the floor a few millimetres from a 3 mm step up (a wall's foot: the concave
    side) take the floor's height, not a blend with the step's top."""
    scan = step(np.random.default_rng(seed))
    centres = along_x(-offset_m, 0.0008)
    model = model_for(scan, centres)
    fit = fit_faces(centres, model, radius_m=0.008, neighbours=400, scale_m=0.004)
    # Where the fit grew over the riser instead, it says so (the point then keeps the trace).
    assert np.mean(fit.ok) >= 0.9
    assert np.abs(fit.target_m[fit.ok, 2]).max() < 0.25 * MM
    # The floor's normal, not the step's.
    assert np.abs(fit.normal[fit.ok, 2]).min() > np.cos(np.radians(25))


@pytest.mark.xfail(
    strict=True,
    reason="known defect: on the top of a low step, within a few millimetres of its convex "
    "edge, the face under a point can be misjudged (a slice's short, tilted line over the "
    "3 mm riser is taken for it): up to 1.9 mm off on one of three scans (docs/real-parts.md)",
)
def test_beside_a_step_s_edge_the_height_comes_from_the_top():
    for seed in (12, 13, 14):
        scan = step(np.random.default_rng(seed))
        for offset_m in (0.0025, 0.003, 0.004):
            centres = along_x(offset_m, 0.0038)
            model = model_for(scan, centres)
            fit = fit_faces(centres, model, radius_m=0.008, neighbours=400, scale_m=0.004)
            assert fit.ok.all()
            assert np.abs(fit.target_m[:, 2] - 0.003).max() < 0.25 * MM, (seed, offset_m)


# -- lift-offs --------------------------------------------------------------------------------


def plate_model(points):
    return SimpleNamespace(dense_tree=cKDTree(points))


def test_a_lift_off_s_way_back_may_cross_a_small_gap_in_the_scan_but_not_a_step():
    """On one face the scan runs along the way from the flank to the lifted point's target even
    where a random scan leaves a gap of a millimetre; across a 5 mm step it does not."""
    rng = np.random.default_rng(13)
    plate = np.column_stack(
        [rng.uniform(-0.03, 0.03, 6000), rng.uniform(-0.01, 0.01, 6000), np.zeros(6000)]
    )
    start, end = np.array([[-0.02, 0.0, 0.0]]), np.array([[0.02, 0.0, 0.0]])
    # A gap of 1.6 mm around x = 0 (a little more than the tube's 1.8 mm radius reaches over).
    gap = plate[np.linalg.norm(plate[:, :2], axis=1) > 0.0026]
    assert anchored._scan_along(start, end, plate_model(gap))[0]
    # A 5 mm step at x = 0: the lower level on one side, the upper on the other.
    step = plate.copy()
    step[step[:, 0] > 0, 2] += 0.005
    end_up = np.array([[0.02, 0.0, 0.005]])
    assert not anchored._scan_along(start, end_up, plate_model(step))[0]
    # A hole longer than the allowed gap is not crossed either.
    hole = plate[np.abs(plate[:, 0]) > 0.004]
    assert not anchored._scan_along(start, end, plate_model(hole))[0]


def test_a_lift_off_is_followed_down_only_through_free_air():
    """The way down from a lifted point to its target is clear over an open plate, and blocked
    when the scan has material between (the point is under an overhang, not lifted)."""
    rng = np.random.default_rng(14)
    plate = np.column_stack(
        [rng.uniform(-0.02, 0.02, 4000), rng.uniform(-0.02, 0.02, 4000), np.zeros(4000)]
    )
    lifted = np.array([[0.0, 0.0, 0.006]])
    target = np.array([[0.0, 0.0, 0.0]])
    assert anchored._in_free_air(lifted, target, plate_model(plate))[0]
    shelf = np.column_stack(
        [rng.uniform(-0.005, 0.005, 400), rng.uniform(-0.005, 0.005, 400), np.full(400, 0.003)]
    )
    assert not anchored._in_free_air(lifted, target, plate_model(np.concatenate([plate, shelf])))[0]


def test_faces_fitted_in_parts_are_the_whole_fit_to_the_bit():
    """fit_faces bounds its memory by fitting FIT_CHUNK points at a time: each point's fit is
    its own, so the parts give the very numbers of one fit over all the points."""
    from dataclasses import fields

    from recon import faces

    scan = step(np.random.default_rng(15))
    spacing = {"spacing_m": 0.0002}  # 201 points each
    centres = np.concatenate(
        [along_x(-0.003, 0.0008, **spacing), along_x(0.004, 0.0041, **spacing)]
    )
    model = model_for(scan, centres)
    assert len(centres) > faces.FIT_CHUNK
    kwargs = {"radius_m": 0.008, "neighbours": 400, "scale_m": 0.004}
    in_parts = fit_faces(centres, model, **kwargs)
    whole = faces._fit_faces_part(centres, model, **kwargs)
    for field in fields(faces.FaceFit):
        np.testing.assert_array_equal(
            getattr(in_parts, field.name), getattr(whole, field.name), err_msg=field.name
        )
