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

import numpy as np
from scipy.spatial import cKDTree

from recon.edges import EdgePoints, thin_edges
from recon.features import ScanFeatures, prepare_scan
from recon.types import FloatArray, ReconParams, Scan

#: The edge-line fits use balls this much larger than the curvature ball, to reach past the
#: crest's band of blended normals onto both faces with enough points on each.
EDGE_FIT_RADIUS_FACTOR = 2.0
#: Edge lines are fitted every this fraction of the fit radius along the path (4 mm for a 16 mm
#: ball): neighbouring fits share most of their points, so denser fits add cost, not information.
EDGE_QUERY_SPACING_FRACTION = 0.375
#: Spacing of the points sampled along each fitted edge line.
EDGE_SAMPLE_SPACING_M = 0.001
#: Version of the layout written by :meth:`ScanModel.to_arrays`; bump it when the keys change.
ARRAYS_VERSION = 1

# Array keys of to_arrays: (key, attribute of ScanFeatures or EdgePoints, dtype).
_FEATURE_ARRAYS = (
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
_EDGE_ARRAYS = (
    ("edge_points_m", "points_m", np.float64),
    ("edge_directions", "directions", np.float64),
    ("edge_residual_m", "residual_m", np.float64),
    ("edge_n_points", "n_points", np.int64),
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
            Scan frame; the samples get the residual and face count of the model's typical edge
            sample (the median), as they come from lines fitted to those samples.
        drop : ndarray of shape (E,), bool, optional
            The model's own samples to leave out (those the new ones replace).

        Returns
        -------
        ScanModel
            A new model; its edge tree is rebuilt on first use, the others are shared.
        """
        edges = self.edges
        if drop is not None and np.any(drop):
            kept = ~np.asarray(drop, dtype=bool)
            edges = EdgePoints(
                points_m=edges.points_m[kept],
                directions=edges.directions[kept],
                residual_m=edges.residual_m[kept],
                n_points=edges.n_points[kept],
            )
        residual = float(np.median(edges.residual_m)) if len(edges) else 0.0
        count = int(np.median(edges.n_points)) if len(edges) else 0
        grown = EdgePoints(
            points_m=np.concatenate([edges.points_m, points_m]),
            directions=np.concatenate([edges.directions, directions]),
            residual_m=np.concatenate([edges.residual_m, np.full(len(points_m), residual)]),
            n_points=np.concatenate([edges.n_points, np.full(len(points_m), count, np.int64)]),
        )
        model = ScanModel(
            features=self.features,
            edges=grown,
            edge_fit_radius_m=self.edge_fit_radius_m,
            edge_query_spacing_m=self.edge_query_spacing_m,
            edge_sample_spacing_m=self.edge_sample_spacing_m,
        )
        for shared in ("coarse_tree", "dense_tree"):
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
        for key, attr, dtype in _EDGE_ARRAYS:
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
        if version != ARRAYS_VERSION:
            raise ValueError(
                f"the scan model's arrays have layout version {version}; this version reads "
                f"{ARRAYS_VERSION}: build the model again from the scan"
            )
        feature_kwargs = {
            attr: np.array(arrays[key], dtype=dtype) for key, attr, dtype in _FEATURE_ARRAYS
        }
        feature_kwargs |= {
            attr: kind(np.asarray(arrays[key])) for key, attr, kind in _FEATURE_SCALARS
        }
        edges = EdgePoints(
            **{attr: np.array(arrays[key], dtype=dtype) for key, attr, dtype in _EDGE_ARRAYS}
        )
        features = ScanFeatures(**feature_kwargs)
        _check_shapes(features, edges)
        return cls(
            features=features,
            edges=edges,
            **{key: float(np.asarray(arrays[key])) for key in _MODEL_SCALARS},
        )


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
    edges = thin_edges(
        features,
        path,
        radius_m=fit_radius,
        query_spacing_m=query_spacing,
        sample_spacing_m=EDGE_SAMPLE_SPACING_M,
        trees=(coarse_tree, dense_tree),
        beyond_ends_m=fit_radius,
    )
    model = ScanModel(
        features=features,
        edges=edges,
        edge_fit_radius_m=fit_radius,
        edge_query_spacing_m=query_spacing,
        edge_sample_spacing_m=EDGE_SAMPLE_SPACING_M,
    )
    # The edge thinning searched these very trees: seed the model's lazy ones with them rather
    # than build them again (cached_property keeps its value in the instance's __dict__).
    model.__dict__.update(coarse_tree=coarse_tree, dense_tree=dense_tree)
    return model
