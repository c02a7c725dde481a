"""Rigid transforms: apply, invert, validate, measure, and convert to and from UR poses.

A transform ``T_a_b`` is a 4x4 homogeneous matrix that maps points of frame ``b`` into frame ``a``
(see docs/architecture.md). Every check of "is this rigid" in the project uses
:data:`RIGID_TOLERANCE` through :func:`is_rigid` or :func:`check_rigid`, so a matrix accepted in
one place (a calibration file, a REST request, a camera pose) is accepted everywhere.

This module imports nothing else of ``recon``: every layer may use it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Largest entry-wise deviation of ``R R^T`` from the identity, and of the last row from
#: (0, 0, 0, 1), that still counts as rigid. Matrices written with 6-8 significant digits (JSON
#: calibrations, camera pose logs) are orthonormal to about 1e-6, so 1e-4 accepts them with
#: margin; a scale error of 1e-4 moves a point 1 m away by 0.1 mm at most.
RIGID_TOLERANCE = 1e-4


def apply_transform(T: NDArray[np.float64], points_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Map points by a rigid transform.

    Parameters
    ----------
    T : ndarray of shape (4, 4)
        ``T_a_b``.
    points_m : ndarray of shape (N, 3), metres
        Points in frame b.

    Returns
    -------
    ndarray of shape (N, 3), metres
        The points in frame a.
    """
    return points_m @ T[:3, :3].T + T[:3, 3]


def rotate_vectors(T: NDArray[np.float64], vectors: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotate direction vectors (normals, edge directions) by a transform's rotation part.

    Parameters
    ----------
    T : ndarray of shape (4, 4)
    vectors : ndarray of shape (N, 3)

    Returns
    -------
    ndarray of shape (N, 3)
        ``R v`` for each row: translation does not apply to directions.
    """
    return vectors @ T[:3, :3].T


def invert_transform(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of a rigid transform (exact, without a general matrix inverse).

    Parameters
    ----------
    T : ndarray of shape (4, 4)
        ``T_a_b``.

    Returns
    -------
    ndarray of shape (4, 4)
        ``T_b_a``.
    """
    R, t = T[:3, :3], T[:3, 3]
    inverse = np.eye(4)
    inverse[:3, :3] = R.T
    inverse[:3, 3] = -R.T @ t
    return inverse


def is_proper_rotation(R: NDArray[np.float64]) -> bool:
    """Whether a 3x3 matrix is orthonormal within :data:`RIGID_TOLERANCE` with determinant +1.

    Parameters
    ----------
    R : ndarray of shape (3, 3)
    """
    R = np.asarray(R, dtype=np.float64)
    return bool(
        np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=RIGID_TOLERANCE) and np.linalg.det(R) > 0
    )


def is_rigid(T: NDArray[np.float64]) -> bool:
    """Whether ``T`` is a finite 4x4 rigid transform (see :func:`check_rigid`).

    Parameters
    ----------
    T : array_like of shape (4, 4)
    """
    T = np.asarray(T, dtype=np.float64)
    return bool(
        T.shape == (4, 4)
        and np.all(np.isfinite(T))
        and is_proper_rotation(T[:3, :3])
        and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=RIGID_TOLERANCE)
    )


def check_rigid(T: ArrayLike, *, name: str = "transform") -> NDArray[np.float64]:
    """Validate a 4x4 rigid transform and return it as a float array.

    Parameters
    ----------
    T : array_like of shape (4, 4)
    name : str
        What the matrix is, for the error message.

    Returns
    -------
    ndarray of shape (4, 4)

    Raises
    ------
    ValueError
        Wrong shape, non-finite values, a rotation part that is not orthonormal with
        determinant +1, or a bottom row other than (0, 0, 0, 1) (within :data:`RIGID_TOLERANCE`).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    if not is_proper_rotation(T[:3, :3]):
        raise ValueError(f"{name} has a rotation part that is not a proper rotation")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=RIGID_TOLERANCE):
        raise ValueError(f"{name} must have (0, 0, 0, 1) as its last row")
    return T


#: The frames of one robot cell (tracker, scanner, robot base) are this close at most (m): a
#: calibration that puts them farther apart is a unit mix-up or a typing error.
MAX_CELL_TRANSLATION_M = 10.0


def check_cell_transform(T: ArrayLike, *, name: str = "transform") -> NDArray[np.float64]:
    """:func:`check_rigid`, and a translation within :data:`MAX_CELL_TRANSLATION_M`.

    Raises
    ------
    ValueError
        As :func:`check_rigid`, or a translation beyond the cell.
    """
    T = check_rigid(T, name=name)
    distance_m = float(np.linalg.norm(T[:3, 3]))
    if distance_m > MAX_CELL_TRANSLATION_M:
        raise ValueError(
            f"{name} moves points by {distance_m:.3g} m, beyond the "
            f"{MAX_CELL_TRANSLATION_M:.0f} m of a robot cell: check its units (metres) and values"
        )
    return T


def rotation_angle_deg(T: NDArray[np.float64]) -> float:
    """Angle of a transform's rotation part, degrees in [0, 180].

    Parameters
    ----------
    T : ndarray of shape (4, 4) (or (3, 3): a rotation matrix)
    """
    c = (np.trace(np.asarray(T)[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def translation_m(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Translation part of a transform.

    Parameters
    ----------
    T : ndarray of shape (4, 4)

    Returns
    -------
    ndarray of shape (3,), metres
    """
    return np.asarray(T)[:3, 3]


def transform_from_pose(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """Transforms from UR poses ``(x, y, z, rx, ry, rz)`` (metres, rotation vector in radians).

    Parameters
    ----------
    pose : array_like of shape (6,) or (N, 6)

    Returns
    -------
    ndarray of shape (4, 4) or (N, 4, 4)
    """
    from scipy.spatial.transform import Rotation  # here: importing scipy.spatial takes 0.2 s

    pose = np.asarray(pose, dtype=np.float64)
    T = np.zeros((*pose.shape[:-1], 4, 4))
    T[..., :3, :3] = Rotation.from_rotvec(pose[..., 3:6]).as_matrix()
    T[..., :3, 3] = pose[..., :3]
    T[..., 3, 3] = 1.0
    return T


def pose_from_transform(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """UR poses ``(x, y, z, rx, ry, rz)`` (metres, rotation vector in radians) of transforms.

    Parameters
    ----------
    T : ndarray of shape (4, 4) or (N, 4, 4)

    Returns
    -------
    ndarray of shape (6,) or (N, 6)
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    rotvec = _canonical_half_turns(Rotation.from_matrix(T[..., :3, :3]).as_rotvec())
    return np.concatenate([T[..., :3, 3], rotvec], axis=-1)


def _canonical_half_turns(rotvec: NDArray[np.float64]) -> NDArray[np.float64]:
    """A half turn has two rotation vectors, r and -r; which one SciPy returns depends on the
    last bits of the matrix. Pick the one whose largest component is positive, so the same pose
    reads the same wherever it was computed. ``rotvec``: shape (3,) or (N, 3)."""
    rotvec = np.array(rotvec, dtype=np.float64)
    flat = rotvec.reshape(-1, 3)
    half_turn = np.linalg.norm(flat, axis=1) > np.pi - 1e-9
    largest = flat[np.arange(len(flat)), np.argmax(np.abs(flat), axis=1)]
    flat[half_turn & (largest < 0)] *= -1.0
    return flat.reshape(rotvec.shape)
