"""``skycap demo``: a full simulated flight, headless: N drones orbit the person, then the flight is summarised.

    skycap demo --out flights/demo                     # 3 drones, 60 s of orbit
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
prints its table. The flight folder: ``drone_<i>.mcap``, ``truth.mcap``, ``config.toml`` (resolved),
``plan.json``, ``summary.json``, ``logs/``.
"""

from __future__ import annotations

import argparse
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

from skycap.config import add_config_args
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
    out: str = "flights/demo"
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
        from skycap.config import ConfigError

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
    p.add_argument("--out", type=Path, default=None, help="flight folder (default flights/demo)")
    p.add_argument("--mode", choices=("orbit", "track"), default=None,
                   help="orbit (default): circle the plan's centre; track: find and follow the person (active capture)")
    add_config_args(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from skycap.config import config_from_args

    cfg = config_from_args(DemoConfig, args, {"drones": args.drones, "duration_s": args.duration, "out": args.out,
                                                "mode": getattr(args, "mode", None)})
    summary = run_demo(cfg.validate())
    return 0 if summary is not None else 1


def _drone_ids(n: int) -> list[str]:
    return [f"drone_{i + 1}" for i in range(n)]


def _has_command(name: str) -> bool:
    from apps.cli import build_parser

    parser = build_parser()
    for action in parser._subparsers._group_actions:  # noqa: SLF001 - argparse has no public accessor
        if name in getattr(action, "choices", {}):
            return True
    return False


class _Procs:
    """Child processes of the demo, each with its log file; stopped in reverse order."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.items: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, cmd: list[str]) -> subprocess.Popen:
        f = open(self.log_dir / f"{name}.log", "w")
        log.info("starting %s: %s", name, " ".join(cmd))
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        self.items.append((name, p))
        return p

    def check_alive(self, skip: set[str] | frozenset = frozenset()) -> None:
        for name, p in self.items:
            if name not in skip and p.poll() is not None:
                raise SkycapError(f"{name} exited early (code {p.returncode}); see {self.log_dir / (name + '.log')}")

    def stop(self, names: list[str] | None = None, timeout_s: float = 30.0) -> dict[str, int]:
        """SIGTERM the named processes (all if None), wait, SIGKILL what is left; returns exit codes."""
        chosen = [(n, p) for n, p in self.items if names is None or n in names]
        for n, p in chosen:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes = {}
        t_end = time.monotonic() + timeout_s
        for n, p in chosen:
            try:
                codes[n] = p.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not stop within %.0f s: killing it", n, timeout_s)
                os.killpg(p.pid, signal.SIGKILL)
                codes[n] = p.wait()
        return codes


def _look_down_deg(cfg: DemoConfig) -> float:
    """Gimbal pitch that points the camera from the orbit at the centre (negative = down)."""
    return -math.degrees(math.atan2(cfg.orbit.altitude_m + cfg.orbit.center_ned_m[2], cfg.orbit.radius_m))


def _spawn_positions(cfg: DemoConfig, phases: dict[str, float]) -> list[list[float]]:
    c = cfg.orbit.center_ned_m
    return [[round(c[0] + cfg.orbit.radius_m * math.cos(phases[d]), 3), round(c[1] + cfg.orbit.radius_m * math.sin(phases[d]), 3)]
            for d in _drone_ids(cfg.drones)]


def run_demo(cfg: DemoConfig) -> dict | None:
    """Run the whole demo; returns the summary dict (None when the flight produced none)."""
    from groundstation.fleet import FleetClient, make_orbit_plan
    from evaluation.flight import format_table, reconstruction_accuracy, summarize_flight
    from flightdata.folder import FlightFolder
    from onboard.orbit import evenly_spaced_phases
    from flightdata.recorder import Recorder, truth_log_path
    from comms.transport import Transport, TransportConfig
    from shared_msgs import SimTruth, keys
    from skycap.config import save_config

    out = Path(cfg.out)
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    track = cfg.mode == "track"
    for old in [*out.glob("drone_*.mcap"), *out.glob("drone_*.track.json"), out / "truth.mcap", out / "summary.json",
                out / "plan.json"]:
        old.unlink(missing_ok=True)
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
    save_config(cfg, out / "config.toml")
    py = [sys.executable, "-m", "apps.cli"]
    procs = _Procs(logs)
    bus = Transport.open(TransportConfig.rendezvous(cfg.zenoh_endpoint), "demo")
    truth_rec = Recorder(truth_log_path(out), node_id="sim", metadata={"fleet": cfg.fleet})
    truth_sub = bus.subscribe(keys.sim_key(cfg.fleet, keys.TRUTH), lambda rx: truth_rec.record_received("truth", rx),
                              SimTruth)
    fleet = FleetClient(cfg.fleet, bus, heartbeat_hz=2.0)
    summary = None
    killed: set[str] = set()
    fault_report: dict = {"config": {k: v for k, v in vars(cfg.faults).items()}}
    t_begin = time.monotonic()
    try:
        # 1. simulator (+ truth); 2. cameras; 3. agents
        sim_cmd = [sys.executable, "-m", "apps.demo", "--fleet", cfg.fleet, "--zenoh-connect",
                   cfg.zenoh_endpoint, "--truth-hz", str(cfg.truth_hz), "--out", str(out),
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
            cam = _camera_command()
            if cam is None:
                log.warning("the simulator has no camera node yet: flying without cameras")
            else:
                for i, d in enumerate(ids):
                    cmd = cam + ["--drone-id", d, "--fleet", cfg.fleet, "--zenoh-connect", cfg.zenoh_endpoint]
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
        FlightFolder(out).save_plan(plan)
        fleet.send_plan(plan)
        _require(fleet.wait_acks(plan.plan_id, ids, 5), ids, "plan")
        _require(fleet.command("start", wait_s=10, expect=ids, results=("accepted", "refused", "failed")), ids, "start")
        t_start = plan.start_time_ns * 1e-9
        t_orbit_end = t_start + cfg.duration_s
        log.info("%s for %.0f s", "tracking" if track else "orbiting", cfg.duration_s)
        next_table = time.time()
        injector = _MalformedInjector(bus, cfg.fleet, ids, fc.malformed_detections_hz) if fc.malformed_detections_hz > 0 else None
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
        if _has_command("reconstruct"):
            t0 = time.monotonic()
            # the method that runs writes its summary: multiview -> reconstruction/, monocular (one drone) ->
            # reconstruction_monocular/; a summary left there by an earlier run in this folder must not be taken
            summaries = (out / "reconstruction" / "summary.json", out / "reconstruction_monocular" / "summary.json")
            for rs in summaries:
                rs.unlink(missing_ok=True)
            with open(logs / "reconstruct.log", "w") as f:
                r = subprocess.run(py + ["reconstruct", str(out)], stdout=f, stderr=subprocess.STDOUT)
            recon = {"ran": True, "exit_code": r.returncode, "seconds": round(time.monotonic() - t0, 1),
                     "log": str(logs / "reconstruct.log")}
            fresh = [rs for rs in summaries if rs.is_file()]
            if r.returncode == 0 and fresh:
                recon["summary"] = json.loads(fresh[0].read_text())
            log.info("skycap reconstruct %s: exit %d in %.0f s (log: %s)", out, r.returncode, recon["seconds"],
                     logs / "reconstruct.log")
        else:
            log.info("no 'skycap reconstruct' command in this build: skipping reconstruction")
    summary = summarize_flight(out, settle_s=cfg.settle_s)
    if track:
        from evaluation.flight import summarize_tracking

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
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(format_table(summary), flush=True)
    if track:
        from evaluation.flight import format_tracking_table

        print(format_tracking_table(summary["tracking"]), flush=True)
    acc = recon.get("accuracy_vs_truth") or {}
    if acc:
        print(f"reconstruction vs truth: steady orbit MPJPE {acc.get('mpjpe_mm_window', float('nan')):.1f} mm, "
              f"PA-MPJPE {acc.get('pa_mpjpe_mm_window', float('nan')):.1f} mm over {acc.get('frames_scored_window', 0)} "
              f"frames; whole flight incl. take-off and landing MPJPE {acc['mpjpe_mm']:.1f} mm, "
              f"PA-MPJPE {acc['pa_mpjpe_mm']:.1f} mm", flush=True)
    print(f"summary: {out / 'summary.json'}", flush=True)
    return summary


class _MalformedInjector:
    """Publishes malformed detections at ``rate_hz`` (fault injection), cycling through four kinds:

    0. a NaN box on the first drone's own detector key (``<d1>/sim/detections``): refused by the codec on receipt;
    1. an inverted box as the second drone's shared detections (``<d2>/detections``): decodes, the tracking
       stage of every other drone must ignore it;
    2. a non-rigid camera pose on ``<d1>/sim/detections``: decodes, the first drone's stage must ignore it;
    3. a NaN camera pose as ``<d2>/detections``: refused by the codec on receipt.

    With one drone, every kind goes to its own detector key.
    """

    KINDS = ("nan_box", "inverted_box", "non_rigid_pose", "nan_pose")

    def __init__(self, bus, fleet: str, ids: list[str], rate_hz: float):
        self.bus, self.fleet, self.ids, self.period_s = bus, fleet, ids, 1.0 / rate_hz
        self.t_next = 0.0
        self.n = 0
        self.counts = {k: 0 for k in self.KINDS}

    def message(self, kind: str, t_ns: int):
        from shared_msgs import encode, keys, stamp_sent
        from shared_msgs.messages import BoundingBox, Detections

        own, mate = self.ids[0], self.ids[1] if len(self.ids) > 1 else self.ids[0]
        key = keys.drone_key(self.fleet, own, keys.SIM_DETECTIONS) if kind in ("nan_box", "non_rigid_pose") or mate == own \
            else keys.drone_key(self.fleet, mate, keys.DETECTIONS)
        sender = own if "sim/detections" in key else mate
        T = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, -6.0, 0, 0, 0, 1.0]
        box = dict(x_min_px=100.0, y_min_px=100.0, x_max_px=140.0, y_max_px=200.0, score=0.9)
        if kind == "nan_box":
            box["x_min_px"] = float("nan")
        elif kind == "inverted_box":
            box["x_max_px"], box["x_min_px"] = 100.0, 140.0
        elif kind == "non_rigid_pose":
            T = [2.0 * v if i in (0, 5, 10) else v for i, v in enumerate(T)]
        elif kind == "nan_pose":
            T[3] = float("nan")
        msg = Detections(header=Detections.make_header(sender, t_ns, 10_000_000 + self.n), camera_id="chaos",
                         frame_index=10_000_000 + self.n, detector="fault_injector", mode="simulated",
                         boxes=[BoundingBox(**box)], width_px=960, height_px=540, T_world_cam=tuple(T))
        return key, encode(stamp_sent(msg))  # raw bytes: the sender-side validation is bypassed on purpose

    def tick(self, now_s: float) -> None:
        if now_s < self.t_next:
            return
        self.t_next = now_s + self.period_s
        kind = self.KINDS[self.n % len(self.KINDS)]
        key, data = self.message(kind, int(now_s * 1e9))
        try:
            self.bus.publish_raw(key, data)
            self.counts[kind] += 1
        except Exception as e:
            log.warning("malformed-detection injection failed: %s", e)
        self.n += 1


def _require(acks: dict, ids: list[str], what: str) -> None:
    missing = [d for d in ids if d not in acks]
    bad = {d: f"{a.result}: {a.reason}" for d, a in acks.items() if a.result in ("refused", "failed")}
    if missing or bad:
        raise SkycapError(f"{what}: no answer from {missing}, refused/failed by {bad}; see the logs folder")


def _camera_command() -> list[str] | None:
    """The simulator's per-drone camera node command, when it exists."""
    try:
        import importlib

        importlib.import_module("simulator.scene.node")
    except ModuleNotFoundError:
        return None
    return [sys.executable, "-m", "simulator.scene.node"]


# ------------------------------------------------------------------------------------------------------------
# The simulator node of the demo: ``skycap sim``'s SimWorld plus the ground truth (vehicles and, when the
# scene is available, the person) published as SimTruth on ``sim/truth``. ``skycap sim`` does not publish
# the truth (yet); this node does, in the simulator's own process, from a tick hook.
def _sim_node_main(argv: list[str] | None = None) -> int:
    import asyncio


    from comms.transport import Transport, TransportConfig
    from shared_msgs import SimTruth, VehicleTruth, keys
    from simulator.config import SimConfig
    from simulator.runner import SimWorld
    from skycap.frames import quat_wxyz_from_R
    from skycap.logsetup import setup_logging
    from skycap.config import load_config, save_config

    ap = argparse.ArgumentParser(prog="python -m apps.demo", description="the demo's simulator node")
    ap.add_argument("--fleet", default="demo")
    ap.add_argument("--zenoh-connect", default="tcp/127.0.0.1:7447")
    ap.add_argument("--truth-hz", type=float, default=50.0)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--gimbal-pitch-deg", type=float, default=None,
                    help="camera gimbal pitch reported in the truth (the simulator has no MAVLink gimbal yet)")
    ap.add_argument("--gps-jump", default=None, metavar="INDEX,AT_S,N,E,D",
                    help="fault injection: vehicle INDEX's position estimate jumps by (N, E, D) m AT_S seconds after "
                         "the start time of the first orbit plan seen on the fleet's plan key")
    ap.add_argument("--param-at", action="append", default=[], metavar="INDEX,AT_S,NAME,VALUE",
                    help="set vehicle INDEX's autopilot parameter NAME to VALUE AT_S seconds after the start time of "
                         "the first orbit plan (e.g. COM_OBL_RC_ACT=4: land on offboard loss); repeatable")
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args(argv)
    gimbal_rad = math.radians(args.gimbal_pitch_deg) if args.gimbal_pitch_deg is not None else 0.0
    setup_logging("INFO")
    cfg = load_config(SimConfig, overrides=args.set).validate()
    if args.out is not None:
        save_config(cfg, args.out / "logs" / "sim_config.toml")
    world = SimWorld(cfg)
    person = None
    try:
        from simulator.scene.config import PersonConfig
        from simulator.scene.person import PersonSim

        person = PersonSim(PersonConfig())
    except Exception as e:  # the scene is optional for the flight
        log.warning("no simulated person (%s): truth carries the vehicles only", e)
    bus = Transport.open(TransportConfig.local_peer(args.zenoh_connect), "sim")
    bus.declare_alive(keys.alive_key(args.fleet, keys.SIM))
    key = keys.sim_key(args.fleet, keys.TRUTH)
    zeros = tuple(0.0 for _ in range(51))

    def publish_truth(t_ns: int, truths) -> None:
        vehicles = [VehicleTruth(drone_id=f"drone_{v.index + 1}", position_ned_m=tuple(map(float, v.position_ned_m)),
                                 velocity_ned_m_s=tuple(map(float, v.velocity_ned_m_s)),
                                 q_world_body=tuple(map(float, quat_wxyz_from_R(v.R_world_body))),
                                 gimbal_pitch_rad=gimbal_rad)
                    for v in truths]
        extra = person.state_at(world.t_s).truth_fields() if person is not None else \
            dict(person_joints_ned_m=zeros, person_root_ned_m=(0.0, 0.0, 0.0))
        bus.publish(key, SimTruth(header=SimTruth.make_header(keys.SIM, t_ns), vehicles=vehicles, **extra))

    world.add_tick_hook(publish_truth, rate_hz=args.truth_hz)
    _schedule_faults(world, bus, args)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await world.run(stop, status_every_s=10.0)

    try:
        asyncio.run(main())
    finally:
        bus.close()
    log.info("simulator node stopped after %.1f s (%d overruns)", world.t_s, world.overruns)
    return 0


def _schedule_faults(world, bus, args) -> None:
    """The sim node's fault schedule (``--gps-jump``, ``--param-at``), relative to the start time of the first
    orbit plan seen on the fleet's plan key (converted to simulation time when it arrives)."""
    from shared_msgs import OrbitPlan, keys

    n = len(world.vehicles)
    jump = None
    if args.gps_jump:
        try:
            idx_s, at_s, *off = args.gps_jump.split(",")
            jump = (int(idx_s), float(at_s), [float(v) for v in off])
            if len(jump[2]) != 3 or not 0 <= jump[0] < n:
                raise ValueError
        except ValueError:
            raise SkycapError(f"--gps-jump {args.gps_jump!r}: give INDEX,AT_S,N,E,D with INDEX < {n}") from None
    params = []
    for text in args.param_at:
        try:
            idx_s, at_s, name, value = text.split(",")
            params.append((int(idx_s), float(at_s), name.strip(), float(value)))
            if not 0 <= params[-1][0] < n or world.vehicles[0].params.get(name.strip()) is None:
                raise ValueError
        except ValueError:
            raise SkycapError(f"--param-at {text!r}: give INDEX,AT_S,NAME,VALUE with INDEX < {n} and a known "
                              "parameter name") from None
    if jump is None and not params:
        return
    pending: list[tuple[float, int, str, float]] = []

    def on_plan(rx) -> None:  # Zenoh thread: schedule once, in simulation time
        if pending or getattr(on_plan, "done", False):
            return
        on_plan.done = True
        t0_sim = world.t_s + (rx.msg.start_time_ns * 1e-9 - time.time())
        if jump is not None:
            world.vehicles[jump[0]].schedule_gps_jump(t0_sim + jump[1], jump[2])
            log.warning("FAULT: GPS jump of vehicle %d by %s m scheduled at sim t=%.1f s", jump[0], jump[2], t0_sim + jump[1])
        pending.extend(sorted((t0_sim + at, i, name, v) for i, at, name, v in params))

    def apply_params(t_ns: int, truths) -> None:  # simulation loop
        while pending and pending[0][0] <= world.t_s:
            _, i, name, v = pending.pop(0)
            world.vehicles[i].params.set(name, v)
            log.warning("FAULT schedule: vehicle %d parameter %s = %s at sim t=%.1f s", i, name, v, world.t_s)

    world.add_tick_hook(apply_params, rate_hz=50.0)
    bus.subscribe(keys.gcs_key(args.fleet, keys.PLAN), on_plan, OrbitPlan)


if __name__ == "__main__":
    sys.exit(_sim_node_main())
