"""What a reconstruction returns (:class:`Reconstruction`), its per-point diagnostics, its
segments and reports, and the scan-to-tracker registration.

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray, piece_labels
from recon.classify import SegmentKind
from recon.recon_params import ReconParams
from recon.transforms import rotation_angle_deg, translation_m

if TYPE_CHECKING:
    from recon.scan_model import ScanModel


class PointMode(enum.IntEnum):
    """What a reconstructed point followed."""

    PATH = 0  #: the path alone (no scan, alpha = 1, or no scan support near this point)
    SURFACE = 1  #: a surface of the scan
    EDGE = 2  #: an edge of the scan
    UNCHANGED = 3  #: too few points around it for a fit; passed through as resampled

    @property
    def label(self) -> str:
        return self.name.lower()


class PointReason(enum.IntEnum):
    """Why a point was not reconstructed as its segment claims (the scan's evidence failed
    there), or how it was, where that needs saying. ``NONE`` for every point that followed its
    segment's feature, and for every point of a reconstruction without a scan."""

    NONE = 0  #: as its segment claims
    NO_FEATURE = 1  #: the scan shows no such feature here (nothing fitted, too few points)
    FAR_FROM_TRACE = 2  #: the feature is farther from the trace than the hand's error explains
    OFF_EVIDENCE = 3  #: the fitted feature is not where the scan's points are (too far from them)
    #: the whole segment ran far from the scan (no longer produced: judged point by point as
    #: FAR_FROM_TRACE; kept so records that hold it still read)
    SEGMENT_DISAGREES = 4
    ONE_FACE = 5  #: the edge was not found here; the height comes from the one face under it
    CONTINUED = 6  #: past the end of the scan's feature, continued along its line
    PAST_END = 7  #: farther past the end of the scan's feature than it is continued

    @property
    def label(self) -> str:
        return "" if self is PointReason.NONE else self.name.lower()

    @property
    def fallen_back(self) -> bool:
        """The scan was not used at this point although the segment claimed it."""
        return self in (
            PointReason.NO_FEATURE,
            PointReason.FAR_FROM_TRACE,
            PointReason.OFF_EVIDENCE,
            PointReason.SEGMENT_DISAGREES,
            PointReason.PAST_END,
        )


#: A segment where more than this share of the points fell back to the trace is one where the
#: scan is not trusted (said in the summary).
DISTRUST_SHARE = 0.05


@dataclass(frozen=True)
class Segment:
    """A run of path points between corners, reconstructed on its own.

    ``start`` and ``stop`` index the resampled path (``stop`` exclusive); neighbouring segments
    share their corner point, which belongs to the later one in ``Reconstruction.segment``.
    ``kind`` is a :class:`recon.classify.SegmentKind`, a string enum: ``dataclasses.asdict`` of a
    segment serialises to JSON as ``"edge"``, ``"surface"`` or ``"path"``.

    The evidence for an edge segment's choice: ``edge_fraction`` (the share of the segment the
    chosen edge runs along), ``edge_distance_m`` (how far the trace ran from it, median) and
    ``next_edge_m`` (how far the next candidate edge lay from it, median; None when there was
    none). ``fallen_back`` is the share of its points where the scan's evidence failed and the
    trace was kept; a segment with more than :data:`DISTRUST_SHARE` of them is one where the
    scan is not trusted.
    """

    start: int
    stop: int
    kind: SegmentKind
    edge_fraction: float
    edge_distance_m: float | None = None
    next_edge_m: float | None = None
    fallen_back: float = 0.0

    @property
    def scan_trusted(self) -> bool:
        """Whether the scan's evidence held along the segment (see :data:`DISTRUST_SHARE`)."""
        return self.fallen_back <= DISTRUST_SHARE

    def __post_init__(self) -> None:
        # Imported here: recon.classify imports this module. A plain string is accepted (a
        # segment read back from JSON) and refused if it names no kind.

        object.__setattr__(self, "kind", SegmentKind(self.kind))


@dataclass(frozen=True)
class DemonstrationReport:
    """How one of several demonstrations of a path entered their fusion.

    Attributes
    ----------
    used : bool
    reversed : bool
        It was traced the other way round and turned.
    mean_offset_m : float
        Its mean distance from the others' median.
    roughness_m : float
        RMS departure from its own smoothing (hand tremor and tracker noise).
    reason : str
        Why it was left out (empty when used).
    """

    used: bool
    reversed: bool
    mean_offset_m: float
    roughness_m: float
    reason: str = ""


@dataclass(frozen=True)
class CornerReport:
    """Where the trace turned sharply, and whether the path was split there.

    Attributes
    ----------
    index : int
        The resampled point of the turn.
    angle_deg : float
        How much the trace turned there.
    split : bool
    reason : str
        Why (or why not), in words.
    point_m : tuple of 3 floats or None
        Where the scan's edges meet, tracker frame, when they placed the corner: both segments
        end there (with ``beta`` < 1, that share of the way there from the trace).
    """

    index: int
    angle_deg: float
    split: bool
    reason: str
    point_m: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Registration:
    """Result of registering the path to the scan.

    Attributes
    ----------
    T_scan_tracker : ndarray of shape (4, 4)
        Maps path (tracker-frame) points into the scan frame.
    rmse_m : float
        Root mean square distance of the paired points after registration.
    fitness : float
        Fraction of path points that were paired (with non-zero robust weight) at the end.
    n_pairs : int
        Number of such pairs.
    target : str
        What the path was registered to: "edge" or "surface".
    constrained_dof : int
        How many of the six rigid degrees of freedom the scan's feature fixed (6 for a corner,
        5 for a circle, 4 for a straight edge, 3 for a plane); the others kept the initial guess.
    path_moved_mean_m, path_moved_max_m : float
        How far the path's points moved from where the initial guess put them (mean, max; NaN
        if unknown). What a user means by "registration moved the path": the transform's own
        translation also holds the scanner's placement, metres away for a scanner whose origin
        is far from the tracker's.
    path_moved_off_feature_median_m : float
        The part of a point's move toward or away from the feature it was registered to
        (along the surface's normal, across the edge), median over the path (NaN if unknown).
        A path moved by millimetres but off its feature by a fraction of one slid along it:
        where the feature hardly fixes that sliding (a nearly flat patch), the move says little
        about the scanner.
    reason : str
        Why this target was chosen (empty when there was no choice).
    alternative : dict or None
        The other target's figures when it was tried too: ``target``, ``rmse_m``, ``fitness``,
        ``constrained_dof``, ``following_edge`` (the fraction of the path that would follow the
        edge), ``path_moved_mean_m``.
    covariance : ndarray of shape (6, 6) or None
        Of the transform's error as a twist ``(L omega, t)`` about ``motion_centre_m`` with
        ``L = motion_length_m`` (see :class:`recon.icp.RigidMotion`), scan frame; zero along the
        motions the target leaves free. None when unknown.
    motion_centre_m : ndarray of shape (3,) or None
    motion_length_m : float or None
    """

    T_scan_tracker: FloatArray
    rmse_m: float
    fitness: float
    n_pairs: int
    target: str
    constrained_dof: int = 6
    path_moved_mean_m: float = float("nan")
    path_moved_max_m: float = float("nan")
    path_moved_off_feature_median_m: float = float("nan")
    reason: str = ""
    alternative: dict[str, Any] | None = field(default=None, compare=False)
    covariance: FloatArray | None = field(default=None, compare=False, repr=False)
    motion_centre_m: FloatArray | None = field(default=None, compare=False, repr=False)
    motion_length_m: float | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        T = np.array(self.T_scan_tracker, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_scan_tracker must be 4x4, got {T.shape}")
        T.setflags(write=False)
        object.__setattr__(self, "T_scan_tracker", T)

    @property
    def translation_m(self) -> FloatArray:
        return translation_m(self.T_scan_tracker)

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation part, degrees."""
        return rotation_angle_deg(self.T_scan_tracker)


#: The fields of a :class:`Reconstruction` that hold one row per point, in the order of the
#: reconstruction CSV's columns.
PER_POINT_FIELDS = (
    "points_m",
    "input_points_m",
    "t_s",
    "orientations_xyzw",
    "displacement_m",
    "mode",
    "segment",
    "n_path",
    "n_surface",
    "residual_path_m",
    "residual_surface_m",
    "alpha",
    "piece",
    "uncertainty_m",
    "reason",
)


@dataclass(frozen=True)
class Reconstruction:
    """A reconstructed path with per-point diagnostics, in the tracker frame.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        The reconstructed path.
    input_points_m : ndarray of shape (N, 3), metres
        The equidistantly resampled input that ``points_m`` corresponds to point by point.
    t_s : ndarray of shape (N,), seconds, or None
        Sample times interpolated at the resampled points, when the input had times.
    orientations_xyzw : ndarray of shape (N, 4), or None
        The pen's orientations interpolated at the resampled points, when the input had them.
    displacement_m : ndarray of shape (N,), metres
        How far each point moved: ``|points_m - input_points_m|``.
    mode : ndarray of shape (N,), int8
        :class:`PointMode` of each point.
    segment : ndarray of shape (N,), int
        Index into ``segments``.
    n_path, n_surface : ndarray of shape (N,), int
        Sizes of N_P and N_S (0 where no scan was used).
    residual_path_m, residual_surface_m : ndarray of shape (N,), metres
        RMS residual of the path and scan fits (NaN where there was no such fit).
    alpha : ndarray of shape (N,)
        The path weight used at each point (1 where only the path was used).
    piece : ndarray of shape (N,), int
        The trace's piece each point belongs to (see :class:`Recording`); no segment spans two.
    segments : tuple of Segment
    registration : Registration or None
        None when no scan was used or registration was switched off.
    params : ReconParams
    notes : tuple of str
    orientations_xyzw : see above
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the scan was used with: the registration's, else the initial (calibrated)
        one given, else identity when a scan was used without either; None when no scan was used.
    scan_model : ScanModel or None
        The scan's structure near the path, scan frame, as the reconstruction used it (None
        without a scan). Planning reuses it with ``T_scan_tracker`` instead of recomputing it.
        Left out of equality and repr: it is large and derived from the inputs.
    corners : tuple of CornerReport
        Every place the trace turned sharply, split or not, and why.
    uncertainty_m : ndarray of shape (N,), metres, or None
        1-sigma uncertainty of each point across the path, tracker frame: from the fits, the
        trace's estimated noise and the registration (the transform's uncertainty moves the
        scan's features, and the path with them). None for results made before it was kept.
    demonstrations : tuple of DemonstrationReport
        When several demonstrations were fused into the trace: how each one entered.
    reason : ndarray of shape (N,), int8, or None
        :class:`PointReason` of each point: why the scan's evidence was not used where the
        segment claimed it, or how it was used past a feature's end. None for results made
        before it was kept.
    """

    points_m: FloatArray
    input_points_m: FloatArray
    t_s: FloatArray | None
    displacement_m: FloatArray
    mode: NDArray[np.int8]
    segment: NDArray[np.int64]
    n_path: NDArray[np.int64]
    n_surface: NDArray[np.int64]
    residual_path_m: FloatArray
    residual_surface_m: FloatArray
    alpha: FloatArray
    segments: tuple[Segment, ...]
    registration: Registration | None
    params: ReconParams
    notes: tuple[str, ...] = field(default=())
    orientations_xyzw: FloatArray | None = None
    T_scan_tracker: FloatArray | None = None
    scan_model: ScanModel | None = field(default=None, compare=False, repr=False)
    piece: NDArray[np.int64] | None = None
    corners: tuple[CornerReport, ...] = ()
    uncertainty_m: FloatArray | None = None
    demonstrations: tuple[DemonstrationReport, ...] = ()
    reason: NDArray[np.int8] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "piece", piece_labels(self.piece, len(self.points_m)))
        if self.T_scan_tracker is not None:
            T = np.array(self.T_scan_tracker, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"T_scan_tracker must be 4x4, got {T.shape}")
            T.setflags(write=False)
            object.__setattr__(self, "T_scan_tracker", T)
        n = len(self.points_m)
        for name in PER_POINT_FIELDS:
            value = getattr(self, name)
            if value is None:
                continue
            arr = np.array(value, copy=True)
            if len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} rows for {n} points")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def point_pieces(self) -> NDArray[np.int64]:
        """``piece`` as ``__post_init__`` left it (one label per point; never None)."""
        assert self.piece is not None  # labelled by __post_init__
        return self.piece

    def __len__(self) -> int:
        return len(self.points_m)

    def count(self, mode: PointMode) -> int:
        """Number of points reconstructed in ``mode``."""
        return int(np.count_nonzero(self.mode == int(mode)))
