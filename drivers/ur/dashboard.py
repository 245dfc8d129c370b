"""The UR dashboard server's line protocol (TCP 29999), answered from a ``URControllerModel``.

Requests are single lines ending in ``\\n``; each gets one reply line; a banner line is sent on connect
(devices.md section 5). The replies the ``ur_rtde`` client checks are exact: ``stop`` -> ``Stopped``, ``play`` ->
``Starting program``, ``unlock protective stop`` -> ``Protective stop releasing``, ``PolyscopeVersion`` -> a
four-part version, ``get serial number`` -> digits, ``is in remote control`` -> ``true``/``false``.
"""

from __future__ import annotations

from hydrosoft.drivers.ur.safety_status import RuntimeState
from hydrosoft.drivers.ur.controller import URControllerModel

BANNER = "Connected: Universal Robots Dashboard Server"
QUIT_REPLY = "Disconnected"
UNLOCK_TOO_EARLY = (
    "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
)


def dashboard_reply(model: URControllerModel, line: str) -> str:
    """The reply line (without newline) to one request ``line``; acts on ``model`` (stop, play, unlock...).

    Unknown requests get ``could not understand: '<line>'`` and are counted (``dashboard_unknown``).
    """
    request = line.strip()
    command = request.lower()
    model.counters["dashboard_requests"] += 1
    if command == "polyscopeversion":
        major, minor, bugfix, build = model.identity.version
        return f"URSoftware {major}.{minor}.{bugfix}.{build} (simulated)"
    if command == "get serial number":
        return model.identity.serial_number
    if command == "get robot model":
        return model.identity.robot_model
    if command == "is in remote control":
        return "true" if model.remote_control else "false"
    if command == "stop":
        model.stop_program()
        return "Stopped"
    if command == "play":
        return "Starting program" if model.play() else "Failed to execute: play"
    if command == "pause":
        model.pause_program()
        return "Pausing program"
    if command == "unlock protective stop":
        return "Protective stop releasing" if model.unlock_protective_stop() else UNLOCK_TOO_EARLY
    if command == "running":
        return f"Program running: {'true' if model.script.running else 'false'}"
    if command == "programstate":
        if model.runtime_state == RuntimeState.PAUSED:
            return "PAUSED rtde_control"
        return "PLAYING rtde_control" if model.runtime_state == RuntimeState.PLAYING else "STOPPED <unnamed>"
    if command == "isprogramsaved":
        return "True rtde_control"
    if command == "robotmode":
        return f"Robotmode: {'POWER_OFF' if model.emergency_stop else 'RUNNING'}"
    if command in ("safetymode", "safetystatus"):
        label = "Safetymode" if command == "safetymode" else "Safetystatus"
        if model.emergency_stop:
            return f"{label}: ROBOT_EMERGENCY_STOP"
        if model.safeguard_stop:
            return f"{label}: SAFEGUARD_STOP"
        return f"{label}: {'PROTECTIVE_STOP' if model.protective_stop else 'NORMAL'}"
    if command == "power on":
        return "Powering on"
    if command == "power off":
        return "Powering off"
    if command == "brake release":
        return "Brake releasing"
    if command == "close safety popup":
        return "closing safety popup"
    if command.startswith("load "):
        return f"Loading program: {request[5:]}"
    if command == "quit":
        return QUIT_REPLY
    model.counters["dashboard_unknown"] += 1
    return f"could not understand: '{request}'"
