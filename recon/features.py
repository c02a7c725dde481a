"""Surface structure of the scan near the path: crop, clean, normals, curvature, edges.

Curvature needs a scale. Surface variation ``l3 / (l1 + l2 + l3)`` of the local covariance is
computed in a fixed-radius ball on a cloud first averaged down to a voxel grid; with a fixed
number of nearest neighbours on a dense cloud the ball shrinks to the noise and nearly every point
looks like an edge.

The band of points flagged as edges is as wide as the curvature ball and its centroid lies inside
the corner, not on it. :func:`fit_edge_lines` recovers the edge itself as the intersection of the
two faces fitted on either side, which is what the thinned edge points used by registration and
reconstruction are made of.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.errors import NoOverlapError
from recon.fitting import fit_linear, gather, symmetric_eig3, weighted_pca
from recon.types import FloatArray

#: Surface variation never flags an edge below this: a noise-free plane has 0 and a 90-degree
#: edge about 0.1 at its crest (measured on the synthetic scenes of recon.scenes).
EDGE_CURVATURE_FLOOR = 0.03
#: Lower bound of the face-fit noise level, as a fraction of the ball radius (see
#: :func:`fit_edge_lines`).
SIGMA_FLOOR_FRACTION = 0.01
#: Dense points per edge-fit ball: the edge is where two faces are extrapolated to meet, so its
#: precision grows with the points on each face (measured: 384 -> 768 at 1 mm scan noise took
#: the per-point scatter from 0.56 / 0.79 mm to 0.22 / 0.33 mm, radial / vertical).
EDGE_FIT_NEIGHBOURS = 768
#: Variance of an edge point from its line fit per unit of face variance over face points
#: (see :attr:`EdgePoints.variance_m2`).
EDGE_VARIANCE_FACTOR = 20.0
#: Two faces closer than this to coplanar do not define an edge line well enough to follow.
MIN_DIHEDRAL_DEG = 20.0


@dataclass(frozen=True)
class ScanFeatures:
    """The processed part of a scan near the path.

    Attributes
    ----------
    points_m : ndarray of shape (M, 3), metres
        The cropped scan averaged down to the voxel grid, outliers removed: the cloud the
        normals, curvature and edge flags belong to.
    dense_points_m : ndarray of shape (D, 3), metres
        The cropped scan at full resolution (capped in density), for the fits that locate edges
        and surfaces: averaging into voxels does not reduce noise comparable to the voxel size,
        so precision comes from fitting many raw points.
    normals : ndarray of shape (M, 3)
        Unit normals from the local covariance (sign arbitrary).
    curvature : ndarray of shape (M,)
        Surface variation in [0, 1/3].
    is_edge : ndarray of shape (M,), bool
    edge_threshold : float
        The surface variation that separated edges from faces.
    n_input, n_cropped, n_outliers : int
        Points in the whole scan, near the path, and removed as outliers.
    """

    points_m: FloatArray
    dense_points_m: FloatArray
    normals: FloatArray
    curvature: FloatArray
    is_edge: NDArray[np.bool_]
    edge_threshold: float
    n_input: int
    n_cropped: int
    n_outliers: int

    def transformed(self, T_new_old: FloatArray) -> ScanFeatures:
        """The same features in another frame (rigid transform; curvature is invariant)."""
        R, t = T_new_old[:3, :3], T_new_old[:3, 3]
        return replace(
            self,
            points_m=self.points_m @ R.T + t,
            dense_points_m=self.dense_points_m @ R.T + t,
            normals=self.normals @ R.T,
        )


def crop_near(points_m: FloatArray, path_m: FloatArray, radius_m: float) -> NDArray[np.bool_]:
    """Mask of ``points_m`` near ``path_m``: within ``radius_m``, give or take half of it.

    Points are kept whose cell (edge ``radius_m / 2``) lies within two cells of a cell the path
    passes through. That keeps everything within ``radius_m`` and nothing beyond about
    ``1.9 radius_m``, without a distance computation per scan point, which keeps a 1M-point
    scan cheap (the crop only bounds the work; the fits select their own neighbours).

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    path_m : ndarray of shape (N, 3)
    radius_m : float

    Returns
    -------
    ndarray of shape (M,), bool
    """
    cell = radius_m / 2.0
    lo = path_m.min(axis=0) - radius_m
    hi = path_m.max(axis=0) + radius_m
    in_box = np.all((points_m >= lo) & (points_m <= hi), axis=1)
    box_idx = np.flatnonzero(in_box)
    mask = np.zeros(len(points_m), dtype=bool)
    if len(box_idx) == 0:
        return mask
    dims = np.floor((hi - lo) / cell).astype(np.int64) + 5

    def key(cells: NDArray[np.int64]) -> NDArray[np.int64]:
        return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]

    path_cells = np.unique(np.floor((path_m - lo) / cell).astype(np.int64) + 2, axis=0)
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near_cells = np.unique(key((path_cells[:, None, :] + offsets[None]).reshape(-1, 3)))
    cand_cells = np.floor((points_m[box_idx] - lo) / cell).astype(np.int64) + 2
    mask[box_idx[np.isin(key(cand_cells), near_cells)]] = True
    return mask


def covariance_features(
    points_m: FloatArray, *, radius_m: float, max_neighbours: int = 48
) -> tuple[FloatArray, FloatArray]:
    """Normals and surface variation from the covariance of a fixed-radius ball at each point.

    Parameters
    ----------
    points_m : ndarray of shape (M, 3)
    radius_m : float
    max_neighbours : int
        Cap on the ball's population (Open3D's hybrid search). The cost grows with it (0.35 s
        for 32, 2.7 s for 256 on 150k points); a face of 2 mm voxels has about 50 points in an
        8 mm ball, so 48 truncates the ball little.

    Returns
    -------
    normals : ndarray of shape (M, 3)
    curvature : ndarray of shape (M,)
        ``l3 / (l1 + l2 + l3)``; 1/3 (isotropic, i.e. no surface) where a ball holds < 3 points.
    """
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_m))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius_m, max_neighbours))
    values, normals = symmetric_eig3(np.asarray(cloud.covariances))
    total = values.sum(axis=1)
    curvature = np.where(total > 0, values[:, 0] / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    return normals, np.clip(curvature, 0.0, 1.0 / 3.0)


def edge_threshold(curvature: FloatArray) -> float:
    """Surface variation above which a point counts as an edge point.

    Halfway between the face level (20th percentile: faces dominate any crop) and the crest
    level (98th percentile), and at least :data:`EDGE_CURVATURE_FLOOR`. A histogram split such as
    Otsu's needs two clear modes, which a noisy scan does not have: at 1 mm of noise faces
    read 0.04-0.08 and the crest of a right-angle edge 0.12, and Otsu's threshold fell on the
    crest itself, flagging a band too narrow for a path a few millimetres off to touch. A generous
    band costs little: the edge-line fits reject points that are not between two faces.

    Parameters
    ----------
    curvature : ndarray of shape (M,)

    Returns
    -------
    float
    """
    face, crest = np.percentile(np.asarray(curvature, dtype=np.float64), [20, 98])
    return float(max(EDGE_CURVATURE_FLOOR, 0.5 * (face + crest)))


def _thin_randomly(
    points_m: FloatArray, *, n_voxels: int, voxel_m: float, spacing_m: float, seed: int
) -> FloatArray:
    """Random subset of ``points_m`` with about one point per ``spacing_m`` squared of surface.

    The surface area is estimated from the number of occupied voxels (each holds about
    ``voxel_m`` squared of surface).
    """
    if voxel_m <= 0:
        return points_m
    area_m2 = n_voxels * voxel_m**2
    cap = int(area_m2 / spacing_m**2)
    if len(points_m) <= cap:
        return points_m
    rng = np.random.default_rng(seed)
    return points_m[np.sort(rng.choice(len(points_m), size=cap, replace=False))]


def prepare_scan(
    scan_points_m: FloatArray,
    path_m: FloatArray,
    *,
    crop_margin_m: float,
    voxel_m: float,
    curvature_radius_m: float,
    edge_curvature: float | None = None,
    dense_spacing_m: float = 0.001,
    outlier_neighbours: int = 8,
    outlier_std_ratio: float = 3.0,
    seed: int = 0,
) -> ScanFeatures:
    """Crop the scan to the path's neighbourhood, clean it and compute its structure.

    Parameters
    ----------
    scan_points_m : ndarray of shape (M, 3)
        The scan, in any frame.
    path_m : ndarray of shape (N, 3)
        The path, in the same frame (a rough alignment is enough: crop_margin_m covers the rest).
    crop_margin_m : float
        Points farther than this from the path are dropped before any other work.
    voxel_m : float
        Voxel edge for averaging the cropped cloud down (0: no averaging).
    curvature_radius_m : float
        Ball radius for normals and curvature.
    edge_curvature : float, optional
        Fixed edge threshold; default :func:`edge_threshold`.
    dense_spacing_m : float
        Typical spacing the dense cloud is randomly thinned to when the scan is denser (it
        bounds the cost of the fits on very dense scans; random, not averaged, keeps the noise
        unbiased).
    outlier_neighbours, outlier_std_ratio :
        Open3D statistical outlier removal on the voxel cloud: a point whose mean distance to its
        neighbours is more than this many standard deviations above the average is dropped.
        (The fits on the dense cloud reject outliers themselves.)
    seed : int
        Seed of the random thinning of the dense cloud, for reproducible results.

    Returns
    -------
    ScanFeatures

    Raises
    ------
    NoOverlapError
        Fewer than 20 scan points lie within ``crop_margin_m`` of the path.
    """
    near = crop_near(scan_points_m, path_m, crop_margin_m)
    n_cropped = int(np.count_nonzero(near))
    if n_cropped < 20:
        raise NoOverlapError(
            f"only {n_cropped} scan points lie within {crop_margin_m * 1000:.0f} mm of the path: "
            "check that path and scan are in the same frame and units, or give an initial "
            "calibration (T_scan_tracker) that brings them together"
        )
    cropped = scan_points_m[near]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cropped))
    if voxel_m > 0:
        cloud = cloud.voxel_down_sample(voxel_m)
    # The cheap crop keeps a superset that depends on the axes; the statistics below (outlier
    # removal, the edge threshold's percentiles) must not, so the voxel cloud is cut exactly.
    coarse = np.asarray(cloud.points)
    dist, _ = cKDTree(path_m).query(coarse, distance_upper_bound=crop_margin_m, workers=-1)
    cloud = cloud.select_by_index(np.flatnonzero(np.isfinite(dist)).tolist())
    n_before = len(cloud.points)
    if n_before > outlier_neighbours:
        cloud, _ = cloud.remove_statistical_outlier(outlier_neighbours, outlier_std_ratio)
    points = np.asarray(cloud.points).copy()
    normals, curvature = covariance_features(points, radius_m=curvature_radius_m)
    threshold = edge_curvature if edge_curvature is not None else edge_threshold(curvature)
    dense = _thin_randomly(
        cropped, n_voxels=n_before, voxel_m=voxel_m, spacing_m=dense_spacing_m, seed=seed
    )
    return ScanFeatures(
        points_m=points,
        dense_points_m=dense,
        normals=normals,
        curvature=curvature,
        is_edge=curvature > threshold,
        edge_threshold=float(threshold),
        n_input=len(scan_points_m),
        n_cropped=n_cropped,
        n_outliers=n_before - len(points),
    )


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


def _axial_two_means(normals: FloatArray, weights: FloatArray, iterations: int = 5):
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

    Returns
    -------
    EdgeLineFit
    """
    query_m = np.asarray(query_m, dtype=np.float64)
    if trees is None:
        trees = (cKDTree(features.points_m), cKDTree(features.dense_points_m))
    starts = range(0, len(query_m), chunk)
    # numpy's matmul and eigh release the GIL, so chunks run in parallel on threads.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        parts = list(
            pool.map(
                lambda i: _fit_edge_lines_chunk(
                    query_m[i : i + chunk], features, trees, radius_m, min_points
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


def _neighbours(tree: cKDTree, values: FloatArray, query_m: FloatArray, k: int, radius_m: float):
    """Up to ``k`` points of ``tree`` within ``radius_m``: (points (Q, k, 3), present (Q, k))."""
    k = min(k, tree.n)
    # One worker: the caller already runs chunks in parallel threads.
    dist, idx = tree.query(query_m, k=k, distance_upper_bound=radius_m, workers=1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    return gather(values, idx, fill_index=tree.n), np.isfinite(dist), idx


def _dots(vectors: FloatArray, direction: FloatArray) -> FloatArray:
    """Dot product of each of K vectors with one direction per row: (Q, K, 3), (Q, 3) -> (Q, K)."""
    return np.matmul(vectors, direction[..., None])[..., 0]


def _masked_median(values: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    """Median of each row of ``values`` over ``mask``; NaN for rows with nothing masked in."""
    filled = np.where(mask, values, np.inf)
    count = mask.sum(axis=1)
    ordered = np.sort(filled, axis=1)
    rows = np.arange(len(values))
    lo = ordered[rows, np.maximum((count - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(count // 2, 0)]
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def _fit_edge_lines_chunk(query_m, features, trees, radius_m, min_points) -> EdgeLineFit:
    coarse_tree, dense_tree = trees
    # Initial split: normals of the voxel cloud, off-crest points only.
    coarse, c_present, c_idx = _neighbours(coarse_tree, features.points_m, query_m, 128, radius_m)
    c_normals = gather(features.normals, c_idx, fill_index=coarse_tree.n)
    c_edge = gather(features.is_edge.astype(np.float64), c_idx, coarse_tree.n).astype(bool)
    flat = c_present & ~c_edge
    # Where the crest's band fills most of the ball, seed from every point rather than none.
    few = np.count_nonzero(flat, axis=1) < 4 * min_points
    flat = np.where(few[:, None], c_present, flat)
    second = _axial_two_means(c_normals, flat.astype(np.float64))
    pa = weighted_pca(coarse, (flat & ~second).astype(np.float64))
    pb = weighted_pca(coarse, (flat & second).astype(np.float64))

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


@dataclass(frozen=True)
class EdgePoints:
    """The thinned edge: points on the local edge lines, one per processed band point.

    Attributes
    ----------
    points_m : ndarray of shape (E, 3)
    directions : ndarray of shape (E, 3)
    residual_m : ndarray of shape (E,)
        Face-fit residual at each point (a noise level for alpha="auto").
    n_points : ndarray of shape (E,), int
        Points on the smaller face of each point's fit.
    """

    points_m: FloatArray
    directions: FloatArray
    residual_m: FloatArray
    n_points: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.points_m)

    @property
    def variance_m2(self) -> FloatArray:
        """Variance of each point's position from its line fit, ``K sigma^2 / n``.

        An edge point is where two noisy faces, fitted off the crest, are extrapolated to meet;
        the extrapolation multiplies the faces' noise. K = 20 is the factor measured on
        right-angle edges (per-fit scatter 0.22-0.33 mm at sigma = 1 mm with about 250 points
        per face).
        """
        return EDGE_VARIANCE_FACTOR * self.residual_m**2 / np.maximum(self.n_points, 1)

    def transformed(self, T_new_old: FloatArray) -> EdgePoints:
        R, t = T_new_old[:3, :3], T_new_old[:3, 3]
        return replace(self, points_m=self.points_m @ R.T + t, directions=self.directions @ R.T)


def _every(path_m: FloatArray, spacing_m: float) -> FloatArray:
    """Points of a polyline, one at each multiple of ``spacing_m`` of arc length (and the end)."""
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(path_m, axis=0), axis=1))))
    stations = np.append(np.arange(0.0, arc[-1], spacing_m), arc[-1])
    index = np.unique(np.searchsorted(arc, stations))
    return path_m[np.clip(index, 0, len(path_m) - 1)]


def thin_edges(
    features: ScanFeatures,
    near_m: FloatArray,
    *,
    radius_m: float,
    query_spacing_m: float,
    sample_spacing_m: float,
    trees: tuple[cKDTree, cKDTree] | None = None,
) -> EdgePoints:
    """Thin the band of edge points to the edge itself, along a path that follows it.

    Edge lines are fitted (:func:`fit_edge_lines`) at points of ``near_m`` spaced
    ``query_spacing_m`` apart, where the band of edge points is within reach; each fitted line
    is then sampled every ``sample_spacing_m`` over the stretch its query stands for. Querying
    along the path rather than at every band point avoids fitting the same stretch of edge many
    times over across the band's width, and sampling the local lines gives registration a
    continuous edge rather than isolated points.

    Parameters
    ----------
    features : ScanFeatures
    near_m : ndarray of shape (N, 3)
        An ordered path near the edges of interest (the trace, roughly aligned). Queries are
        taken along it by arc length, which does not depend on the frame (a voxel grid would).
    radius_m : float
        Neighbourhood radius of the two-face fits.
    query_spacing_m : float
        Distance between fits along ``near_m``.
    sample_spacing_m : float
        Spacing of the returned points along each local line.
    trees : (cKDTree, cKDTree), optional
        Trees over the voxel and dense clouds, to reuse (see :func:`fit_edge_lines`).

    Returns
    -------
    EdgePoints
        Possibly empty.
    """
    empty = EdgePoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
    if not np.any(features.is_edge) or len(near_m) == 0:
        return empty
    queries = _every(np.asarray(near_m, np.float64), query_spacing_m)
    # Only where the band of edge points is within half a ball: elsewhere the ball would reach a
    # distant edge, or none.
    band = features.points_m[features.is_edge]
    band_dist, _ = cKDTree(band).query(queries, distance_upper_bound=0.5 * radius_m, workers=-1)
    queries = queries[np.isfinite(band_dist)]
    if len(queries) == 0:
        return empty
    fit = fit_edge_lines(queries, features, radius_m=radius_m, trees=trees)
    moved = np.linalg.norm(fit.points_m - queries, axis=1)
    keep = fit.ok & (moved <= 0.5 * radius_m)
    if np.any(keep):
        # A fit spanning three faces (near a box corner) has a large residual: drop the worst.
        typical = np.median(fit.residual_m[keep])
        keep &= fit.residual_m <= 2.0 * typical + 1e-6
    if not np.any(keep):
        return empty
    half = 0.5 * query_spacing_m
    offsets = np.arange(-half, half + 1e-12, sample_spacing_m)
    centres, directions = fit.points_m[keep], fit.directions[keep]
    samples = centres[:, None, :] + offsets[None, :, None] * directions[:, None, :]
    count = len(offsets)
    return EdgePoints(
        points_m=samples.reshape(-1, 3),
        directions=np.repeat(directions, count, axis=0),
        residual_m=np.repeat(fit.residual_m[keep], count),
        n_points=np.repeat(fit.n_points[keep], count),
    )
