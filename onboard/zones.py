"""The plan's geofence and keep-out zones on board: plan checks and the setpoint clamp. Pure logic, no I/O.

The ground station sends them with the plan (:class:`shared_msgs.OrbitPlan` version 2: ``geofence``, a vertical
cylinder with an altitude band, and ``keepout_zones``, vertical cylinders of infinite height), in the flight's
local NED world frame: north / east metres from the flight's origin (the frame of the plan's ``center_ned_m``),
heights above the take-off ground. Every agent enforces them three ways:

* :func:`plan_zone_violation` -- the agent refuses (its :class:`~shared_msgs.CommandAck` says why) a plan whose
  orbit circle leaves the fence or crosses a zone, whose altitude is outside the fence's band, or (a tracking
  formation, or an orbit that does not turn) whose slot at the plan's centre lies outside the fence or in a zone;
* track mode: the formation MPC gets the fence (as its inscribed polygon, :func:`fence_polygon_ne`) and the
  zones (as obstacles) as constraints, and its failsafe brakes and holds when a fence breach is predicted;
* :func:`clamp_setpoint` -- every streamed setpoint (orbit and track mode) that would lie in a zone or outside the
  fence is moved to the zone's / fence's edge (less ``margin_m``) with its velocity component across that edge
  removed, and the agent warns once per zone (a track-mode person walking next to a zone, an orbit's approach
  path crossing one).

Heights: only the fence's ceiling is clamped; its floor is checked on the plan (the drone climbs from the ground
to the plan's altitude, so a floor clamp would only ask it for a jump).
"""

from __future__ import annotations

import math

import numpy as np

from shared_msgs import GeofenceZone, KeepOutZone, OrbitPlan

__all__ = ["fence_polygon_ne", "plan_zone_violation", "clamp_setpoint", "zone_label", "slot_point_ne"]


def zone_label(z: KeepOutZone, i: int) -> str:
    return f"keep-out zone {z.name!r}" if z.name else f"keep-out zone #{i + 1}"


def fence_polygon_ne(fence: GeofenceZone, sides: int = 16) -> tuple[tuple[float, float], ...]:
    """The fence circle's inscribed regular polygon (north_m, east_m) vertices: convex, inside the circle (the
    formation MPC takes convex polygons)."""
    cn, ce = fence.center_ne_m
    return tuple((cn + fence.radius_m * math.cos(2 * math.pi * k / sides),
                  ce + fence.radius_m * math.sin(2 * math.pi * k / sides)) for k in range(sides))


def slot_point_ne(plan: OrbitPlan, drone_id: str) -> tuple[float, float]:
    """Where ``drone_id``'s slot is at the plan's start (north_m, east_m)."""
    a = plan.phase_offset_rad[drone_id]
    return (plan.center_ned_m[0] + plan.radius_m * math.cos(a), plan.center_ned_m[1] + plan.radius_m * math.sin(a))


def plan_zone_violation(plan: OrbitPlan, drone_id: str) -> str | None:
    """Why ``drone_id`` must refuse ``plan`` for its fence or keep-out zones, or None (no fence / zones: None).

    An orbit that turns (``angular_speed_rad_s`` > 0) sweeps its whole circle: the circle must stay inside the
    fence and miss every zone. A tracking formation (``mode = "track"``) or a still orbit: this drone's slot at the
    plan's centre (the person's start guess) must be inside the fence and outside every zone, and the centre itself
    inside the fence."""
    cn, ce = plan.center_ned_m[0], plan.center_ned_m[1]
    sweeps = plan.mode != "track" and plan.angular_speed_rad_s > 0
    f = plan.geofence
    if f is not None:
        vals = [*f.center_ne_m, f.radius_m, f.min_altitude_m, f.max_altitude_m]
        if not all(math.isfinite(v) for v in vals):
            return "bad field geofence: non-finite number"
        if f.radius_m <= 0 or not 0 <= f.min_altitude_m < f.max_altitude_m:
            return (f"bad field geofence: radius_m={f.radius_m} must be > 0 and 0 <= min_altitude_m "
                    f"({f.min_altitude_m}) < max_altitude_m ({f.max_altitude_m})")
        if not f.min_altitude_m <= plan.altitude_m <= f.max_altitude_m:
            return (f"geofence: altitude_m={plan.altitude_m:g} is outside the fence's band "
                    f"{f.min_altitude_m:g}..{f.max_altitude_m:g} m")
        fn, fe = f.center_ne_m
        d_centre = math.hypot(cn - fn, ce - fe)
        if sweeps and d_centre + plan.radius_m > f.radius_m:
            return (f"geofence: the orbit (centre {cn:g}, {ce:g} m, radius {plan.radius_m:g} m) leaves the fence "
                    f"(radius {f.radius_m:g} m around {fn:g}, {fe:g})")
        if d_centre > f.radius_m:
            return f"geofence: the plan's centre ({cn:g}, {ce:g} m) is outside the fence ({f.radius_m:g} m)"
        if not sweeps:
            sn, se = slot_point_ne(plan, drone_id)
            if math.hypot(sn - fn, se - fe) > f.radius_m:
                return (f"geofence: {drone_id}'s slot ({sn:.1f}, {se:.1f} m) is outside the fence "
                        f"({f.radius_m:g} m around {fn:g}, {fe:g})")
    for i, z in enumerate(plan.keepout_zones):
        label = zone_label(z, i)
        if not all(math.isfinite(v) for v in (z.north_m, z.east_m, z.radius_m)) or z.radius_m <= 0:
            return f"bad field keepout_zones[{i}]: {label} needs finite numbers and radius_m > 0"
        d = math.hypot(cn - z.north_m, ce - z.east_m)
        if sweeps:
            if abs(d - plan.radius_m) < z.radius_m:
                return (f"{label}: the orbit (centre {cn:g}, {ce:g} m, radius {plan.radius_m:g} m) passes through "
                        f"it ({z.radius_m:g} m around {z.north_m:g}, {z.east_m:g})")
        else:
            sn, se = slot_point_ne(plan, drone_id)
            if math.hypot(sn - z.north_m, se - z.east_m) < z.radius_m:
                return (f"{label}: {drone_id}'s slot ({sn:.1f}, {se:.1f} m) is inside it ({z.radius_m:g} m around "
                        f"{z.north_m:g}, {z.east_m:g})")
    return None


def clamp_setpoint(position_ned_m, velocity_ned_m_s, fence: GeofenceZone | None, zones: list[KeepOutZone],
                   margin_m: float = 0.5) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(position, velocity, what was clamped): a setpoint moved out of every keep-out zone (to its edge +
    ``margin_m``, radially) and inside the fence (to its edge - ``margin_m``, and under its ceiling), the velocity
    component across each edge it was moved to removed. ``what`` names each zone / the fence that clamped it
    (empty: the setpoint was fine and is returned unchanged)."""
    p = np.array(position_ned_m, dtype=float)
    v = np.array(velocity_ned_m_s, dtype=float)
    what: list[str] = []
    for i, z in enumerate(zones):
        d = p[:2] - (z.north_m, z.east_m)
        dist = float(np.hypot(*d))
        r = z.radius_m + margin_m
        if dist < r:
            n = d / dist if dist > 1e-6 else np.array([1.0, 0.0])
            p[:2] = (z.north_m, z.east_m) + n * r
            inward = float(v[:2] @ n)
            if inward < 0:
                v[:2] -= inward * n
            what.append(zone_label(z, i))
    if fence is not None:
        c = np.asarray(fence.center_ne_m, dtype=float)
        d = p[:2] - c
        dist = float(np.hypot(*d))
        r = max(0.0, fence.radius_m - margin_m)
        if dist > r:
            n = d / dist
            p[:2] = c + n * r
            outward = float(v[:2] @ n)
            if outward > 0:
                v[:2] -= outward * n
            what.append("geofence")
        ceiling_down = -fence.max_altitude_m
        if p[2] < ceiling_down:
            p[2] = ceiling_down
            v[2] = max(v[2], 0.0)
            what.append("geofence ceiling")
    return p, v, what
