"""RTDE wire format (protocol version 2): packet framing, the field type table, data packages.

Every packet starts with a 3-byte big-endian header: ``uint16`` size (header included) and a
``uint8`` type. Package types and the field names/types follow UR's published RTDE guide; only
what the ur_rtde client and the fake controller need is implemented.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass

HEADER = struct.Struct(">HB")

#: Package types (ASCII letters in UR's guide).
REQUEST_PROTOCOL_VERSION = ord("V")  # 86
GET_URCONTROL_VERSION = ord("v")  # 118
TEXT_MESSAGE = ord("M")  # 77
DATA_PACKAGE = ord("U")  # 85
SETUP_OUTPUTS = ord("O")  # 79
SETUP_INPUTS = ord("I")  # 73
START = ord("S")  # 83
PAUSE = ord("P")  # 80

#: struct format and element count of each RTDE type.
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

#: Controller -> client fields (UR's RTDE guide, "Robot controller outputs").
_OUTPUTS_FIXED: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
}

#: Client -> controller fields (UR's RTDE guide, "Robot controller inputs").
_INPUTS_FIXED: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}

#: General purpose registers: 0-47 (24-47 are the "upper range" meant for external clients).
_REGISTER = re.compile(r"^(input|output)_(bit|int|double)_register_(\d+)$")
_REGISTER_TYPES = {"bit": "BOOL", "int": "INT32", "double": "DOUBLE"}
REGISTER_COUNT = 48
#: Bit registers 0-63 are the two 32-bit words above; 64-127 are addressable one by one.
BIT_REGISTER_RANGE = range(64, 128)


def _register_type(name: str, direction: str) -> str | None:
    match = _REGISTER.match(name)
    if match is None or match.group(1) != direction:
        return None
    kind, index = match.group(2), int(match.group(3))
    valid = BIT_REGISTER_RANGE if kind == "bit" else range(REGISTER_COUNT)
    return _REGISTER_TYPES[kind] if index in valid else None


def output_type(name: str) -> str | None:
    """The RTDE type of an output field, or None if the controller has no such field."""
    if name in _OUTPUTS_FIXED:
        return _OUTPUTS_FIXED[name]
    # Input registers can be read back as outputs too.
    return _register_type(name, "output") or _register_type(name, "input")


def input_type(name: str) -> str | None:
    """The RTDE type of an input field, or None if it is not writable."""
    return _INPUTS_FIXED.get(name) or _register_type(name, "input")


@dataclass(frozen=True)
class Recipe:
    """An ordered list of fields and the struct that packs their values.

    Attributes
    ----------
    recipe_id : int
    names, types : tuple of str
    """

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in self.types))

    def pack(self, values: dict[str, object]) -> bytes:
        """A data package body (recipe id + values) for ``values`` keyed by field name."""
        flat: list[object] = []
        for name, kind in zip(self.names, self.types, strict=True):
            value = values[name]
            if kind.startswith("VECTOR"):
                flat.extend(value)  # type: ignore[arg-type]
            else:
                flat.append(value)
        return bytes([self.recipe_id]) + self.struct.pack(*flat)

    def unpack(self, body: bytes) -> dict[str, object]:
        """Field values of a data package body that starts after the recipe id byte."""
        flat = list(self.struct.unpack(body))
        values: dict[str, object] = {}
        for name, kind in zip(self.names, self.types, strict=True):
            count = int(TYPE_FORMATS[kind][0]) if TYPE_FORMATS[kind][0].isdigit() else 1
            if count > 1:
                values[name], flat = tuple(flat[:count]), flat[count:]
            else:
                values[name], flat = flat[0], flat[1:]
        return values


def packet(kind: int, payload: bytes = b"") -> bytes:
    """A whole packet: header and payload."""
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def split_packets(buffer: bytearray) -> list[tuple[int, bytes]]:
    """Take every complete packet off the front of ``buffer`` (which is consumed)."""
    out = []
    while len(buffer) >= HEADER.size:
        size, kind = HEADER.unpack_from(buffer)
        if size < HEADER.size:
            raise ValueError(f"RTDE packet with impossible size {size}")
        if len(buffer) < size:
            break
        out.append((kind, bytes(buffer[HEADER.size : size])))
        del buffer[:size]
    return out


def text_message(message: str, source: str = "fake_ur", level: int = 3) -> bytes:
    """A protocol-2 text message packet (level 3: info)."""
    m, s = message.encode()[:255], source.encode()[:255]
    return packet(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


def setup_reply(recipe_id: int, types: Sequence[str]) -> bytes:
    """The body of an output or input setup reply."""
    return bytes([recipe_id]) + ",".join(types).encode()
