"""The simulator's ground truth on the fleet's network, and its fault schedule.

:class:`TruthPublisher` publishes, from a :class:`simulator.runner.SimWorld` tick hook, every vehicle's true
pose and (when the scene is available) the simulated person's joints as one ``SimTruth`` on ``sim/truth``;
the demo records it to the flight folder's truth log. :func:`schedule_faults` arms the simulator-side fault
injections (a GPS jump, a parameter change) relative to the first orbit plan's start time. Both are wired by
``skycap sim`` (:mod:`simulator.cli`), the one simulator entry point.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from comms.transport import Transport
from shared_msgs import OrbitPlan, SimTruth, VehicleTruth, keys
from simulator.runner import SimWorld
from skycap.errors import SkycapError
from skycap.frames import quat_wxyz_from_R

log = logging.getLogger(__name__)

__all__ = ["PersonTruth", "TruthPublisher", "SimFaults", "schedule_faults"]


class PersonTruth:
    """The simulated person's part of a ``SimTruth`` (:class:`simulator.scene.person.PersonSim` with the default
    person, or the recorded motion of ``motion.file``: :class:`simulator.scene.person.BvhPerson`), or a still person
    of zeros when the scene is unavailable (it needs the motion clips). Shared by the built-in simulator's
    :class:`TruthPublisher` and PX4 SITL's :class:`simulator.px4_truth.SihTruthPublisher`. A ``motion`` file that
    cannot be played is an error (:class:`simulator.scene.person.PersonError`), not a silent default walk."""

    def __init__(self, enabled: bool = True, motion=None) -> None:
        self.person = None
        if enabled and motion is not None and motion.file:
            from simulator.scene.person import make_person

            self.person = make_person(None, motion)
        elif enabled:
            try:  # the scene is optional for the flight (it needs the motion clips)
                from simulator.scene.config import PersonConfig
                from simulator.scene.person import PersonSim

                self.person = PersonSim(PersonConfig())
            except Exception as e:
                log.warning("no simulated person (%s): truth carries the vehicles only", e)
        self._zeros = tuple(0.0 for _ in range(51))

    def fields(self, t_s: float) -> dict:
        """``SimTruth`` keyword arguments of the person at ``t_s`` (seconds since the simulation started)."""
        if self.person is None:
            return dict(person_joints_ned_m=self._zeros, person_root_ned_m=(0.0, 0.0, 0.0))
        return self.person.state_at(t_s).truth_fields()


class TruthPublisher:
    """Publishes ``SimTruth`` at ``rate_hz`` from the world's tick (vehicles, their gimbals, person).

    Each vehicle's gimbal angles are its simulated gimbal's true attitude; a vehicle without a gimbal
    (``gimbal.enabled = false``) reports ``gimbal_pitch_rad`` (a fixed camera pitch) and yaw 0."""

    def __init__(self, world: SimWorld, bus: Transport, fleet: str, rate_hz: float = 50.0,
                 gimbal_pitch_rad: float = 0.0, with_person: bool = True, motion=None) -> None:
        self.world, self.bus, self.gimbal_pitch_rad = world, bus, gimbal_pitch_rad
        self.key = keys.sim_key(fleet, keys.TRUTH)
        self.person = PersonTruth(with_person, motion)
        world.add_tick_hook(self.publish, rate_hz=rate_hz)

    def publish(self, t_ns: int, truths) -> None:
        vehicles = [VehicleTruth(drone_id=f"drone_{v.index + 1}", position_ned_m=tuple(map(float, v.position_ned_m)),
                                 velocity_ned_m_s=tuple(map(float, v.velocity_ned_m_s)),
                                 q_world_body=tuple(map(float, quat_wxyz_from_R(v.R_world_body))),
                                 gimbal_pitch_rad=self.gimbal_pitch_rad if v.gimbal_pitch_rad is None else
                                 float(v.gimbal_pitch_rad),
                                 gimbal_yaw_rad=0.0 if v.gimbal_yaw_rad is None else float(v.gimbal_yaw_rad))
                    for v in truths]
        self.bus.publish(self.key, SimTruth(header=SimTruth.make_header(keys.SIM, t_ns), vehicles=vehicles,
                                            **self.person.fields(self.world.t_s)))


@dataclass
class SimFaults:
    """Simulator-side fault injections, in seconds after the first orbit plan's start time.

    ``gps_jump``: (vehicle index, at_s, (north_m, east_m, down_m)) -- the vehicle's position estimate jumps.
    ``params``: [(vehicle index, at_s, name, value)] -- an autopilot parameter changes (e.g. COM_OBL_RC_ACT=4).
    """

    gps_jump: tuple[int, float, list[float]] | None = None
    params: list[tuple[int, float, str, float]] = field(default_factory=list)
    #: [(vehicle index, at_s, for_s)]: the vehicle's offboard MAVLink link carries nothing for for_s
    link_losses: list[tuple[int, float, float]] = field(default_factory=list)

    @classmethod
    def parse(cls, gps_jump: str | None, param_at: list[str], n_vehicles: int, known_param,
              link_loss: list[str] | None = None) -> SimFaults:
        """From the command line's ``INDEX,AT_S,N,E,D``, ``INDEX,AT_S,NAME,VALUE`` and ``INDEX,AT_S,FOR_S``
        texts."""
        out = cls()
        for text in link_loss or []:
            try:
                idx_s, at_s, for_s = text.split(",")
                out.link_losses.append((int(idx_s), float(at_s), float(for_s)))
                if not 0 <= out.link_losses[-1][0] < n_vehicles or not float(for_s) > 0:
                    raise ValueError
            except ValueError:
                raise SkycapError(f"--link-loss {text!r}: give INDEX,AT_S,FOR_S with INDEX < {n_vehicles} and "
                                  "FOR_S > 0") from None
        if gps_jump:
            try:
                idx_s, at_s, *off = gps_jump.split(",")
                out.gps_jump = (int(idx_s), float(at_s), [float(v) for v in off])
                if len(out.gps_jump[2]) != 3 or not 0 <= out.gps_jump[0] < n_vehicles:
                    raise ValueError
            except ValueError:
                raise SkycapError(f"--gps-jump {gps_jump!r}: give INDEX,AT_S,N,E,D with INDEX < {n_vehicles}") from None
        for text in param_at:
            try:
                idx_s, at_s, name, value = text.split(",")
                out.params.append((int(idx_s), float(at_s), name.strip(), float(value)))
                if not 0 <= out.params[-1][0] < n_vehicles or not known_param(name.strip()):
                    raise ValueError
            except ValueError:
                raise SkycapError(f"--param-at {text!r}: give INDEX,AT_S,NAME,VALUE with INDEX < {n_vehicles} and a "
                                  "known parameter name") from None
        return out

    @property
    def active(self) -> bool:
        return self.gps_jump is not None or bool(self.params) or bool(self.link_losses)


def schedule_faults(world: SimWorld, bus: Transport, fleet: str, faults: SimFaults) -> None:
    """Arm ``faults`` relative to the start time of the first orbit plan seen on the fleet's plan key
    (converted to simulation time when it arrives)."""
    if not faults.active:
        return
    pending: list[tuple[float, int, str, float]] = []
    armed = [False]

    def on_plan(rx) -> None:  # Zenoh thread: schedule once, in simulation time
        if armed[0]:
            return
        armed[0] = True
        t0_sim = world.t_s + (rx.msg.start_time_ns * 1e-9 - time.time())
        if faults.gps_jump is not None:
            i, at_s, off = faults.gps_jump
            world.vehicles[i].schedule_gps_jump(t0_sim + at_s, off)
            log.warning("FAULT: GPS jump of vehicle %d by %s m scheduled at sim t=%.1f s", i, off, t0_sim + at_s)
        pending.extend(sorted((t0_sim + at, i, name, v) for i, at, name, v in faults.params))
        for i, at_s, for_s in faults.link_losses:
            world.endpoints[i].schedule_link_loss(t0_sim + at_s, for_s)
            log.warning("FAULT: MAVLink link loss of vehicle %d for %.1f s scheduled at sim t=%.1f s", i, for_s,
                        t0_sim + at_s)

    def apply_params(t_ns: int, truths) -> None:  # simulation loop
        while pending and pending[0][0] <= world.t_s:
            _, i, name, v = pending.pop(0)
            world.vehicles[i].params.set(name, v)
            log.warning("FAULT schedule: vehicle %d parameter %s = %s at sim t=%.1f s", i, name, v, world.t_s)

    world.add_tick_hook(apply_params, rate_hz=50.0)
    bus.subscribe(keys.gcs_key(fleet, keys.PLAN), on_plan, OrbitPlan)


