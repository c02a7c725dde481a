"""A URScript interpreter for standalone programs sent to the fake controller's script ports.

teachpath exports programs for the teach pendant; its tests run them on the fake and compare the
executed path with the plan. This module compiles such a program once (:func:`compile_program`)
and runs it one control period at a time (:class:`Runner`, driven by the controller's tick as
ur_rtde's command loop is), so a program of tens of thousands of ``servoj`` lines is parsed once
and never re-read.

The subset (what an exported program uses):

- one ``def name(): ... end`` block, optionally followed by the call ``name()``, or a bare
  sequence of statements (as a program sent to the secondary port may be); ``#`` comments,
  blank lines; numbers in any float notation; strings; ``True`` / ``False``;
- assignments of a value to a name (``x = ...``, ``local x = ...``, ``global x = ...``) and
  names as arguments -- values only: no arithmetic, no indexing;
- calls, with positional and keyword arguments as URScript binds them: ``textmsg``, ``sync``,
  ``sleep``, ``halt``, ``set_tcp``, ``set_payload``, ``set_payload_mass``, ``set_payload_cog``,
  ``set_target_payload``, ``movej``, ``movel``, ``movep``, ``servoj``, ``stopj``, ``stopl``.

Anything else -- an unknown function, ``while`` / ``if`` / ``thread`` / nested ``def``, an
expression the subset has no meaning for -- is refused when the program is compiled, with its
line, and nothing runs (a real controller refuses a program that does not compile, too). What
can only fail at run time (no inverse kinematics solution, a speed <= 0, a value of the wrong
kind in a variable) stops the program at that line as a URScript runtime error does.

Motion (see :class:`Runner` for the timing of each call): ``movej`` is a synchronised joint
trapezoid; ``movel`` a straight TCP line; ``movep`` and blended ``movel`` runs are one tool path
at constant speed whose corners are rounded within the blend radius (:func:`tool_path`);
blended ``movej`` runs are passed at speed in joint space, rounded by the servo law (as
ur_rtde's movePath is); ``servoj`` feeds the same lookahead / gain model as ur_rtde's servoJ.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

from recon.arrays import FloatArray

#: Non-blocking statements run in one control period at most (the rest wait for the next one),
#: so a program of ten thousand ``textmsg`` lines cannot stall the control tick.
STATEMENTS_PER_TICK = 500
#: Dense sampling of a tool path's geometry (m): finer than any tolerance the tests check.
TOOL_PATH_STEP_M = 2e-4
#: A tool path is sampled at no more points than this (a longer path is sampled coarser).
TOOL_PATH_MAX_POINTS = 200_000


class ScriptRuntimeError(Exception):
    """What stops a URScript program at run time: no IK solution, an invalid argument, a move
    the controller cannot run. The fake stops the program, as the controller would."""


class CompileError(ValueError):
    """A program the fake cannot run at all (syntax, unknown function, outside the subset).

    Attributes
    ----------
    line : int
        1-based line of the program text.
    """

    def __init__(self, line: int, message: str) -> None:
        super().__init__(f"line {line}: {message}")
        self.line = line
        self.message = message


# -- values ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Pose:
    """A URScript pose ``p[x, y, z, rx, ry, rz]`` (m, rotation vector in rad)."""

    values: np.ndarray


@dataclass(frozen=True)
class Name:
    """A variable read at run time."""

    name: str


@dataclass(frozen=True, eq=False)
class ListOf:
    """A list literal with names among its items (evaluated at run time)."""

    items: tuple[Any, ...]
    pose: bool


def _evaluate(expr: Any, variables: dict[str, Any]) -> Any:
    if isinstance(expr, Name):
        if expr.name not in variables:
            raise ScriptRuntimeError(f"variable {expr.name!r} is not defined")
        return variables[expr.name]
    if isinstance(expr, ListOf):
        values = []
        for item in expr.items:
            value = _evaluate(item, variables)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ScriptRuntimeError("a list or pose holds numbers only in the fake's subset")
            values.append(float(value))
        array = np.array(values, dtype=np.float64)
        return Pose(array) if expr.pose else array
    return expr


# -- the functions the subset knows ---------------------------------------------------------------

_REQUIRED = object()


@dataclass(frozen=True)
class Signature:
    """A function's parameters in order, with defaults (``_REQUIRED`` for none)."""

    params: tuple[tuple[str, Any], ...]

    def bind(
        self, function: str, args: Sequence[Any], kwargs: dict[str, Any], line: int
    ) -> tuple[Any, ...]:
        """Values in parameter order, as URScript binds positional then keyword arguments."""
        names = [name for name, _ in self.params]
        if len(args) > len(names):
            raise CompileError(
                line, f"{function}() takes at most {len(names)} arguments, {len(args)} given"
            )
        bound = dict(zip(names, args, strict=False))
        for key, value in kwargs.items():
            if key not in names:
                raise CompileError(line, f"{function}() has no parameter {key!r}")
            if key in bound:
                raise CompileError(line, f"{function}() got {key!r} twice")
            bound[key] = value
        values = []
        for name, default in self.params:
            if name not in bound:
                if default is _REQUIRED:
                    raise CompileError(line, f"{function}() needs its argument {name!r}")
                bound[name] = default
            values.append(bound[name])
        return tuple(values)


def _sig(*params: str | tuple[str, Any]) -> Signature:
    return Signature(tuple(p if isinstance(p, tuple) else (p, _REQUIRED) for p in params))


#: URScript's signatures and defaults (URScript manual) for the functions the fake runs.
FUNCTIONS: dict[str, Signature] = {
    "textmsg": _sig("s1", ("s2", "")),
    "sync": _sig(),
    "sleep": _sig("t"),
    "halt": _sig(),
    "popup": _sig(
        "s", ("title", "Popup"), ("warning", False), ("error", False), ("blocking", False)
    ),
    "set_tcp": _sig("pose"),
    "set_payload": _sig("m", ("cog", None)),
    "set_payload_mass": _sig("m"),
    "set_payload_cog": _sig("CoG"),
    "set_target_payload": _sig(
        "mass", "center_of_gravity", ("inertia", None), ("transition_time", 0.0)
    ),
    "movej": _sig("q", ("a", 1.4), ("v", 1.05), ("t", 0.0), ("r", 0.0)),
    "movel": _sig("pose", ("a", 1.2), ("v", 0.25), ("t", 0.0), ("r", 0.0)),
    "movep": _sig("pose", ("a", 1.2), ("v", 0.25), ("r", 0.0)),
    "servoj": _sig(
        "q", ("a", 0.0), ("v", 0.0), ("t", 0.002), ("lookahead_time", 0.1), ("gain", 300.0)
    ),
    "stopj": _sig("a"),
    "stopl": _sig("a", ("aRot", None)),
}
MOVES = ("movej", "movel", "movep")

#: Statements that begin a block: outside the subset (refused at compile time).
_BLOCK_KEYWORDS = {"while", "if", "elif", "else", "for", "thread", "def", "sec", "run", "join"}


@dataclass(frozen=True, eq=False)
class Statement:
    """One statement: a call (``target`` None) or an assignment to ``target``.

    Attributes
    ----------
    line : int
        1-based line in the program text.
    function : str
        The called function (``"="`` for an assignment).
    args : tuple
        The arguments bound to the function's parameters in order (constants, or
        :class:`Name` / :class:`ListOf` read at run time); the value for an assignment.
    """

    line: int
    function: str
    args: tuple[Any, ...]
    target: str | None = None
    body: tuple[Statement, ...] = ()


@dataclass(frozen=True, eq=False)
class Program:
    """A compiled program: its name and statements in order."""

    name: str
    statements: tuple[Statement, ...]
    lines: int = 0


# -- the parser ------------------------------------------------------------------------------------

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_TOKEN = re.compile(
    rf"""\s*(?:(?P<number>{_NUMBER})|(?P<string>"[^"\n]*"|'[^'\n]*')|(?P<name>[A-Za-z_]\w*)"""
    r"""|(?P<op>[\[\](),=:])|(?P<other>\S))"""
)
# The common case, fast: ``name([n, n, n, n, n, n], k=n, ...)`` with literal numbers only.
_FAST_CALL = re.compile(
    rf"^(?P<function>[A-Za-z_]\w*)\s*\(\s*(?P<pose>p?)\[\s*(?P<values>{_NUMBER}(?:\s*,\s*{_NUMBER})*)"
    rf"\s*\](?P<rest>(?:\s*,\s*(?:[A-Za-z_]\w*\s*=\s*)?{_NUMBER})*)\s*\)$"
)
_FAST_REST = re.compile(rf"\s*,\s*(?:([A-Za-z_]\w*)\s*=\s*)?({_NUMBER})")
_DEF = re.compile(r"^def\s+([A-Za-z_]\w*)\s*\(\s*\)\s*:$")
# The one conditional the subset has: a check that the arm stands where a program starts
# (``teachpath export-urscript`` writes one per joint):
# ``if norm(get_actual_joint_positions()[J] - (X)) > D:`` opening a block of calls (a popup,
# halt) closed by ``end``.
_JOINT_GUARD = re.compile(
    rf"^if\s+norm\s*\(\s*get_actual_joint_positions\s*\(\s*\)\s*\[\s*(?P<joint>[0-5])\s*\]"
    rf"\s*-\s*\(?\s*(?P<target>{_NUMBER})\s*\)?\s*\)\s*>\s*(?P<limit>{_NUMBER})\s*:$"
)
_CALL_PROGRAM = re.compile(r"^([A-Za-z_]\w*)\s*\(\s*\)$")


def _strip_comment(line: str) -> str:
    if "#" not in line:
        return line.strip()
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            return line[:i].strip()
    return line.strip()


class _Tokens:
    def __init__(self, text: str, line: int) -> None:
        self.line = line
        self.items: list[tuple[str, str]] = []
        position = 0
        text = text.rstrip()
        while position < len(text):
            match = _TOKEN.match(text, position)
            if match is None:  # only trailing blanks are left
                break
            kind = match.lastgroup or "other"
            self.items.append((kind, match.group(kind)))
            position = match.end()
        self.i = 0

    def peek(self, offset: int = 0) -> tuple[str, str]:
        j = self.i + offset
        return self.items[j] if j < len(self.items) else ("end", "")

    def take(self) -> tuple[str, str]:
        item = self.peek()
        self.i += 1
        return item

    def expect(self, value: str) -> None:
        kind, got = self.take()
        if got != value or kind != "op":
            raise CompileError(self.line, f"expected {value!r}, found {got or 'end of line'!r}")


def _expression(tokens: _Tokens) -> float | str | bool | Name | ListOf | Pose | FloatArray:
    kind, value = tokens.take()
    if kind == "number":
        return float(value)
    if kind == "string":
        return value[1:-1]
    if kind == "name":
        if value == "p" and tokens.peek() == ("op", "["):
            tokens.take()
            return _list(tokens, pose=True)
        if value in ("True", "False"):
            return value == "True"
        if tokens.peek() == ("op", "("):
            raise CompileError(
                tokens.line, f"a call as an argument ({value}(...)) is outside the fake's subset"
            )
        return Name(value)
    if (kind, value) == ("op", "["):
        return _list(tokens, pose=False)
    raise CompileError(
        tokens.line,
        f"unexpected {value or 'end of line'!r} (the fake runs values and calls only: no "
        "arithmetic, indexing or operators)",
    )


def _list(tokens: _Tokens, *, pose: bool) -> ListOf | Pose | FloatArray:
    items = []
    if tokens.peek() != ("op", "]"):
        while True:
            item = _expression(tokens)
            if isinstance(item, bool) or not isinstance(item, (float, Name)):
                raise CompileError(tokens.line, "a list or pose holds numbers only")
            items.append(item)
            if tokens.peek() == ("op", ","):
                tokens.take()
                continue
            break
    tokens.expect("]")
    if any(isinstance(item, Name) for item in items):
        return ListOf(tuple(items), pose)
    array = np.array(items, dtype=np.float64)
    return Pose(array) if pose else array


def _call(function: str, tokens: _Tokens, line: int) -> Statement:
    if function not in FUNCTIONS:
        raise CompileError(
            line, f"unknown function {function}() (not in the fake's URScript subset)"
        )
    tokens.expect("(")
    args: list[Any] = []
    kwargs: dict[str, Any] = {}
    if tokens.peek() != ("op", ")"):
        while True:
            if tokens.peek()[0] == "name" and tokens.peek(1) == ("op", "="):
                key = tokens.take()[1]
                tokens.take()
                kwargs[key] = _expression(tokens)
            elif kwargs:
                raise CompileError(line, "a positional argument after a keyword argument")
            else:
                args.append(_expression(tokens))
            if tokens.peek() == ("op", ","):
                tokens.take()
                continue
            break
    tokens.expect(")")
    if tokens.peek()[0] != "end":
        raise CompileError(line, f"unexpected {tokens.peek()[1]!r} after {function}(...)")
    return Statement(line, function, FUNCTIONS[function].bind(function, args, kwargs, line))


def _fast(text: str, line: int) -> Statement | None:
    match = _FAST_CALL.match(text)
    if match is None or match.group("function") not in FUNCTIONS:
        return None
    values = np.array(match.group("values").split(","), dtype=np.float64)
    first = Pose(values) if match.group("pose") else values
    args: list[Any] = [first]
    kwargs: dict[str, Any] = {}
    for key, number in _FAST_REST.findall(match.group("rest")):
        if key:
            kwargs[key] = float(number)
        elif kwargs:
            raise CompileError(line, "a positional argument after a keyword argument")
        else:
            args.append(float(number))
    function = match.group("function")
    return Statement(line, function, FUNCTIONS[function].bind(function, args, kwargs, line))


def _statement(text: str, line: int) -> Statement:
    fast = _fast(text, line)
    if fast is not None:
        return fast
    tokens = _Tokens(text, line)
    kind, value = tokens.take()
    if kind != "name":
        raise CompileError(line, f"unexpected {value!r} at the start of a statement")
    if value in _BLOCK_KEYWORDS or (tokens.items and tokens.items[-1] == ("op", ":")):
        raise CompileError(
            line, f"'{value}' blocks are outside the fake's URScript subset (no control flow)"
        )
    if value == "end":
        raise CompileError(line, "'end' without a block")
    if value in ("local", "global"):
        kind, value = tokens.take()
        if kind != "name" or tokens.peek() != ("op", "="):
            raise CompileError(line, "expected an assignment after local / global")
    if tokens.peek() == ("op", "="):
        tokens.take()
        if value in FUNCTIONS or value in ("p", "True", "False"):
            raise CompileError(line, f"cannot assign to {value!r}")
        expr = _expression(tokens)
        if tokens.peek()[0] != "end":
            raise CompileError(
                line, f"unexpected {tokens.peek()[1]!r}: only a value can be assigned"
            )
        return Statement(line, "=", (expr,), target=value)
    if tokens.peek() == ("op", "("):
        return _call(value, tokens, line)
    raise CompileError(line, f"unexpected {value!r}: a statement is a call or an assignment")


def compile_program(text: str) -> Program:
    """Compile a program received on a script port.

    Raises
    ------
    CompileError
        Syntax the subset does not have, an unknown function, control flow, a second program,
        statements after the program other than its call; with the line.
    """
    statements: list[Statement] = []
    name = ""
    state = "bare"  # bare -> (def) body -> after
    called = False
    # An open joint guard: its line, (joint, target), limit and body.
    guard: tuple[int, tuple[int, float], float, list[Statement]] | None = None
    lines = text.splitlines()
    for number, raw in enumerate(lines, start=1):
        code = _strip_comment(raw)
        if not code:
            continue
        if code == "halt":  # a statement in URScript, with or without parentheses here
            code = "halt()"
        if guard is not None:
            if code == "end":
                line, target, limit, body = guard
                statements.append(Statement(line, "joint_guard", (target, limit), body=tuple(body)))
                guard = None
                continue
            statement = _statement(code, number)
            if statement.function not in ("popup", "textmsg", "halt"):
                raise CompileError(number, "the start check may only hold popup, textmsg and halt")
            guard[3].append(statement)
            continue
        match = _JOINT_GUARD.match(code)
        if match is not None:
            target = (int(match.group("joint")), float(match.group("target")))
            guard = (number, target, float(match.group("limit")), [])
            continue
        match = _DEF.match(code)
        if match is not None:
            if state != "bare" or statements:
                raise CompileError(number, "one program per upload: a def after the program")
            name, state = match.group(1), "body"
            continue
        if state == "body" and code == "end":
            state = "after"
            continue
        if state == "after":
            call = _CALL_PROGRAM.match(code)
            if call is None or call.group(1) != name or called:
                raise CompileError(
                    number, f"after 'end' of {name}() only the call {name}() may follow"
                )
            called = True  # the program runs once either way
            continue
        statements.append(_statement(code, number))
    if guard is not None:
        raise CompileError(guard[0], "the start check (if ...:) has no 'end'")
    if state == "body":
        raise CompileError(len(lines), f"def {name}() has no 'end'")
    return Program(name=name or "<script>", statements=tuple(statements), lines=len(lines))


# -- tool paths (movep, blended movel) -------------------------------------------------------------


@dataclass(frozen=True)
class ToolPath:
    """A tool path sampled every control period.

    Attributes
    ----------
    poses : ndarray of shape (K, 6)
        TCP poses (m, rotation vector).
    move_ticks : ndarray of shape (M,)
        Sample index at which each move (after the first) starts, ascending.
    """

    poses: np.ndarray
    move_ticks: np.ndarray


def tool_path(
    start: np.ndarray,
    targets: Sequence[np.ndarray],
    *,
    speeds: Sequence[float],
    accelerations: Sequence[float],
    blends_m: Sequence[float],
    dt: float,
) -> ToolPath:
    """Sample a run of linear moves (``movep`` / ``movel``) through ``targets`` from ``start``.

    The TCP moves along straight segments; at an interior waypoint with a blend radius ``r``
    the corner is cut by a quadratic Bezier curve from ``r`` before the waypoint to ``r`` after
    it (``r`` limited to half of either segment), which passes within ``r / 2`` of the waypoint
    -- a circular blend, as UR's controller makes, passes within about ``0.3 r``; both stay
    inside ``r``. The tool speed is capped by each move's ``v`` (the lower of the two in a
    blend), ramps at the lowest ``a`` of the run and falls to zero at both ends only, so a run
    of movep moves keeps a constant tool speed through its blends. The orientation is
    interpolated (slerp) along each segment by the distance travelled; a segment without
    translation turns at once (orientation speed is not modelled).

    Parameters
    ----------
    start : ndarray of shape (6,)
        The TCP pose the run starts from.
    targets : sequence of ndarray of shape (6,)
        Each move's TCP target pose.
    speeds, accelerations, blends_m : sequences of float, one per move
        ``v`` (m/s), ``a`` (m/s^2), ``r`` (m; the last move's is ignored: the run stops there).
    dt : float
        Control period (s).
    """
    points = np.array([start[:3]] + [t[:3] for t in targets], dtype=np.float64)
    rotations = Rotation.from_rotvec(np.array([start[3:6]] + [t[3:6] for t in targets]))
    n = len(targets)
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    radius = np.zeros(n + 1)  # at waypoint k (0 and n: none)
    for k in range(1, n):
        radius[k] = max(0.0, min(float(blends_m[k - 1]), lengths[k - 1] / 2, lengths[k] / 2))
    # Pieces in order: ("line", segment, from_m, to_m) and ("blend", waypoint).
    pieces: list[tuple[Any, ...]] = []
    for k in range(n):
        pieces.append(("line", k, radius[k], lengths[k] - radius[k + 1]))
        if k + 1 < n and radius[k + 1] > 0:
            pieces.append(("blend", k + 1))
    directions = np.diff(points, axis=0) / np.maximum(lengths, 1e-12)[:, None]
    tau = np.linspace(0.0, 1.0, 65)
    piece_lengths, blend_tables = [], {}
    for piece in pieces:
        if piece[0] == "line":
            piece_lengths.append(max(piece[3] - piece[2], 0.0))
            continue
        k = piece[1]
        curve = _bezier(points, directions, radius, k, tau)
        table = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
        blend_tables[k] = table
        piece_lengths.append(float(table[-1]))
    knots = np.concatenate([[0.0], np.cumsum(piece_lengths)])
    total = float(knots[-1])
    if total < 1e-9:
        # No translation at all: the orientation turns at once (documented).
        return ToolPath(np.array([np.asarray(targets[-1], dtype=np.float64)]), np.zeros(0, int))
    step = max(TOOL_PATH_STEP_M, total / TOOL_PATH_MAX_POINTS)
    s = np.linspace(0.0, total, max(int(np.ceil(total / step)), 2) + 1)
    h = s[1] - s[0]
    piece_at = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(pieces) - 1)
    xyz = np.empty((len(s), 3))
    u = np.empty(len(s))  # polyline parameter: segment index + fraction, for the orientation
    cap = np.empty(len(s))
    for index, piece in enumerate(pieces):
        mask = piece_at == index
        if not mask.any():
            continue
        local = s[mask] - knots[index]
        if piece[0] == "line":
            k, begin = piece[1], piece[2]
            along = begin + local
            xyz[mask] = points[k] + along[:, None] * directions[k]
            u[mask] = k + along / max(lengths[k], 1e-12)
            cap[mask] = speeds[k]
        else:
            k = piece[1]
            t = np.interp(local, blend_tables[k], tau)
            xyz[mask] = _bezier(points, directions, radius, k, t)
            before, after = radius[k] / lengths[k - 1], radius[k] / lengths[k]
            u[mask] = (k - before) + t * (before + after)
            cap[mask] = min(speeds[k - 1], speeds[k])
    # Speed: capped, from and to rest at the run's acceleration (forward and backward passes
    # in closed form on the uniform grid: v^2(i) = min_j cap^2(j) + 2 a h |i - j|).
    a = float(min(accelerations))
    cap2 = cap**2
    cap2[0] = cap2[-1] = 0.0
    i = np.arange(len(s))
    ramp = 2 * a * h * i
    forward = ramp + np.minimum.accumulate(cap2 - ramp)
    backward = -ramp + np.minimum.accumulate((cap2 + ramp)[::-1])[::-1]
    speed = np.sqrt(np.maximum(np.minimum(cap2, np.minimum(forward, backward)), 0.0))
    mean = np.maximum(0.5 * (speed[1:] + speed[:-1]), 1e-9)
    t_at = np.concatenate([[0.0], np.cumsum(h / mean)])
    times = np.arange(dt, t_at[-1] + dt, dt)
    s_at = np.interp(times, t_at, s)
    sample_xyz = np.column_stack([np.interp(s_at, s, xyz[:, j]) for j in range(3)])
    sample_u = np.clip(np.interp(s_at, s, u), 0.0, n)
    sample_u[-1] = n
    segment = np.clip(np.floor(sample_u).astype(int), 0, n - 1)
    rotvec = np.empty((len(times), 3))
    for k in np.unique(segment):
        mask = segment == k
        slerp = Slerp([0.0, 1.0], rotations[[k, k + 1]])
        rotvec[mask] = slerp(np.clip(sample_u[mask] - k, 0.0, 1.0)).as_rotvec()
    # Move k (0-based, k >= 1) starts once the path passes waypoint k's blend start.
    move_starts = np.searchsorted(sample_u, np.arange(1, n) - 1e-9)
    return ToolPath(np.hstack([sample_xyz, rotvec]), move_starts.astype(int))


def _bezier(
    points: FloatArray, directions: FloatArray, radius: FloatArray, k: int, t: ArrayLike
) -> FloatArray:
    """The blend at waypoint ``k``: quadratic Bezier from ``r`` before to ``r`` after it."""
    t = np.asarray(t, dtype=np.float64)[:, None]
    p0 = points[k] - radius[k] * directions[k - 1]
    p2 = points[k] + radius[k] * directions[k]
    curve: FloatArray = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * points[k] + t**2 * p2
    return curve


def timed_profile(distance: float, acceleration: float, time_s: float) -> tuple[float, float]:
    """Speed and acceleration of a trapezoid over ``distance`` that lasts ``time_s`` (a move's
    ``t``, which takes priority over ``v`` and ``a``): ``a`` is kept when the time allows it,
    else the profile is a triangle of the acceleration the time needs."""
    if distance < 1e-12:
        return 1.0, 1.0
    disc = (acceleration * time_s) ** 2 - 4 * acceleration * distance
    if acceleration > 0 and disc >= 0:
        return (acceleration * time_s - np.sqrt(disc)) / 2, acceleration
    acceleration = 4 * distance / time_s**2
    return acceleration * time_s / 2, acceleration


# -- running a program -----------------------------------------------------------------------------


@dataclass
class _MoveArgs:
    line: int
    kind: str
    target: np.ndarray
    is_pose: bool
    a: float
    v: float
    t: float
    r: float


@dataclass
class RunState:
    """Where a program is (for the control channel's ``program_status``)."""

    state: str = "running"  # running | finished | error | stopped | refused
    number: int = 0  # the how-manyth program the controller received (1 = the first)
    line: int | None = None
    message: str | None = None
    started_s: float = 0.0
    ended_s: float | None = None
    executed: int = 0


@dataclass
class Runner:
    """Runs a compiled :class:`Program` on a host controller, one control period a
    :meth:`step`.

    Timing, as on a controller: a move blocks until the arm has arrived (the servo law
    settled); consecutive moves with a blend radius ``r > 0`` in the same space (``movej``
    with ``movej``; ``movel`` / ``movep`` with each other) are planned as one run, and a
    run ends at the first move without a blend or before any other statement (whose blend is
    then taken as a stop); ``servoj`` takes ``t`` of controller time and the arm follows its
    target through the lookahead buffer; a move after ``servoj`` (or the program's end) first
    lets the arm settle on the last servo target; ``sleep(t)`` waits ``t``; ``sync()`` one
    period; ``stopj`` / ``stopl`` brake at their rate and return once the arm rests.

    The host (the fake controller) provides ``t_s``, ``dt_s``, ``message(text)``,
    ``set_tcp(pose)``, ``set_payload(mass, cog, inertia)`` (None: kept), ``actual_q()`` (the
    arm's joints now), ``start_moves(moves)`` (starts one move or a blended run; returns its
    motion and the tick at which each move after the first starts), ``servo(q, t, lookahead,
    gain)`` (returns the call's length in control periods), ``settle_servo()`` (a motion, or
    None when no servo stream runs), ``brake(linear, a)`` (a motion) and
    ``motion_running(motion)``. Its methods
    raise :class:`ScriptRuntimeError` (with a ``line`` attribute for a move within a run).
    """

    program: Program
    host: Any
    variables: dict[str, Any] = field(default_factory=dict)
    pc: int = 0
    status: RunState = field(default_factory=RunState)
    _wait: Callable[[], bool] | None = None
    _group_lines: tuple[int, ...] = ()
    _group_ticks: tuple[int, ...] = ()
    _motion: Any = None
    _servoing: bool = False

    def __post_init__(self) -> None:
        self.status.started_s = self.host.t_s

    @property
    def finished(self) -> bool:
        return self.status.state != "running"

    def current_line(self) -> int | None:
        """The line being executed (within a run of blended moves, the move under way)."""
        if self._group_lines and self._motion is not None:
            k = int(np.searchsorted(self._group_ticks, self._motion.tick, side="right"))
            return self._group_lines[min(k, len(self._group_lines) - 1)]
        return self.status.line

    def step(self) -> None:
        """Run statements until one takes time, or the program ends.

        Raises
        ------
        ScriptRuntimeError
            With ``status.line`` set to the failing line; the host stops the program.
        """
        if self.finished:
            return
        if self._wait is not None:
            if not self._wait():
                return
            self._wait = None
            self._group_lines = ()
        for _ in range(STATEMENTS_PER_TICK):
            if self.pc >= len(self.program.statements):
                if self._servoing:  # the arm settles on the last servo target first
                    self._block_on(self.host.settle_servo())
                    self._servoing = False
                    if self._wait is not None:
                        return
                self.status.state = "finished"
                self.status.ended_s = self.host.t_s
                return
            statement = self.program.statements[self.pc]
            self.status.line = statement.line
            self._execute(statement)
            if self._wait is not None:
                return

    def _block_on(self, motion: Any) -> None:
        if motion is None:
            return
        self._motion = motion
        self._wait = lambda: not self.host.motion_running(motion)

    def _value(self, expr: Any) -> Any:
        return _evaluate(expr, self.variables)

    def _number(self, function: str, name: str, expr: Any) -> float:
        value = self._value(expr)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ScriptRuntimeError(f"{function}: {name} must be a number")
        if not np.isfinite(value):
            raise ScriptRuntimeError(f"{function}: {name} must be finite")
        return float(value)

    def _vector(
        self, function: str, name: str, expr: Any, size: int, *, pose: bool | None
    ) -> tuple[FloatArray, bool]:
        """A list (``pose`` False), a pose (True) or either (None) of ``size`` numbers, and
        whether it was a pose."""
        value = self._value(expr)
        is_pose = isinstance(value, Pose)
        array = value.values if is_pose else value
        if not isinstance(array, np.ndarray) or (pose is not None and pose != is_pose):
            kind = {True: "a pose p[...]", False: "a list [...]", None: "a list or a pose"}[pose]
            raise ScriptRuntimeError(f"{function}: {name} must be {kind}")
        if array.shape != (size,):
            raise ScriptRuntimeError(f"{function}: {name} needs {size} values, not {array.size}")
        if not np.all(np.isfinite(array)):
            raise ScriptRuntimeError(f"{function}: {name} must be finite")
        return array.copy(), is_pose

    def _execute(self, statement: Statement) -> None:  # noqa: C901
        function, args = statement.function, statement.args
        if function == "=":
            if statement.target is None:
                raise ScriptRuntimeError("an assignment without a variable to assign to")
            self.status.executed += 1
            self.variables[statement.target] = self._value(args[0])
            self.pc += 1
            return
        if self._servoing and function != "servoj" and function in (*MOVES, "stopj", "stopl"):
            # servoj's target stream ends: settle on it before the next motion.
            self._servoing = False
            self._block_on(self.host.settle_servo())
            if self._wait is not None:
                return  # the statement runs when the arm has settled
        self.status.executed += 1
        if function in MOVES:
            self._moves()
            return
        self.pc += 1
        if function == "joint_guard":
            joint, target = args[0]
            if abs(float(self.host.actual_q()[joint]) - target) > args[1]:
                resume = self.pc  # the body's statements are not the program's
                for inner in statement.body:
                    self._execute(inner)
                    if self.finished:
                        return
                self.pc = resume
        elif function == "textmsg":
            self.host.message("".join(_text(self._value(a)) for a in args))
        elif function == "popup":
            self.host.message(f"popup: {_text(self._value(args[0]))}")
        elif function == "sync":
            until = self.host.t_s + 0.5 * self.host.dt_s
            self._wait = lambda: self.host.t_s > until
        elif function == "sleep":
            duration = self._number("sleep", "t", args[0])
            if duration < 0:
                raise ScriptRuntimeError("sleep: t must be >= 0")
            until = self.host.t_s + duration - 0.5 * self.host.dt_s
            self._wait = lambda: self.host.t_s >= until
        elif function == "halt":
            self.pc = len(self.program.statements)
            self._servoing = False
            self.status.state = "finished"
            self.status.ended_s = self.host.t_s
        elif function == "set_tcp":
            pose, _ = self._vector("set_tcp", "pose", args[0], 6, pose=True)
            self.host.set_tcp(pose)
        elif function in ("set_payload", "set_target_payload"):
            mass = self._number(function, "mass", args[0])
            if mass < 0:
                raise ScriptRuntimeError(f"{function}: the mass must be >= 0")
            cog = (
                None
                if args[1] is None
                else self._vector(function, "cog", args[1], 3, pose=False)[0]
            )
            inertia = None
            if function == "set_target_payload" and args[2] is not None:
                inertia = self._vector(function, "inertia", args[2], 6, pose=False)[0]
            self.host.set_payload(mass, cog, inertia)
        elif function == "set_payload_mass":
            mass = self._number(function, "m", args[0])
            if mass < 0:
                raise ScriptRuntimeError(f"{function}: the mass must be >= 0")
            self.host.set_payload(mass, None, None)
        elif function == "set_payload_cog":
            self.host.set_payload(
                None, self._vector(function, "CoG", args[0], 3, pose=False)[0], None
            )
        elif function == "servoj":
            self._servoj(args)
        elif function in ("stopj", "stopl"):
            rate = self._number(function, "a", args[0])
            if not rate > 0:
                raise ScriptRuntimeError(f"{function}: deceleration must be > 0")
            self._block_on(self.host.brake(function == "stopl", rate))
        else:  # pragma: no cover - FUNCTIONS and this dispatch are kept together
            raise ScriptRuntimeError(f"{function}() is not implemented by the fake")

    def _servoj(self, args: tuple[Any, ...]) -> None:
        q, _ = self._vector("servoj", "q", args[0], 6, pose=False)
        t = self._number("servoj", "t", args[3])
        lookahead = self._number("servoj", "lookahead_time", args[4])
        gain = self._number("servoj", "gain", args[5])
        if not t > 0:
            raise ScriptRuntimeError("servoj: t must be > 0")
        # URScript's documented ranges.
        if not 0.03 <= lookahead <= 0.2:
            raise ScriptRuntimeError(f"servoj: lookahead_time {lookahead} outside [0.03, 0.2]")
        if not 100 <= gain <= 2000:
            raise ScriptRuntimeError(f"servoj: gain {gain} outside [100, 2000]")
        ticks = self.host.servo(q, t, lookahead, gain)
        self._servoing = True
        until = self.host.t_s + (ticks - 0.5) * self.host.dt_s
        self._wait = lambda: self.host.t_s >= until

    def _move_args(self, statement: Statement) -> _MoveArgs:
        function, args = statement.function, statement.args
        target, is_pose = self._vector(function, "the target", args[0], 6, pose=None)
        a = self._number(function, "a", args[1])
        v = self._number(function, "v", args[2])
        t = 0.0 if function == "movep" else self._number(function, "t", args[3])
        r = self._number(function, "r", args[-1])
        if t < 0 or r < 0:
            raise ScriptRuntimeError(f"{function}: t and r must be >= 0")
        if t == 0 and not (v > 0 and a > 0):
            raise ScriptRuntimeError(
                f"{function}: speed and acceleration must be > 0 (v={v}, a={a})"
            )
        return _MoveArgs(statement.line, function, target, is_pose, a, v, t, r)

    def _moves(self) -> None:
        """The move at ``pc`` and the moves it blends into: one motion."""
        statements = self.program.statements
        first = statements[self.pc]
        joint_space = first.function == "movej"
        group = [self._move_args(first)]
        end = self.pc + 1
        while group[-1].r > 0 and end < len(statements):
            following = statements[end]
            if following.function not in MOVES or (following.function == "movej") != joint_space:
                break
            self.status.line = following.line
            group.append(self._move_args(following))
            self.status.executed += 1
            end += 1
        self.status.line = first.line
        motion, ticks = self.host.start_moves(group)
        self.pc = end
        self._group_lines = tuple(m.line for m in group)
        self._group_ticks = tuple(int(t) for t in ticks)
        self._block_on(motion)
        if self._wait is None:
            self._group_lines = ()


def _text(value: object) -> str:
    if isinstance(value, Pose):
        return "p[" + ", ".join(f"{v:.6g}" for v in value.values) + "]"
    if isinstance(value, np.ndarray):
        return "[" + ", ".join(f"{v:.6g}" for v in value) + "]"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
