"""The ground-station app's real widgets (pytest-qt, offscreen) against one real simulated fleet of two drones
(simulator, cameras, agents; mutual TLS with a temporary fleet CA) shared by the module.

Order matters: the last test stops drone_2's agent (stale link, no answer)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QPoint, Qt  # noqa: E402

from groundstation.app.config import GsConfig  # noqa: E402
from groundstation.app.model import PlanForm  # noqa: E402

pytestmark = pytest.mark.slow

IDS = ["drone_1", "drone_2"]


@pytest.fixture(scope="module")
def gs(qapp, tmp_path_factory):
    """(session, window) over a simulated fleet of two drones, healthy."""
    from groundstation.app.session import GsSession
    from groundstation.app.window import MainWindow

    tmp = tmp_path_factory.mktemp("gs")
    cfg = GsConfig(flights_dir=str(tmp / "flights"))
    cfg.ui.command_timeout_s = 3.0
    session = GsSession.open(cfg, sim_drones=2, sim_out=tmp / "flights" / "f1")
    win = MainWindow(session.model, session.cfg)
    win.resize(1500, 900)
    win.show()
    try:
        c = session.client
        ok = _pump_until(qapp, lambda: all(d in c.states and c.states[d].health_ok and d in c.healths for d in IDS),
                         120)
        assert ok, f"simulated drones not healthy: dead processes {session.sim.dead()}"
        yield session, win
    finally:
        win.close()
        session.close()


def _pump_until(qapp, pred, timeout_s: float) -> bool:
    from groundstation.app.selftest import pump_until

    return pump_until(pred, timeout_s)


def _results(win, run):
    return win.model.results(run)


def _table_text(table, row: int, col: int) -> str:
    it = table.item(row, col)
    return it.text() if it else ""


def test_fleet_panel_shows_each_drone_live(gs, qtbot):
    session, win = gs
    qtbot.waitUntil(lambda: win.table.rowCount() == 2, timeout=5000)
    rows = {_table_text(win.table, r, 0): r for r in range(win.table.rowCount())}
    assert set(rows) == set(IDS)
    for d, r in rows.items():
        link = _table_text(win.table, r, win.COLUMNS.index("link"))
        assert link.endswith(" s") and float(link.split()[0]) < 2.0, link  # age of the last message
        assert _table_text(win.table, r, win.COLUMNS.index("state")) == "idle"
        assert _table_text(win.table, r, win.COLUMNS.index("GPS")).startswith("3D")
        assert _table_text(win.table, r, win.COLUMNS.index("battery")).endswith("%")
    assert "mutual TLS" in win.status_label.text() and session.bus.secure


def test_plan_field_refusals_name_the_problem_and_send_nothing(gs, qtbot):
    session, win = gs
    n_acks = len(session.client.acks)
    cases = {"radius_m": ("-1", "radius must be positive"), "altitude_m": ("100", "outside the fence"),
             "speed_m_s": ("fast", "is not a number")}
    for field, (bad, why) in cases.items():
        old = win.plan_fields[field].text()
        win.plan_fields[field].setText(bad)
        qtbot.mouseClick(win.send_plan_btn, Qt.LeftButton)
        assert "NOT SENT" in win.plan_reason.text() and why in win.plan_reason.text(), win.plan_reason.text()
        win.plan_fields[field].setText(old)
    win.plan_fields["radius_m"].setText("1")  # two drones 2 m apart < 3 m
    qtbot.mouseClick(win.send_plan_btn, Qt.LeftButton)
    assert "separation not feasible" in win.plan_reason.text()
    win.plan_fields["radius_m"].setText("8")
    plan, why = session.model.validate_plan(PlanForm(drones=["drone_1", "drone_1"]))
    assert plan is None and "named more than once" in why
    qtbot.wait(500)
    assert session.model.plan is None and len(session.client.acks) == n_acks  # nothing was sent


def test_the_agents_refuse_a_plan_through_a_keepout_zone_sent_around_the_apps_checks(gs, qtbot):
    """The zones travel with the plan and the agents enforce them: a plan whose orbit crosses a keep-out zone,
    published past the app's own check, is refused by each agent with the zone named in its ack."""
    import msgspec

    from groundstation.fleet import make_orbit_plan
    from shared_msgs import GeofenceZone, KeepOutZone, keys

    session, win = gs
    plan = make_orbit_plan(IDS, radius_m=8.0, geofence=GeofenceZone(radius_m=30.0))
    plan = msgspec.structs.replace(plan, keepout_zones=[KeepOutZone(name="shed", north_m=8.0, east_m=0.0,
                                                                    radius_m=2.0)])
    session.bus.publish(keys.gcs_key(session.cfg.fleet, keys.PLAN), plan)
    acks = session.client.wait_acks(plan.plan_id, IDS, 8.0, ("accepted", "refused"))
    assert set(acks) == set(IDS), acks
    for a in acks.values():
        assert a.result == "refused" and "keep-out zone 'shed': the orbit" in a.reason, a


def test_plan_centre_by_click_and_each_drone_accepts(gs, qtbot):
    session, win = gs
    win.show_tab("Map / plan")
    target = win.map.to_px(2.0, -3.0)
    qtbot.mouseClick(win.map, Qt.LeftButton, pos=QPoint(round(target.x()), round(target.y())))
    assert abs(float(win.plan_fields["center_north_m"].text()) - 2.0) < 0.3
    assert abs(float(win.plan_fields["center_east_m"].text()) + 3.0) < 0.3
    win.plan_fields["center_north_m"].setText("0")
    win.plan_fields["center_east_m"].setText("0")
    qtbot.mouseClick(win.send_plan_btn, Qt.LeftButton)
    qtbot.waitUntil(lambda: all(r == "accepted" for r, _ in _results(win, win.plan_run).values()), timeout=8000)
    assert sorted(_table_text(win.plan_acks, r, 0) for r in range(win.plan_acks.rowCount())) == IDS
    assert session.model.plan.radius_m == 8.0


def test_drone_refusal_is_shown_with_its_reason(gs, qtbot):
    """Pause on the ground: each agent refuses and says why; the app shows it per drone (never a silent success)."""
    session, win = gs
    win.select_drones(None)
    qtbot.mouseClick(win.cmd_buttons["pause"], Qt.LeftButton)
    assert all(d in win.confirm.label.text() for d in IDS) and win.confirm.armed
    win.confirm.slide()
    qtbot.waitUntil(lambda: all(r == "refused" for r, _ in _results(win, win.last_run).values()), timeout=8000)
    qtbot.waitUntil(lambda: win.results.rowCount() == 2 and all(
        "nothing to pause" in _table_text(win.results, r, 2) for r in range(2)), timeout=2000)
    assert {_table_text(win.results, r, 1) for r in range(2)} == {"refused"}
    qtbot.waitUntil(lambda: sum("REFUSED" in e.text for e in session.model.alerts()) >= 2, timeout=2000)


def test_checklist_failing_blocks_takeoff_until_override_then_fly_and_land_all(gs, qtbot):
    session, win = gs
    m = session.model
    m.cfg.checklist.min_battery_frac = 1.01  # no battery can pass
    try:
        win.show_tab("Checklist")
        assert not m.checklist_ok("drone_1")
        assert any(_table_text(win.check_table, r, 1) == "FAIL" for r in range(win.check_table.rowCount()))
        win.select_drones(["drone_1"])
        qtbot.mouseClick(win.cmd_buttons["takeoff"], Qt.LeftButton)
        assert "will NOT be sent" in win.confirm.label.text() and "checklist failing (battery)" in win.confirm.label.text()
        win.confirm.slide()
        res = _results(win, win.last_run)
        assert res["drone_1"][0] == "not sent" and "battery" in res["drone_1"][1], res
        qtbot.wait(1000)
        assert session.client.healths["drone_1"].state == "idle"  # nothing was sent
        # the operator's explicit override: logged, then take-off goes out
        win.select_drones(["drone_1"])
        win.override_reason.setText("test: battery gauge known wrong")
        qtbot.mouseClick(win.override_btn, Qt.LeftButton)
        assert any("CHECKLIST OVERRIDE" in e.text and "battery" in e.text for e in m.events)
        assert "CHECKLIST OVERRIDE" in win.log_view.toPlainText()
        assert "CHECKLIST OVERRIDE" in (Path(m.cfg.flights_dir) / "gs-events.log").read_text()  # kept on disk too
        win.select_drones(["drone_1"])
        qtbot.mouseClick(win.cmd_buttons["takeoff"], Qt.LeftButton)
        assert "will NOT be sent" not in win.confirm.label.text()
        win.confirm.slide()
        qtbot.waitUntil(lambda: _results(win, win.last_run)["drone_1"][0] == "completed", timeout=15000)
        qtbot.waitUntil(lambda: session.client.healths["drone_1"].state == "hover", timeout=30000)
        # land-all is one action: no confirmation
        qtbot.mouseClick(win.land_all_btn, Qt.LeftButton)
        assert set(win.last_run.targets) == set(IDS)
        qtbot.waitUntil(lambda: session.client.healths["drone_1"].state in ("landed", "idle"), timeout=40000)
        assert _results(win, win.last_run)["drone_1"][0] == "completed"
    finally:
        m.cfg.checklist.min_battery_frac = 0.5


def test_thumbnails_with_detection_boxes(gs, qtbot):
    session, win = gs
    qtbot.waitUntil(lambda: all(session.model.thumb_count.get(d, 0) > 0 for d in IDS), timeout=10000)
    win.show_tab("Live view")
    qtbot.waitUntil(lambda: all(win.thumbs.tiles.get(d) and win.thumbs.tiles[d][0].pixmap() is not None
                                and not win.thumbs.tiles[d][0].pixmap().isNull() for d in IDS), timeout=5000)
    assert "s old" in win.thumbs.tiles["drone_1"][1].text()
    decoded = win.thumbs.decoded
    win.show_tab("Map / plan")  # hidden tiles are not decoded
    qtbot.wait(2500)
    assert win.thumbs.decoded == decoded


def test_map_draws_the_person_estimate_ellipse_and_formation_paths(gs, qtbot):
    """Track mode's messages (the orbit-mode simulated fleet sends none): a person estimate with its 2-sigma
    ellipse and a drone's shared MPC path are drawn where they are."""
    from shared_msgs import FormationPlan, TargetEstimate

    session, win = gs
    m = session.model
    cov = [0.0] * 36
    cov[0], cov[7] = 4.0, 1.0  # sigma north 2 m, east 1 m
    m.targets["drone_1"] = TargetEstimate(header=TargetEstimate.make_header("drone_1"), position_ned_m=(5.0, 5.0, 0.0),
                                          velocity_ned_m_s=(0.0, 0.0, 0.0), covariance=tuple(cov), num_sources=2)
    m.formation["drone_1"] = FormationPlan(header=FormationPlan.make_header("drone_1"), t0_ns=0, dt_s=0.1,
                                           positions_ned_m=(-10.0, -10.0, -5.0, -10.0, 10.0, -5.0, 0.0, 10.0, -5.0))
    try:
        win.show_tab("Map / plan")
        img = win.map.grab().toImage()
        c = win.map.to_px(5.0, 5.0)
        s = win.map._scale()
        # inside the ellipse (1.5 sigma north of the centre): the purple fill; outside (3 sigma): not
        inside = img.pixelColor(round(c.x()), round(c.y() - 1.5 * 2.0 * s))
        outside = img.pixelColor(round(c.x()), round(c.y() - 3 * 2.0 * s))
        def purple(px):  # the translucent purple fill over the light background
            return px.red() > px.green() + 10 and px.blue() > px.green() + 10

        assert purple(inside) and not purple(outside), (inside.name(), outside.name())
        mid = win.map.to_px(-10.0, 0.0)  # on the path's first leg, west to east at north -10: orange dashes
        along = [img.pixelColor(round(mid.x()) + k, round(mid.y()) + dy) for k in range(12) for dy in (-1, 0, 1)]
        assert any(px.red() > 200 and px.blue() < 120 for px in along), [px.name() for px in along]
        off = [img.pixelColor(round(mid.x()) + k, round(mid.y()) + 15) for k in range(12)]  # 15 px beside it
        assert not any(px.red() > 180 and px.blue() < 120 for px in off)
    finally:
        m.targets.pop("drone_1", None)
        m.formation.pop("drone_1", None)


def test_stale_link_refused_here_and_no_answer_after_timeout(gs, qtbot):
    """drone_2's agent stops: its row greys with its age, a start is not sent to it (stale link), a land is sent
    anyway and ends as 'no answer' after the timeout; link lost is an alert."""
    session, win = gs
    session.sim.stop_agent("drone_2")
    qtbot.waitUntil(lambda: session.model.row("drone_2").stale, timeout=10000)
    win.select_drones(["drone_2"])
    qtbot.mouseClick(win.cmd_buttons["start"], Qt.LeftButton)
    win.confirm.slide()
    res = _results(win, win.last_run)
    assert res["drone_2"][0] == "not sent" and "link stale" in res["drone_2"][1], res
    win.select_drones(["drone_2"])
    qtbot.mouseClick(win.cmd_buttons["land"], Qt.LeftButton)
    win.confirm.slide()
    assert _results(win, win.last_run)["drone_2"][0] == "waiting"
    qtbot.waitUntil(lambda: _results(win, win.last_run)["drone_2"][0] == "no answer", timeout=6000)
    qtbot.waitUntil(lambda: any("LINK LOST" in e.text and e.drone == "drone_2" for e in session.model.alerts()),
                    timeout=8000)
    row = next(r for r in range(win.table.rowCount()) if _table_text(win.table, r, 0) == "drone_2")
    assert _table_text(win.table, row, 1).startswith("LOST")
    assert win.table.item(row, 2).foreground().color().name() == "#969696"  # greyed


def test_tls_endpoint_without_fleet_folder_is_a_clear_error():
    from groundstation.app.session import GsSession
    from skycap.errors import SkycapError

    with pytest.raises(SkycapError, match="network.keys_dir is empty"):
        GsSession(GsConfig())

