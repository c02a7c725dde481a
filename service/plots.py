"""Pictures of a reconstruction: the scene in 3-D and the residuals along the path (Fig. 5)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never a window

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from drivers.files import atomic_path  # noqa: E402
from recon.metrics import distance_to_curve  # noqa: E402
from recon.types import FloatArray, Reconstruction  # noqa: E402

#: Scan points drawn at most (a dense scan would bury the paths and take seconds to render).
MAX_SCAN_POINTS = 20000


def _piece_breaks(piece: np.ndarray):
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
    breaks = _piece_breaks(recon.piece)
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
    steps[np.diff(recon.piece) != 0] = 0.0
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
    for start in np.flatnonzero(np.diff(recon.piece)) + 1:
        ax.axvline(arc[start], c="tab:red", lw=0.8, ls="--")  # the arm lifts here
    ax.set_xlabel("arc length along the path [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(title or "teachpath reconstruction")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _equal_axes(ax, points: FloatArray) -> None:
    """Same scale on all three axes, so a circle looks round."""
    centre = (points.max(axis=0) + points.min(axis=0)) / 2
    half = max(float(np.ptp(points, axis=0).max()) / 2, 1e-6)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
