"""The fake controller's network side: its ports, the control tick, the test control channel.

Ports (fixed, as on a real controller; run fakes side by side on distinct loopback addresses):

======  ==========================================================================
29999   dashboard server (:mod:`.dashboard`)
30001,  script ports: a URScript program sent here is started (only ur_rtde's
30002,  control script is emulated; other programs are accepted and ignored)
30003
30004   RTDE (:mod:`.rtde_server`)
30100   control channel for tests (:data:`CONTROL_PORT`, not a UR port): one JSON
        object a line in, one a line out, e.g. ``{"cmd": "protective_stop"}``
======  ==========================================================================

Control channel commands (reply ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``):
``status``; ``protective_stop``; ``emergency_stop``; ``release_emergency_stop``;
``drop_connections`` (close every client socket; with ``refuse_s``, new connections are
closed at once for that long -- a link that stays down, which ur_rtde's automatic
reconnection cannot bridge);
``freeze`` / ``unfreeze`` (stop / resume answering: no data, no replies, sockets stay open);
``reset`` (arm at rest at ``q_rad`` or the start pose, faults cleared, powered, program stopped,
registers zeroed, options back to their defaults);
``configure`` (options: ``unlock_wait_s``, how long after a protective stop the dashboard
refuses to unlock it, default 5 s as on UR's controllers -- 0 for tests that do not care);
``last_script`` (the text of the last program received); ``shutdown``.
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

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
#: A script upload larger than this without its end is refused (ur_rtde's is about 60 kB).
MAX_SCRIPT_CHARS = 4_000_000


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
        handlers.update({port: self._script for port in SCRIPT_PORTS})
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

    def _spawn(self, target, *args, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        # One thread per client connection: forget the finished ones so a long-running fake
        # does not keep every connection it ever served.
        self._threads = [t for t in self._threads if t.is_alive()] + [thread]

    def _accept(self, server: socket.socket, handler) -> None:
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

    def _guard(self, handler, sock: socket.socket, port: int) -> None:
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
        text = ""
        while True:
            data = sock.recv(65536)
            if not data:
                return
            text += data.decode(errors="replace")
            if len(text) > MAX_SCRIPT_CHARS:
                log.warning(
                    "script on %d over %d characters without an end: dropped", port, len(text)
                )
                return
            if cs.program_complete(text):
                self.last_script = text
                started = self.controller.load_program(text)
                log.info("program received on %d (%d bytes), started: %s", port, len(text), started)
                text = ""

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

    def handle_control(self, request: dict) -> dict | None:
        """Carry out one control channel request (see the module docstring)."""
        c = self.controller
        command = request.get("cmd")
        if command == "status":
            with c.lock:
                return {
                    "robot": c.arm.name,
                    "q_rad": [float(v) for v in c.q],
                    "robot_mode": c.robot_mode,
                    "safety_mode": c.safety_mode,
                    "runtime_state": c.runtime_state,
                    "frozen": c.frozen,
                    "int_offset": c.script.int_offset if c.script else None,
                    "commands": [cmd for _, cmd in list(c.command_log)[-50:]],
                    "path_moves": len(c.script.path) if c.script else 0,
                    "rtde_clients": len(self._rtde),
                }
        if command == "protective_stop":
            c.protective_stop()
        elif command == "emergency_stop":
            c.emergency_stop()
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
        elif command == "configure":
            unknown = set(request) - {"cmd", "unlock_wait_s"}
            if unknown:
                raise ValueError(f"unknown options {sorted(unknown)}")
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
