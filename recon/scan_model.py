"""The scan model: the scan's structure near a path, in the scan frame, ready to be searched.

What every stage after registration looks the scan up in: the cropped and cleaned clouds with
normals, curvature and edge flags (:class:`recon.features.ScanFeatures`), the thinned edge
(:class:`recon.edges.EdgePoints`) and the search trees over them, built on first use.

A model is built once per reconstruction (:func:`build_scan_model`) and handed on with it, so that
planning finds the scan's normals at the reconstructed path without cropping, denoising or
registering again. It converts to plain numpy arrays and back (:meth:`ScanModel.to_arrays`,
:meth:`ScanModel.from_arrays`) for storage next to a reconstruction; the trees are rebuilt from
the arrays on first use.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.edges import EdgePoints, stations_along, thin_edges
from recon.features import ScanFeatures, ball_moments, prepare_scan
from recon.fitting import symmetric_eig3
from recon.inputs import Scan
from recon.profiles import Profiles, find_profiles
from recon.recon_params import ReconParams

#: The edge-line fits use balls this much larger than the curvature ball, to reach past the
#: crest's band of blended normals onto both faces with enough points on each.
EDGE_FIT_RADIUS_FACTOR = 2.0
#: Edge lines are fitted every this fraction of the fit radius along the path (4 mm for a 16 mm
#: ball): neighbouring fits share most of their points, so denser fits add cost, not information.
EDGE_QUERY_SPACING_FRACTION = 0.375
#: Spacing of the points sampled along each fitted edge line.
EDGE_SAMPLE_SPACING_M = 0.001
#: The small-scale normals of the dense points: from this many nearest dense points ...
FINE_NORMAL_NEIGHBOURS = 16
#: ... within this distance (at a depth camera's point per square millimetre, about 2.3 mm) ...
FINE_NORMAL_RADIUS_M = 0.004
#: ... at least this many of them ...
MIN_FINE_NORMAL_POINTS = 6
#: Small-scale normals are computed only this near the slices along the path (their radius, and
#: the faces' seeds nearby).
FINE_NORMAL_REACH_M = 0.016
#: ... whose smallest spread is clearly the smallest: below the middle one by this share of it.
PLANE_EIGEN_GAP = 0.3
#: A point's face is looked up in the nearest slice within this distance ...
FACE_SLICE_REACH_M = 0.004
#: ... among the lines within this height of the point ...
FACE_HEIGHT_REACH_M = 0.004
#: ... whose points reach within this of the point's foot on the line.
FACE_FOOT_MARGIN_M = 0.002
#: Version of the layout written by :meth:`ScanModel.to_arrays`; bump it when the keys change.
#: Version 1 (without edge tracks and variances) is still read.
ARRAYS_VERSION = 2

# Array keys of to_arrays: (key, attribute of ScanFeatures or EdgePoints, dtype).
#: (key in the arrays, attribute, dtype) of each stored array.
_FEATURE_ARRAYS: tuple[tuple[str, str, type], ...] = (
    ("points_m", "points_m", np.float64),
    ("dense_points_m", "dense_points_m", np.float64),
    ("normals", "normals", np.float64),
    ("curvature", "curvature", np.float64),
    ("is_edge", "is_edge", np.bool_),
)
_FEATURE_SCALARS = (
    ("edge_threshold", "edge_threshold", float),
    ("n_input", "n_input", int),
    ("n_cropped", "n_cropped", int),
    ("n_outliers", "n_outliers", int),
)
_EDGE_ARRAYS: tuple[tuple[str, str, type], ...] = (
    ("edge_points_m", "points_m", np.float64),
    ("edge_directions", "directions", np.float64),
    ("edge_residual_m", "residual_m", np.float64),
    ("edge_n_points", "n_points", np.int64),
)
#: Edge arrays added in version 2 (a version-1 model reads without them: tracks unknown,
#: variances from the residuals).
_EDGE_ARRAYS_V2: tuple[tuple[str, str, type], ...] = (
    ("edge_track", "track", np.int64),
    ("edge_variance_m2", "variance_m2", np.float64),
    ("edge_corner", "corner", np.int64),
)
_MODEL_SCALARS = ("edge_fit_radius_m", "edge_query_spacing_m", "edge_sample_spacing_m")


@dataclass(frozen=True, eq=False)
class ScanModel:
    """The scan's structure near a path, scan frame, with search trees built on first use.

    Attributes
    ----------
    features : ScanFeatures
        Voxel and dense clouds near the path, normals, curvature, edge flags.
    edges : EdgePoints
        The thinned edge along the path (possibly empty).
    edge_fit_radius_m : float
        Ball radius of the two-face fits: the thinned edge was fitted with it, and the tool's
        bisector at edges is fitted with it too.
    edge_query_spacing_m : float
        Distance along the path between the edge-line fits the thinned edge was sampled from.
    edge_sample_spacing_m : float
        Spacing of the thinned edge's points along each fitted line.
    profiles : Profiles or None
        The cross-sections along the path the model was built around, where the edges came
        from; they also say which face lies under a point (:meth:`face_normals_under`). Not
        stored by :meth:`to_arrays` (None in a model read back).

    Notes
    -----
    Equality is identity (``eq=False``): models hold large arrays and are compared through
    :meth:`to_arrays` where needed.
    """

    features: ScanFeatures
    edges: EdgePoints
    edge_fit_radius_m: float
    edge_query_spacing_m: float
    edge_sample_spacing_m: float
    profiles: Profiles | None = None

    @cached_property
    def coarse_tree(self) -> cKDTree:
        """Tree over ``features.points_m`` (the voxel cloud)."""
        return cKDTree(self.features.points_m)

    @cached_property
    def dense_tree(self) -> cKDTree:
        """Tree over ``features.dense_points_m``."""
        return cKDTree(self.features.dense_points_m)

    @cached_property
    def edge_tree(self) -> cKDTree | None:
        """Tree over ``edges.points_m``; None when there are no edge points."""
        return cKDTree(self.edges.points_m) if len(self.edges) else None

    @cached_property
    def dense_normals(self) -> FloatArray:
        """The normal of each dense point's nearest voxel (shape (D, 3); sign arbitrary): which
        way the surface faces there, at the curvature ball's scale."""
        _, nearest = self.coarse_tree.query(self.features.dense_points_m, workers=-1)
        normals: FloatArray = self.features.normals[nearest]
        return normals

    @cached_property
    def fine_normals(self) -> FloatArray:
        """Unit normals of the dense points at a small scale (sign arbitrary, shape (D, 3)): the
        plane through each point's :data:`FINE_NORMAL_NEIGHBOURS` nearest dense points within
        :data:`FINE_NORMAL_RADIUS_M`, which tells a wall a few millimetres tall from the faces
        above and below it (the curvature ball's normals blend them).

        Zero where the ball shows no plane (too few points, or no clearly smallest spread: a
        lone point, a line of them), which no rotation of the data could make the same twice;
        and for the points farther than :data:`FINE_NORMAL_REACH_M` from the path's slices,
        which nothing asks about (computed only when there are slices).
        """
        dense = self.features.dense_points_m
        wanted = np.arange(len(dense))
        if self.profiles is not None and len(self.profiles):
            gap, _ = cKDTree(self.profiles.origin_m).query(
                dense, distance_upper_bound=FINE_NORMAL_REACH_M, workers=-1
            )
            wanted = np.flatnonzero(np.isfinite(gap))
        normals = np.zeros_like(dense)
        if len(wanted) == 0:
            return normals
        covariances, counts = ball_moments(
            dense,
            self.dense_tree if "dense_tree" in self.__dict__ else None,
            radius_m=FINE_NORMAL_RADIUS_M,
            max_neighbours=FINE_NORMAL_NEIGHBOURS,
            rows=wanted,
        )
        values, vectors = symmetric_eig3(covariances)
        planar = (counts >= MIN_FINE_NORMAL_POINTS) & (
            values[:, 1] - values[:, 0] >= PLANE_EIGEN_GAP * np.maximum(values[:, 1], 1e-30)
        )
        normals[wanted] = np.where(planar[:, None], vectors, 0.0)
        return normals

    def faces_under(self, points_m: FloatArray) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """The face each point lies over, from the nearest cross-section: the line of that
        slice nearest to the point whose points reach past its foot.

        Parameters
        ----------
        points_m : ndarray of shape (B, 3)
            Scan frame.

        Returns
        -------
        normals : ndarray of shape (B, 3)
            Unit, sign arbitrary; meaningless where not ``found``.
        feet_m : ndarray of shape (B, 3)
            The foot of each point on its face (in the slice): where the face is.
        found : ndarray of shape (B,), bool
            A slice within :data:`FACE_SLICE_REACH_M` has such a line.
        """
        points_m = np.asarray(points_m, dtype=np.float64)
        b = len(points_m)
        profiles = self.profiles
        if profiles is None or len(profiles) == 0:
            return np.zeros((b, 3)), points_m.copy(), np.zeros(b, dtype=bool)
        gap, station = cKDTree(profiles.origin_m).query(points_m, workers=-1)
        rel = points_m - profiles.origin_m[station]
        axes = profiles.axes[station]
        local = np.einsum("bki,bi->bk", axes, rel)  # (B, 2)
        normal = profiles.normal[station]  # (B, L, 2)
        height = np.abs(np.einsum("blk,bk->bl", normal, local) - profiles.offset_m[station])
        foot = np.einsum("blk,bk->bl", np.stack([-normal[..., 1], normal[..., 0]], -1), local)
        extent = profiles.extent_m[station]
        covers = (foot >= extent[..., 0] - FACE_FOOT_MARGIN_M) & (
            foot <= extent[..., 1] + FACE_FOOT_MARGIN_M
        )
        usable = profiles.line_ok[station] & covers & (height <= FACE_HEIGHT_REACH_M)
        pick = np.argmin(np.where(usable, height, np.inf), axis=1)
        rows = np.arange(b)
        n2 = normal[rows, pick]
        normals = n2[:, :1] * axes[:, 0] + n2[:, 1:] * axes[:, 1]
        # The point moved onto the line, within its slice's plane.
        signed = np.einsum("bk,bk->b", n2, local) - profiles.offset_m[station][rows, pick]
        feet = points_m - signed[:, None] * normals
        found = usable[rows, pick] & (gap <= FACE_SLICE_REACH_M)
        return normals, feet, found

    @property
    def trees(self) -> tuple[cKDTree, cKDTree]:
        """The voxel and dense trees, as :func:`recon.edge_lines.fit_edge_lines` takes them."""
        return self.coarse_tree, self.dense_tree

    def with_extra_edges(
        self, points_m: FloatArray, directions: FloatArray, *, drop: np.ndarray | None = None
    ) -> ScanModel:
        """The model with more thinned-edge samples (e.g. a corner's edge lines filled in).

        Parameters
        ----------
        points_m, directions : ndarrays of shape (S, 3)
            Scan frame; the samples get the residual, face count and variance of the model's
            typical edge sample (the median), as they come from lines fitted to those samples,
            and the track of the model's nearest sample along the same direction (-1 if none).
        drop : ndarray of shape (E,), bool, optional
            The model's own samples to leave out (those the new ones replace).

        Returns
        -------
        ScanModel
            A new model; its edge tree is rebuilt on first use, the others are shared.
        """
        edges = self.edges
        if drop is not None and np.any(drop):
            edges = edges.subset(~np.asarray(drop, dtype=bool))
        points_m = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        residual = float(np.median(edges.residual_m)) if len(edges) else 0.0
        count = int(np.median(edges.n_points)) if len(edges) else 0
        variance = float(np.median(edges.variances_m2())) if len(edges) else 0.0
        track = np.full(len(points_m), -1, np.int64)
        if len(edges) and len(points_m):
            gap, nearest = cKDTree(edges.points_m).query(points_m)
            along = np.abs(np.einsum("ni,ni->n", edges.directions[nearest], directions))
            same = (gap <= 0.002) & (along >= np.cos(np.radians(30.0)))
            track = np.where(same, edges.track_labels()[nearest], -1)
        grown = EdgePoints.concatenate(
            [
                edges,
                EdgePoints(
                    points_m=points_m,
                    directions=directions,
                    residual_m=np.full(len(points_m), residual),
                    n_points=np.full(len(points_m), count, np.int64),
                    track=track,
                    variance_m2=np.full(len(points_m), variance),
                    corner=np.full(len(points_m), -1, np.int64),
                ),
            ]
        )
        model = ScanModel(
            features=self.features,
            edges=grown,
            edge_fit_radius_m=self.edge_fit_radius_m,
            edge_query_spacing_m=self.edge_query_spacing_m,
            edge_sample_spacing_m=self.edge_sample_spacing_m,
            profiles=self.profiles,
        )
        for shared in ("coarse_tree", "dense_tree", "dense_normals", "fine_normals"):
            if shared in self.__dict__:
                model.__dict__[shared] = self.__dict__[shared]
        return model

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The model as plain arrays (scalars as 0-d arrays), for ``np.savez`` without pickle.

        Returns
        -------
        dict of str to ndarray
            Keys: ``points_m`` (M, 3), ``dense_points_m`` (D, 3), ``normals`` (M, 3),
            ``curvature`` (M,), ``is_edge`` (M,) bool, ``edge_points_m`` (E, 3),
            ``edge_directions`` (E, 3), ``edge_residual_m`` (E,), ``edge_n_points`` (E,) int,
            and 0-d ``edge_threshold``, ``n_input``, ``n_cropped``, ``n_outliers``,
            ``edge_fit_radius_m``, ``edge_query_spacing_m``, ``edge_sample_spacing_m``,
            ``version``. Lengths in metres.
        """
        out: dict[str, np.ndarray] = {"version": np.asarray(ARRAYS_VERSION, dtype=np.int64)}
        for key, attr, dtype in _FEATURE_ARRAYS:
            out[key] = np.asarray(getattr(self.features, attr), dtype=dtype)
        for key, attr, kind in _FEATURE_SCALARS:
            out[key] = np.asarray(kind(getattr(self.features, attr)))
        for key, attr, dtype in _EDGE_ARRAYS + _EDGE_ARRAYS_V2:
            out[key] = np.asarray(getattr(self.edges, attr), dtype=dtype)
        for key in _MODEL_SCALARS:
            out[key] = np.asarray(float(getattr(self, key)))
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> ScanModel:
        """Rebuild a model from :meth:`to_arrays` (or an ``np.load`` of what it wrote).

        Parameters
        ----------
        arrays : mapping of str to ndarray
            Extra keys are ignored, so the model may share a file with other arrays.

        Returns
        -------
        ScanModel

        Raises
        ------
        ValueError
            A key missing, another layout version, or arrays whose shapes disagree.
        """
        keys = (
            ["version"]
            + [k for k, _, _ in _FEATURE_ARRAYS + _EDGE_ARRAYS]
            + [k for k, _, _ in _FEATURE_SCALARS]
            + list(_MODEL_SCALARS)
        )
        missing = [k for k in keys if k not in arrays]
        if missing:
            raise ValueError(f"the scan model's arrays lack {', '.join(missing)}")
        version = int(np.asarray(arrays["version"]))
        if version not in (1, ARRAYS_VERSION):
            raise ValueError(
                f"the scan model's arrays have layout version {version}; this version reads "
                f"1 and {ARRAYS_VERSION}: build the model again from the scan"
            )
        if version >= 2:
            missing = [k for k, _, _ in _EDGE_ARRAYS_V2 if k not in arrays]
            if missing:
                raise ValueError(f"the scan model's arrays lack {', '.join(missing)}")
        feature_kwargs: dict[str, Any] = {
            attr: np.array(arrays[key], dtype=dtype) for key, attr, dtype in _FEATURE_ARRAYS
        }
        feature_kwargs |= {
            attr: kind(np.asarray(arrays[key])) for key, attr, kind in _FEATURE_SCALARS
        }
        edge_arrays = _EDGE_ARRAYS + (_EDGE_ARRAYS_V2 if version >= 2 else ())
        edge_kwargs: dict[str, Any] = {
            attr: np.array(arrays[key], dtype=dtype) for key, attr, dtype in edge_arrays
        }
        edges = EdgePoints(**edge_kwargs)
        features = ScanFeatures(**feature_kwargs)
        _check_shapes(features, edges)
        scalars: dict[str, Any] = {key: float(np.asarray(arrays[key])) for key in _MODEL_SCALARS}
        return cls(features=features, edges=edges, **scalars)


def _check_shapes(features: ScanFeatures, edges: EdgePoints) -> None:
    """Refuse arrays that cannot belong together (a damaged or hand-edited file)."""
    m = len(features.points_m)
    if features.points_m.shape != (m, 3) or features.dense_points_m.ndim != 2:
        raise ValueError("the scan model's points must have shape (M, 3)")
    if features.normals.shape != (m, 3) or features.curvature.shape != (m,):
        raise ValueError(f"the scan model's normals and curvature must have {m} rows")
    if features.is_edge.shape != (m,):
        raise ValueError(f"the scan model's edge flags must have {m} rows")
    e = len(edges.points_m)
    if edges.points_m.shape != (e, 3) or edges.directions.shape != (e, 3):
        raise ValueError("the scan model's edge points and directions must have shape (E, 3)")
    if edges.residual_m.shape != (e,) or edges.n_points.shape != (e,):
        raise ValueError(f"the scan model's edge residuals and counts must have {e} rows")
    if (
        edges.track_labels().shape != (e,)
        or edges.variances_m2().shape != (e,)
        or edges.corner_labels().shape != (e,)
    ):
        raise ValueError(f"the scan model's edge tracks, variances and corners must have {e} rows")


def build_scan_model(scan: Scan, points_in_scan_m: FloatArray, params: ReconParams) -> ScanModel:
    """The scan's structure near a path already in the scan frame (no registration here).

    Crops the scan to ``params.crop_margin_m`` of the path, averages it to ``params.voxel_m``
    voxels, removes outliers, computes normals and curvature in a ``params.curvature_radius_m``
    ball, flags edges (``params.edge_curvature`` or the automatic threshold) and thins the edge
    band to the edge along the path.

    Parameters
    ----------
    scan : Scan
        The workpiece, scan frame.
    points_in_scan_m : ndarray of shape (N, 3), metres
        The path (a trace or a reconstruction), mapped into the scan frame by whatever
        ``T_scan_tracker`` is known; a rough alignment is enough for the crop, but the thinned
        edge is sampled along it.
    params : ReconParams

    Returns
    -------
    ScanModel

    Raises
    ------
    NoOverlapError
        Too few scan points near the path.
    """
    path = np.asarray(points_in_scan_m, dtype=np.float64)
    features = prepare_scan(
        scan.points_m,
        path,
        crop_margin_m=params.crop_margin_m,
        voxel_m=params.voxel_m,
        curvature_radius_m=params.curvature_radius_m,
        edge_curvature=params.edge_curvature,
    )
    fit_radius = EDGE_FIT_RADIUS_FACTOR * params.curvature_radius_m
    query_spacing = EDGE_QUERY_SPACING_FRACTION * fit_radius
    coarse_tree = cKDTree(features.points_m)
    dense_tree = cKDTree(features.dense_points_m)
    model = ScanModel(
        features=features,
        edges=EdgePoints.empty(),
        edge_fit_radius_m=fit_radius,
        edge_query_spacing_m=query_spacing,
        edge_sample_spacing_m=EDGE_SAMPLE_SPACING_M,
    )
    model.__dict__.update(coarse_tree=coarse_tree, dense_tree=dense_tree)
    stations, along = stations_along(path)
    profiles = find_profiles(
        stations, along, features.dense_points_m, model.fine_normals, dense_tree
    )
    edges = thin_edges(profiles, features, (coarse_tree, dense_tree), fit_radius_m=fit_radius)
    shared = {k: model.__dict__[k] for k in ("coarse_tree", "dense_tree", "fine_normals")}
    model = ScanModel(
        features=features,
        edges=edges,
        edge_fit_radius_m=fit_radius,
        edge_query_spacing_m=query_spacing,
        edge_sample_spacing_m=EDGE_SAMPLE_SPACING_M,
        profiles=profiles,
    )
    model.__dict__.update(shared)
    return model
