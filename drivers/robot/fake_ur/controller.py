"""The emulated arm and the emulated ur_rtde control script, advanced one control period a tick.

The joints are integrated by the ``sim`` backend's model (:class:`~drivers.robot.sim.SimBackend`:
servoJ lookahead buffer, critically damped tracking with feed-forward, joint speed limits, a
joint limit is a protective stop), so the fake moves like the simulated arm teachpath already
checks its plans against. Every move is a stream of joint targets fed to that model once per
control period: moveJ a synchronised trapezoid, moveL a Cartesian line solved by the arm's IK,
movePath the sim's blended path, servoJ the client's latest target, a stop no target (brake).

Programs that are not ur_rtde's control script are compiled and run by :mod:`.urscript` (its
:class:`~.urscript.Runner` is stepped by the same tick), on the same motion machinery.

The active TCP (``set_tcp`` / ur_rtde's setTcp) and payload (``set_payload`` / setPayload) are
kept: every pose the controller reports or takes -- actual / target TCP pose, forward and
inverse kinematics, moveL and movel lines, tool speed for stopl -- is the TCP's, as on a real
controller. The payload is stored and reported only (no dynamics are modelled). Both persist
until changed or the fake is reset, across program stops and uploads.

The script emulation mirrors the main loop of the pinned client's control script
(:mod:`.control_script`): read the command register, answer ready (1) / done (2), write results
and async progress registers. A command that fails the way a URScript runtime error would (no IK
solution, speed or acceleration <= 0, a path the fake cannot run) stops the program with a
logged message, so ur_rtde returns False / raises as it would against a real controller; it
never answers "done" for work it did not do. Everything here runs under
:attr:`FakeController.lock`.

Stops brake at the requested deceleration, as the pinned script does inside the command (so
"done" comes once the arm rests): servoStop runs ``stopl(a)``, speedStop ``stopj(a)``; stopJ /
stopL run ``stopj`` synchronously and ``stopl`` asynchronously -- the script picks the kind from
a global that only an async stop sets, and the fake follows it. servoJ's ``t`` is honoured (the
target is sampled every ``t`` and approached linearly over it), speedJ's acceleration too.

Not emulated:

- moveL / movePath pose moves ignore orientation speed (a pure rotation turns at once) and a
  movePath pose move runs as a joint move to its IK solution (no straight line, no ``movep``
  constant tool speed);
- speedJ's ``t``: the pinned script re-issues speedj in a loop, so it has no visible effect
  there either; speedL, servoC, force mode, contact detection, jogging, teach mode and I/O
  commands: acknowledged without effect; the payload has no effect on the motion;
- joint currents and temperatures, collision detection; speed scaling comes from the speed
  slider only (RTDE's ``speed_slider_fraction``, ur_rtde's setSpeedSlider), never from the
  controller slowing a move near a limit.

The speed slider scales the moves the controller times (moveJ, moveL, movePath and a program's
moves) as UR's does: the motion goes on along the same targets at the scaled speed, its scaling
ramping to the slider's value within :data:`SLIDER_RAMP_S`; at 0 the arm comes to rest on its
way and waits. servoJ follows the client's targets whatever the slider says.
"""

from __future__ import annotations

import bisect
import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation, Slerp

from drivers.errors import ProtectiveStopError
from drivers.robot.fake_ur import control_script as cs
from drivers.robot.fake_ur import urscript
from drivers.robot.fake_ur.rtde_protocol import REGISTER_COUNT
from drivers.robot.sim import (
    HOME_RAD,
    SimBackend,
    SimConfig,
    _path_samples,
    trapezoid_fractions,
)
from recon import kinematics
from recon.transforms import invert_transform, pose_from_transform, transform_from_pose
from recon.waypoints import CoarsePath

log = logging.getLogger("fake_ur.controller")

#: From a program's arrival to its command loop's first pass (s): a real controller compiles and
#: starts a program in far longer; this only has to outlast the client's clearing of the
#: command register, sent on another socket while it uploads.
PROGRAM_START_S = 0.02

#: RTDE robot_mode values.
ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
ROBOT_MODE_NAMES = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 7: "RUNNING"}
#: RTDE safety_mode values.
SAFETY_NORMAL = 1
SAFETY_PROTECTIVE_STOP = 3
SAFETY_SYSTEM_EMERGENCY_STOP = 6
SAFETY_ROBOT_EMERGENCY_STOP = 7
SAFETY_NAMES = {
    1: "NORMAL",
    3: "PROTECTIVE_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
}
EMERGENCY_STOPS = (SAFETY_SYSTEM_EMERGENCY_STOP, SAFETY_ROBOT_EMERGENCY_STOP)
#: RTDE runtime_state values.
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2
#: robot_status_bits: power on, program running.
STATUS_POWER_ON = 1 << 0
STATUS_PROGRAM_RUNNING = 1 << 1
#: safety_status_bits (UR's RTDE guide).
SAFETY_BIT_NORMAL = 1 << 0
SAFETY_BIT_PROTECTIVE_STOPPED = 1 << 2
SAFETY_BIT_SYSTEM_EMERGENCY_STOPPED = 1 << 5
SAFETY_BIT_ROBOT_EMERGENCY_STOPPED = 1 << 6
SAFETY_BIT_EMERGENCY_STOPPED = 1 << 7
#: A move counts as settled when no joint moves faster than this (same as the sim backend).
SETTLED_RAD_S = 1e-4
#: Settling after the last target of a move is bounded by this (s), as in the sim backend.
SETTLE_MAX_S = 0.5
#: A protective stop cannot be unlocked sooner than this after it happened (s), as on UR's
#: controllers (PolyScope enforces it for the dashboard server too).
UNLOCK_WAIT_S = 5.0
#: moveL solves IK for this many line points at once: one call costs about as much as one
#: point, and solving them one chunk per tick keeps the control tick short.
IK_CHUNK = 16
#: The speed scaling follows the speed slider at most this fast: from 100 % to 0 (or back) in
#: this long (s), so a change never jumps the arm's speed.
SLIDER_RAMP_S = 0.4
#: The motions whose timing is the controller's: the speed slider scales them (a servo target
#: is the client's, a brake is a stop).
SCALED_MOTIONS = ("move", "path")
#: Bounds on the logs kept for tests and status (entries).
COMMAND_LOG_MAX = 1000
MESSAGES_MAX = 200
#: A program's recorded trace (joints and TCP each control period) keeps this many samples at
#: most (10 min at 500 Hz, ~30 MB); older ones are dropped and counted.
TRACE_MAX = 300_000
TRACE_BLOCK = 5_000
#: After a program ends the trace goes on while the arm still moves (a stop's braking), this
#: long at most (s).
TRACE_TAIL_S = 2.0

ScriptRuntimeError = urscript.ScriptRuntimeError


class Trace:
    """Controller time, actual joints, actual TCP pose and the program line executing, one
    row a control period, in blocks so that a long program neither reallocates nor grows
    without bound."""

    def __init__(self, max_samples: int = TRACE_MAX) -> None:
        self.max_samples = max_samples
        self.blocks: deque[np.ndarray] = deque()
        self.fill = TRACE_BLOCK  # rows used in the last block
        self.dropped = 0

    def __len__(self) -> int:
        return max(0, len(self.blocks) * TRACE_BLOCK - (TRACE_BLOCK - self.fill))

    def append(self, t_s: float, q: ArrayLike, pose: ArrayLike, line: int = 0) -> None:
        if self.fill == TRACE_BLOCK:
            self.blocks.append(np.empty((TRACE_BLOCK, 14)))
            self.fill = 0
            while len(self.blocks) * TRACE_BLOCK > self.max_samples and len(self.blocks) > 1:
                self.blocks.popleft()
                self.dropped += TRACE_BLOCK
        row = self.blocks[-1][self.fill]
        row[0] = t_s
        row[1:7] = q
        row[7:13] = pose
        row[13] = line
        self.fill += 1

    def rows(self, start: int = 0, stop: int | None = None, every: int = 1) -> np.ndarray:
        """Samples ``start`` .. ``stop`` (indices counted from the program's start, dropped ones
        included), every ``every``-th, shape (K, 14): t, q0..q5, x, y, z, rx, ry, rz, line
        (of a standalone program; 0 for none)."""
        size = len(self)
        first = max(start - self.dropped, 0)
        last = size if stop is None else max(min(stop - self.dropped, size), first)
        if first >= last:
            return np.empty((0, 14))
        # Only the blocks asked for are copied: this runs under the controller's lock.
        blocks = list(self.blocks)[first // TRACE_BLOCK : (last - 1) // TRACE_BLOCK + 1]
        offset = (first // TRACE_BLOCK) * TRACE_BLOCK
        data = np.concatenate(blocks)
        return data[first - offset : last - offset : every]


@dataclass
class _Motion:
    """Joint targets fed to the physics one per tick (None: brake), and how the move ends."""

    name: str
    targets: Iterator[np.ndarray | None]
    sync: bool = False  # the command answers "done" only when the motion ends
    is_async: bool = False  # report async progress (start, per path move, finished)
    # Ticks at which path moves 1 .. n-1 start (ascending), for async progress.
    waypoint_ticks: tuple[int, ...] = ()
    # Braking at a set rate (rad/s^2 per joint, shape (6,)) instead of following targets.
    deceleration: np.ndarray | None = None
    started_s: float = 0.0
    expected_s: float = 0.0
    tick: int = 0
    settling: int = 0
    last: np.ndarray | None = None  # last target fed: a move settles on it
    reported: int = 0  # last async progress written (0: started)
    # Speed-scaled playback of the targets (controller-timed moves): how far along them (in
    # targets), the two around that point, and whether the iterator ran out.
    cursor: float = 0.0
    around: tuple[np.ndarray, np.ndarray] | None = None
    pulled: int = 0
    exhausted: bool = False


class FakeController:
    """A UR controller's state: arm, safety, program, registers.

    Parameters
    ----------
    robot : str
        UR model (``recon.kinematics.model`` name); sets the kinematics and the control rate
        (500 Hz e-series, 125 Hz CB3).
    q_start_rad : sequence of 6 floats, optional
    powered : bool
        Start powered on with brakes released (robot mode RUNNING) rather than POWER_OFF.
    program_start_s : float
        From a program's arrival to its command loop's first pass (see
        :data:`PROGRAM_START_S`, what the served fake uses); 0 for tests that step it directly.
    """

    def __init__(
        self,
        robot: str = "ur5e",
        *,
        q_start_rad: Iterable[float] = HOME_RAD,
        powered: bool = True,
        program_start_s: float = 0.0,
    ) -> None:
        self.program_start_s = program_start_s
        self.arm = kinematics.model(robot)
        self.rate_hz = float(self.arm.control_rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.lock = threading.RLock()
        self.q_start_rad = tuple(float(v) for v in q_start_rad)
        self.in_int = [0] * REGISTER_COUNT
        self.in_double = [0.0] * REGISTER_COUNT
        self.out_int = [0] * REGISTER_COUNT
        self.out_double = [0.0] * REGISTER_COUNT
        self.t_s = 0.0  # controller time since start
        self._loop_starts_s = 0.0  # when the loaded program's command loop begins
        # The RTDE watchdog the control script sets (rtde_set_watchdog, action "stop"): the
        # program stops when the command register goes un-updated longer than this.
        self.watchdog_period_s: float | None = None
        self._register_seen_s = 0.0  # when a data package last wrote the command register
        self.robot_mode = ROBOT_MODE_RUNNING if powered else ROBOT_MODE_POWER_OFF
        self.safety_mode = SAFETY_NORMAL
        self.runtime_state = RUNTIME_STOPPED
        self.program_name = "<none>"
        self.script: cs.ScriptInfo | None = None
        self.remote_control = True
        self.frozen = False  # "stops answering": no data, no replies
        # Text the script would have printed (textmsg) and runtime errors.
        self.messages: deque[str] = deque(maxlen=MESSAGES_MAX)
        # (time, command) for tests and logs.
        self.command_log: deque[tuple[float, int]] = deque(maxlen=COMMAND_LOG_MAX)
        self.unlock_wait_s = UNLOCK_WAIT_S
        self.protective_stop_s = 0.0  # controller time of the last protective stop
        # The speed slider (RTDE speed_slider_fraction, 0..1) and the scaling the timed moves
        # run at now, following it (see SLIDER_RAMP_S).
        self.speed_slider = 1.0
        self.speed_scaling = 1.0
        # RTDE input fields and the connection that set them up (one writer per field).
        self.input_owners: dict[str, object] = {}
        # A standalone URScript program and what became of the last program of either kind.
        self.runner: urscript.Runner | None = None
        self.run: urscript.RunState | None = None
        self.programs_received = 0  # numbers the runs, see _new_run
        self.trace = Trace()
        self._trace_until: float | None = None  # recording ends then (None: while running)
        self._pose_cache: tuple[bytes, list[float]] = (b"", [])
        self.reset_tool()
        self.reset_arm()

    def reset_tool(self) -> None:
        """No TCP offset (the flange) and no payload, as after a reset."""
        with self.lock:
            self.tcp_offset = np.zeros(6)  # flange -> TCP, pose (m, rotation vector)
            self.payload_kg = 0.0
            self.payload_cog_m = np.zeros(3)
            self.payload_inertia = np.zeros(6)  # Ixx, Iyy, Izz, Ixy, Ixz, Iyz (kg m^2)

    def clear_registers(self) -> None:
        """Zero the general purpose registers (commands, arguments, results)."""
        with self.lock:
            for ints in (self.in_int, self.out_int):
                ints[:] = [0] * REGISTER_COUNT
            for doubles in (self.in_double, self.out_double):
                doubles[:] = [0.0] * REGISTER_COUNT

    # -- arm ---------------------------------------------------------------------------------------

    def reset_arm(self, q_rad: Iterable[float] | None = None) -> None:
        """Put the arm at rest at ``q_rad`` (default: the start pose) with no motion."""
        with self.lock:
            q = self.q_start_rad if q_rad is None else tuple(float(v) for v in q_rad)
            self.sim = SimBackend(SimConfig(robot=self.arm.name, q_start_rad=q))
            self.sim._t = self.t_s  # the physics runs on this controller's clock
            self.motion: _Motion | None = None
            self.servo_target: np.ndarray | None = None
            self.servo_time_s = self.dt_s
            self.speed_qd = np.zeros(6)
            self.speed_acceleration = 0.5
            self._stop_type_l = False  # the script's stop_type: set by an async stop
            self._executing = False
            self._waiting_sync: _Motion | None = None
            self._async_wr_count = 0
            self._async_op_id = 0

    @property
    def q(self) -> np.ndarray:
        return self.sim._q

    @property
    def qd(self) -> np.ndarray:
        return self.sim._qd

    def tcp_pose(self, q: ArrayLike | None = None, tcp: ArrayLike | None = None) -> list[float]:
        """The TCP pose at ``q`` (default: now) with ``tcp`` (default: the active TCP)."""
        if q is None and tcp is None:
            # Asked several times a period (stream, trace, status): computed once per state.
            key = self.q.tobytes() + self.tcp_offset.tobytes()
            if self._pose_cache[0] != key:
                self._pose_cache = (key, self._tcp_pose(self.q, self.tcp_offset))
            return list(self._pose_cache[1])
        offset = self.tcp_offset if tcp is None else np.asarray(tcp, dtype=np.float64)
        return self._tcp_pose(self.q if q is None else np.asarray(q), offset)

    def _tcp_pose(self, q: np.ndarray, offset: np.ndarray) -> list[float]:
        T = kinematics.forward(self.arm, q)
        if np.any(offset):
            T = T @ transform_from_pose(offset)
        pose: list[float] = pose_from_transform(T).tolist()
        return pose

    @property
    def protective_stopped(self) -> bool:
        return self.safety_mode == SAFETY_PROTECTIVE_STOP

    @property
    def emergency_stopped(self) -> bool:
        return self.safety_mode in EMERGENCY_STOPS

    @property
    def can_move(self) -> bool:
        return self.safety_mode == SAFETY_NORMAL and self.robot_mode == ROBOT_MODE_RUNNING

    # -- RTDE outputs --------------------------------------------------------------------------

    def outputs(self) -> dict[str, object]:
        """Current values of the output fields the fake fills (others read as zeros)."""
        q = [float(v) for v in self.q]
        qd = [float(v) for v in self.qd]
        pose = self.tcp_pose()
        status = (STATUS_POWER_ON if self.robot_mode >= 4 else 0) | (
            STATUS_PROGRAM_RUNNING if self.runtime_state == RUNTIME_PLAYING else 0
        )
        safety_bits = {
            SAFETY_NORMAL: SAFETY_BIT_NORMAL,
            SAFETY_PROTECTIVE_STOP: SAFETY_BIT_PROTECTIVE_STOPPED,
            SAFETY_SYSTEM_EMERGENCY_STOP: SAFETY_BIT_SYSTEM_EMERGENCY_STOPPED
            | SAFETY_BIT_EMERGENCY_STOPPED,
            SAFETY_ROBOT_EMERGENCY_STOP: SAFETY_BIT_ROBOT_EMERGENCY_STOPPED
            | SAFETY_BIT_EMERGENCY_STOPPED,
        }[self.safety_mode]
        values: dict[str, object] = {
            "timestamp": self.t_s,
            "target_q": q,
            "target_qd": qd,
            "actual_q": q,
            "actual_qd": qd,
            "actual_TCP_pose": pose,
            "target_TCP_pose": pose,
            "robot_mode": self.robot_mode,
            "joint_mode": [253 if self.robot_mode == ROBOT_MODE_RUNNING else 236] * 6,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "speed_scaling": self.speed_scaling,
            "target_speed_fraction": self.speed_slider,
            "runtime_state": self.runtime_state,
            "robot_status_bits": status,
            "safety_status_bits": safety_bits,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0 if self.robot_mode >= 4 else 0.0,
            "joint_temperatures": [30.0] * 6,
            "actual_execution_time": 0.1,
            "payload": self.payload_kg,
            "payload_cog": [float(v) for v in self.payload_cog_m],
            "payload_inertia": [float(v) for v in self.payload_inertia],
            "script_control_line": self._control_line(),
        }
        for i in range(REGISTER_COUNT):
            values[f"output_int_register_{i}"] = self.out_int[i]
            values[f"output_double_register_{i}"] = self.out_double[i]
            values[f"input_int_register_{i}"] = self.in_int[i]
            values[f"input_double_register_{i}"] = self.in_double[i]
        return values

    def apply_inputs(self, values: dict[str, object]) -> None:
        """Input fields of a data package from a client (registers; the rest is ignored). A
        package that writes the command register feeds the RTDE watchdog, whatever it holds."""
        if f"input_int_register_{self._i(0)}" in values:
            self._register_seen_s = self.t_s
        if values.get("speed_slider_mask") == 1 and "speed_slider_fraction" in values:
            fraction = float(values["speed_slider_fraction"])  # type: ignore[arg-type]
            if np.isfinite(fraction):  # UR takes 0..1; outside, the nearest end
                self.speed_slider = min(max(fraction, 0.0), 1.0)
        for name, value in values.items():
            if name.startswith("input_int_register_"):
                self.in_int[int(name.rsplit("_", 1)[1])] = int(value)  # type: ignore[call-overload]
            elif name.startswith("input_double_register_"):
                self.in_double[int(name.rsplit("_", 1)[1])] = float(value)  # type: ignore[arg-type]

    # -- program -------------------------------------------------------------------------------

    def load_program(self, text: str) -> bool:
        """A program arrived on a script port: stop the running one and start it.

        ur_rtde's control script is emulated by its register protocol; any other program is
        compiled by :mod:`.urscript` (outside the lock: a long program takes a while) and run
        by the tick. Returns False when the program does not start: the controller refuses
        programs (frozen, local control, not running, a safety stop) or it does not compile.
        """
        info = cs.inspect(text)
        program: urscript.Program | None = None
        compile_error: urscript.CompileError | None = None
        if not info.is_rtde_control:
            try:
                program = urscript.compile_program(text)
            except urscript.CompileError as error:
                compile_error = error
        with self.lock:
            if self.frozen:  # a controller that stopped answering starts nothing either
                log.warning("frozen: program %s not started", info.name)
                return False
            name = info.name or (program.name if program else "") or "<unnamed>"
            if not self.remote_control:
                # In local control the controller takes no programs from the script ports.
                self._refused(name, "the controller is in local control")
                return False
            self.stop_program("replaced by a new program")
            if not self.can_move:
                log.warning("refusing to start %s: the arm is not ready to run programs", name)
                self._refused(name, "the arm is not ready to run programs (safety stop or off)")
                return False
            self.script = info
            self.program_name = name
            self.runner = None
            self.run = self._new_run()
            if compile_error is not None:
                message = f"Compile error: {compile_error}"
                log.warning("program %s not started: %s", name, message)
                self.messages.append(message)
                self.run.state, self.run.line = "error", compile_error.line
                self.run.message, self.run.ended_s = compile_error.message, self.t_s
                return False
            self.trace = Trace()
            self._trace_until = None
            if program is not None:
                self.runner = urscript.Runner(program, self, status=self.run)
                self.runtime_state = RUNTIME_PLAYING
                log.info(
                    "running URScript program %s (%d statements)", name, len(program.statements)
                )
                return True
            self.runtime_state = RUNTIME_PLAYING
            # A controller takes a while to compile and start a program; ur_rtde clears its
            # command register while it uploads one, and that must land before the new loop
            # reads it, as it does on a real controller (else a stale command runs again).
            self._loop_starts_s = self.t_s + self.program_start_s
            self._executing = False
            self.watchdog_period_s = None  # a watchdog belongs to the program that set it
            self._waiting_sync = None
            self._stop_type_l = False
            self._write_async_progress(-1)  # reset_async_progress()
            self.out_int[self._i(0)] = 1  # signal_ready()
            self.messages.append("RTDE Control Script Loaded")
            log.info(
                "running ur_rtde control script (register offset %d, %d path moves)",
                info.int_offset,
                len(info.path),
            )
            return True

    def _refused(self, name: str, reason: str) -> None:
        log.warning("program %s refused: %s", name, reason)
        self.run = self._new_run(state="refused", message=reason, ended_s=self.t_s)

    def _new_run(self, **fields: Any) -> urscript.RunState:
        """The state of the next program, numbered: the controller clock moves in whole
        periods, so two programs (a refused one and the next) can share a start time."""
        self.programs_received += 1
        return urscript.RunState(number=self.programs_received, started_s=self.t_s, **fields)

    def restart_program(self) -> bool:
        """The dashboard's ``play``: run the last standalone program again from its start, or
        resume ur_rtde's control script loop. False if there is none or the arm cannot move."""
        with self.lock:
            if self.script is None or not self.can_move or not self.remote_control:
                return False
            if self.script.is_rtde_control:
                self.runtime_state = RUNTIME_PLAYING
                return True
            program = self.runner.program if self.runner is not None else None
            if program is None:
                return False
            self.stop_program("restarted")
            self.run = self._new_run()
            self.runner = urscript.Runner(program, self, status=self.run)
            self.trace = Trace()
            self._trace_until = None
            self.runtime_state = RUNTIME_PLAYING
            return True

    def stop_program(self, reason: str = "stopped") -> None:
        """Stop the running program (the arm brakes); ``reason`` is what ``program_status``
        reports for a program stopped while running."""
        with self.lock:
            if self.runtime_state == RUNTIME_PLAYING:
                log.info("program %s stopped (%s)", self.program_name, reason)
                if self.run is not None and self.run.state == "running":
                    self.run.state, self.run.message = "stopped", reason
                    self.run.line = self._control_line() or None
                    self.run.ended_s = self.t_s
                self._trace_until = self.t_s + TRACE_TAIL_S
            self.runtime_state = RUNTIME_STOPPED
            self._waiting_sync = None
            if self.motion is not None:
                self.motion = _Motion("brake", iter(()))
            self.servo_target = None

    def runtime_error(self, message: str, line: int | None = None) -> None:
        """Stop the program as a URScript runtime error does (the arm brakes)."""
        with self.lock:
            if self.run is not None and self.run.state == "running":
                line = line if line is not None else (self._control_line() or None)
                self.run.state, self.run.message, self.run.line = "error", message, line
                self.run.ended_s = self.t_s
            if self.runner is not None and line is not None:
                message = f"line {line}: {message}"
            log.warning("runtime error, program stopped: %s", message)
            self.messages.append(message)
            self.stop_program("runtime error")

    def _control_line(self) -> int:
        """The line the standalone program executes (0 when none runs)."""
        if self.runner is None or self.runtime_state != RUNTIME_PLAYING:
            return 0
        return self.runner.current_line() or 0

    def _i(self, index: int) -> int:
        return index + (self.script.int_offset if self.script else 0)

    def _f(self, index: int) -> int:
        return index + (self.script.float_offset if self.script else 0)

    def _float_regs(self, first: int, count: int = 6) -> np.ndarray:
        return np.array([self.in_double[self._f(first + k)] for k in range(count)])

    # -- faults --------------------------------------------------------------------------------

    def protective_stop(self, reason: str = "protective stop (injected)") -> None:
        with self.lock:
            log.warning("protective stop: %s", reason)
            self.safety_mode = SAFETY_PROTECTIVE_STOP
            self.protective_stop_s = self.t_s
            self._halt(f"protective stop: {reason}")

    def emergency_stop(self, source: str = "robot") -> None:
        """An emergency stop: ``source`` "robot" (the pendant's button: ROBOT_EMERGENCY_STOP)
        or "system" (an external e-stop input: SYSTEM_EMERGENCY_STOP). The arm powers off."""
        if source not in ("robot", "system"):
            raise ValueError(f"emergency stop source is 'robot' or 'system', not {source!r}")
        with self.lock:
            log.warning("emergency stop (%s)", source)
            self.safety_mode = (
                SAFETY_ROBOT_EMERGENCY_STOP if source == "robot" else SAFETY_SYSTEM_EMERGENCY_STOP
            )
            self.robot_mode = ROBOT_MODE_POWER_OFF
            self._halt(f"{source} emergency stop")

    def release_emergency_stop(self) -> None:
        with self.lock:
            if self.emergency_stopped:
                self.safety_mode = SAFETY_NORMAL  # still powered off: power on, release brakes

    def unlock_too_early(self) -> bool:
        """Whether a protective stop is on and happened less than :attr:`unlock_wait_s` ago."""
        with self.lock:
            return self.protective_stopped and (
                self.t_s - self.protective_stop_s < self.unlock_wait_s
            )

    def unlock_protective_stop(self) -> bool:
        """Clear a protective stop; False if there is none or it is too early to unlock."""
        with self.lock:
            if not self.protective_stopped or self.unlock_too_early():
                return False
            self.safety_mode = SAFETY_NORMAL
            return True

    def _halt(self, reason: str) -> None:
        """The arm stops hard and the program stops, as a safety stop does."""
        self.sim._qd[:] = 0.0
        self.motion = None
        self.servo_target = None
        self.stop_program(reason)

    # -- one control period --------------------------------------------------------------------

    def step(self) -> None:
        """Advance by one control period: the script loop (ur_rtde's or a standalone
        program's), then the physics, then the program's trace."""
        with self.lock:
            self.t_s += self.dt_s
            script = self.script
            playing = self.runtime_state == RUNTIME_PLAYING
            if playing and script and script.is_rtde_control:
                self._script_loop()
                self._rtde_watchdog()
            elif playing and self.runner is not None:
                self._program_step(self.runner)
            self._physics()
            self._record()

    def _program_step(self, runner: urscript.Runner) -> None:
        try:
            runner.step()
        except ScriptRuntimeError as error:
            self.runtime_error(str(error), getattr(error, "line", None) or runner.status.line)
            return
        except Exception:
            # A bug in the fake: stopped like a runtime error, so the program never hangs.
            log.exception("program %s failed inside the fake controller", self.program_name)
            self.runtime_error("internal error of the fake controller", runner.status.line)
            return
        if runner.finished:
            log.info("program %s finished", self.program_name)
            self.messages.append(f"Program {self.program_name} finished")
            self.runtime_state = RUNTIME_STOPPED
            self._trace_until = self.t_s + TRACE_TAIL_S

    def _record(self) -> None:
        if self.run is None or self.script is None:
            return
        if self.runtime_state != RUNTIME_PLAYING:
            if self._trace_until is None or self.t_s > self._trace_until:
                return
            if float(np.abs(self.qd).max()) < SETTLED_RAD_S:
                self._trace_until = None  # at rest after the program: the trace is complete
        self.trace.append(self.t_s, self.q, self.tcp_pose(), self._control_line())

    def _rtde_watchdog(self) -> None:
        """The controller's RTDE watchdog (``rtde_set_watchdog(..., "stop")``): no package on
        the command register for longer than its period stops the program (the arm brakes)."""
        period = self.watchdog_period_s
        if period is None or self.t_s - self._register_seen_s <= period:
            return
        message = (
            f"RTDE watchdog: input_int_register_{self._i(0)} not updated for "
            f"{self.t_s - self._register_seen_s:.3f} s (at least {1 / period:g} Hz expected): "
            "program stopped"
        )
        log.warning(message)
        self.messages.append(message)
        self.watchdog_period_s = None
        self.stop_program("RTDE watchdog")

    def _script_loop(self) -> None:
        """One pass of the control script's main loop."""
        if self._waiting_sync is not None:
            return  # process_cmd is still blocked in a synchronous move
        if self.t_s < self._loop_starts_s:
            return  # the program is still starting
        cmd = self.in_int[self._i(0)]
        try:
            if cmd in cs.REALTIME_COMMANDS:
                self._process(cmd)
                self.out_int[self._i(0)] = 1
            elif cmd == 0:
                self._executing = False
                self.out_int[self._i(0)] = 1
            elif not self._executing:
                self._executing = True
                self.command_log.append((self.t_s, cmd))
                if cmd == cs.CMD_STOP_SCRIPT:
                    self.messages.append("Received stop script!")
                    self.stop_program("stopScript")
                    return
                if not self._process(cmd):
                    self.out_int[self._i(0)] = 2
        except ScriptRuntimeError as error:
            self.runtime_error(str(error))
        except Exception:
            # A bug in the fake: without this the command would stay "executing" and ur_rtde
            # would wait 300 s for it. Stopped like a runtime error, so the client fails fast.
            log.exception("command %d failed inside the fake controller", cmd)
            self.runtime_error(f"command {cmd} failed inside the fake controller")

    def _process(self, cmd: int) -> bool:  # noqa: C901
        """Run one command; True if it answers later (a synchronous move)."""
        if cmd == cs.CMD_SERVOJ:
            self.servo_target = self._float_regs(0)
            # servoj(q, t=...): the controller approaches each target over t (one period or
            # more); the register protocol's servoj thread re-reads the target every t.
            self.servo_time_s = max(float(self.in_double[self._f(8)]), self.dt_s)
            lookahead_s, gain = self.in_double[self._f(9)], self.in_double[self._f(10)]
            if 0.03 <= lookahead_s <= 0.2 and 100 <= gain <= 2000:
                self.sim._delay = max(1, int(round(lookahead_s / self.dt_s)))
                self.sim._omega = float(np.sqrt(gain))
            if self.motion is None or self.motion.name != "servoj":
                self.motion = _Motion("servoj", self._servo_targets())
            return False
        if cmd == cs.CMD_SPEEDJ:
            acceleration = float(self.in_double[self._f(6)])
            if not acceleration > 0:
                raise ScriptRuntimeError(f"speedj: acceleration must be > 0, got {acceleration}")
            self.speed_qd = self._float_regs(0)
            self.speed_acceleration = acceleration
            if self.motion is None or self.motion.name != "speedj":
                self.motion = _Motion("speedj", self._speed_targets())
            return False
        if cmd in (cs.CMD_SERVO_STOP, cs.CMD_SPEED_STOP):
            # The script brakes inside the command: stopl(a) after servoJ, stopj(a) after
            # speedJ; "done" comes when the arm rests.
            self.servo_target = None
            linear = cmd == cs.CMD_SERVO_STOP
            return self._start(self._brake("stop", linear, sync=True, is_async=False))
        if cmd in (cs.CMD_STOPJ, cs.CMD_STOPL):
            self._stop_async_move()
            is_async = self.in_int[self._i(1)] == 1
            if is_async:
                self._stop_type_l = True  # the script's stop_type = 1, kept for later stops
            linear = self._stop_type_l
            return self._start(self._brake("stop", linear, sync=not is_async, is_async=is_async))
        if cmd in (cs.CMD_MOVEJ, cs.CMD_MOVEJ_IK, cs.CMD_MOVEL, cs.CMD_MOVEL_FK):
            return self._move(cmd)
        if cmd == cs.CMD_MOVE_PATH:
            return self._move_path()
        if cmd == cs.CMD_GET_FORWARD_KIN_DEFAULT:  # get_forward_kin(): now, the active TCP
            self._write_pose(self.tcp_pose())
            return False
        if cmd == cs.CMD_GET_FORWARD_KIN_ARGS:
            # get_forward_kin(q, tcp_offset): the script reads the TCP from float registers
            # 6-11 whether or not the client wrote them -- ur_rtde's getForwardKinematics(q)
            # without a TCP sends q only, so a real controller uses whatever the registers
            # held last (a quirk of the client, emulated as such).
            self._write_pose(self.tcp_pose(self._float_regs(0), tcp=self._float_regs(6)))
            return False
        if cmd == cs.CMD_SET_TCP:
            self.set_tcp(self._float_regs(0))
            return False
        if cmd == cs.CMD_GET_TCP_OFFSET:
            self._write_pose(self.tcp_offset)
            return False
        if cmd in (cs.CMD_SET_PAYLOAD, cs.CMD_SET_TARGET_PAYLOAD):
            mass = float(self.in_double[self._f(0)])
            cog = self._float_regs(1, 3)
            inertia = self._float_regs(4, 6) if cmd == cs.CMD_SET_TARGET_PAYLOAD else None
            # The script keeps the current centre of gravity when the client sends zeros.
            self.set_payload(mass, cog if np.any(cog) else None, inertia)
            return False
        if cmd in (cs.CMD_GET_INVERSE_KIN_ARGS, cs.CMD_GET_INVERSE_KIN_DEFAULT):
            near = self._float_regs(6) if cmd == cs.CMD_GET_INVERSE_KIN_ARGS else self.q
            q = self._ik(self._float_regs(0), near)
            if q is None:  # get_inverse_kin raises in URScript: the program stops
                raise ScriptRuntimeError("get_inverse_kin: no inverse kinematics solution")
            for k, v in enumerate(q):
                self.out_double[self._f(k)] = float(v)
            return False
        if cmd == cs.CMD_PROTECTIVE_STOP:
            self.protective_stop("triggered by the client")
            return False
        if cmd == cs.CMD_SET_WATCHDOG:
            frequency_hz = float(self.in_double[self._f(0)])
            if not frequency_hz > 0:
                raise ScriptRuntimeError(
                    f"rtde_set_watchdog: min_frequency must be > 0, got {frequency_hz}"
                )
            self.watchdog_period_s = 1.0 / frequency_hz
            self._register_seen_s = self.t_s
            log.info("RTDE watchdog set: %g Hz", frequency_hz)
            return False
        # Any other command: acknowledged without effect, so the client never hangs on it.
        log.info("command %d is not emulated: acknowledged without effect", cmd)
        return False

    # -- moves ---------------------------------------------------------------------------------

    def _start(self, motion: _Motion) -> bool:
        self.motion = motion
        motion.started_s = self.t_s
        if motion.is_async:
            self._write_async_progress(0)
        if motion.sync:
            self._waiting_sync = motion
        return motion.sync

    def _stop_async_move(self) -> None:
        if self.motion is not None and self.motion.is_async and self.motion.name != "stop":
            self._write_async_progress(-1)
            self.motion = None

    def _write_pose(self, pose: Iterable[float]) -> None:
        for k, v in enumerate(pose):
            self.out_double[self._f(k)] = float(v)

    def _brake(
        self, name: str, linear: bool, *, sync: bool, is_async: bool, rate: float | None = None
    ) -> _Motion:
        """A stop at ``rate`` (default: the deceleration in float register 0): ``stopj(a)``
        (rad/s^2, the fastest joint) or, ``linear``, ``stopl(a)`` (m/s^2 of the TCP). All joints
        slow down in proportion, so the arm stops on the line it was moving along."""
        rate = float(self.in_double[self._f(0)]) if rate is None else float(rate)
        if not rate > 0:
            raise ScriptRuntimeError(f"{'stopl' if linear else 'stopj'}: deceleration must be > 0")
        qd = np.abs(self.qd)
        speed = float(qd.max())
        if linear:
            h = 1e-3  # s: the tool's speed by a finite difference of the forward kinematics
            ahead = np.asarray(self.tcp_pose(self.q + self.qd * h))[:3]
            speed = float(np.linalg.norm(ahead - np.asarray(self.tcp_pose())[:3]) / h)
        t_stop = speed / rate
        deceleration = qd / t_stop if t_stop > 1e-9 else np.full(6, np.inf)
        return _Motion(
            name,
            iter(()),
            sync=sync,
            is_async=is_async,
            deceleration=np.minimum(deceleration, self.sim._acc_max),
            expected_s=t_stop,
        )

    def _move(self, cmd: int) -> bool:
        target = self._float_regs(0)
        speed, acceleration = (float(v) for v in self._float_regs(6, 2))
        is_async = self.in_int[self._i(1)] == 1
        kind = "movej" if cmd in (cs.CMD_MOVEJ, cs.CMD_MOVEJ_IK) else "movel"
        if not (speed > 0 and acceleration > 0):  # also refuses NaN
            raise ScriptRuntimeError(
                f"{kind}: speed and acceleration must be > 0 (v={speed}, a={acceleration})"
            )
        self._stop_async_move()
        q0 = self.q.copy()
        if kind == "movej":
            goal = target if cmd == cs.CMD_MOVEJ else self._ik(target, q0)
            if goal is None:
                raise ScriptRuntimeError("movej: no inverse kinematics solution for the pose")
            fractions = trapezoid_fractions(
                float(np.abs(goal - q0).max()), speed, acceleration, self.dt_s
            )
            targets: Iterator[np.ndarray] = iter(q0 + (goal - q0) * fractions[:, None])
        else:
            pose = np.asarray(self.tcp_pose(target)) if cmd == cs.CMD_MOVEL_FK else target
            if self._ik(pose, q0) is None:
                raise ScriptRuntimeError("movel: no inverse kinematics solution for the pose")
            fractions, targets = self._line_targets(q0, pose, speed, acceleration)
        motion = _Motion(
            "move",
            targets,
            sync=not is_async,
            is_async=is_async,
            expected_s=len(fractions) * self.dt_s,
        )
        return self._start(motion)

    def _move_path(self) -> bool:
        script = self.script
        is_async = self.in_int[self._i(1)] == 1
        if script is not None and script.path_error:
            raise ScriptRuntimeError(script.path_error)
        moves = script.path if script else ()
        self._stop_async_move()
        if not moves:
            log.warning("movePath without injected moves: nothing to run")
            return False
        bad = [m for m in moves if not (m.speed > 0 and m.acceleration > 0)]
        if bad:
            raise ScriptRuntimeError(f"{bad[0].kind}: speed and acceleration must be > 0")
        q = [self.q.copy()]
        for move in moves:
            # teachpath sends joint-space moveJ waypoints; a pose target is solved by IK
            # and run as a joint move (no straight line): documented limitation.
            goal = self._ik(move.target, q[-1]) if move.is_pose else move.target
            if goal is None:
                raise ScriptRuntimeError(f"{move.kind}: no inverse kinematics solution")
            q.append(np.asarray(goal))
        path = CoarsePath(
            sample_index=np.arange(len(q)),
            q_rad=np.array(q),
            speed_rad_s=np.array([moves[0].speed] + [m.speed for m in moves]),
            acceleration_rad_s2=float(min(m.acceleration for m in moves)),
            blend_m=np.array([0.0] + [m.blend_m for m in moves[:-1]] + [0.0]),
            deviation_max_m=0.0,
        )
        targets, s_at, knots = _path_samples(path, self.dt_s)
        # Move k+1 starts at the first target past waypoint k along the path parameter, which
        # only grows: a path that comes back over itself still reports its moves in order.
        starts = np.searchsorted(s_at, knots[1:-1] - 1e-9)
        motion = _Motion(
            "path",
            iter(targets),
            sync=not is_async,
            is_async=is_async,
            waypoint_ticks=tuple(int(t) for t in starts),
            expected_s=len(targets) * self.dt_s,
        )
        return self._start(motion)

    def _servo_targets(self) -> Iterator[np.ndarray | None]:
        """The servoj thread: every ``t`` take the client's latest target and approach it
        linearly over ``t`` (one control period when ``t`` is the period)."""
        previous = None
        while True:
            if self.servo_target is None:
                previous = None
                yield None
                continue
            target = self.servo_target.copy()
            start = self.q.copy() if previous is None else previous
            ticks = max(1, int(round(self.servo_time_s / self.dt_s)))
            for k in range(1, ticks + 1):
                yield start + (target - start) * (k / ticks)
            previous = target

    def _speed_targets(self) -> Iterator[np.ndarray | None]:
        q = self.q.copy()
        qd = self.qd.copy()
        while True:
            step = self.speed_acceleration * self.dt_s
            qd = np.clip(
                qd + np.clip(self.speed_qd - qd, -step, step),
                -self.arm.qd_max_rad_s,
                self.arm.qd_max_rad_s,
            )
            q = q + qd * self.dt_s
            yield q.copy()

    def _ik(
        self, pose: ArrayLike, q_near: ArrayLike, tcp: ArrayLike | None = None
    ) -> np.ndarray | None:
        """The IK solution of a TCP pose (``tcp``, default the active TCP) nearest ``q_near``
        (None if unreachable)."""
        return self._ik_many(np.asarray(pose, dtype=np.float64)[None], q_near, tcp)[0]

    def _ik_many(
        self, poses: np.ndarray, q_near: ArrayLike, tcp: ArrayLike | None = None
    ) -> list[np.ndarray | None]:
        """IK of TCP poses (N, 6) in order, each solution nearest the previous one (the first
        nearest ``q_near``); None where a pose is unreachable."""
        T = transform_from_pose(poses[:, :6])
        offset = self.tcp_offset if tcp is None else np.asarray(tcp, dtype=np.float64)
        if np.any(offset):
            T = T @ invert_transform(transform_from_pose(offset))  # T_base_flange
        solutions = kinematics.inverse(self.arm, T)
        near = np.asarray(q_near, dtype=np.float64)
        out: list[np.ndarray | None] = []
        for valid, candidates in zip(solutions.valid, solutions.q_rad, strict=True):
            if not valid.any():
                out.append(None)
                continue
            candidates = candidates[valid]
            # Pick each joint's 2*pi turn nearest q_near, then the closest branch.
            candidates = candidates + 2 * np.pi * np.round((near - candidates) / (2 * np.pi))
            near = candidates[np.argmin(np.abs(candidates - near).max(axis=1))]
            out.append(near)
        return out

    def _line_targets(
        self,
        q0: np.ndarray,
        pose: np.ndarray,
        speed: float,
        acceleration: float,
        time_s: float = 0.0,
    ) -> tuple[np.ndarray, Iterator[np.ndarray]]:
        """Fractions (K,) of a straight TCP line to ``pose`` (trapezoidal in distance; lasting
        ``time_s`` if > 0) and its joint targets, solved lazily :data:`IK_CHUNK` at a time as
        the motion consumes them -- solving a long line at once would stall the control tick
        for seconds.

        Raises ScriptRuntimeError from the iterator when a point of the line has no IK
        solution (movel fails mid-way on a real controller too)."""
        start = np.asarray(self.tcp_pose(q0))
        distance = float(np.linalg.norm(pose[:3] - start[:3]))
        if time_s > 0:
            speed, acceleration = urscript.timed_profile(distance, acceleration, time_s)
        fractions = trapezoid_fractions(max(distance, 1e-9), speed, acceleration, self.dt_s)
        slerp = Slerp([0.0, 1.0], Rotation.from_rotvec([start[3:6], pose[3:6]]))

        def poses(first: int, last: int) -> np.ndarray:
            s = fractions[first:last]
            return np.hstack(
                [start[:3] + s[:, None] * (pose[:3] - start[:3]), slerp(s).as_rotvec()]
            )

        return fractions, self._solve_stream(q0, len(fractions), poses, "movel")

    def _solve_stream(
        self, q0: ArrayLike, count: int, poses: Callable[[int, int], np.ndarray], what: str
    ) -> Iterator[np.ndarray]:
        """Joint targets for ``count`` TCP poses (``poses(first, last)`` gives rows first ..
        last - 1), each nearest the previous, solved :data:`IK_CHUNK` at a time with the TCP
        active when the move started."""
        tcp = self.tcp_offset.copy()

        def solve() -> Iterator[np.ndarray]:
            q = np.asarray(q0, dtype=np.float64)
            for first in range(0, count, IK_CHUNK):
                for q_next in self._ik_many(poses(first, first + IK_CHUNK), q, tcp):
                    if q_next is None:
                        raise ScriptRuntimeError(
                            f"{what}: no inverse kinematics solution on the line"
                        )
                    q = q_next
                    yield q

        return solve()

    # -- the host of a standalone program (urscript.Runner) -------------------------------------

    def actual_q(self) -> np.ndarray:
        """The arm's joints now (for a program's start check)."""
        return np.array(self.q, dtype=np.float64)

    def message(self, text: str) -> None:
        """textmsg: the program's log line."""
        log.info("textmsg: %s", text)
        self.messages.append(text)

    def set_tcp(self, pose: ArrayLike) -> None:
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise ScriptRuntimeError("set_tcp: the TCP must be a pose of 6 finite numbers")
        self.tcp_offset = pose.copy()
        log.info("active TCP set to %s", np.round(pose, 6).tolist())

    def set_payload(
        self, mass: float | None, cog: ArrayLike | None = None, inertia: ArrayLike | None = None
    ) -> None:
        """The active payload (mass None / cog None: kept as it is)."""
        if mass is not None:
            if not (np.isfinite(mass) and mass >= 0):
                raise ScriptRuntimeError(f"set_payload: the mass must be >= 0, got {mass}")
            self.payload_kg = float(mass)
        if cog is not None:
            self.payload_cog_m = np.asarray(cog, dtype=np.float64).copy()
        if inertia is not None:
            self.payload_inertia = np.asarray(inertia, dtype=np.float64).copy()
        log.info("payload set to %.3f kg at %s", self.payload_kg, self.payload_cog_m.tolist())

    def motion_running(self, motion: object) -> bool:
        return self.motion is motion

    def servo(self, q: ArrayLike, t: float, lookahead_s: float, gain: float) -> int:
        """servoj: approach ``q`` over ``t`` through the lookahead model; its length in control
        periods (the time the call takes)."""
        self.servo_target = np.asarray(q, dtype=np.float64)
        self.servo_time_s = max(float(t), self.dt_s)
        self.sim._delay = max(1, int(round(lookahead_s / self.dt_s)))
        self.sim._omega = float(np.sqrt(gain))
        if self.motion is None or self.motion.name != "servoj":
            self.motion = _Motion("servoj", self._servo_targets(), started_s=self.t_s)
        return max(1, int(round(self.servo_time_s / self.dt_s)))

    def settle_servo(self) -> _Motion | None:
        """End a servoj stream: hold its last target until the arm rests on it."""
        motion = self.motion
        target = self.servo_target
        self.servo_target = None
        if motion is None or motion.name != "servoj" or target is None:
            return None
        settle = _Motion("move", iter(()), started_s=self.t_s, expected_s=SETTLE_MAX_S)
        settle.last = target
        self.motion = settle
        return settle

    def brake(self, linear: bool, rate: float) -> _Motion:
        """stopj(a) / stopl(a): brake at ``rate``."""
        self.servo_target = None
        motion = self._brake("stop", linear, sync=False, is_async=False, rate=rate)
        motion.started_s = self.t_s
        self.motion = motion
        return motion

    def start_moves(self, moves: Sequence[urscript._MoveArgs]) -> tuple[_Motion, np.ndarray]:
        """Start one move or a run of blended moves (``urscript._MoveArgs``, one space); the
        motion and the tick at which each move after the first starts."""
        q0 = self.q.copy()
        if moves[0].kind == "movej":
            goals = [q0]
            for move in moves:
                goal = self._ik(move.target, goals[-1]) if move.is_pose else move.target
                if goal is None:
                    raise _at(move, "movej: no inverse kinematics solution for the pose")
                goals.append(np.asarray(goal, dtype=np.float64))
            if len(moves) == 1:
                move = moves[0]
                distance = float(np.abs(goals[1] - q0).max())
                speed, acceleration = move.v, move.a
                if move.t > 0:
                    speed, acceleration = urscript.timed_profile(distance, move.a, move.t)
                fractions = trapezoid_fractions(distance, speed, acceleration, self.dt_s)
                targets = iter(q0 + (goals[1] - q0) * fractions[:, None])
                return self._begin(targets, len(fractions)), np.zeros(0, int)
            q = np.array(goals)
            lengths = np.abs(np.diff(q, axis=0)).max(axis=1)
            speeds, acceleration = _run_limits(moves, lengths)
            path = CoarsePath(
                sample_index=np.arange(len(q)),
                q_rad=q,
                speed_rad_s=np.array([speeds[0], *speeds]),
                acceleration_rad_s2=acceleration,
                blend_m=np.array([0.0] + [m.r for m in moves[:-1]] + [0.0]),
                deviation_max_m=0.0,
            )
            targets, s_at, knots = _path_samples(path, self.dt_s)
            ticks = np.searchsorted(s_at, knots[1:-1] - 1e-9)
            return self._begin(iter(targets), len(targets)), ticks
        # Tool space: movel / movep (joint targets mean their TCP pose).
        poses = []
        near = q0
        for move in moves:
            pose = move.target if move.is_pose else np.asarray(self.tcp_pose(move.target))
            solution = self._ik(pose, near)
            if solution is None:
                raise _at(move, f"{move.kind}: no inverse kinematics solution for the pose")
            poses.append(np.asarray(pose, dtype=np.float64))
            near = solution
        if len(moves) == 1 and moves[0].kind == "movel":
            move = moves[0]
            fractions, targets = self._line_targets(q0, poses[0], move.v, move.a, move.t)
            return self._begin(targets, len(fractions)), np.zeros(0, int)
        start = np.asarray(self.tcp_pose(q0))
        points = np.array([start[:3], *[p[:3] for p in poses]])
        speeds, acceleration = _run_limits(moves, np.linalg.norm(np.diff(points, axis=0), axis=1))
        blended = urscript.tool_path(
            start,
            poses,
            speeds=speeds,
            accelerations=[acceleration],
            blends_m=[m.r for m in moves],
            dt=self.dt_s,
        )
        samples = blended.poses
        targets = self._solve_stream(q0, len(samples), lambda a, b: samples[a:b], moves[0].kind)
        return self._begin(targets, len(samples)), blended.move_ticks

    def _begin(self, targets: Iterator[np.ndarray], count: int) -> _Motion:
        motion = _Motion("move", targets, started_s=self.t_s, expected_s=count * self.dt_s)
        self.motion = motion
        return motion

    # -- physics and async progress ------------------------------------------------------------

    def _physics(self) -> None:
        motion = self.motion
        if motion is not None and motion.deceleration is not None and self.can_move:
            self._brake_step(motion)
        else:
            self._follow(motion)
        if self.motion is motion and motion is not None and self._motion_finished(motion):
            self._finish(motion)

    def _follow(self, motion: _Motion | None) -> None:
        """One period of the servo law towards the motion's next target (None: brake hard)."""
        target = None
        self._follow_slider()
        if motion is not None and self.can_move:
            try:
                target = (
                    self._scaled_target(motion)
                    if motion.name in SCALED_MOTIONS
                    else next(motion.targets, None)
                )
            except ScriptRuntimeError as error:
                self.runtime_error(str(error))  # the motion is now a brake
                motion, target = None, None
            if motion is not None:
                if target is not None:
                    motion.last = target
                elif motion.name in ("move", "path"):
                    motion.settling += 1
                    target = motion.last
                # How far along its targets (speed-scaled for the timed moves: a program's
                # groups and the async progress follow the path, not the clock).
                scaled = motion.name in SCALED_MOTIONS
                motion.tick = int(motion.cursor) if scaled else motion.tick + 1
                if motion.is_async and motion.waypoint_ticks:
                    # The script signals the index of the move it starts (0 .. n-1).
                    passed = bisect.bisect_left(motion.waypoint_ticks, motion.tick)
                    self._progress_if_changed(motion, passed)
        try:
            self.sim._advance(self.t_s, target=target)
        except ProtectiveStopError as error:  # a joint ran into its limit
            self.sim._active = None
            self.protective_stop(str(error))

    def _follow_slider(self) -> None:
        """The speed scaling, one period closer to the slider (at most 1 / SLIDER_RAMP_S per
        second)."""
        step = self.dt_s / SLIDER_RAMP_S
        change = self.speed_slider - self.speed_scaling
        # Exactly the slider once within a step (full speed plays the targets unchanged).
        if abs(change) <= step:
            self.speed_scaling = self.speed_slider
        else:
            self.speed_scaling += float(np.sign(change)) * step

    def _scaled_target(self, motion: _Motion) -> np.ndarray | None:
        """A timed move's target this period at the speed scaling: its targets (one per period
        at full speed) played back at the scaling, between two of them by linear interpolation;
        at scaling 0 the same point again. None once past the last one."""
        if motion.around is None:
            motion.around = (self.q.copy(), self.q.copy())  # where it starts
        motion.cursor += self.speed_scaling
        while motion.pulled < np.ceil(motion.cursor - 1e-9) and not motion.exhausted:
            following = next(motion.targets, None)
            if following is None:
                motion.exhausted = True
                break
            motion.around = (motion.around[1], np.asarray(following, dtype=np.float64))
            motion.pulled += 1
        if motion.exhausted and motion.cursor > motion.pulled:
            return None
        # Between target pulled - 1 (around[0]) and target pulled (around[1]).
        share = 1.0 - (motion.pulled - motion.cursor)
        before, after = motion.around
        return after if share >= 1.0 else before + min(max(share, 0.0), 1.0) * (after - before)

    def _brake_step(self, motion: _Motion) -> None:
        """One period of braking at the motion's deceleration (stopj / stopl)."""
        assert motion.deceleration is not None
        qd = self.sim._qd
        slower = np.sign(qd) * np.maximum(np.abs(qd) - motion.deceleration * self.dt_s, 0.0)
        q = self.sim._q + 0.5 * (qd + slower) * self.dt_s
        self.sim._buffer.clear()  # what servoJ had buffered is dropped by a stop
        self.sim._t = self.t_s
        outside = (q < self.arm.q_min_rad) | (q > self.arm.q_max_rad)
        self.sim._q = np.clip(q, self.arm.q_min_rad, self.arm.q_max_rad)
        self.sim._qd = slower
        motion.tick += 1
        if np.any(outside):
            self.protective_stop(f"joint {int(np.argmax(outside)) + 1} reached its position limit")

    def _motion_finished(self, motion: _Motion) -> bool:
        resting = float(np.abs(self.qd).max()) < SETTLED_RAD_S
        if motion.name in ("brake", "stop"):
            return resting
        if motion.name in ("move", "path") and motion.settling > 0:
            return (resting and motion.settling > self.sim._delay + 2) or (
                motion.settling * self.dt_s > SETTLE_MAX_S
            )
        return False

    def _finish(self, motion: _Motion) -> None:
        if motion.is_async:
            self._write_async_progress(-1)
        if self._waiting_sync is motion:
            self._waiting_sync = None
            self.out_int[self._i(0)] = 2  # signal_done_with_cmd()
        if self.motion is motion:
            self.motion = None

    def _progress_if_changed(self, motion: _Motion, value: int) -> None:
        if motion.reported != value:
            motion.reported = value
            self._write_async_progress(value)

    def _write_async_progress(self, value: int) -> None:
        """Encode async progress the way the pinned script does: bits 24-30 operation id
        (incremented when an operation starts), bits 16-23 a write counter, bit 15 running,
        bits 0-14 progress; a negative value means finished."""
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[self._i(2)] = reg

    # -- for the watchdog ------------------------------------------------------------------------

    def busy_command(self) -> tuple[str, float, float] | None:
        """(what, running for s, expected s) of the motion a command waits on, if any."""
        motion = self._waiting_sync or (
            self.motion if self.motion is not None and self.motion.is_async else None
        )
        if motion is None:
            return None
        return motion.name, self.t_s - motion.started_s, motion.expected_s


def _at(move: urscript._MoveArgs, message: str) -> ScriptRuntimeError:
    """A runtime error at the line of ``move`` (within a run of blended moves)."""
    error = ScriptRuntimeError(message)
    error.line = move.line  # type: ignore[attr-defined]
    return error


def _run_limits(
    moves: Sequence[urscript._MoveArgs], lengths: Iterable[float]
) -> tuple[list[float], float]:
    """Speed caps of a run of blended moves (a move's ``t`` becomes the speed that covers its
    length in ``t``) and the run's acceleration (the lowest ``a`` of its moves)."""
    speeds = [
        m.v if m.t == 0 else max(float(d) / m.t, 1e-6) for m, d in zip(moves, lengths, strict=True)
    ]
    untimed = [m.a for m in moves if m.t == 0]
    return speeds, float(min(untimed) if untimed else 4 * max(speeds))
