"""Scenes on real CAD parts: a part's true feature curve, a hand trace of it, and the part as a
depth camera held by a person scans it (:mod:`recon.scenes.depth_camera`).

The part and its curves come from outside (the corpus of real CAD models with annotated feature
curves: the tests and benchmarks load it and hand the arrays in; nothing here reads files). A
part is stood on a table the way it would rest (its thinnest extent upright) and every scene is
in that tracker frame. What a scene can trace (:data:`TRACE_KINDS`):

``edge``
    Along the feature curve itself (convex or concave).
``past_ends``
    The same, starting and stopping a millimetre or two past the feature's ends, as a hand does.
``face``
    On one of the two faces next to the feature, a few millimetres off it and parallel to it:
    along a wall (next to a concave edge) or near a face's border (next to a convex one). The
    scan then defines only the height; the feature next to it must not capture the path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.inputs import Scan
from recon.scenes.base import MM, Face, Scene, interpolated_curve
from recon.scenes.depth_camera import (
    DepthCamera,
    SimulatedScan,
    cpu_tensor,
    hand_held_views,
    scan_mesh,
)
from recon.scenes.noise import HandNoise, hand_trace, misalignment
from recon.transforms import apply_transform

if TYPE_CHECKING:
    import open3d as o3d

#: What a scene traces (see the module docstring).
TRACE_KINDS = ("edge", "past_ends", "face")
#: The hand of the real-parts benchmark: the synthetic scenes' (the paper's operator error),
#: tremor and a slow drift, about 0.7 mm per direction across the path.
REAL_PART_HAND = HandNoise()
#: Probes around a curve point (in the plane across the curve) tell the part's inside from the
#: air; this far from the curve (beyond the meshes' tessellation error, within their thinnest
#: ribs).
PROBE_RADIUS_M = 0.4 * MM
#: Probes per circle.
PROBE_COUNT = 72
#: A face trace runs this far from its feature, on the face.
FACE_OFFSET_M = 4 * MM
#: A past-the-ends trace starts and stops this far past the feature's ends.
OVERRUN_M = 1.5 * MM
#: A curve longer than this is scanned from three views (two otherwise).
LONG_CURVE_M = 0.15
#: Longest stretch of a curve that is traced (a sub-arc of a longer one).
MAX_TRACE_M = 0.25
#: A curve sample is seen when the scan has a point this close to it. A depth camera loses the
#: pixels along a silhouette and on faces seen nearly edge-on, so a convex edge seen from one side
#: has no return right on it; its faces still reach to within a millimetre or so.
VISIBLE_WITHIN_M = 1.5 * MM


@dataclass(frozen=True, eq=False)
class Part:
    """A CAD part with its true feature curves, tracker frame once stood on the table.

    Attributes
    ----------
    name : str
    vertices_m : ndarray of shape (V, 3)
    triangles : ndarray of shape (F, 3), int
    curves_m : tuple of ndarray of shape (K, 3)
        The true sharp feature curves (polylines; a closed one repeats its first point).
    """

    name: str
    vertices_m: FloatArray
    triangles: np.ndarray
    curves_m: tuple[FloatArray, ...]

    @cached_property
    def raycasting(self) -> o3d.t.geometry.RaycastingScene:
        """Open3D's ray-casting scene of the mesh (inside/outside and closest-point queries)."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            cpu_tensor(self.vertices_m),
            cpu_tensor(self.triangles, "uint32"),
        )
        return scene

    def inside(self, points_m: FloatArray) -> NDArray[np.bool_]:
        """Whether each point is inside the part (bool, shape (N,))."""
        query = cpu_tensor(np.asarray(points_m).reshape(-1, 3))
        occupied: NDArray[np.bool_] = self.raycasting.compute_occupancy(query).numpy().astype(bool)
        return occupied

    def distance(self, points_m: FloatArray) -> FloatArray:
        """Unsigned distance of each point to the part's surface (shape (N,), metres)."""
        query = cpu_tensor(np.asarray(points_m).reshape(-1, 3))
        distance: FloatArray = self.raycasting.compute_distance(query).numpy().astype(np.float64)
        return distance

    def closest(self, points_m: FloatArray) -> FloatArray:
        """The closest point of the surface to each point (shape (N, 3))."""
        query = cpu_tensor(np.asarray(points_m).reshape(-1, 3))
        found = self.raycasting.compute_closest_points(query)
        closest: FloatArray = found["points"].numpy().astype(np.float64)
        return closest


def stood_on_table(
    name: str, vertices_m: FloatArray, triangles: np.ndarray, curves_m: list[FloatArray]
) -> Part:
    """The part turned so that its thinnest extent is upright (z) and its bounding box centred
    over the origin on the table (z = 0 at its bottom): how it would rest to be worked on."""
    vertices_m = np.asarray(vertices_m, dtype=np.float64)
    extent = np.ptp(vertices_m, axis=0)
    order = np.argsort(extent)[::-1]  # longest along x, thinnest along z
    rotation = np.eye(3)[order]
    if np.linalg.det(rotation) < 0:
        rotation[1] *= -1
    centre = 0.5 * (vertices_m.min(axis=0) + vertices_m.max(axis=0))

    def moved(points: FloatArray) -> FloatArray:
        turned: FloatArray = (np.asarray(points, dtype=np.float64) - centre) @ rotation.T
        return turned

    v = moved(vertices_m)
    lift = np.array([0.0, 0.0, -v[:, 2].min()])
    return Part(
        name=name,
        vertices_m=v + lift,
        triangles=np.asarray(triangles, dtype=np.int64),
        curves_m=tuple(moved(c) + lift for c in curves_m),
    )


@dataclass(frozen=True)
class EdgeProfile:
    """The part's shape across a curve at each of its samples.

    Attributes
    ----------
    air_fraction : ndarray of shape (N,)
        Share of a small circle across the curve that is outside the part: 0.75 at a
        right-angle convex edge, 0.25 at a right-angle concave one, 0.5 on a flat face.
    bisector : ndarray of shape (N, 3)
        Unit direction into the air, halfway between the two faces.
    faces_along : ndarray of shape (N, 2, 3)
        The two faces' directions away from the curve, across it (unit).
    face_normals : ndarray of shape (N, 2, 3)
        The two faces' outward normals.
    """

    air_fraction: FloatArray
    bisector: FloatArray
    faces_along: FloatArray
    face_normals: FloatArray

    @property
    def concave(self) -> bool:
        """Whether the curve is an inside edge (more material than air around it, on median)."""
        return bool(np.median(self.air_fraction) < 0.5)

    @property
    def dihedral_deg(self) -> float:
        """Median angle between the two faces' normals (0 flat, 90 a right angle)."""
        fraction = np.median(self.air_fraction)
        return float(abs(360.0 * fraction - 180.0))


def edge_profile(part: Part, points_m: FloatArray) -> EdgeProfile:
    """:class:`EdgeProfile` of a curve, from inside/outside probes around each point.

    Parameters
    ----------
    part : Part
    points_m : ndarray of shape (N, 3)
        The curve, densely sampled, N >= 2.
    """
    points_m = np.asarray(points_m, dtype=np.float64)
    tangent = np.gradient(points_m, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1), 1e-12)[:, None]
    helper = np.where(np.abs(tangent[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    a = np.cross(tangent, helper)
    a /= np.linalg.norm(a, axis=1)[:, None]
    b = np.cross(tangent, a)
    angles = np.linspace(0.0, 2.0 * np.pi, PROBE_COUNT, endpoint=False)
    directions = (
        np.cos(angles)[None, :, None] * a[:, None, :] + np.sin(angles)[None, :, None] * b[:, None]
    )
    probes = points_m[:, None, :] + PROBE_RADIUS_M * directions
    air = ~part.inside(probes.reshape(-1, 3)).reshape(len(points_m), PROBE_COUNT)
    bisector = np.einsum("nk,nki->ni", air.astype(np.float64), directions)
    bisector /= np.maximum(np.linalg.norm(bisector, axis=1), 1e-12)[:, None]
    # The faces bound the run of air probes: where air turns to material going round, and back.
    turn_in = air & ~np.roll(air, -1, axis=1)  # last air probe before material
    turn_out = air & ~np.roll(air, 1, axis=1)  # first air probe after material
    faces_along = np.zeros((len(points_m), 2, 3))
    face_normals = np.zeros((len(points_m), 2, 3))
    rows = np.arange(len(points_m))
    for slot, boundary in enumerate((turn_in, turn_out)):
        k = np.argmax(boundary, axis=1)
        along = directions[rows, k]
        faces_along[:, slot] = along
        normal = np.cross(tangent, along)
        normal *= np.sign(np.einsum("ni,ni->n", normal, bisector) + 1e-12)[:, None]
        face_normals[:, slot] = normal
    return EdgeProfile(air.mean(axis=1), bisector, faces_along, face_normals)


def densified(polyline_m: FloatArray, spacing_m: float = 0.2 * MM) -> FloatArray:
    """A polyline resampled every ``spacing_m`` of arc length (its end point kept)."""
    steps = np.linalg.norm(np.diff(polyline_m, axis=0), axis=1)
    keep = np.r_[True, steps > 1e-12]
    polyline_m = polyline_m[keep]
    curve, length = interpolated_curve(polyline_m)
    return curve(np.r_[np.arange(0.0, length, spacing_m), length])


@dataclass(frozen=True, eq=False)
class CurveCase:
    """One curve of a part chosen for tracing, and what it is.

    Attributes
    ----------
    part : Part
    index : int
        Into ``part.curves_m``.
    truth_m : ndarray of shape (G, 3)
        The stretch that is traced, densely sampled (tracker frame).
    closed : bool
        The whole curve is a loop (its ends are not the feature's ends).
    profile : EdgeProfile
        Of ``truth_m``.
    """

    part: Part
    index: int
    truth_m: FloatArray
    closed: bool
    profile: EdgeProfile

    @property
    def name(self) -> str:
        return f"{self.part.name}#{self.index}"

    @property
    def length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.truth_m, axis=0), axis=1)))


def curve_case(part: Part, index: int, rng: np.random.Generator) -> CurveCase:
    """The stretch of curve ``index`` to trace: all of it, or a random stretch of
    :data:`MAX_TRACE_M` of a longer one (of a loop: at most 90 % of it, as a hand's trace of a
    loop stops short of where it started)."""
    polyline = np.asarray(part.curves_m[index], dtype=np.float64)
    closed = bool(np.linalg.norm(polyline[0] - polyline[-1]) < 1e-9)
    dense = densified(polyline)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))]
    length = float(arc[-1])
    span = min(MAX_TRACE_M, 0.9 * length if closed else length)
    start = float(rng.uniform(0.0, length - span)) if span < length else 0.0
    if closed and span < length:
        # A loop may be started anywhere: roll it so that the stretch does not wrap.
        shift = int(np.searchsorted(arc, start))
        dense = np.concatenate([dense[shift:-1], dense[: shift + 1]])
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))]
        start = 0.0
    keep = (arc >= start - 1e-12) & (arc <= start + span + 1e-12)
    truth = dense[keep]
    return CurveCase(part, index, truth, closed, edge_profile(part, truth))


def _extended(truth_m: FloatArray, overrun_m: float) -> FloatArray:
    """The curve run on straight past both ends by ``overrun_m`` (along its end tangents over
    the last 3 mm)."""
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth_m, axis=0), axis=1))]
    head_ref = truth_m[np.searchsorted(arc, min(3 * MM, arc[-1]))]
    tail_ref = truth_m[np.searchsorted(arc, max(arc[-1] - 3 * MM, 0.0))]
    head = truth_m[0] - head_ref
    tail = truth_m[-1] - tail_ref
    head /= np.linalg.norm(head)
    tail /= np.linalg.norm(tail)
    steps = np.arange(0.2 * MM, overrun_m + 1e-12, 0.2 * MM)
    return np.concatenate(
        [truth_m[0] + np.outer(steps[::-1], head), truth_m, truth_m[-1] + np.outer(steps, tail)]
    )


def face_truth(case: CurveCase, offset_m: float = FACE_OFFSET_M) -> tuple[FloatArray, int]:
    """The line ``offset_m`` off a curve on one of its faces (the more upward-facing one, which a
    hand would trace on), put on the part's surface.

    Returns
    -------
    truth_m : ndarray of shape (G, 3)
    face : int
        0 or 1, the face of :attr:`EdgeProfile.face_normals` it lies on.

    Raises
    ------
    ValueError
        The face is not a flat stretch that wide all along the curve (it ends, bends or meets
        another sharp feature within the offset): no line to trace there.
    """
    profile = case.profile
    upward = np.median(profile.face_normals[:, :, 2], axis=0)
    face = int(np.argmax(upward))
    # The line stops short of the curve's ends, where the face meets the next feature.
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(case.truth_m, axis=0), axis=1))]
    inner = (arc >= FACE_END_CLEARANCE_M) & (arc <= arc[-1] - FACE_END_CLEARANCE_M)
    if np.count_nonzero(inner) < 10:
        raise ValueError(f"{case.name}: too short for a face line")
    truth_m = case.truth_m[inner]
    moved = truth_m + offset_m * profile.faces_along[inner, face]
    on_surface = case.part.closest(moved)
    # Flat all the way out: the point offset straight along the face lies on the surface
    # (within the probes' angular resolution) ...
    off_plane = np.linalg.norm(on_surface - moved, axis=1)
    # ... and no other sharp feature comes near the line.
    others = [c for k, c in enumerate(case.part.curves_m) if k != case.index]
    clearance = np.inf
    if others:
        dense_others = np.concatenate([densified(np.asarray(c)) for c in others])
        clearance = float(cKDTree(dense_others).query(on_surface)[0].min())
    if off_plane.max() > FACE_FLATNESS_M or clearance < FACE_CLEARANCE_M:
        raise ValueError(
            f"{case.name}: its face is not flat for {offset_m * 1e3:.0f} mm all along it "
            f"(off plane by up to {off_plane.max() * 1e3:.1f} mm, another edge "
            f"{clearance * 1e3:.1f} mm from the line)"
        )
    return densified(on_surface), face


#: A face line stops this far short of its curve's ends ...
FACE_END_CLEARANCE_M = 6 * MM
#: ... must stay within this of the face's plane ...
FACE_FLATNESS_M = 0.6 * MM
#: ... and this far from every other sharp feature of the part.
FACE_CLEARANCE_M = 3 * MM


def visible_fraction(truth_m: FloatArray, scan_points_m: FloatArray, *, within_m: float) -> float:
    """Share of a curve's samples with a scan point within ``within_m`` (same frame)."""
    if len(scan_points_m) == 0:
        return 0.0
    distance, _ = cKDTree(scan_points_m).query(truth_m, distance_upper_bound=within_m)
    return float(np.mean(np.isfinite(distance)))


#: A face next to a curve counts as seen where at least :data:`FACE_SEEN_HITS` of the camera's
#: rays met it within this distance of the curve (on a wall only a few millimetres tall, nearer
#: to it than to the next face) ...
FACE_SEEN_WITHIN_M = 2.5 * MM
FACE_SEEN_HITS = 5
#: ... on triangles facing the face's way (within this angle), in its plane.
FACE_SEEN_ANGLE_DEG = 20.0


def faces_seen(case: CurveCase, scan: SimulatedScan) -> tuple[FloatArray, FloatArray]:
    """Whether the camera saw each of the two faces next to each sample of a curve.

    Judged on what the rays truly hit (not on the noisy returns): a face is seen at a sample
    when some ray met a triangle of that face (its normal within :data:`FACE_SEEN_ANGLE_DEG` of
    the face's, the hit within 0.2 mm of the face's plane) within :data:`FACE_SEEN_WITHIN_M` of
    the sample, :data:`FACE_SEEN_HITS` rays at least (a face seen at a glancing angle, by a
    handful of rays, shows where it is no better than the trace does).

    Parameters
    ----------
    case : CurveCase
    scan : SimulatedScan
        In the part's (tracker) frame.

    Returns
    -------
    both, either : ndarrays of shape (G,), bool
        Per truth sample: both faces seen (the scan defines the edge there), at least one.
    """
    g = len(case.truth_m)
    if len(scan.surface_m) == 0:
        return np.zeros(g, bool), np.zeros(g, bool)
    v, f = case.part.vertices_m, case.part.triangles
    tri_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    tri_normals /= np.maximum(np.linalg.norm(tri_normals, axis=1), 1e-300)[:, None]
    k = min(64, len(scan.surface_m))
    dist, idx = cKDTree(scan.surface_m).query(
        case.truth_m, k=k, distance_upper_bound=FACE_SEEN_WITHIN_M
    )
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    present = np.isfinite(dist)
    safe = np.where(present, idx, 0)
    hit_normals = tri_normals[scan.triangle[safe]]  # (G, K, 3)
    offset = scan.surface_m[safe] - case.truth_m[:, None]
    seen = []
    for face in (0, 1):
        normal = case.profile.face_normals[:, face]
        facing = np.abs(np.einsum("gki,gi->gk", hit_normals, normal)) >= np.cos(
            np.radians(FACE_SEEN_ANGLE_DEG)
        )
        in_plane = np.abs(np.einsum("gki,gi->gk", offset, normal)) <= 0.2 * MM
        seen.append(np.count_nonzero(present & facing & in_plane, axis=1) >= FACE_SEEN_HITS)
    return seen[0] & seen[1], seen[0] | seen[1]


def true_corners(
    truth_m: FloatArray, *, angle_deg: float = 40.0, chord_m: float = 2 * MM
) -> FloatArray:
    """Points where a curve turns by more than ``angle_deg`` over ``chord_m`` either side."""
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(truth_m, axis=0), axis=1))]
    before = np.searchsorted(arc, arc - chord_m).clip(0, len(arc) - 1)
    after = np.searchsorted(arc, arc + chord_m).clip(0, len(arc) - 1)
    d1 = truth_m - truth_m[before]
    d2 = truth_m[after] - truth_m
    n1 = np.linalg.norm(d1, axis=1)
    n2 = np.linalg.norm(d2, axis=1)
    ok = (n1 > 0.5 * chord_m) & (n2 > 0.5 * chord_m)
    cos = np.einsum("ni,ni->n", d1, d2) / np.maximum(n1 * n2, 1e-18)
    turning = ok & (cos < np.cos(np.radians(angle_deg)))
    corners = []
    for run in np.split(
        np.flatnonzero(turning), np.flatnonzero(np.diff(np.flatnonzero(turning)) > 1) + 1
    ):
        if len(run):
            corners.append(truth_m[run[np.argmin(cos[run])]])
    return np.asarray(corners).reshape(-1, 3)


def touch_faces(part: Part, *, inset_m: float = 4 * MM, count: int = 3) -> tuple[Face, ...]:
    """Up to ``count`` flat faces of the part an operator would touch to register the scanner:
    the largest planar regions that face up or sideways (not the bottom, which rests on the
    table), with mutually different normals (30 degrees at least), largest first.

    Each face samples points at least ``inset_m`` inside its borders.
    """
    v, f = part.vertices_m, part.triangles
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = 0.5 * np.linalg.norm(normals, axis=1)
    normals = normals / np.maximum(2 * area, 1e-300)[:, None]
    offset = np.einsum("fi,fi->f", normals, v[f[:, 0]])
    # Coplanar triangles: same normal (to about 1 degree) and plane offset (to 0.2 mm).
    key = np.column_stack([np.round(normals * 60), np.round(offset / (0.2 * MM))]).astype(np.int64)
    _, label = np.unique(key, axis=0, return_inverse=True)
    label = label.ravel()
    totals = np.bincount(label, weights=area)
    chosen: list[int] = []
    for region in np.argsort(totals)[::-1]:
        if totals[region] < (20 * MM) ** 2 or len(chosen) == count:
            break
        normal = normals[label == region][0]
        if normal[2] < -0.3:
            continue
        if any(abs(normal @ normals[label == c][0]) > np.cos(np.radians(30)) for c in chosen):
            continue
        chosen.append(int(region))
    faces: list[Face] = []
    for region in chosen:
        members = np.flatnonzero(label == region)
        faces.append(
            Face(f"face {len(faces)}", _face_sampler(part, members, normals, area, inset_m))
        )
    return tuple(faces)


def _face_sampler(
    part: Part,
    members: NDArray[np.intp],
    normals: FloatArray,
    area: FloatArray,
    inset_m: float,
) -> Callable[[np.random.Generator, int], tuple[FloatArray, FloatArray]]:
    v, f = part.vertices_m, part.triangles[members]
    normal = normals[members[0]]
    # The region's border: triangle edges used once within the region.
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    border = unique[counts == 1]
    t = np.linspace(0.0, 1.0, 50)[None, :, None]
    border_points = (v[border[:, 0]][:, None] * (1 - t) + v[border[:, 1]][:, None] * t).reshape(
        -1, 3
    )
    border_tree = cKDTree(border_points)
    weights = area[members] / area[members].sum()

    def sample(rng: np.random.Generator, n: int) -> tuple[FloatArray, FloatArray]:
        out = []
        for _ in range(200):
            tri = rng.choice(len(f), size=4 * n, p=weights)
            r1, r2 = rng.uniform(size=(2, 4 * n))
            flip = r1 + r2 > 1
            r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
            p = v[f[tri, 0]] + r1[:, None] * (v[f[tri, 1]] - v[f[tri, 0]])
            p += r2[:, None] * (v[f[tri, 2]] - v[f[tri, 0]])
            gap, _ = border_tree.query(p)
            out.extend(p[gap >= inset_m])
            if len(out) >= n:
                break
        if len(out) < n:
            raise ValueError(f"the face has no room {inset_m * 1e3:.0f} mm inside its borders")
        points = np.asarray(out[:n])
        return points, np.tile(normal, (n, 1))

    return sample


#: The random streams of a scene: the hand's trace, the camera's scan, the scanner's pose.
TRACE_STREAM, SCAN_STREAM, POSE_STREAM = 0, 1, 2


def scene_rng(case: CurveCase, seed: int, stream: int) -> np.random.Generator:
    """One random stream of a case's scene: the same scan for the same case and seed whether
    the whole scene is built or only its scan."""
    return np.random.default_rng([seed, case.index, sum(map(ord, case.part.name)), stream])


def scan_case(
    case: CurveCase,
    rng: np.random.Generator,
    *,
    views: int | None = None,
    camera: DepthCamera | None = None,
) -> SimulatedScan:
    """The part scanned by a hand-held depth camera pointed at a curve: one view at each part of
    the curve (its thirds, or halves), from the side it faces, as a person covers a feature they
    mean to program. Tracker frame.

    Parameters
    ----------
    case : CurveCase
    rng : numpy.random.Generator
    views : int, optional
        1 to 3; by default two, three for a curve longer than :data:`LONG_CURVE_M`.
    camera : DepthCamera, optional
    """
    count = views if views is not None else (3 if case.length_m > LONG_CURVE_M else 2)
    marks = ((np.arange(count) + 0.5) / count * (len(case.truth_m) - 1)).astype(int)
    window = max(1, len(case.truth_m) // (2 * count))
    bisector = case.profile.bisector
    facings = np.array([bisector[max(0, m - window) : m + window + 1].mean(axis=0) for m in marks])
    return scan_mesh(
        case.part.vertices_m,
        case.part.triangles,
        hand_held_views(case.truth_m[marks], rng, facings=facings),
        rng,
        camera=camera or DepthCamera(),
    )


def cad_scene(
    case: CurveCase,
    seed: int,
    *,
    kind: str = "edge",
    views: int | None = None,
    camera: DepthCamera | None = None,
    noise: HandNoise = REAL_PART_HAND,
    shift_m: float = 2 * MM,
    angle_deg: float = 1.0,
) -> Scene:
    """A hand trace of a part's curve and the part as a hand-held depth camera scans it.

    Parameters
    ----------
    case : CurveCase
    seed : int
        Trace, camera and misplacement are a deterministic function of it (and of the case).
    kind : {"edge", "past_ends", "face"}
        See the module docstring.
    views : int, optional
        Depth-camera views merged into the scan, 1 to 3: by default two, three for a curve
        longer than :data:`LONG_CURVE_M`.
    camera : DepthCamera, optional
    noise : HandNoise
    shift_m, angle_deg : float
        How far off the scanner's pose is known (the scan frame against the tracker frame).

    Returns
    -------
    Scene
        ``feature`` "edge" (edge, past_ends) or "surface" (face); ``surface_height`` is the
        distance to the part's surface; ``corners_m`` where the true curve turns sharply.
    """
    if kind not in TRACE_KINDS:
        raise ValueError(f"kind must be one of {', '.join(TRACE_KINDS)}, got {kind!r}")
    rng = scene_rng(case, seed, TRACE_STREAM)
    profile = case.profile
    truth = case.truth_m
    traced = truth
    if kind == "face":
        truth, face = face_truth(case)
        traced = truth
        up_vectors = np.repeat(profile.face_normals[:, face], 1, axis=0)
    else:
        up_vectors = profile.bisector
    if kind == "past_ends":
        traced = _extended(truth, OVERRUN_M)
    up_tree = cKDTree(case.truth_m)
    curve, length = interpolated_curve(traced)

    def up(s: FloatArray) -> FloatArray:
        _, nearest = up_tree.query(curve(s))
        vectors: FloatArray = up_vectors[np.minimum(nearest, len(up_vectors) - 1)]
        return vectors

    recording, _ = hand_trace(curve, length, rng, noise=noise, sample_spacing_m=1 * MM, up=up)
    scan = scan_case(case, scene_rng(case, seed, SCAN_STREAM), views=views, camera=camera)
    T = misalignment(scene_rng(case, seed, POSE_STREAM), shift_m=shift_m, angle_deg=angle_deg)
    feature = "surface" if kind == "face" else "edge"
    edge_kind = "concave" if profile.concave else "convex"
    return Scene(
        name=f"{case.name}:{kind}",
        description=f"{case.part.name}, curve {case.index} ({edge_kind}, "
        f"{profile.dihedral_deg:.0f} deg, {case.length_m * 1e3:.0f} mm), traced {kind}",
        truth_m=truth if kind != "past_ends" else _extended(truth, OVERRUN_M),
        recording=recording,
        scan=Scan(points_m=apply_transform(T, scan.points_m)),
        T_scan_tracker=T,
        feature=feature,
        surface_height=case.part.distance,
        curve=curve,
        length_m=length,
        noise=noise,
        faces=touch_faces(case.part),
        corners_m=true_corners(truth),
    )


@dataclass(frozen=True)
class CaseChoice:
    """What the choice of a part's traceable curves found.

    Attributes
    ----------
    case : CurveCase
    visible : float
        Share of the traced stretch with a scan point within :data:`VISIBLE_WITHIN_M`.
    defined : float
        Share of the traced stretch where the scan shows both faces next to it: where the scan
        defines the edge (elsewhere it shows one face, or none).
    """

    case: CurveCase
    visible: float
    defined: float

    @property
    def scan_defines_edge(self) -> bool:
        """Both faces seen along most of the curve (:data:`DEFINED_SHARE`)."""
        return self.defined >= DEFINED_SHARE


#: A curve whose two faces are both seen along this share of it is one the scan defines.
DEFINED_SHARE = 0.8


def traceable_cases(
    part: Part,
    *,
    per_part: int = 3,
    min_length_m: float = 40 * MM,
    min_visible: float = 0.8,
    min_dihedral_deg: float = 30.0,
    seed: int = 0,
) -> list[CaseChoice]:
    """The curves of a part an operator would trace after scanning it: long enough, a real
    crease (not a facet of a curved face), and seen by the camera pointed at them along most of
    their length. At most one concave curve, then the longest convex ones; at most ``per_part``.

    Visibility is judged on the scan of ``seed``'s scene (another seed points the camera a
    little differently): a scan point within :data:`VISIBLE_WITHIN_M` of most of the stretch.
    """
    found: list[CaseChoice] = []
    for index in range(len(part.curves_m)):
        case = curve_case(part, index, np.random.default_rng([seed, index]))
        if case.length_m < min_length_m or case.profile.dihedral_deg < min_dihedral_deg:
            continue
        scan = scan_case(case, scene_rng(case, seed, SCAN_STREAM))
        visible = visible_fraction(case.truth_m, scan.points_m, within_m=VISIBLE_WITHIN_M)
        if visible >= min_visible:
            both, _ = faces_seen(case, scan)
            found.append(CaseChoice(case, visible, float(np.mean(both))))
    concave = [c for c in found if c.case.profile.concave]
    convex = [c for c in found if not c.case.profile.concave]
    convex.sort(key=lambda c: -c.case.length_m)
    # Curves of the same length are usually copies of one feature (a pattern of holes): keep
    # one of each length.
    distinct: list[CaseChoice] = []
    for choice in concave[:1] + convex:
        if all(abs(choice.case.length_m - d.case.length_m) > 2 * MM for d in distinct):
            distinct.append(choice)
    return distinct[:per_part]
