"""Speed override and pause of a streamed trajectory: the plan's clock runs at a fraction of
real time.

A UR program's speed slider scales the controller's time; a servoJ stream is ours to time, so
the stream does the same: each controller period it advances a cursor on the plan's clock by
``s * period`` (``s`` the speed fraction, 1 = as planned, 0 = paused) and sends the plan's
position there. The arm goes along the same path in joint space; only the timing changes.

What that does to the joint motion, with ``q(tau)`` the plan and ``tau(t)`` its clock::

    qd  = q'(tau) s                      <= the plan's speed, for s <= 1
    qdd = q''(tau) s^2 + q'(tau) s_dot    the plan's acceleration, plus the ramp's term

So ``s`` never exceeds 1 (never faster than the plan the gate checked), and it changes no
faster than the joints' acceleration limits leave room for: per joint,
``|q''| s^2 + |q'| |s_dot| <= qdd_max``. Where the plan already uses all of a joint's
acceleration at full speed, ``s`` holds until the room is there (a pause then takes effect a
little later, never with a jolt); a stop (``servoStop``) is not this: it brakes at once.

Positions between two planned samples are interpolated on the straight joint-space segment
between them (what the controller's servo does between two servoJ targets at full speed); at
``s = 1`` the cursor lands on the samples themselves, and the stream is the plan's samples
exactly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from recon.arrays import FloatArray

#: The speed fraction changes by at most this much per second (0 -> 100 % in a second at the
#: quickest), whatever the acceleration limits would allow: an operator's slider, not a jolt.
MAX_RAMP_PER_S = 1.0
#: The lowest speed an operator can set short of a pause (UR's slider goes down to 1 %; below a
#: few per cent a run only looks stuck).
MIN_SPEED_FRACTION = 0.05
#: A pause longer than this ends the run as stopped (the arm holds under servo control while
#: paused; a run left paused for good must not keep the arm and the cell).
MAX_PAUSE_S = 600.0
#: Joint speeds below this (rad/s) put no bound on the ramp (the arm is at rest there).
_AT_REST_RAD_S = 1e-9


class PlanCursor:
    """Where a time-scaled stream is on its plan, advanced once per controller period.

    Parameters
    ----------
    q_rad : ndarray of shape (K, 6)
        The planned samples, one per ``period_s``.
    period_s : float
        The plan's sample period, which is also the stream's period.
    qdd_max_rad_s2 : ndarray of shape (6,)
        Joint acceleration limits the ramps of the speed fraction stay within.
    start_fraction : float
        The speed fraction at the first sample: the arm stands still when a stream starts, so
        any is reachable there at once. Anything outside 0 .. 1 counts as a pause.

    Attributes
    ----------
    position : float
        The cursor, in planned samples (0 .. K-1; fractional between two samples).
    fraction : float
        The speed fraction now (0 .. 1).
    paused_s : float
        How long the cursor has stood still since it last moved (s).

    Examples
    --------
    A stream's loop: send :meth:`here`, stop after the last sample, else :meth:`advance`.

    >>> import numpy as np
    >>> cursor = PlanCursor(np.linspace(0, 0.1, 11)[:, None] * np.ones(6), 0.002, np.full(6, 5.0))
    >>> sent = []
    >>> while True:
    ...     sent.append(cursor.here()[0])
    ...     if cursor.done:
    ...         break
    ...     cursor.advance(1.0)
    >>> len(sent), float(sent[-1])
    (11, 0.1)
    """

    def __init__(
        self,
        q_rad: ArrayLike,
        period_s: float,
        qdd_max_rad_s2: ArrayLike,
        start_fraction: float = 1.0,
    ) -> None:
        self.q_rad = np.asarray(q_rad, dtype=np.float64)
        if self.q_rad.ndim != 2 or len(self.q_rad) < 1:
            raise ValueError(f"the plan must be (K, joints) samples, got {self.q_rad.shape}")
        self.period_s = float(period_s)
        self.qdd_max_rad_s2 = np.asarray(qdd_max_rad_s2, dtype=np.float64)
        if len(self.q_rad) > 1:
            # The plan's joint speed and acceleration at each sample (rad/s, rad/s^2).
            self._qd = np.abs(np.gradient(self.q_rad, self.period_s, axis=0))
            self._qdd = np.abs(np.gradient(np.gradient(self.q_rad, self.period_s, axis=0),
                                           self.period_s, axis=0))  # fmt: skip
        else:
            self._qd = self._qdd = np.zeros_like(self.q_rad)
        self.position = 0.0
        # The arm stands still when a stream starts: any fraction is as gentle as the plan.
        self.fraction = _clean(start_fraction)
        self.paused_s = 0.0
        self._last = len(self.q_rad) - 1

    @property
    def done(self) -> bool:
        """Whether the cursor has reached the last sample."""
        return self.position >= self._last

    @property
    def index(self) -> int:
        """The planned sample nearest the cursor."""
        return min(int(round(self.position)), self._last)

    @property
    def plan_time_s(self) -> float:
        """The cursor on the plan's clock (s since its first sample)."""
        return self.position * self.period_s

    def max_ramp(self) -> float:
        """How fast (per second) the speed fraction may change here without a joint going over
        its acceleration limit."""
        i = self.index
        room = self.qdd_max_rad_s2 - self._qdd[i] * self.fraction**2  # (6,), rad/s^2
        moving = self._qd[i] > _AT_REST_RAD_S
        if not moving.any():
            return MAX_RAMP_PER_S
        ramp = float(np.min(np.maximum(room[moving], 0.0) / self._qd[i][moving]))
        return min(ramp, MAX_RAMP_PER_S)

    @property
    def paused_too_long(self) -> bool:
        """Whether the cursor has stood still for more than :data:`MAX_PAUSE_S`."""
        return self.paused_s > MAX_PAUSE_S

    def advance(self, target_fraction: float) -> None:
        """One controller period: move the speed fraction towards ``target_fraction`` (as fast
        as :meth:`max_ramp` allows), then the cursor by it (see :meth:`here` for where it is).

        Parameters
        ----------
        target_fraction : float
            0 (pause) or :data:`MIN_SPEED_FRACTION` .. 1; anything else (a torn or hostile
            value) counts as a pause.
        """
        target = _clean(target_fraction)
        step = self.max_ramp() * self.period_s
        if target > self.fraction:
            self.fraction = min(target, self.fraction + step)
        elif target < self.fraction:
            self.fraction = max(target, self.fraction - step)
        # At full speed the cursor moves by exactly 1.0 and stays on whole samples.
        self.position = min(self.position + self.fraction, float(self._last))
        self.paused_s = self.paused_s + self.period_s if self.fraction == 0.0 else 0.0

    def here(self) -> FloatArray:
        """The position at the cursor: a planned sample, or the straight joint-space segment
        between the two around it (rad, shape (6,))."""
        i = int(np.floor(self.position))
        part = self.position - i
        if part == 0.0 or i >= self._last:
            sample: FloatArray = self.q_rad[min(i, self._last)].copy()
            return sample
        between: FloatArray = self.q_rad[i] + part * (self.q_rad[i + 1] - self.q_rad[i])
        return between


def _clean(fraction: float) -> float:
    """A speed fraction as given, or 0 (a pause) for anything outside 0 .. 1 (NaN too)."""
    value = float(fraction)
    return value if 0.0 <= value <= 1.0 else 0.0
