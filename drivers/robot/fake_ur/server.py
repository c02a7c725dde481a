"""The fake controller's network side: its ports, the control tick, the test control channel.

Ports (fixed, as on a real controller; run fakes side by side on distinct loopback addresses):

======  ==========================================================================
29999   dashboard server (:mod:`.dashboard`)
30001,  script ports: a URScript program sent here is started: ur_rtde's control
30002,  script by its register protocol, any other by the interpreter of
30003   :mod:`.urscript` (a subset; what it lacks is refused with the line)
30004   RTDE (:mod:`.rtde_server`)
30100   control channel for tests (:data:`CONTROL_PORT`, not a UR port): one JSON
        object a line in, one a line out, e.g. ``{"cmd": "protective_stop"}``
======  ==========================================================================

Control channel commands (reply ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``):
``status`` (arm, modes, active TCP and payload, the program); ``protective_stop``;
``emergency_stop`` (``"source": "robot"`` -- the default, ROBOT_EMERGENCY_STOP -- or
``"system"``, SYSTEM_EMERGENCY_STOP); ``release_emergency_stop``;
``drop_connections`` (close every client socket; with ``refuse_s``, new connections are
closed at once for that long -- a link that stays down, which ur_rtde's automatic
reconnection cannot bridge);
``freeze`` / ``unfreeze`` (stop / resume answering: no data, no replies, sockets stay open);
``reset`` (arm at rest at ``q_rad`` or the start pose, faults cleared, powered, program stopped,
registers zeroed, options back to their defaults);
``configure`` (options: ``unlock_wait_s``, how long after a protective stop the dashboard
refuses to unlock it, default 5 s as on UR's controllers -- 0 for tests that do not care;
``remote_control``, false for local control: programs on the script ports and the
dashboard's ``play`` are refused, ``is in remote control`` answers false);
``last_script`` (the text of the last program received);
``program_status`` (what became of the last program: :func:`program_status`);
``program_trace`` (the arm's joints and TCP pose every control period since the last
program started: :func:`program_trace`); ``shutdown``.

A program on a script port starts when it is complete: ur_rtde's control script at its
closing ``end``; any other program when the sender closes the connection or pauses for
:data:`SCRIPT_QUIET_S` after a complete line (a ``def`` block only once its ``end`` has come).
"""

from __future__ import annotations

import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.robot.fake_ur import control_script as cs
from drivers.robot.fake_ur import controller as ctl
from drivers.robot.fake_ur import dashboard, watchdog
from drivers.robot.fake_ur.rtde_server import RTDEConnection

log = logging.getLogger("fake_ur")

DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
RTDE_PORT = 30004
CONTROL_PORT = 30100
#: A script upload larger than this without its end is refused (ur_rtde's is about 60 kB; a
#: standalone program of 50 000 servoj lines about 4 MB).
MAX_SCRIPT_CHARS = 16_000_000
#: A standalone program is taken as complete once its sender pauses this long (s) -- or closes
#: the connection -- after a complete line (the controller has no other end marker for a bare
#: sequence of statements, and a ``def`` block may be followed by its call).
SCRIPT_QUIET_S = 0.1
#: At most this many trace samples per ``program_trace`` reply (~5 MB of JSON).
TRACE_REPLY_MAX = 20_000


class FakeUR:
    """A fake UR controller listening on ``host``.

    Parameters
    ----------
    host : str
        Loopback address to bind (e.g. 127.0.0.2).
    robot : str
        UR model; e-series names run at 500 Hz, CB3 (ur3/ur5/ur10) at 125 Hz.
    powered : bool
        Start with the arm powered and brakes released (RUNNING).
    """

    def __init__(self, host: str, robot: str = "ur5e", *, powered: bool = True) -> None:
        self.host = host
        self.controller = ctl.FakeController(
            robot, powered=powered, program_start_s=ctl.PROGRAM_START_S
        )
        e_series = self.controller.rate_hz >= 500
        self.version = (5, 11, 1, 108318) if e_series else (3, 15, 7, 106331)
        self.polyscope = (
            "URSoftware 5.11.1.108318 (Mar 22 2021)"
            if e_series
            else "URSoftware 3.15.7.106331 (Oct 19 2021)"
        )
        self.model_name = robot.upper().removesuffix("E") if e_series else robot.upper()
        self.serial = "20235500001" if e_series else "2018300001"
        self.last_script = ""
        self._stop = threading.Event()
        self._servers: list[socket.socket] = []
        self._clients: list[socket.socket] = []
        self._rtde: list[RTDEConnection] = []
        self._threads: list[threading.Thread] = []
        self._clients_lock = threading.Lock()
        self._refuse_until = 0.0  # monotonic time until which new connections are closed

    # -- life cycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Bind every port (raises OSError if one is taken) and start serving."""
        handlers = {DASHBOARD_PORT: self._dashboard, RTDE_PORT: self._rtde_client}
        handlers.update(dict.fromkeys(SCRIPT_PORTS, self._script))
        handlers[CONTROL_PORT] = self._control
        for port, handler in handlers.items():
            server = socket.create_server((self.host, port), reuse_port=False)
            server.settimeout(0.2)
            self._servers.append(server)
            self._spawn(self._accept, server, handler, name=f"accept {port}")
        self._spawn(self._tick, name="tick")
        self._spawn(watchdog.watch, self.controller, self._stop, name="watchdog")
        log.info("fake %s controller on %s", self.controller.arm.name, self.host)

    def wait(self) -> None:
        """Block until :meth:`shutdown` (or the ``shutdown`` control command)."""
        while not self._stop.wait(0.5):
            pass

    def shutdown(self) -> None:
        self._stop.set()
        for server in self._servers:
            server.close()
        self.drop_connections()

    def drop_connections(self) -> None:
        """Close every client socket (the ports keep listening)."""
        with self._clients_lock:
            clients, self._clients = self._clients, []
            rtde, self._rtde = self._rtde, []
        for connection in rtde:
            connection.close()
        for sock in clients:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    # -- plumbing --------------------------------------------------------------------------------

    def _spawn(self, target: Callable[..., object], *args: Any, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        # One thread per client connection: forget the finished ones so a long-running fake
        # does not keep every connection it ever served.
        self._threads = [t for t in self._threads if t.is_alive()] + [thread]

    def _accept(
        self, server: socket.socket, handler: Callable[[socket.socket, int], object]
    ) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            port = server.getsockname()[1]
            if port != CONTROL_PORT and time.monotonic() < self._refuse_until:
                sock.close()  # "unreachable": ur_rtde's automatic reconnection fails too
                continue
            sock.settimeout(None)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if port != CONTROL_PORT:  # the test's channel survives drop_connections
                with self._clients_lock:
                    self._clients.append(sock)
            self._spawn(self._guard, handler, sock, port, name=f"client {port}")

    def _guard(
        self, handler: Callable[[socket.socket, int], object], sock: socket.socket, port: int
    ) -> None:
        try:
            handler(sock, port)
        except OSError as exc:
            log.debug("client on %d gone: %s", port, exc)
        except Exception:  # a bug in the fake: log it, keep the other clients served
            log.exception("fake controller error on port %d", port)
        finally:
            with self._clients_lock:
                if sock in self._clients:
                    self._clients.remove(sock)
            sock.close()

    def _tick(self) -> None:
        """The control loop: one step and one round of data packages per control period.

        Deadlines are absolute so the stream keeps its rate on average when a tick runs late.
        """
        c = self.controller
        next_s = time.monotonic()
        while not self._stop.is_set():
            next_s += c.dt_s
            delay = next_s - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                next_s = time.monotonic()  # far behind (machine stalled): do not burst
            if c.frozen:
                continue
            try:
                c.step()
                with c.lock:
                    values = c.outputs()
                with self._clients_lock:
                    connections = list(self._rtde)
                for connection in connections:
                    connection.send_data(values)
            except Exception:
                # A bug in the fake: stop the program so a waiting client fails instead of
                # hanging, and keep ticking (data keeps flowing, the test can go on).
                log.exception("error in the control tick")
                c.runtime_error("internal error in the fake controller's control tick")

    # -- ports -----------------------------------------------------------------------------------

    def _rtde_client(self, sock: socket.socket, port: int) -> None:
        connection = RTDEConnection(sock, self.controller, self.version)
        with self._clients_lock:
            self._rtde.append(connection)
        try:
            connection.serve()
        finally:
            with self._clients_lock:
                if connection in self._rtde:
                    self._rtde.remove(connection)

    def _dashboard(self, sock: socket.socket, port: int) -> None:
        sock.sendall((dashboard.GREETING + "\n").encode())
        for raw in sock.makefile("rb"):
            line = raw.decode(errors="replace")
            if self.controller.frozen:
                continue
            answer = dashboard.reply(
                self.controller,
                line,
                polyscope=self.polyscope,
                serial=self.serial,
                model=self.model_name,
            )
            log.info("dashboard: %r -> %r", line.strip(), answer)
            sock.sendall((answer + "\n").encode())
            if answer == "Disconnected":
                return

    def _script(self, sock: socket.socket, port: int) -> None:
        chunks: list[str] = []
        size = 0
        while True:
            waiting = bool(chunks) and _may_end(chunks[-1])
            sock.settimeout(SCRIPT_QUIET_S if waiting else None)
            try:
                data = sock.recv(65536)
            except TimeoutError:
                data = None  # the sender paused after a complete line
            if data == b"":  # closed: whatever came is the program
                if chunks and "".join(chunks).strip():
                    self._load("".join(chunks), port)
                return
            if data is None:
                text = "".join(chunks)
                if _standalone_complete(text):
                    self._load(text, port)
                    chunks, size = [], 0
                continue
            chunk = data.decode(errors="replace")
            chunks.append(chunk)
            size += len(chunk)
            if size > MAX_SCRIPT_CHARS:
                log.warning("script on %d over %d characters without an end: dropped", port, size)
                return
            # ur_rtde's control script starts at its end, at once (its client waits for it).
            if "end" in chunk and cs.REQUIRED_MARKERS["program"] in chunks[0]:
                text = "".join(chunks)
                if cs.program_complete(text) and not cs.missing_markers(text):
                    self._load(text, port)
                    chunks, size = [], 0

    def _load(self, text: str, port: int) -> None:
        self.last_script = text
        started = self.controller.load_program(text)
        log.info("program received on %d (%d bytes), started: %s", port, len(text), started)

    def _control(self, sock: socket.socket, port: int) -> None:
        for raw in sock.makefile("rb"):
            command = None
            try:
                request = json.loads(raw)
                if not isinstance(request, dict):
                    raise ValueError('a request is a JSON object: {"cmd": "status", ...}')
                command = request.get("cmd")
                answer = {"ok": True, **(self.handle_control(request) or {})}
            except Exception as exc:  # the reply says what went wrong
                answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            sock.sendall((json.dumps(answer) + "\n").encode())
            if command == "shutdown" and answer["ok"]:
                self.shutdown()
                return

    def handle_control(self, request: dict[str, Any]) -> dict[str, Any] | None:  # noqa: C901
        """Carry out one control channel request (see the module docstring)."""
        c = self.controller
        command = request.get("cmd")
        if command == "status":
            with c.lock:
                return {
                    "robot": c.arm.name,
                    "q_rad": [float(v) for v in c.q],
                    "tcp_pose": c.tcp_pose(),
                    "tcp_offset": [float(v) for v in c.tcp_offset],
                    "payload_kg": c.payload_kg,
                    "payload_cog_m": [float(v) for v in c.payload_cog_m],
                    "payload_inertia": [float(v) for v in c.payload_inertia],
                    "robot_mode": c.robot_mode,
                    "safety_mode": c.safety_mode,
                    "runtime_state": c.runtime_state,
                    "remote_control": c.remote_control,
                    "frozen": c.frozen,
                    "program": program_status(c)["state"],
                    "int_offset": c.script.int_offset if c.script else None,
                    "commands": [cmd for _, cmd in list(c.command_log)[-50:]],
                    "path_moves": len(c.script.path) if c.script else 0,
                    "speed_slider": c.speed_slider,
                    "speed_scaling": c.speed_scaling,
                    "rtde_clients": len(self._rtde),
                }
        if command == "program_status":
            with c.lock:
                return program_status(c)
        if command == "program_trace":
            unknown = set(request) - {"cmd", "start", "stop", "every"}
            if unknown:
                raise ValueError(f"unknown options {sorted(unknown)}")
            return program_trace(
                c,
                start=_count(request, "start", 0),
                stop=None if request.get("stop") is None else _count(request, "stop", 0),
                every=_count(request, "every", 1, minimum=1),
            )
        if command == "protective_stop":
            c.protective_stop()
        elif command == "emergency_stop":
            c.emergency_stop(str(request.get("source", "robot")))
        elif command == "release_emergency_stop":
            c.release_emergency_stop()
        elif command == "drop_connections":
            self._refuse_until = time.monotonic() + float(request.get("refuse_s", 0.0))
            self.drop_connections()
        elif command == "freeze":
            c.frozen = True
        elif command == "unfreeze":
            c.frozen = False
        elif command == "reset":
            self._refuse_until = 0.0
            with c.lock:
                c.frozen = False
                c.safety_mode = ctl.SAFETY_NORMAL
                c.robot_mode = ctl.ROBOT_MODE_RUNNING
                c.stop_program()
                q = request.get("q_rad")
                c.reset_arm(None if q is None else np.asarray(q, dtype=np.float64))
                c.clear_registers()  # no command or result of the last test left behind
                c.unlock_wait_s = ctl.UNLOCK_WAIT_S
                c.remote_control = True
                c.reset_tool()
                c.speed_slider = c.speed_scaling = 1.0
                c.runner, c.run, c.script = None, None, None
                c.program_name = "<none>"
                c.trace = ctl.Trace()
        elif command == "configure":
            unknown = set(request) - {"cmd", "unlock_wait_s", "remote_control"}
            if unknown:
                raise ValueError(f"unknown options {sorted(unknown)}")
            if "remote_control" in request:
                if not isinstance(request["remote_control"], bool):
                    raise ValueError("remote_control is true or false")
                with c.lock:
                    c.remote_control = request["remote_control"]
            if "unlock_wait_s" in request:
                wait_s = float(request["unlock_wait_s"])
                if not wait_s >= 0:
                    raise ValueError("unlock_wait_s must be >= 0")
                with c.lock:
                    c.unlock_wait_s = wait_s
        elif command == "last_script":
            return {"script": self.last_script}
        elif command == "shutdown":
            pass
        else:
            raise ValueError(f"unknown control command {command!r}")
        return None


def _may_end(chunk: str) -> bool:
    """Whether a program's text may end after ``chunk`` (it ends a line)."""
    return chunk.endswith("\n")


def _standalone_complete(text: str) -> bool:
    """A program that is not ur_rtde's control script, paused after: complete unless it is a
    ``def`` block whose ``end`` has not come (or ur_rtde's script still arriving)."""
    if not text.strip() or cs.REQUIRED_MARKERS["program"] in text:
        return cs.program_complete(text) and bool(text.strip())
    if re.search(r"^def\s", text, re.MULTILINE):
        return cs.program_complete(text)
    return True


def _count(request: dict[str, Any], name: str, default: int, *, minimum: int = 0) -> int:
    value = request.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}")
    return value


def program_status(c: ctl.FakeController) -> dict[str, Any]:
    """What became of the last program (call under the controller's lock).

    ``{"state": "none" | "running" | "finished" | "error" | "stopped" | "refused",
    "kind": "urscript" | "rtde_control" | null, "name": str, "line": int | null (the line
    running, or where it failed / stopped), "message": str | null (the error, or why it
    stopped / was refused), "number": the how-manyth program this is (0: none yet),
    "started_s", "ended_s": controller time (s) | null,
    "statements": int, "executed": int (statements run), "trace_samples": int,
    "q_rad": [6], "tcp_pose": [6] (now), "messages": [str] (the last textmsg / errors)}``
    """
    run = c.run
    kind = None
    if c.script is not None:
        kind = "rtde_control" if c.script.is_rtde_control else "urscript"
    line = run.line if run is not None else None
    if run is not None and run.state == "running" and c.runner is not None:
        line = c.runner.current_line()
    return {
        "state": run.state if run is not None else "none",
        "kind": kind,
        "name": c.program_name,
        "line": line,
        "message": run.message if run is not None else None,
        "number": run.number if run is not None else 0,
        "started_s": run.started_s if run is not None else None,
        "ended_s": run.ended_s if run is not None else None,
        "statements": len(c.runner.program.statements) if c.runner is not None else 0,
        "executed": run.executed if run is not None else 0,
        "trace_samples": c.trace.dropped + len(c.trace),
        "t_s": c.t_s,
        "q_rad": [float(v) for v in c.q],
        "tcp_pose": c.tcp_pose(),
        "messages": list(c.messages)[-20:],
    }


def program_trace(
    c: ctl.FakeController, *, start: int = 0, stop: int | None = None, every: int = 1
) -> dict[str, Any]:
    """The recorded trace from sample ``start`` (counted from the program's start) to
    ``stop``, every ``every``-th, at most :data:`TRACE_REPLY_MAX` rows a reply.

    ``{"t_s": [K], "q_rad": [K][6], "tcp_pose": [K][6] (actual, with the TCP active then),
    "line": [K] (the standalone program's line executing then; 0 for none), "start": int,
    "next": int (the ``start`` of the following page), "total": int, "dropped": int
    (samples older than the bound, gone), "complete": bool (the program has ended and the
    arm come to rest: no more samples will come)}``
    """
    with c.lock:
        total = c.trace.dropped + len(c.trace)
        stop = total if stop is None else min(stop, total)
        stop = min(stop, start + TRACE_REPLY_MAX * every)
        rows = c.trace.rows(start, stop, every)
        dropped = c.trace.dropped
        complete = c.runtime_state != ctl.RUNTIME_PLAYING and c._trace_until is None
    first = max(start, dropped)
    return {
        "t_s": rows[:, 0].tolist(),
        "q_rad": rows[:, 1:7].tolist(),
        "tcp_pose": rows[:, 7:13].tolist(),
        "line": rows[:, 13].astype(int).tolist(),
        "start": first,
        "next": first + len(rows) * every,
        "total": total,
        "dropped": dropped,
        "complete": bool(complete and first + len(rows) * every >= total),
    }
