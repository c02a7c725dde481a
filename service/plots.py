"""Pictures of a reconstruction: the scene in 3-D and the residuals along the path (Fig. 5)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # files only; never a window

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from drivers.files import atomic_path  # noqa: E402
from recon.arrays import FloatArray  # noqa: E402
from recon.metrics import distance_to_curve  # noqa: E402
from recon.results import Reconstruction

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from mpl_toolkits.mplot3d.axes3d import Axes3D
    from numpy.typing import NDArray

    from recon.trajectory import JointTrajectory

#: Scan points drawn at most (a dense scan would bury the paths and take seconds to render).
MAX_SCAN_POINTS = 20000


def _piece_breaks(piece: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A function that puts a NaN row between pieces of (N, 3) points, so lines break there."""
    starts = np.flatnonzero(np.diff(piece)) + 1

    def broken(points: np.ndarray) -> np.ndarray:
        return np.insert(np.asarray(points, dtype=np.float64), starts, np.nan, axis=0)

    return broken


def plot_reconstruction(
    path: str | Path,
    recon: Reconstruction,
    *,
    scan_m: FloatArray | None = None,
    truth_m: FloatArray | None = None,
    title: str = "",
    seed: int = 0,
) -> None:
    """Write a PNG: scan (subsampled), input and reconstructed path in 3-D, and a residual plot.

    Parameters
    ----------
    path : path
        PNG file; appears only when complete.
    recon : Reconstruction
    scan_m : ndarray of shape (M, 3), optional
        The scan in the reconstruction's (tracker) frame.
    truth_m : ndarray of shape (G, 3), optional
        Ground truth: the residual plot then shows the error of input and result against it
        (as the paper's Fig. 5); otherwise it shows how far each point moved.
    title : str
    seed : int
        For the random subsample of the scan.
    """
    mm = 1e3
    fig = plt.figure(figsize=(13, 5.5))
    ax3d = fig.add_subplot(1, 2, 1, projection="3d")
    if scan_m is not None and len(scan_m):
        shown = scan_m
        if len(scan_m) > MAX_SCAN_POINTS:
            pick = np.random.default_rng(seed).choice(len(scan_m), MAX_SCAN_POINTS, replace=False)
            shown = scan_m[pick]
        ax3d.scatter(*(shown.T * mm), s=0.6, c="0.45", alpha=0.35, linewidths=0, label="scan")
    breaks = _piece_breaks(recon.point_pieces())
    ax3d.plot(
        *(breaks(recon.input_points_m).T * mm), c="tab:blue", lw=0.8, label="input (resampled)"
    )
    ax3d.plot(*(breaks(recon.points_m).T * mm), c="tab:green", lw=1.4, label="reconstruction")
    if truth_m is not None:
        ax3d.plot(*(truth_m.T * mm), c="k", lw=0.8, ls="--", label="ground truth")
    ax3d.set_xlabel("x [mm]")
    ax3d.set_ylabel("y [mm]")
    ax3d.set_zlabel("z [mm]")
    ax3d.legend(loc="upper left", fontsize=8)
    _equal_axes(ax3d, recon.points_m * mm)

    ax = fig.add_subplot(1, 2, 2)
    # Arc length along the traced path: the stretch between two pieces was not traced.
    steps = np.linalg.norm(np.diff(recon.input_points_m, axis=0), axis=1)
    steps[np.diff(recon.point_pieces()) != 0] = 0.0
    arc = np.concatenate(([0.0], np.cumsum(steps))) * mm
    if truth_m is not None:
        ax.plot(
            arc,
            distance_to_curve(recon.input_points_m, truth_m) * mm,
            c="tab:blue",
            lw=0.8,
            label="input",
        )
        ax.plot(
            arc,
            distance_to_curve(recon.points_m, truth_m) * mm,
            c="tab:green",
            lw=1.2,
            label="reconstruction",
        )
        ax.set_ylabel("distance to ground truth [mm]")
    else:
        ax.plot(arc, recon.displacement_m * mm, c="tab:green", lw=1.2, label="displacement")
        ax.set_ylabel("distance moved [mm]")
    for segment in recon.segments[1:]:
        ax.axvline(arc[segment.start], c="0.6", lw=0.6, ls=":")
    for start in np.flatnonzero(np.diff(recon.point_pieces())) + 1:
        ax.axvline(arc[start], c="tab:red", lw=0.8, ls="--")  # the arm lifts here
    ax.set_xlabel("arc length along the path [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title or "teachpath reconstruction")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _equal_axes(ax: Axes3D, points: FloatArray) -> None:
    """Same scale on all three axes, so a circle looks round."""
    centre = (points.max(axis=0) + points.min(axis=0)) / 2
    half = max(float(np.ptp(points, axis=0).max()) / 2, 1e-6)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)


#: Colours of the motion's phases in the plan picture.
_PHASE_COLOURS = {
    "transit": "0.85",
    "approach": "#cfe3ff",
    "process": "white",
    "retract": "#ffe2c6",
    "return": "0.85",
}


def plot_plan(path: str | Path, trajectory: JointTrajectory, *, title: str = "") -> None:
    """Write the plan's picture: TCP speed along the motion against the requested speed, with
    each slow-down and its cause; joint angles against their limits; joint speeds as a share of
    their limits. The phases (transit, approach, process, retract) are shaded.

    Parameters
    ----------
    path : str or Path
        The PNG to write (written whole or not at all).
    trajectory : recon.trajectory.JointTrajectory
        ``t_s`` (M,), ``q_rad`` and ``qd_rad_s`` (M, 6), ``tcp_m`` (M, 3), its phases and
        ``speed_drops`` (metres of process path).
    title : str
    """
    from recon.paths import Phase
    from service.preview import speed_drop_times, tcp_speed_m_s

    arm = trajectory.arm
    t = trajectory.t_s
    phases = trajectory.phases
    speed_mm_s = tcp_speed_m_s(trajectory) * 1e3
    # A Figure of its own, not pyplot's global state: the service draws it in request threads.
    fig = Figure(figsize=(10, 9))
    ax_speed, ax_q, ax_qd = fig.subplots(3, 1, sharex=True)
    for ax in (ax_speed, ax_q, ax_qd):
        _shade_phases(ax, t, phases)
        ax.grid(alpha=0.3)
    ax_speed.plot(t, speed_mm_s, c="tab:blue", lw=1.2, label="TCP speed")
    ax_speed.axhline(
        trajectory.requested_speed_m_s * 1e3, c="tab:green", ls="--", lw=1, label="requested"
    )
    for drop in speed_drop_times(trajectory):
        ax_speed.axvspan(drop["start_s"], drop["end_s"], color="tab:red", alpha=0.15)
        ax_speed.annotate(
            f"{drop['min_speed_m_s'] * 1e3:.0f} mm/s: {drop['cause']}",
            ((drop["start_s"] + drop["end_s"]) / 2, drop["min_speed_m_s"] * 1e3),
            fontsize=7,
            color="tab:red",
            xytext=(0, -14),
            textcoords="offset points",
            ha="center",
        )
    process = np.flatnonzero(phases == int(Phase.PROCESS))
    # The scale of the process path: the joint moves of the transit are much faster at the TCP
    # (half a metre a second) and would flatten it; their peak is named instead.
    requested_mm_s = trajectory.requested_speed_m_s * 1e3
    process_top = speed_mm_s[process].max() if len(process) else requested_mm_s
    top = 1.6 * max(requested_mm_s, process_top)
    ax_speed.set_ylim(0, top)
    if speed_mm_s.max() > top:
        ax_speed.text(
            t[int(np.argmax(speed_mm_s))], top * 0.93, f"peak {speed_mm_s.max():.0f} mm/s",
            fontsize=7, ha="center", va="top",
        )  # fmt: skip
    _name_phases(ax_speed, t, phases, top)
    ax_speed.set_ylabel("TCP speed [mm/s]")
    ax_speed.legend(fontsize=8, loc="lower right")
    degrees = np.degrees(trajectory.q_rad)
    for j in range(6):
        (line,) = ax_q.plot(t, degrees[:, j], lw=1, label=f"q{j}")
        for limit in (arm.q_min_rad[j], arm.q_max_rad[j]):
            if np.isfinite(limit) and abs(limit) < 2 * np.pi + 1e-9:
                ax_q.axhline(np.degrees(limit), c=line.get_color(), lw=0.5, ls=":")
    ax_q.set_ylabel("joint angle [deg] (limits dotted)")
    ax_q.legend(fontsize=7, ncol=6, loc="upper right")
    share = np.abs(trajectory.qd_rad_s) / arm.qd_max_rad_s
    for j in range(6):
        ax_qd.plot(t, share[:, j] * 100, lw=1, label=f"q{j}")
    ax_qd.axhline(100, c="tab:red", lw=1, ls="--")
    ax_qd.set_ylabel("joint speed [% of limit]")
    ax_qd.set_xlabel("time [s]")
    ax_qd.legend(fontsize=7, ncol=6, loc="upper right")
    fig.suptitle(title or f"teachpath plan ({trajectory.robot})")
    fig.tight_layout()
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def _phase_spans(phases: NDArray[np.int8]) -> Iterator[tuple[int, int, str]]:
    """(first, last sample, label) of each run of one phase."""
    from recon.paths import Phase

    changes = np.flatnonzero(np.diff(phases)) + 1
    for start, stop in zip(np.r_[0, changes], np.r_[changes, len(phases)], strict=True):
        yield int(start), int(stop) - 1, Phase(int(phases[start])).label


def _shade_phases(ax: Axes, t: FloatArray, phases: NDArray[np.int8]) -> None:
    """Shade each phase's time span."""
    for first, last, label in _phase_spans(phases):
        ax.axvspan(t[first], t[last], color=_PHASE_COLOURS.get(label, "white"), lw=0)


def _name_phases(ax: Axes, t: FloatArray, phases: NDArray[np.int8], top: float) -> None:
    """Name each phase at the top of its span."""
    for first, last, label in _phase_spans(phases):
        ax.text((t[first] + t[last]) / 2, top * 0.99, label, fontsize=7, ha="center", va="top")
