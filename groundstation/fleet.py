"""The fleet client: what the ground station (CLI now, the Qt app later) uses to talk to the drones.

    with FleetClient.open("f1") as fleet:            # joins Zenoh, starts the ground-station heartbeat
        plan = fleet.send_plan(make_orbit_plan(["drone_1", "drone_2"], radius_m=8, altitude_m=6))
        acks = fleet.command("takeoff", wait_s=5)    # {drone_id: CommandAck}
        fleet.wait_until(lambda f: all(s.landed_state == "in_air" for s in f.states.values()), 30)
        print(fleet.table())

Everything received is kept: latest :class:`~shared_msgs.VehicleState` and
:class:`~shared_msgs.Health` per drone, every :class:`~shared_msgs.CommandAck`, who is alive.
Thread-safe (Zenoh callbacks fill it; any thread reads it).
"""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from typing import Callable, Iterable

from shared_msgs import Command, CommandAck, GeofenceZone, Health, KeepOutZone, OrbitPlan, VehicleState, keys
from skycap.errors import SkycapError
from comms.transport import Transport, TransportConfig
from onboard.config import SafetyConfig
from onboard.mission import validate_plan
from onboard.orbit import evenly_spaced_phases

log = logging.getLogger(__name__)

__all__ = ["FleetClient", "FleetError", "check_plan", "make_orbit_plan"]


class FleetError(SkycapError):
    """A fleet operation that did not get the answers it needed."""


def make_orbit_plan(
    drone_ids: Iterable[str],
    center_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    radius_m: float = 8.0,
    altitude_m: float = 6.0,
    angular_speed_rad_s: float = 0.15,
    direction: int = 1,
    start_in_s: float = 0.0,
    first_phase_rad: float = 0.0,
    min_separation_m: float = 3.0,
    max_speed_m_s: float = 5.0,
    gimbal_pitch_rad: float | None = None,
    plan_id: str | None = None,
    phase_offset_rad: dict[str, float] | None = None,
    mode: str = "",
    geofence: GeofenceZone | None = None,
    keepout_zones: Iterable[KeepOutZone] = (),
) -> OrbitPlan:
    """An :class:`OrbitPlan` with the drones evenly spaced (in the given order) and a shared start time
    ``start_in_s`` from now (0 = each drone starts when it receives it).

    ``mode``: "orbit", "track" (a tracking formation: ``center_ned_m`` is the person's start guess, ``radius_m`` /
    ``altitude_m`` the stand-off, no turning) or "" (each agent flies it in its own mode); ``geofence`` and
    ``keepout_zones`` travel with the plan and are enforced by the agents (and checked here first)."""
    if mode not in ("", "orbit", "track"):
        raise FleetError(f"plan mode {mode!r}: use 'orbit', 'track' or '' (each agent's own mode)")

    ids = list(drone_ids)
    if not ids:
        raise FleetError("an orbit plan needs at least one drone id (e.g. drone_1)")
    dup = sorted({d for d in ids if ids.count(d) > 1})
    if dup:
        raise FleetError(f"drone {', '.join(dup)} named more than once in the plan's drones {ids}: one slot per drone")
    bad_id = [d for d in ids if not keys.valid_segment(d)]
    if bad_id:
        raise FleetError(f"drone id {bad_id[0]!r}: letters, digits, '_' or '-' only (e.g. drone_1)")
    start_ns = time.time_ns() + int(start_in_s * 1e9) if start_in_s > 0 else 0
    plan = OrbitPlan(
        header=OrbitPlan.make_header(keys.GCS),
        plan_id=plan_id or f"plan-{uuid.uuid4().hex[:8]}",
        center_ned_m=tuple(float(x) for x in center_ned_m),
        radius_m=float(radius_m),
        altitude_m=float(altitude_m),
        angular_speed_rad_s=float(angular_speed_rad_s),
        direction=int(direction),
        start_time_ns=start_ns,
        phase_offset_rad=phase_offset_rad if phase_offset_rad is not None else evenly_spaced_phases(ids, first_phase_rad),
        gimbal_pitch_rad=gimbal_pitch_rad,
        min_separation_m=float(min_separation_m),
        max_speed_m_s=float(max_speed_m_s),
        mode=mode,
        geofence=geofence,
        keepout_zones=list(keepout_zones),
    )
    check_plan(plan)
    return plan


def check_plan(plan: OrbitPlan, safety: SafetyConfig | None = None) -> None:
    """Refuse, before it is sent, a plan the drones would refuse: the agents' own check
    (:func:`onboard.mission.validate_plan`: finite values, positive radius, altitude inside the band, slot speed,
    slot separation, gimbal pitch) for every slot, against ``safety`` (default: the agents' default limits).
    The plan's geofence and keep-out zones are checked the agents' way too (:func:`onboard.zones.plan_zone_violation`).
    A :class:`FleetError` names the field and the rule."""
    safety = safety or SafetyConfig()
    if not plan.phase_offset_rad:
        raise FleetError(f"plan {plan.plan_id}: no drone slots (phase_offset_rad is empty)")
    if plan.direction not in (-1, 1):
        raise FleetError(f"plan {plan.plan_id}: bad field direction={plan.direction}: use 1 or -1")
    for drone_id in plan.phase_offset_rad:
        reason = validate_plan(plan, drone_id, safety, plan.header.t_sent_ns)
        if reason is not None:
            raise FleetError(f"plan {plan.plan_id} not sent: {reason}")


class FleetClient:
    """The ground station's view of and handle on the fleet ``fleet`` over a :class:`~comms.transport.Transport`."""

    def __init__(self, fleet: str, bus, heartbeat_hz: float = 2.0, sender_id: str = keys.GCS):
        self.fleet = fleet
        self.bus = bus
        self.sender_id = sender_id
        self._lock = threading.RLock()  # re-entrant: predicates of wait_until may call drones()/table()
        self.states: dict[str, VehicleState] = {}
        self.healths: dict[str, Health] = {}
        self.acks: list[CommandAck] = []
        self.alive: set[str] = set()
        #: monotonic time of the last state or health received from each drone (link age, staleness)
        self.last_rx_s: dict[str, float] = {}
        self._cv = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._hb_thread: threading.Thread | None = None
        self.heartbeat_hz = heartbeat_hz
        self._subs = [
            bus.subscribe(keys.all_drones_key(fleet, keys.STATE), self._on_state, VehicleState),
            bus.subscribe(keys.all_drones_key(fleet, keys.HEALTH), self._on_health, Health),
            bus.subscribe(keys.all_drones_key(fleet, keys.ACK), self._on_ack, CommandAck),
            bus.watch_presence(keys.all_drones_key(fleet, "alive"), self._on_join, self._on_leave),
        ]
        try:
            bus.declare_alive(keys.alive_key(fleet, keys.GCS))
        except Exception as e:
            log.debug("no liveliness token: %s", e)
        if heartbeat_hz > 0:
            self.start_heartbeat()

    @classmethod
    def open(cls, fleet: str, transport_cfg=None, heartbeat_hz: float = 2.0) -> "FleetClient":

        bus = Transport.open(transport_cfg or TransportConfig(), node_id="gcs")
        client = cls(fleet, bus, heartbeat_hz)
        client._own_bus = True
        return client

    # --- inputs (Zenoh threads) -------------------------------------------------------------------
    def _node(self, key: str) -> str:
        return keys.parse_key(key)[1]

    def _on_state(self, rx) -> None:
        node = self._node(rx.key)
        with self._cv:
            self.states[node] = rx.msg
            self.last_rx_s[node] = time.monotonic()
            self._cv.notify_all()

    def _on_health(self, rx) -> None:
        node = self._node(rx.key)
        if node == keys.GCS:
            return
        with self._cv:
            self.healths[node] = rx.msg
            self.last_rx_s[node] = time.monotonic()
            self._cv.notify_all()

    def _on_ack(self, rx) -> None:
        with self._cv:
            self.acks.append(rx.msg)
            self._cv.notify_all()
        a = rx.msg
        (log.warning if a.result in ("refused", "failed") else log.info)(
            "%s: %s %s%s", a.header.sender_id, a.result, a.command_id, f" ({a.reason})" if a.reason else "")

    def _on_join(self, key: str) -> None:
        with self._cv:
            self.alive.add(self._node(key))
            self._cv.notify_all()

    def _on_leave(self, key: str) -> None:
        with self._cv:
            self.alive.discard(self._node(key))
            self._cv.notify_all()

    # --- heartbeat --------------------------------------------------------------------------------
    def heartbeat(self) -> None:
        """Publish one ground-station heartbeat (agents land when these stop)."""
        self.bus.publish(keys.gcs_key(self.fleet, keys.HEALTH),
                         Health(header=Health.make_header(self.sender_id), role="ground_station", state="online"))

    def start_heartbeat(self) -> None:
        if self._hb_thread is not None:
            return
        self._stop.clear()

        def loop():
            while not self._stop.wait(1.0 / self.heartbeat_hz):
                try:
                    self.heartbeat()
                except Exception as e:
                    if not self._stop.is_set():
                        log.warning("heartbeat failed: %s", e)

        self.heartbeat()
        self._hb_thread = threading.Thread(target=loop, name="gcs-heartbeat", daemon=True)
        self._hb_thread.start()

    def stop_heartbeat(self) -> None:
        self._stop.set()
        if self._hb_thread is not None:
            self._hb_thread.join(timeout=2.0)
            self._hb_thread = None

    # --- outputs ----------------------------------------------------------------------------------
    def send_plan(self, plan: OrbitPlan) -> OrbitPlan:
        """Check ``plan`` (:func:`check_plan`) and publish it (latched: agents starting later query it)."""
        check_plan(plan)
        self.bus.publish(keys.gcs_key(self.fleet, keys.PLAN), plan, latch=True)
        log.info("plan %s (%s) sent: radius %.1f m, altitude %.1f m, %.3f rad/s, %s, %d keep-out zone(s), slots %s",
                 plan.plan_id, plan.mode or "agents' mode", plan.radius_m, plan.altitude_m, plan.angular_speed_rad_s,
                 "fenced" if plan.geofence else "no fence", len(plan.keepout_zones),
                 {k: round(math.degrees(v)) for k, v in plan.phase_offset_rad.items()})
        return plan

    def send_command(self, action: str, target: str = "*", params: dict[str, float] | None = None,
                     max_age_s: float = 5.0) -> Command:
        cmd = Command(header=Command.make_header(self.sender_id), command_id=f"{action}-{uuid.uuid4().hex[:8]}",
                      target=target, action=action, params=dict(params or {}), max_age_s=max_age_s)
        self.bus.publish(keys.gcs_key(self.fleet, keys.CMD), cmd)
        return cmd

    def command(self, action: str, target: str = "*", params: dict[str, float] | None = None,
                wait_s: float = 3.0, expect: Iterable[str] | None = None,
                results: tuple[str, ...] = ("accepted", "refused", "failed", "completed")) -> dict[str, CommandAck]:
        """Send a command and wait up to ``wait_s`` for one ack in ``results`` from each expected drone
        (``expect``; default: the target, or every drone alive for "*"). Returns {drone_id: ack}."""
        if expect is None:
            expect = [target] if target != "*" else self.drones()
        expect = list(expect)
        if not expect:
            raise FleetError(f"'{action}' not sent: no drone of fleet {self.fleet!r} is present (check the fleet id, "
                             "that the agents run, and that they and this client reach the same Zenoh endpoint)")
        cmd = self.send_command(action, target, params)
        return self.wait_acks(cmd.command_id, expect, wait_s, results)

    def wait_acks(self, command_id: str, expect: Iterable[str], wait_s: float,
                  results: tuple[str, ...] = ("accepted", "refused", "failed", "completed")) -> dict[str, CommandAck]:
        expect = set(expect)
        t_end = time.monotonic() + wait_s
        with self._cv:
            while True:
                got = {a.header.sender_id: a for a in self.acks if a.command_id == command_id and a.result in results}
                if expect <= set(got) or time.monotonic() >= t_end:
                    return got
                self._cv.wait(timeout=max(0.0, min(0.2, t_end - time.monotonic())))

    def wait_until(self, predicate: Callable[["FleetClient"], bool], timeout_s: float, what: str = "") -> bool:
        """Wait until ``predicate(self)`` holds (re-checked on every update); False on timeout."""
        t_end = time.monotonic() + timeout_s
        with self._cv:
            while not predicate(self):
                left = t_end - time.monotonic()
                if left <= 0:
                    if what:
                        log.warning("timed out after %.0f s waiting for %s", timeout_s, what)
                    return False
                self._cv.wait(timeout=min(0.2, left))
        return True

    # --- views ------------------------------------------------------------------------------------
    def drones(self) -> list[str]:
        """Ids of the agents present: alive, or heard from (an agent health report) when not yet alive."""
        with self._lock:
            agents = {d for d, h in self.healths.items() if h.role == "agent"}
            return sorted(agents | (self.alive & set(self.states)))

    def table(self) -> str:
        """One line per drone: state machine, mode, position, speed, battery, rates."""
        with self._lock:
            ids = sorted(set(self.states) | set(self.healths) | (self.alive - {keys.GCS, keys.SIM}))
            rows = ["drone      state     mode         armed  north_m  east_m  alt_m  speed  batt  setpt_hz  state_hz"]
            for d in ids:
                s, h = self.states.get(d), self.healths.get(d)
                mode = s.flight_mode if s else "-"
                if s:
                    n, e, dn = s.position_ned_m
                    sp = math.hypot(*s.velocity_ned_m_s)
                    pos = f"{n:7.1f} {e:7.1f} {-dn:6.1f} {sp:6.1f} {100 * s.battery_remaining_frac:4.0f}%"
                else:
                    pos = "      -       -      -      -     -"
                rates = h.rates_hz if h else {}
                rows.append(f"{d:10s} {(h.state if h else '-'):9s} {mode:12s} {str(bool(s and s.armed)):6s} {pos} "
                            f"{rates.get('setpoint', 0):8.1f}  {rates.get('state', 0):8.1f}")
            return "\n".join(rows)

    def close(self) -> None:
        self.stop_heartbeat()
        for s in self._subs:
            try:
                s.close()
            except Exception:
                pass
        if getattr(self, "_own_bus", False):
            self.bus.close()

    def __enter__(self) -> "FleetClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
