"""What the fake controller needs to know about ur_rtde's uploaded control script.

ur_rtde (pinned in pyproject.toml) uploads a URScript program on the script port and then talks
to it through RTDE general purpose registers -- a private protocol of that client version. The
facts below were read off the script the pinned client uploads (observed on loopback), not
copied from its source:

- the program is one ``def ...():`` block ending with an ``end`` line at column 0, and carries
  the markers in :data:`REQUIRED_MARKERS`;
- the register offset (0, or 24 with the "upper range" flag) is assigned to ``reg_offset_int`` /
  ``reg_offset_float`` in the header;
- the command id arrives in input int register 0; the script answers in output int register 0
  (1 ready, 2 done with the command), writes results to output int register 1 and output double
  registers 0-5, and async progress to output int register 2;
- movePath re-uploads the script with the path's moves in place of the ``# inject move path``
  comment inside ``exec_move_path()``;
- each command the fake emulates has its ``cmd == <id>:`` branch in the main loop, reads its
  arguments from the input registers named in :data:`ARGUMENT_MARKERS`, and the real-time
  commands are listed on one ``if cmd == .. or cmd == ..:`` line.

:func:`missing_markers` decides whether an upload is ur_rtde's control script;
:func:`protocol_differences` (markers, command ids, argument registers, the real-time list) is
what the canary test checks against a freshly recorded upload.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

#: Text the pinned client's script contains and the fake relies on.
REQUIRED_MARKERS: dict[str, str] = {
    "program": "def rtde_control():",
    "header": "# HEADER_BEGIN",
    "header end": "# HEADER_END",
    "control loop": "# NODE_CONTROL_LOOP_BEGINS",
    "int register offset": "global reg_offset_int =",
    "float register offset": "global reg_offset_float =",
    "command register": "cmd = read_input_integer_reg(0)",
    "ready signal": "write_output_integer_reg(0, 1)",
    "done signal": "write_output_integer_reg(0, 2)",
    "async progress register": "write_output_integer_reg(2, reg_value)",
    "move path hook": "def exec_move_path():",
}

#: Where the pinned script reads the arguments the fake interprets (float register numbers).
ARGUMENT_MARKERS: dict[str, str] = {
    "servoJ time": "servo_time = read_input_float_reg(8)",
    "servoJ lookahead": "servo_lookahead_time = read_input_float_reg(9)",
    "servoJ gain": "servo_gain = read_input_float_reg(10)",
    "speedJ acceleration": "speed_acceleration = read_input_float_reg(6)",
    "stop deceleration": "deceleration_rate = read_input_float_reg(0)",
    "async stop type": "stop_type = 1",
}

#: Commands (input int register 0) of the pinned script that the fake emulates.
CMD_MOVEJ = 1
CMD_MOVEJ_IK = 2
CMD_MOVEL = 3
CMD_MOVEL_FK = 4
CMD_SPEEDJ = 9
CMD_SERVOJ = 11
CMD_SPEED_STOP = 15
CMD_SERVO_STOP = 16
CMD_SET_PAYLOAD = 17
CMD_SET_TCP = 29
CMD_GET_INVERSE_KIN_ARGS = 30
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_SET_WATCHDOG = 35
CMD_GET_TCP_OFFSET = 40
CMD_GET_FORWARD_KIN_DEFAULT = 43
CMD_GET_FORWARD_KIN_ARGS = 44
CMD_MOVE_PATH = 45
CMD_GET_INVERSE_KIN_DEFAULT = 46
CMD_SET_TARGET_PAYLOAD = 65
CMD_STOP_SCRIPT = 255

#: Commands the script handles "in real time": processed and answered with ready (1) at once,
#: never with done (2). Read off the main loop of the pinned script.
REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})

#: Every command id the fake gives a meaning to (a renumbering in the client breaks the fake).
EMULATED_COMMANDS = frozenset(
    {
        CMD_MOVEJ,
        CMD_MOVEJ_IK,
        CMD_MOVEL,
        CMD_MOVEL_FK,
        CMD_SPEEDJ,
        CMD_SERVOJ,
        CMD_SPEED_STOP,
        CMD_SERVO_STOP,
        CMD_SET_PAYLOAD,
        CMD_SET_TCP,
        CMD_GET_INVERSE_KIN_ARGS,
        CMD_PROTECTIVE_STOP,
        CMD_STOPL,
        CMD_STOPJ,
        CMD_SET_WATCHDOG,
        CMD_GET_TCP_OFFSET,
        CMD_GET_FORWARD_KIN_DEFAULT,
        CMD_GET_FORWARD_KIN_ARGS,
        CMD_MOVE_PATH,
        CMD_GET_INVERSE_KIN_DEFAULT,
        CMD_SET_TARGET_PAYLOAD,
        CMD_STOP_SCRIPT,
    }
)

#: What the branch of a command must contain (its URScript call and where it reads its
#: arguments), for the commands whose meaning the fake takes from the branch rather than
#: from the id alone: a client upgrade that renumbers them moves these lines to another
#: branch, which :func:`protocol_differences` reports. Read off the pinned script.
BRANCH_MARKERS: dict[int, tuple[str, ...]] = {
    CMD_SET_PAYLOAD: (
        "set_payload(mass, cog)",
        "mass = read_input_float_reg(0)",
        "cog_x = read_input_float_reg(1)",
        "cog_z = read_input_float_reg(3)",
        "set_payload(mass, get_target_payload_cog())",
    ),
    CMD_SET_TCP: ("pose = pose_from_input_float_registers(0)", "set_tcp(pose)"),
    CMD_GET_TCP_OFFSET: ("get_tcp_offset()", "pose_to_output_float_registers(0, tcp_offset)"),
    CMD_GET_FORWARD_KIN_DEFAULT: ("get_forward_kin()",),
    CMD_GET_FORWARD_KIN_ARGS: (
        "q = q_from_input_float_registers(0)",
        "tcp_offset = pose_from_input_float_registers(6)",
        "get_forward_kin(q, tcp_offset)",
    ),
    CMD_GET_INVERSE_KIN_DEFAULT: ("x = pose_from_input_float_registers(0)", "get_inverse_kin(x)"),
    CMD_GET_INVERSE_KIN_ARGS: (
        "qnear = q_from_input_float_registers(6)",
        "get_inverse_kin(x, qnear, maxPositionError, maxOrientationError)",
    ),
    # The controller's own RTDE watchdog on the command register; it stops the program.
    CMD_SET_WATCHDOG: (
        "watchdog_min_frequency = read_input_float_reg(0)",
        'rtde_set_watchdog("input_int_register_0", watchdog_min_frequency, "stop")',
        'rtde_set_watchdog("input_int_register_24", watchdog_min_frequency, "stop")',
    ),
    CMD_SET_TARGET_PAYLOAD: (
        "mass = read_input_float_reg(0)",
        "inertia[0] = read_input_float_reg(4)",
        "inertia[5] = read_input_float_reg(9)",
        "set_target_payload(mass, cog, inertia)",
    ),
}

_DEF = re.compile(r"^def\s+(\w+)\s*\(\s*\)\s*:", re.MULTILINE)
_OFFSET = {
    kind: re.compile(rf"global\s+reg_offset_{kind}\s*=[^\n]*?(?:#[^\n]*)?\n?\s*(\d+)")
    for kind in ("int", "float")
}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_MOVE = re.compile(
    rf"^\s*(movej|movel|movep)\(\s*(p?)\[([^\]]*)\]((?:\s*,\s*\w+\s*=\s*{_NUMBER})*)\s*\)",
    re.MULTILINE,
)
_KEYWORD = re.compile(rf"(\w+)\s*=\s*({_NUMBER})")
#: Any motion call in the injected path, parsed or not (what must not be dropped silently).
_ANY_MOTION = re.compile(r"^[ \t]*((?:move|servo|speed)\w*)\s*\(", re.MULTILINE)
_REALTIME_LINE = re.compile(
    r"^\s*if\s+(cmd\s*==\s*\d+(?:\s+or\s+cmd\s*==\s*\d+)+)\s*:", re.MULTILINE
)


@dataclass(frozen=True)
class PathMove:
    """One move of a movePath, as injected into the script.

    Attributes
    ----------
    kind : {"movej", "movel", "movep"}
    target : ndarray of shape (6,)
        Joint angles (rad) or, with ``is_pose``, a pose x, y, z (m), rotation vector (rad).
    is_pose : bool
    speed, acceleration : float
        ``v`` and ``a`` (rad/s, rad/s^2 for joint moves; m/s, m/s^2 for linear ones).
    blend_m : float
        ``r``, the blend radius.
    """

    kind: str
    target: np.ndarray
    is_pose: bool
    speed: float
    acceleration: float
    blend_m: float


@dataclass(frozen=True)
class ScriptInfo:
    """An uploaded program as the fake sees it.

    Attributes
    ----------
    name : str
        The program's ``def`` name.
    is_rtde_control : bool
        It is ur_rtde's control script (all :data:`REQUIRED_MARKERS` present).
    int_offset, float_offset : int
        Register offset the script declares (0, or 24 for the upper range).
    path : tuple of PathMove
        Moves injected for movePath (empty when none).
    path_error : str or None
        Why the injected path cannot be run (a move the fake cannot parse), if so.
    """

    name: str
    is_rtde_control: bool
    int_offset: int = 0
    float_offset: int = 0
    path: tuple[PathMove, ...] = field(default_factory=tuple)
    path_error: str | None = None


def program_complete(text: str) -> bool:
    """Whether ``text`` holds a whole program: a ``def`` line and a closing ``end`` line at
    column 0 (how the controller delimits a program sent to the script port)."""
    return _DEF.search(text) is not None and re.search(r"^end\s*$", text, re.MULTILINE) is not None


def missing_markers(text: str) -> list[str]:
    """Names of the :data:`REQUIRED_MARKERS` that ``text`` lacks."""
    return [name for name, marker in REQUIRED_MARKERS.items() if marker not in text]


def realtime_commands(text: str) -> frozenset[int] | None:
    """The command ids on the script's real-time ``if cmd == .. or ..:`` line (None if absent)."""
    match = _REALTIME_LINE.search(text)
    if match is None:
        return None
    return frozenset(int(v) for v in re.findall(r"\d+", match.group(1)))


def command_branch(text: str, cmd: int) -> str | None:
    """The body of the script's ``cmd == <cmd>:`` branch, up to the next ``cmd == ..``
    branch (None if it has none)."""
    match = re.search(rf"\bcmd\s*==\s*{cmd}\s*:", text)
    if match is None:
        return None
    following = re.compile(r"^\s*(?:el)?if\s+cmd\s*==\s*\d+\s*:", re.MULTILINE)
    end = following.search(text, match.end())
    return text[match.end() : end.start() if end else len(text)]


def protocol_differences(text: str) -> list[str]:
    """Everything in ``text`` that differs from the protocol the fake emulates: missing
    :data:`REQUIRED_MARKERS` and :data:`ARGUMENT_MARKERS`, a missing ``cmd == <id>:`` branch
    for an id of :data:`EMULATED_COMMANDS`, a branch without its :data:`BRANCH_MARKERS`, a
    different real-time command list."""
    differences = missing_markers(text)
    differences += [name for name, marker in ARGUMENT_MARKERS.items() if marker not in text]
    for cmd in sorted(EMULATED_COMMANDS):
        branch = command_branch(text, cmd)
        if branch is None:
            differences.append(f"command {cmd} branch")
            continue
        for marker in BRANCH_MARKERS.get(cmd, ()):
            if marker not in branch:
                differences.append(f"command {cmd} branch lacks {marker!r}")
    if realtime_commands(text) != REALTIME_COMMANDS:
        differences.append(f"real-time command list (got {sorted(realtime_commands(text) or ())})")
    return differences


def register_offset(text: str, kind: str = "int") -> int:
    """The register offset the script assigns to ``reg_offset_<kind>``.

    Raises
    ------
    ValueError
        The script does not declare it.
    """
    match = _OFFSET[kind].search(text)
    if match is None:
        raise ValueError(f"the script declares no reg_offset_{kind}")
    return int(match.group(1))


def parse_move_path(text: str) -> tuple[PathMove, ...]:
    """The moves injected into ``exec_move_path()`` (empty if there are none).

    Raises
    ------
    ValueError
        A motion call in the path that the fake cannot parse (e.g. ``movec``, or a target
        without 6 values): running the rest would report a path it did not run.
    """
    start = text.find("def exec_move_path():")
    if start < 0:
        return ()
    end = re.compile(r"^\s*end\s*$", re.MULTILINE).search(text, start)
    body = text[start : end.start() if end else len(text)]
    parsed = {m.start(1) for m in _MOVE.finditer(body)}
    for call in _ANY_MOTION.finditer(body):
        if call.start(1) not in parsed:
            line = body[call.start(1) :].splitlines()[0]
            raise ValueError(f"the movePath has a move the fake cannot run: {line[:120]}")
    moves = []
    for match in _MOVE.finditer(body):
        kind, pose_flag, values, keywords = match.groups()
        target = np.array([float(v) for v in values.split(",")], dtype=np.float64)
        if target.shape != (6,):
            raise ValueError(f"a {kind} in the movePath has {target.size} values, not 6")
        options = {k: float(v) for k, v in _KEYWORD.findall(keywords)}
        moves.append(
            PathMove(
                kind=kind,
                target=target,
                is_pose=bool(pose_flag),
                # URScript's defaults when v / a are left out.
                speed=options.get("v", 1.05 if kind == "movej" else 0.25),
                acceleration=options.get("a", 1.4 if kind == "movej" else 1.2),
                blend_m=options.get("r", 0.0),
            )
        )
    return tuple(moves)


def inspect(text: str) -> ScriptInfo:
    """Recognise an uploaded program."""
    match = _DEF.search(text)
    name = match.group(1) if match else ""
    if missing_markers(text):
        return ScriptInfo(name=name, is_rtde_control=False)
    try:
        path, path_error = parse_move_path(text), None
    except ValueError as exc:  # refused when the path is run, as a script error stops it
        path, path_error = (), str(exc)
    return ScriptInfo(
        name=name,
        is_rtde_control=True,
        int_offset=register_offset(text, "int"),
        float_offset=register_offset(text, "float"),
        path=path,
        path_error=path_error,
    )
