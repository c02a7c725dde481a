"""The pipelines behind every job, shared by the command line and the service's worker tasks.

Each pipeline takes domain objects (a raw trace, a recording and a scan, a reconstructed path, a
trajectory) and returns an outcome that knows its JSON summary and its terminal report. Reading
and writing files is the caller's business: ``service/cli`` reads the user's files, the worker
tasks (``service/tasks.py``) the session's stored arrays. So a reconstruction, its preview, a
plan or a dry run comes out the same whichever way it was asked for.

Heavy imports (Open3D, SciPy, toppra, matplotlib) happen inside the functions: the command line
imports this module for every command.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from recon.arrays import FloatArray
from recon.params import PIVOT_TOLERANCE_M

if TYPE_CHECKING:  # the plan module is imported where a plan is made, not for every command
    from drivers.robot.base import ExecutionRecord
    from drivers.robot.dryrun import ExecutionReport
    from drivers.tracking.readers import RawTrace
    from recon.calibrate import PivotCalibration, PointPairCalibration
    from recon.collision import Cell, CollisionReport
    from recon.inputs import Recording, Scan
    from recon.kinematics import DHCalibration
    from recon.paths import ReconstructedPath
    from recon.plan import MovePlan, Plan
    from recon.plan_params import PlanParams
    from recon.recon_params import ReconParams
    from recon.results import Reconstruction, Registration
    from recon.scan_model import ScanModel
    from recon.touches import Dwell, TouchRegistration
    from recon.trajectory import JointTrajectory


def _off_feature(reg: Registration, mm: float) -> str:
    """ " (x mm of it off the surface, the rest along it)" for a registration report: a path
    moved by millimetres but hardly off its feature slid along it."""
    off = reg.path_moved_off_feature_median_m
    if not np.isfinite(off) or not reg.path_moved_max_m > 0:
        return ""
    across = "off the surface" if reg.target == "surface" else "across the edge"
    return f" ({off * mm:.2f} mm of it {across} on median, the rest along it)"


def _jsonable_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


# -- calibrations ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PivotOutcome:
    """A pivot calibration from a recording, with what was left out of it."""

    calibration: PivotCalibration
    n_lost: int
    rigid_body: str | None
    format: str

    def as_json(self) -> dict[str, Any]:
        c = self.calibration
        return {
            "tip_offset_m": c.tip_offset_m.tolist(),
            "pivot_point_m": c.pivot_point_m.tolist(),
            "residual_rms_m": c.residual_rms_m,
            "residual_max_m": c.residual_max_m,
            "rotation_spread_deg": c.rotation_spread_deg,
            "n_used": c.n_used,
            "n_rejected": c.n_rejected,
            "n_lost": self.n_lost,
            "rigid_body": self.rigid_body,
            "format": self.format,
        }

    def line(self) -> str:
        c, mm = self.calibration, 1e3
        x, y, z = c.tip_offset_m * mm
        return (
            f"tip offset ({x:.2f}, {y:.2f}, {z:.2f}) mm in the rigid body's frame; residual "
            f"{c.residual_rms_m * mm:.3f} mm RMS, {c.residual_max_m * mm:.3f} mm max; pen "
            f"turned {c.rotation_spread_deg:.0f} deg; {c.n_used} samples used, "
            f"{c.n_rejected} rejected, {self.n_lost} lost"
        )


def _refuse_poor_fit(what: str, reason: str | None, accept: bool, detail: dict[str, Any]) -> None:
    """Raise :class:`PoorFitError` for a fit worse than its tolerance, unless accepted."""
    from recon.errors import PoorFitError

    if reason is not None and not accept:
        raise PoorFitError(
            f"the {what} was not stored: {reason}. Re-measure, or accept it explicitly "
            "(accept_poor_fit: true, --accept-poor-fit)",
            detail=detail,
        )


def pivot(
    raw: RawTrace, *, tolerance_m: float = PIVOT_TOLERANCE_M, accept_poor_fit: bool = False
) -> PivotOutcome:
    """The pen's tip offset from a pivoting recording.

    Parameters
    ----------
    raw : drivers.tracking.readers.RawTrace
        Every sample as read; lost samples and samples without an orientation are left out.

    Raises
    ------
    InputFileError
        The recording has no orientations.
    DegenerateInputError
        Too few samples, or the pen did not pivot about two axes.
    PoorFitError
        The tip wandered more than ``tolerance_m`` RMS, or lies implausibly far from the rigid
        body, and ``accept_poor_fit`` is false.
    """
    from drivers.tracking.readers import require_orientations
    from recon.calibrate import pivot_calibration

    require_orientations(raw, "a pivot calibration")
    batch = raw.batch
    q = np.asarray(batch.orientation_xyzw, dtype=np.float64)
    good = (
        np.asarray(batch.valid, dtype=bool)
        & np.isfinite(batch.position_m).all(axis=1)
        & np.isfinite(q).all(axis=1)
    )
    q = q[good] / np.linalg.norm(q[good], axis=1)[:, None]
    calibration = pivot_calibration(np.asarray(batch.position_m)[good], q)
    outcome = PivotOutcome(
        calibration=calibration,
        n_lost=int(np.count_nonzero(~good)),
        rigid_body=raw.meta.get("rigid_body"),
        format=raw.format,
    )
    refuse_poor_pivot(outcome.as_json(), tolerance_m, accept_poor_fit)
    return outcome


def refuse_poor_pivot(result: dict[str, Any], tolerance_m: float, accept_poor_fit: bool) -> None:
    """Raise :class:`PoorFitError` for a pivot result (:meth:`PivotOutcome.as_json`) worse than
    ``tolerance_m``, unless ``accept_poor_fit``."""
    from recon.calibrate import pivot_fit_impossible, pivot_fit_problem
    from recon.errors import PoorFitError

    tip, rms = np.asarray(result["tip_offset_m"]), float(result["residual_rms_m"])
    impossible = pivot_fit_impossible(tip, rms)
    if impossible is not None:
        # The override widens a tolerance within what a pen can be; it never stores nonsense.
        raise PoorFitError(
            f"the pivot calibration was not stored: {impossible}. No override stores it: "
            "pivot again",
            detail={**result, "tolerance_m": tolerance_m, "overridable": False},
        )
    problem = pivot_fit_problem(tip, rms, tolerance_m)
    _refuse_poor_fit(
        "pivot calibration", problem, accept_poor_fit, {**result, "tolerance_m": tolerance_m}
    )


@dataclass(frozen=True)
class PointPairOutcome:
    """``T_base_tracker`` fitted to point pairs, with every pair's residuals."""

    fit: PointPairCalibration

    def as_json(self) -> dict[str, Any]:
        fit = self.fit
        return {
            "T_base_tracker": fit.T_a_b.tolist(),
            "residuals_m": fit.residuals_m.tolist(),
            "leave_one_out_m": [_jsonable_or_none(v) for v in fit.leave_one_out_m],
            "residual_rms_m": fit.residual_rms_m,
            "suspect": fit.suspect.tolist(),
            "used": fit.used.tolist(),
            "tolerance_m": fit.tolerance_m,
            "report": fit.lines(),
        }

    def lines(self) -> list[str]:
        return self.fit.lines()


def point_pairs(
    base_m: ArrayLike, tracker_m: ArrayLike, *, tolerance_m: float, accept_poor_fit: bool = False
) -> PointPairOutcome:
    """Fit ``T_base_tracker`` to the same points measured in both frames (metres).

    Raises
    ------
    ValueError
        Coordinates beyond a cell (a unit mix-up), or a transform beyond it.
    DegenerateInputError
        Fewer than 3 pairs, or collinear points.
    PoorFitError
        Pairs that disagree by more than ``tolerance_m``, unless ``accept_poor_fit``.
    """
    from recon.calibrate import fit_point_pairs
    from recon.transforms import check_cell_transform

    fit = fit_point_pairs(
        np.asarray(base_m, dtype=np.float64),
        np.asarray(tracker_m, dtype=np.float64),
        tolerance_m=tolerance_m,
    )
    outcome = PointPairOutcome(fit)
    _refuse_poor_fit("base calibration", fit.poor_fit(), accept_poor_fit, outcome.as_json())
    check_cell_transform(fit.T_a_b, name="the fitted T_base_tracker")
    return outcome


# -- the scanner registered by touching ------------------------------------------------------------


@dataclass(frozen=True)
class TouchOutcome:
    """The scanner's pose from touches of the workpiece, and the rests they came from.

    Attributes
    ----------
    registration : recon.touches.TouchRegistration
        With its ``judgement`` (what the touches leave at the path, or near them) when checked.
    dwells : list of recon.touches.Dwell
    notes : list of str
        Rests left out, touches left out.
    """

    registration: TouchRegistration
    dwells: list[Dwell]
    notes: list[str]

    def as_json(self) -> dict[str, Any]:
        """What the calibration file and the API keep beside the matrix."""
        reg = self.registration
        judged = reg.judgement
        return {
            "source": "touches",
            "touches_m": np.asarray(reg.touches_m).tolist(),
            "touch_times_s": [[d.t_start_s, d.t_end_s] for d in self.dwells],
            "touch_residuals_m": [_jsonable_or_none(v) for v in reg.residual_m],
            "touches_used": [bool(v) for v in reg.used],
            "fixed_motions": reg.fixed_motions,
            "free_motions": list(reg.free_motions),
            # The rule the calibration passed (recon.touches.touch_uncertainty): the largest
            # 1-sigma error the touches leave where they were judged, and each motion's share.
            "uncertainty_m": None if judged is None else _jsonable_or_none(judged.worst_m),
            "judged": None if judged is None else judged.where,
            "motions": []
            if judged is None
            else [
                {
                    "motion": m.motion,
                    "uncertainty_m": _jsonable_or_none(m.at_path_m),
                    "pinned_by_touches": m.solved,
                }
                for m in judged.motions
            ],
            "notes": list(self.notes) + list(reg.notes),
        }

    @property
    def residual_rms_m(self) -> float:
        reg = self.registration
        used = np.asarray(reg.residual_m)[np.asarray(reg.used)]
        return float(np.sqrt(np.mean(used**2)))

    def lines(self) -> list[str]:
        reg, mm = self.registration, 1e3
        first = f"{len(self.dwells)} touches found, {int(np.sum(reg.used))} used"
        if reg.judgement is not None:
            first += f"; they place the scan to {reg.judgement.summary()}"
        lines = [
            first,
            "residual per touch (mm): "
            + ", ".join(
                "-" if not np.isfinite(v) else f"{v * mm:+.3f}" + ("" if used else " (left out)")
                for v, used in zip(reg.residual_m, reg.used, strict=True)
            ),
        ]
        return lines + [f"note: {n}" for n in self.notes + list(reg.notes)]


def touch_calibration(
    touches: Recording,
    scan: Scan,
    *,
    trace: Recording | None = None,
    params: ReconParams | None = None,
    T_scan_tracker_init: ArrayLike | None = None,
    check: bool = True,
) -> TouchOutcome:
    """The scanner registered by touches (see :mod:`recon.touches`), judged by the rule a
    reconstruction applies (:func:`recon.touches.touch_uncertainty`): accepted when the 1-sigma
    error they leave is within ``params.uncertainty_tolerance_m``.

    Parameters
    ----------
    touches : recon.inputs.Recording
        The touch recording (with times): the tip rests on each of several points.
    scan : recon.inputs.Scan
    trace : recon.inputs.Recording, optional
        The path these touches are for: without ``T_scan_tracker_init`` the touches start from
        registering it to the scan, and they are judged at it, across its features. Without
        it they are judged over the scanned workpiece around them, in every direction (a path
        there may need any of them).
    params : recon.recon_params.ReconParams, optional
    T_scan_tracker_init : array_like of shape (4, 4), optional
        Where to start (identity when neither it nor a trace is given).
    check : bool
        Refuse touches that leave more than the tolerance (a reconstruction checks again against
        the path it reconstructs, and passes False).

    Raises
    ------
    recon.errors.DegenerateInputError
        No sample times, or fewer than three rests.
    recon.errors.RegistrationError
        Too few touches on the scanned surface; (TouchesInsufficientError) they leave more than
        the tolerance, each poorly pinned motion named with its millimetres.
    """
    from recon.recon_params import ReconParams
    from recon.reconstruct import touches_for_trace
    from recon.touches import (
        INITIAL_GUESS_SIGMA_M,
        ROUGH_GUESS_SIGMA_M,
        judge_near_touches,
        register_touches,
        touches_in,
    )

    params = params or ReconParams()
    found = touches_in(touches.points_m, touches.t_s)
    init = None if T_scan_tracker_init is None else np.asarray(T_scan_tracker_init, np.float64)
    if trace is not None:
        registration = touches_for_trace(
            trace,
            found.points_m,
            scan,
            params=params,
            T_scan_tracker_init=init,
            touch_sigma_m=found.sigma_m,
            check=check,
        )
    else:
        registration = register_touches(
            found.points_m,
            scan.points_m,
            T_scan_tracker_init=np.eye(4) if init is None else init,
            touch_sigma_m=found.sigma_m,
            # The frames as given are a rougher guess than a stored calibration.
            initial_sigma_m=ROUGH_GUESS_SIGMA_M if init is None else INITIAL_GUESS_SIGMA_M,
        )
        if check:
            judged = judge_near_touches(registration, scan.points_m)
            judged.check(
                params.uncertainty_tolerance_m,
                remedy="or give the path these touches are for (--trace PATH_FILE), to judge "
                "them only where it runs and in the directions its features need",
            )
            registration = replace(registration, judgement=judged)
    dwells, notes = found.dwells, found.notes
    return TouchOutcome(registration=registration, dwells=dwells, notes=notes)


# -- reconstruction --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReconstructOutcome:
    """A reconstruction and what its preview draws.

    Attributes
    ----------
    reconstruction : recon.results.Reconstruction
    scan_tracker_m : ndarray of shape (M, 3), or None
        The scan moved into the tracker frame with the transform the reconstruction used (the
        registration's, else the given one), so the preview draws it where the path saw it.
    """

    reconstruction: Reconstruction
    scan_tracker_m: FloatArray | None

    def summary(self) -> dict[str, Any]:
        """The artifact's summary (see :class:`service.artifacts.ReconstructionSummary`)."""
        from recon.results import PointMode, PointReason

        recon = self.reconstruction
        reg = recon.registration
        T = recon.T_scan_tracker
        reasons = (
            {}
            if recon.reason is None
            else {
                r.label: int(np.count_nonzero(recon.reason == int(r)))
                for r in PointReason
                if r is not PointReason.NONE and np.any(recon.reason == int(r))
            }
        )
        return {
            "n_points": len(recon),
            "modes": {m.label: recon.count(m) for m in PointMode},
            "reasons": reasons,
            "mean_displacement_m": float(recon.displacement_m.mean()),
            "max_displacement_m": float(recon.displacement_m.max()),
            "segments": [
                {
                    k: (_jsonable_or_none(v) if isinstance(v, float) else v)
                    for k, v in asdict(s).items()
                }
                for s in recon.segments
            ],
            "n_pieces": int(recon.point_pieces()[-1]) + 1,
            "T_scan_tracker": None if T is None else np.asarray(T).tolist(),
            "registration": None
            if reg is None
            else {
                "T_scan_tracker": reg.T_scan_tracker.tolist(),
                "rmse_m": reg.rmse_m,
                "fitness": reg.fitness,
                "n_pairs": reg.n_pairs,
                "target": str(reg.target),
                "constrained_dof": reg.constrained_dof,
                "path_moved_mean_m": _jsonable_or_none(reg.path_moved_mean_m),
                "path_moved_max_m": _jsonable_or_none(reg.path_moved_max_m),
                "path_moved_off_feature_median_m": _jsonable_or_none(
                    reg.path_moved_off_feature_median_m
                ),
                "reason": reg.reason,
                "alternative": None
                if reg.alternative is None
                else {
                    k: (_jsonable_or_none(v) if isinstance(v, float) else v)
                    for k, v in reg.alternative.items()
                },
            },
            "corners": [asdict(c) for c in recon.corners],
            "demonstrations": [
                {**asdict(d), "mean_offset_m": _jsonable_or_none(d.mean_offset_m)}
                for d in recon.demonstrations
            ],
            "uncertainty_mean_m": None
            if recon.uncertainty_m is None
            else _jsonable_or_none(float(np.mean(recon.uncertainty_m))),
            "uncertainty_max_m": None
            if recon.uncertainty_m is None
            else _jsonable_or_none(np.max(recon.uncertainty_m)),
            "notes": list(recon.notes),
        }

    def lines(self) -> list[str]:
        """A few lines on what the reconstruction did (the command line prints them)."""
        from recon.results import PointMode

        recon, mm = self.reconstruction, 1e3
        counts = ", ".join(
            f"{recon.count(mode)} {mode.label}" for mode in PointMode if recon.count(mode)
        )
        lines = [
            f"{len(recon)} points ({counts}) in {len(recon.segments)} segment(s); "
            f"moved {np.mean(recon.displacement_m) * mm:.2f} mm on average, "
            f"{np.max(recon.displacement_m) * mm:.2f} mm at most",
        ]
        if recon.uncertainty_m is not None:
            lines.append(
                f"uncertainty (1 sigma, across the path): {np.mean(recon.uncertainty_m) * mm:.2f} "
                f"mm on average, {np.max(recon.uncertainty_m) * mm:.2f} mm at most"
            )
        for index, segment in enumerate(recon.segments):
            if segment.kind == "edge":
                nxt = (
                    "no other edge near it"
                    if segment.next_edge_m is None
                    else f"the next edge over {segment.next_edge_m * mm:.1f} mm away"
                )
                far = (
                    ""
                    if segment.edge_distance_m is None
                    else (f", {segment.edge_distance_m * mm:.2f} mm from the trace on median")
                )
                lines.append(
                    f"segment {index}: follows the scan's edge along "
                    f"{segment.edge_fraction * 100:.0f} % of it{far}; {nxt}"
                    + (
                        f"; {segment.fallen_back * 100:.0f} % of its points kept the trace"
                        if segment.fallen_back
                        else ""
                    )
                )
        for corner in recon.corners:
            lines.append(f"corner at point {corner.index}: {corner.reason}")
        reg = recon.registration
        if reg is not None and reg.target == "touches":
            lines.append(
                f"scanner registered by touches: {reg.reason}; the path moved "
                f"{reg.path_moved_mean_m * mm:.2f} mm on average from the initial placement, "
                f"touch residual {reg.rmse_m * mm:.3f} mm RMS"
            )
        elif reg is not None:
            lines.append(
                f"registered to the scan's {reg.target}: the path moved "
                f"{reg.path_moved_mean_m * mm:.2f} mm on average, "
                f"{reg.path_moved_max_m * mm:.2f} mm at most from the initial placement"
                + _off_feature(reg, mm)
                + f", residual {reg.rmse_m * mm:.2f} mm RMS, "
                f"{reg.fitness * 100:.0f} % of the path paired, {reg.constrained_dof}/6 motions "
                f"fixed ({reg.reason})"
            )
        lines += [f"note: {note}" for note in recon.notes]
        return lines

    def write_preview(self, path: str | Path, *, title: str) -> None:
        """A PNG of the scan, the trace and the result, with the displacements."""
        from service.plots import plot_reconstruction

        plot_reconstruction(path, self.reconstruction, scan_m=self.scan_tracker_m, title=title)


def reconstruct(
    recording: Recording | list[Recording] | tuple[Recording, ...],
    scan: Scan | None,
    *,
    params: ReconParams,
    T_scan_tracker_init: ArrayLike | None = None,
    touches: Recording | None = None,
) -> ReconstructOutcome:
    """Reconstruct a trace with the scan's structure (see :func:`recon.reconstruct.reconstruct`).

    Parameters
    ----------
    recording : recon.inputs.Recording or list of them
        Several recordings are demonstrations of one path, fused first.
    scan : recon.inputs.Scan or None
    params : recon.recon_params.ReconParams
    T_scan_tracker_init : array_like of shape (4, 4), optional
        The stored calibration: registration's initial guess, or the transform itself when
        ``params.register`` is False.
    touches : recon.inputs.Recording, optional
        A touch recording: the scanner is registered by it (started from the calibration, or
        from registering the trace) instead of by the trace.
    """
    from recon.reconstruct import reconstruct as run
    from recon.transforms import apply_transform, invert_transform

    init = None if T_scan_tracker_init is None else np.asarray(T_scan_tracker_init, np.float64)
    recordings = recording if isinstance(recording, list | tuple) else [recording]
    touched = None
    if touches is not None and scan is not None and params.uses_scan:
        # Started from the first demonstration's registration; checked against the path
        # actually reconstructed (the fused one, with several) by the reconstruction itself.
        touched = touch_calibration(
            touches, scan, trace=recordings[0], params=params, T_scan_tracker_init=init,
            check=False,
        )  # fmt: skip
    path = recordings if len(recordings) > 1 else recordings[0]
    recon = run(
        path,
        scan,
        params=params,
        T_scan_tracker_init=init,
        touches=None if touched is None else touched.registration,
    )
    if touched is not None and touched.notes:
        recon = replace(recon, notes=(*recon.notes, *touched.notes))
    scan_tracker = None
    if scan is not None:
        T = recon.T_scan_tracker if recon.T_scan_tracker is not None else init
        scan_tracker = (
            np.asarray(scan.points_m)
            if T is None
            else apply_transform(invert_transform(np.asarray(T)), scan.points_m)
        )
    return ReconstructOutcome(reconstruction=recon, scan_tracker_m=scan_tracker)


# -- planning --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlacedScan:
    """A scan's structure near a path, and where the scan is relative to the tracker.

    Attributes
    ----------
    model : recon.scan_model.ScanModel
        Scan frame.
    T_scan_tracker : ndarray of shape (4, 4)
    registration : recon.results.Registration or None
        Set when the transform had to be found by registering the path here.
    """

    model: ScanModel
    T_scan_tracker: FloatArray
    registration: Registration | None


def place_scan(
    scan: Scan, path: ReconstructedPath, *, recon_params: ReconParams | None = None
) -> PlacedScan:
    """The scan model around a reconstructed path, placed with the path's ``T_scan_tracker``.

    For a path that does not say where the scan was (a reconstruction CSV from the command line
    without ``--scan-from-tracker``), the path is registered to the scan first, as the
    reconstruction did; the result says so.
    """
    from recon.inputs import Recording
    from recon.plan import scan_model_for_path
    from recon.recon_params import ReconParams
    from recon.reconstruct import plan_segments, prepare_scan_model

    params = recon_params or ReconParams()
    if path.T_scan_tracker is not None:
        T = np.asarray(path.T_scan_tracker, dtype=np.float64)
        model = scan_model_for_path(scan, path.points_m, T_scan_tracker=T, recon_params=params)
        return PlacedScan(model=model, T_scan_tracker=T, registration=None)
    segments = plan_segments(Recording(points_m=path.points_m, piece=path.piece), params)
    prepared = prepare_scan_model(
        segments.resampled.points_m, scan, segments.bounds, params, T_scan_tracker_init=None
    )
    return PlacedScan(
        model=prepared.model,
        T_scan_tracker=prepared.T_scan_tracker,
        registration=prepared.registration,
    )


#: The limits every planned sample was checked against, in words.
LIMITS_CHECKED = "joint position, speed and acceleration limits at every sample"


def _teachpath_version() -> str:
    """The version that planned it, for the record ("0" when not installed)."""
    from importlib import metadata

    try:
        return metadata.version("teachpath")
    except metadata.PackageNotFoundError:
        return "0"


def _smallest_clearance_m(report: CollisionReport | None) -> float | None:
    """The closest approach a collision report found (None: not checked, or no samples)."""
    if report is None or not len(report.clearance_m):
        return None
    return float(np.min(report.clearance_m))


def _collision_checks(report: CollisionReport | None) -> list[str]:
    """The collision check passed, in words (none when no check was made)."""
    if report is None:
        return []
    smallest = _smallest_clearance_m(report)
    smallest = np.inf if smallest is None else smallest
    return [
        f"no collision of the arm or the tool with the {', '.join(report.obstacles)} "
        f"(smallest clearance {smallest * 1e3:.1f} mm, margin {report.margin_m * 1e3:.1f} mm)"
    ]


@dataclass(frozen=True)
class PlanOutcome:
    """A planned trajectory and the transform its tool axis was taken with."""

    plan: Plan
    T_scan_tracker: FloatArray | None
    T_base_tracker: FloatArray | None = None
    start_from: str = "given"

    @property
    def trajectory(self) -> JointTrajectory:
        return self.plan.trajectory

    def checks(self) -> list[str]:
        """The checks the plan passed, in words (what the trajectory file and the pendant show)."""
        plan = self.plan
        passed = [
            LIMITS_CHECKED,
            "wrist, elbow and shoulder singularity margins along the path",
            f"one IK configuration throughout ({plan.configuration.words()})",
        ]
        return passed + _collision_checks(plan.collision)

    def summary(self) -> dict[str, Any]:
        """The artifact's summary (see :class:`service.artifacts.TrajectorySummary`)."""
        plan, traj = self.plan, self.plan.trajectory
        joints = plan.joints
        params = plan.params
        clearance = _smallest_clearance_m(plan.collision)
        return {
            "phase_durations_s": traj.phase_durations_s(),
            "phase_max_tcp_speed_m_s": traj.phase_max_tcp_speed_m_s(),
            "start_q_rad": [float(v) for v in plan.start_q_rad],
            "start_from": self.start_from,
            "configuration": plan.configuration.words(),
            "approach_m": plan.approach_m,
            "tcp_pose": [float(v) for v in params.tcp],
            "payload_kg": params.payload_kg,
            "payload_cog_m": list(params.payload_cog_m),
            "T_base_tracker": None
            if self.T_base_tracker is None
            else np.asarray(self.T_base_tracker).tolist(),
            "min_clearance_m": clearance if clearance is None or np.isfinite(clearance) else None,
            "checks": self.checks(),
            "teachpath": _teachpath_version(),
            "robot": traj.robot,
            "kinematics": traj.arm.kinematics_words,
            "calibration": None if traj.calibration is None else traj.calibration.as_dict(),
            "requested_speed_m_s": traj.requested_speed_m_s,
            "duration_s": traj.duration_s,
            "n_samples": len(traj),
            "rate_hz": 1.0 / traj.period_s,
            "path_length_m": float(plan.tool.arc_length_m[-1]),
            "n_pieces": plan.n_pieces,
            "tool_axis_from": plan.tool.source,
            "ik_branch": joints.branch,
            "min_limit_margin_rad": float(joints.limit_margin_rad.min()),
            "min_wrist_singularity": float(joints.wrist_singularity.min()),
            "min_elbow_singularity": float(joints.elbow_singularity.min()),
            "min_shoulder_margin_m": float(joints.shoulder_margin_m.min()),
            "speed_drops": [asdict(d) for d in traj.speed_drops],
            "T_scan_tracker": None
            if self.T_scan_tracker is None
            else np.asarray(self.T_scan_tracker).tolist(),
            "report": plan.report_lines(),
        }

    def lines(self) -> list[str]:
        return self.plan.report_lines()


def plan(
    path: ReconstructedPath,
    *,
    params: PlanParams,
    T_base_tracker: ArrayLike | None = None,
    scan_model: ScanModel | None = None,
    recon_params: ReconParams | None = None,
    scan: Scan | None = None,
    keep_out_boxes: Sequence[Sequence[float]] = (),
    cell_planes: Sequence[Sequence[float]] = (),
    start_from: str = "given",
    calibration: DHCalibration | None = None,
) -> PlanOutcome:
    """The whole motion along a reconstructed path, checked against the cell.

    Parameters
    ----------
    path : recon.paths.ReconstructedPath
        The reconstruction (tracker frame) with the ``T_scan_tracker`` it used.
    params : recon.plan_params.PlanParams
    T_base_tracker : array_like of shape (4, 4), optional
        Where the tracker frame is in the robot's base frame (default: the same frame).
    scan_model : recon.scan_model.ScanModel, optional
        The scan's structure near the path (scan frame), for the tool axis from the scan's
        normals. It is used with ``path.T_scan_tracker``: nothing is registered again.
    recon_params : recon.recon_params.ReconParams, optional
        The reconstruction's parameters (the radii of the normal fits); default the defaults.
    scan : recon.inputs.Scan, optional
        The workpiece, for the collision check (placed with ``path.T_scan_tracker`` and
        ``T_base_tracker``).
    keep_out_boxes : sequence of 6 floats each
        ``x_min, y_min, z_min, x_max, y_max, z_max`` in the base frame (m).
    cell_planes : sequence of 4 floats each
        ``nx, ny, nz, d``: surfaces besides the mounting one, base frame; the arm keeps to
        ``n . p >= d`` (m).
    start_from : str
        Where ``params.start_q_rad`` came from ("arm", "home", "given"), for the record.
    calibration : recon.kinematics.DHCalibration, optional
        The arm's own kinematics calibration (default: UR's nominal model).

    Raises
    ------
    ValueError
        A scan model without the transform it belongs to, a missing orientation source, or a
        calibration that is not this arm type's.
    InfeasibleTrajectoryError
        The arm cannot follow the path; ``CollisionError`` when the motion collides.
    """
    from recon.plan import approach_in, normals_from_scan, plan_path

    T_base = None if T_base_tracker is None else np.asarray(T_base_tracker, dtype=np.float64)
    normals = None
    T_scan_tracker = None
    if scan_model is not None and params.orientation in ("auto", "scan"):
        if path.T_scan_tracker is None:
            raise ValueError(
                "the reconstruction does not record where the scan was (T_scan_tracker): "
                "reconstruct it again with the scan, or give the transform"
            )
        T_scan_tracker = np.asarray(path.T_scan_tracker, dtype=np.float64)
        normals = normals_from_scan(
            path.points_m,
            path.mode,
            scan_model,
            T_scan_tracker=T_scan_tracker,
            approach_tracker=approach_in(T_base, params.approach_direction),
            recon_params=recon_params,
        )
    result = plan_path(
        path.points_m,
        params=params,
        T_base_tracker=T_base,
        normals=normals,
        pen_xyzw=path.orientations_xyzw,
        cell=cell_for(scan, path.T_scan_tracker, T_base, keep_out_boxes, cell_planes),
        piece=path.piece,
        start_from=start_from,
        calibration=calibration,
    )
    return PlanOutcome(
        plan=result, T_scan_tracker=T_scan_tracker, T_base_tracker=T_base, start_from=start_from
    )


@dataclass(frozen=True)
class MoveOutcome:
    """A move to a plan's start and the plan it leads to.

    Attributes
    ----------
    move : recon.plan.MovePlan
    target_id : str
        The plan the move leads to the start of.
    target_summary : dict
        That plan's summary (its configuration, IK branch and tracker-to-base transform).
    start_from : str
        Where the move's first joints came from ("arm" or "home").
    """

    move: MovePlan
    target_id: str
    target_summary: dict[str, Any]
    start_from: str = "arm"

    @property
    def trajectory(self) -> JointTrajectory:
        """The move's samples (:class:`recon.trajectory.JointTrajectory`)."""
        return self.move.trajectory

    def summary(self) -> dict[str, Any]:
        """The artifact's summary: a trajectory's (:class:`service.artifacts.TrajectorySummary`)
        with ``move_to_start_of`` naming the plan; no traced path, no process phase."""
        move, traj, target = self.move, self.move.trajectory, self.target_summary
        clearance = _smallest_clearance_m(move.collision)
        checks = [LIMITS_CHECKED, *_collision_checks(move.collision)]
        return {
            "move_to_start_of": self.target_id,
            "phase_durations_s": traj.phase_durations_s(),
            "phase_max_tcp_speed_m_s": traj.phase_max_tcp_speed_m_s(),
            "start_q_rad": [float(v) for v in move.start_q_rad],
            "goal_q_rad": [float(v) for v in move.goal_q_rad],
            "start_from": self.start_from,
            "configuration": target.get("configuration"),
            # The straight move off the workpiece the move starts with, if any.
            "approach_m": move.retract_m or None,
            "tcp_pose": [float(v) for v in move.params.tcp],
            "payload_kg": move.params.payload_kg,
            "payload_cog_m": list(move.params.payload_cog_m),
            "T_base_tracker": target.get("T_base_tracker"),
            "min_clearance_m": clearance if clearance is None or np.isfinite(clearance) else None,
            "checks": checks,
            "teachpath": _teachpath_version(),
            "robot": traj.robot,
            "kinematics": traj.arm.kinematics_words,
            "calibration": None if traj.calibration is None else traj.calibration.as_dict(),
            "requested_speed_m_s": traj.requested_speed_m_s,
            "duration_s": traj.duration_s,
            "n_samples": len(traj),
            "rate_hz": 1.0 / traj.period_s,
            "path_length_m": 0.0,
            "n_pieces": 0,
            "tool_axis_from": "none: a joint move",
            "ik_branch": int(target.get("ik_branch", -1)),
            **move.margins(),
            "speed_drops": [],
            "T_scan_tracker": None,
            "report": move.report_lines(),
        }


def move_to_start(
    q_from_rad: ArrayLike,
    target: JointTrajectory,
    *,
    target_id: str,
    target_summary: dict[str, Any],
    params: PlanParams,
    scan: Scan | None = None,
    T_scan_tracker: FloatArray | None = None,
    T_base_tracker: ArrayLike | None = None,
    keep_out_boxes: Sequence[Sequence[float]] = (),
    cell_planes: Sequence[Sequence[float]] = (),
    start_from: str = "arm",
    calibration: DHCalibration | None = None,
) -> MoveOutcome:
    """A move of its own from where the arm is to ``target``'s first sample, checked against
    the cell the target is checked against (its scan placed as it was planned).

    Parameters
    ----------
    q_from_rad : array-like of shape (6,)
        Where the arm is.
    target : recon.trajectory.JointTrajectory
        The plan to move to the start of.
    target_id : str
    target_summary : dict
        Its summary (its configuration, IK branch and tracker-to-base transform are the move's).
    params : recon.plan_params.PlanParams
        The target's parameters (tool, transit speeds, clearance).
    scan, T_scan_tracker, T_base_tracker, keep_out_boxes, cell_planes
        The cell, as :func:`cell_for` takes them.
    start_from : str
        Where ``q_from_rad`` came from ("arm" or "home").
    calibration : recon.kinematics.DHCalibration, optional

    Returns
    -------
    MoveOutcome

    Raises
    ------
    ValueError
        Joints outside the arm's limits, or a scan whose place is unknown.
    CollisionError
        The move collides whichever way it is made.
    """
    from recon.plan import plan_move, ways_back

    T_base = None if T_base_tracker is None else np.asarray(T_base_tracker, dtype=np.float64)
    q_from = np.asarray(q_from_rad, dtype=np.float64)
    move = plan_move(
        q_from,
        target.q_rad[0],
        params=params,
        cell=cell_for(scan, T_scan_tracker, T_base, keep_out_boxes, cell_planes),
        calibration=calibration,
        # Where the direct move collides: by the target's approach start, or back along its path.
        ways=ways_back(target, q_from, params, calibration=calibration),
    )
    return MoveOutcome(move, target_id, target_summary, start_from)


def cell_for(
    scan: Scan | None,
    T_scan_tracker: FloatArray | None,
    T_base_tracker: FloatArray | None,
    keep_out_boxes: Sequence[Sequence[float]] = (),
    cell_planes: Sequence[Sequence[float]] = (),
) -> Cell:
    """The cell a plan is checked against (base frame): the mounting surface (the base's z = 0
    plane), other planes of the cell, the keep-out boxes and the scanned workpiece.

    Parameters
    ----------
    scan : recon.inputs.Scan or None
        The workpiece (scan frame).
    T_scan_tracker : ndarray of shape (4, 4), or None
        Where the scan is relative to the tracker (needed with a scan).
    T_base_tracker : ndarray of shape (4, 4), or None
        Where the tracker frame is in the robot's base frame (None: the same frame).
    keep_out_boxes : sequence of 6 floats each
        ``x_min, y_min, z_min, x_max, y_max, z_max`` in the base frame (m).
    cell_planes : sequence of 4 floats each
        ``nx, ny, nz, d``: the arm keeps to ``n . p >= d`` (base frame, m).

    Raises
    ------
    ValueError
        A scan whose place (``T_scan_tracker``) is unknown: it is never left out of the check
        silently (register the path to it, or give the transform).
    """
    from recon.collision import Box, Cell, HalfSpace
    from recon.transforms import apply_transform, invert_transform

    boxes = tuple(
        Box(
            min_m=np.asarray(box[:3], dtype=np.float64),
            max_m=np.asarray(box[3:], dtype=np.float64),
            name=f"keep-out box {index + 1}",
        )
        for index, box in enumerate(keep_out_boxes)
    )
    points = None
    if scan is not None and T_scan_tracker is None:
        raise ValueError(
            "the scan's place relative to the tracker (T_scan_tracker) is unknown, so the "
            "motion cannot be checked against the workpiece: plan along a reconstruction made "
            "with the scan, give the transform (--scan-from-tracker), or leave the scan out"
        )
    if scan is not None:
        T_base = np.eye(4) if T_base_tracker is None else np.asarray(T_base_tracker)
        T_base_scan = T_base @ invert_transform(np.asarray(T_scan_tracker, dtype=np.float64))
        points = apply_transform(T_base_scan, np.asarray(scan.points_m))
    # n . p >= d with n as given: the half-space of the unit normal at d / |n|.
    planes = tuple(
        HalfSpace(
            normal=np.asarray(plane[:3], dtype=np.float64),
            offset_m=plane[3] / max(float(np.linalg.norm(plane[:3])), 1e-300),
            name=f"cell plane {index + 1}",
        )
        for index, plane in enumerate(cell_planes)
    )
    return Cell(planes=planes, boxes=boxes, scan_points_m=points)


# -- execution -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExecutionOutcome:
    """What an execution showed (dry run or real arm) and what it recorded."""

    report: ExecutionReport
    record: ExecutionRecord | None
    backend: str
    tolerance_m: float

    def summary(self) -> dict[str, Any]:
        """The artifact's summary (see :class:`service.artifacts.ExecutionSummary`)."""
        report = asdict(self.report)
        report["faults"] = list(report["faults"])
        report["speed_drops"] = [dict(d) for d in report["speed_drops"]]
        return {
            **report,
            "backend": self.backend,
            "tolerance_m": self.tolerance_m,
            "report": self.report.lines(),
        }

    def lines(self) -> list[str]:
        return self.report.lines()

    @property
    def passed(self) -> bool:
        return bool(self.report.completed and not self.report.faults)


def dry_run(
    trajectory: JointTrajectory, *, mode: str = "servoj", tolerance_m: float = 5e-4
) -> ExecutionOutcome:
    """Execute ``trajectory`` on the simulated arm, faster than real time.

    Raises
    ------
    InfeasibleTrajectoryError
        Its samples break the arm's limits (checked first: a file is not trusted).
    """
    from drivers.robot.clock import FakeClock
    from drivers.robot.dryrun import dry_run as run
    from drivers.robot.sim import SimBackend, SimConfig
    from recon.sample_check import require_within_limits

    require_within_limits(trajectory, what="dry-run it")
    config = SimConfig(robot=trajectory.robot, q_start_rad=tuple(trajectory.q_rad[0]))
    sim = SimBackend(config, clock=FakeClock())
    report = run(trajectory, backend=sim, mode=mode, tolerance_m=tolerance_m)
    return ExecutionOutcome(
        report=report, record=sim.last_record, backend="sim", tolerance_m=tolerance_m
    )
