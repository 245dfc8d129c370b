"""One RTDE connection of the simulated controller, without sockets: handshake, recipes, inputs, output stream.

``RtdeSession.handle`` answers each packet a client sends (through the ``send`` callable it was given) and applies
input data packages to the controller model; ``stream`` sends the output recipes whose period has elapsed. Input
fields are owned controller-wide (``owners``: field name -> session id): a field another connection owns is
answered ``IN_USE``. Recipe ids count from 1 on each connection, as ur_rtde hard-codes them (devices.md 1, 3.3, 6.1).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Callable

from hydrosoft.drivers.ur import rtde_protocol as rtde
from hydrosoft.drivers.ur.controller import URControllerModel

MAX_BACKLOG_BYTES = 1 << 20  # a client this far behind gets no more data packages until it drains


class RtdeSession:
    """State of one RTDE client connection.

    Args:
        session_id: unique per connection; the owner id of the input fields it sets up.
        model: the controller it reads outputs from and writes inputs to.
        owners: controller-wide input-field ownership, shared by all sessions.
        counters: where refusals and traffic are counted (``rtde_*`` names).
        max_output_hz: cap on the output rate a client may ask for.
        send: writes bytes to the client.
    """

    def __init__(
        self,
        session_id: int,
        model: URControllerModel,
        owners: dict[str, int],
        counters: Counter,
        max_output_hz: float,
        send: Callable[[bytes], None],
    ) -> None:
        self.session_id = session_id
        self.model = model
        self.owners = owners
        self.counters = counters
        self.max_output_hz = max_output_hz
        self.send = send
        self.outputs: list[tuple[rtde.Recipe, int]] = []  # recipe, period in ns
        self.next_send_ns: list[int] = []
        self.inputs: dict[int, rtde.Recipe] = {}
        self.started = False

    def handle(self, packet: rtde.Packet, now_ns: int) -> None:
        """Answer one client packet, or apply it (input data package). Raises ``RtdeProtocolError`` for a payload
        that does not parse; the session stays usable."""
        cmd = packet.command
        if cmd == rtde.CMD_DATA_PACKAGE:
            self._apply_input(packet.payload, now_ns)
        elif cmd == rtde.CMD_REQUEST_PROTOCOL_VERSION:
            version = rtde.decode_protocol_version_request(packet.payload)
            self.send(rtde.encode_protocol_version_reply(version in rtde.SUPPORTED_PROTOCOL_VERSIONS))
        elif cmd == rtde.CMD_GET_URCONTROL_VERSION:
            self.send(rtde.encode_controller_version_reply(*self.model.identity.version))
        elif cmd == rtde.CMD_SETUP_OUTPUTS:
            self._setup_outputs(packet.payload)
        elif cmd == rtde.CMD_SETUP_INPUTS:
            self._setup_inputs(packet.payload)
        elif cmd == rtde.CMD_START:
            self.started = True
            self.next_send_ns = [now_ns] * len(self.outputs)
            self.send(rtde.encode_start_reply(True))
        elif cmd == rtde.CMD_PAUSE:
            self.started = False
            self.send(rtde.encode_pause_reply(True))
        elif cmd == rtde.CMD_TEXT_MESSAGE:
            self.counters["rtde_text_message"] += 1
        else:
            self.counters["rtde_unknown_command"] += 1

    def due(self, now_ns: int) -> bool:
        """True when started and some output recipe's period has elapsed."""
        return self.started and any(now_ns >= t for t in self.next_send_ns)

    def stream(self, now_ns: int, values: dict[str, object], backlog_bytes: int) -> None:
        """Send each output recipe that is due at ``now_ns``, with ``values`` (``URControllerModel.output_values``);
        skip (and count) when ``backlog_bytes`` still wait unsent to this client."""
        for index, (recipe, period_ns) in enumerate(self.outputs):
            if now_ns < self.next_send_ns[index]:
                continue
            # keep the schedule, but never run more than one period behind (no bursts after a late tick)
            self.next_send_ns[index] = max(self.next_send_ns[index] + period_ns, now_ns - period_ns)
            if backlog_bytes > MAX_BACKLOG_BYTES:
                self.counters["rtde_output_dropped"] += 1
                continue
            self.send(rtde.encode_data_package(recipe, values))

    def release(self) -> None:
        """Give up every input field this connection owned (the connection closed)."""
        for name in [n for n, owner in self.owners.items() if owner == self.session_id]:
            del self.owners[name]

    def _setup_outputs(self, payload: bytes) -> None:
        frequency_hz, names = rtde.decode_output_setup(payload)
        missing = rtde.unknown_names(names, rtde.OUTPUT_TYPES)
        if missing:
            self.counters["rtde_output_not_found"] += 1
            types = [rtde.NOT_FOUND if n in missing else rtde.OUTPUT_TYPES[n] for n in names]
            self.send(rtde.encode_setup_reply(rtde.CMD_SETUP_OUTPUTS, 0, types))
            return
        if not (math.isfinite(frequency_hz) and 0.0 < frequency_hz <= self.max_output_hz):
            self.counters["rtde_output_rate_capped"] += 1
            frequency_hz = self.max_output_hz
        recipe = rtde.Recipe.build(len(self.outputs) + 1, names, rtde.OUTPUT_TYPES)
        self.outputs.append((recipe, int(1e9 / frequency_hz)))
        self.next_send_ns.append(0)
        self.send(rtde.encode_setup_reply(rtde.CMD_SETUP_OUTPUTS, recipe.recipe_id, list(recipe.types)))

    def _setup_inputs(self, payload: bytes) -> None:
        names = rtde.decode_input_setup(payload)
        types = []
        for name in names:
            if name not in rtde.INPUT_TYPES:
                types.append(rtde.NOT_FOUND)
            elif self.owners.get(name, self.session_id) != self.session_id:
                types.append(rtde.IN_USE)
            else:
                types.append(rtde.INPUT_TYPES[name])
        if rtde.NOT_FOUND in types or rtde.IN_USE in types:
            self.counters["rtde_input_refused"] += 1
            self.send(rtde.encode_setup_reply(rtde.CMD_SETUP_INPUTS, 0, types))
            return
        for name in names:
            self.owners[name] = self.session_id
        recipe = rtde.Recipe.build(len(self.inputs) + 1, names, rtde.INPUT_TYPES)
        self.inputs[recipe.recipe_id] = recipe
        self.send(rtde.encode_setup_reply(rtde.CMD_SETUP_INPUTS, recipe.recipe_id, list(recipe.types)))

    def _apply_input(self, payload: bytes, now_ns: int) -> None:
        recipe = self.inputs.get(rtde.data_package_recipe_id(payload))
        if recipe is None:
            self.counters["rtde_input_unknown_recipe"] += 1
            return
        self.model.write_inputs(rtde.decode_data_package(recipe, payload), now_ns)
        self.counters["rtde_input_packages"] += 1
