"""What several commands share: the parser class, value types, option groups, file readers."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

if TYPE_CHECKING:
    from drivers.tracking.readers import Piece
    from recon.arrays import FloatArray
    from recon.inputs import Recording, Scan
    from recon.params import Spec

_Params = TypeVar("_Params")

#: Exit status for bad input or impossible work (argparse uses 2 for bad usage).
EXIT_FAILURE = 1


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, like every other error here."""

    def error(self, message: str) -> NoReturn:  # noqa: D401 - argparse's name
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def note(message: str) -> None:
    """A line on stderr about what was done to the input (the result goes to stdout)."""
    print(f"note: {message}", file=sys.stderr)


# -- value types -----------------------------------------------------------------------------------


def positive(value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, not {value!r}") from None
    if not (number > 0 and math.isfinite(number)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return number


def numbers(count: int, what: str) -> Callable[[str], tuple[float, ...]]:
    """An argparse type for ``count`` comma-separated finite numbers (``what`` names them)."""

    def parse(value: str) -> tuple[float, ...]:
        try:
            parts = tuple(float(v) for v in value.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} numbers, not {value!r}") from None
        if len(parts) != count or not all(math.isfinite(v) for v in parts):
            raise argparse.ArgumentTypeError(
                f"expected {count} finite numbers {what}, not {value!r}"
            )
        return parts

    return parse


vector3 = numbers(3, "X,Y,Z")
_six = numbers(6, "X0,Y0,Z0,X1,Y1,Z1")
_four = numbers(4, "NX,NY,NZ,D")


def box6(value: str) -> tuple[float, ...]:
    """An argparse type for a keep-out box, checked as the planner checks it."""
    import numpy as np

    from recon.collision import Box

    box = _six(value)
    try:
        Box(min_m=np.array(box[:3]), max_m=np.array(box[3:]))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return box


def cell_plane(value: str) -> tuple[float, ...]:
    """An argparse type for a plane of the cell, checked as the planner checks it."""
    import numpy as np

    from recon.collision import HalfSpace

    plane = _four(value)
    try:
        HalfSpace(normal=np.array(plane[:3]), offset_m=plane[3])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return plane


def check_output(path: str, suffix: str) -> Path:
    """An output path with the right suffix in a folder that exists."""
    out = Path(path)
    if out.suffix.lower() != suffix:
        raise ValueError(f"{path} should end in {suffix}")
    if not out.parent.is_dir() and str(out.parent):
        raise ValueError(f"the folder of {path} does not exist; create it first")
    return out


# -- traces ----------------------------------------------------------------------------------------


def add_trace_options(parser: argparse.ArgumentParser, *, tip: bool = True) -> None:
    parser.add_argument(
        "--path-format",
        choices=("csv", "motive", "c3d"),
        help="format of the trace (default from the suffix; Motive exports are recognised)",
    )
    parser.add_argument("--rigid-body", metavar="NAME", help="Motive: the pen's rigid body")
    parser.add_argument("--marker", metavar="NAME", help="Motive or C3D: a single marker")
    if tip:
        parser.add_argument(
            "--tip-calibration",
            metavar="TIP.json",
            help="pen-tip offset (teachpath calibrate pivot); default: the tracked point itself",
        )
        parser.add_argument(
            "--piece",
            type=piece_choice,
            metavar="N|all",
            help="when long dropouts split the trace: which piece (0-based), or all of them "
            "(the arm lifts between pieces); default the longest",
        )


def piece_choice(text: str) -> int | str:
    """``--piece``: a piece index or "all"."""
    if text.strip().lower() == "all":
        return "all"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a piece number or 'all', got {text!r}"
        ) from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"a piece number is 0 or more, got {value}")
    return value


def add_units_option(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("--units", choices=("m", "mm"), help=help)


def read_trace_for(
    args: argparse.Namespace, path: str | None = None, *, piece: Piece = None
) -> Recording:
    """The trace of a command (``args.path_file`` unless ``path`` is given), with its tip
    calibration applied and its gaps cleaned; what the cleaning did goes to stderr.

    ``piece`` overrides ``--piece`` (touch recordings keep all of theirs)."""
    from drivers.calibration import read_tip_calibration
    from drivers.errors import InputFileError
    from drivers.tracking.readers import read_trace

    tip = None
    if getattr(args, "tip_calibration", None):
        calibration = read_tip_calibration(args.tip_calibration)
        named = calibration.rigid_body
        if named and args.rigid_body and named != args.rigid_body:
            raise InputFileError(
                f"{args.tip_calibration} is the tip of rigid body {named!r}, but the trace is "
                f"of {args.rigid_body!r}; calibrate that pen (teachpath calibrate pivot) or "
                "pick the matching --rigid-body"
            )
        tip = calibration.offset_m
    trace = read_trace(
        path or args.path_file,
        fmt=args.path_format,
        units=args.units,
        rigid_body=args.rigid_body,
        marker=args.marker,
        tip_offset_m=tip,
        piece=piece if piece is not None else args.piece,
    )
    report = trace.clean.report
    if report.events or len(trace.clean.pieces) > 1:
        for line in report.lines():
            note(line)
        if len(trace.clean.pieces) > 1 and trace.piece == "all":
            note(f"using all {len(trace.clean.pieces)} pieces; the arm lifts between them")
        elif len(trace.clean.pieces) > 1 and isinstance(trace.piece, int):
            start, end = report.pieces[trace.piece]
            note(
                f"using piece {trace.piece} ({start:.2f}-{end:.2f} s) of "
                f"{len(trace.clean.pieces)}; choose another with --piece (or all)"
            )
    return trace.recording


# -- scans -----------------------------------------------------------------------------------------


def add_scan_options(parser: argparse.ArgumentParser) -> None:
    from drivers.scanning.base import SCAN_READERS

    parser.add_argument(
        "--scan-format",
        choices=sorted(SCAN_READERS),
        help="format of the scan (default from the suffix; a folder is RGB-D frames)",
    )
    parser.add_argument(
        "--scan-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help='an option of the scan\'s reader, e.g. depth_scale=1000 or fusion="points" '
        "(repeatable; values are JSON, bare words are text)",
    )


def read_scan_for(args: argparse.Namespace) -> Scan:
    """The scan of a command, with its format, unit and reader options; its notes go to
    stderr."""
    from drivers.scanning.base import format_for
    from drivers.scanning.pointcloud import POINT_CLOUD_FORMATS, read_scan

    options: dict[str, Any] = {}  # JSON values, as the reader's options take them
    for item in args.scan_option:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--scan-option takes KEY=VALUE, not {item!r}")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            options[key.strip()] = value
    fmt = args.scan_format
    if fmt is None:
        fmt = "rgbd" if Path(args.scan).is_dir() else format_for(args.scan)
    # --units is for files that do not state theirs; E57, RGB-D and bags fix their own.
    units = (args.units or "m") if fmt in POINT_CLOUD_FORMATS.values() else "m"
    scan_file = read_scan(args.scan, units=units, fmt=fmt, options=options or None)
    for line in scan_file.notes:
        note(line)
    if scan_file.n_dropped:
        note(f"{scan_file.n_dropped} scan points {scan_file.dropped_because} were left out")
    return scan_file.scan


def read_matrix(path: str | None, expect: str) -> FloatArray | None:
    """A stored calibration's 4x4 matrix, or None without a file."""
    if not path:
        return None
    from drivers.calibration import read_calibration

    return read_calibration(path, expect=expect).matrix


# -- core parameters (declared once in recon, see recon.params) ------------------------------------


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _value_type(name: str, hint: Any, spec: Spec) -> Callable[[str], object]:
    """An argparse type for one parameter: numbers, words its annotation names, or X,Y,Z."""
    import typing

    from recon.params import _literals

    words = [w for w in _literals(hint) if isinstance(w, str)]
    args = typing.get_args(hint)
    if hint is str:
        return str
    if hint is bool:
        return _boolean
    tuples = [a for a in (hint, *args) if typing.get_origin(a) is tuple]
    if tuples and Ellipsis in typing.get_args(tuples[0]):
        return _any_numbers
    if tuples:
        count = len(typing.get_args(tuples[0]))
        return numbers(count, ",".join(["N"] * count))
    numeric: type[int] | type[float] = int if hint is int or int in args else float

    def parse(value: str) -> str | int | float:
        if value in words:
            return value
        try:
            return numeric(value)
        except ValueError:
            choices = " or ".join(repr(w) for w in words)
            kind = "an integer" if numeric is int else "a number"
            raise argparse.ArgumentTypeError(
                f"{_flag(name)} takes {kind}"
                + (f" or {choices}" if words else "")
                + f", not {value!r}"
            ) from None

    return parse


def _any_numbers(value: str) -> tuple[float, ...]:
    """Comma-separated finite numbers, as many as given (the parameter checks the count)."""
    try:
        parts = tuple(float(v) for v in value.split(",")) if value.strip() else ()
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers N,N,..., not {value!r}") from None
    if not all(math.isfinite(v) for v in parts):
        raise argparse.ArgumentTypeError(f"expected finite numbers, not {value!r}")
    return parts


def _boolean(value: str) -> bool:
    if value.lower() in ("true", "yes", "1"):
        return True
    if value.lower() in ("false", "no", "0"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, not {value!r}")


def add_param_options(
    parser: argparse.ArgumentParser,
    cls: type[object],
    names: Iterable[str],
    *,
    required: Collection[str] = (),
    aliases: Mapping[str, Sequence[str]] | None = None,
) -> None:
    """Options for the named parameters of a core dataclass, with its help, default and bounds.

    An option not given leaves the core's default (``required`` ones have to be given); the
    values are checked by the core itself when the parameters are built
    (:func:`params_from_args`). ``aliases`` maps a name to more option strings.
    """
    import typing

    from recon.params import _literals, default_of, specs, type_hints

    declared, hints = specs(cls), type_hints(cls)
    for name in names:
        spec, hint, default = declared[name], hints[name], default_of(cls, name)
        shown = ",".join(f"{v:g}" for v in default) if isinstance(default, tuple) else default
        bounds = spec.describe()
        unit = f" {spec.unit}" if spec.unit and not bounds and default is not None else ""
        words = spec.choices or tuple(w for w in _literals(hint) if isinstance(w, str))
        only_words = words and not any(t in (int, float) for t in (hint, *typing.get_args(hint)))
        given = f"default {shown}{unit}" if name not in required else "required"
        if default is None and name not in required:
            given = "default: see above"
        parser.add_argument(
            _flag(name),
            *(aliases or {}).get(name, ()),
            dest=name,
            type=str if only_words else _value_type(name, hint, spec),
            choices=words if only_words else None,
            required=name in required,
            metavar=_metavar(hint),
            help=f"{spec.help} ({given}" + (f"; {bounds})" if bounds else ")"),
        )


def _metavar(hint: Any) -> str | None:
    import typing

    if hint is bool:
        return "true|false"
    for a in (hint, *typing.get_args(hint)):
        if typing.get_origin(a) is tuple and Ellipsis in typing.get_args(a):
            return "N,N,..."
        if typing.get_origin(a) is tuple:
            count = len(typing.get_args(a))
            return "X,Y,Z" if count == 3 else ",".join(["N"] * count)
    return None


def params_from_args(
    cls: Callable[..., _Params], args: argparse.Namespace, names: Iterable[str], **fixed: object
) -> _Params:
    """The core's parameters: its defaults, with the named options the command line was given.

    Raises
    ------
    ValueError
        A value the core refuses (it names the parameter and its bounds).
    """
    given = {name: getattr(args, name) for name in names if getattr(args, name) is not None}
    return cls(**{**given, **fixed})
