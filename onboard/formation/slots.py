"""Formation slots: the angle of each drone around the person.

Equal spacing (``2 pi / n``) among the drones present, rotated to where the drones already are (so that a
re-spacing after a teammate is lost moves everyone as little as possible and keeps their order around the
person), or the operator's chosen angles. Deterministic in its inputs, so every drone computes the same
assignment from the same shared positions.
"""

from __future__ import annotations

import math

import numpy as np

from skycap.errors import SkycapError

__all__ = ["assign_slot_angles", "SlotError"]


class SlotError(SkycapError, ValueError):
    """Bad input to the slot assignment."""


def assign_slot_angles(
    drone_ids: list[str],
    person_ned_m: np.ndarray,
    positions_ned_m: dict[str, np.ndarray] | None = None,
    operator_angles_rad: dict[str, float] | None = None,
    base_angle_rad: float = 0.0,
) -> dict[str, float]:
    """Slot angle (rad, from north toward east, in [-pi, pi)) per drone id.

    Args:
        drone_ids: the drones present.
        person_ned_m: (3,) the person (only north/east are used).
        positions_ned_m: current positions per id; drones without one are placed after the others in id order.
        operator_angles_rad: if it covers every present drone, these angles are used as given.
        base_angle_rad: the first slot's angle when no positions are known.
    """
    ids = sorted(set(drone_ids))
    if not ids:
        return {}
    if operator_angles_rad and all(i in operator_angles_rad for i in ids):
        out = {i: float(operator_angles_rad[i]) for i in ids}
        if not all(math.isfinite(a) for a in out.values()):
            raise SlotError("operator slot angles must be finite (radians)")
        return {i: float((a + math.pi) % (2 * math.pi) - math.pi) for i, a in out.items()}
    n = len(ids)
    step = 2 * math.pi / n
    c = np.asarray(person_ned_m, dtype=float)[:2]
    positions_ned_m = positions_ned_m or {}
    known = [i for i in ids if i in positions_ned_m and np.all(np.isfinite(positions_ned_m[i]))]
    if not known:
        order = ids
        base = base_angle_rad
    else:
        bearing = {}
        for i in known:
            d = np.asarray(positions_ned_m[i], dtype=float)[:2] - c
            bearing[i] = math.atan2(d[1], d[0])
        # order around the person, starting from the known drone with the smallest bearing
        order = sorted(known, key=lambda i: (bearing[i], i)) + [i for i in ids if i not in bearing]
        # rotation minimising the squared angular displacement of the known drones (circular mean)
        s = sum(math.sin(bearing[i] - step * k) for k, i in enumerate(order) if i in bearing)
        co = sum(math.cos(bearing[i] - step * k) for k, i in enumerate(order) if i in bearing)
        base = math.atan2(s, co) if (s * s + co * co) > 1e-12 else base_angle_rad
    return {i: float(((base + step * k) + math.pi) % (2 * math.pi) - math.pi) for k, i in enumerate(order)}
