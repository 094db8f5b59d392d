"""``skycap demo``: a full simulated flight, headless: N drones orbit the person, then the flight is summarised.

    skycap demo                                        # 3 drones, 60 s of orbit, into a new flights/demo-<time>/
    skycap demo --drones 2 --duration 20 --out /tmp/f --set orbit.radius_m=6
    skycap demo --set rtk=false                        # GPS-grade position estimate (m-level bias) instead of RTK
    skycap demo --mode track --out flights/track       # active capture: find and follow the person
    skycap demo --mode track --set faults.drop_prob=0.3 --set 'faults.kill_agent="drone_3"'   # under faults

    skycap demo --autopilot px4 --drones 2             # the same on real PX4 SITL (SIH) from ../shared/px4-sitl
    skycap demo --sorties 2                            # take off, orbit, land twice without restarting anything
    skycap demo --motion cmu/005/005_10.bvh                          # the person performs a recorded motion

``--motion FILE.bvh`` (``motion.*``, :class:`simulator.scene.person.PersonMotionConfig`): the simulated person
performs that recorded motion (any CMU-style BVH: rig, axes and unit detected, what was assumed logged) instead of
the default walk with stops, placed at the orbit's centre on the ground from the simulation's start, looped
(``motion.end = "loop"``, each seam cross-faded) or held at its last frame (``"clamp"``). The file is read before
anything starts (a missing file, one without the needed joints or of an unknown unit is a clear error);
``config.toml`` names it with its sha256 (``motion.file``, ``motion.sha256``) and ``summary.json`` under
``motion`` (file, sha256, rig, frames, unit and height assumed, ground, loop/clamp and a note of how often it
played over the flight).

``--autopilot px4``: the vehicles are real PX4 SITL instances with PX4's SIH simulator (``--px4-dir DIR``,
default ``../shared/px4-sitl`` beside the checkout or ``$SKYCAP_PX4_SITL``; refused with a clear error when it
is absent), started by ``skycap sim --autopilot px4`` (:mod:`simulator.px4_truth`): instances
``px4_first_instance`` .. +N-1, instance i on MAVLink UDP 14540 + i (``mavlink_base`` does not apply), each
drone's home under its orbit slot. The truth (rendered by the cameras, recorded to ``truth.mcap``, the
reference of every orbit figure in the summary) is SIH's true state, altitudes above SIH's ground, camera pitch
fixed (SIH has no gimbal). The estimate is PX4's EKF2 on SIH's sensors: ``rtk`` and the built-in simulator's
``sim_set`` (estimator, ports) do not apply (only ``origin.*`` / ``vehicles.*`` are accepted), a GPS jump is
refused, the kill-agent fault's parameter change goes through PX4's shell. ``summary.json`` names the
autopilot under ``autopilot`` (kind, PX4 folder, version, instances).

``--sorties N``: after landing, wait ``sortie_pause_s``, take off again, fly a new orbit plan, land; N times.
The agents keep running and recording (their ``drone_<i>.s001.mcap`` holds every sortie: a file sortie is an
agent start); ``plan.json`` is the first plan; ``summary.json`` keeps the first sortie's figures at the top
and adds ``sorties`` (each orbit against its own plan, up to the land command that ended it; frame counts,
rates, min separation and flight time there are the whole flight's). Faults act in the first sortie.

``--mode track`` (active capture): each agent fuses its own and its teammates' person detections (simulated
detector, ``<drone>/sim/detections``) in its cooperative filter, publishes the fused target and flies the
formation MPC around it, starting from the operator's approximate start position of the person
(``track.start_guess_ned_m``); GPS-grade position estimate by default (``track.rtk``) so that the filter's
own-offset correction shows. The summary then adds the tracking figures (see :mod:`evaluation.flight`).

Fault injection (``faults.*``, :class:`FaultsDemoConfig`; simulation/chaos options, all off by default):
teammate messages dropped / teammates' detections delayed at every agent (the transport's receive-side
fault layer, ``transport.fault``), one agent SIGKILLed mid-flight (its vehicle then lands on offboard loss;
the others re-space), a GPS jump of one vehicle's estimate (in the simulator's estimator), malformed
detections (NaN, inverted boxes, broken poses) published by this launcher on the drones' detection keys, a flood
of malformed states and commands (``malformed_flood_hz``), the killed agent restarted (``restart_agent_after_s``;
from a warm ``--standby`` spare by default), the ground station's link lost (``gcs_link_lost_at_s``), one
vehicle's MAVLink link lost for a while (``mavlink_loss_*``, the simulator's vehicle link), one recorder's disk
full or its writer killed (``recorder_fault*``, signalled to that agent). What was injected goes into
``summary.json`` under ``faults``; ``skycap faults run`` (:mod:`apps.faults`) flies the named scenarios.

The demo finishes whatever state the drones end in: the final land goes only to the drones still flying; a
drone already on the ground (landed by a failsafe, or by another client's command) or already landing is
reported in ``summary.json`` (``drones.<id>.ended``), not an error; ``summary.json`` is always written (with
``error`` when no orbit figures could be made) and the reconstruction runs on what was recorded.

What it launches (each an OS process, as on the real system; logs in ``<out>/logs/``):

1. the simulator (``skycap sim``: PX4-like vehicles over MAVLink UDP, or PX4 SITL with ``--autopilot px4``;
   the drones stand on the ground under their orbit slots) and its ground-truth publisher (SimTruth on ``sim/truth``, recorded to ``truth.mcap``);
2. a camera node per drone (the simulator's scene camera: CameraInfo, CameraFrame, simulated Keypoints2D),
   when the simulator provides one;
3. one onboard agent per drone (``skycap agent``: MAVSDK to its vehicle, Zenoh to the fleet, MCAP recording);
4. the fleet client, in this process (ground-station heartbeat; take off, orbit plan, start, then land).

Then it stops everything cleanly (SIGTERM: agents close their recordings), runs ``skycap process
<out>`` (the keypoint models on the recorded images; ``--set reconstruct_keypoints='"sim"'`` fits the simulator's
keypoints instead) when that command exists, and writes ``summary.json`` (see :mod:`evaluation.flight`) and
prints its table. The flight folder (:mod:`flightdata.folder`): ``drone_<i>.s001.mcap``, ``truth.mcap``, ``config.toml`` (resolved),
``plan.json``, ``summary.json``, ``logs/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import signal
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from comms.faults import MalformedDetectionsInjector, MalformedFloodInjector
from comms.outsider import OutsiderProbe
from comms.security import FleetKeys
from comms.transport import Transport, TransportConfig
from evaluation.flight import (format_accuracy, format_table, format_tracking_table, reconstruction_accuracy, summarize_flight,
                               summarize_tracking)
from flightdata.folder import FlightFolder
from flightdata.recorder import Recorder
from groundstation.fleet import FleetClient, make_orbit_plan
from onboard.orbit import evenly_spaced_phases
from shared_msgs import SimTruth, keys
from simulator.config import grade_overrides
from simulator.scene.person import PersonMotionConfig, load_bvh_motion
from skycap.childproc import ProcessSupervisor
from skycap.config import ConfigError, add_config_args, config_from_args, save_config
from skycap.errors import SkycapError

log = logging.getLogger("apps.demo")

__all__ = ["DemoConfig", "OrbitDemoConfig", "register", "run_demo"]


@dataclass
class OrbitDemoConfig:
    """The orbit flown (world NED; the person walks around the origin)."""

    center_ned_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    radius_m: float = 8.0
    altitude_m: float = 6.0
    angular_speed_rad_s: float = 0.15
    direction: int = 1
    #: shared start time = this long after the plan is sent
    start_in_s: float = 3.0
    min_separation_m: float = 3.0
    #: spawn the drones on the ground under their orbit slots (else: the simulator's default line)
    spawn_under_slots: bool = True


@dataclass
class TrackDemoConfig:
    """``--mode track``: the formation keeps ``orbit.radius_m`` / ``orbit.altitude_m`` from the person at
    equal angles (``orbit.angular_speed_rad_s`` is not used)."""

    #: the operator's approximate start position of the person (world NED m; the person starts near the origin)
    start_guess_ned_m: list[float] = field(default_factory=lambda: [1.5, -1.0, 0.0])
    #: the person's box height given to the agents (m): the simulator's person box (from the projected body
    #: ellipsoids, head top to soles) measures ~1.95 m (range ratio truth / 1.69 m-prior measurement on GT boxes
    #: of a track flight: median 1.14-1.18, i.e. 1.93-1.99 m)
    person_height_m: float = 1.95
    #: RTK-grade estimate in track mode (default off: GPS-grade bias, which the cooperative filter estimates)
    rtk: bool = False
    #: the agents' own detections: "sim" (the simulator's box detector: projected body box with noise, misses and
    #: false alarms) or "onnx" (the real NanoDet person detector on the rendered camera frames, in the ROI the
    #: filter predicts; ~20-90 ms per frame on one core, so on a 2-core laptop each drone detects at a few Hz)
    detections: str = "sim"


@dataclass
class FaultsDemoConfig:
    """Fault injection (simulation / chaos testing; all off by default). Times are seconds after the plan's
    start time."""

    #: share of the messages each agent receives from its teammates that is dropped (state, detections,
    #: formation plans, targets, health: ``transport.fault.drop_prob`` of every agent)
    drop_prob: float = 0.0
    #: extra delay (s) of the teammates' detections at every agent (``transport.fault.delay_s``)
    detection_delay_s: float = 0.0
    #: SIGKILL this drone's agent (e.g. "drone_3") at ``kill_agent_at_s``; its vehicle then lands on offboard
    #: loss (its COM_OBL_RC_ACT is set to land just before)
    kill_agent: str = ""
    kill_agent_at_s: float = 10.0
    #: a sudden jump of this drone's position estimate by ``gps_jump_ned_m`` at ``gps_jump_at_s``
    gps_jump_drone: str = ""
    gps_jump_at_s: float = 10.0
    gps_jump_ned_m: list[float] = field(default_factory=lambda: [3.0, 0.0, 0.0])
    #: malformed detections per second published by this launcher from the plan's start (in turn: a NaN box
    #: and a non-rigid camera pose on the first drone's own detector key, an inverted box and a NaN pose as the
    #: second drone's shared detections)
    malformed_detections_hz: float = 0.0
    #: malformed messages per second on the keys every agent listens to, from the plan's start (NaN and garbage
    #: teammate states and ground-station commands: comms.faults.MalformedFloodInjector)
    malformed_flood_hz: float = 0.0
    #: restart the killed agent (``kill_agent``) this many seconds after the kill (< 0: never; its vehicle then
    #: lands on offboard loss). Restarted, it records into a new file (``drone_<i>.s002.mcap``) and takes its
    #: vehicle -- held by the autopilot's offboard-loss action meanwhile -- over by its
    #: ``safety.on_restart_airborne`` (the fault suite's scenario: "resume"; then the launcher re-sends the plan
    #: and ``start`` to it; "land": it lands, by policy)
    restart_agent_after_s: float = -1.0
    #: the restart wakes a warm spare agent started with the others (``skycap agent --standby``: everything
    #: imported, waiting for SIGUSR1) instead of starting a new process (a cold start: ~1-3 s of Python start and
    #: imports on a loaded 2-core machine, all of it recording lost)
    restart_from_standby: bool = True
    #: the ground station's link lost at this time (< 0: never): its heartbeat stops for the rest of the flight
    #: and the agents act by their ``safety.gcs_loss_action`` (land: a landing by policy)
    gcs_link_lost_at_s: float = -1.0
    #: this drone's MAVLink link (the built-in simulator's vehicle end) carries nothing, either way, for
    #: ``mavlink_loss_s`` from ``mavlink_loss_at_s``
    mavlink_loss_drone: str = ""
    mavlink_loss_at_s: float = 10.0
    mavlink_loss_s: float = 3.0
    #: a fault of this drone's recorder at ``recorder_fault_at_s``: "disk_full" (the disk refuses every further
    #: write with ENOSPC; simulated in the recorder, see flightdata.recorder) or "killed" (the recorder's writer
    #: thread dies of an injected error); the launcher signals the agent (``record.fault_signals``)
    recorder_fault_drone: str = ""
    recorder_fault: str = ""
    recorder_fault_at_s: float = 10.0
    #: an outsider without the fleet's certificate (:class:`comms.outsider.OutsiderProbe`: plaintext, and a
    #: foreign CA's "gcs" certificate) joins at this time (< 0: never) for ``outsider_s``, snoops and sends
    #: 'land' to every drone twice a second; the report says what it got and whether any drone answered it
    outsider_at_s: float = -1.0
    outsider_s: float = 10.0


@dataclass
class DemoConfig:
    """Configuration of ``skycap demo`` (``--config demo.toml``, ``--set orbit.radius_m=6``)."""

    drones: int = 3
    #: seconds of orbit (take-off before and landing after come on top)
    duration_s: float = 60.0
    #: the flight folder; empty: a new ``flights/demo-<UTC date>-<time>`` (an existing flight is never overwritten)
    out: str = ""
    fleet: str = "demo"
    #: Zenoh rendezvous endpoint opened by this launcher; secure (the default), its protocol becomes ``tls``
    zenoh_endpoint: str = "tcp/127.0.0.1:7447"
    #: plaintext Zenoh with no authentication or access control (``--insecure``): for debugging only; logged
    #: loudly and written into ``summary.json`` (``security``)
    insecure: bool = False
    #: the fleet folder (``skycap keys``) whose certificates the processes present; empty: a new fleet CA and
    #: one certificate per drone, the simulator and this launcher (the ground station) in a temporary folder,
    #: deleted at the end (private keys never go into the flight folder)
    keys_dir: str = ""
    #: first MAVLink port (vehicle i sends to mavlink_base + i; its agent listens there)
    mavlink_base: int = 14540
    orbit: OrbitDemoConfig = field(default_factory=OrbitDemoConfig)
    #: fly with an RTK-grade position estimate (simulated GNSS bias 2 cm horizontal, 3 cm vertical), as a
    #: motion-capture fleet does (reconstruction needs cm-level camera positions). ``--set rtk=false`` flies on
    #: the simulator's GPS-grade estimate (1 m / 0.5 m bias std): the orbit errors against the truth are then
    #: dominated by that bias, which the agents cannot see (the cooperative filter of active capture corrects it)
    rtk: bool = True
    #: truth publishing rate (Hz) of the simulator node
    truth_hz: float = 50.0
    #: extra ``--set`` overrides for the simulator, the camera nodes and each agent
    sim_set: list[str] = field(default_factory=list)
    camera_set: list[str] = field(default_factory=list)
    agent_set: list[str] = field(default_factory=list)
    cameras: bool = True
    reconstruct: bool = True
    #: what the reconstruction (``skycap process``) fits: "models" (the keypoint models on the recorded images) or
    #: "sim" (the simulator's recorded noisy true keypoints, for evaluation)
    reconstruct_keypoints: str = "models"
    #: "orbit" (the plan's circle around the centre) or "track" (active capture, see TrackDemoConfig)
    mode: str = "orbit"
    track: TrackDemoConfig = field(default_factory=TrackDemoConfig)
    faults: FaultsDemoConfig = field(default_factory=FaultsDemoConfig)
    #: the person performs this recorded motion (``--motion FILE.bvh``; placed at the orbit's centre in orbit mode);
    #: ``motion.file`` "" = the simulator's default walk with stops
    motion: PersonMotionConfig = field(default_factory=PersonMotionConfig)
    #: timeouts (s)
    ready_timeout_s: float = 60.0
    takeoff_timeout_s: float = 60.0
    land_timeout_s: float = 60.0
    #: steady-orbit settling time excluded from the errors (s after the plan's start time)
    settle_s: float = 8.0
    #: the vehicles' autopilot: "builtin" (the project's simulated vehicles, ``skycap sim``) or "px4" (real PX4
    #: SITL with PX4's SIH simulator, ``skycap sim --autopilot px4``; see the module doc)
    autopilot: str = "builtin"
    #: the PX4 SITL build (``--autopilot px4``); empty: ``../shared/px4-sitl`` beside the checkout (or
    #: ``$SKYCAP_PX4_SITL``)
    px4_dir: str = ""
    #: PX4 instance number of the first drone (instance i: MAVLink UDP 14540 + i; 0..9) -- lets two PX4 fleets
    #: run side by side on one machine
    px4_first_instance: int = 0
    #: take-off, orbit, landing this many times without restarting anything (the agents keep recording into
    #: the same files); the summary then has one entry per sortie under ``sorties``
    sorties: int = 1
    #: seconds on the ground between a landing and the next take-off (PX4 disarms ~2 s after touchdown)
    sortie_pause_s: float = 5.0

    def validate(self) -> "DemoConfig":
        if not 1 <= self.drones <= 20:
            raise ConfigError(f"drones={self.drones}: use 1..20")
        if self.mode not in ("orbit", "track"):
            raise ConfigError(f"mode={self.mode!r}; use 'orbit' or 'track'")
        if self.mode == "track" and not self.cameras:
            raise ConfigError("mode='track' needs the cameras (cameras=true): the drones find the person in them")
        if self.reconstruct_keypoints not in ("models", "sim"):
            raise ConfigError(f"reconstruct_keypoints={self.reconstruct_keypoints!r}; use 'models' or 'sim'")
        if self.track.detections not in ("sim", "onnx"):
            raise ConfigError(f"track.detections={self.track.detections!r}; use 'sim' or 'onnx'")
        ids = _drone_ids(self.drones)
        f = self.faults
        for name in ("kill_agent", "gps_jump_drone", "mavlink_loss_drone", "recorder_fault_drone"):
            v = getattr(f, name)
            if v and v not in ids:
                raise ConfigError(f"faults.{name}={v!r} is not one of the drones {ids}")
        if f.kill_agent and self.drones < 2:
            raise ConfigError("faults.kill_agent needs at least 2 drones (the others must carry on)")
        if f.restart_agent_after_s >= 0 and not f.kill_agent:
            raise ConfigError("faults.restart_agent_after_s restarts the killed agent: set faults.kill_agent too")
        if f.recorder_fault not in ("", "disk_full", "killed") or bool(f.recorder_fault) != bool(f.recorder_fault_drone):
            raise ConfigError(f"faults.recorder_fault={f.recorder_fault!r}: use 'disk_full' or 'killed', with "
                              "faults.recorder_fault_drone naming the drone (both or neither)")
        if f.mavlink_loss_drone and not 0 < f.mavlink_loss_s <= 60:
            raise ConfigError(f"faults.mavlink_loss_s={f.mavlink_loss_s}: use 0 < s <= 60")
        if len(f.gps_jump_ned_m) != 3:
            raise ConfigError(f"faults.gps_jump_ned_m={f.gps_jump_ned_m}: give [north, east, down] metres")
        if not 0.0 <= f.drop_prob <= 1.0 or f.detection_delay_s < 0 or f.malformed_detections_hz < 0 or \
                f.malformed_flood_hz < 0:
            raise ConfigError("faults: drop_prob in 0..1, detection_delay_s >= 0, malformed_detections_hz >= 0, "
                              "malformed_flood_hz >= 0")
        if self.autopilot not in ("builtin", "px4"):
            raise ConfigError(f"autopilot={self.autopilot!r}; use 'builtin' or 'px4'")
        if not 1 <= self.sorties <= 20 or self.sortie_pause_s < 0:
            raise ConfigError(f"sorties={self.sorties}, sortie_pause_s={self.sortie_pause_s}: use 1..20 sorties and "
                              "a pause >= 0 s")
        if self.autopilot == "px4":
            if not 0 <= self.px4_first_instance <= 10 - self.drones:
                raise ConfigError(f"px4_first_instance={self.px4_first_instance} with {self.drones} drones: PX4 "
                                  f"instances must lie in 0..9 (use 0..{10 - self.drones})")
            if f.gps_jump_drone:
                raise ConfigError("faults.gps_jump_drone acts on the built-in simulator's estimator; PX4's cannot be "
                                  "offset from outside: leave it out with --autopilot px4")
            if f.mavlink_loss_drone:
                raise ConfigError("faults.mavlink_loss_drone acts on the built-in simulator's vehicle link: leave it "
                                  "out with --autopilot px4")
            if self.mavlink_base != DemoConfig.mavlink_base:
                raise ConfigError("mavlink_base is the built-in simulator's; with --autopilot px4 the ports follow "
                                  "the PX4 instances (14540 + instance): set px4_first_instance instead")
            other = [x for x in self.sim_set if not x.strip().startswith(("origin.", "vehicles."))]
            if other:
                raise ConfigError(f"sim_set {other}: with --autopilot px4 only origin.* and vehicles.* apply (the "
                                  "rest configures the built-in simulator's vehicles); set PX4 parameters with "
                                  "PX4 itself")
        elif self.px4_dir or self.px4_first_instance:
            raise ConfigError("px4_dir and px4_first_instance are for autopilot='px4'")
        if self.duration_s < self.settle_s + 5:
            raise ConfigError(f"duration_s={self.duration_s} leaves no steady orbit after settle_s={self.settle_s}; "
                              f"use --duration {self.settle_s + 10:.0f} or more")
        return self


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run a full simulated flight (N drones orbit the person), headless, and summarise it",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--drones", type=int, default=None, help="number of drones (default 3)")
    p.add_argument("--duration", type=float, default=None, help="seconds of orbit (default 60)")
    p.add_argument("--out", type=Path, default=None, help="a new flight folder (default: flights/demo-<UTC date>-<time>)")
    p.add_argument("--mode", choices=("orbit", "track"), default=None,
                   help="orbit (default): circle the plan's centre; track: find and follow the person (active capture)")
    p.add_argument("--autopilot", choices=("builtin", "px4"), default=None,
                   help="builtin (default): the project's simulated vehicles; px4: real PX4 SITL with SIH")
    p.add_argument("--px4-dir", default=None, help="the PX4 SITL build for --autopilot px4 (default ../shared/px4-sitl)")
    p.add_argument("--sorties", type=int, default=None,
                   help="take off, orbit and land this many times without restarting anything (default 1)")
    p.add_argument("--motion", default=None, metavar="FILE.bvh",
                   help="the person performs this recorded motion (any CMU-style BVH; motion.end=loop|clamp)")
    p.add_argument("--insecure", action="store_true", default=None,
                   help="DEBUGGING ONLY: plaintext Zenoh, no certificates, no access control")
    add_config_args(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = config_from_args(DemoConfig, args, {"drones": args.drones, "duration_s": args.duration, "out": args.out,
                                                "mode": getattr(args, "mode", None),
                                                "autopilot": getattr(args, "autopilot", None),
                                                "px4_dir": getattr(args, "px4_dir", None),
                                                "sorties": getattr(args, "sorties", None),
                                                "insecure": getattr(args, "insecure", None),
                                                "motion.file": getattr(args, "motion", None)})
    summary = run_demo(cfg.validate())
    return 0 if summary is not None and "sortie_error" not in summary else 1


#: the agents' mission states in the air (onboard.mission.AIRBORNE)
_AIRBORNE_STATES = ("takeoff", "hover", "orbit", "paused", "landing", "returning")


def _drone_ids(n: int) -> list[str]:
    return [f"drone_{i + 1}" for i in range(n)]


def _look_down_deg(cfg: DemoConfig) -> float:
    """Gimbal pitch that points the camera from the orbit at the centre (negative = down)."""
    return -math.degrees(math.atan2(cfg.orbit.altitude_m + cfg.orbit.center_ned_m[2], cfg.orbit.radius_m))


def _slots_where_they_are(slots: dict[str, float], positions_ned_m: dict, center_ned_m) -> dict[str, float]:
    """``slots`` (phase offsets, rad) all turned by one angle -- the circular mean of each drone's bearing from
    the centre minus its slot -- so that the spacing is kept and each slot lies nearest its drone."""
    diffs = [math.atan2(p[1] - center_ned_m[1], p[0] - center_ned_m[0]) - slots[d] for d, p in positions_ned_m.items()]
    turn = math.atan2(sum(math.sin(a) for a in diffs), sum(math.cos(a) for a in diffs))
    return {d: math.remainder(v + turn, 2 * math.pi) for d, v in slots.items()}


def _spawn_positions(cfg: DemoConfig, phases: dict[str, float]) -> list[list[float]]:
    c = cfg.orbit.center_ned_m
    return [[round(c[0] + cfg.orbit.radius_m * math.cos(phases[d]), 3), round(c[1] + cfg.orbit.radius_m * math.sin(phases[d]), 3)]
            for d in _drone_ids(cfg.drones)]


def run_demo(cfg: DemoConfig) -> dict | None:
    """Run the whole demo; returns the summary dict (None when the flight produced none)."""
    px4 = cfg.autopilot == "px4"
    px4_folder = _px4_folder(cfg) if px4 else None  # before anything is made: a clear error when PX4 is absent
    if not cfg.out:
        cfg = dataclasses.replace(cfg, out=time.strftime("flights/demo-%Y%m%d-%H%M%S", time.gmtime()))
    motion = None
    if cfg.motion.file:  # read before anything starts: a file the person cannot play is a clear error now
        if cfg.mode == "orbit":  # at the plan's centre
            cfg = dataclasses.replace(cfg, motion=dataclasses.replace(cfg.motion, center_ne_m=list(cfg.orbit.center_ned_m[:2])))
        motion = load_bvh_motion(cfg.motion)
        cfg = dataclasses.replace(cfg, motion=dataclasses.replace(cfg.motion, file=str(motion.path), sha256=motion.sha256))
    flight = FlightFolder(cfg.out)
    out = flight.path
    if flight.has_recordings() or flight.summary_path.exists():
        raise SkycapError(f"{out} already holds a flight ({', '.join(flight.drone_ids()) or 'truth / summary'}); "
                          "recordings are never overwritten: pass a new --out folder (or move that one away)")
    logs = flight.logs_dir
    logs.mkdir(parents=True, exist_ok=True)
    track = cfg.mode == "track"
    ids = _drone_ids(cfg.drones)
    phases = evenly_spaced_phases(ids)
    # the vehicles' MAVLink ports: the built-in simulator's from mavlink_base, PX4's from its instance numbers
    mavlink_base = 14540 + cfg.px4_first_instance if px4 else cfg.mavlink_base
    sim_set = [f"vehicles.count={cfg.drones}"]
    if not px4:  # the built-in simulator's ports and estimator (PX4 SITL has its own: SIH's GPS and PX4's EKF)
        sim_set += [f"ports.offboard_base={cfg.mavlink_base}", "ports.local_base=0", "ports.gcs_port=0"]
        if (cfg.track.rtk if track else cfg.rtk):
            sim_set += grade_overrides("rtk")  # simulator.config.POSITION_GRADES
    if cfg.orbit.spawn_under_slots:  # the built-in vehicles' spawn points, PX4's homes
        spawn = ", ".join(f"[{n}, {e}]" for n, e in _spawn_positions(cfg, phases))
        sim_set.append(f"vehicles.spawn_ne_m=[{spawn}]")
    if motion is not None:  # the simulator plays the same file (and checks its sha256)
        mc = cfg.motion
        sim_set += [f"motion.file={json.dumps(mc.file)}", f"motion.sha256={json.dumps(mc.sha256)}",
                    f"motion.end={json.dumps(mc.end)}", f"motion.loop_blend_s={mc.loop_blend_s}",
                    f"motion.units_to_m={mc.units_to_m}", f"motion.center_ne_m={json.dumps(list(mc.center_ne_m))}",
                    f"motion.skip_first_frame={json.dumps(mc.skip_first_frame)}"]
    fc = cfg.faults
    sim_set += cfg.sim_set
    save_config(cfg, flight.config_path)
    py = [sys.executable, "-m", "apps.cli"]
    fleet_keys, temp_keys = _fleet_keys(cfg, ids)
    endpoint, net_args = _network(cfg, fleet_keys)
    procs = ProcessSupervisor(logs)
    bus = Transport.open(TransportConfig.rendezvous(endpoint, keys_dir=str(fleet_keys.folder) if fleet_keys else ""),
                         "demo", identity=keys.GCS)
    truth_rec = Recorder(flight.truth_path, node_id="sim", metadata={"fleet": cfg.fleet})
    truth_sub = bus.subscribe(keys.sim_key(cfg.fleet, keys.TRUTH), lambda rx: truth_rec.record_received("truth", rx),
                              SimTruth)
    fleet = FleetClient(cfg.fleet, bus, heartbeat_hz=2.0)
    summary = None
    killed: set[str] = set()  #: process names SIGKILLed by the fault injection
    down: set[str] = set()  #: drones without an agent (killed, not restarted)
    agent_proc = {d: d for d in ids}  #: each drone's current agent process name
    agent_cmds: dict[str, list[str]] = {}
    ended: dict[str, str] = {}  #: how each drone's flight ended (summary.json drones.<id>.ended)
    last_health: dict[str, dict] = {}  #: each drone's last health report seen by the fleet client
    pending: dict[str, float] = {}  #: scheduled launcher-side faults not yet done: name -> time (UNIX s)
    plans: list = []  #: every sortie's orbit plan, in order
    sortie_error: dict = {}  #: the sortie that failed after an orbit was flown, and why
    orbits_flown = [0]  #: sorties whose orbit was flown to its end (landing may still have failed)
    fault_report: dict = {"config": {k: v for k, v in vars(cfg.faults).items()}}
    closers: list = []  #: extra sessions to close at the end
    outsider: list = [None]  #: the outsider probe while it runs (faults.outsider_at_s)
    t_begin = time.monotonic()
    try:
        # 1. simulator (+ truth); 2. cameras; 3. agents
        sim_cmd = py + ["sim", "--fleet", cfg.fleet, *net_args, "--truth-hz",
                        str(cfg.truth_hz), "--out", str(logs / "sim"), "--status-every", "10",
                        "--gimbal-pitch-deg", f"{_look_down_deg(cfg):.2f}"]
        if px4:
            sim_cmd += ["--autopilot", "px4", "--px4-dir", str(px4_folder), "--px4-first-instance",
                        str(cfg.px4_first_instance)]
        for s in sim_set:
            sim_cmd += ["--set", s]
        if fc.gps_jump_drone:
            sim_cmd += ["--gps-jump", ",".join([str(ids.index(fc.gps_jump_drone)), str(fc.gps_jump_at_s),
                                                *map(str, fc.gps_jump_ned_m)])]
        if fc.mavlink_loss_drone:
            sim_cmd += ["--link-loss", f"{ids.index(fc.mavlink_loss_drone)},{fc.mavlink_loss_at_s},{fc.mavlink_loss_s}"]
        if fc.kill_agent and fc.restart_agent_after_s < 0:
            # the orphaned vehicle lands on offboard loss (PX4 COM_OBL_RC_ACT = 4), set just before its agent dies
            # (earlier, a load-induced setpoint stall would land it too; the fleet otherwise holds and resumes)
            sim_cmd += ["--param-at", f"{ids.index(fc.kill_agent)},{max(0.0, fc.kill_agent_at_s - 0.2)},COM_OBL_RC_ACT,4"]
        procs.start("sim", sim_cmd)
        if cfg.cameras:
            for i, d in enumerate(ids):
                cmd = _camera_command() + ["--drone-id", d, "--fleet", cfg.fleet, *net_args]
                for s in cfg.camera_set:
                    cmd += ["--set", s]
                procs.start(f"camera_{d}", cmd)
        for i, d in enumerate(ids):
            cmd = py + ["agent", "--drone-id", d, "--fleet", cfg.fleet, "--connection",
                        f"udpin://0.0.0.0:{mavlink_base + i}", "--record-dir", str(out), *net_args]
            if track:
                # the camera node tags each frame with the drone's latest published estimate: publish it often
                # so that the pose at capture is not up to 100 ms stale while the drone turns
                cmd += ["--set", "mode=track", "--set", "rates.state_publish_hz=25", "--set",
                        f"track.camera_position_sigma_m={0.05 if cfg.track.rtk else 1.0}", "--set",
                        f"track.person_height_m={cfg.track.person_height_m}", "--set",
                        f"track.detections=\"{cfg.track.detections}\""]
            if fc.drop_prob > 0 or fc.detection_delay_s > 0:
                cmd += ["--set", f"transport.fault.drop_prob={fc.drop_prob}", "--set",
                        f"transport.fault.delay_s={fc.detection_delay_s}", "--set", f"transport.fault.seed={i + 1}"]
            if d == fc.recorder_fault_drone:
                cmd += ["--set", "record.fault_signals=true"]
            for s in cfg.agent_set:
                cmd += ["--set", s]
            agent_cmds[d] = cmd
            procs.start(d, cmd)
            if d == fc.kill_agent and fc.restart_agent_after_s >= 0 and fc.restart_from_standby:
                procs.start(f"{d}.standby", cmd + ["--standby"])

        # 4. the flight
        def all_(pred):
            return lambda f: all(pred(f, d) for d in ids)

        log.info("waiting for %d healthy drones", len(ids))
        ok = fleet.wait_until(all_(lambda f, d: d in f.states and f.states[d].health_ok and d in f.healths),
                              cfg.ready_timeout_s, "healthy drones")
        procs.check_alive()
        if not ok:
            raise SkycapError(f"the drones did not report healthy within {cfg.ready_timeout_s:.0f} s; see {logs}")
        o = cfg.orbit
        # track mode: the plan's centre is the operator's approximate start position of the person, its slots
        # the formation's angles (no turning: the formation follows the person)
        center = tuple(cfg.track.start_guess_ned_m) if track else tuple(o.center_ned_m)
        injector = flood = None
        if fc.malformed_detections_hz > 0 or fc.malformed_flood_hz > 0:
            # a faulty teammate: its messages are published under the drones' own certificates (an outsider's
            # could not even reach the fleet); the flood's malformed commands under the ground station's
            impostor = _AsTheDrones(endpoint, fleet_keys, ids[:2])
            closers.append(impostor.close)
            if fc.malformed_detections_hz > 0:
                injector = MalformedDetectionsInjector(impostor, cfg.fleet, ids, fc.malformed_detections_hz)
            if fc.malformed_flood_hz > 0:
                flood = MalformedFloodInjector(_ByKeyOwner(bus, impostor), cfg.fleet, ids, fc.malformed_flood_hz)
        def fly_sortie(sortie: int) -> None:
            alive = [d for d in ids if d not in down]
            if sortie > 1:
                log.info("sortie %d of %d: %.0f s on the ground, then take-off again", sortie, cfg.sorties,
                         cfg.sortie_pause_s)
                time.sleep(cfg.sortie_pause_s)
            acks = fleet.command("takeoff", wait_s=10, expect=alive, results=("accepted", "refused", "failed"))
            _require(acks, alive, f"takeoff (sortie {sortie})")
            if not fleet.wait_until(lambda f: all(f.healths[d].state == "hover" for d in alive), cfg.takeoff_timeout_s,
                                    "hover"):
                raise SkycapError(f"sortie {sortie}: not every drone reached hover within {cfg.takeoff_timeout_s:.0f} s; "
                                  f"see {logs}")
            slots = {d: phases[d] for d in alive}
            if sortie > 1:
                # the drones took off where the last orbit left them: turn the slots (spacing kept) to where they
                # are, or a drone would cross the circle (and its teammates' paths) to reach its first slot
                slots = _slots_where_they_are(slots, {d: fleet.states[d].position_ned_m for d in alive}, center)
                log.info("sortie %d: slots turned to the drones' positions: %s", sortie,
                         {d: round(math.degrees(v), 1) for d, v in slots.items()})
            plan = make_orbit_plan(alive, center, o.radius_m, o.altitude_m, 0.0 if track else o.angular_speed_rad_s,
                                   o.direction, start_in_s=o.start_in_s, min_separation_m=o.min_separation_m,
                                   phase_offset_rad=slots)
            if sortie == 1:
                flight.save_plan(plan)  # plan.json: the first sortie's plan; every sortie's is in summary.json
            plans.append(plan)
            fleet.send_plan(plan)
            _require(fleet.wait_acks(plan.plan_id, alive, 5), alive, f"plan (sortie {sortie})")
            _require(fleet.command("start", wait_s=10, expect=alive, results=("accepted", "refused", "failed")), alive,
                     f"start (sortie {sortie})")
            t_start = plan.start_time_ns * 1e-9
            t_orbit_end = t_start + cfg.duration_s
            if sortie == 1:
                if fc.kill_agent:
                    pending["kill"] = t_start + fc.kill_agent_at_s
                if fc.gcs_link_lost_at_s >= 0:
                    pending["gcs_link"] = t_start + fc.gcs_link_lost_at_s
                if fc.recorder_fault:
                    pending["recorder"] = t_start + fc.recorder_fault_at_s
                if fc.outsider_at_s >= 0:
                    pending["outsider"] = t_start + fc.outsider_at_s
            log.info("sortie %d: %s for %.0f s", sortie, "tracking" if track else "orbiting", cfg.duration_s)
            next_table = time.time()
            while time.time() < t_orbit_end:
                procs.check_alive(skip=killed)
                now = time.time()
                # faults: in the first sortie (their times count from its plan's start)
                if "kill" in pending and now >= pending["kill"]:
                    del pending["kill"]
                    p = dict(procs.items)[fc.kill_agent]
                    os.killpg(p.pid, signal.SIGKILL)
                    killed.add(fc.kill_agent)
                    down.add(fc.kill_agent)
                    fault_report["agent_killed"] = {"drone": fc.kill_agent, "t_s": round(now, 3),
                                                    "after_start_s": round(now - t_start, 2)}
                    log.warning("FAULT: killed %s's agent (SIGKILL, pid %d) %.1f s after the start", fc.kill_agent,
                                p.pid, now - t_start)
                    if fc.restart_agent_after_s >= 0:
                        pending["restart"] = now + fc.restart_agent_after_s
                if "restart" in pending and now >= pending["restart"]:
                    del pending["restart"]
                    d = fc.kill_agent
                    if fc.restart_from_standby:
                        agent_proc[d] = f"{d}.standby"
                        os.kill(dict(procs.items)[agent_proc[d]].pid, signal.SIGUSR1)  # wake the warm spare
                    else:
                        agent_proc[d] = f"{d}.restart"
                        procs.start(agent_proc[d], agent_cmds[d])
                    down.discard(d)
                    pending["resume"] = now + 60.0  # give up resuming it after this
                    fault_report["agent_restarted"] = {"drone": d, "t_s": round(now, 3),
                                                       "after_start_s": round(now - t_start, 2),
                                                       "how": "warm standby woken" if fc.restart_from_standby
                                                       else "cold start of a new process"}
                    log.warning("FAULT: restarted %s's agent %.1f s after the start (%s)", d, now - t_start,
                                fault_report["agent_restarted"]["how"])
                if "resume" in pending:
                    d = fc.kill_agent
                    h = fleet.healths.get(d)
                    if h is not None and h.state in ("hover", "paused") and \
                            h.header.t_sent_ns * 1e-9 > fault_report["agent_restarted"]["t_s"]:
                        del pending["resume"]
                        # the latched plan is too old for the new agent to accept: send it again, then start it
                        t_sent_ns = time.time_ns()
                        fleet.send_plan(plan)  # then start, once it has the plan (the two keys are not ordered)
                        fleet.wait_until(lambda f: any(a.command_id == plan.plan_id and a.header.sender_id == d and
                                                       a.header.t_sent_ns > t_sent_ns for a in f.acks), 5.0, "plan ack")
                        acks = [a for a in fleet.acks if a.command_id == plan.plan_id and a.header.sender_id == d
                                and a.header.t_sent_ns > t_sent_ns]
                        acks += fleet.command("start", target=d, wait_s=5.0,
                                              results=("accepted", "refused", "failed")).values()
                        fault_report["agent_restarted"].update(
                            resumed_after_start_s=round(time.time() - t_start, 2),
                            resume_acks=[f"{a.command_id}: {a.result}{': ' + a.reason if a.reason else ''}"
                                         for a in acks])
                        log.warning("%s's restarted agent took its vehicle over: plan and start re-sent: %s", d,
                                    fault_report["agent_restarted"]["resume_acks"])
                    elif now >= pending["resume"]:
                        del pending["resume"]
                        log.error("%s's restarted agent did not take its vehicle over (hover) within 60 s", d)
                if "gcs_link" in pending and now >= pending["gcs_link"]:
                    del pending["gcs_link"]
                    fleet.stop_heartbeat()
                    fault_report["gcs_link_lost"] = {"t_s": round(now, 3), "after_start_s": round(now - t_start, 2)}
                    log.warning("FAULT: the ground station's link lost (heartbeat stopped) %.1f s after the start",
                                now - t_start)
                if "recorder" in pending and now >= pending["recorder"]:
                    del pending["recorder"]
                    d = fc.recorder_fault_drone
                    p = dict(procs.items)[agent_proc[d]]
                    os.kill(p.pid, signal.SIGUSR2 if fc.recorder_fault == "disk_full" else signal.SIGUSR1)
                    fault_report["recorder_fault"] = {"drone": d, "fault": fc.recorder_fault, "t_s": round(now, 3),
                                                      "after_start_s": round(now - t_start, 2)}
                    log.warning("FAULT: %s's recorder %s %.1f s after the start", d, fc.recorder_fault, now - t_start)
                if "outsider" in pending and now >= pending["outsider"]:
                    if outsider[0] is None:
                        outsider[0] = OutsiderProbe(endpoint.partition("/")[2], cfg.fleet, logs)
                    outsider[0].tick(now)
                    if now >= pending["outsider"] + fc.outsider_s:
                        del pending["outsider"]
                        fault_report["outsider"] = _outsider_report(outsider[0], fleet, now - t_start)
                        outsider[0] = None
                if sortie == 1 and injector is not None and now >= t_start:
                    injector.tick(now)
                if sortie == 1 and flood is not None and now >= t_start:
                    flood.t_next = flood.t_next or now
                    while flood.t_next <= now:  # catch up: the rate kept whatever the loop's period
                        flood.tick(flood.t_next)
                if now >= next_table:
                    next_table += 10.0
                    print(fleet.table(), flush=True)
                busy = pending or flood is not None
                time.sleep(min(0.1 if busy else 0.5, 0.5 / fc.malformed_detections_hz if injector is not None else 1.0))
            if sortie == 1 and injector is not None:
                fault_report["malformed_detections_injected"] = dict(injector.counts)
            if sortie == 1 and flood is not None:
                fault_report["malformed_messages_injected"] = dict(flood.counts)
            orbits_flown[0] = sortie
            alive = [d for d in ids if d not in down]
            landed = _land_airborne(fleet, alive, cfg.land_timeout_s, ended, f"sortie {sortie}")
            print(fleet.table(), flush=True)
            if not landed:
                log.error("sortie %d: not every drone landed within %.0f s", sortie, cfg.land_timeout_s)
                if sortie < cfg.sorties:
                    raise SkycapError(f"sortie {sortie}: not every drone landed within {cfg.land_timeout_s:.0f} s: no "
                                      f"further sortie; see {logs}")

        for sortie in range(1, cfg.sorties + 1):
            try:
                fly_sortie(sortie)
            except SkycapError as e:
                if not orbits_flown[0]:
                    raise  # nothing flown to summarise
                # a sortie failed after an orbit was flown: keep what was measured, bring everyone down, report it
                log.error("sortie %d failed: %s; landing every drone and summarising the orbits flown", sortie, e)
                sortie_error.update(sortie=sortie, error=str(e))
                alive = [d for d in ids if d not in down]
                try:
                    _land_airborne(fleet, alive, cfg.land_timeout_s, ended, f"sortie {sortie}, after its failure")
                except SkycapError as e2:
                    log.error("landing after the failure: %s", e2)
                break
    finally:
        # each drone's last health as the fleet client saw it (its warnings: failsafes, a failed recorder -- which
        # the drone's own recording may lack)
        for d, h in dict(fleet.healths).items():
            last_health[d] = {"state": h.state, "ok": h.ok, "warnings": list(h.warnings)}
        codes = procs.stop([agent_proc[d] for d in ids if agent_proc[d] not in killed], timeout_s=30.0)
        codes.update(procs.stop(None, timeout_s=15.0))
        bad = {n: c for n, c in codes.items() if c not in (0, -signal.SIGTERM) and n not in killed}
        if bad:
            log.warning("processes that did not exit cleanly: %s", bad)
        for close in closers:
            close()
        fleet.close()
        truth_sub.close()
        truth_rec.close()
        bus.close()
        if temp_keys:
            shutil.rmtree(fleet_keys.folder.parent, ignore_errors=True)  # the mkdtemp folder
    played_s = time.monotonic() - t_begin  # the simulator (and the person's motion) started about then
    log.info("flight done in %.0f s; files in %s", played_s, out)

    recon: dict = {"ran": False}
    if cfg.reconstruct:
        t0 = time.monotonic()
        # the method that runs writes its summary: multiview -> reconstruction/, monocular (one drone) ->
        # reconstruction_monocular/ (the folder is new: run_demo refuses one that holds a flight)
        summaries = tuple(flight.reconstruction_dir(m) / "summary.json" for m in ("multiview", "monocular"))
        with open(logs / "reconstruct.log", "w") as f:
            r = subprocess.run(py + ["process", str(out), "--keypoints", cfg.reconstruct_keypoints], stdout=f,
                               stderr=subprocess.STDOUT)
        recon = {"ran": True, "exit_code": r.returncode, "seconds": round(time.monotonic() - t0, 1),
                 "keypoints_source": cfg.reconstruct_keypoints, "log": str(logs / "reconstruct.log")}
        fresh = [rs for rs in summaries if rs.is_file()]
        if r.returncode == 0 and fresh:
            recon["summary"] = json.loads(fresh[0].read_text())
            # what the 2D step used: the model names ("movenet_lightning+blazepose_lite") or "sim"
            recon["keypoints_source"] = recon["summary"].get("keypoints_source", cfg.reconstruct_keypoints)
            recon["seconds_per_flight_second"] = recon["summary"].get("seconds_per_flight_second")
        log.info("skycap process %s: exit %d in %.0f s (log: %s)", out, r.returncode, recon["seconds"],
                 logs / "reconstruct.log")
    try:
        summary = summarize_flight(out, settle_s=cfg.settle_s)  # the first sortie (plan.json)
    except SkycapError as e:
        # e.g. the drones were landed before a steady orbit (by someone else, or a failsafe): no orbit figures,
        # the summary still says what happened
        log.error("no orbit figures: %s", e)
        summary = {"flight_dir": str(out), "error": f"no orbit figures: {e}", "drones": {}, "fleet": {}}
    for d in ids:
        if d in last_health:
            summary["drones"].setdefault(d, {})["last_health"] = last_health[d]
        summary["drones"].setdefault(d, {})["ended"] = ended.get(d) or (
            "agent killed (SIGKILL), not restarted: its vehicle was left to the autopilot's offboard-loss action"
            if d in down else "unknown (the flight did not reach its final land command)")
    if cfg.sorties > 1 and "error" not in summary:
        # one orbit per sortie in the same recordings (the agents were not restarted: drone_<i>.s001.mcap holds
        # every sortie); each scored against its own plan, up to the first land command after its start
        summary["sorties"] = [{"sortie": k + 1, "plan": msgspec.to_builtins(p),
                               **summarize_flight(out, settle_s=cfg.settle_s, plan=p)}
                              for k, p in enumerate(plans[:orbits_flown[0]])]
        if sortie_error:
            summary["sortie_error"] = sortie_error
    if motion is not None:
        summary["motion"] = motion.info(played_s)
    summary["autopilot"] = _autopilot_report(cfg, px4_folder)
    summary["security"] = _security_report(fleet_keys, temp_keys)
    if track:
        summary["mode"] = "track"
        summary["tracking"] = summarize_tracking(out, settle_s=cfg.settle_s)
    if recon.get("exit_code") == 0 and "error" not in summary:
        # simulated flight: score the reconstruction against the simulator's truth (all frames, steady orbit)
        npz = (recon.get("summary") or {}).get("outputs", {}).get("npz")  # where the method wrote its motion
        recon["accuracy_vs_truth"] = reconstruction_accuracy(
            out, motion_npz=npz, window_s=summary["fleet"]["steady_orbit_window_s"],
            keypoints_source=recon.get("keypoints_source") or (recon.get("summary") or {}).get("keypoints_source"),
            position_grade=summary["autopilot"].get("position_estimate"))
    summary["reconstruction"] = recon
    if cfg.faults != FaultsDemoConfig():
        summary["faults"] = fault_report
    flight.summary_path.write_text(json.dumps(summary, indent=2))
    print(f"autopilot: {summary['autopilot']['kind']}; transport: {summary['security']['transport']}", flush=True)
    if motion is not None:
        mi = summary["motion"]
        print(f"motion: {mi['file']} (sha256 {mi['sha256'][:12]}..., rig {mi['rig']}, unit {mi['units']}, person about "
              f"{mi['height_m']:.2f} m tall; {mi['note']})", flush=True)
    for entry in summary.get("sorties", []):
        print(f"sortie {entry['sortie']} (frames, rates, min_separation_m and flight_s: whole flight):\n"
              + format_table(entry), flush=True)
    if "sorties" not in summary and "error" not in summary:
        print(format_table(summary), flush=True)
    for d in ids:
        print(f"{d}: {summary['drones'][d]['ended']}", flush=True)
    if track:
        print(format_tracking_table(summary["tracking"]), flush=True)
    acc = recon.get("accuracy_vs_truth") or {}
    if acc:
        print(format_accuracy(acc), flush=True)
    if sortie_error:
        print(f"sortie {sortie_error['sortie']} of {cfg.sorties} FAILED: {sortie_error['error']}", flush=True)
    print(f"summary: {flight.summary_path}", flush=True)
    return summary


def _land_airborne(fleet: FleetClient, alive: list[str], timeout_s: float, ended: dict[str, str], what: str) -> bool:
    """The final land: sent to the drones of ``alive`` still in the air; the ones already on the ground (landed
    by someone else, by a failsafe) are noted in ``ended``, not an error. Waits up to ``timeout_s`` until none
    of ``alive`` is airborne; returns whether that happened."""
    def state(d: str) -> str:
        h = fleet.healths.get(d)
        return h.state if h is not None else "unknown (no health report)"

    def already_down(d: str) -> None:
        ended[d] = f"on the ground before the final land command (state {state(d)}; landed by a failsafe or " \
                   "another client's command)"
        log.warning("%s: %s", d, ended[d])

    airborne = [d for d in alive if state(d) in _AIRBORNE_STATES and state(d) not in ("landing", "returning")]
    for d in alive:
        if state(d) in ("landing", "returning"):
            ended[d] = f"{state(d)} before the final land command (by a failsafe or another client's command)"
            log.warning("%s: %s", d, ended[d])
        elif d not in airborne:
            already_down(d)
    if airborne:
        acks = fleet.command("land", wait_s=10, expect=airborne, results=("accepted", "refused", "failed"))
        for d in list(airborne):
            a = acks.get(d)
            if a is not None and a.result == "refused" and "not airborne" in a.reason:
                airborne.remove(d)  # it touched down between the look and the command
                acks.pop(d)
                already_down(d)
        _require(acks, airborne, f"land ({what})")
        for d in airborne:
            ended[d] = "landed by the final land command"
    ok = fleet.wait_until(lambda f: all(state(d) not in _AIRBORNE_STATES for d in alive), timeout_s, "landed")
    if not ok:
        for d in alive:
            if state(d) in _AIRBORNE_STATES:
                ended[d] = f"still airborne {timeout_s:.0f} s after the final land command (state {state(d)})"
    return ok


def _require(acks: dict, ids: list[str], what: str) -> None:
    missing = [d for d in ids if d not in acks]
    bad = {d: f"{a.result}: {a.reason}" for d, a in acks.items() if a.result in ("refused", "failed")}
    if missing or bad:
        raise SkycapError(f"{what}: no answer from {missing}, refused/failed by {bad}; see the logs folder")


def _px4_folder(cfg: DemoConfig) -> Path:
    """The PX4 SITL build for ``--autopilot px4``, or an error that says how to provide it."""
    from simulator.px4_sitl import Px4SitlError, find_px4_folder

    try:
        return find_px4_folder(cfg.px4_dir or None)
    except Px4SitlError as e:
        raise SkycapError(f"skycap demo --autopilot px4 needs a PX4 SITL build: {e}. Give it with --px4-dir DIR "
                          "(--set px4_dir=...), or use the built-in simulator (--autopilot builtin)") from None


def _px4_version(folder: Path) -> str:
    """The PX4 build's source as its folder's README.md names it (``PX4-Autopilot main at commit ...``)."""
    import re

    try:
        text = (folder / "README.md").read_text(errors="replace")
    except OSError:
        return "unknown (no README.md in the PX4 folder)"
    m = re.search(r"Source:\s*(.+?)(?:,\s*board|\n)", text)
    return " ".join(m.group(1).replace("`", "").split()) if m else "unknown (README.md names no source)"


def _autopilot_report(cfg: DemoConfig, px4_folder: Path | None) -> dict:
    """What flew the vehicles, for summary.json."""
    if px4_folder is None:
        return {"kind": "builtin", "simulator": "skycap sim (the project's simulated PX4-like vehicles)",
                "position_estimate": "rtk" if (cfg.track.rtk if cfg.mode == "track" else cfg.rtk) else "gps"}
    return {"kind": "px4_sitl", "simulator": "PX4 SIH (sihsim_quadx, airframe 10040)", "px4_dir": str(px4_folder),
            "version": _px4_version(px4_folder),
            "instances": list(range(cfg.px4_first_instance, cfg.px4_first_instance + cfg.drones)),
            "truth": "SIH HIL_STATE_QUATERNION (true state), resampled to SimTruth at "
                     f"{cfg.truth_hz:g} Hz; altitudes above SIH's ground",
            "position_estimate": "PX4 EKF2 on SIH's simulated sensors"}


def _outsider_report(probe: OutsiderProbe, fleet: FleetClient, after_start_s: float) -> dict:
    """What the outsider got: links, fleet messages received, commands sent, and any drone's answer to them."""
    rep = probe.close()
    ids = set(probe.command_ids)
    answered = [f"{a.header.sender_id}: {a.result} {a.command_id}" for a in list(fleet.acks) if a.command_id in ids]
    rep.update(answered=answered, ended_after_start_s=round(after_start_s, 2))
    (log.error if answered or any(rep["links"].values()) or any(rep["received"].values()) else log.info)(
        "outsider: links %s, fleet messages received %s, %d land commands sent, answered by the drones: %s",
        rep["links"], rep["received"], rep["commands_sent"], answered or "none")
    return rep


def _fleet_keys(cfg: DemoConfig, ids: list[str]):
    """(the fleet folder, whether it is a temporary one made here) -- (None, False) with ``insecure``."""
    if cfg.insecure:
        log.warning("INSECURE demo (--insecure): plaintext Zenoh, no certificates, no access control -- anyone on "
                    "this machine's network can read the fleet and command it. For debugging only.")
        return None, False
    if cfg.keys_dir:
        fleet_keys = FleetKeys.load(cfg.keys_dir)
        if fleet_keys.fleet != cfg.fleet:
            raise SkycapError(f"keys_dir {cfg.keys_dir} is fleet {fleet_keys.fleet!r}, the demo flies {cfg.fleet!r}: "
                              f"set fleet = {fleet_keys.fleet!r} or make keys for {cfg.fleet!r}")
        for ident in [keys.GCS, keys.SIM, *ids]:
            fleet_keys.check(ident)
        return fleet_keys, False
    folder = Path(tempfile.mkdtemp(prefix="skycap-keys-")) / "fleet"
    fleet_keys = FleetKeys.create(folder, cfg.fleet, drones=ids, sim=True, days=2)
    log.info("secure fleet: a new CA and %d certificates in %s (mutual TLS + access control; deleted at the end)",
             len(fleet_keys.identities), folder)
    return fleet_keys, True


def _network(cfg: DemoConfig, fleet_keys) -> tuple[str, list[str]]:
    """The rendezvous endpoint (``tls/`` when secure) and the network options of every child process."""
    endpoint = cfg.zenoh_endpoint
    if fleet_keys is None:
        return endpoint, ["--zenoh-connect", endpoint]
    endpoint = "tls/" + endpoint.partition("/")[2]
    return endpoint, ["--zenoh-connect", endpoint, "--zenoh-keys", str(fleet_keys.folder)]


def _security_report(fleet_keys, temporary: bool) -> dict:
    if fleet_keys is None:
        return {"transport": "INSECURE (plaintext, no authentication, no access control: --insecure)",
                "insecure": True}
    return {"transport": "mutual TLS + Zenoh access control", "insecure": False,
            "keys": "temporary fleet CA (deleted after the flight)" if temporary else str(fleet_keys.folder),
            "identities": dict(sorted(fleet_keys.identities.items()))}


class _AsTheDrones:
    """``publish_raw`` under the certificate of the drone whose key it is (fault injection of a faulty teammate)."""

    def __init__(self, endpoint: str, fleet_keys, drones: list[str]):
        sec = str(fleet_keys.folder) if fleet_keys is not None else ""
        self.buses = {d: Transport.open(TransportConfig.local_peer(endpoint, sec), f"faulty-{d}", identity=d)
                      for d in drones}

    def publish_raw(self, key: str, data: bytes) -> None:
        self.buses[keys.parse_key(key)[1]].publish_raw(key, data)

    def close(self) -> None:
        for b in self.buses.values():
            b.close()


class _ByKeyOwner:
    """``publish_raw`` on a ground-station key through the launcher's own session (the ground station's
    certificate), on a drone's key through :class:`_AsTheDrones`."""

    def __init__(self, gcs_bus: Transport, drones: _AsTheDrones):
        self.gcs_bus, self.drones = gcs_bus, drones

    def publish_raw(self, key: str, data: bytes) -> None:
        (self.gcs_bus if keys.parse_key(key)[1] == keys.GCS else self.drones).publish_raw(key, data)


def _camera_command() -> list[str]:
    """The simulator's per-drone camera node command."""
    return [sys.executable, "-m", "simulator.scene.node"]
