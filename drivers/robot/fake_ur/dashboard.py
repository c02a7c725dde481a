"""The dashboard server (TCP 29999): one command per line, one UR-style line in reply.

Replies follow the wording of UR's dashboard server documentation for the commands ur_rtde's
DashboardClient and teachpath's adapter use; anything else gets UR's "Could not understand"
reply, so a client never waits for an answer that will not come.
"""

from __future__ import annotations

from drivers.robot.fake_ur import controller as ctl

GREETING = "Connected: Universal Robots Dashboard Server"
#: The reply to an unlock within :data:`~.controller.UNLOCK_WAIT_S` of the protective stop
#: (UR's wording).
UNLOCK_TOO_EARLY = (
    "Cannot unlock protective stop until 5s after occurrence. "
    "Always inspect cause of protective stop before unlocking"
)


def reply(c: ctl.FakeController, line: str, *, polyscope: str, serial: str, model: str) -> str:  # noqa: C901
    """The one-line answer to the dashboard command ``line`` (state changes applied)."""
    command = line.strip()
    lower = command.lower()
    with c.lock:
        if lower == "polyscopeversion":
            return polyscope
        if lower == "get serial number":
            return serial
        if lower == "get robot model":
            return model
        if lower == "is in remote control":
            return "true" if c.remote_control else "false"
        if lower == "robotmode":
            return f"Robotmode: {ctl.ROBOT_MODE_NAMES.get(c.robot_mode, 'POWER_OFF')}"
        if lower == "safetymode":
            return f"Safetymode: {ctl.SAFETY_NAMES[c.safety_mode]}"
        if lower == "safetystatus":
            return f"Safetystatus: {ctl.SAFETY_NAMES[c.safety_mode]}"
        if lower == "programstate":
            state = "PLAYING" if c.runtime_state == ctl.RUNTIME_PLAYING else "STOPPED"
            return f"{state} {c.program_name}"
        if lower == "running":
            return f"Program running: {str(c.runtime_state == ctl.RUNTIME_PLAYING).lower()}"
        if lower == "get loaded program":
            return f"Loaded program: {c.program_name}"
        if lower == "play":
            # A standalone program starts again from its first line; ur_rtde's script
            # resumes its loop. Refused in local control, as on an e-series controller.
            if not c.restart_program():
                return "Failed to execute: play"
            return "Starting program"
        if lower == "stop":
            # "Stopped" also when nothing runs: ur_rtde stops its old script through the
            # registers and then on the dashboard when it reconnects, and fails on any other
            # reply -- which it could not do against a real controller.
            c.stop_program("stopped from the dashboard")
            return "Stopped"
        if lower == "pause":
            return "Pausing program"
        if lower == "power on":
            if c.emergency_stopped:
                return "Failed to execute: power on"
            if c.robot_mode < ctl.ROBOT_MODE_IDLE:
                c.robot_mode = ctl.ROBOT_MODE_IDLE
            return "Powering on"
        if lower == "power off":
            c.stop_program("powered off")
            c.robot_mode = ctl.ROBOT_MODE_POWER_OFF
            return "Powering off"
        if lower == "brake release":
            if c.robot_mode >= ctl.ROBOT_MODE_IDLE and not c.emergency_stopped:
                c.robot_mode = ctl.ROBOT_MODE_RUNNING
            return "Brake releasing"
        if lower == "unlock protective stop":
            if c.unlock_too_early():
                return UNLOCK_TOO_EARLY
            if c.unlock_protective_stop():
                return "Protective stop releasing"
            return "Cannot unlock protective stop"
        if lower == "close safety popup":
            return "closing safety popup"
        if lower == "close popup":
            return "closing popup"
        if lower == "restart safety":
            c.safety_mode = ctl.SAFETY_NORMAL
            c.robot_mode = ctl.ROBOT_MODE_POWER_OFF
            return "Restarting safety"
        if lower == "quit":
            return "Disconnected"
    return f"Could not understand: '{command}'"
