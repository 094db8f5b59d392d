"""The ground station's fleet model: everything the widgets show and every operator action, without Qt.

:class:`FleetModel` wraps a :class:`~groundstation.fleet.FleetClient` (states, healths, acks, presence, the
ground-station heartbeat) and adds what the app needs: thumbnails, detections and person estimates, link
ages, alerts kept in an event log, the pre-flight checklist, plan validation from the form's fields, and
commands whose per-drone results (accepted, completed, refused with reason, no answer) are tracked without
blocking. The Qt widgets only read :meth:`FleetModel.rows` etc. and call the action methods.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from groundstation.app.config import GsConfig
from groundstation.fleet import FleetClient, FleetError, make_orbit_plan
from shared_msgs import CameraFrame, Detections, GeofenceZone, KeepOutZone, OrbitPlan, TargetEstimate, keys
from shared_msgs.messages import CameraInfo, CameraStatus, FormationPlan, SimTruth
from skycap.frames import yaw_from_quat_wxyz

log = logging.getLogger(__name__)

__all__ = ["Check", "CommandRun", "DroneRow", "Event", "FleetModel", "PlanForm", "PLAN_MODES", "GPS_GRADES"]

#: MAVLink GPS_FIX_TYPE -> the grade shown
GPS_GRADES = {0: "no GPS", 1: "no fix", 2: "2D", 3: "3D", 4: "DGPS", 5: "RTK float", 6: "RTK fixed", 7: "static",
              8: "PPP"}
#: agent states in the air (commands that need the ground are refused by the agents themselves)
AIRBORNE = {"takeoff", "hover", "orbit", "track", "paused", "return", "landing"}
#: the operator's commands, QGroundControl's words -> the agents' actions
ACTIONS = {"takeoff": "Arm + take off", "start": "Start", "pause": "Pause", "land": "Land", "return": "Return"}
#: commands always sent, even to a drone whose link is stale: bringing it down must never be blocked
SAFE_ACTIONS = {"land", "return"}


@dataclass
class Event:
    t_wall_s: float
    level: str  #: "info", "warning", "alert"
    drone: str
    text: str

    def line(self) -> str:
        return f"{time.strftime('%H:%M:%S', time.localtime(self.t_wall_s))} {self.level.upper():7s} " \
               f"{self.drone or '-':9s} {self.text}"


@dataclass
class DroneRow:
    """One drone in the fleet panel; ``age_s`` is the time since its last state or health message."""

    drone: str
    present: bool
    age_s: float | None
    stale: bool
    lost: bool
    state: str = "-"
    mode: str = "-"
    armed: bool = False
    battery_frac: float | None = None
    gps: str = "-"
    satellites: int = 0
    position_std_m: float | None = None
    setpoint_hz: float = 0.0
    state_hz: float = 0.0
    recorder: str = "-"  #: the fleet panel's text: file, MB written, dropped, free space (or why none)
    detector: str = "-"
    #: the agent's recorder (Health v2; None: not reported)
    recorder_file: str | None = None
    recorder_mb: float | None = None  #: MB (1e6 bytes) the current recording has written
    recorder_dropped: int | None = None
    free_disk_gb: float | None = None  #: the recording folder's free space (GB = 1e9 bytes); None: unknown
    tracker: str = "-"
    warnings: list[str] = field(default_factory=list)
    north_m: float = 0.0
    east_m: float = 0.0
    altitude_m: float = 0.0
    yaw_rad: float = 0.0
    ok: bool = False


@dataclass
class Check:
    name: str
    ok: bool
    detail: str


PLAN_MODES = {"orbit": "Orbit", "track": "Tracking formation"}


@dataclass
class PlanForm:
    """The plan form's fields, as the operator typed them.

    ``mode = "orbit"``: the drones circle ``center`` at ``radius_m`` / ``altitude_m`` and ``speed_m_s``.
    ``mode = "track"`` (a tracking formation, flown by agents in track mode: they find the person in their cameras,
    fuse their detections and keep their slots around the fused estimate): ``center`` is the operator's start
    guess of the person (where the drones look until the first detection is fused), ``radius_m`` / ``altitude_m``
    the stand-off kept from the person, the slots equally spaced around them; ``speed_m_s`` and ``direction`` are
    not used."""

    center_north_m: float = 0.0
    center_east_m: float = 0.0
    radius_m: float = 8.0
    altitude_m: float = 6.0
    speed_m_s: float = 1.2  #: along the circle
    direction: int = 1  #: 1 clockwise from above, -1 anticlockwise
    drones: list[str] = field(default_factory=list)
    min_separation_m: float = 3.0
    mode: str = "orbit"  #: "orbit" or "track"


@dataclass
class CommandRun:
    """A command (or a plan) sent to ``targets``: each drone's result is read from the acks as they arrive."""

    action: str
    targets: list[str]
    command_ids: dict[str, str]  #: drone -> command id (plan id for a plan)
    t_sent_s: float
    timeout_s: float
    refused_here: dict[str, str] = field(default_factory=dict)  #: drone -> why the app did not send it
    override: bool = False

    def results(self, acks, now_s: float) -> dict[str, tuple[str, str]]:
        """{drone: (result, reason)}: completed > failed > refused > accepted; "no answer" after the timeout,
        "waiting" before; "not sent" for the drones the app refused."""
        rank = {"completed": 4, "failed": 3, "refused": 2, "accepted": 1}
        out: dict[str, tuple[str, str]] = {d: ("not sent", r) for d, r in self.refused_here.items()}
        best: dict[str, tuple[int, str, str]] = {}
        for a in acks:
            d = a.header.sender_id
            if self.command_ids.get(d) != a.command_id:  # a plan's id is shared by its drones: match both
                continue
            r = rank.get(a.result, 0)
            if r > best.get(d, (0, "", ""))[0]:
                best[d] = (r, a.result, a.reason)
        for d in self.command_ids:
            if d in best:
                out[d] = (best[d][1], best[d][2])
            elif now_s - self.t_sent_s >= self.timeout_s:
                out[d] = ("no answer", f"no answer within {self.timeout_s:.0f} s")
            else:
                out[d] = ("waiting", "")
        return out

    def done(self, acks, now_s: float) -> bool:
        return all(r not in ("waiting",) for r, _ in self.results(acks, now_s).values())

    def summary(self, acks, now_s: float) -> str:
        res = self.results(acks, now_s)
        return ", ".join(f"{d}: {r}{' (' + why + ')' if why and r != 'no answer' else ''}"
                         for d, (r, why) in sorted(res.items()))


NOT_REPORTED = "not reported (the agent's health has no {what}: an older agent, update it; or override)"


def recorder_text(rs) -> str:
    """The fleet panel's recorder cell from a Health ``recorder`` (:class:`shared_msgs.RecorderStatus` or None)."""
    if rs is None:
        return "not reported"
    free = f"{rs.free_disk_bytes / 1e9:.1f} GB free" if rs.free_disk_bytes >= 0 else "free space unknown"
    if not rs.recording:
        return f"NOT recording ({rs.error or 'no reason given'}), {free}"
    text = f"{rs.file}, {rs.bytes_written / 1e6:.1f} MB, {rs.dropped} dropped, {free}"
    return text if rs.ok else f"ERROR {rs.error}; {text}"


def tracker_text(t: TargetEstimate) -> str:
    """The fleet panel's tracker cell from a drone's fused person estimate: status, sources fused, where (local NED
    north / east m) and the 1-sigma horizontal position uncertainty."""
    cov = t.covariance
    sigma = math.sqrt(max(0.0, cov[0]) + max(0.0, cov[7])) if len(cov) >= 36 else float("nan")
    n, e = t.position_ned_m[0], t.position_ned_m[1]
    return f"{t.status} ({t.num_sources} src) at ({n:.1f}, {e:.1f}) ±{sigma:.1f} m"


def detector_text(ds) -> str:
    """The fleet panel's detector cell from a Health ``detector`` (:class:`shared_msgs.DetectorStatus` or None)."""
    if ds is None:
        return "not reported"
    if not ds.required:
        return f"not needed: {ds.model}"
    if ds.loaded:
        return f"{ds.model} loaded, {ds.rate_hz:.0f} Hz"
    return f"{ds.model} NOT loaded" + (f": {ds.error}" if ds.error else "")


def recorder_space_check(h, min_free_disk_gb: float) -> Check:
    """The checklist's "recorder space" from a drone's latest Health (None: none received): passes only when the
    drone records, its recorder reports no error and the recording folder has at least ``min_free_disk_gb``."""
    name = "recorder space"
    if h is None:
        return Check(name, False, "no health received from the agent")
    rs = h.recorder
    if rs is None:
        return Check(name, False, NOT_REPORTED.format(what="recorder status"))
    need = f"need ≥ {min_free_disk_gb:g} GB"
    if not rs.ok:
        return Check(name, False, f"recorder error: {rs.error or 'no reason given'}")
    if not rs.recording:
        return Check(name, False, f"not recording: {rs.error or 'no reason given'}")
    if rs.free_disk_bytes < 0:
        return Check(name, False, f"free space unknown{': ' + rs.error if rs.error else ' (not measured yet)'} ({need})")
    free_gb = rs.free_disk_bytes / 1e9
    detail = f"{free_gb:.1f} GB free ({need}); {rs.file}: {rs.bytes_written / 1e6:.1f} MB, {rs.dropped} dropped"
    if free_gb < min_free_disk_gb:
        return Check(name, False, f"too little space: {detail}")
    return Check(name, True, detail)


def detector_check(h, require_detector: bool) -> Check:
    """The checklist's "detector" from a drone's latest Health: passes when the drone's ONNX model is loaded or it
    reports needing none (unless ``require_detector``); fails when a model is expected and not loaded."""
    name = "detector"
    if h is None:
        return Check(name, False, "no health received from the agent")
    ds = h.detector
    if ds is None:
        return Check(name, False, NOT_REPORTED.format(what="detector status"))
    if ds.required:
        if ds.loaded:
            return Check(name, True, f"{ds.model} loaded, {ds.rate_hz:.1f} Hz")
        return Check(name, False, f"{ds.model} expected, NOT loaded" + (f": {ds.error}" if ds.error else ""))
    if require_detector:
        return Check(name, False, f"no onboard detector ({ds.model}) but checklist.require_detector is set")
    return Check(name, True, f"not needed: {ds.model}")


class FleetModel:
    """The app's fleet model over ``client`` (a :class:`FleetClient`); ``clock`` is monotonic seconds."""

    def __init__(self, client: FleetClient, cfg: GsConfig, clock: Callable[[], float] = time.monotonic):
        self.client = client
        self.cfg = cfg
        self.clock = clock
        self.fleet = client.fleet
        self._lock = threading.Lock()
        self.thumbs: dict[str, CameraFrame] = {}
        self.thumb_rx: dict[str, float] = {}
        self.thumb_count: dict[str, int] = {}
        self.detections: dict[str, Detections] = {}
        self.camera_info: dict[str, CameraInfo] = {}
        self.camera_status: dict[str, CameraStatus] = {}
        self.targets: dict[str, TargetEstimate] = {}
        self.formation: dict[str, FormationPlan] = {}  #: track mode: each drone's planned positions (MPC horizon)
        self.truth: SimTruth | None = None
        #: a live (17, 3) COCO-17 skeleton, NED metres, drawn by the 3D tab: nothing fills it yet; a future live
        #: triangulation of the drones' published keypoints would set it here (None = no live skeleton)
        self.live_skeleton_ned = None
        self.events: list[Event] = []
        self.runs: list[CommandRun] = []
        self.plan: OrbitPlan | None = None  #: the plan shown (the last sent, until every drone refused it)
        self._plan_before: OrbitPlan | None = None
        self._plan_run: CommandRun | None = None
        self.overrides: dict[str, str] = {}  #: drone -> why the operator overrode its failing checklist
        self._seen: dict[str, dict] = {}  #: per drone: what was already alerted (edge-triggered alerts)
        self._acks_seen = 0
        bus = client.bus
        f = self.fleet
        self._subs = [
            bus.subscribe(keys.all_drones_key(f, keys.CAMERA_THUMB), self._on_thumb, CameraFrame),
            bus.subscribe(keys.all_drones_key(f, keys.CAMERA_INFO), self._on_put("camera_info"), CameraInfo),
            bus.subscribe(keys.all_drones_key(f, keys.CAMERA_STATUS), self._on_put("camera_status"), CameraStatus),
            bus.subscribe(keys.all_drones_key(f, keys.TARGET), self._on_put("targets"), TargetEstimate),
            bus.subscribe(keys.all_drones_key(f, keys.DETECTIONS), self._on_put("detections"), Detections),
            bus.subscribe(keys.all_drones_key(f, keys.SIM_DETECTIONS), self._on_put("detections"), Detections),
            bus.subscribe(keys.all_drones_key(f, keys.FORMATION_PLAN), self._on_put("formation"), FormationPlan),
            bus.subscribe(keys.sim_key(f, keys.TRUTH), self._on_truth, SimTruth),
        ]
        self.event_file = None
        if cfg.event_log:
            from pathlib import Path

            path = Path(cfg.flights_dir) / cfg.event_log
            path.parent.mkdir(parents=True, exist_ok=True)
            self.event_file = open(path, "a", buffering=1)
        self.log_event("info", "", f"ground station joined fleet {f!r} ({'mutual TLS, gcs certificate' if bus.secure else 'INSECURE plaintext'}); heartbeat {client.heartbeat_hz:g} Hz")

    # --- inputs (Zenoh threads) -------------------------------------------------------------------
    def _on_thumb(self, rx) -> None:
        d = keys.parse_key(rx.key)[1]
        with self._lock:
            self.thumbs[d] = rx.msg
            self.thumb_rx[d] = self.clock()
            self.thumb_count[d] = self.thumb_count.get(d, 0) + 1

    def _on_put(self, name: str):
        store = getattr(self, name)

        def put(rx) -> None:
            with self._lock:
                store[keys.parse_key(rx.key)[1]] = rx.msg
        return put

    def _on_truth(self, rx) -> None:
        self.truth = rx.msg

    # --- events -----------------------------------------------------------------------------------
    def log_event(self, level: str, drone: str, text: str) -> Event:
        ev = Event(time.time(), level, drone, text)
        with self._lock:
            self.events.append(ev)
            if self.event_file is not None:
                self.event_file.write(ev.line() + "\n")
        (log.warning if level != "info" else log.info)("%s %s", drone or "gcs", text)
        return ev

    def alerts(self) -> list[Event]:
        return [e for e in self.events if e.level == "alert"]

    def poll_alerts(self) -> None:
        """Turn changes into events: link lost / back, failsafe warnings, low battery, refused or failed acks."""
        now = self.clock()
        for r in self.rows():
            seen = self._seen.setdefault(r.drone, {"lost": False, "warnings": set(), "low_batt": False})
            if r.lost and not seen["lost"]:
                self.log_event("alert", r.drone, f"LINK LOST: no message for {r.age_s:.1f} s")
            elif not r.lost and seen["lost"]:
                self.log_event("info", r.drone, "link back")
            seen["lost"] = r.lost
            for w in r.warnings:
                if w not in seen["warnings"]:
                    seen["warnings"].add(w)
                    self.log_event("alert", r.drone, f"FAILSAFE / warning: {w}")
            low = r.battery_frac is not None and r.battery_frac < self.cfg.checklist.min_battery_frac * 0.6
            if low and not seen["low_batt"]:
                self.log_event("alert", r.drone, f"LOW BATTERY: {100 * r.battery_frac:.0f} %")
            seen["low_batt"] = low
        acks = self.client.acks
        for a in acks[self._acks_seen:]:
            if a.result in ("refused", "failed"):
                self.log_event("alert", a.header.sender_id, f"{a.result.upper()}: {a.command_id}: {a.reason}")
            else:
                self.log_event("info", a.header.sender_id, f"{a.result}: {a.command_id}")
        self._acks_seen = len(acks)
        for run in self.runs:
            if not getattr(run, "_timeouts_logged", False) and now - run.t_sent_s >= run.timeout_s:
                run._timeouts_logged = True  # type: ignore[attr-defined]
                for d, (res, why) in run.results(acks, now).items():
                    if res == "no answer":
                        self.log_event("alert", d, f"NO ANSWER to {run.action} within {run.timeout_s:.0f} s")
        self._check_plan_refused(acks, now)

    def _plan_accepted(self, run: CommandRun) -> bool:
        return any(r == "accepted" for r, _ in run.results(list(self.client.acks), self.clock()).values())

    def _check_plan_refused(self, acks, now: float) -> None:
        """Every drone answered the last plan and none accepted it: the map shows the plan before it again."""
        run = self._plan_run
        if run is None or self.plan is None or not run.done(acks, now) or getattr(run, "_refusal_seen", False):
            return
        run._refusal_seen = True  # type: ignore[attr-defined]
        if not any(r == "accepted" for r, _ in run.results(acks, now).values()):
            refused = self.plan
            self.plan = self._plan_before
            self.log_event("alert", "", f"plan {refused.plan_id} accepted by no drone: not shown on the map"
                           + (f"; the map shows plan {self.plan.plan_id} again" if self.plan else ""))

    # --- views ------------------------------------------------------------------------------------
    def drone_ids(self) -> list[str]:
        c = self.client
        with c._lock:
            ids = set(c.states) | {d for d, h in c.healths.items() if h.role == "agent"}
            ids |= {d for d in c.alive if d not in (keys.GCS, keys.SIM)} & (set(c.states) | set(c.healths))
        from flightdata.folder import natural_key
        return sorted(ids, key=natural_key)

    def row(self, d: str) -> DroneRow:
        c, ui, now = self.client, self.cfg.ui, self.clock()
        with c._lock:
            s, h, t = c.states.get(d), c.healths.get(d), c.last_rx_s.get(d)
            present = d in c.alive
        age = None if t is None else now - t
        r = DroneRow(drone=d, present=present, age_s=age, stale=age is None or age > ui.stale_s,
                     lost=age is not None and age > ui.link_lost_s)
        if s is not None:
            r.mode, r.armed, r.battery_frac = s.flight_mode, s.armed, s.battery_remaining_frac
            r.gps = GPS_GRADES.get(s.gps_fix_type, str(s.gps_fix_type))
            r.satellites = s.gps_num_satellites
            r.position_std_m = math.sqrt(max(0.0, s.position_cov_m2[0]) + max(0.0, s.position_cov_m2[1]))
            n, e, dn = s.position_ned_m
            r.north_m, r.east_m, r.altitude_m = n, e, -dn
            r.yaw_rad = yaw_from_quat_wxyz(s.q_world_body)
            r.ok = s.health_ok
        if h is not None:
            r.state = h.state
            r.warnings = list(h.warnings)
            rates = h.rates_hz
            r.setpoint_hz, r.state_hz = rates.get("setpoint", 0.0), rates.get("state", 0.0)
            r.recorder = recorder_text(h.recorder)
            rs = h.recorder
            if rs is not None:
                r.recorder_file = rs.file if rs.recording else None
                r.recorder_mb = rs.bytes_written / 1e6 if rs.recording else None
                r.recorder_dropped = rs.dropped if rs.recording else None
                r.free_disk_gb = rs.free_disk_bytes / 1e9 if rs.free_disk_bytes >= 0 else None
            r.detector = detector_text(h.detector)
            r.ok = r.ok and h.ok
        with self._lock:
            tgt = self.targets.get(d)
            st = self.camera_status.get(d)
        if tgt is not None:
            r.tracker = tracker_text(tgt)
        if st is not None:
            r.recorder += f", cam dropped {st.dropped}"
        return r

    def person_estimate(self) -> TargetEstimate | None:
        """The fleet's person estimate to show: the newest of the drones' fused estimates that is tracking (else the
        newest of any status); None before any drone published one."""
        with self._lock:
            ests = list(self.targets.values())
        if not ests:
            return None
        return max(ests, key=lambda t: (t.status == "tracking", t.header.t_measurement_ns))

    def rows(self) -> list[DroneRow]:
        return [self.row(d) for d in self.drone_ids()]

    def checklist(self, d: str) -> list[Check]:
        """Pre-flight checks of drone ``d`` from its latest state and health."""
        cc = self.cfg.checklist
        r = self.row(d)
        with self.client._lock:
            s = self.client.states.get(d)
        checks = [Check("link", not r.stale and r.age_s is not None,
                        "no message yet" if r.age_s is None else f"last message {r.age_s:.1f} s ago"
                        + (" (stale)" if r.stale else ""))]
        if s is None:
            checks.append(Check("position fix", False, "no vehicle state received"))
        else:
            fix_ok = s.gps_fix_type >= cc.min_gps_fix_type and (r.position_std_m or 99) <= cc.max_position_std_m
            checks.append(Check("position fix", fix_ok, f"{r.gps}, {s.gps_num_satellites} sats, "
                                f"±{r.position_std_m:.2f} m (need ≥ {GPS_GRADES.get(cc.min_gps_fix_type)}, "
                                f"≤ {cc.max_position_std_m:g} m)"))
            checks.append(Check("battery", s.battery_remaining_frac >= cc.min_battery_frac,
                                f"{100 * s.battery_remaining_frac:.0f} % (need ≥ {100 * cc.min_battery_frac:.0f} %)"))
            checks.append(Check("autopilot health", s.health_ok, "global position, home and armable"
                                + (" ok" if s.health_ok else " NOT ok")))
        with self.client._lock:
            h = self.client.healths.get(d)
        frame_hz = h.rates_hz.get("frame", 0.0) if h else 0.0
        with self._lock:
            has_info = d in self.camera_info
        cam_ok = frame_hz > 0.5 or has_info
        checks.append(Check("camera", cam_ok or not cc.require_camera,
                            f"frames {frame_hz:.1f} Hz{', camera_info received' if has_info else ''}"
                            + ("" if cc.require_camera else " (not required)")))
        checks.append(detector_check(h, cc.require_detector))
        checks.append(recorder_space_check(h, cc.min_free_disk_gb))
        return checks

    def checklist_ok(self, d: str) -> bool:
        return all(c.ok for c in self.checklist(d))

    def override_checklist(self, d: str, reason: str) -> None:
        """The operator arms ``d`` despite failing checks: logged with the checks that failed."""
        failing = [f"{c.name}: {c.detail}" for c in self.checklist(d) if not c.ok]
        self.overrides[d] = reason or "operator override"
        self.log_event("alert", d, f"CHECKLIST OVERRIDE by the operator ({reason or 'no reason given'}); "
                       f"failing: {'; '.join(failing) or 'none'}")

    # --- plans ------------------------------------------------------------------------------------
    def geofence_zone(self) -> GeofenceZone:
        """The configured fence as the plan carries it (around the local frame's origin)."""
        g = self.cfg.geofence
        return GeofenceZone(center_ne_m=(0.0, 0.0), radius_m=float(g.radius_m), min_altitude_m=float(g.min_altitude_m),
                            max_altitude_m=float(g.max_altitude_m))

    def keepout_zones(self) -> list[KeepOutZone]:
        """The configured keep-out zones as the plan carries them."""
        return [KeepOutZone(name=z.name, north_m=float(z.north_m), east_m=float(z.east_m), radius_m=float(z.radius_m))
                for z in self.cfg.keepout_zones]

    def validate_plan(self, form: PlanForm) -> tuple[OrbitPlan | None, str]:
        """(plan, "") or (None, the reason): field values, geofence, separation, duplicates, then the agents'
        own checks (:func:`groundstation.fleet.check_plan`: with the fence and the keep-out zones, the agents' own
        :func:`onboard.zones.plan_zone_violation`: the orbit circle, or each formation slot, outside the fence or in
        a zone)."""
        g = self.cfg.geofence
        if form.mode not in PLAN_MODES:
            return None, f"plan mode {form.mode!r}: use {' or '.join(PLAN_MODES)}"
        track = form.mode == "track"
        if not form.drones:
            return None, "select at least one drone for the plan"
        dup = sorted({d for d in form.drones if form.drones.count(d) > 1})
        if dup:
            return None, f"drone {', '.join(dup)} named more than once: one slot per drone"
        for name in ("center_north_m", "center_east_m", "radius_m", "altitude_m", "speed_m_s", "min_separation_m"):
            v = getattr(form, name)
            if not math.isfinite(v):
                return None, f"{name} = {v} is not a number"
        if form.radius_m <= 0:
            return None, (f"radius_m = {form.radius_m:g}: the "
                          f"{'stand-off radius' if track else 'radius'} must be positive")
        if not track and form.speed_m_s < 0:  # a tracking formation does not turn: speed not used
            return None, f"speed_m_s = {form.speed_m_s:g}: the speed must be ≥ 0 (direction sets the sense)"
        if not g.min_altitude_m <= form.altitude_m <= g.max_altitude_m:
            return None, (f"altitude_m = {form.altitude_m:g} is outside the fence's band "
                          f"{g.min_altitude_m:g}..{g.max_altitude_m:g} m")
        if not track and math.hypot(form.center_north_m, form.center_east_m) + form.radius_m > g.radius_m:
            return None, (f"the orbit (centre {form.center_north_m:g}, {form.center_east_m:g} m, radius "
                          f"{form.radius_m:g} m) leaves the fence's {g.radius_m:g} m circle")
        if track and math.hypot(form.center_north_m, form.center_east_m) > g.radius_m:
            return None, (f"the person's start guess ({form.center_north_m:g}, {form.center_east_m:g} m) is outside "
                          f"the fence's {g.radius_m:g} m circle")
        n = len(form.drones)
        if n > 1:
            chord = 2 * form.radius_m * math.sin(math.pi / n)
            if chord < form.min_separation_m:
                return None, (f"separation not feasible: {n} drones on a {form.radius_m:g} m "
                          f"{'stand-off circle' if track else 'circle'} are "
                              f"{chord:.1f} m apart, under min_separation_m = {form.min_separation_m:g} m; "
                              f"use a radius ≥ {form.min_separation_m / (2 * math.sin(math.pi / n)):.1f} m")
        if form.direction not in (1, -1):
            return None, f"direction = {form.direction}: 1 (clockwise) or -1"
        try:
            plan = make_orbit_plan(form.drones, (form.center_north_m, form.center_east_m, 0.0), form.radius_m,
                                   form.altitude_m, 0.0 if track else form.speed_m_s / form.radius_m,
                                   form.direction, min_separation_m=form.min_separation_m, mode=form.mode,
                                   geofence=self.geofence_zone(), keepout_zones=self.keepout_zones())
        except FleetError as e:  # the agents' own rules; the form shows "NOT SENT" already, without the plan's id
            return None, re.sub(r"^plan \S+ not sent: ", "", str(e))
        return plan, ""

    def send_plan(self, form: PlanForm) -> tuple[CommandRun | None, str]:
        plan, why = self.validate_plan(form)
        if plan is None:
            self.log_event("warning", "", f"plan not sent: {why}")
            return None, why
        self.client.send_plan(plan)
        if self.plan is not None and self._plan_run is not None and self._plan_accepted(self._plan_run):
            self._plan_before = self.plan  # the plan some drone flies: shown again if every drone refuses this one
        self.plan = plan
        run = CommandRun("plan", list(form.drones), {d: plan.plan_id for d in form.drones}, self.clock(),
                         self.cfg.ui.command_timeout_s)
        self.runs.append(run)
        self._plan_run = run
        what = (f"tracking formation, start guess ({form.center_north_m:g}, {form.center_east_m:g}) m, stand-off "
                f"{plan.radius_m:g} m" if form.mode == "track" else
                f"orbit, radius {plan.radius_m:g} m, {form.speed_m_s:g} m/s")
        self.log_event("info", "", f"plan {plan.plan_id} ({what}, altitude {plan.altitude_m:g} m; fence "
                       f"{self.cfg.geofence.radius_m:g} m and {len(plan.keepout_zones)} keep-out zone(s) sent with it) "
                       f"sent to {', '.join(form.drones)}")
        return run, ""

    # --- commands ---------------------------------------------------------------------------------
    def precheck(self, action: str, targets: list[str]) -> dict[str, str]:
        """{drone: why the app will not send ``action`` to it}: stale link (except land / return), failing
        checklist for take-off without an override."""
        out = {}
        for d in targets:
            r = self.row(d)
            if action not in SAFE_ACTIONS and r.stale:
                out[d] = ("link stale: " + ("no message yet" if r.age_s is None else
                                            f"last message {r.age_s:.1f} s ago") + " (land / return are still sent)")
            elif action == "takeoff" and d not in self.overrides and not self.checklist_ok(d):
                failing = ", ".join(c.name for c in self.checklist(d) if not c.ok)
                out[d] = f"pre-flight checklist failing ({failing}): fix it or override (logged)"
        return out

    def command(self, action: str, targets: list[str], params: dict[str, float] | None = None) -> CommandRun:
        """Send ``action`` to each of ``targets`` (one command per drone, so that each answer is its own) unless
        :meth:`precheck` refuses it; never blocks: read the results from :meth:`CommandRun.results`."""
        if action not in ACTIONS and action not in ("arm", "disarm"):
            raise FleetError(f"unknown action {action!r}: one of {', '.join(ACTIONS)}")
        if not targets:
            raise FleetError(f"'{action}': select at least one drone (or use the land-all button)")
        refused = self.precheck(action, targets)
        ids = {}
        for d in targets:
            if d in refused:
                continue
            ids[d] = self.client.send_command(action, d, params).command_id
        run = CommandRun(action, list(targets), ids, self.clock(), self.cfg.ui.command_timeout_s,
                         refused_here=refused, override=any(d in self.overrides for d in targets))
        self.runs.append(run)
        self.log_event("info", "", f"{ACTIONS.get(action, action)} sent to {', '.join(ids) or 'nobody'}"
                       + (f"; not sent to {', '.join(f'{d} ({w})' for d, w in refused.items())}" if refused else ""))
        for d, why in refused.items():
            self.log_event("alert", d, f"{action} NOT SENT: {why}")
        return run

    def land_all(self) -> CommandRun:
        """Land every drone known (one action, no confirmation: bringing the fleet down is never blocked)."""
        targets = self.drone_ids()
        if not targets:
            self.log_event("alert", "", "LAND ALL: no drone known to land")
        ids = {d: self.client.send_command("land", d).command_id for d in targets}
        run = CommandRun("land", targets, ids, self.clock(), self.cfg.ui.command_timeout_s)
        self.runs.append(run)
        self.log_event("alert", "", f"LAND ALL sent to {', '.join(targets) or 'nobody'}")
        return run

    def results(self, run: CommandRun) -> dict[str, tuple[str, str]]:
        return run.results(list(self.client.acks), self.clock())

    def close(self) -> None:
        for s in self._subs:
            try:
                s.close()
            except Exception:
                pass
        if self.event_file is not None:
            self.event_file.close()
            self.event_file = None
