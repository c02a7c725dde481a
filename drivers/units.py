"""Length units accepted on the way in; everything inside is metres."""

from __future__ import annotations

#: Metres per unit.
LENGTH_UNITS: dict[str, float] = {"m": 1.0, "mm": 1e-3}


def metres_per(units: str) -> float:
    """Scale factor from ``units`` to metres.

    Raises
    ------
    ValueError
        An unknown unit name.
    """
    try:
        return LENGTH_UNITS[units]
    except KeyError:
        raise ValueError(
            f"unknown length unit {units!r}; use one of {', '.join(LENGTH_UNITS)}"
        ) from None
