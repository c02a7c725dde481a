"""Tool orientations along a path.

The tool frame follows the usual convention of UR tools: its z-axis is the tool axis, pointing
from the flange towards the workpiece; its x-axis is the direction of travel (made perpendicular
to z); y completes a right-handed frame. Three sources, in order of preference:

* the scan: z is minus the surface normal (at an edge, minus the bisector of the two faces'
  normals), normals turned towards the side the tool comes from (``approach``);
* the pen: z is the tracked pen's z-axis (the pen frame's axis towards its tip);
* fixed: z points along ``-approach`` (by default down the base frame's z-axis).

Lead and tilt then lean the tool: lead rotates it about its y-axis (positive: the tool axis leans
towards the direction of travel, the tip ahead of the flange, a push angle), tilt about the
direction of travel.

Orientations are smoothed along the path on the sphere of tool axes (a Gaussian-weighted mean of
unit vectors, renormalised) before the frame is built, never per Euler angle: 0.4 degrees of
noise on the tool axis is enough to make a time-optimal parametrisation crawl at a few mm/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.edge_lines import fit_edge_lines
from recon.fitting import gather, weighted_pca
from recon.paths import ToolPath
from recon.results import PointMode
from recon.scan_model import ScanModel

#: Scan points per local surface-normal fit.
NORMAL_NEIGHBOURS = 64
#: The direction of travel is always smoothed over at least this much path (metres).
MIN_HEADING_SMOOTH_M = 0.005


@dataclass(frozen=True)
class ScanNormals:
    """Outward surface directions at path points.

    Attributes
    ----------
    normals : ndarray of shape (N, 3)
        Unit vectors pointing away from the material, towards the tool; zero where unknown.
    known : ndarray of shape (N,), bool
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the scan was looked up with, when the normals are in the tracker frame
        and came from a scan (see :func:`recon.plan.normals_from_scan`).
    """

    normals: FloatArray
    known: NDArray[np.bool_]
    T_scan_tracker: FloatArray | None = None


def scan_normals(
    points_m: FloatArray,
    model: ScanModel,
    *,
    mode: NDArray[np.int8],
    approach: FloatArray,
    radius_m: float,
) -> ScanNormals:
    """Surface normals (or edge bisectors) of the scan at the path's points.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3), metres
        Path points, in the frame of ``model`` (the scan frame).
    model : ScanModel
        Its trees are reused; the two-face fits at edges use its ``edge_fit_radius_m``.
    mode : ndarray of shape (N,)
        :class:`PointMode` of each point: edge points get the bisector of the two faces, surface
        points the normal of a local plane fit, path-only points none.
    approach : ndarray of shape (3,)
        Direction the tool comes from, in the same frame: normals are turned to face it.
    radius_m : float
        Neighbourhood radius of the plane fits.

    Returns
    -------
    ScanNormals
    """
    points = np.asarray(points_m, dtype=np.float64)
    approach = np.asarray(approach, dtype=np.float64) / np.linalg.norm(approach)
    normals = np.zeros_like(points)
    known = np.zeros(len(points), dtype=bool)
    on_edge = mode == PointMode.EDGE
    on_surface = mode == PointMode.SURFACE
    if np.any(on_edge):
        fit = fit_edge_lines(
            points[on_edge], model.features, radius_m=model.edge_fit_radius_m, trees=model.trees
        )
        normals[on_edge] = fit.bisector
        known[on_edge] = fit.ok
    if np.any(on_surface):
        dense = model.features.dense_points_m
        k = min(NORMAL_NEIGHBOURS, len(dense))
        dist, idx = model.dense_tree.query(
            points[on_surface], k=k, distance_upper_bound=radius_m, workers=-1
        )
        if k == 1:
            dist, idx = dist[:, None], idx[:, None]
        present = np.isfinite(dist)
        pca = weighted_pca(gather(dense, idx, fill_index=len(dense)), present.astype(float))
        normals[on_surface] = pca.axes[:, :, 2]
        known[on_surface] = present.sum(axis=1) >= 6
    flip = normals @ approach < 0
    normals[flip] *= -1
    normals[~known] = 0.0
    return ScanNormals(normals=normals, known=known)


def fill_along_path(vectors: FloatArray, known: NDArray[np.bool_]) -> FloatArray:
    """Unknown unit vectors replaced by the nearest known one along the path.

    Raises
    ------
    ValueError
        No vector is known.
    """
    if not np.any(known):
        raise ValueError("no known vector to fill from")
    index = np.arange(len(vectors))
    known_index = index[known]
    nearest = known_index[np.clip(np.searchsorted(known_index, index), 0, len(known_index) - 1)]
    before = known_index[np.clip(np.searchsorted(known_index, index) - 1, 0, len(known_index) - 1)]
    use_before = np.abs(before - index) < np.abs(nearest - index)
    source = np.where(use_before, before, nearest)
    return np.where(known[:, None], vectors, vectors[source])


def smooth_directions(vectors: FloatArray, *, sigma_points: float) -> FloatArray:
    """Gaussian-smoothed unit vectors along a path, renormalised (a mean on the sphere).

    Parameters
    ----------
    vectors : ndarray of shape (N, 3)
        Unit vectors.
    sigma_points : float
        Standard deviation of the Gaussian, in points; 0 returns the input.
    """
    if sigma_points <= 0 or len(vectors) < 3:
        return vectors
    smoothed = gaussian_filter1d(vectors, sigma_points, axis=0, mode="nearest")
    unit: FloatArray = smoothed / np.maximum(np.linalg.norm(smoothed, axis=1), 1e-12)[:, None]
    return unit


def _carried(x0: FloatArray, axis: FloatArray) -> FloatArray:
    """A direction perpendicular to each axis, starting at ``x0`` and carried from one axis to
    the next with the least turn (parallel transport: no twist about the axis).

    Parameters
    ----------
    x0 : ndarray of shape (3,)
        Perpendicular to ``axis[0]``.
    axis : ndarray of shape (N, 3)
        Unit tool axes.

    Returns
    -------
    ndarray of shape (N, 3)
    """
    out = np.empty_like(axis)
    x = np.asarray(x0, dtype=np.float64)
    for i, z in enumerate(axis):
        x = x - (x @ z) * z
        x /= np.linalg.norm(x)
        out[i] = x
    return out


def tool_path(
    points_m: FloatArray,
    *,
    normals: FloatArray | None = None,
    pen_xyzw: FloatArray | None = None,
    approach: FloatArray | tuple[float, float, float] = (0.0, 0.0, 1.0),
    lead_deg: float = 0.0,
    tilt_deg: float = 0.0,
    smooth_m: float = 0.01,
    heading: str = "travel",
) -> ToolPath:
    """Tool poses along a path.

    Parameters
    ----------
    points_m : ndarray of shape (N, 3)
        TCP positions, metres, in the frame the poses should be in (the robot base).
    normals : ndarray of shape (N, 3), optional
        Outward unit normals from the scan, same frame: the tool axis is minus these.
    pen_xyzw : ndarray of shape (N, 4), optional
        Pen orientations (scalar-last quaternions), same frame: the tool axis is the pen's z.
    approach : array_like of shape (3,)
        Where the tool comes from; the fixed tool axis is minus this.
    lead_deg, tilt_deg : float
        Lean of the tool about its y-axis (towards the direction of travel) and its x-axis.
    smooth_m : float
        Standard deviation, in metres of path, of the smoothing of the tool axis and the
        heading (the heading at least :data:`MIN_HEADING_SMOOTH_M`).
    heading : {"travel", "free"}
        The tool's x axis: along the direction of travel (a tool with a working direction:
        a knife, a dispenser's slot), or free about the tool axis for a round tool: the
        first point's travel direction carried along with the least turning about the axis
        (parallel transport), so that wrist 3 stays still where the axis does (a three-turn
        circle needed 1074 deg of joint 6 with the travel heading).

    Returns
    -------
    ToolPath

    Raises
    ------
    ValueError
        Bad shapes, or fewer than two points.
    """
    points = np.asarray(points_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
        raise ValueError(f"points_m must have shape (N >= 2, 3), got {points.shape}")
    approach = np.asarray(approach, dtype=np.float64)
    approach = approach / np.linalg.norm(approach)
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))))
    spacing = arc[-1] / max(len(points) - 1, 1)
    if normals is not None:
        axis, source = -np.asarray(normals, dtype=np.float64), "scan"
    elif pen_xyzw is not None:
        axis, source = Rotation.from_quat(pen_xyzw).apply([0.0, 0.0, 1.0]), "pen"
    else:
        axis, source = np.tile(-approach, (len(points), 1)), "fixed"
    if axis.shape != points.shape:
        raise ValueError(f"orientation source has shape {axis.shape} for {len(points)} points")
    axis = smooth_directions(axis, sigma_points=smooth_m / max(spacing, 1e-12))

    # The heading also drives a joint (6, about the tool axis): finite differences of a path
    # sampled every millimetre carry degrees of noise, so it is smoothed like the axis.
    travel = np.gradient(points, axis=0)
    travel /= np.maximum(np.linalg.norm(travel, axis=1), 1e-12)[:, None]
    travel = smooth_directions(travel, sigma_points=max(smooth_m, MIN_HEADING_SMOOTH_M) / spacing)
    x = travel - np.einsum("ni,ni->n", travel, axis)[:, None] * axis
    norm = np.linalg.norm(x, axis=1)
    # Where travel runs along the tool axis the heading is undefined: keep the neighbour's.
    good = norm > 1e-9
    if not np.any(good):
        raise ValueError("the path runs along the tool axis everywhere; no heading is defined")
    x = fill_along_path(np.where(good[:, None], x / np.where(good, norm, 1.0)[:, None], 0.0), good)
    if heading == "free":
        x = _carried(x[0], axis)
    elif heading != "travel":
        raise ValueError(f"heading must be 'travel' or 'free', got {heading!r}")
    x = x - np.einsum("ni,ni->n", x, axis)[:, None] * axis
    x /= np.linalg.norm(x, axis=1)[:, None]
    y = np.cross(axis, x)
    frames = Rotation.from_matrix(np.stack([x, y, axis], axis=2))
    lean = Rotation.from_euler("YX", [np.radians(lead_deg), np.radians(tilt_deg)])
    rotations = frames * lean
    return ToolPath(
        points_m=points,
        orientations_xyzw=rotations.as_quat(),
        arc_length_m=arc,
        source=source,
    )
