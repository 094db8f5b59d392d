"""The 3D widgets (pytest-qt, offscreen, real widgets): the skeleton player on a small synthetic motion.npz
(loads, plays at the file's rate, pauses, seeks; bones drawn where the projection says; a missing or malformed
file is a message, not a crash) and the live 3D view drawing every drone of a model fed VehicleState messages."""

from __future__ import annotations

import json
import math
import os
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt  # noqa: E402

from skycap.skeleton import COCO17_LIMBS, COCO17_NAMES  # noqa: E402

RATE_HZ = 20.0


def _standing(north_m: float, east_m: float) -> np.ndarray:
    """A (17, 3) NED person standing at (north, east), facing north (its left = west)."""
    y = {"left": -1.0, "right": 1.0}
    j = np.zeros((17, 3))
    for i, name in enumerate(COCO17_NAMES):
        side = y.get(name.split("_")[0], 0.0)
        if "ankle" in name:
            h, w = 0.05, 0.12
        elif "knee" in name:
            h, w = 0.5, 0.12
        elif "hip" in name:
            h, w = 0.95, 0.15
        elif "wrist" in name:
            h, w = 0.9, 0.35
        elif "elbow" in name:
            h, w = 1.15, 0.3
        elif "shoulder" in name:
            h, w = 1.45, 0.2
        elif "ear" in name:
            h, w = 1.62, 0.08
        elif "eye" in name:
            h, w = 1.65, 0.04
        else:  # nose
            h, w = 1.63, 0.0
        j[i] = (north_m + (0.08 if name in ("nose",) or "eye" in name else 0.0), east_m + side * w, -h)
    return j


def _write_motion(d, frames: int = 40, rrd: bool = False):
    d.mkdir(parents=True, exist_ok=True)
    t_ns = (1_000_000_000 + np.arange(frames) * 1e9 / RATE_HZ).astype(np.int64)
    joints = np.stack([_standing(0.05 * k, 0.0) for k in range(frames)])  # walking north
    np.savez(d / "motion.npz", t_ns=t_ns, joints_ned=joints, joint_names=np.array(COCO17_NAMES))
    (d / "summary.json").write_text(json.dumps({"frames": frames, "cameras": 2, "fit_seconds": 3.25}))
    if rrd:
        (d / "motion.rrd").write_bytes(b"x")
    return t_ns, joints


@pytest.fixture
def player(qtbot):
    from groundstation.app.scene3d import SkeletonPlayer

    w = SkeletonPlayer()
    w.resize(700, 560)
    qtbot.addWidget(w)
    w.show()
    qtbot.waitExposed(w)
    return w


def test_player_loads_plays_at_the_files_rate_pauses_and_seeks(player, qtbot, tmp_path):
    flight = tmp_path / "f1"
    _write_motion(flight / "reconstruction" / "multiview", frames=40)
    (flight / "summary.json").write_text(json.dumps({"reconstruction": {"accuracy_vs_truth": {
        "mpjpe_mm": 99.0, "pa_mpjpe_mm": 99.0, "w_mpjpe_mm": 99.0, "root_err_mm": 99.0, "frames_scored": 40,
        "mpjpe_mm_window": 41.5, "pa_mpjpe_mm_window": 30.25, "w_mpjpe_mm_window": 55.5, "root_err_mm_window": 20.0,
        "frames_scored_window": 30, "keypoints_source": "sim_noisy_gt", "position_grade": "rtk"}}}))
    assert player.load(flight / "reconstruction" / "multiview", flight / "summary.json")
    assert player.frames == 40 and abs(player.frame_period_s() - 1 / RATE_HZ) < 1e-9
    text = player.metrics.text()
    assert "multiview" in text and "frames 40" in text and "cameras 2" in text and "fit 3.2 s" in text
    assert "steady orbit" in text and "MPJPE 41.5 mm" in text and "PA-MPJPE 30.2 mm" in text
    assert "W-MPJPE 55.5 mm" in text and "over 30 frames" in text and "sim_noisy_gt" in text and "rtk" in text
    assert player.time_label.text().startswith("0.00 / 1.95 s")
    t0 = time.monotonic()
    qtbot.mouseClick(player.play_btn, Qt.LeftButton)
    assert player.playing and player.timer.interval() == 50
    qtbot.wait(600)
    i = player.frame
    elapsed = time.monotonic() - t0
    # real rate: about elapsed * 20 frames (the event loop may lag a frame or two; never ahead of the clock)
    assert max(3.0, 0.3 * elapsed * RATE_HZ) <= i <= elapsed * RATE_HZ + 1, (i, elapsed)
    qtbot.mouseClick(player.play_btn, Qt.LeftButton)
    assert not player.playing
    stopped = player.frame
    qtbot.wait(300)
    assert player.frame == stopped  # paused
    player.slider.setValue(30)
    assert player.frame == 30 and player.time_label.text().startswith("1.50 / 1.95 s")
    player.play()  # from 30 to the end (0.5 s), then it stops by itself on the last frame
    qtbot.waitUntil(lambda: not player.playing, timeout=3000)
    assert player.frame == 39


def test_player_draws_bones_where_the_projection_says(player, qtbot, tmp_path):
    t_ns, joints = _write_motion(tmp_path / "multiview", frames=5)
    assert player.load(tmp_path / "multiview")
    player.seek(2)
    v = player.view
    img = v.grab().toImage()
    assert v.bones_drawn == len(COCO17_LIMBS)
    uv = v.to_px(joints[2])
    names = COCO17_NAMES

    def near(px_xy, want) -> bool:
        x, y = px_xy
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                c = img.pixelColor(round(x) + dx, round(y) + dy)
                if want(c):
                    return True
        return False

    blue = lambda c: c.blue() > 150 and c.red() < 110  # noqa: E731 - the person's left
    red = lambda c: c.red() > 150 and c.blue() < 110  # noqa: E731 - the right
    for a, b, want in ((names.index("left_hip"), names.index("left_knee"), blue),
                       (names.index("right_knee"), names.index("right_ankle"), red),
                       (names.index("left_shoulder"), names.index("left_elbow"), blue),
                       (names.index("right_shoulder"), names.index("right_elbow"), red)):
        mid = 0.5 * (uv[a] + uv[b])
        assert near(mid, want), (names[a], names[b], mid, img.pixelColor(round(mid[0]), round(mid[1])).name())
    # 0.6 m to the person's left of its left knee, nothing is drawn: background, neither blue nor red
    a = names.index("left_knee")
    u, w = v.to_px([joints[2][a] + [0.0, -0.6, 0.0]])[0]
    c = img.pixelColor(round(u), round(w))
    assert not blue(c) and not red(c), c.name()


def test_player_missing_or_malformed_npz_is_a_message(player, tmp_path):
    assert not player.load(tmp_path / "nothing_here")
    assert "no motion.npz" in player.view.message and "process the flight" in player.view.message
    assert not player.play_btn.isEnabled() and player.frames == 0
    bad = tmp_path / "bad"
    bad.mkdir()
    np.savez(bad / "motion.npz", t_ns=np.arange(3), joints_ned=np.zeros((3, 5, 3)))
    assert not player.load(bad) and "expected (T, 17, 3)" in player.view.message
    (bad / "motion.npz").write_bytes(b"not a zip file")
    assert not player.load(bad) and "not a readable npz" in player.view.message
    np.savez(bad / "motion.npz", joints=np.zeros((3, 17, 3)))
    assert not player.load(bad) and "lacks t_ns / joints_ned" in player.view.message
    img = player.view.grab().toImage()  # painted without a crash, the message shown
    assert player.view.bones_drawn == 0 and not img.isNull()
    player.play()
    assert not player.playing


def test_rerun_button_enabled_only_with_viewer_and_rrd(player, tmp_path, monkeypatch):
    from groundstation.app import scene3d

    d = tmp_path / "multiview"
    _write_motion(d, frames=3, rrd=True)
    monkeypatch.setattr(scene3d, "rerun_executable", lambda: None)
    player.load(d)
    assert not player.rerun_btn.isEnabled() and "'recon' extra" in player.rerun_btn.toolTip()
    launched = []
    monkeypatch.setattr(scene3d, "rerun_executable", lambda: "/opt/rerun")
    monkeypatch.setattr(scene3d.subprocess, "Popen", lambda cmd, **kw: launched.append(cmd))
    player.load(d)
    assert player.rerun_btn.isEnabled()
    player.rerun_btn.click()
    assert launched == [["/opt/rerun", str(d / "motion.rrd")]]
    (d / "motion.rrd").unlink()
    player.load(d)
    assert not player.rerun_btn.isEnabled() and "no motion.rrd" in player.rerun_btn.toolTip()


class _FakeClient:
    """The FleetClient surface the model reads; states are real VehicleState messages."""

    def __init__(self):
        self.fleet = "test"
        self.bus = SimpleNamespace(subscribe=lambda *a, **k: SimpleNamespace(close=lambda: None), secure=False)
        self.heartbeat_hz = 2.0
        self._lock = threading.Lock()
        self.states, self.healths, self.last_rx_s, self.alive, self.acks = {}, {}, {}, set(), []
        self._hb_thread = None


def test_live_3d_view_draws_every_drone_of_the_model(qtbot, tmp_path):
    from groundstation.app.config import GsConfig
    from groundstation.app.model import FleetModel
    from groundstation.app.scene3d import Live3DView
    from shared_msgs import VehicleState

    client = _FakeClient()
    cfg = GsConfig(flights_dir=str(tmp_path))
    model = FleetModel(client, cfg)
    pos = {"drone_1": (8.0, 0.0, -6.0), "drone_2": (-4.0, 6.9, -6.0), "drone_3": (-4.0, -6.9, -6.0)}
    for d, p in pos.items():
        yaw = math.atan2(-p[1], -p[0])  # facing the centre
        client.states[d] = VehicleState(header=VehicleState.make_header(d), position_ned_m=p,
                                        velocity_ned_m_s=(0.0, 0.0, 0.0),
                                        q_world_body=(math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)),
                                        gps_fix_type=3, health_ok=True)
        client.last_rx_s[d] = time.monotonic()
        client.alive.add(d)
    view = Live3DView(model, cfg)
    view.resize(800, 600)
    qtbot.addWidget(view)
    view.show()
    view.rows = model.rows()
    assert [r.drone for r in view.rows] == sorted(pos)
    img = view.grab().toImage()
    assert view.drawn["drones"] == 3 and view.drawn["skeleton_bones"] == 0
    for d, p in pos.items():  # the drone's dark arms cross at its projected position
        u, v = view.to_px([p])[0]
        dark = [img.pixelColor(round(u) + dx, round(v) + dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
        assert any(c.red() < 80 and c.green() < 80 and c.blue() < 80 for c in dark), d
    view.set_live_skeleton(_standing(0.0, 0.0))
    view.grab()
    assert view.drawn["skeleton_bones"] == len(COCO17_LIMBS)
    with pytest.raises(ValueError, match=r"expected \(17, 3\)"):
        view.set_live_skeleton(np.zeros((5, 3)))
    model.close()


def test_the_qt_binding_keeps_its_references_to_none(qapp):
    """PySide6-Essentials 6.12.0 on Python 3.11 drops a reference to None per void Qt call (the ground-station bench
    aborted with 'Fatal Python error: none_dealloc: deallocating None' after a minute of painting; 6.11.3 does
    not). pyproject.toml excludes that release; this fails on a binding with the bug."""
    import sys

    from PySide6.QtCore import QPointF
    from PySide6.QtGui import QImage, QPainter

    img = QImage(50, 50, QImage.Format_ARGB32)
    p = QPainter(img)
    before = sys.getrefcount(None)
    for _ in range(3000):
        p.drawLine(QPointF(1, 2), QPointF(3, 4))
    after = sys.getrefcount(None)
    p.end()
    assert after > before - 100, f"this PySide6 dropped {before - after} references to None in 3000 drawLine calls"
