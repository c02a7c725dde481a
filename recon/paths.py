"""The path on its way to motion: the reconstructed path, tool poses, joint paths, the phases
of a motion and where its speed drops.

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray, frozen_array, piece_labels


@dataclass(frozen=True)
class ReconstructedPath:
    """What planning needs of a reconstruction, however it was stored (an artifact, a CSV).

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        The reconstructed path, tracker frame.
    mode : ndarray of shape (N,), int8
        :class:`PointMode` per point.
    orientations_xyzw : ndarray of shape (N, 4), or None
        The pen's orientations, tracker frame, scalar last.
    T_scan_tracker : ndarray of shape (4, 4), or None
        The transform the reconstruction used between tracker and scan (None: no scan, or not
        recorded).
    piece : ndarray of shape (N,), int
        The trace's piece of each point (all zeros: one piece); the arm lifts between pieces.
    """

    points_m: FloatArray
    mode: NDArray[np.int8]
    orientations_xyzw: FloatArray | None = None
    T_scan_tracker: FloatArray | None = None
    piece: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "piece", piece_labels(self.piece, len(self.points_m)))


@dataclass(frozen=True)
class ToolPath:
    """TCP poses along a path.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        TCP positions.
    orientations_xyzw : ndarray of shape (N, 4)
        TCP orientations as unit quaternions, scalar last; the tool's z-axis points from the
        flange towards the workpiece, its x-axis along the direction of travel.
    arc_length_m : ndarray of shape (N,), metres
    source : {"scan", "pen", "fixed"}
        Where the tool axis came from.
    """

    points_m: FloatArray
    orientations_xyzw: FloatArray
    arc_length_m: FloatArray
    source: str

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="points_m")
        q = frozen_array(self.orientations_xyzw, shape_tail=(4,), name="orientations_xyzw")
        arc = frozen_array(self.arc_length_m, name="arc_length_m")
        if not len(pts) == len(q) == len(arc):
            raise ValueError("points, orientations and arc lengths differ in length")
        for name, value in (("points_m", pts), ("orientations_xyzw", q), ("arc_length_m", arc)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.points_m)

    def poses(self) -> FloatArray:
        """The poses as 4x4 transforms, shape (N, 4, 4)."""
        from scipy.spatial.transform import Rotation

        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(self.orientations_xyzw).as_matrix()
        T[:, :3, 3] = self.points_m
        return T


@dataclass(frozen=True)
class JointPath:
    """Inverse kinematics along a tool path, one branch kept throughout.

    Attributes
    ----------
    q_rad : ndarray of shape (N, 6)
        Joint angles, unwrapped along the path and shifted into the joint limits.
    branch : int
        Which of the eight analytic solutions (see ``recon.kinematics.IKSolutions``).
    limit_margin_rad : ndarray of shape (N,)
        Smallest distance of any joint to its position limit.
    wrist_singularity, elbow_singularity : ndarray of shape (N,)
        |sin q5| and |sin q3| (0 at the singularity).
    shoulder_margin_m : ndarray of shape (N,)
        Distance of the wrist centre outside the shoulder-singular cylinder.
    """

    q_rad: FloatArray
    branch: int
    limit_margin_rad: FloatArray
    wrist_singularity: FloatArray
    elbow_singularity: FloatArray
    shoulder_margin_m: FloatArray


@dataclass(frozen=True)
class SpeedDrop:
    """A stretch of the path where the TCP moves slower than requested, and why."""

    start_m: float
    end_m: float
    min_speed_m_s: float
    cause: str


#: A summary lists at most this many speed drops, the slowest, and counts the rest.
LISTED_SPEED_DROPS = 5


def speed_drop_lines(drops: tuple[SpeedDrop, ...] | list[SpeedDrop]) -> list[str]:
    """Summary lines for the stretches slower than requested: the slowest
    :data:`LISTED_SPEED_DROPS` in path order, then one line counting the others.

    A 10 m serpentine has over a hundred small drops at its turns; a line for each buried the
    rest of the summary. Every drop stays in the plan (``speed_drops``) for the pendant and the
    files.
    """
    drops = list(drops)
    slowest = sorted(drops, key=lambda d: d.min_speed_m_s)[:LISTED_SPEED_DROPS]
    lines = [
        f"slower than requested from {d.start_m * 1e3:.0f} to {d.end_m * 1e3:.0f} mm of path "
        f"(down to {d.min_speed_m_s * 1e3:.1f} mm/s): {d.cause}"
        for d in sorted(slowest, key=lambda d: d.start_m)
    ]
    rest = len(drops) - len(slowest)
    if rest:
        length_mm = sum(d.end_m - d.start_m for d in drops) * 1e3
        floor = max(d.min_speed_m_s for d in slowest) * 1e3
        lines.append(
            f"... and {rest} more stretches slower than requested, none below {floor:.1f} mm/s "
            f"({len(drops)} in all over {length_mm:.0f} mm of path; every one is in the plan's "
            "speed_drops)"
        )
    return lines


class Phase(enum.IntEnum):
    """What a sample of a planned motion is part of."""

    TRANSIT = 0  #: a joint move from where the arm is to above the path
    APPROACH = 1  #: a straight line down the tool axis onto the path's first point
    PROCESS = 2  #: the path itself
    RETRACT = 3  #: a straight line up the tool axis from the path's last point
    RETURN = 4  #: a joint move back to where the arm started

    @property
    def label(self) -> str:
        return self.name.lower()
