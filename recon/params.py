"""Parameters declared once: each field of a parameter dataclass carries its default, its bounds,
its unit and a line of help.

The core checks the bounds (:func:`check_bounds`, called from ``__post_init__``); the service's
request schemas and the command line's options are generated from the same declarations
(``service/schemas.py``, ``service/cli/options.py``), so a default or a bound is written in one
place and ``--help`` and the OpenAPI spec show the real ones.

Example
-------
>>> @dataclass(frozen=True)
... class Knobs:
...     radius_m: float = param(0.008, gt=0, le=0.2, unit="m", help="neighbourhood radius")
...     def __post_init__(self):
...         check_bounds(self)
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any

#: Key of a field's :class:`Spec` in its ``dataclasses.field`` metadata.
SPEC_KEY = "teachpath.param"

#: A pen pivoted in a dimple keeps its tip within about 0.1-0.5 mm RMS of one point: a pivot
#: calibration worse than this (m) is refused unless accepted.
PIVOT_TOLERANCE_M = 1e-3


@dataclass(frozen=True)
class Spec:
    """What a parameter may be.

    Attributes
    ----------
    help : str
        One line for ``--help`` and the OpenAPI description.
    unit : str
        The unit of its numbers ("m", "deg", "m/s", "" for none).
    ge, gt, le, lt : float or None
        Bounds of a number (each element of a tuple of numbers).
    choices : tuple or None
        The values a text parameter may take.
    """

    help: str
    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[Any, ...] | None = None

    def describe(self) -> str:
        """The bounds in words, e.g. ``(0, 0.2] m``; empty without bounds."""
        lo = self.ge if self.ge is not None else self.gt
        hi = self.le if self.le is not None else self.lt
        if lo is None and hi is None:
            return ""
        left = "[" if self.ge is not None else "("
        right = "]" if self.le is not None else ")"
        low = "-inf" if lo is None else f"{lo:g}"
        high = "inf" if hi is None else f"{hi:g}"
        return f"{left}{low}, {high}{right}" + (f" {self.unit}" if self.unit else "")


def param(
    default: Any,
    *,
    help: str,
    unit: str = "",
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """A dataclass field with its default and its :class:`Spec`."""
    spec = Spec(help=help, unit=unit, ge=ge, gt=gt, le=le, lt=lt, choices=choices)
    if isinstance(default, (list, dict, set)):
        raise TypeError("use a tuple for a sequence default: parameters are immutable")
    return dataclasses.field(default=default, metadata={SPEC_KEY: spec})


def specs(cls: type[Any]) -> dict[str, Spec]:
    """Name -> :class:`Spec` of every declared parameter of a dataclass, in field order."""
    return {f.name: f.metadata[SPEC_KEY] for f in dataclasses.fields(cls) if SPEC_KEY in f.metadata}


def type_hints(cls: type[Any]) -> dict[str, Any]:
    """The resolved annotations of a dataclass's fields."""
    return typing.get_type_hints(cls)


def default_of(cls: type[Any], name: str) -> Any:
    return next(f.default for f in dataclasses.fields(cls) if f.name == name)


def _check_number(name: str, value: Any, spec: Spec, *, integer: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if integer and not isinstance(value, int):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    problems = []
    if spec.ge is not None and not value >= spec.ge:
        problems.append(f">= {spec.ge:g}")
    if spec.gt is not None and not value > spec.gt:
        problems.append(f"> {spec.gt:g}")
    if spec.le is not None and not value <= spec.le:
        problems.append(f"<= {spec.le:g}")
    if spec.lt is not None and not value < spec.lt:
        problems.append(f"< {spec.lt:g}")
    if problems:
        unit = f" {spec.unit}" if spec.unit else ""
        raise ValueError(
            f"{name} must be in {spec.describe() or ' and '.join(problems)}, got {value!r}{unit}"
        )


def check_bounds(instance: object) -> None:
    """Check every declared parameter of a dataclass instance against its :class:`Spec`.

    Numbers are checked against the bounds (each element of a tuple too); text against the
    choices; ``None`` passes where the annotation allows it, a text value (such as ``"auto"``)
    where the annotation names it as a literal.

    Raises
    ------
    ValueError
        Naming the parameter, its bounds and the value given.
    """
    hints = type_hints(type(instance))
    for name, spec in specs(type(instance)).items():
        value = getattr(instance, name)
        allowed = _literals(hints.get(name))
        if value is None and _allows_none(hints.get(name)):
            continue
        if hints.get(name) is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be true or false, got {value!r}")
            continue
        if isinstance(value, str):
            options = spec.choices or tuple(allowed)
            if options and value not in options:
                raise ValueError(
                    f"{name} must be one of {', '.join(map(str, options))}, got {value!r}"
                )
            hint = hints.get(name)
            if not options and not (hint is str or str in typing.get_args(hint)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            continue
        if isinstance(value, tuple):
            for item in value:
                _check_number(name, item, spec)
            continue
        if spec.choices is not None and value not in spec.choices:
            raise ValueError(
                f"{name} must be one of {', '.join(map(str, spec.choices))}, got {value!r}"
            )
        _check_number(name, value, spec, integer=hints.get(name) is int)


def _literals(hint: Any) -> list[Any]:
    """The literal values an annotation names (``Literal["auto"]`` inside a union too)."""
    if hint is None:
        return []
    if typing.get_origin(hint) is typing.Literal:
        return list(typing.get_args(hint))
    return [value for arg in typing.get_args(hint) for value in _literals(arg)]


def _allows_none(hint: Any) -> bool:
    return hint is type(None) or type(None) in typing.get_args(hint)
