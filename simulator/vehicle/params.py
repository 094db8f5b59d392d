"""The small PX4 parameter set the simulated autopilot exposes over the MAVLink PARAM protocol.

Values are kept with their MAVLink type; :func:`encode_param_value` / :func:`decode_param_value`
implement the *bytewise* encoding PX4 uses (an INT32 travels as the float whose bits are the int;
``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE`` is advertised in AUTOPILOT_VERSION).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Callable

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9


@dataclass
class Param:
    name: str
    value: float | int
    type: int  # MAV_PARAM_TYPE_*


def encode_param_value(value: float | int, param_type: int) -> float:
    """The float carried in PARAM_VALUE.param_value / PARAM_SET.param_value (bytewise encoding)."""
    if param_type == MAV_PARAM_TYPE_INT32:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    return float(value)


def decode_param_value(wire_value: float, param_type: int) -> float | int:
    """Inverse of :func:`encode_param_value`."""
    if param_type == MAV_PARAM_TYPE_INT32:
        return struct.unpack("<i", struct.pack("<f", wire_value))[0]
    return float(wire_value)


class ParamStore:
    """Ordered name -> :class:`Param`; ``on_change(name, value)`` runs after every accepted set."""

    def __init__(self, params: list[Param], on_change: Callable[[str, float | int], None] | None = None):
        self._params = {p.name: p for p in params}
        self._order = [p.name for p in params]
        self.on_change = on_change

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, name: str) -> bool:
        return name in self._params

    def __getitem__(self, name: str) -> float | int:
        return self._params[name].value

    def get(self, name: str) -> Param | None:
        return self._params.get(name)

    def index_of(self, name: str) -> int:
        return self._order.index(name)

    def by_index(self, index: int) -> Param | None:
        return self._params[self._order[index]] if 0 <= index < len(self._order) else None

    def all(self) -> list[Param]:
        return [self._params[n] for n in self._order]

    def set(self, name: str, value: float | int) -> Param | None:
        """Set a known parameter (value already decoded); returns it, or None if unknown / not finite."""
        p = self._params.get(name)
        if p is None:
            return None
        if p.type == MAV_PARAM_TYPE_INT32:
            p.value = int(value)
        else:
            if not math.isfinite(float(value)):
                return None
            p.value = float(value)
        if self.on_change is not None:
            self.on_change(name, p.value)
        return p
