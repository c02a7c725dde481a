"""A degeneracy-aware ICP: rigid registration of a path onto feature points (edge or surface).

The paper aligns the noisy path to the scan's edge points with ICP because a mobile scanner's
pose relative to the tracker is uncertain. Here the path is registered to the *thinned* edge
(points on the edge itself, see ``recon.edges.thin_edges``) when it follows edges, and to the
surface (point-to-plane) otherwise; registering to the raw edge band, whose centroid lies inside
the corner, leaves an error of about a millimetre.

What registration cannot do: a slow drift of the trace that looks like a rigid motion (a constant
offset, a tilt) is indistinguishable from a misplaced scanner, so it stays in the result. Where
that matters, track or calibrate the scanner and pass its transform as the initial guess.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.errors import RegistrationError
from recon.results import Registration
from recon.transforms import apply_transform, check_rigid

#: Fewest path points that must find a partner for a registration to be trusted.
MIN_PAIRS = 10
#: Smallest fraction of the path that must find a partner within the final pairing distance.
MIN_FITNESS = 0.3
#: Directions of motion whose information is below this fraction of the best-constrained one are
#: taken as unobservable (sliding along a flat plate or a straight edge, turning about a circle's
#: axis) and left as the initial guess had them. Measured on the synthetic scenes: truly free
#: directions come out at 1e-5..5e-3 (noise in normals and edge directions), constrained ones at
#: 0.02 and above.
DEGENERACY_RATIO = 1e-2
#: A step that does not lower the robust cost is halved at most this many times before the
#: registration is taken as converged (see :func:`_descend`).
STEP_HALVINGS = 3
#: Largest number of path points used for registration (taken evenly along the path).
MAX_SOURCE_POINTS = 5000
#: ICP stops when a step moves the path by less than this (as a twist: metres at the path's ends).
CONVERGED_M = 1e-7
#: Scale of Tukey's robust weights: pairs farther than this from the feature (a pen lifted off
#: the surface, a stretch off the edge) have no influence. Twice a typical trace's error.
ROBUST_SCALE_M = 0.002


def register_icp(
    source_m: FloatArray,
    target_m: FloatArray,
    *,
    init_T_target_source: FloatArray,
    max_distance_m: float,
    target_normals: FloatArray | None = None,
    target_directions: FloatArray | None = None,
    target_label: str,
    max_iterations: int = 60,
    target_tree: cKDTree | None = None,
    max_source_points: int = MAX_SOURCE_POINTS,
) -> Registration:
    """Rigidly register ``source_m`` onto a feature with a degeneracy-aware ICP.

    Each iteration pairs every source point with its nearest target point within the pairing
    distance and takes one Gauss-Newton step on the distances that the feature defines:
    point-to-plane with ``target_normals`` (a surface), point-to-line with
    ``target_directions`` (an edge), point-to-point otherwise. Tukey's robust weights take out
    pairs where the pen lifted off or left the feature.

    Open3D's ICP is not used here because its solver has no notion of a degenerate problem: on
    a flat plate (sliding and turning in the plane are free) its point-to-plane steps wander off
    in the free directions until the path leaves the plate (seen on the Fig. 7 scene). Here the
    step is solved in the eigenbasis of the 6x6 information matrix and directions with less than
    :data:`DEGENERACY_RATIO` of the largest information are not moved, so the transform keeps
    the initial guess in whatever the feature cannot tell. (Open3D's point-to-point ICP is the
    independent check of this one in the tests.)

    Two stages: the first pairs and weighs points up to ``max_distance_m`` apart (the largest
    misalignment expected); the second re-pairs within three robust standard deviations of the
    first's residuals (or twice the median pair distance, which includes the gaps between scan
    points; at least a millimetre) and weighs with a Tukey scale of three robust standard
    deviations (at least :data:`ROBUST_SCALE_M`), so the parts of the path that wander off the
    feature no longer pull.

    Parameters
    ----------
    source_m : ndarray of shape (N, 3)
        The path (tracker frame).
    target_m : ndarray of shape (M, 3)
        Feature points (scan frame).
    init_T_target_source : ndarray of shape (4, 4)
        Initial guess (identity, or a stored calibration).
    max_distance_m : float
    target_normals : ndarray of shape (M, 3), optional
    target_directions : ndarray of shape (M, 3), optional
    target_label : str
        Recorded in the result ("edge" or "surface").
    max_iterations : int
        Per stage.
    target_tree : cKDTree, optional
        A tree over ``target_m`` to reuse.
    max_source_points : int
        The path is thinned evenly to at most this many points.

    Returns
    -------
    Registration
        ``T_scan_tracker`` maps source (tracker) points into the target (scan) frame.

    Raises
    ------
    RegistrationError
        Too few pairs, too little of the path near the features, or a feature that constrains
        no motion at all.
    """
    if len(target_m) < MIN_PAIRS:
        raise RegistrationError(
            f"the scan has only {len(target_m)} {target_label} points near the path, too few to "
            "register it: scan more of the traced feature, or switch registration off and give "
            "a calibration"
        )
    source_m = np.asarray(source_m, dtype=np.float64)
    # Six unknowns need nowhere near 100k pairs; an even subset keeps every step cheap.
    source_m = source_m[:: max(1, -(-len(source_m) // max_source_points))]
    target_m = np.asarray(target_m, dtype=np.float64)
    T = check_rigid(init_T_target_source, name="initial T_scan_tracker")
    if target_tree is not None and target_tree.n != len(target_m):
        raise ValueError(
            f"target_tree holds {target_tree.n} points, target_m {len(target_m)}: not its tree"
        )
    tree = target_tree if target_tree is not None else cKDTree(target_m)
    problem = _Problem(source_m, target_m, tree, target_normals, target_directions)
    # Stage 1 weighs pairs up to the pairing distance (the misalignment may be that large).
    # Stage 2 re-derives pairing distance and Tukey scale from robust spreads (medians) at every
    # iteration, so a lifted stretch of the path, a minority, drops out as the rest settles.
    # Pairing is by Euclidean distance to the nearest target point, which also includes the
    # gaps between scan points, hence the median pair distance in the pairing bound.
    distance, scale = max_distance_m, max_distance_m
    for _ in range(max_iterations):
        T, moving = _advance(problem, T, distance, scale)
        if not moving:
            break
    T, distance, scale = _refine(problem, T, distance, scale, max_iterations)
    final = problem.step(T, distance, scale)
    fitness = final.n_inliers / len(source_m)
    if (
        final.n_inliers < MIN_PAIRS
        or fitness < MIN_FITNESS
        or final.constrained_dof == 0
        or final.motion is None  # no pairs to centre the twists on
    ):
        raise RegistrationError(
            f"only {fitness * 100:.0f} % of the path lies within {distance * 1000:.1f} mm of the "
            f"scan's {target_label} points after registration: check that the scan covers the "
            "traced feature and that both are in the same units, or give a better initial "
            "calibration"
        )
    init = check_rigid(init_T_target_source, name="initial T_scan_tracker")
    move_m = apply_transform(T, source_m) - apply_transform(init, source_m)
    moved_m = np.linalg.norm(move_m, axis=1)
    return Registration(
        T_scan_tracker=T,
        rmse_m=final.rmse_m,
        fitness=float(fitness),
        n_pairs=final.n_inliers,
        target=target_label,
        constrained_dof=final.constrained_dof,
        path_moved_mean_m=float(moved_m.mean()),
        path_moved_max_m=float(moved_m.max()),
        path_moved_off_feature_median_m=problem.off_feature_median_m(T, move_m),
        covariance=final.covariance,
        motion_centre_m=final.motion.centre_m,
        motion_length_m=final.motion.length_m,
    )


def _refine(
    problem: _Problem, T: FloatArray, distance_m: float, scale_m: float, max_iterations: int
) -> tuple[FloatArray, float, float]:
    """The second stage: pairing distance and Tukey scale from the residuals' robust spread at
    every iteration (see :func:`register_icp`); returns the transform, distance and scale."""
    for _ in range(max_iterations):
        current = problem.step(T, distance_m, scale_m)
        if current.n_inliers < MIN_PAIRS:
            break  # nothing to refine; reported by the caller
        distance_m = max(3.0 * current.sigma_m, 2.0 * current.median_pair_m, 1e-3)
        scale_m = max(ROBUST_SCALE_M, 3.0 * current.sigma_m)
        T, moving = _advance(problem, T, distance_m, scale_m)
        if not moving:
            break
    return T, distance_m, scale_m


def _advance(
    problem: _Problem, T: FloatArray, distance_m: float, scale_m: float
) -> tuple[FloatArray, bool]:
    """One iteration of either stage: the step from ``T`` that lowers the robust cost (see
    :func:`_descend`), and whether the iterations should go on (False: converged)."""
    step = problem.step(T, distance_m, scale_m)
    T_next = _descend(problem, T, step, distance_m, scale_m)
    if T_next is None:
        return T, False
    return T_next, step.motion_m >= CONVERGED_M


def _descend(
    problem: _Problem, T: FloatArray, step: _Step, distance_m: float, scale_m: float
) -> FloatArray | None:
    """The step's transform if it lowers the robust cost, else the largest of its halves that
    does (at most :data:`STEP_HALVINGS`); None when none does (converged).

    A Gauss-Newton step is the minimum of the cost *with this step's pairs*; with the pairs
    re-chosen it can be worse, and without this test the iterations crept 10.8 mm across a
    wavy scan fragment to a placement that fitted worse than where they began.
    """
    if step.twist is None or step.motion is None:
        return None  # too few pairs to take a step
    before = step.cost
    twist = step.twist
    for _ in range(STEP_HALVINGS + 1):
        candidate = step.motion.transform(twist) @ T
        if problem.cost(candidate, distance_m, scale_m) <= before:
            return candidate
        twist = twist / 2
    return None


@dataclass(frozen=True)
class _Step:
    T_next: FloatArray
    rmse_m: float  # of the pairs with non-zero weight
    n_inliers: int  # pairs with non-zero weight
    sigma_m: float  # robust spread of the paired residuals: 1.4826 x their median
    median_pair_m: float  # median Euclidean distance of the pairs
    constrained_dof: int
    motion_m: float
    motion: RigidMotion | None = None  # the twists' centre and scale (scan frame)
    covariance: FloatArray | None = None  # of the twist, from the residuals (see _covariance)
    twist: FloatArray | None = None  # the step, about ``motion``
    cost: float = float("inf")  # the robust cost at the step's start (see _Problem.cost)


@dataclass(frozen=True)
class _Problem:
    source: FloatArray
    target: FloatArray
    tree: cKDTree
    normals: FloatArray | None
    directions: FloatArray | None

    def step(self, T: FloatArray, distance_m: float, scale_m: float) -> _Step:
        """Pair, weigh and take one Gauss-Newton step from ``T`` (see :func:`register_icp`).

        ``scale_m`` is the Tukey scale: pairs farther than it from the feature get weight 0.
        """
        moved = apply_transform(T, self.source)
        dist, idx = self.tree.query(moved, distance_upper_bound=distance_m, workers=-1)
        paired = np.isfinite(dist)
        points = moved[paired]
        partner_idx = idx[paired]
        axes = self._axes(partner_idx)
        residual = np.einsum("pai,pi->pa", axes, points - self.target[partner_idx])
        size = np.linalg.norm(residual, axis=1)
        cost = _tukey_cost(size, scale_m, n_unpaired=len(moved) - len(points))
        weight = np.where(size < scale_m, (1.0 - (size / scale_m) ** 2) ** 2, 0.0)
        inlier = weight > 0
        n_inliers = int(np.count_nonzero(inlier))
        if n_inliers < MIN_PAIRS:
            return _Step(T, float("inf"), n_inliers, float("inf"), float("inf"), 0, 0.0)
        rmse = float(np.sqrt(np.mean(size[inlier] ** 2)))
        sigma = 1.4826 * float(np.median(size))
        median_pair = float(np.median(dist[paired]))
        motion = RigidMotion.around(points[inlier])
        jacobian = motion.jacobian(points, axes)
        info = np.einsum("p,pai,paj->ij", weight, jacobian, jacobian)
        gradient = np.einsum("p,pai,pa->i", weight, jacobian, residual)
        twist, keep = solve_constrained(info, gradient)
        return _Step(
            motion.transform(twist) @ T,
            rmse,
            n_inliers,
            sigma,
            median_pair,
            int(np.count_nonzero(keep)),
            float(np.linalg.norm(twist)),
            motion,
            _covariance(info, residual[inlier], axes.shape[1]),
            twist,
            cost,
        )

    def cost(self, T: FloatArray, distance_m: float, scale_m: float) -> float:
        """The robust cost :meth:`step` minimises, at ``T``: Tukey's rho of every pair's
        distance to its feature, with the points that find no partner within ``distance_m``
        counted as outliers (so costs compare when the pairs change), metres squared."""
        moved = apply_transform(T, self.source)
        dist, idx = self.tree.query(moved, distance_upper_bound=distance_m, workers=-1)
        paired = np.isfinite(dist)
        partner_idx = idx[paired]
        residual = np.einsum(
            "pai,pi->pa", self._axes(partner_idx), moved[paired] - self.target[partner_idx]
        )
        size = np.linalg.norm(residual, axis=1)
        return _tukey_cost(size, scale_m, n_unpaired=int(np.count_nonzero(~paired)))

    def off_feature_median_m(self, T: FloatArray, move_m: FloatArray) -> float:
        """The median over the source points of their moves ``move_m`` (N, 3) along their
        feature's residual axes at ``T`` (the surface's normal, across the edge): how far the
        registration moved the path toward or away from the feature, rather than along it.
        (The median: points paired near another face or an edge of the patch see the wrong
        normal.)"""
        _, partner_idx = self.tree.query(apply_transform(T, self.source), workers=-1)
        across = np.einsum("pai,pi->pa", self._axes(partner_idx), move_m)
        return float(np.median(np.linalg.norm(across, axis=1)))

    def _axes(self, partner_idx: NDArray[np.int64]) -> FloatArray:
        if self.normals is not None:
            return self.normals[partner_idx][:, None, :]
        if self.directions is not None:
            return _across(self.directions[partner_idx])
        return np.broadcast_to(np.eye(3), (len(partner_idx), 3, 3))


def _tukey_cost(size_m: FloatArray, scale_m: float, *, n_unpaired: int) -> float:
    """Sum of Tukey's rho over pair distances ``size_m`` (P,), the unpaired points counted at
    rho's ceiling ``scale_m**2 / 6``, metres squared."""
    ceiling = scale_m**2 / 6.0
    inside = np.minimum(size_m / scale_m, 1.0)
    return float(np.sum(ceiling * (1.0 - (1.0 - inside**2) ** 3)) + ceiling * n_unpaired)


def _covariance(info: FloatArray, residual: FloatArray, n_axes: int) -> FloatArray:
    """Covariance of the registration's twist from its residuals.

    The classic ``sigma^2 (J^T W J)^-1`` treats the residuals as independent; along a hand trace
    they are not (drift is correlated over centimetres), and the transform is that much less
    certain. The residuals' correlation length along the path (in pairs: where their
    autocorrelation falls below 1/e, doubled) inflates it. The motions the feature leaves free
    get no variance (they are not estimated at all).

    Parameters
    ----------
    info : ndarray of shape (6, 6)
    residual : ndarray of shape (P, A)
        The inlier pairs' residuals, in path order.
    n_axes : int
        A, the residual components per pair.

    Returns
    -------
    ndarray of shape (6, 6)
    """
    r = residual[:, 0] - residual[:, 0].mean()
    variance = float(np.mean(residual**2))  # per component
    lag = len(r)
    if len(r) > 4 and np.dot(r, r) > 0:
        spectrum = np.fft.rfft(r, n=2 * len(r))
        auto = np.fft.irfft(spectrum * np.conj(spectrum))[: len(r)]
        below = np.flatnonzero(auto / auto[0] < np.exp(-1.0))
        lag = int(below[0]) if len(below) else len(r)
    inflation = float(np.clip(2 * lag, 1, max(len(r) / 3, 1)))
    del n_axes  # the variance is per component already
    return inverse_on_fixed(info)[0] * variance * inflation


@dataclass(frozen=True)
class RigidMotion:
    """Small rigid motions ``x -> x + omega x (x - c) + t`` as a twist ``(L omega, t)``.

    Scaling the rotation by a length L (the extent of the points that constrain it) puts all six
    unknowns in metres, so that the eigenvalues of an information matrix compare and one ratio
    tells a free motion from a fixed one.

    Attributes
    ----------
    centre_m : ndarray of shape (3,)
        c, the point rotations turn about.
    length_m : float
        L.
    """

    centre_m: FloatArray
    length_m: float

    @classmethod
    def around(cls, points_m: FloatArray) -> RigidMotion:
        """Centred on the points' mean, scaled by their extent (at least a millimetre)."""
        points_m = np.asarray(points_m, dtype=np.float64)
        length = max(float(np.linalg.norm(np.ptp(points_m, axis=0))), 1e-3)
        return cls(points_m.mean(axis=0), length)

    def jacobian(self, points_m: FloatArray, axes: FloatArray) -> FloatArray:
        """Derivatives of residuals ``axes . x`` with respect to the twist.

        Parameters
        ----------
        points_m : ndarray of shape (P, 3)
        axes : ndarray of shape (P, A, 3)
            The directions each point's residuals are measured along (a normal; two directions
            across an edge; the three axes).

        Returns
        -------
        ndarray of shape (P, A, 6)
        """
        arm = (points_m - self.centre_m) / self.length_m
        return np.concatenate([np.cross(arm[:, None, :], axes), axes], axis=2)

    def transform(self, twist: FloatArray) -> FloatArray:
        """The 4x4 transform of a twist (exact rotation, so it stays rigid)."""
        delta = np.eye(4)
        R = Rotation.from_rotvec(twist[:3] / self.length_m).as_matrix()
        delta[:3, :3] = R
        delta[:3, 3] = self.centre_m + twist[3:] - R @ self.centre_m
        return delta

    def point_sigma(self, covariance: FloatArray, points_m: FloatArray) -> FloatArray:
        """RMS position error of points moved by a twist of the given covariance.

        Parameters
        ----------
        covariance : ndarray of shape (6, 6)
        points_m : ndarray of shape (N, 3)

        Returns
        -------
        ndarray of shape (N,)
            ``sqrt(trace(J Sigma J^T))`` per point, J the point's 3x6 Jacobian.
        """
        points = np.asarray(points_m, dtype=np.float64)
        axes = np.broadcast_to(np.eye(3), (len(points), 3, 3))
        jacobian = self.jacobian(points, axes)  # (N, 3, 6)
        variance = np.einsum("nai,ij,naj->n", jacobian, covariance, jacobian)
        spread: FloatArray = np.sqrt(np.maximum(variance, 0.0))
        return spread

    def describe(self, direction: FloatArray) -> str:
        """A twist direction in words: turning about an axis, or sliding along a direction.

        A direction and its opposite are the same motion (they come from eigenvectors, whose
        sign is arbitrary): the one written is the one whose largest component is positive, so
        the same motion reads the same whatever rounding flipped the sign.
        """
        rotation, translation = direction[:3], direction[3:]
        turning = bool(np.linalg.norm(rotation) >= np.linalg.norm(translation))
        axis = rotation if turning else translation
        axis = axis / np.linalg.norm(axis)
        if axis[int(np.argmax(np.abs(axis)))] < 0:
            axis = -axis
        x, y, z = (float(v) + 0.0 for v in np.round(axis, 2))  # + 0.0: no "-0.00"
        if turning:
            return f"turning about ({x:.2f}, {y:.2f}, {z:.2f})"
        return f"sliding along ({x:.2f}, {y:.2f}, {z:.2f})"


def fixed_by_ratio(values: FloatArray) -> NDArray[np.bool_]:
    """Which eigenvalues of an information matrix belong to fixed motions: those with at least
    :data:`DEGENERACY_RATIO` of the largest (what a trace's features fix)."""
    fixed: NDArray[np.bool_] = values > DEGENERACY_RATIO * max(values.max(), 1e-300)
    return fixed


def inverse_on_fixed(
    info: FloatArray, fixed_test: Callable[[FloatArray], np.ndarray] = fixed_by_ratio
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """The inverse of an information matrix on the motions it fixes (zero on the others).

    Parameters
    ----------
    info : ndarray of shape (6, 6)
    fixed_test : callable
        Eigenvalues (ascending) -> which are fixed.

    Returns
    -------
    inverse : ndarray of shape (6, 6)
    vectors : ndarray of shape (6, 6)
        The eigenvectors (columns), ascending eigenvalues.
    fixed : ndarray of shape (6,), bool
    """
    values, vectors = np.linalg.eigh(info)
    fixed = fixed_test(values)
    inverse = (vectors[:, fixed] / values[fixed]) @ vectors[:, fixed].T
    return inverse, vectors, fixed


def solve_constrained(
    info: FloatArray,
    gradient: FloatArray,
    fixed_test: Callable[[FloatArray], np.ndarray] = fixed_by_ratio,
) -> tuple[FloatArray, np.ndarray]:
    """One Gauss-Newton step restricted to the motions the information fixes.

    Parameters
    ----------
    info : ndarray of shape (6, 6)
        ``J^T W J``.
    gradient : ndarray of shape (6,)
        ``J^T W r``.
    fixed_test : callable
        Which eigenvalues belong to fixed motions (default :func:`fixed_by_ratio`).

    Returns
    -------
    twist : ndarray of shape (6,)
        Zero along every eigen-direction of ``info`` that is not fixed (left as the initial
        guess had it).
    fixed : ndarray of shape (6,), bool
        Which eigen-directions (of ``numpy.linalg.eigh(info)``) were fixed.
    """
    inverse, _, fixed = inverse_on_fixed(info, fixed_test)
    return -inverse @ gradient, fixed


def _across(directions: FloatArray) -> FloatArray:
    """Two unit vectors perpendicular to each direction.

    Parameters
    ----------
    directions : ndarray of shape (P, 3)
        Unit vectors.

    Returns
    -------
    ndarray of shape (P, 2, 3)
    """
    helper = np.where(np.abs(directions[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(directions, helper)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return np.stack([e1, np.cross(directions, e1)], axis=1)
