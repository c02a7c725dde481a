"""The reconstruction's parameters (:class:`ReconParams`): the paper's weights alpha and beta,
the neighbourhoods, edges, registration and their bounds.

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from recon.params import check_bounds, param

if TYPE_CHECKING:
    pass


Method = Literal["paper", "anchored"]


METHODS: tuple[str, ...] = ("paper", "anchored")


@dataclass(frozen=True)
class ReconParams:
    """Parameters of one reconstruction; stored with every result so it can be replayed.

    Attributes
    ----------
    spacing_m : float
        Distance between resampled path points.
    radius_m : float
        Reconstruction radius r: path points within r of a point (along the path) form N_P.
    degree : int
        Degree d of the fitted polynomials.
    alpha : float in [0, 1] or "auto"
        Weight of the path against the scan (1: path only, 0: scan only). ``"auto"`` picks it per
        point from the estimated noise of both (see ``recon.reconstruct``).
    beta : float in [0, 1]
        Total amount of reconstruction (0 leaves the path as it is for ``anchored``; see paper).
    method : {"paper", "anchored"}
        ``paper``: Eq. (4) of the paper, using only the shape of the scan near the path.
        ``anchored``: uses the registered scan's absolute position and keeps all three components.
    corner_angle_deg : float
        Turning angle above which the path is split into separately reconstructed segments.
    corner_scale_m : float
        Chord length over which the turning angle is measured (larger than hand tremor).
    register : bool
        Register the path to the scan's features with ICP before reconstructing.
    icp_max_distance_m : float
        Largest path-to-scan distance ICP pairs points over (a bound on the misalignment).
    crop_margin_m : float
        Only scan points within this distance of the path are processed.
    voxel_m : float
        Voxel size the cropped scan is averaged down to (0: keep every point). Curvature needs a
        scale: on a dense cloud, small neighbourhoods see only noise.
    curvature_radius_m : float
        Neighbourhood radius for normals and curvature (surface variation).
    edge_curvature : float or None
        Surface variation above which a scan point is an edge point; None derives it from the
        cloud (see ``recon.features.edge_threshold``).
    edge_fraction : float
        A segment follows an edge of the scan when the edge runs along at least this share of it
        (and close to it); its points without the edge then take the height of the face under
        them (see ``recon.classify``).
    surface_k : int
        k nearest scan points of every point of N_P that form N_S on a surface.
    uncertainty_tolerance_m : float
        The summary warns of every stretch whose points' 1-sigma uncertainty exceeds this.
    evidence_sigmas : float
        The scan may move a point at most this many of the trace's standard deviations (the
        hand's error model); a feature farther away is not the one traced there, and the point
        keeps the smoothed trace (said per point in ``reason``).
    """

    spacing_m: float = param(0.001, ge=1e-4, le=0.01, unit="m", help="resampling step")
    radius_m: float = param(0.008, ge=5e-4, le=0.2, unit="m", help="reconstruction radius r")
    degree: int = param(2, ge=1, le=5, help="polynomial degree")
    alpha: float | Literal["auto"] = param(
        "auto", ge=0, le=1, help="weight of the path against the scan (1: path only), or auto"
    )
    beta: float = param(1.0, ge=0, le=1, help="amount of reconstruction")
    method: Method = param(
        "anchored", help="paper: the paper's Eq. (4); anchored: ours, using the scan's position"
    )
    corner_angle_deg: float = param(
        50.0, ge=1, le=180, unit="deg", help="turning angle that splits the path at a corner"
    )
    corner_scale_m: float = param(
        0.004, ge=5e-4, le=0.05, unit="m", help="chord over which the turning angle is measured"
    )
    register: bool = True
    icp_max_distance_m: float = param(
        0.010, ge=1e-4, le=0.1, unit="m", help="largest path-to-scan distance ICP pairs over"
    )
    crop_margin_m: float = param(
        0.020, ge=1e-3, le=0.2, unit="m", help="scan points farther from the path are left out"
    )
    voxel_m: float = param(
        0.002, ge=0, le=0.05, unit="m", help="voxel the cropped scan is averaged to (0: none)"
    )
    curvature_radius_m: float = param(
        0.008, ge=5e-4, le=0.1, unit="m", help="ball of the scan's normals and curvature"
    )
    edge_curvature: float | None = param(
        None, gt=0, lt=1 / 3, help="surface variation above which a scan point is an edge"
    )
    edge_fraction: float = param(
        0.25, ge=0.01, le=1, help="share of a segment an edge must run along for it to follow it"
    )
    surface_k: int = param(
        10, ge=3, le=1000, help="nearest scan points per path point on a surface"
    )
    uncertainty_tolerance_m: float = param(
        0.0005,
        ge=1e-5,
        le=0.01,
        unit="m",
        help="the summary names the stretches whose 1-sigma uncertainty exceeds this",
    )
    evidence_sigmas: float = param(
        3.0,
        ge=0.5,
        le=20,
        help="the scan moves a point at most this many of the trace's standard deviations",
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        if 0 < self.voxel_m < MIN_VOXEL_M:
            raise ValueError(
                f"voxel_m must be 0 (no averaging) or at least {MIN_VOXEL_M} m, got {self.voxel_m}"
            )
        if self.radius_m < 2 * self.spacing_m:
            raise ValueError(
                f"radius_m ({self.radius_m}) must be at least twice spacing_m ({self.spacing_m}) "
                "so that N_P holds enough points for a fit"
            )

    @property
    def uses_scan(self) -> bool:
        """Whether the scan can influence the result at all (alpha = 1 means path only)."""
        return self.alpha == "auto" or self.alpha < 1.0


#: The finest voxel the scan is averaged to (finer than a depth camera resolves is no averaging,
#: and a vanishing one overflows the voxel grid's indices).
MIN_VOXEL_M = 1e-4
