"""Local edge lines of a scan: the intersection of the two faces fitted on either side.

The band of points that curvature flags as an edge is as wide as the curvature ball and its
centroid lies inside the corner. :func:`fit_edge_lines` finds the edge itself near each query
point: the faces are told apart by their normals, refitted on the dense cloud leaving out the
crest, and intersected in the plane perpendicular to the edge. Tool orientations at edges use the
faces' bisector from the same fit.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.features import ScanFeatures
from recon.fitting import PCA, fit_linear, gather, weighted_pca

#: Lower bound of the face-fit noise level, as a fraction of the ball radius (see
#: :func:`fit_edge_lines`).
SIGMA_FLOOR_FRACTION = 0.01
#: Dense points per edge-fit ball: the edge is where two faces are extrapolated to meet, so its
#: precision grows with the points on each face (measured: 384 -> 768 at 1 mm scan noise took
#: the per-point scatter from 0.56 / 0.79 mm to 0.22 / 0.33 mm, radial / vertical).
EDGE_FIT_NEIGHBOURS = 768
#: Two faces closer than this to coplanar do not define an edge line well enough to follow.
MIN_DIHEDRAL_DEG = 20.0


@dataclass(frozen=True)
class EdgeLineFit:
    """Local edge lines: the intersection of the two faces around each query point.

    Attributes
    ----------
    points_m : ndarray of shape (Q, 3)
        The point of the local edge line nearest to each query.
    directions : ndarray of shape (Q, 3)
        Unit direction of the line (sign arbitrary).
    residual_m : ndarray of shape (Q,)
        RMS distance of the neighbourhood to its two fitted planes.
    n_points : ndarray of shape (Q,), int
        Points on the smaller of the two faces.
    dihedral_deg : ndarray of shape (Q,)
        Angle between the two face normals (0: coplanar, 90: a right-angle edge).
    ok : ndarray of shape (Q,), bool
        Both faces well populated and far enough from coplanar for the line to be defined.
    bisector : ndarray of shape (Q, 3)
        Unit bisector of the faces' normals, each turned away from the other face: the outward
        direction of a convex edge, the inward one of a concave edge (a caller that knows where
        the tool comes from picks the sign).
    """

    points_m: FloatArray
    directions: FloatArray
    residual_m: FloatArray
    n_points: NDArray[np.int64]
    dihedral_deg: FloatArray
    ok: NDArray[np.bool_]
    bisector: FloatArray


def _axial_two_means(
    normals: FloatArray, weights: FloatArray, iterations: int = 5
) -> NDArray[np.bool_]:
    """Split each neighbourhood's normals into two direction clusters, ignoring their signs.

    Normals are mapped to doubled angles in the plane of their two main directions, where n and
    -n coincide, and clustered there by 2-means seeded with the two mutually farthest points.

    Parameters
    ----------
    normals : ndarray of shape (Q, K, 3)
    weights : ndarray of shape (Q, K)

    Returns
    -------
    ndarray of shape (Q, K), bool
        True for the second cluster.
    """
    tensor = np.einsum("qk,qki,qkj->qij", weights, normals, normals)
    _, vectors = np.linalg.eigh(tensor)
    e1, e2 = vectors[:, :, 2], vectors[:, :, 1]
    u = np.einsum("qki,qi->qk", normals, e1)
    v = np.einsum("qki,qi->qk", normals, e2)
    phi = 2.0 * np.arctan2(v, u)
    z = np.stack([np.cos(phi), np.sin(phi)], axis=-1)  # (Q, K, 2)
    valid = weights > 0
    mean = np.einsum("qk,qkc->qc", weights, z) / np.maximum(weights.sum(1), 1e-300)[:, None]
    # Seeds: the point farthest from the mean, then the point farthest from that one.
    far = np.where(valid, np.einsum("qkc,qkc->qk", z - mean[:, None], z - mean[:, None]), -1.0)
    seed_a = z[np.arange(len(z)), np.argmax(far, axis=1)]
    far_b = np.where(valid, np.einsum("qkc,qkc->qk", z - seed_a[:, None], z - seed_a[:, None]), -1)
    seed_b = z[np.arange(len(z)), np.argmax(far_b, axis=1)]
    label = np.zeros(weights.shape, dtype=bool)
    for _ in range(iterations):
        da = np.einsum("qkc,qkc->qk", z - seed_a[:, None], z - seed_a[:, None])
        db = np.einsum("qkc,qkc->qk", z - seed_b[:, None], z - seed_b[:, None])
        label = db < da
        wa = weights * ~label
        wb = weights * label
        seed_a = np.einsum("qk,qkc->qc", wa, z) / np.maximum(wa.sum(1), 1e-300)[:, None]
        seed_b = np.einsum("qk,qkc->qc", wb, z) / np.maximum(wb.sum(1), 1e-300)[:, None]
    return label


def _cross_section_corner(
    query_m: FloatArray,
    neighbours: FloatArray,
    on_a: NDArray[np.bool_],
    on_b: NDArray[np.bool_],
    normal_a: FloatArray,
    normal_b: FloatArray,
    direction: FloatArray,
    ok: NDArray[np.bool_],
) -> FloatArray:
    """Where the two faces meet in the plane through the query perpendicular to the edge.

    A plane fitted to a face that curves along the edge (the wall of a cylinder under its rim)
    sits inside the face by a third of the sagitta, about 0.4 mm for a 10 mm ball on a 50 mm
    radius. Each face is therefore refitted as ``w = a0 + a1 v + a2 u + a3 u^2 + a4 u v`` in its
    own frame (u along the edge from the query, v across the face, w along its normal); its
    trace in the plane u = 0 is the straight line ``w = a0 + a1 v``, and the edge point is where
    the two traces cross.

    Returns
    -------
    ndarray of shape (Q, 3)
        The edge point; the query itself where ``ok`` is False.
    """
    rel = neighbours - query_m[:, None, :]
    u = _dots(rel, direction)
    traces = []
    for on_face, normal in ((on_a, normal_a), (on_b, normal_b)):
        across = np.cross(direction, normal)
        v = _dots(rel, across)
        w = _dots(rel, normal)
        design = np.stack([np.ones_like(u), v, u, u * u, u * v], axis=-1)
        coef = fit_linear(design, w, on_face.astype(np.float64)).coef[:, :, 0]
        # The trace w = a0 + a1 v as a point and a direction in 3-D.
        traces.append((coef[:, 0, None] * normal, across + coef[:, 1, None] * normal))
    (pa, da), (pb, db) = traces
    # Closest approach of two (coplanar) lines pa + s da and pb + t db.
    d_ab = pb - pa
    a11, a12, a22 = (np.einsum("qi,qi->q", x, y) for x, y in ((da, da), (da, db), (db, db)))
    b1, b2 = np.einsum("qi,qi->q", da, d_ab), np.einsum("qi,qi->q", db, d_ab)
    det = a11 * a22 - a12 * a12
    det = np.where(ok & (np.abs(det) > 1e-12), det, 1.0)
    s = (b1 * a22 - b2 * a12) / det
    corner = query_m + pa + s[:, None] * da
    return np.where(ok[:, None], corner, query_m)


def fit_edge_lines(
    query_m: FloatArray,
    features: ScanFeatures,
    *,
    radius_m: float,
    trees: tuple[cKDTree, cKDTree] | None = None,
    min_points: int = 6,
    chunk: int = 256,
    seed_planes: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None,
) -> EdgeLineFit:
    """Fit the local edge line near each query point as the intersection of two faces.

    For each query: the voxel cloud's points within ``radius_m`` that are off the crest (low
    curvature, so their normals are reliable) are split into two faces by their normals. The
    dense cloud's points in the same ball are then assigned to the nearer face plane and the
    planes refitted, three times, leaving out the points close to both planes near the crest. The
    result is where the two faces cross in the plane through the query perpendicular to the edge
    (:func:`_cross_section_corner`).

    Parameters
    ----------
    query_m : ndarray of shape (Q, 3)
    features : ScanFeatures
    radius_m : float
        Neighbourhood radius; it must reach past the crest's band onto both faces.
    trees : (cKDTree, cKDTree), optional
        Trees over ``features.points_m`` and ``features.dense_points_m`` to reuse.
    min_points : int
        Fewest points each face needs.
    chunk : int
        Queries processed at once (bounds memory: a chunk holds chunk x 768 neighbours).
    seed_planes : (normal_a, point_a, normal_b, point_b), each of shape (Q, 3), optional
        The two faces to start from (e.g. the lines of a cross-section through the query, see
        :mod:`recon.profiles`), instead of splitting the ball's normals in two: which faces
        meet is then already decided, the fit only makes them precise.

    Returns
    -------
    EdgeLineFit
    """
    query_m = np.asarray(query_m, dtype=np.float64)
    if trees is None:
        trees = (cKDTree(features.points_m), cKDTree(features.dense_points_m))
    starts = range(0, len(query_m), chunk)

    def seeds_of(i: int) -> tuple[FloatArray, ...] | None:
        if seed_planes is None:
            return None
        return tuple(np.asarray(a, dtype=np.float64)[i : i + chunk] for a in seed_planes)

    # numpy's matmul and eigh release the GIL, so chunks run in parallel on threads.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        parts = list(
            pool.map(
                lambda i: _fit_edge_lines_chunk(
                    query_m[i : i + chunk], features, trees, radius_m, min_points, seeds_of(i)
                ),
                starts,
            )
        )
    if not parts:
        empty = np.zeros((0, 3))
        return EdgeLineFit(
            empty, empty, np.zeros(0), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool), empty
        )
    return EdgeLineFit(
        *(
            np.concatenate(arrays)
            for arrays in zip(
                *(
                    (
                        p.points_m,
                        p.directions,
                        p.residual_m,
                        p.n_points,
                        p.dihedral_deg,
                        p.ok,
                        p.bisector,
                    )
                    for p in parts
                ),
                strict=True,
            )
        )
    )


def _neighbours(
    tree: cKDTree, values: FloatArray, query_m: FloatArray, k: int, radius_m: float
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.int64]]:
    """Up to ``k`` points of ``tree`` within ``radius_m``: (points (Q, k, 3), present (Q, k))."""
    k = min(k, tree.n)
    # One worker: the caller already runs chunks in parallel threads.
    dist, idx = tree.query(query_m, k=k, distance_upper_bound=radius_m, workers=1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    return gather(values, idx, fill_index=tree.n), np.isfinite(dist), idx


def _plane(normal: FloatArray, point: FloatArray) -> PCA:
    """A plane given by its normal and a point, as the PCA the fits use (normal third)."""
    normal = normal / np.linalg.norm(normal, axis=1)[:, None]
    helper = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    first = np.cross(helper, normal)
    first /= np.linalg.norm(first, axis=1)[:, None]
    second = np.cross(normal, first)
    axes = np.stack([first, second, normal], axis=2)
    b = len(normal)
    return PCA(mean=point, axes=axes, variances=np.zeros((b, 3)), weight=np.ones(b))


def _dots(vectors: FloatArray, direction: FloatArray) -> FloatArray:
    """Dot product of each of K vectors with one direction per row: (Q, K, 3), (Q, 3) -> (Q, K)."""
    dots: FloatArray = np.matmul(vectors, direction[..., None])[..., 0]
    return dots


def _masked_median(values: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    """Median of each row of ``values`` over ``mask``; NaN for rows with nothing masked in."""
    filled = np.where(mask, values, np.inf)
    count = mask.sum(axis=1)
    ordered = np.sort(filled, axis=1)
    rows = np.arange(len(values))
    lo = ordered[rows, np.maximum((count - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(count // 2, 0)]
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def _fit_edge_lines_chunk(
    query_m: FloatArray,
    features: ScanFeatures,
    trees: tuple[cKDTree, cKDTree],
    radius_m: float,
    min_points: int,
    seeds: tuple[FloatArray, ...] | None = None,
) -> EdgeLineFit:
    coarse_tree, dense_tree = trees
    if seeds is None:
        # Initial split: normals of the voxel cloud, off-crest points only.
        coarse, c_present, c_idx = _neighbours(
            coarse_tree, features.points_m, query_m, 128, radius_m
        )
        c_normals = gather(features.normals, c_idx, fill_index=coarse_tree.n)
        c_edge = gather(features.is_edge.astype(np.float64), c_idx, coarse_tree.n).astype(bool)
        flat = c_present & ~c_edge
        # Where the crest's band fills most of the ball, seed from every point rather than none.
        few = np.count_nonzero(flat, axis=1) < 4 * min_points
        flat = np.where(few[:, None], c_present, flat)
        second = _axial_two_means(c_normals, flat.astype(np.float64))
        pa = weighted_pca(coarse, (flat & ~second).astype(np.float64))
        pb = weighted_pca(coarse, (flat & second).astype(np.float64))
    else:
        pa, pb = (_plane(normal, point) for normal, point in (seeds[:2], seeds[2:]))

    dense, present, _ = _neighbours(
        dense_tree, features.dense_points_m, query_m, EDGE_FIT_NEIGHBOURS, radius_m
    )
    sigma = np.full((len(query_m), 1), np.inf)
    for _ in range(3):
        na, nb_normal = pa.axes[:, :, 2], pb.axes[:, :, 2]
        da = np.abs(_dots(dense - pa.mean[:, None], na))
        db = np.abs(_dots(dense - pb.mean[:, None], nb_normal))
        if np.isinf(sigma).all():
            # First pass: a noise level from the points' distances to the coarse planes.
            sigma = _masked_median(np.minimum(da, db) ** 2, present) / 0.4549  # chi2(1) median
            sigma = np.sqrt(np.where(np.isfinite(sigma), sigma, radius_m**2))[:, None]
            sigma = np.maximum(sigma, SIGMA_FLOOR_FRACTION * radius_m)
        # Assign each point to the nearer face, leaving out the ambiguous ones near the crest
        # (within 3 sigma of both planes): nearest-plane assignment would hand the noisy ones to
        # the wrong face and pull both planes into the corner. Far points are outliers.
        near_face = np.minimum(da, db) < 3.0 * sigma
        clear = np.maximum(da, db) >= 3.0 * sigma
        on_a = present & near_face & clear & (da <= db)
        on_b = present & near_face & clear & (db < da)
        pa = weighted_pca(dense, on_a.astype(np.float64))
        pb = weighted_pca(dense, on_b.astype(np.float64))
        member = on_a | on_b
        resid = np.where(on_a, da, np.where(on_b, db, 0.0))
        sigma = np.sqrt((resid**2).sum(1) / np.maximum(member.sum(1), 1))[:, None]
        # On a nearly noise-free scan the planes' residual is their misfit to curved faces, and
        # a 3-sigma band that thin would reject most of a curved face: floor it at 1 % of the ball.
        sigma = np.maximum(sigma, SIGMA_FLOOR_FRACTION * radius_m)

    na, nb_normal = pa.axes[:, :, 2], pb.axes[:, :, 2]
    count_a = np.count_nonzero(on_a, axis=1)
    count_b = np.count_nonzero(on_b, axis=1)
    cos_dihedral = np.abs(np.einsum("qi,qi->q", na, nb_normal))
    dihedral = np.degrees(np.arccos(np.clip(cos_dihedral, 0.0, 1.0)))
    direction = np.cross(na, nb_normal)
    norm = np.linalg.norm(direction, axis=1)
    ok = (
        (dihedral >= MIN_DIHEDRAL_DEG)
        & (np.minimum(count_a, count_b) >= min_points)
        & (norm > 1e-9)
    )
    direction = np.where(ok[:, None], direction / np.where(norm > 1e-9, norm, 1.0)[:, None], 0.0)
    direction[~ok] = (1.0, 0.0, 0.0)  # keeps the solves below regular; these rows are not used
    line_point = _cross_section_corner(query_m, dense, on_a, on_b, na, nb_normal, direction, ok)
    # Each face's normal turned away from the other face's points, then summed.
    away_a = -np.sign(np.einsum("qi,qi->q", na, pb.mean - line_point) + 1e-300)[:, None] * na
    away_b = -np.sign(np.einsum("qi,qi->q", nb_normal, pa.mean - line_point) + 1e-300)[:, None]
    bisector = away_a + away_b * nb_normal
    bisector /= np.maximum(np.linalg.norm(bisector, axis=1), 1e-12)[:, None]
    return EdgeLineFit(
        points_m=line_point,
        directions=direction,
        residual_m=sigma[:, 0],
        n_points=np.minimum(count_a, count_b),
        dihedral_deg=dihedral,
        ok=ok,
        bisector=bisector,
    )
