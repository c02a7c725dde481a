"""Named failures of the numerical core.

Bad arguments (wrong shape, NaN, a negative radius) raise :class:`ValueError`. Work that cannot be
done with valid arguments raises a :class:`ReconError` subclass whose message says what to change.
``service/errors.py`` maps each class to one HTTP status and a stable code, so the classes here are
part of the public contract: add new ones rather than re-purposing old ones.
"""

from __future__ import annotations

from typing import Any


class ReconError(Exception):
    """Base class of every failure of work the core was asked to do with valid arguments."""


class DegenerateInputError(ReconError):
    """The input is well formed but carries too little information (too few points, zero length)."""


class NoOverlapError(ReconError):
    """The path does not come near the scan, so the scan cannot inform the reconstruction."""


class UnitsMismatchError(ReconError):
    """Sizes that look off by a factor of about 1000: metres read as millimetres or the reverse."""


class RegistrationError(ReconError):
    """Registration (ICP) of the path to the scan did not produce a trustworthy transform."""


class TouchesInsufficientError(RegistrationError):
    """Touches of the workpiece that leave the scan's placement uncertain by more than the
    tolerance (1 sigma) where it matters: at the path, across its features (all touches on one
    face for a path along an edge, say). The message names each poorly pinned motion, the
    millimetres it leaves and where to touch."""


class PoorFitError(ReconError):
    """A calibration fit is worse than its tolerance (pairs that disagree, a pivot that
    wandered). Refused unless the caller accepts a poor fit; ``detail`` holds the figures."""

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.detail = detail


class InfeasibleTrajectoryError(ReconError):
    """The robot cannot follow the path within its limits (reach, joint limits, singularities)."""


class CollisionError(InfeasibleTrajectoryError):
    """The motion would bring the arm or the tool into the cell (the workpiece, the mounting
    plane, a keep-out box). ``detail`` says where: phase, time, link, point, clearance."""

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.detail = detail
