"""``skycap gs --selftest DIR``: a whole operator session, offscreen, against the built-in simulated fleet, through
the app's own widgets and actions; a PNG of the window after each step and ``DIR/selftest.json``.

Steps (``mode = "orbit"``, the default): fleet up -> a plan with a bad field (refused, reason shown) -> an orbit
through the keep-out zone (refused by the app, reason shown) -> a tracking formation sent to these orbit-mode agents
(each drone refuses it, its reason shown per drone) -> plan the orbit (clicked centre; each drone accepts) ->
checklist -> arm + take off (slide to confirm) -> start -> watch (live view, 3D view, map) -> LAND ALL -> flight
ended (agents stop, recordings closed) -> process flight (``skycap reconstruct``) -> result (the 3D skeleton player
showing a frame with its bones).

``mode = "track"`` (``skycap gs --selftest DIR --sim-mode track``: the simulated agents in track mode): fleet up ->
bad field -> a tracking formation with a slot in the keep-out zone (refused by the app) -> plan the tracking
formation (start guess, stand-off; each drone accepts) -> checklist -> take off -> start -> watch the tracking (every
drone's fused person estimate live, tracking, near the simulator's truth; the fleet panel's tracker column and the
map's estimate and slots) -> 3D -> LAND ALL -> flight ended [-> process flight -> result].

Both sessions run with one keep-out zone configured (``SELFTEST_ZONE``), drawn on the map and in the 3D view and
sent to the drones with every plan.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

__all__ = ["run_selftest", "pump_until"]


def pump_until(pred: Callable[[], bool], timeout_s: float, step_s: float = 0.05) -> bool:
    """Run the Qt event loop until ``pred()`` holds (True) or ``timeout_s`` passed (False)."""
    from PySide6.QtWidgets import QApplication

    t_end = time.monotonic() + timeout_s
    while True:
        QApplication.processEvents()
        if pred():
            return True
        if time.monotonic() >= t_end:
            return False
        time.sleep(step_s)


def pump(seconds: float) -> None:
    pump_until(lambda: False, seconds)


#: the keep-out zone of the self-test's configuration (local NED frame, metres from the origin): clear of the
#: orbit and of the formation slots it plans, inside the 30 m fence
SELFTEST_ZONE = {"name": "shed", "north_m": 16.0, "east_m": -16.0, "radius_m": 3.0}


def run_selftest(out: str | Path, drones: int = 2, orbit_s: float = 20.0, process: bool = True,
                 process_timeout_s: float = 600.0, mode: str = "orbit", cfg=None) -> dict:
    """Run the scripted session (``mode``: the simulated agents' mode, "orbit" or "track"; ``cfg``: the app's
    configuration, its flights folder and keep-out zones replaced by the self-test's); returns (and writes) the
    selftest.json content."""
    from PySide6.QtCore import QPoint, Qt
    from PySide6.QtTest import QTest
    from PySide6.QtWidgets import QApplication

    from groundstation.app.config import GsConfig
    from groundstation.app.session import GsSession
    from groundstation.app.window import MainWindow

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    app = QApplication.instance() or QApplication(["skycap-gs-selftest"])
    import dataclasses

    from groundstation.app.config import KeepOutZoneConfig

    cfg = dataclasses.replace(cfg or GsConfig(), flights_dir=str(out / "flights"),
                              keepout_zones=[KeepOutZoneConfig(**SELFTEST_ZONE)])
    track = mode == "track"
    steps: list[dict] = []
    report: dict = {"steps": steps, "processed": None, "drones": drones, "orbit_s": orbit_s, "mode": mode}
    session = GsSession.open(cfg, sim_drones=drones, sim_out=out / "flights" / "selftest-flight", sim_mode=mode)
    win = MainWindow(session.model, session.cfg, title="skycap ground station (self-test)")
    win.resize(1600, 950)
    win.show()
    m = session.model
    ids = session.sim.ids
    t0 = time.monotonic()

    def step(name: str, ok: bool, detail: str, tab: str | None = None) -> bool:
        if tab:
            win.show_tab(tab)
        pump(0.3)
        shot = out / f"{len(steps) + 1:02d}_{name}.png"
        win.grab().save(str(shot))
        steps.append({"name": name, "ok": bool(ok), "screenshot": shot.name, "detail": detail,
                      "t_s": round(time.monotonic() - t0, 1)})
        (log.info if ok else log.error)("self-test step %s: %s - %s", name, "ok" if ok else "FAILED", detail)
        return ok

    def states(want: set[str]) -> bool:
        return all(session.client.healths.get(d) is not None and session.client.healths[d].state in want for d in ids)

    def results_of(run) -> dict:
        return m.results(run) if run is not None else {}

    try:
        ok = pump_until(lambda: all(d in session.client.states and session.client.states[d].health_ok
                                    and d in session.client.healths for d in ids), 120)
        if not step("fleet_up", ok, f"{len(ids)} simulated drones present and healthy" if ok else
                    f"drones not healthy within 120 s; dead processes: {session.sim.dead()}", "Map / plan"):
            return report
        # a plan with a bad field: refused before sending, the reason shown
        win.plan_fields["radius_m"].setText("-2")
        QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
        why = win.plan_reason.text()
        step("plan_refused_bad_field", "radius" in why and "NOT SENT" in why, why, "Map / plan")
        zone = SELFTEST_ZONE
        if not track:
            # an orbit through the keep-out zone: refused by the app before sending, the zone named
            win.plan_fields["radius_m"].setText("8")
            win.plan_fields["center_north_m"].setText("10")
            win.plan_fields["center_east_m"].setText("-10")
            QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
            why = win.plan_reason.text()
            step("plan_refused_keepout", "NOT SENT" in why and f"keep-out zone '{zone['name']}'" in why, why,
                 "Map / plan")
            # a tracking formation sent to these orbit-mode agents: each drone refuses it and says why
            win.set_plan_mode("track")
            win.plan_fields["center_north_m"].setText("0")
            win.plan_fields["center_east_m"].setText("0")
            QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
            ok = pump_until(lambda: win.plan_run is not None and all(r == "refused" for r, _ in
                                                                      results_of(win.plan_run).values()), 10)
            res = results_of(win.plan_run)
            ok = ok and all("wrong mode" in why for _, why in res.values())
            pump(0.3)
            ok = ok and win.plan_acks.rowCount() == len(ids)
            step("plan_track_refused_by_orbit_agents", ok, f"per-drone answers {res}", "Map / plan")
            win.set_plan_mode("orbit")
            # the orbit: centre by a click on the map, then each drone's acknowledgement
            win.plan_fields["radius_m"].setText("8")
            win.plan_fields["altitude_m"].setText("6")
            win.plan_fields["speed_m_s"].setText("1.5")
            c = win.map.to_px(0.0, 0.0)
            QTest.mouseClick(win.map, Qt.LeftButton, Qt.NoModifier, QPoint(int(c.x()), int(c.y())))
            QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
            ok = pump_until(lambda: win.plan_run is not None and all(r == "accepted" for r, _ in
                                                                      results_of(win.plan_run).values()), 10)
            step("plan_orbit", ok, f"centre ({win.plan_fields['center_north_m'].text()}, "
                 f"{win.plan_fields['center_east_m'].text()}) m by click; acks {results_of(win.plan_run)}", "Map / plan")
        else:
            win.set_plan_mode("track")
            win.plan_fields["radius_m"].setText("8")
            win.plan_fields["altitude_m"].setText("6")
            # a start guess that puts drone_1's slot (north of the person) in the keep-out zone: refused by the app
            win.plan_fields["center_north_m"].setText(f"{zone['north_m'] - 8:g}")
            win.plan_fields["center_east_m"].setText(f"{zone['east_m']:g}")
            QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
            why = win.plan_reason.text()
            step("plan_refused_keepout", "NOT SENT" in why and f"keep-out zone '{zone['name']}'" in why
                 and "slot" in why, why, "Map / plan")
            # the tracking formation: the person's start guess by a click on the map (the person starts near the
            # origin), the stand-off; each drone accepts
            c = win.map.to_px(1.5, -1.0)
            QTest.mouseClick(win.map, Qt.LeftButton, Qt.NoModifier, QPoint(int(c.x()), int(c.y())))
            QTest.mouseClick(win.send_plan_btn, Qt.LeftButton)
            ok = pump_until(lambda: win.plan_run is not None and all(r == "accepted" for r, _ in
                                                                      results_of(win.plan_run).values()), 10)
            ok = ok and m.plan is not None and m.plan.mode == "track" and m.plan.angular_speed_rad_s == 0.0
            step("plan_track", ok, f"tracking formation: start guess ({win.plan_fields['center_north_m'].text()}, "
                 f"{win.plan_fields['center_east_m'].text()}) m by click, stand-off 8 m, altitude 6 m; acks "
                 f"{results_of(win.plan_run)}; zones sent {len(m.plan.keepout_zones) if m.plan else 0}", "Map / plan")
        # checklist
        win.show_tab("Checklist")
        pump(0.5)
        failing = {d: [c.name for c in m.checklist(d) if not c.ok] for d in ids}
        if any(failing.values()):
            win.select_drones([d for d, f in failing.items() if f])
            win.override_reason.setText("self-test: simulated fleet")
            QTest.mouseClick(win.override_btn, Qt.LeftButton)
        step("checklist", True, f"failing checks: {failing or 'none'}"
             + ("; overridden by the operator (logged)" if any(failing.values()) else "; all pass"), "Checklist")
        # arm + take off with the slide-to-confirm naming every target
        win.show_tab("Map / plan")
        win.select_drones(None)
        QTest.mouseClick(win.cmd_buttons["takeoff"], Qt.LeftButton)
        pump(0.2)
        named = all(d in win.confirm.label.text() for d in ids)
        step("takeoff_confirm", win.confirm.armed and named, win.confirm.label.text())
        win.confirm.slide()
        ok = pump_until(lambda: win.last_run is not None and all(r in ("accepted", "completed") for r, _ in
                                                                  results_of(win.last_run).values()), 10)
        ok = ok and pump_until(lambda: states({"hover"}), 60)
        step("takeoff", ok, f"results {results_of(win.last_run)}; states "
             f"{ {d: session.client.healths[d].state for d in ids} }")
        if not ok:
            return report
        QTest.mouseClick(win.cmd_buttons["start"], Qt.LeftButton)
        win.confirm.slide()
        ok = pump_until(lambda: win.last_run is not None and win.last_run.action == "start" and all(
            r in ("accepted", "completed") for r, _ in results_of(win.last_run).values()), 10)
        ok = ok and pump_until(lambda: states({"orbit"}), 20)
        step("start", ok, f"results {results_of(win.last_run)}")
        t_orbit = time.monotonic()
        if track:
            # every drone's fused person estimate live and tracking, near the simulator's truth; the fleet panel's
            # tracker column and the map's estimate and formation slots show them
            win.show_tab("Map / plan")

            def tracking() -> bool:
                return all(d in m.targets and m.targets[d].status == "tracking" and m.targets[d].num_sources > 0
                           for d in ids)
            ok = pump_until(tracking, 45)
            pump(min(orbit_s / 2, 8.0))
            col = win.COLUMNS.index("tracker")
            cells = {win.table.item(r, 0).text(): win.table.item(r, col).text() for r in range(win.table.rowCount())}
            err = {}
            truth = m.truth
            if truth is not None:
                # each estimate predicted to the truth's time with its velocity (they are published at 10 Hz, the
                # truth at 20 Hz: the person walks ~1 m/s)
                tr, t_tr = truth.person_root_ned_m, truth.header.t_measurement_ns
                for d, t in list(m.targets.items()):
                    dt = (t_tr - t.header.t_measurement_ns) * 1e-9
                    n = t.position_ned_m[0] + t.velocity_ned_m_s[0] * dt
                    e = t.position_ned_m[1] + t.velocity_ned_m_s[1] * dt
                    err[d] = round(((n - tr[0]) ** 2 + (e - tr[1]) ** 2) ** 0.5, 2)
            ok = ok and tracking() and all(c.startswith("tracking") for c in cells.values())
            ok = ok and bool(err) and max(err.values()) < 3.0
            report["tracking"] = {"tracker_cells": cells, "horizontal_error_to_truth_m": err}
            step("watch_tracking", ok, f"tracker column {cells}; estimate minus sim truth (horizontal, at the truth's time) {err} m; "
                 f"states { {d: session.client.healths[d].state for d in ids} }", "Map / plan")
        else:
            pump(orbit_s / 2)
        win.show_tab("Live view")
        ok = pump_until(lambda: win.thumbs.showing() >= set(ids), 10)
        step("watch_live_view", ok, f"thumbnails received {dict(m.thumb_count)}, shown for "
             f"{sorted(win.thumbs.showing())} of {ids}, detections "
             f"{ {d: len(m.detections[d].boxes) for d in ids if d in m.detections} }", "Live view")
        # the 3D tab during the flight: ok only if the last paint drew every drone and the keep-out zone
        win.show_tab("3D")
        ok = pump_until(lambda: win.view3d.drawn["drones"] >= len(ids) and win.view3d.drawn["zones"] >= 1, 5)
        ok = ok and (not track or win.view3d.drawn["persons"] >= 1)
        step("view_3d", ok, f"3D view drew {win.view3d.drawn['drones']} of {len(ids)} drones, "
             f"{win.view3d.drawn['persons']} person marker(s), {win.view3d.drawn['zones']} keep-out zone(s); live "
             f"skeleton bones {win.view3d.drawn['skeleton_bones']} (none published yet)", "3D")
        pump(max(0.0, orbit_s - (time.monotonic() - t_orbit)))
        rows = m.rows()
        step("watch_map", all(not r.stale for r in rows),
             "; ".join(f"{r.drone} {r.state} at ({r.north_m:.1f}, {r.east_m:.1f}) alt {r.altitude_m:.1f} m" for r in rows),
             "Map / plan")
        QTest.mouseClick(win.land_all_btn, Qt.LeftButton)
        ok = pump_until(lambda: states({"landed", "idle"}), 90)
        disarmed = pump_until(lambda: not any(session.client.states[d].armed for d in ids), 20)
        step("land_all", ok, f"results {results_of(win.last_run)}; states "
             f"{ {d: session.client.healths[d].state for d in ids} }; "
             f"{'disarmed' if disarmed else 'still armed 20 s after landing'}")
        flight_dir = session.sim.out
        session.sim.stop()  # the agents close their recordings
        session.sim = None
        step("flight_ended", True, f"agents stopped; recordings in {flight_dir}", "Flights")
        if not process:
            return report
        win.refresh_flights()
        for i in range(win.flights.count()):
            if win.flights.item(i).data(Qt.UserRole) == str(flight_dir):
                win.flights.setCurrentRow(i)
        QTest.mouseClick(win.process_btn, Qt.LeftButton)
        # the screenshot once the reconstruction reached a stage (its imports take a few seconds)
        pump_until(lambda: win.job is None or win.job.fraction() >= 0.3 or win.job.progress()[0] not in ("queued", "running"), 90)
        pump(1.0)
        step("process_flight_running", win.job is not None, win.job_stage.text(), "Flights")
        ok = pump_until(lambda: win.job is not None and win.job.progress()[0] not in ("queued", "running"), process_timeout_s)
        if not ok and win.job is not None:
            win.job.cancel()
        pump(1.5)
        res = win.job_result
        report["processed"] = res["summary"] if res else None
        report["processed_outputs"] = res["outputs"] if res else None
        win.show_tab("Flights")
        pl = win.player
        if pl.frames:
            pl.seek(pl.frames // 2)  # a frame mid-flight
        pump(0.3)
        pl.view.grab()  # paints it: bones_drawn is the last paint's count
        step("process_flight_result", res is not None and pl.frames > 0 and pl.view.bones_drawn > 0,
             f"player: {pl.frames} frames, frame {pl.frame + 1} drew {pl.view.bones_drawn} bones"
             + ("" if pl.frames else f" ({pl.view.message})") + " | " + win.job_stage.text() + " | "
             + win.job_result_view.toPlainText()[:300], "Flights")
        step("event_log", True, f"{len(m.events)} events, {len(m.alerts())} alerts", "Event log")
        return report
    finally:
        report["ok"] = bool(steps) and all(s["ok"] for s in steps)
        (out / "selftest.json").write_text(json.dumps(report, indent=2, default=str))
        win.close()
        session.close()
