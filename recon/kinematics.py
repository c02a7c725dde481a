"""Universal Robots arms: models, forward kinematics and closed-form inverse kinematics.

UR arms follow the standard Denavit-Hartenberg convention with ``alpha = (pi/2, 0, 0, pi/2,
-pi/2, 0)``, ``a = (0, a2, a3, 0, 0, 0)`` and ``d = (d1, 0, 0, d4, d5, d6)``; the parameters below
are Universal Robots' published nominal values (a calibrated arm differs by a fraction of a
millimetre). Joint angles are radians, lengths metres; poses are 4x4 transforms of the flange
(tool0) in the base frame, ``T_base_flange``.

The inverse kinematics is the analytic solution for this geometry (Hawkins, "Analytic Inverse
Kinematics for the Universal Robots UR-5/UR-10 Arms", 2013): two shoulder, two wrist and two
elbow branches, eight solutions in all, vectorised over many poses.

**Calibrated arms.** Every UR arm leaves the factory with its own kinematics calibration: offsets
to the four DH parameters of each joint (the controller's ``calibration.conf``; the controller
reports the sums as its DH parameters). The published example of a real UR10e's calibration puts
its flange 2.1 mm (median) and 3.4 mm (worst) from the nominal model's over random
configurations, far above the half millimetre this project aims at. An arm with a
:class:`DHCalibration` (:func:`with_calibration`) has the controller's forward kinematics; its
inverse kinematics starts from the nominal closed form, branch by branch, and Newton's method on
the calibrated chain takes each solution onto the pose (the offsets are small enough that the
branches do not change). The calibrated DH chain is not the physical one (parallel axes put
some of its frames hundreds of metres away along their axes): :func:`joint_frames` keeps the
nominal frames for the links' geometry and only the flange is the calibrated one.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray
from recon.errors import InfeasibleTrajectoryError
from recon.paths import JointPath

ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
#: A home pose for every UR arm: upper arm up, forearm forward, tool pointing down (elbow up).
HOME_Q_RAD = (0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0)
DEG = np.pi / 180.0

#: Joint position range, +- radians. Every joint is +-360 deg nominally, but the elbow cannot
#: physically turn past about +-180 deg (the upper arm is in the way: UR's ROS description limits
#: it to that for the same reason). An elbow unwrapped to 248 deg instead of -112 deg is the same
#: pose, yet the move to it would fold the forearm through the upper arm.
JOINT_RANGE_RAD = np.array([2 * np.pi, 2 * np.pi, np.pi, 2 * np.pi, 2 * np.pi, 2 * np.pi])
JOINT_RANGE_RAD.setflags(write=False)
_ENDLESS_WRIST_3_RANGE_RAD = np.append(JOINT_RANGE_RAD[:5], np.inf)


@dataclass(frozen=True)
class DHCalibration:
    """An arm's own kinematics calibration: offsets added to its nominal DH parameters.

    Attributes
    ----------
    delta_theta_rad, delta_a_m, delta_d_m, delta_alpha_rad : ndarray of shape (6,)
        Per joint, as the controller's ``calibration.conf`` stores them. Not small in general:
        near-parallel axes (joints 2-4) are described by common normals far along the axes, so
        ``delta_d_m`` reaches hundreds of metres while the flange moves by millimetres.
    source : str
        Where it was read (a file name), for the plan's report.
    """

    delta_theta_rad: FloatArray
    delta_a_m: FloatArray
    delta_d_m: FloatArray
    delta_alpha_rad: FloatArray
    source: str = ""

    def __post_init__(self) -> None:
        for name in ("delta_theta_rad", "delta_a_m", "delta_d_m", "delta_alpha_rad"):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != (6,) or not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be 6 finite numbers, got {getattr(self, name)!r}")
            if np.abs(value).max() > CALIBRATION_MAX_OFFSET:
                raise ValueError(
                    f"{name} has an offset of {np.abs(value).max():g}: no arm's calibration "
                    f"reaches {CALIBRATION_MAX_OFFSET:g} (metres or radians)"
                )
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def as_dict(self) -> dict[str, Any]:
        """The offsets as lists and the source: what a trajectory's record keeps."""
        return {
            "delta_theta_rad": self.delta_theta_rad.tolist(),
            "delta_a_m": self.delta_a_m.tolist(),
            "delta_d_m": self.delta_d_m.tolist(),
            "delta_alpha_rad": self.delta_alpha_rad.tolist(),
            "source": self.source,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DHCalibration:
        """The inverse of :meth:`as_dict`.

        Raises
        ------
        ValueError
            A field missing or not six finite numbers.
        """
        if not isinstance(data, dict):
            raise ValueError(f"a calibration maps its offsets, got {type(data).__name__}")
        try:
            return cls(
                delta_theta_rad=data["delta_theta_rad"],
                delta_a_m=data["delta_a_m"],
                delta_d_m=data["delta_d_m"],
                delta_alpha_rad=data["delta_alpha_rad"],
                source=str(data.get("source", "")),
            )
        except KeyError as exc:
            raise ValueError(f"a calibration needs {exc}") from None
        except TypeError as exc:
            raise ValueError(f"not a calibration: {exc}") from None

    def same_as(self, other: DHCalibration | None) -> bool:
        """The same offsets (the source aside)."""
        return other is not None and all(
            np.array_equal(getattr(self, name), getattr(other, name))
            for name in ("delta_theta_rad", "delta_a_m", "delta_d_m", "delta_alpha_rad")
        )


#: Largest offset a calibration may hold (metres or radians): real ones reach ~450 m in d for
#: the near-parallel axes; this only keeps arithmetic far from overflow.
CALIBRATION_MAX_OFFSET = 1.0e4
#: A calibration whose flange is farther than this from the nominal model's, at any of the
#: configurations :func:`with_calibration` tries, is not this arm's (UR speaks of errors "in the
#: magnitude of centimetres" without one; the published UR10e example is 3.4 mm at worst).
CALIBRATION_MAX_DIFFERENCE_M = 0.03
#: ... or turns the flange by more than this.
CALIBRATION_MAX_TURN_RAD = np.radians(2.0)
#: Newton steps of the calibrated inverse kinematics (each one about squares the error: from the
#: nominal solution's millimetres to 1e-12 m takes three or four; near a singularity more).
IK_REFINE_STEPS = 10
#: A calibrated solution counts when it reaches the pose within these.
IK_REFINE_TOLERANCE_M = 1e-9
IK_REFINE_TOLERANCE_RAD = 1e-9


@dataclass(frozen=True)
class URModel:
    """One UR arm type.

    Attributes
    ----------
    name : str
    d1, a2, a3, d4, d5, d6 : float
        DH parameters, metres (a2, a3 negative as UR publishes them).
    q_min_rad, q_max_rad : ndarray of shape (6,)
        Joint position limits.
    qd_max_rad_s : ndarray of shape (6,)
        Joint speed limits.
    qdd_max_rad_s2 : ndarray of shape (6,)
        Joint accelerations used for planning. UR publishes no joint acceleration limit (its ROS
        descriptions say so); these are conservative planning values, overridable per plan.
    tcp_speed_max_m_s : float
        Largest TCP speed planning accepts: a planning cap of ours, not a published limit.
    control_rate_hz : float
        Controller (RTDE) rate: 500 Hz on e-series, 125 Hz on CB3.
    payload_kg : float
    calibration : DHCalibration or None
        The arm's own kinematics calibration (None: the nominal model).
    """

    name: str
    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float
    qd_max_rad_s: FloatArray
    qdd_max_rad_s2: FloatArray
    control_rate_hz: float
    payload_kg: float
    tcp_speed_max_m_s: float = 1.0
    q_min_rad: FloatArray = None  # type: ignore[assignment]
    q_max_rad: FloatArray = None  # type: ignore[assignment]
    calibration: DHCalibration | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        for name in ("qd_max_rad_s", "qdd_max_rad_s2", "q_min_rad", "q_max_rad"):
            value = getattr(self, name)
            if value is None:
                value = -JOINT_RANGE_RAD if name == "q_min_rad" else JOINT_RANGE_RAD
            arr = np.array(value, dtype=np.float64)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def d(self) -> FloatArray:
        return np.array([self.d1, 0.0, 0.0, self.d4, self.d5, self.d6])

    @property
    def a(self) -> FloatArray:
        return np.array([0.0, self.a2, self.a3, 0.0, 0.0, 0.0])

    @property
    def nominal(self) -> URModel:
        """The same arm without its calibration."""
        return self if self.calibration is None else replace(self, calibration=None)

    @property
    def kinematics_words(self) -> str:
        """Which kinematic model this is, for a report."""
        if self.calibration is None:
            return f"{self.name}, UR's nominal kinematics (no calibration given)"
        where = f" from {self.calibration.source}" if self.calibration.source else ""
        return f"{self.name}, calibrated kinematics{where}"

    def chain(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The DH parameters the forward kinematics uses: joint-angle offsets, d, a, alpha,
        each of shape (6,); the calibrated ones where the arm has a calibration."""
        theta0, d, a, alpha = np.zeros(6), self.d, self.a, ALPHA.copy()
        if self.calibration is not None:
            c = self.calibration
            theta0 = theta0 + c.delta_theta_rad
            d, a, alpha = d + c.delta_d_m, a + c.delta_a_m, alpha + c.delta_alpha_rad
        return theta0, d, a, alpha

    @property
    def reach_m(self) -> float:
        """Distance from the shoulder to the wrist centre with the arm stretched."""
        return abs(self.a2) + abs(self.a3)


def _e_series_rates(*values_deg_s: float) -> FloatArray:
    return np.array(values_deg_s, dtype=np.float64) * DEG


#: The supported arms, by lower-case name. DH parameters from UR's "DH parameters for
#: calculations of kinematics and dynamics" (the same values as ur-analytic-ik's table); joint
#: speeds (deg/s) from UR's ROS 2 description (config/<model>/joint_limits.yaml). Joint positions
#: are ``JOINT_RANGE_RAD``, except wrist 3 of the UR3 and UR3e, which turns without limit.
UR_MODELS: dict[str, URModel] = {
    m.name: m
    for m in (
        URModel(
            "ur3e",
            0.15185,
            -0.24355,
            -0.2132,
            0.13105,
            0.08535,
            0.0921,
            _e_series_rates(180, 180, 180, 360, 360, 360),
            np.full(6, 6.0),
            500.0,
            3.0,
            q_min_rad=-_ENDLESS_WRIST_3_RANGE_RAD,
            q_max_rad=_ENDLESS_WRIST_3_RANGE_RAD,
        ),
        URModel(
            "ur5e",
            0.1625,
            -0.425,
            -0.3922,
            0.1333,
            0.0997,
            0.0996,
            _e_series_rates(180, 180, 180, 180, 180, 180),
            np.full(6, 4.0),
            500.0,
            5.0,
        ),
        URModel(
            "ur10e",
            0.1807,
            -0.6127,
            -0.57155,
            0.17415,
            0.11985,
            0.11655,
            _e_series_rates(120, 120, 180, 180, 180, 180),
            np.full(6, 3.0),
            500.0,
            12.5,
        ),
        URModel(
            "ur16e",
            0.1807,
            -0.4784,
            -0.36,
            0.17415,
            0.11985,
            0.11655,
            _e_series_rates(120, 120, 180, 180, 180, 180),
            np.full(6, 3.0),
            500.0,
            16.0,
        ),
        URModel(
            "ur20",
            0.2363,
            -0.862,
            -0.7287,
            0.201,
            0.1593,
            0.1543,
            _e_series_rates(120, 120, 150, 210, 210, 210),
            np.full(6, 2.0),
            500.0,
            20.0,
        ),
        URModel(
            "ur30",
            0.2363,
            -0.637,
            -0.5037,
            0.201,
            0.1593,
            0.1543,
            _e_series_rates(120, 120, 150, 210, 210, 210),
            np.full(6, 2.0),
            500.0,
            30.0,
        ),
        URModel(
            "ur3",
            0.1519,
            -0.24365,
            -0.21325,
            0.11235,
            0.08535,
            0.0819,
            _e_series_rates(180, 180, 180, 360, 360, 360),
            np.full(6, 6.0),
            125.0,
            3.0,
            q_min_rad=-_ENDLESS_WRIST_3_RANGE_RAD,
            q_max_rad=_ENDLESS_WRIST_3_RANGE_RAD,
        ),
        URModel(
            "ur5",
            0.089159,
            -0.425,
            -0.39225,
            0.10915,
            0.09465,
            0.0823,
            _e_series_rates(180, 180, 180, 180, 180, 180),
            np.full(6, 4.0),
            125.0,
            5.0,
        ),
        URModel(
            "ur10",
            0.1273,
            -0.612,
            -0.5723,
            0.163941,
            0.1157,
            0.0922,
            _e_series_rates(120, 120, 180, 180, 180, 180),
            np.full(6, 3.0),
            125.0,
            10.0,
        ),
    )
}


def model(name: str) -> URModel:
    """The arm called ``name`` (case-insensitive).

    Raises
    ------
    ValueError
        An unknown name; the message lists the known ones.
    """
    try:
        return UR_MODELS[name.lower()]
    except KeyError:
        raise ValueError(
            f"unknown robot {name!r}; known UR arms: {', '.join(sorted(UR_MODELS))}"
        ) from None


def _dh(theta: FloatArray, d: float, a: float, alpha: float) -> FloatArray:
    """Standard DH link transforms for many angles: (...,) -> (..., 4, 4)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    T = np.zeros((*np.shape(theta), 4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2], T[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2], T[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    T[..., 2, 1], T[..., 2, 2], T[..., 2, 3] = sa, ca, d
    T[..., 3, 3] = 1.0
    return T


def limit_margins_rad(arm: URModel, q_rad: FloatArray) -> FloatArray:
    """How far each joint is from its nearer limit.

    Parameters
    ----------
    arm : URModel
    q_rad : ndarray of shape (..., 6)

    Returns
    -------
    ndarray of shape (..., 6), radians
        Infinite for a joint without limits (the UR3's wrist 3).
    """
    q = np.asarray(q_rad, dtype=np.float64)
    return np.minimum(q - arm.q_min_rad, arm.q_max_rad - q)


#: The arm's points whose speed the cap bounds besides the TCP: the origins of DH frames 2..6,
#: on the axes of the elbow, the three wrist joints and at the flange. A link is rigid, so the
#: speed along its axis is largest at one of its ends (the speed field is affine in position):
#: with the TCP they bound the speed of every point on the chain's axes. UR's safety limits
#: bound the elbow's and the tool's speed alike.
SPEED_POINT_FRAMES = (2, 3, 4, 5, 6)
SPEED_POINT_NAMES = ("elbow", "wrist 1", "wrist 2", "wrist 3", "flange", "TCP")


def speed_points_m(arm: URModel, q_rad: FloatArray, T_flange_tcp: FloatArray) -> FloatArray:
    """The points whose speed a cap bounds (:data:`SPEED_POINT_NAMES`), base frame.

    Parameters
    ----------
    arm : URModel
    q_rad : ndarray of shape (..., 6)
    T_flange_tcp : ndarray of shape (4, 4)

    Returns
    -------
    ndarray of shape (..., 6, 3), metres
    """
    frames = joint_frames(arm, q_rad)
    tcp = frames[..., 6, :, :] @ np.asarray(T_flange_tcp, dtype=np.float64)
    first, last = SPEED_POINT_FRAMES[0], SPEED_POINT_FRAMES[-1]  # consecutive frames
    return np.concatenate([frames[..., first : last + 1, :3, 3], tcp[..., None, :3, 3]], axis=-2)


def forward(arm: URModel, q_rad: FloatArray) -> FloatArray:
    """Flange poses for joint vectors.

    Parameters
    ----------
    arm : URModel
    q_rad : ndarray of shape (..., 6)

    Returns
    -------
    ndarray of shape (..., 4, 4)
        ``T_base_flange``.
    """
    q = np.asarray(q_rad, dtype=np.float64)
    theta0, d, a, alpha = arm.chain()
    T = _dh(q[..., 0] + theta0[0], d[0], a[0], alpha[0])
    for i in range(1, 6):
        T = T @ _dh(q[..., i] + theta0[i], d[i], a[i], alpha[i])
    return T


def _chain_frames(arm: URModel, q_rad: FloatArray) -> FloatArray:
    """The frames of the arm's DH chain, calibrated where it is: (..., 7, 4, 4). Not the links'
    physical frames on a calibrated arm (see the module docstring): for Jacobians only."""
    q = np.asarray(q_rad, dtype=np.float64)
    theta0, d, a, alpha = arm.chain()
    frames = np.empty((*q.shape[:-1], 7, 4, 4))
    frames[..., 0, :, :] = np.eye(4)
    T = np.broadcast_to(np.eye(4), (*q.shape[:-1], 4, 4))
    for i in range(6):
        T = T @ _dh(q[..., i] + theta0[i], d[i], a[i], alpha[i])
        frames[..., i + 1, :, :] = T
    return frames


def with_calibration(arm: URModel, calibration: DHCalibration) -> URModel:
    """The arm with its own kinematics calibration, checked to be plausibly this arm's.

    Parameters
    ----------
    arm : URModel
    calibration : DHCalibration

    Returns
    -------
    URModel

    Raises
    ------
    ValueError
        At some of 500 configurations spread over the joint ranges the calibrated flange is
        more than :data:`CALIBRATION_MAX_DIFFERENCE_M` or :data:`CALIBRATION_MAX_TURN_RAD`
        from the nominal one: another arm type's calibration, or not a calibration at all.
    """
    calibrated = replace(arm.nominal, calibration=calibration)
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (500, 6))
    nominal_T, calibrated_T = forward(arm.nominal, q), forward(calibrated, q)
    moved_m = np.linalg.norm(calibrated_T[:, :3, 3] - nominal_T[:, :3, 3], axis=1).max()
    turn = np.swapaxes(nominal_T[:, :3, :3], 1, 2) @ calibrated_T[:, :3, :3]
    turned_rad = np.linalg.norm(Rotation.from_matrix(turn).as_rotvec(), axis=1).max()
    if moved_m > CALIBRATION_MAX_DIFFERENCE_M or turned_rad > CALIBRATION_MAX_TURN_RAD:
        raise ValueError(
            f"the calibration{' in ' + calibration.source if calibration.source else ''} puts "
            f"the {arm.name}'s flange up to {moved_m * 1e3:.1f} mm and "
            f"{np.degrees(turned_rad):.2f} deg from its nominal model (a calibration moves it by "
            f"millimetres): is it this arm's, and is the robot model right?"
        )
    return calibrated


def calibration_difference_m(arm: URModel, q_rad: FloatArray) -> FloatArray:
    """How far the calibrated flange is from the nominal model's at these joints.

    Parameters
    ----------
    arm : URModel
        With a calibration (zeros without one).
    q_rad : ndarray of shape (..., 6)

    Returns
    -------
    ndarray of shape (...,), metres
    """
    difference: FloatArray = np.linalg.norm(
        forward(arm, q_rad)[..., :3, 3] - forward(arm.nominal, q_rad)[..., :3, 3], axis=-1
    )
    return difference


def joint_frames(arm: URModel, q_rad: FloatArray) -> FloatArray:
    """The DH frames of the chain for joint vectors: base, after joint 1, …, flange.

    Frame ``k`` (k = 1..6) is ``A_1 … A_k``; its z-axis is the axis of joint ``k + 1`` and frame 6
    is the flange, so ``joint_frames(arm, q)[..., 6, :, :] == forward(arm, q)``. On a calibrated
    arm frames 1-5 are the nominal ones (the links' geometry) and frame 6 the calibrated flange.

    Parameters
    ----------
    arm : URModel
    q_rad : ndarray of shape (..., 6)

    Returns
    -------
    ndarray of shape (..., 7, 4, 4)
        ``T_base_k`` for k = 0 (identity) .. 6.
    """
    q = np.asarray(q_rad, dtype=np.float64)
    d, a = arm.d, arm.a
    frames = np.empty((*q.shape[:-1], 7, 4, 4))
    frames[..., 0, :, :] = np.eye(4)
    T = _dh(q[..., 0], d[0], a[0], ALPHA[0])
    frames[..., 1, :, :] = T
    for i in range(1, 6):
        T = T @ _dh(q[..., i], d[i], a[i], ALPHA[i])
        frames[..., i + 1, :, :] = T
    if arm.calibration is not None:
        # The links where they physically are (nominal), the flange where the controller
        # puts it (calibrated): the two differ by millimetres.
        frames[..., 6, :, :] = forward(arm, q)
    return frames


@dataclass(frozen=True)
class IKSolutions:
    """All eight analytic solutions for a batch of poses.

    Attributes
    ----------
    q_rad : ndarray of shape (N, 8, 6)
        Angles wrapped to (-pi, pi]. Branch ``b`` has shoulder sign ``(b >> 2) & 1``, wrist sign
        ``(b >> 1) & 1`` and elbow sign ``b & 1`` (0: plus, 1: minus).
    valid : ndarray of shape (N, 8), bool
        The branch exists at this pose (reachable; not through a singularity that removes it).
    failure : ndarray of shape (N, 8), int8
        Why a branch does not exist: 0 it does, 1 the wrist centre is inside the shoulder's
        cylinder (too close to the base axis), 2 the wrist cannot take the orientation there,
        3 the elbow cannot span the distance (too far, or too close to the shoulder), 4 on a
        calibrated arm, the nominal solution did not converge onto the pose (at a
        singularity's edge).
    shoulder_margin_m : ndarray of shape (N,)
        How far the wrist centre is outside the cylinder of radius d4 around the base axis; at 0
        the shoulder branches meet (shoulder singularity), below it the pose is unreachable.
    """

    q_rad: FloatArray
    valid: NDArray[np.bool_]
    shoulder_margin_m: FloatArray
    failure: NDArray[np.int8]


def inverse(arm: URModel, T_base_flange: FloatArray) -> IKSolutions:
    """The eight closed-form inverse-kinematics solutions of many flange poses.

    Where the wrist is singular (sin q5 = 0) q6 is undetermined; it is set to 0 there, and the
    pose is still reported valid (the joint values reach the pose).

    Parameters
    ----------
    arm : URModel
    T_base_flange : ndarray of shape (N, 4, 4)

    Returns
    -------
    IKSolutions
    """
    T = np.asarray(T_base_flange, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_base_flange must have shape (N, 4, 4), got {T.shape}")
    if arm.calibration is not None:
        return _refine_on_calibration(arm, T, inverse(arm.nominal, T))
    n = len(T)
    d1, a2, a3, d4, d6 = arm.d1, arm.a2, arm.a3, arm.d4, arm.d6
    p06 = T[:, :3, 3]
    z6 = T[:, :3, 2]
    p05 = p06 - d6 * z6
    radius = np.hypot(p05[:, 0], p05[:, 1])
    shoulder_margin = shoulder_margin_m(arm, T)

    q = np.zeros((n, 8, 6))
    valid = np.ones((n, 8), dtype=bool)
    failure = np.zeros((n, 8), dtype=np.int8)
    psi = np.arctan2(p05[:, 1], p05[:, 0])
    cos_phi = d4 / np.maximum(radius, 1e-12)
    reachable_shoulder = np.abs(cos_phi) <= 1.0
    phi = np.arccos(np.clip(cos_phi, -1.0, 1.0))
    T60 = np.linalg.inv(T)
    for shoulder in (0, 1):
        q1 = psi + (phi if shoulder == 0 else -phi) + np.pi / 2
        s1, c1 = np.sin(q1), np.cos(q1)
        cos5 = (p06[:, 0] * s1 - p06[:, 1] * c1 - d4) / d6
        wrist_ok = np.abs(cos5) <= 1.0 + 1e-9
        for wrist in (0, 1):
            q5 = np.arccos(np.clip(cos5, -1.0, 1.0)) * (1.0 if wrist == 0 else -1.0)
            s5 = np.sin(q5)
            singular = np.abs(s5) < 1e-9
            safe_s5 = np.where(singular, 1.0, s5)
            q6 = np.arctan2(
                (-T60[:, 1, 0] * s1 + T60[:, 1, 1] * c1) / safe_s5,
                (T60[:, 0, 0] * s1 - T60[:, 0, 1] * c1) / safe_s5,
            )
            q6 = np.where(singular, 0.0, q6)
            # Position of the wrist's joint-4 frame seen from joint 1: a planar 2-link problem.
            T01 = _dh(q1, d1, 0.0, ALPHA[0])
            T45 = _dh(q5, arm.d5, 0.0, ALPHA[4])
            T56 = _dh(q6, d6, 0.0, ALPHA[5])
            T14 = np.linalg.inv(T01) @ T @ np.linalg.inv(T45 @ T56)
            p13 = T14[:, :3, :3] @ np.array([0.0, -d4, 0.0]) + T14[:, :3, 3]
            length_sq = np.einsum("ni,ni->n", p13, p13)
            cos3 = (length_sq - a2**2 - a3**2) / (2 * a2 * a3)
            elbow_ok = np.abs(cos3) <= 1.0 + 1e-9
            for elbow in (0, 1):
                q3 = np.arccos(np.clip(cos3, -1.0, 1.0)) * (1.0 if elbow == 0 else -1.0)
                length = np.sqrt(np.maximum(length_sq, 1e-300))
                q2 = -np.arctan2(p13[:, 1], -p13[:, 0]) + np.arcsin(
                    np.clip(a3 * np.sin(q3) / length, -1.0, 1.0)
                )
                T12 = _dh(q2, 0.0, a2, ALPHA[1])
                T23 = _dh(q3, 0.0, a3, ALPHA[2])
                T34 = np.linalg.inv(T12 @ T23) @ T14
                q4 = np.arctan2(T34[:, 1, 0], T34[:, 0, 0])
                branch = (shoulder << 2) | (wrist << 1) | elbow
                q[:, branch] = np.column_stack([q1, q2, q3, q4, q5, q6])
                valid[:, branch] = reachable_shoulder & wrist_ok & elbow_ok
                failure[:, branch] = np.where(
                    ~reachable_shoulder, 1, np.where(~wrist_ok, 2, np.where(~elbow_ok, 3, 0))
                )
    q = (q + np.pi) % (2 * np.pi) - np.pi
    return IKSolutions(q_rad=q, valid=valid, shoulder_margin_m=shoulder_margin, failure=failure)


def _refine_on_calibration(arm: URModel, T: FloatArray, nominal: IKSolutions) -> IKSolutions:
    """Newton's method on the calibrated chain from each valid nominal solution.

    Parameters
    ----------
    arm : URModel
        With a calibration.
    T : ndarray of shape (N, 4, 4)
        The flange poses.
    nominal : IKSolutions
        The nominal model's solutions of ``T``.

    Returns
    -------
    IKSolutions
        The branches that reached the pose within :data:`IK_REFINE_TOLERANCE_M` and
        :data:`IK_REFINE_TOLERANCE_RAD`; the others invalid (failure 4).
    """
    q = nominal.q_rad.copy()
    valid = nominal.valid.copy()
    rows, branches = np.nonzero(valid)
    target = T[rows]
    x = q[rows, branches]
    for _ in range(IK_REFINE_STEPS):
        frames = _chain_frames(arm, x)
        flange = frames[:, 6]
        position_error = target[:, :3, 3] - flange[:, :3, 3]
        turn = target[:, :3, :3] @ np.swapaxes(flange[:, :3, :3], 1, 2)
        rotation_error = Rotation.from_matrix(turn).as_rotvec()
        axes, origins = frames[:, :6, :3, 2], frames[:, :6, :3, 3]
        # Geometric Jacobian of the calibrated chain (columns: joints): the cross product
        # drops the component along each axis, so origins far along it cost no precision.
        linear = np.cross(axes, flange[:, None, :3, 3] - origins)
        jacobian = np.concatenate([linear, axes], axis=2).transpose(0, 2, 1)  # (K, 6, 6)
        error = np.concatenate([position_error, rotation_error], axis=1)
        # Damped least squares: at a wrist singularity the free combination stays put.
        damping = 1e-12 * np.eye(6)
        jjt = jacobian @ np.swapaxes(jacobian, 1, 2) + damping
        x = x + np.einsum("kji,kj->ki", jacobian, np.linalg.solve(jjt, error[..., None])[..., 0])
    flange = forward(arm, x)
    reached_m = np.linalg.norm(target[:, :3, 3] - flange[:, :3, 3], axis=1)
    turn = target[:, :3, :3] @ np.swapaxes(flange[:, :3, :3], 1, 2)
    reached_rad = np.linalg.norm(Rotation.from_matrix(turn).as_rotvec(), axis=1)
    converged = (reached_m < IK_REFINE_TOLERANCE_M) & (reached_rad < IK_REFINE_TOLERANCE_RAD)
    q[rows, branches] = (x + np.pi) % (2 * np.pi) - np.pi
    valid[rows, branches] = converged
    failure = nominal.failure.copy()
    failure[rows[~converged], branches[~converged]] = 4
    return IKSolutions(
        q_rad=q, valid=valid, shoulder_margin_m=nominal.shoulder_margin_m, failure=failure
    )


def shoulder_margin_m(arm: URModel, T_base_flange: FloatArray) -> FloatArray:
    """How far the wrist centre is outside the shoulder-singular cylinder (radius ``|d4|``
    about the base's z axis); negative inside it.

    Parameters
    ----------
    arm : URModel
    T_base_flange : ndarray of shape (N, 4, 4)

    Returns
    -------
    ndarray of shape (N,), metres
    """
    T = np.asarray(T_base_flange, dtype=np.float64)
    wrist_centre = T[:, :3, 3] - arm.d6 * T[:, :3, 2]
    return np.hypot(wrist_centre[:, 0], wrist_centre[:, 1]) - abs(arm.d4)


def wrist_singularity(q_rad: FloatArray) -> FloatArray:
    """|sin q5|: 0 when the axes of joints 4 and 6 align (wrist singularity)."""
    return np.abs(np.sin(np.asarray(q_rad)[..., 4]))


def elbow_singularity(q_rad: FloatArray) -> FloatArray:
    """|sin q3|: 0 with the arm fully stretched or folded (elbow singularity)."""
    return np.abs(np.sin(np.asarray(q_rad)[..., 2]))


@dataclass(frozen=True)
class Configuration:
    """Which of the arm's solutions to take, in words (``None``: either).

    Attributes
    ----------
    shoulder : {"left", "right"} or None
        Which side of the arm's reach the shoulder joint's axis points to, seen from above
        (the two solutions of joint 1).
    elbow : {"up", "down"} or None
        Whether the elbow lies above or below the line from the shoulder to the wrist (for a
        table mount, "up" keeps it away from the table).
    wrist : {"flip", "noflip"} or None
        The sign of joint 5: ``noflip`` for sin(q5) > 0.
    """

    shoulder: str | None = None
    elbow: str | None = "up"
    wrist: str | None = None

    def __post_init__(self) -> None:
        for name, options in (
            ("shoulder", ("left", "right")),
            ("elbow", ("up", "down")),
            ("wrist", ("flip", "noflip")),
        ):
            value = getattr(self, name)
            if value is not None and value not in options:
                raise ValueError(
                    f"{name} must be one of {', '.join(options)} or any, got {value!r}"
                )

    def matches(self, named: Configuration) -> bool:
        """Whether a solution named ``named`` (every field set) is one this allows."""
        return all(
            want is None or want == have
            for want, have in (
                (self.shoulder, named.shoulder),
                (self.elbow, named.elbow),
                (self.wrist, named.wrist),
            )
        )

    def words(self) -> str:
        """E.g. "shoulder left, elbow up, wrist noflip" (or "any configuration")."""
        parts = [
            f"{name} {value}"
            for name, value in (
                ("shoulder", self.shoulder),
                ("elbow", self.elbow),
                ("wrist", self.wrist),
            )
            if value is not None
        ]
        return ", ".join(parts) or "any configuration"


def configuration_of(arm: URModel, q_rad: FloatArray) -> Configuration:
    """The configuration a joint vector is in (every field set).

    Parameters
    ----------
    arm : URModel
    q_rad : ndarray of shape (6,)
    """
    frames = joint_frames(arm, np.asarray(q_rad, dtype=np.float64))
    shoulder, elbow, wrist = frames[1, :3, 3], frames[2, :3, 3], frames[3, :3, 3]
    up = np.array([0.0, 0.0, 1.0])
    # Elbow: above or below the shoulder-wrist chord, "above" meaning towards the base's +z
    # (measured perpendicular to the chord; for a vertical chord, away from the base's axis).
    chord = wrist - shoulder
    chord /= max(float(np.linalg.norm(chord)), 1e-12)
    across = up - (up @ chord) * chord
    if np.linalg.norm(across) < 1e-6:
        across = np.array([wrist[0], wrist[1], 0.0])
    offset = elbow - shoulder
    elbow_up = float((offset - (offset @ chord) * chord) @ across) >= 0.0
    # Shoulder: joint 2's axis (z of frame 1) points to the left or right of the horizontal
    # direction from the base's axis to the wrist, seen from above.
    reach = np.array([wrist[0], wrist[1], 0.0])
    axis = frames[1, :3, 2]
    left = float(np.cross(reach, axis)[2]) >= 0.0
    return Configuration(
        shoulder="left" if left else "right",
        elbow="up" if elbow_up else "down",
        wrist="noflip" if np.sin(q_rad[4]) >= 0 else "flip",
    )


def branches_for(arm: URModel, T_base_flange: FloatArray, want: Configuration) -> tuple[int, ...]:
    """The IK branches (see :class:`IKSolutions`) whose solution at a pose is in the wanted
    configuration. A branch keeps its configuration along a path that passes no singularity,
    which :func:`follow_path` refuses anyway, so the first pose decides."""
    sol = inverse(arm, np.asarray(T_base_flange, dtype=np.float64)[None])
    return tuple(
        b
        for b in range(8)
        if sol.valid[0, b] and want.matches(configuration_of(arm, sol.q_rad[0, b]))
    )


#: Below these the path is refused as passing (too near) a singularity: |sin q5| and |sin q3| of
#: 0.02 are about 1.1 degrees from it, where joint speeds grow without bound.
MIN_WRIST_SINGULARITY = 0.02
MIN_ELBOW_SINGULARITY = 0.02
#: Smallest distance of the wrist centre from the shoulder-singular cylinder, metres.
MIN_SHOULDER_MARGIN_M = 0.005
#: Branch scores and start distances are compared to this many decimals (rad or sin), so that
#: rounding noise never picks between two equally good branches.
SCORE_DECIMALS = 9
#: Largest change of any joint between neighbouring waypoints (they are a few mm apart): more
#: means the branch flipped through a singularity.
MAX_JOINT_STEP_RAD = 0.35


def follow_path(
    arm: URModel,
    T_base_flange: FloatArray,
    *,
    q_near_rad: FloatArray | None = None,
    allowed_branches: tuple[int, ...] | None = None,
) -> JointPath:
    """Joint angles along a sequence of flange poses, keeping one IK branch throughout.

    Every branch that reaches every waypoint is unwrapped along the path and shifted by whole
    turns into the joint limits; among those without a singularity or a jump, the one with the
    largest smallest margin (to limits and singularities) is kept, or, given ``q_near_rad``
    (the arm's current joints), the one whose first waypoint is nearest to it.

    Parameters
    ----------
    arm : URModel
    T_base_flange : ndarray of shape (N, 4, 4)
    q_near_rad : ndarray of shape (6,), optional
    allowed_branches : tuple of int, optional
        Only these branches (0-7, see :class:`IKSolutions`), e.g. to keep the elbow up.

    Returns
    -------
    JointPath

    Raises
    ------
    InfeasibleTrajectoryError
        No branch follows the whole path; the message names the first waypoint that defeats the
        best branch and why (out of reach, wrist orientation, singularity, joint limit, jump).
    """
    poses = np.asarray(T_base_flange, dtype=np.float64)
    sol = inverse(arm, poses)
    n = len(poses)
    candidates = []
    failures = []  # (first bad waypoint, reason) per branch
    for branch in range(8) if allowed_branches is None else allowed_branches:
        valid = sol.valid[:, branch]
        if not valid.all():
            first = int(np.argmin(valid))
            failures.append((first, _unreachable_reason(arm, poses[first], sol, first, branch)))
            continue
        q = np.unwrap(sol.q_rad[:, branch], axis=0)
        q, limit_problem = _into_limits(arm, q, q_near_rad)
        if limit_problem is not None:
            failures.append(limit_problem)
            continue
        steps = np.abs(np.diff(q, axis=0))
        if n > 1 and steps.max() > MAX_JOINT_STEP_RAD:
            i, j = np.unravel_index(np.argmax(steps), steps.shape)
            failures.append(
                (
                    int(i) + 1,
                    f"joint {j + 1} would jump by "
                    f"{np.degrees(steps[i, j]):.0f} deg to the next waypoint (the path "
                    "crosses a singularity)",
                )
            )
            continue
        wrist, elbow = wrist_singularity(q), elbow_singularity(q)
        shoulder = sol.shoulder_margin_m
        bad = (
            (wrist < MIN_WRIST_SINGULARITY)
            | (elbow < MIN_ELBOW_SINGULARITY)
            | (shoulder < MIN_SHOULDER_MARGIN_M)
        )
        if bad.any():
            first = int(np.argmax(bad))
            which = (
                "wrist (joints 4 and 6 aligned)"
                if wrist[first] < MIN_WRIST_SINGULARITY
                else "elbow (arm stretched out or folded)"
                if elbow[first] < MIN_ELBOW_SINGULARITY
                else "shoulder (wrist centre above the base axis)"
            )
            failures.append((first, f"it passes the {which} singularity"))
            continue
        margin = np.min(limit_margins_rad(arm, q), axis=1)
        score = min(float(wrist.min()), float(elbow.min()), float(margin.min()) / np.pi)
        distance = 0.0 if q_near_rad is None else float(np.abs(q[0] - q_near_rad).max())
        candidates.append((branch, q, margin, wrist, elbow, score, distance))
    if not candidates:
        first, reason = max(failures, key=lambda f: f[0])
        x, y, z = poses[first, :3, 3]
        raise InfeasibleTrajectoryError(
            f"waypoint {first} at ({x:.3f}, {y:.3f}, {z:.3f}) m cannot be followed by the "
            f"{arm.name}: {reason}. Move the workpiece (or the base-from-tracker calibration), "
            "change the tool orientation, or choose another arm"
        )
    if q_near_rad is not None:
        branch, q, margin, wrist, elbow, _, _ = min(
            candidates, key=lambda c: (round(c[6], SCORE_DECIMALS), c[0])
        )
    else:
        # Mirror-image branches score the same up to rounding (the elbow-up and elbow-down
        # solutions of a pose have the same margins), so the last bits must not decide: equal
        # scores prefer the elbow up, then the lowest branch number.
        branch, q, margin, wrist, elbow, _, _ = max(
            candidates,
            key=lambda c: (
                round(c[5], SCORE_DECIMALS),
                configuration_of(arm, c[1][0]).elbow == "up",
                -c[0],
            ),
        )
    return JointPath(
        q_rad=q,
        branch=branch,
        limit_margin_rad=margin,
        wrist_singularity=wrist,
        elbow_singularity=elbow,
        shoulder_margin_m=sol.shoulder_margin_m,
    )


def _into_limits(
    arm: URModel, q: FloatArray, q_near: FloatArray | None
) -> tuple[FloatArray, tuple[int, str] | None]:
    """Shift each unwrapped joint by whole turns into its limits (nearest ``q_near`` or most
    central). Returns (q, None) or (q, (waypoint, reason))."""
    q = q.copy()
    for j in range(6):
        if not (np.isfinite(arm.q_min_rad[j]) and np.isfinite(arm.q_max_rad[j])):
            # A joint that turns without limit (UR3/UR3e wrist 3) fits anywhere, but it too is
            # taken the whole turns nearest ``q_near`` (or zero): skipped, a retract line met
            # the path 360 deg apart on the UR3e.
            target = (
                q_near[j] - q[0, j]
                if q_near is not None
                else -0.5 * (q[:, j].min() + q[:, j].max())
            )
            q[:, j] += np.round(target / (2 * np.pi)) * 2 * np.pi
            continue
        lo, hi = q[:, j].min(), q[:, j].max()
        k_min = np.ceil((arm.q_min_rad[j] - lo) / (2 * np.pi))
        k_max = np.floor((arm.q_max_rad[j] - hi) / (2 * np.pi))
        if k_min > k_max:
            span = np.degrees(hi - lo)
            return q, (
                0,
                f"joint {j + 1} would have to turn {span:.0f} deg along the path, more "
                "than its limits allow",
            )
        options = np.arange(k_min, k_max + 1) * 2 * np.pi
        if q_near is not None:
            shift = options[np.argmin(np.abs(q[0, j] + options - q_near[j]))]
        else:
            centre = 0.5 * (arm.q_min_rad[j] + arm.q_max_rad[j])
            shift = options[np.argmin(np.abs(0.5 * (lo + hi) + options - centre))]
        q[:, j] += shift
    return q, None


def _unreachable_reason(
    arm: URModel, pose: FloatArray, sol: IKSolutions, i: int, branch: int
) -> str:
    code = int(sol.failure[i, branch])
    if code == 1:
        return "it is too close to the base's axis for the shoulder"
    if code == 2:
        return "the tool orientation there cannot be reached at that position"
    wrist_centre = pose[:3, 3] - arm.d6 * pose[:3, 2]
    distance = float(np.linalg.norm(wrist_centre - [0.0, 0.0, arm.d1]))
    if distance > 0.5 * arm.reach_m:
        return (
            f"it is out of reach (the wrist centre would be {distance:.3f} m from the "
            f"shoulder; the arm reaches about {arm.reach_m:.3f} m)"
        )
    return f"it is too close to the shoulder ({distance:.3f} m) for the elbow to fold"
