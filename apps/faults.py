"""``skycap faults run``: the fault suite -- the simulated fleet flown through named fault scenarios, each judged.

    skycap faults run --out /tmp/faults                          # every scenario
    skycap faults run --scenario gcs_link_lost --scenario gps_jump_3m --out /tmp/faults
    skycap faults run --out /tmp/faults --set demo.drones=3 --set demo.duration_s=40
    skycap faults list                                           # the scenarios and what each injects

Each scenario is one ``skycap demo`` flight (:func:`apps.demo.run_demo`, the same launcher: simulator, camera
nodes, agent processes, the fleet client) with the scenario's ``faults.*`` (and a few other) overrides on the
suite's base demo configuration (``demo.*``), into ``DIR/<scenario>/``. Fault times count from the orbit plan's
start. The flight is then judged (:mod:`evaluation.faults`):

* ``safe``: from the simulator's truth -- separation never below the plan's ``min_separation_m``, no drone
  outside the geofence (``geofence_radius_m`` around the orbit centre, ``geofence_max_alt_m``), no landing
  before the final land command other than the scenario's policy expects (``landing_by_policy``);
* ``recording_lost_s``: per drone, the gaps in its recorded state + camera streams (across the files of an
  agent restart) between the plan's start and the final land command (or its touchdown); a crash scenario
  (``crash``) may lose up to ``max_lost_per_crash_s`` (1 s), the others none (``recording_ok``);
* what the drones did (how each flight ended, failsafe warnings in their health, the launcher's fault report)
  and the messages each agent's transport refused, and why (``<drone>.s<NNN>.transport.json``).

Writes ``DIR/faults.json`` (``{"scenarios": [{"name", "safe", "recording_lost_s", "what_happened", ...}]}``),
``DIR/config.toml`` (this suite's resolved configuration) and the table (printed, and ``DIR/faults.txt``). A scenario that cannot run yet
says so (``"safe": null``, ``what_happened``: why) and is not flown. Exit code 0 when every scenario that ran
was safe and within its recording budget, 1 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from apps.demo import DemoConfig
from skycap.ports import free_tcp_port, free_udp_base
from skycap.config import ConfigError, add_config_args, config_from_args, load_config, save_config
from skycap.errors import SkycapError

log = logging.getLogger("apps.faults")

__all__ = ["FaultsConfig", "SCENARIOS", "Scenario", "format_faults_table", "register", "run_faults", "run_scenario"]


@dataclass(frozen=True)
class Scenario:
    """One named fault scenario."""

    name: str
    #: what is injected, in words
    injects: str
    #: ``--set`` overrides of the demo configuration (``faults.*`` and others); ``{d1}`` / ``{dlast}`` name
    #: the first / last drone
    sets: tuple[str, ...] = ()
    #: the drones whose landing before the final land command is the expected policy ("*": every drone)
    landing_by_policy: tuple[str, ...] = ()
    #: a crash (an agent or its recorder dies): up to ``max_lost_per_crash_s`` of recording may be lost
    crash: bool = False
    #: why it cannot run yet (not flown; reported with "safe": null)
    not_run: str = ""
    #: the fault leaves nowhere to record (disk full): the faulted drone's recording is judged up to the fault
    #: (none of it may be lost); what could not be recorded after it is reported, not judged
    nowhere_to_record_after_fault: bool = False


#: the scenarios, in the order they run
SCENARIOS: dict[str, Scenario] = {s.name: s for s in [
    Scenario("message_loss_30pct", "30 % of the messages each agent receives from its teammates dropped (state, "
             "health, detections, formation plans, targets)", ("faults.drop_prob=0.3",)),
    Scenario("delay_200ms", "every message from a teammate delivered 200 ms late (state, health, detections, "
             "formation plans, targets)",
             ("faults.detection_delay_s=0.2",
              'agent_set=["transport.fault.delay_topics=[\\"state\\", \\"health\\", \\"detections\\", '
              '\\"formation/plan\\", \\"target\\"]"]')),
    Scenario("agent_sigkill_restart", "{dlast}'s agent SIGKILLed mid-orbit (10 s after the start) and restarted at "
             "once (a warm standby agent woken, as a supervisor would); its vehicle holds meanwhile (offboard-loss "
             "action), the new agent takes it over (safety.on_restart_airborne = resume) and is sent the plan and "
             "start again",
             ('faults.kill_agent="{dlast}"', "faults.kill_agent_at_s=10", "faults.restart_agent_after_s=0",
              'agent_set=["safety.on_restart_airborne=\\"resume\\""]'),
             crash=True),
    Scenario("gcs_link_lost", "the ground station's link lost 10 s after the start (its heartbeat stops for good): "
             "the agents land by policy (safety.gcs_loss_action = land)",
             ("faults.gcs_link_lost_at_s=10",), landing_by_policy=("*",)),
    Scenario("mavlink_link_lost_3s", "{d1}'s MAVLink link (vehicle <-> agent) carries nothing for 3 s from 10 s "
             "after the start: the autopilot's offboard-loss action (hold), then the agent resumes the orbit",
             ('faults.mavlink_loss_drone="{d1}"', "faults.mavlink_loss_at_s=10", "faults.mavlink_loss_s=3")),
    Scenario("gps_jump_3m", "{dlast}'s position estimate jumps 3 m north 10 s after the start (the simulator's "
             "estimator)", ('faults.gps_jump_drone="{dlast}"', "faults.gps_jump_at_s=10",
                            "faults.gps_jump_ned_m=[3.0, 0.0, 0.0]")),
    Scenario("malformed_flood", "from the start, 50 malformed messages/s on the keys every agent listens to (NaN and "
             "garbage teammate states and ground-station commands) and 10/s malformed detections (NaN / inverted "
             "boxes, broken poses)", ("faults.malformed_flood_hz=50", "faults.malformed_detections_hz=10")),
    Scenario("outsider_without_certificate", "from 5 s after the start, for 10 s, a node without the fleet's "
             "certificate (plaintext tcp, and mutual TLS with a foreign CA's 'gcs' certificate) subscribes to the "
             "whole fleet (snoop) and sends 'land' to every drone twice a second",
             ("faults.outsider_at_s=5", "faults.outsider_s=10")),
    Scenario("recorder_disk_full", "{d1}'s recording disk is full from 10 s after the start (simulated in the "
             "recorder: every further write fails with ENOSPC, no new file can be created): the drone keeps "
             "flying, reports it in its health, and what was written stays readable",
             ('faults.recorder_fault_drone="{d1}"', 'faults.recorder_fault="disk_full"', "faults.recorder_fault_at_s=10"),
             nowhere_to_record_after_fault=True),
    Scenario("recorder_killed", "{d1}'s recorder writer thread killed 10 s after the start (an injected error): the "
             "agent reports it and records on into a new file",
             ('faults.recorder_fault_drone="{d1}"', 'faults.recorder_fault="killed"', "faults.recorder_fault_at_s=10"),
             crash=True),
]}


def _base_demo() -> DemoConfig:
    return DemoConfig(drones=2, duration_s=30.0, reconstruct=False, fleet="faults")


@dataclass
class FaultsConfig:
    """Configuration of ``skycap faults run`` (``--config faults.toml``, ``--set demo.drones=3``)."""

    #: the output folder (new, or empty)
    out: str = ""
    #: the scenarios to run (empty: every one, in the registry's order)
    scenarios: list[str] = field(default_factory=list)
    #: the base demo configuration of every scenario (its ``faults`` are the scenario's)
    demo: DemoConfig = field(default_factory=_base_demo)
    #: pick free Zenoh and MAVLink ports for each scenario (else: ``demo.zenoh_endpoint`` / ``demo.mavlink_base``)
    free_ports: bool = True
    #: the geofence: horizontal radius around the orbit centre (m) and the ceiling (m above ground)
    geofence_radius_m: float = 20.0
    geofence_max_alt_m: float = 15.0
    #: recording lost: a gap longer than this in a drone's recorded streams counts (s)
    max_gap_s: float = 0.5
    #: recording a crash scenario may lose per drone (s); the others: none
    max_lost_per_crash_s: float = 1.0

    def validate(self) -> "FaultsConfig":
        unknown = [s for s in self.scenarios if s not in SCENARIOS]
        if unknown:
            raise ConfigError(f"unknown scenario(s) {unknown}; the scenarios: {', '.join(SCENARIOS)}")
        if self.geofence_radius_m <= 0 or self.geofence_max_alt_m <= 0 or self.max_gap_s <= 0:
            raise ConfigError("geofence_radius_m, geofence_max_alt_m and max_gap_s must be > 0")
        self.demo.validate()
        if self.demo.sorties != 1:
            raise ConfigError("demo.sorties: the fault scenarios fly one sortie each")
        return self


# --------------------------------------------------------------------------------------------- CLI
def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("faults", help="the fault suite: fly the simulated fleet through named fault scenarios",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    fsub = p.add_subparsers(dest="faults_command", metavar="ACTION")
    r = fsub.add_parser("run", help="run scenarios (default: all) and write DIR/faults.json",
                        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("--scenario", action="append", default=None, choices=list(SCENARIOS), metavar="NAME",
                   help=f"a scenario to run (repeatable; default all): {', '.join(SCENARIOS)}")
    r.add_argument("--out", type=Path, default=None, help="the output folder (new or empty)")
    add_config_args(r)
    r.set_defaults(func=_run)
    ls = fsub.add_parser("list", help="list the scenarios")
    ls.set_defaults(func=_list)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _list(args: argparse.Namespace) -> int:
    for s in SCENARIOS.values():
        print(f"{s.name}{' [not run: ' + s.not_run + ']' if s.not_run else ''}\n    {s.injects}")
    return 0


def _run(args: argparse.Namespace) -> int:
    cfg = _load(args)
    report = run_faults(cfg)
    ran = [s for s in report["scenarios"] if s["safe"] is not None]
    return 0 if all(s["safe"] and s["recording_ok"] for s in ran) else 1


def _load(args: argparse.Namespace) -> FaultsConfig:
    return config_from_args(FaultsConfig, args, {"out": args.out, "scenarios": args.scenario}).validate()


# ------------------------------------------------------------------------------------------ running
def _expand(text: str, ids: list[str]) -> str:
    return text.replace("{d1}", ids[0]).replace("{dlast}", ids[-1])


def scenario_demo_config(cfg: FaultsConfig, sc: Scenario, out: Path):
    """The demo configuration of scenario ``sc``: the base with the scenario's overrides, into ``out``."""
    import tempfile

    ids = [f"drone_{i + 1}" for i in range(cfg.demo.drones)]
    base = dataclasses.replace(cfg.demo, out=str(out), fleet=f"{cfg.demo.fleet}-{sc.name}".replace("_", "-"))
    if cfg.free_ports:
        base = dataclasses.replace(base, zenoh_endpoint=f"tcp/127.0.0.1:{free_tcp_port()}",
                                   mavlink_base=free_udp_base(base.drones))
    with tempfile.TemporaryDirectory() as tmp:  # the base as a file, the scenario's overrides on top of it
        path = save_config(base, Path(tmp) / "base.toml")
        return load_config(DemoConfig, path, overrides=[_expand(s, ids) for s in sc.sets]).validate()


def run_scenario(cfg: FaultsConfig, sc: Scenario, out: Path) -> dict:
    """Fly scenario ``sc`` into ``out`` and judge it; the scenario's entry of faults.json."""
    from apps.demo import run_demo
    from evaluation.faults import SafetyLimits, judge_flight
    from flightdata.folder import FlightFolder

    ids = [f"drone_{i + 1}" for i in range(cfg.demo.drones)]
    entry: dict = {"name": sc.name, "injects": _expand(sc.injects, ids), "safe": None, "recording_lost_s": None,
                   "recording_ok": None, "what_happened": "", "folder": str(out)}
    if sc.not_run:
        entry["what_happened"] = sc.not_run
        return entry
    dcfg = scenario_demo_config(cfg, sc, out)
    t0 = time.monotonic()
    error = ""
    try:
        summary = run_demo(dcfg)
    except Exception as e:  # the flight itself failed: judged on what was recorded, and said
        log.error("scenario %s: the flight failed: %s", sc.name, e)
        log.debug("details", exc_info=True)
        summary, error = None, f"{type(e).__name__}: {e}"
        if not isinstance(e, SkycapError):
            error += "\n" + traceback.format_exc(limit=3)
    entry["wall_s"] = round(time.monotonic() - t0, 1)
    flight = FlightFolder(out)
    if not flight.plan_path.exists() or not flight.truth_path.exists():
        entry.update(safe=False, what_happened=f"the flight did not start: {error or 'no plan / truth recorded'}")
        return entry
    plan = flight.plan()
    t_start_s = plan.start_time_ns * 1e-9
    t_final_land_s = _final_land_time_s(flight, ids, t_start_s, dcfg.duration_s)
    policy = ids if "*" in sc.landing_by_policy else [_expand(d, ids) for d in sc.landing_by_policy]
    limits = SafetyLimits(min_separation_m=plan.min_separation_m, geofence_center_ned_m=list(plan.center_ned_m),
                          geofence_radius_m=cfg.geofence_radius_m, geofence_max_alt_m=cfg.geofence_max_alt_m,
                          landing_by_policy=policy)
    judged = judge_flight(out, ids, limits, t_start_s, t_final_land_s, cfg.max_gap_s)
    rf = ((summary or {}).get("faults") or {}).get("recorder_fault")
    if sc.nowhere_to_record_after_fault and rf:
        # judged up to the fault (what was written must all be there); after it there was nowhere to record
        d = rf["drone"]
        upto = judge_flight(out, [d], limits, t_start_s, min(rf["t_s"], t_final_land_s), cfg.max_gap_s)["drones"][d]
        judged["drones"][d]["not_recordable_after_fault_s"] = judged["drones"][d]["recording_lost_s"]
        judged["drones"][d]["recording_lost_s"] = upto["recording_lost_s"]
        judged["drones"][d]["recording_gaps_before_fault"] = upto["recording_gaps"]
    breach = _outsider_breach(((summary or {}).get("faults") or {}).get("outsider"))
    if breach:
        judged["safe"] = False
        judged["unsafe_because"].append(breach)
    lost = {d: judged["drones"][d]["recording_lost_s"] for d in ids}
    budget = cfg.max_lost_per_crash_s if sc.crash else 0.0
    refused, fault_layer = _refused(flight, ids)
    ended = {d: ((summary or {}).get("drones", {}).get(d, {}) or {}).get("ended", "unknown (no summary)") for d in ids}
    warnings = _health_warnings(flight, ids)
    for d in ids:  # plus the last health the launcher saw (a drone whose recorder failed did not record it)
        for w in ((summary or {}).get("drones", {}).get(d, {}).get("last_health") or {}).get("warnings", []):
            if w not in warnings[d]:
                warnings[d].append(w)
    safe = judged["safe"] and not error
    entry.update(
        safe=bool(safe), recording_lost_s=round(max(lost.values()), 3), recording_lost_s_by_drone=lost,
        recording_ok=all(v <= budget + 1e-9 for v in lost.values()), recording_budget_s=budget,
        what_happened=_what_happened(sc, judged, ended, warnings, (summary or {}).get("faults", {}), error, t_start_s),
        min_separation_m=judged["min_separation_m"], configured_min_separation_m=limits.min_separation_m,
        geofence_outside_s=judged["geofence_outside_s"], uncommanded_landings=judged["uncommanded_landings"],
        touchdowns_after_start_s={d: [round(t - t_start_s, 2) for t in ts] for d, ts in judged["touchdowns_s"].items()},
        landing_by_policy=policy, unsafe_because=judged["unsafe_because"] + ([f"flight failed: {error}"] if error else []),
        drones={d: {"ended": ended[d], "health_warnings": warnings[d], "refused_messages": refused[d],
                    "fault_layer": fault_layer[d], **judged["drones"][d]} for d in ids},
        launcher_faults=(summary or {}).get("faults", {}),
    )
    return entry


def _final_land_time_s(flight, ids: list[str], t_start_s: float, duration_s: float) -> float:
    """When the launcher's final land command went out (the first land command after the plan's orbit ended
    in the drones' recordings); the orbit's planned end when none was sent (every drone was already down)."""
    from flightdata.flightlog import SortieLogs
    from shared_msgs import Command

    t_end_orbit = t_start_s + duration_s
    best = None
    for d, sessions in flight.drone_logs(drone_ids=ids).items():
        for m in SortieLogs([s.path for s in sessions]).messages(["gcs/cmd"]):
            if isinstance(m.msg, Command) and m.msg.action == "land":
                t = m.msg.header.t_sent_ns * 1e-9
                if t >= t_end_orbit - 1.0 and (best is None or t < best):
                    best = t
    return best if best is not None else t_end_orbit


def _refused(flight, ids: list[str]) -> tuple[dict[str, dict], dict[str, dict]]:
    """Per drone, the messages its transport refused, by subscription: count and the last reason; and the
    simulated fault layer's counts (judged, dropped, delayed) -- from every agent start's ``.transport.json``
    (an agent killed by SIGKILL wrote none)."""
    out: dict[str, dict] = {}
    layer: dict[str, dict] = {}
    for d in ids:
        rows: dict[str, dict] = {}
        fl = layer.setdefault(d, {"fault_judged": 0, "fault_dropped": 0, "fault_delayed": 0})
        for s in flight.sorties(d):
            p = s.transport_stats_path
            if not p.is_file():
                continue
            for sub, st in json.loads(p.read_text()).items():
                if isinstance(st, dict):
                    for k in fl:
                        fl[k] += int(st.get(k, 0))
                if not isinstance(st, dict) or not st.get("malformed"):
                    continue
                key = sub.split("#")[0].split("/", 3)[-1]  # skycap/v1/<fleet>/<node>/<topic> -> <node>/<topic>
                row = rows.setdefault(key, {"refused": 0, "last_reason": ""})
                row["refused"] += int(st["malformed"])
                row["last_reason"] = st.get("last_error", "")[:200]
        out[d] = rows
    return out, layer


def _health_warnings(flight, ids: list[str]) -> dict[str, list[str]]:
    """Per drone, the distinct warnings of its recorded health reports (failsafes, recorder failures...)."""
    from flightdata.flightlog import SortieLogs
    from shared_msgs import Health

    out = {}
    for d in ids:
        seen: list[str] = []
        for m in SortieLogs([s.path for s in flight.sorties(d)]).messages(["health"]):
            if isinstance(m.msg, Health):
                for w in m.msg.warnings:
                    if w not in seen:
                        seen.append(w)
        out[d] = seen[:10]
    return out


def _outsider_breach(rep: dict | None) -> str:
    """Why an outsider's attempt breached the fleet ('' when it got nothing: no link, no message, no answer)."""
    if rep is None:
        return ""
    why = []
    if any(rep["links"].values()):
        why.append(f"it got links {rep['links']}")
    if any(rep["received"].values()):
        why.append(f"it received fleet messages {rep['received']}")
    if rep["answered"]:
        why.append(f"drones answered its commands: {rep['answered'][:3]}")
    return ("the outsider without a certificate: " + "; ".join(why)) if why else ""


def _what_happened(sc: Scenario, judged: dict, ended: dict, warnings: dict, faults: dict, error: str,
                   t_start_s: float) -> str:
    parts = []
    if "outsider" in faults:
        o = faults["outsider"]
        parts.append(f"outsider (plaintext + foreign CA): links {o['links']}, fleet messages received {o['received']}, "
                     f"{o['commands_sent']} land commands sent, "
                     + (f"{len(o['answered'])} answers from the drones (first: {o['answered'][:2]})" if o["answered"]
                        else "answered by no drone"))
    for k in ("agent_killed", "agent_restarted", "gcs_link_lost", "recorder_fault"):
        if k in faults:
            f = faults[k]
            extra = f", resumed {f['resumed_after_start_s']:.1f} s" if "resumed_after_start_s" in f else ""
            what = f" ({f['fault']})" if "fault" in f else ""
            parts.append(f"{k.replace('_', ' ')} {f.get('drone', '')}{what} at {f['after_start_s']:.1f} s{extra}".replace("  ", " "))
    for d, e in ended.items():
        w = "; ".join(warnings[d][:3])
        row = judged["drones"][d]
        no_state = row["stream_gaps_s"].get("state", 0.0)
        telemetry = f", no vehicle state recorded for {no_state:.1f} s" if no_state > 0.0 else ""
        parts.append(f"{d}: {e}{telemetry}" + (f" [health: {w}]" if w else ""))
    if judged["unsafe_because"]:
        parts.append("UNSAFE: " + "; ".join(judged["unsafe_because"]))
    if error:
        parts.append(f"the flight failed: {error.splitlines()[0]}")
    return " | ".join(parts)


def run_faults(cfg: FaultsConfig) -> dict:
    """Run the configured scenarios; writes ``faults.json`` and ``config.toml`` into ``cfg.out`` and prints the
    table. Returns the report."""
    out = Path(cfg.out or time.strftime("flights/faults-%Y%m%d-%H%M%S", time.gmtime()))
    if out.exists() and any(out.iterdir()):
        raise SkycapError(f"{out} is not empty; results are never overwritten: pass a new --out folder")
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    names = cfg.scenarios or list(SCENARIOS)
    report: dict = {"config": str(out / "config.toml"), "scenarios": []}
    t0 = time.monotonic()
    for name in names:
        sc = SCENARIOS[name]
        log.info("=== scenario %s: %s", name, sc.injects)
        entry = run_scenario(cfg, sc, out / name)
        report["scenarios"].append(entry)
        report["wall_s"] = round(time.monotonic() - t0, 1)
        (out / "faults.json").write_text(json.dumps(report, indent=2))  # after each: a partial run is kept
        log.info("=== scenario %s: safe=%s, recording lost %s s", name, entry["safe"], entry["recording_lost_s"])
    table = format_faults_table(report)
    (out / "faults.txt").write_text(table + "\n")
    print(table, flush=True)
    print(f"faults: {out / 'faults.json'}", flush=True)
    return report


def format_faults_table(report: dict) -> str:
    """The suite's table: one row per scenario."""
    rows = [("scenario", "safe", "min_sep_m", "lost_s", "rec_ok", "refused", "what happened")]
    for s in report["scenarios"]:
        refused = sum(r["refused"] for d in (s.get("drones") or {}).values() for r in d.get("refused_messages", {}).values())
        rows.append((s["name"], {True: "yes", False: "NO", None: "-"}[s["safe"]],
                     "-" if s.get("min_separation_m") is None else f"{s['min_separation_m']:.1f}",
                     "-" if s["recording_lost_s"] is None else f"{s['recording_lost_s']:.2f}",
                     {True: "yes", False: "NO", None: "-"}[s["recording_ok"]],
                     "-" if s["safe"] is None else str(refused), s["what_happened"]))
    w = [max(len(r[i]) for r in rows) for i in range(6)]
    return "\n".join("  ".join(r[i].ljust(w[i]) for i in range(6)) + "  " + r[6] for r in rows)
