"""The cell this server plans and runs in: keep-out boxes and planes, base frame, metres.

The start-up settings name it (``TEACHPATH_KEEP_OUT_BOXES``, ``TEACHPATH_CELL_PLANES``). An
operator may edit it in the pendant (``PUT /cell``): the edit is stored in the database under
the arm's name (:attr:`service.settings.Settings.cell_key`) and applies at once to every plan
and to the real-arm gate; ``DELETE /cell`` goes back to the start-up settings. Every change
bumps a revision, and an edit made from an older view is refused (two pendants editing at once
lose nothing silently).

A plan records the cell it was checked against: one made in another cell is shown as outdated
(:mod:`service.provenance`), and the gate checks the samples against the cell as it is now,
never the plan's copy. A stored cell that cannot be read is not guessed at: planning and the
gate refuse until it is set again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import numpy as np

from service.errors import ApiError
from service.store import CellChangedError, Store

if TYPE_CHECKING:
    from service.core import Services
    from service.settings import Settings

#: At most this many boxes and planes (a cell has a handful; each costs every collision check).
MAX_BOXES = 32
MAX_PLANES = 16
#: No coordinate or plane offset beyond this (m): a UR arm reaches 1.3 m at most, and a number
#: typed in millimetres where metres were meant is caught.
MAX_COORDINATE_M = 10.0


@dataclass(frozen=True)
class CellNow:
    """The cell as it applies now.

    Attributes
    ----------
    keep_out_boxes_m : list of tuple of 6 floats
        x_min, y_min, z_min, x_max, y_max, z_max per box (base frame, m).
    cell_planes : list of tuple of 4 floats
        nx, ny, nz, d per plane: the arm keeps to n . p >= d (base frame, d in m).
    revision : int
        Changes stored so far (0: never edited).
    edited_at : datetime or None
        When it was last edited in the pendant; None: the start-up settings apply.
    """

    keep_out_boxes_m: list[tuple[float, ...]]
    cell_planes: list[tuple[float, ...]]
    revision: int
    edited_at: datetime | None

    @property
    def source(self) -> str:
        """Where the boxes and planes come from, in the operator's words."""
        if self.edited_at is None:
            return "the server's start-up settings"
        at = self.edited_at.replace(tzinfo=self.edited_at.tzinfo or UTC).astimezone(UTC)
        return f"edited in the pendant at {at:%Y-%m-%d %H:%M:%S} UTC (revision {self.revision})"

    def as_lists(self) -> tuple[list[list[float]], list[list[float]]]:
        """The boxes and planes as JSON lists (as a plan records them and ``GET /cell`` says)."""
        return [list(box) for box in self.keep_out_boxes_m], [list(p) for p in self.cell_planes]

    def differs_from(self, boxes: list[Any], planes: list[Any]) -> bool:
        """Whether ``boxes`` and ``planes`` (as a plan stored them: JSON, perhaps not numbers)
        are not this cell."""
        return (
            _as_tuples(boxes, 6) != self.keep_out_boxes_m
            or _as_tuples(planes, 4) != self.cell_planes
        )


class CellUnreadable(ApiError):
    """The stored cell cannot be read as boxes and planes: nothing can be checked against it."""

    def __init__(self, problem: str, revision: int) -> None:
        super().__init__(
            409,
            "cell_unreadable",
            f"the cell stored for this arm cannot be read ({problem}), so no motion can be "
            "checked against it: set the boxes and planes again in the pendant (Calibrate, "
            "Cell) or go back to the start-up settings",
            detail={"revision": revision},
        )


def check_shapes(
    boxes: object, planes: object
) -> tuple[list[tuple[float, ...]], list[tuple[float, ...]]]:
    """Boxes and planes the planner can check against, or the first problem.

    Parameters
    ----------
    boxes : list of 6 numbers each
        x_min, y_min, z_min, x_max, y_max, z_max (m).
    planes : list of 4 numbers each
        nx, ny, nz, d: the arm keeps to nx x + ny y + nz z >= d (m); the normal need not be
        a unit vector.

    Returns
    -------
    boxes : list of tuple of 6 floats
    planes : list of tuple of 4 floats
        Each plane as its unit normal and its distance along it (m): the same half-space.

    Raises
    ------
    ValueError
        Naming the box or plane (counted from 1) and what to change.
    """
    from recon.collision import Box, HalfSpace

    if not isinstance(boxes, list) or not isinstance(planes, list):
        raise ValueError("the boxes and the planes must each be a list")
    if len(boxes) > MAX_BOXES or len(planes) > MAX_PLANES:
        raise ValueError(
            f"a cell holds at most {MAX_BOXES} boxes and {MAX_PLANES} planes "
            f"(got {len(boxes)} and {len(planes)})"
        )
    checked_boxes: list[tuple[float, ...]] = []
    for number, box in enumerate(boxes, start=1):
        values = _numbers(box, 6, f"keep-out box {number}")
        if any(abs(v) > MAX_COORDINATE_M for v in values):
            raise ValueError(
                f"keep-out box {number}: a corner is more than {MAX_COORDINATE_M:g} m from the "
                "base (were millimetres typed as metres?)"
            )
        if any(hi <= lo for lo, hi in zip(values[:3], values[3:], strict=True)):
            raise ValueError(
                f"keep-out box {number}: each maximum (x, y, z) must be above its minimum"
            )
        Box(min_m=np.array(values[:3]), max_m=np.array(values[3:]), name=f"keep-out box {number}")
        checked_boxes.append(values)
    checked_planes: list[tuple[float, ...]] = []
    for number, plane in enumerate(planes, start=1):
        values = _numbers(plane, 4, f"plane {number}")
        length = math.hypot(*values[:3])
        if not length > 0.0:
            raise ValueError(
                f"plane {number}: its normal (nx, ny, nz) is zero; give the direction that "
                "points away from the wall, into the arm's side"
            )
        # n . p >= d as typed, kept as the unit normal and the distance along it (what the
        # planner checks and the pendant draws).
        unit = (*(v / length for v in values[:3]), values[3] / length)
        HalfSpace(normal=np.array(unit[:3]), offset_m=unit[3])
        if abs(unit[3]) > MAX_COORDINATE_M:
            raise ValueError(
                f"plane {number}: it is more than {MAX_COORDINATE_M:g} m from the base (were "
                "millimetres typed as metres?)"
            )
        checked_planes.append(unit)
    return checked_boxes, checked_planes


def cell_now(store: Store, settings: Settings) -> CellNow:
    """The cell that applies now: the one edited for this arm, else the start-up settings.

    Raises
    ------
    CellUnreadable
        The stored cell is not a list of valid boxes and planes.
    """
    row = store.cell(settings.cell_key)
    startup = check_shapes(list(settings.keep_out_boxes), list(settings.cell_planes))
    if row is None:
        return CellNow(*startup, revision=0, edited_at=None)
    if row.keep_out_boxes is None and row.cell_planes is None:
        return CellNow(*startup, revision=row.revision, edited_at=None)
    try:
        boxes, planes = check_shapes(row.keep_out_boxes, row.cell_planes)
    except (TypeError, ValueError) as exc:
        raise CellUnreadable(str(exc)[:200], row.revision) from None
    return CellNow(boxes, planes, revision=row.revision, edited_at=row.updated_at)


def edit_cell(
    services: Services,
    boxes: list[list[float]] | None,
    planes: list[list[float]] | None,
    *,
    revision: int,
) -> CellNow:
    """Store this arm's cell (``None, None``: back to the start-up settings).

    Parameters
    ----------
    services : service.core.Services
    boxes, planes : list of list of float, or None
        As :func:`check_shapes` returns them, each box and plane as a list (as
        :class:`service.schemas.CellIn` holds them).
    revision : int
        The revision the operator saw and edited.

    Returns
    -------
    CellNow
        The cell in force after the edit.

    Raises
    ------
    ApiError
        409 ``arm_running`` while a real-arm execution runs (its motion was checked against the
        cell as it is); 409 ``cell_changed`` when the stored cell is newer than ``revision``.
    """
    # Under the lock that starts executions: no run starts between this check and the edit,
    # and the gate re-reads the revision under the same lock. (One instance drives an arm, as
    # its ownership is this process's: the edits that matter reach that instance.)
    with services.live.lock:
        owner = services.live.arm_owner()
        if owner is not None:
            raise ApiError(
                409,
                "arm_running",
                f"the arm is running execution {owner}, whose motion was checked against the "
                "cell as it is: stop it or let it finish, then edit the cell",
            )
        try:
            services.store.set_cell(
                services.settings.cell_key,
                boxes=boxes,
                planes=planes,
                expected_revision=revision,
            )
        except CellChangedError as exc:
            raise ApiError(
                409,
                "cell_changed",
                f"the cell was changed meanwhile (it is now at revision {exc.revision}; this "
                f"edit was made from revision {revision}): reload it, check the change and "
                "edit again",
                detail={"revision": exc.revision},
            ) from None
    return cell_now(services.store, services.settings)


def _numbers(values: object, count: int, name: str) -> tuple[float, ...]:
    if (
        not isinstance(values, list | tuple)
        or len(values) != count
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
    ):
        raise ValueError(f"{name}: give {count} numbers")
    try:
        numbers = tuple(float(v) for v in values)
    except OverflowError:  # an integer of hundreds of digits
        numbers = (math.inf,)
    if not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"{name}: every number must be finite")
    return numbers


def _as_tuples(values: Any, count: int) -> list[tuple[float, ...]]:
    try:
        return [tuple(float(v) for v in item) for item in values or []]
    except (TypeError, ValueError):
        return [(math.nan,) * count]  # a stored copy that is not numbers is never this cell
