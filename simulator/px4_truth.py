"""PX4 SITL (SIH) as the demo's simulator: SIH's true vehicle states as the fleet's ``SimTruth``, and the fault
schedule's parameter changes through PX4's shell.

``skycap sim --autopilot px4`` (:mod:`simulator.cli`) starts the PX4 instances (:class:`simulator.px4_sitl.Px4Sitl`)
and, with ``--fleet``, runs :class:`SihTruthPublisher` and :func:`schedule_px4_params`.

Truth: SIH sends each vehicle's true state (HIL_STATE_QUATERNION: geodetic position, attitude, velocity) at about
25 Hz, each vehicle on its own clock; :class:`simulator.px4_sitl.SihTruthReader` receives it. The publisher
**resamples** it at ``rate_hz`` on the receiving machine's wall clock (the clock of the agents' and cameras'
timestamps): each ``SimTruth`` carries every vehicle's newest sample, its position advanced with the sample's
true velocity from the sample's arrival to the publishing time (at most ~40 ms at SIH's 25 Hz; attitude as
received). Altitudes: SIH's ground is at ``SIH_LOC_H0`` (PX4's default 489.4 m AMSL), not at the world
origin's altitude; the world frame's down = 0 is the ground where the person stands, so each vehicle's down is
``-(altitude AMSL - ground altitude)`` with the ground altitude given (``ground_alt_amsl_m``, e.g. SIH_LOC_H0
read from PX4) or, when not given, each vehicle's altitude in its first sample (resting on the ground before
take-off). SIH has no gimbal: every vehicle reports the fixed ``gimbal_pitch_rad`` and yaw 0. The person is
the same :class:`simulator.truth.PersonTruth` as the built-in simulator's, on this publisher's own clock
(seconds since it started).
"""

from __future__ import annotations

import logging
import re
import threading
import time

import numpy as np

from comms.transport import Transport
from shared_msgs import OrbitPlan, SimTruth, VehicleTruth, keys
from simulator.px4_sitl import Px4Sitl, Px4SitlError, SihTruth, SihTruthReader
from simulator.truth import PersonTruth, SimFaults

log = logging.getLogger(__name__)

__all__ = ["SihTruthPublisher", "sih_to_vehicle_truth", "schedule_px4_params", "read_px4_param", "px4_param_name_ok"]

#: PX4 parameter names: upper-case letters, digits and '_', at most 16 characters
_PX4_PARAM_RE = re.compile(r"^[A-Z][A-Z0-9_]{0,15}$")


def px4_param_name_ok(name: str) -> bool:
    """Whether ``name`` is spelled as a PX4 parameter (PX4 itself says whether it exists when it is set)."""
    return bool(_PX4_PARAM_RE.match(name))


def read_px4_param(sitl: Px4Sitl, k: int, name: str) -> float | None:
    """A parameter's value from PX4's shell (``param show NAME``), None when it cannot be read."""
    try:
        text = sitl.shell(k, f"param show {name}")
    except (Px4SitlError, OSError) as e:
        log.warning("cannot read %s from PX4 instance %d: %s", name, sitl.instance(k), e)
        return None
    m = re.search(rf"{re.escape(name)}\s*(?:\[[^\]]*\])?\s*:\s*(-?[0-9.]+(?:[eE][-+]?\d+)?)", text)
    return float(m.group(1)) if m else None


def sih_to_vehicle_truth(drone_id: str, s: SihTruth, ground_alt_amsl_m: float, origin_alt_m: float,
                         gimbal_pitch_rad: float, dt_s: float = 0.0) -> VehicleTruth:
    """One vehicle's ``VehicleTruth`` in the world frame (down = 0 on the ground at ``ground_alt_amsl_m``) from a
    SIH sample converted about an origin at ``origin_alt_m`` (:class:`SihTruthReader`), its position advanced by
    ``dt_s`` seconds with its velocity."""
    p = np.asarray(s.position_ned_m, dtype=float).copy()
    p[2] += ground_alt_amsl_m - origin_alt_m  # reader: down about the origin's altitude -> about the ground
    v = np.asarray(s.velocity_ned_m_s, dtype=float)
    p = p + v * dt_s
    return VehicleTruth(drone_id=drone_id, position_ned_m=tuple(map(float, p)), velocity_ned_m_s=tuple(map(float, v)),
                        q_world_body=tuple(map(float, s.q_world_body_wxyz)), gimbal_pitch_rad=float(gimbal_pitch_rad),
                        gimbal_yaw_rad=0.0)


class SihTruthPublisher:
    """Publishes ``SimTruth`` (vehicles ``drone_1..N`` from SIH's truth on UDP ``ports``, and the person) on the
    fleet's ``sim/truth`` at ``rate_hz`` from a background thread (see the module doc for the resampling and the
    altitudes). :meth:`close` stops it."""

    def __init__(self, bus: Transport, fleet: str, ports: list[int], origin: tuple[float, float, float],
                 rate_hz: float = 50.0, gimbal_pitch_rad: float = 0.0, ground_alt_amsl_m: float | None = None,
                 with_person: bool = True, drone_ids: list[str] | None = None, motion=None) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate_hz={rate_hz}: give a positive publishing rate")
        self.bus, self.rate_hz, self.gimbal_pitch_rad = bus, float(rate_hz), float(gimbal_pitch_rad)
        self.origin = tuple(float(x) for x in origin)
        self.key = keys.sim_key(fleet, keys.TRUTH)
        self.drone_ids = list(drone_ids) if drone_ids else [f"drone_{k + 1}" for k in range(len(ports))]
        if len(self.drone_ids) != len(ports):
            raise ValueError(f"{len(self.drone_ids)} drone ids for {len(ports)} truth ports")
        #: per vehicle, the ground's altitude AMSL (None until the first sample when not given)
        self.ground_alt_amsl_m: list[float | None] = [ground_alt_amsl_m] * len(ports)
        self.person = PersonTruth(with_person, motion)
        self.published = 0
        self._t0_s = time.monotonic()
        self.reader = SihTruthReader(ports, self.origin, on_truth=self._on_sample)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sih-truth-publisher", daemon=True)
        self._thread.start()

    def _on_sample(self, k: int, s: SihTruth) -> None:  # reader thread
        if self.ground_alt_amsl_m[k] is None:
            self.ground_alt_amsl_m[k] = s.altitude_amsl_m
            log.info("%s: ground at %.3f m AMSL (its first SIH sample, on the ground)", self.drone_ids[k],
                     s.altitude_amsl_m)

    def message(self, t_ns: int) -> SimTruth | None:
        """The ``SimTruth`` at wall time ``t_ns`` (None until every vehicle sent a sample)."""
        latest = self.reader.latest()
        if any(s is None for s in latest) or any(g is None for g in self.ground_alt_amsl_m):
            return None
        vehicles = [sih_to_vehicle_truth(d, s, g, self.origin[2], self.gimbal_pitch_rad,
                                         dt_s=max(0.0, (t_ns - s.t_received_ns) * 1e-9))
                    for d, s, g in zip(self.drone_ids, latest, self.ground_alt_amsl_m)]
        return SimTruth(header=SimTruth.make_header(keys.SIM, t_ns), vehicles=vehicles,
                        **self.person.fields(time.monotonic() - self._t0_s))

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        t_next = time.monotonic()
        while not self._stop.is_set():
            msg = self.message(time.time_ns())
            if msg is not None:
                self.bus.publish(self.key, msg)
                self.published += 1
            t_next += period
            delay = t_next - time.monotonic()
            if delay < -period:  # fell behind (a loaded machine): do not burst to catch up
                t_next = time.monotonic()
                delay = 0.0
            self._stop.wait(max(0.0, delay))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.reader.close()


def schedule_px4_params(sitl: Px4Sitl, bus: Transport, fleet: str, faults: SimFaults) -> threading.Event:
    """Set ``faults.params`` (vehicle index, seconds after the first orbit plan's start time, name, value) on the
    PX4 instances through PX4's shell (``param set``) at their times. A GPS jump cannot be injected into PX4 (the
    caller refuses it). Returns the event that cancels what is still pending."""
    cancel = threading.Event()
    if not faults.params:
        return cancel
    armed = [False]

    def run(t0_s: float) -> None:
        for at_s, i, name, value in sorted((at, i, name, v) for i, at, name, v in faults.params):
            if cancel.wait(max(0.0, t0_s + at_s - time.time())):
                return
            try:
                sitl.shell(i, f"param set {name} {value:g}")
                log.warning("FAULT schedule: vehicle %d (PX4 instance %d) parameter %s = %g, %.1f s after the plan's "
                            "start", i, sitl.instance(i), name, value, time.time() - t0_s)
            except (Px4SitlError, OSError) as e:
                log.error("FAULT schedule: PX4 instance %d: param set %s %g failed: %s", sitl.instance(i), name,
                          value, e)

    def on_plan(rx) -> None:  # Zenoh thread: schedule once
        if armed[0]:
            return
        armed[0] = True
        threading.Thread(target=run, args=(rx.msg.start_time_ns * 1e-9,), name="px4-param-schedule",
                         daemon=True).start()

    bus.subscribe(keys.gcs_key(fleet, keys.PLAN), on_plan, OrbitPlan)
    return cancel
