"""Surface structure of the scan near the path: crop, clean, normals, curvature, edge flags.

Curvature needs a scale. Surface variation ``l3 / (l1 + l2 + l3)`` of the local covariance is
computed in a fixed-radius ball on a cloud first averaged down to a voxel grid; with a fixed
number of nearest neighbours on a dense cloud the ball shrinks to the noise and nearly every point
looks like an edge.

The band of points flagged as edges is as wide as the curvature ball and its centroid lies inside
the corner, not on it: :mod:`recon.edge_lines` recovers the edge itself from the two faces, and
:mod:`recon.edges` thins the band to points on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.errors import NoOverlapError
from recon.fitting import symmetric_eig3
from recon.types import FloatArray

#: Surface variation never flags an edge below this: a noise-free plane has 0 and a 90-degree
#: edge about 0.1 at its crest (measured on the synthetic scenes of recon.scenes).
EDGE_CURVATURE_FLOOR = 0.03


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
