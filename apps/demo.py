"""``skycap demo``: a full simulated flight, headless: N drones orbit the person, then the flight is summarised.

    skycap demo                                        # 3 drones, 60 s of orbit, into a new flights/demo-<time>/
    skycap demo --drones 2 --duration 20 --out /tmp/f --set orbit.radius_m=6
    skycap demo --set rtk=false                        # GPS-grade position estimate (m-level bias) instead of RTK
    skycap demo --mode track --out flights/track       # active capture: find and follow the person
    skycap demo --mode track --set faults.drop_prob=0.3 --set 'faults.kill_agent="drone_3"'   # under faults

``--mode track`` (active capture): each agent fuses its own and its teammates' person detections (simulated
detector, ``<drone>/sim/detections``) in its cooperative filter, publishes the fused target and flies the
formation MPC around it, starting from the operator's approximate start position of the person
(``track.start_guess_ned_m``); GPS-grade position estimate by default (``track.rtk``) so that the filter's
own-offset correction shows. The summary then adds the tracking figures (see :mod:`evaluation.flight`).

Fault injection (``faults.*``, :class:`FaultsDemoConfig`; simulation/chaos options, all off by default):
teammate messages dropped / teammates' detections delayed at every agent (the transport's receive-side
fault layer, ``transport.fault``), one agent SIGKILLed mid-flight (its vehicle then lands on offboard loss;
the others re-space), a GPS jump of one vehicle's estimate (in the simulator's estimator), malformed
detections (NaN, inverted boxes, broken poses) published by this launcher on the drones' detection keys.
What was injected goes into ``summary.json`` under ``faults``.

What it launches (each an OS process, as on the real system; logs in ``<out>/logs/``):

1. the simulator (``skycap sim``: PX4-like vehicles over MAVLink UDP; the drones stand on the ground under
   their orbit slots) and its ground-truth publisher (SimTruth on ``sim/truth``, recorded to ``truth.mcap``);
2. a camera node per drone (the simulator's scene camera: CameraInfo, CameraFrame, simulated Keypoints2D),
   when the simulator provides one;
3. one onboard agent per drone (``skycap agent``: MAVSDK to its vehicle, Zenoh to the fleet, MCAP recording);
4. the fleet client, in this process (ground-station heartbeat; take off, orbit plan, start, then land).

Then it stops everything cleanly (SIGTERM: agents close their recordings), runs ``skycap reconstruct
<out>`` when that command exists, and writes ``summary.json`` (see :mod:`evaluation.flight`) and
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
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from apps.supervisor import ProcessSupervisor
from comms.faults import MalformedDetectionsInjector
from comms.transport import Transport, TransportConfig
from evaluation.flight import (format_table, format_tracking_table, reconstruction_accuracy, summarize_flight,
                               summarize_tracking)
from flightdata.folder import FlightFolder
from flightdata.recorder import Recorder
from groundstation.fleet import FleetClient, make_orbit_plan
from onboard.orbit import evenly_spaced_phases
from shared_msgs import SimTruth, keys
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


@dataclass
class DemoConfig:
    """Configuration of ``skycap demo`` (``--config demo.toml``, ``--set orbit.radius_m=6``)."""

    drones: int = 3
    #: seconds of orbit (take-off before and landing after come on top)
    duration_s: float = 60.0
    #: the flight folder; empty: a new ``flights/demo-<UTC date>-<time>`` (an existing flight is never overwritten)
    out: str = ""
    fleet: str = "demo"
    #: Zenoh rendezvous endpoint opened by this launcher
    zenoh_endpoint: str = "tcp/127.0.0.1:7447"
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
    #: "orbit" (the plan's circle around the centre) or "track" (active capture, see TrackDemoConfig)
    mode: str = "orbit"
    track: TrackDemoConfig = field(default_factory=TrackDemoConfig)
    faults: FaultsDemoConfig = field(default_factory=FaultsDemoConfig)
    #: timeouts (s)
    ready_timeout_s: float = 60.0
    takeoff_timeout_s: float = 60.0
    land_timeout_s: float = 60.0
    #: steady-orbit settling time excluded from the errors (s after the plan's start time)
    settle_s: float = 8.0

    def validate(self) -> "DemoConfig":
        if not 1 <= self.drones <= 20:
            raise ConfigError(f"drones={self.drones}: use 1..20")
        if self.mode not in ("orbit", "track"):
            raise ConfigError(f"mode={self.mode!r}; use 'orbit' or 'track'")
        if self.mode == "track" and not self.cameras:
            raise ConfigError("mode='track' needs the cameras (cameras=true): the drones find the person in them")
        if self.track.detections not in ("sim", "onnx"):
            raise ConfigError(f"track.detections={self.track.detections!r}; use 'sim' or 'onnx'")
        ids = _drone_ids(self.drones)
        f = self.faults
        for name in ("kill_agent", "gps_jump_drone"):
            v = getattr(f, name)
            if v and v not in ids:
                raise ConfigError(f"faults.{name}={v!r} is not one of the drones {ids}")
        if f.kill_agent and self.drones < 2:
            raise ConfigError("faults.kill_agent needs at least 2 drones (the others must carry on)")
        if len(f.gps_jump_ned_m) != 3:
            raise ConfigError(f"faults.gps_jump_ned_m={f.gps_jump_ned_m}: give [north, east, down] metres")
        if not 0.0 <= f.drop_prob <= 1.0 or f.detection_delay_s < 0 or f.malformed_detections_hz < 0:
            raise ConfigError("faults: drop_prob in 0..1, detection_delay_s >= 0, malformed_detections_hz >= 0")
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
    add_config_args(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = config_from_args(DemoConfig, args, {"drones": args.drones, "duration_s": args.duration, "out": args.out,
                                                "mode": getattr(args, "mode", None)})
    summary = run_demo(cfg.validate())
    return 0 if summary is not None else 1


def _drone_ids(n: int) -> list[str]:
    return [f"drone_{i + 1}" for i in range(n)]


def _look_down_deg(cfg: DemoConfig) -> float:
    """Gimbal pitch that points the camera from the orbit at the centre (negative = down)."""
    return -math.degrees(math.atan2(cfg.orbit.altitude_m + cfg.orbit.center_ned_m[2], cfg.orbit.radius_m))


def _spawn_positions(cfg: DemoConfig, phases: dict[str, float]) -> list[list[float]]:
    c = cfg.orbit.center_ned_m
    return [[round(c[0] + cfg.orbit.radius_m * math.cos(phases[d]), 3), round(c[1] + cfg.orbit.radius_m * math.sin(phases[d]), 3)]
            for d in _drone_ids(cfg.drones)]


def run_demo(cfg: DemoConfig) -> dict | None:
    """Run the whole demo; returns the summary dict (None when the flight produced none)."""
    if not cfg.out:
        cfg = dataclasses.replace(cfg, out=time.strftime("flights/demo-%Y%m%d-%H%M%S", time.gmtime()))
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
    sim_set = [f"vehicles.count={cfg.drones}", f"ports.offboard_base={cfg.mavlink_base}", "ports.local_base=0",
               "ports.gcs_port=0"]
    if cfg.orbit.spawn_under_slots:
        spawn = ", ".join(f"[{n}, {e}]" for n, e in _spawn_positions(cfg, phases))
        sim_set.append(f"vehicles.spawn_ne_m=[{spawn}]")
    if (cfg.track.rtk if track else cfg.rtk):
        sim_set += ["estimator.pos_bias_std_xy_m=0.02", "estimator.pos_bias_std_z_m=0.03"]
    fc = cfg.faults
    sim_set += cfg.sim_set
    save_config(cfg, flight.config_path)
    py = [sys.executable, "-m", "apps.cli"]
    procs = ProcessSupervisor(logs)
    bus = Transport.open(TransportConfig.rendezvous(cfg.zenoh_endpoint), "demo")
    truth_rec = Recorder(flight.truth_path, node_id="sim", metadata={"fleet": cfg.fleet})
    truth_sub = bus.subscribe(keys.sim_key(cfg.fleet, keys.TRUTH), lambda rx: truth_rec.record_received("truth", rx),
                              SimTruth)
    fleet = FleetClient(cfg.fleet, bus, heartbeat_hz=2.0)
    summary = None
    killed: set[str] = set()
    fault_report: dict = {"config": {k: v for k, v in vars(cfg.faults).items()}}
    t_begin = time.monotonic()
    try:
        # 1. simulator (+ truth); 2. cameras; 3. agents
        sim_cmd = py + ["sim", "--fleet", cfg.fleet, "--zenoh-connect", cfg.zenoh_endpoint, "--truth-hz",
                        str(cfg.truth_hz), "--out", str(logs / "sim"), "--status-every", "10",
                        "--gimbal-pitch-deg", f"{_look_down_deg(cfg):.2f}"]
        for s in sim_set:
            sim_cmd += ["--set", s]
        if fc.gps_jump_drone:
            sim_cmd += ["--gps-jump", ",".join([str(ids.index(fc.gps_jump_drone)), str(fc.gps_jump_at_s),
                                                *map(str, fc.gps_jump_ned_m)])]
        if fc.kill_agent:
            # the orphaned vehicle lands on offboard loss (PX4 COM_OBL_RC_ACT = 4), set just before its agent dies
            # (earlier, a load-induced setpoint stall would land it too; the fleet otherwise holds and resumes)
            sim_cmd += ["--param-at", f"{ids.index(fc.kill_agent)},{max(0.0, fc.kill_agent_at_s - 0.2)},COM_OBL_RC_ACT,4"]
        procs.start("sim", sim_cmd)
        if cfg.cameras:
            for i, d in enumerate(ids):
                cmd = _camera_command() + ["--drone-id", d, "--fleet", cfg.fleet, "--zenoh-connect", cfg.zenoh_endpoint]
                for s in cfg.camera_set:
                    cmd += ["--set", s]
                procs.start(f"camera_{d}", cmd)
        for i, d in enumerate(ids):
            cmd = py + ["agent", "--drone-id", d, "--fleet", cfg.fleet, "--connection",
                        f"udpin://0.0.0.0:{cfg.mavlink_base + i}", "--record-dir", str(out),
                        "--zenoh-connect", cfg.zenoh_endpoint]
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
            for s in cfg.agent_set:
                cmd += ["--set", s]
            procs.start(d, cmd)

        # 4. the flight
        def all_(pred):
            return lambda f: all(pred(f, d) for d in ids)

        log.info("waiting for %d healthy drones", len(ids))
        ok = fleet.wait_until(all_(lambda f, d: d in f.states and f.states[d].health_ok and d in f.healths),
                              cfg.ready_timeout_s, "healthy drones")
        procs.check_alive()
        if not ok:
            raise SkycapError(f"the drones did not report healthy within {cfg.ready_timeout_s:.0f} s; see {logs}")
        acks = fleet.command("takeoff", wait_s=10, expect=ids, results=("accepted", "refused", "failed"))
        _require(acks, ids, "takeoff")
        if not fleet.wait_until(all_(lambda f, d: f.healths[d].state == "hover"), cfg.takeoff_timeout_s, "hover"):
            raise SkycapError(f"not every drone reached hover within {cfg.takeoff_timeout_s:.0f} s; see {logs}")
        o = cfg.orbit
        # track mode: the plan's centre is the operator's approximate start position of the person, its slots
        # the formation's angles (no turning: the formation follows the person)
        center = tuple(cfg.track.start_guess_ned_m) if track else tuple(o.center_ned_m)
        plan = make_orbit_plan(ids, center, o.radius_m, o.altitude_m, 0.0 if track else o.angular_speed_rad_s, o.direction,
                               start_in_s=o.start_in_s, min_separation_m=o.min_separation_m, phase_offset_rad=phases)
        flight.save_plan(plan)
        fleet.send_plan(plan)
        _require(fleet.wait_acks(plan.plan_id, ids, 5), ids, "plan")
        _require(fleet.command("start", wait_s=10, expect=ids, results=("accepted", "refused", "failed")), ids, "start")
        t_start = plan.start_time_ns * 1e-9
        t_orbit_end = t_start + cfg.duration_s
        log.info("%s for %.0f s", "tracking" if track else "orbiting", cfg.duration_s)
        next_table = time.time()
        injector = MalformedDetectionsInjector(bus, cfg.fleet, ids, fc.malformed_detections_hz) if fc.malformed_detections_hz > 0 else None
        while time.time() < t_orbit_end:
            procs.check_alive(skip=killed)
            now = time.time()
            if fc.kill_agent and fc.kill_agent not in killed and now >= t_start + fc.kill_agent_at_s:
                p = dict(procs.items)[fc.kill_agent]
                os.killpg(p.pid, signal.SIGKILL)
                killed.add(fc.kill_agent)
                fault_report["agent_killed"] = {"drone": fc.kill_agent, "t_s": round(now, 3),
                                                "after_start_s": round(now - t_start, 2)}
                log.warning("FAULT: killed %s's agent (SIGKILL, pid %d) %.1f s after the start", fc.kill_agent, p.pid,
                            now - t_start)
            if injector is not None and now >= t_start:
                injector.tick(now)
            if now >= next_table:
                next_table += 10.0
                print(fleet.table(), flush=True)
            time.sleep(0.5 if injector is None else min(0.5, 0.5 / fc.malformed_detections_hz))
        if injector is not None:
            fault_report["malformed_detections_injected"] = dict(injector.counts)
        alive = [d for d in ids if d not in killed]
        _require(fleet.command("land", wait_s=10, expect=alive, results=("accepted", "refused", "failed")), alive, "land")
        if not fleet.wait_until(lambda f: all(f.healths[d].state == "landed" for d in alive), cfg.land_timeout_s, "landed"):
            log.error("not every drone landed within %.0f s", cfg.land_timeout_s)
        print(fleet.table(), flush=True)
    finally:
        codes = procs.stop([d for d in ids if d not in killed], timeout_s=30.0)
        codes.update(procs.stop(None, timeout_s=15.0))
        bad = {n: c for n, c in codes.items() if c not in (0, -signal.SIGTERM) and n not in killed}
        if bad:
            log.warning("processes that did not exit cleanly: %s", bad)
        fleet.close()
        truth_sub.close()
        truth_rec.close()
        bus.close()
    log.info("flight done in %.0f s; files in %s", time.monotonic() - t_begin, out)

    recon: dict = {"ran": False}
    if cfg.reconstruct:
        t0 = time.monotonic()
        # the method that runs writes its summary: multiview -> reconstruction/, monocular (one drone) ->
        # reconstruction_monocular/ (the folder is new: run_demo refuses one that holds a flight)
        summaries = tuple(flight.reconstruction_dir(m) / "summary.json" for m in ("multiview", "monocular"))
        with open(logs / "reconstruct.log", "w") as f:
            r = subprocess.run(py + ["reconstruct", str(out)], stdout=f, stderr=subprocess.STDOUT)
        recon = {"ran": True, "exit_code": r.returncode, "seconds": round(time.monotonic() - t0, 1),
                 "log": str(logs / "reconstruct.log")}
        fresh = [rs for rs in summaries if rs.is_file()]
        if r.returncode == 0 and fresh:
            recon["summary"] = json.loads(fresh[0].read_text())
        log.info("skycap reconstruct %s: exit %d in %.0f s (log: %s)", out, r.returncode, recon["seconds"],
                 logs / "reconstruct.log")
    summary = summarize_flight(out, settle_s=cfg.settle_s)
    if track:
        summary["mode"] = "track"
        summary["tracking"] = summarize_tracking(out, settle_s=cfg.settle_s)
    if recon.get("exit_code") == 0:
        # simulated flight: score the reconstruction against the simulator's truth (all frames, steady orbit)
        npz = (recon.get("summary") or {}).get("outputs", {}).get("npz")  # where the method wrote its motion
        recon["accuracy_vs_truth"] = reconstruction_accuracy(out, motion_npz=npz,
                                                             window_s=summary["fleet"]["steady_orbit_window_s"])
    summary["reconstruction"] = recon
    if cfg.faults != FaultsDemoConfig():
        summary["faults"] = fault_report
    flight.summary_path.write_text(json.dumps(summary, indent=2))
    print(format_table(summary), flush=True)
    if track:
        print(format_tracking_table(summary["tracking"]), flush=True)
    acc = recon.get("accuracy_vs_truth") or {}
    if acc:
        print(f"reconstruction vs truth: steady orbit MPJPE {acc.get('mpjpe_mm_window', float('nan')):.1f} mm, "
              f"PA-MPJPE {acc.get('pa_mpjpe_mm_window', float('nan')):.1f} mm over {acc.get('frames_scored_window', 0)} "
              f"frames; whole flight incl. take-off and landing MPJPE {acc['mpjpe_mm']:.1f} mm, "
              f"PA-MPJPE {acc['pa_mpjpe_mm']:.1f} mm", flush=True)
    print(f"summary: {flight.summary_path}", flush=True)
    return summary


def _require(acks: dict, ids: list[str], what: str) -> None:
    missing = [d for d in ids if d not in acks]
    bad = {d: f"{a.result}: {a.reason}" for d, a in acks.items() if a.result in ("refused", "failed")}
    if missing or bad:
        raise SkycapError(f"{what}: no answer from {missing}, refused/failed by {bad}; see the logs folder")


def _camera_command() -> list[str]:
    """The simulator's per-drone camera node command."""
    return [sys.executable, "-m", "simulator.scene.node"]
