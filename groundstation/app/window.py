"""The ground station's Qt widgets: they read :class:`~groundstation.app.model.FleetModel` on timers and call its
actions; no fleet logic lives here.

Layout: a toolbar (fleet, security, heartbeat, alert banner, LAND ALL), the fleet table with the command bar,
its slide-to-confirm and each drone's result on the left; tabs on the right: map / plan, checklist, live view,
3D (drones, person, plan, fence), flights (with the result's 3D skeleton playback), event log.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

from PySide6.QtCore import QPointF, QRectF, Qt, QTimer, Signal
from PySide6.QtGui import (QBrush, QColor, QFont, QImage, QKeySequence, QPainter, QPen, QPixmap, QPolygonF,
                           QShortcut)
from PySide6.QtWidgets import (QAbstractItemView, QComboBox, QFormLayout, QGridLayout, QGroupBox,
                               QHBoxLayout, QHeaderView, QLabel, QLineEdit, QListWidget, QListWidgetItem,
                               QMainWindow, QPlainTextEdit, QProgressBar, QPushButton, QScrollArea, QSlider,
                               QSplitter, QTableWidget, QTableWidgetItem, QTabWidget, QToolBar, QVBoxLayout, QWidget)

from groundstation.app.config import GsConfig
from groundstation.app.jobs import JobError, ProcessFlightJob, list_flights
from groundstation.app.model import ACTIONS, PLAN_MODES, CommandRun, FleetModel, PlanForm
from groundstation.app.scene3d import Live3DView, SkeletonPlayer
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

GREY = QColor(150, 150, 150)
RED = QColor(200, 30, 30)
GREEN = QColor(20, 140, 40)
ORANGE = QColor(210, 120, 0)
RESULT_COLOURS = {"accepted": ORANGE, "completed": GREEN, "refused": RED, "failed": RED, "no answer": RED,
                  "not sent": RED, "waiting": GREY}


def _item(text: str, colour: QColor | None = None, bold: bool = False) -> QTableWidgetItem:
    it = QTableWidgetItem(text)
    it.setFlags(it.flags() & ~Qt.ItemIsEditable)
    if len(text) > 24:
        it.setToolTip(text)  # a long reason or status, cut by its column: whole in the tooltip
    if colour is not None:
        it.setForeground(QBrush(colour))
    if bold:
        f = it.font()
        f.setBold(True)
        it.setFont(f)
    return it


class ConfirmSlider(QWidget):
    """QGroundControl's slide-to-confirm: names the action and every target; slide to the end to send."""

    confirmed = Signal()

    def __init__(self):
        super().__init__()
        self.label = QLabel("no command pending")
        self.label.setWordWrap(True)
        self.slider = QSlider(Qt.Horizontal)
        self.slider.setRange(0, 100)
        self.slider.sliderReleased.connect(self._released)
        self.cancel_btn = QPushButton("Cancel")
        self.cancel_btn.clicked.connect(self.disarm)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.label)
        row = QHBoxLayout()
        row.addWidget(self.slider, 1)
        row.addWidget(self.cancel_btn)
        lay.addLayout(row)
        self.disarm()

    def arm(self, text: str) -> None:
        self.label.setText(text)
        self.label.setStyleSheet("QLabel { background: #fff3c4; font-weight: bold; padding: 4px; }")
        self.slider.setValue(0)
        self.setEnabled(True)
        self.slider.setEnabled(True)
        self.cancel_btn.setEnabled(True)

    def disarm(self) -> None:
        self.label.setText("no command pending: choose drones and a command")
        self.label.setStyleSheet("")
        self.slider.setValue(0)
        self.slider.setEnabled(False)
        self.cancel_btn.setEnabled(False)

    @property
    def armed(self) -> bool:
        return self.slider.isEnabled()

    def _released(self) -> None:
        if self.slider.value() >= 95 and self.armed:
            self.slider.setEnabled(False)
            self.confirmed.emit()
        else:
            self.slider.setValue(0)

    def slide(self) -> None:
        """The operator's gesture: press, drag to the end, release (what tests and the self-test do)."""
        self.slider.setSliderDown(True)
        self.slider.setValue(100)
        self.slider.setSliderDown(False)


class MapView(QWidget):
    """A local metric map (north up, metres; no tiles): fence, plan (circle and slots), drones with heading and
    camera footprint, the person estimate with its 2-sigma ellipse (and the simulator's truth)."""

    clicked = Signal(float, float)  # north_m, east_m

    def __init__(self, model: FleetModel, cfg: GsConfig):
        super().__init__()
        self.model = model
        self.cfg = cfg
        self.half_m = cfg.ui.map_half_width_m
        self.preview = None  #: (north, east, radius) of the plan being edited
        self.setMinimumSize(380, 380)
        self.rows = []

    def _scale(self) -> float:
        return min(self.width(), self.height()) / (2 * self.half_m)

    def to_px(self, north_m: float, east_m: float) -> QPointF:
        s = self._scale()
        return QPointF(self.width() / 2 + east_m * s, self.height() / 2 - north_m * s)

    def to_m(self, x: float, y: float) -> tuple[float, float]:
        s = self._scale()
        return (self.height() / 2 - y) / s, (x - self.width() / 2) / s

    def mousePressEvent(self, ev) -> None:
        n, e = self.to_m(ev.position().x(), ev.position().y())
        self.clicked.emit(round(n, 1), round(e, 1))

    def wheelEvent(self, ev) -> None:
        self.half_m = max(5.0, min(500.0, self.half_m * (0.85 if ev.angleDelta().y() > 0 else 1.18)))
        self.update()

    def paintEvent(self, ev) -> None:
        p = QPainter(self)
        p.setRenderHint(QPainter.Antialiasing)
        p.fillRect(self.rect(), QColor(245, 247, 240))
        s = self._scale()
        step = 5.0 if self.half_m <= 30 else 10.0 if self.half_m <= 80 else 50.0
        p.setPen(QPen(QColor(220, 222, 215), 1))
        k = int(self.half_m * 1.5 / step) + 1
        for i in range(-k, k + 1):
            a, b = self.to_px(i * step, -2 * self.half_m), self.to_px(i * step, 2 * self.half_m)
            p.drawLine(a, b)
            a, b = self.to_px(-2 * self.half_m, i * step), self.to_px(2 * self.half_m, i * step)
            p.drawLine(a, b)
        p.setPen(QPen(QColor(90, 90, 90), 1))
        p.drawText(8, self.height() - 8, f"grid {step:g} m   north up   local NED frame, origin = fence centre   "
                   "(click: orbit centre / person start guess)")
        g = self.cfg.geofence
        p.setPen(QPen(RED, 2, Qt.DashLine))
        p.setBrush(Qt.NoBrush)
        p.drawEllipse(self.to_px(0, 0), g.radius_m * s, g.radius_m * s)
        p.drawText(self.to_px(g.radius_m, 0) + QPointF(-70, -5), f"geofence {g.radius_m:g} m, "
                   f"{g.min_altitude_m:g}-{g.max_altitude_m:g} m alt")
        for i, z in enumerate(self.cfg.keepout_zones):  # keep-out zones: hatched red discs with their names
            zc = self.to_px(z.north_m, z.east_m)
            p.setPen(QPen(RED, 2))
            p.setBrush(QBrush(QColor(200, 30, 30, 110), Qt.BDiagPattern))
            p.drawEllipse(zc, z.radius_m * s, z.radius_m * s)
            p.drawText(zc + QPointF(-30, -z.radius_m * s - 4), f"keep-out: {z.name or i + 1} ({z.radius_m:g} m)")
        p.setBrush(Qt.NoBrush)
        plan = self.model.plan
        if plan is not None and plan.mode == "track":
            # a tracking formation: the start guess, and the slots around the fused person estimate (the guess
            # until the drones have one)
            g0 = self.to_px(plan.center_ned_m[0], plan.center_ned_m[1])
            p.setPen(QPen(QColor(30, 90, 200), 2))
            p.drawLine(g0 + QPointF(-6, -6), g0 + QPointF(6, 6))
            p.drawLine(g0 + QPointF(-6, 6), g0 + QPointF(6, -6))
            p.drawText(g0 + QPointF(-80, -8), "start guess")
            est = self.model.person_estimate()
            cn, ce = (est.position_ned_m[0], est.position_ned_m[1]) if est is not None else plan.center_ned_m[:2]
            c = self.to_px(cn, ce)
            p.setPen(QPen(QColor(30, 90, 200), 2, Qt.DashLine))
            p.drawEllipse(c, plan.radius_m * s, plan.radius_m * s)
            for d, ph in plan.phase_offset_rad.items():
                sp = self.to_px(cn + plan.radius_m * math.cos(ph), ce + plan.radius_m * math.sin(ph))
                p.setBrush(QColor(30, 90, 200, 60))
                p.drawEllipse(sp, 5, 5)
                p.drawText(sp + QPointF(6, 12), f"slot {d}")
            p.setBrush(Qt.NoBrush)
            p.drawText(c + QPointF(-60, plan.radius_m * s + 14), f"tracking formation: stand-off {plan.radius_m:g} m")
        elif plan is not None:
            c = self.to_px(plan.center_ned_m[0], plan.center_ned_m[1])
            p.setPen(QPen(QColor(30, 90, 200), 2))
            p.drawEllipse(c, plan.radius_m * s, plan.radius_m * s)
            for d, ph in plan.phase_offset_rad.items():
                sp = self.to_px(plan.center_ned_m[0] + plan.radius_m * math.cos(ph),
                                plan.center_ned_m[1] + plan.radius_m * math.sin(ph))
                p.setBrush(QColor(30, 90, 200, 60))
                p.drawEllipse(sp, 5, 5)
                p.drawText(sp + QPointF(6, 12), f"slot {d}")
            p.setBrush(Qt.NoBrush)
        if self.preview is not None:
            n, e, r = self.preview
            p.setPen(QPen(QColor(30, 90, 200), 1, Qt.DotLine))
            p.drawEllipse(self.to_px(n, e), r * s, r * s)
            p.drawLine(self.to_px(n, e) + QPointF(-6, 0), self.to_px(n, e) + QPointF(6, 0))
            p.drawLine(self.to_px(n, e) + QPointF(0, -6), self.to_px(n, e) + QPointF(0, 6))
        truth = self.model.truth
        if truth is not None:
            tp = self.to_px(truth.person_root_ned_m[0], truth.person_root_ned_m[1])
            p.setPen(QPen(QColor(120, 120, 120), 1))
            p.setBrush(Qt.NoBrush)
            p.drawRect(QRectF(tp.x() - 4, tp.y() - 4, 8, 8))
            p.drawText(tp + QPointF(6, -6), "person (sim truth)")
        shown = self.model.person_estimate()
        for d, t in list(self.model.targets.items()):
            cov = t.covariance
            sn = math.sqrt(max(cov[0], 1e-6)) if len(cov) >= 36 else 1.0
            se = math.sqrt(max(cov[7], 1e-6)) if len(cov) >= 36 else 1.0
            c = self.to_px(t.position_ned_m[0], t.position_ned_m[1])
            p.setPen(QPen(QColor(160, 0, 160), 2))
            p.setBrush(QColor(160, 0, 160, 40))
            p.drawEllipse(c, max(3, 2 * se * s), max(3, 2 * sn * s))
            if t is shown:  # one label (the estimates of the drones overlap): the fleet's newest tracking one
                p.drawText(c + QPointF(8, 16), f"person est. ({d}, {t.status}; {len(self.model.targets)} drone(s))")
        for d, fp in list(self.model.formation.items()):  # track mode: each drone's planned path (MPC horizon)
            pts = fp.positions_ned_m
            if len(pts) >= 6:
                p.setPen(QPen(QColor(230, 120, 0), 2, Qt.DashLine))
                p.setBrush(Qt.NoBrush)
                p.drawPolyline(QPolygonF([self.to_px(pts[i], pts[i + 1]) for i in range(0, len(pts) - 2, 3)]))
        for r in self.rows:
            if r.age_s is None:
                continue
            colour = GREY if r.stale else (QColor(20, 20, 20) if r.ok else ORANGE)
            pos = self.to_px(r.north_m, r.east_m)
            # camera footprint: the ground patch seen with the gimbal looking at the plan's centre (or 45 deg down)
            fp = self._footprint(r)
            if fp:
                p.setPen(QPen(QColor(0, 140, 140, 150), 1))
                p.setBrush(QColor(0, 160, 160, 40))
                p.drawPolygon(QPolygonF([self.to_px(n, e) for n, e in fp]))
            yaw = r.yaw_rad
            p.setPen(QPen(colour, 2))
            p.drawLine(pos, QPointF(pos.x() + 24 * math.sin(yaw), pos.y() - 24 * math.cos(yaw)))
            tip = QPointF(pos.x() + 14 * math.sin(yaw), pos.y() - 14 * math.cos(yaw))
            left = QPointF(pos.x() + 8 * math.sin(yaw - 2.5), pos.y() - 8 * math.cos(yaw - 2.5))
            right = QPointF(pos.x() + 8 * math.sin(yaw + 2.5), pos.y() - 8 * math.cos(yaw + 2.5))
            p.setPen(QPen(colour, 2))
            p.setBrush(QColor(colour.red(), colour.green(), colour.blue(), 120))
            p.drawPolygon(QPolygonF([tip, left, right]))
            p.drawText(pos + QPointF(10, -8), f"{r.drone} {r.altitude_m:.1f} m"
                       + (f" ({r.age_s:.0f} s old)" if r.stale else ""))
        p.end()

    def _footprint(self, r) -> list[tuple[float, float]] | None:
        alt = r.altitude_m
        if alt < 0.5:
            return None
        info = self.model.camera_info.get(r.drone)
        plan = self.model.plan
        yaw = r.yaw_rad
        if info is not None:  # the camera's reported gimbal angles (pitch negative = down; yaw from the heading)
            pitch, yaw = -info.gimbal_pitch_rad, r.yaw_rad + info.gimbal_yaw_rad
        elif plan is not None:  # assumed: the gimbal looks at the plan's centre
            dist = math.hypot(plan.center_ned_m[0] - r.north_m, plan.center_ned_m[1] - r.east_m)
            pitch = math.atan2(alt, max(dist, 0.1))
        else:
            pitch = math.radians(45)
        hfov = 2 * math.atan2(info.width_px / 2, info.fx_px) if info else math.radians(70)
        vfov = 2 * math.atan2(info.height_px / 2, info.fy_px) if info else math.radians(50)
        pts = []
        for dv, dh in ((-1, -1), (-1, 1), (1, 1), (1, -1)):
            depress = pitch + dv * vfov / 2
            if depress <= math.radians(3):
                depress = math.radians(3)
            ground = alt / math.tan(depress)
            bearing = yaw + dh * hfov / 2
            pts.append((r.north_m + min(ground, 4 * self.half_m) * math.cos(bearing),
                        r.east_m + min(ground, 4 * self.half_m) * math.sin(bearing)))
        return pts


class ThumbGrid(QWidget):
    """Every drone's ``camera/thumb`` at a low rate, with its latest detection boxes; only visible tiles are
    decoded, and only when a new thumbnail arrived."""

    def __init__(self, model: FleetModel):
        super().__init__()
        self.model = model
        self.grid = QGridLayout(self)
        self.grid.setAlignment(Qt.AlignTop | Qt.AlignLeft)
        self.tiles: dict[str, tuple[QLabel, QLabel]] = {}
        self._shown: dict[str, int] = {}
        self.decoded = 0

    def showing(self) -> set[str]:
        """The drones whose tile shows a decoded thumbnail."""
        return set(self._shown)

    def refresh(self) -> None:
        if not self.isVisible():
            return
        for d in self.model.drone_ids():
            if d not in self.tiles:
                img, cap = QLabel("no thumbnail yet"), QLabel(d)
                img.setFixedSize(240, 180)
                img.setAlignment(Qt.AlignCenter)
                img.setStyleSheet("background: #222; color: #ccc;")
                k = len(self.tiles)
                self.grid.addWidget(img, 2 * (k // 3), k % 3)
                self.grid.addWidget(cap, 2 * (k // 3) + 1, k % 3)
                self.tiles[d] = (img, cap)
            img, cap = self.tiles[d]
            n = self.model.thumb_count.get(d, 0)
            age = time.monotonic() - self.model.thumb_rx[d] if d in self.model.thumb_rx else None
            dets = self.model.detections.get(d)
            cap.setText(f"{d}: " + ("no thumbnail received" if age is None else f"{age:.1f} s old")
                        + (f", {len(dets.boxes)} detection(s)" if dets else ""))
            if n == self._shown.get(d) or not img.isVisible():
                continue
            frame = self.model.thumbs.get(d)
            if frame is None:
                continue
            qi = QImage.fromData(frame.data)
            if qi.isNull():
                continue
            self.decoded += 1
            pm = QPixmap.fromImage(qi).scaled(240, 180, Qt.KeepAspectRatio)
            if dets is not None and dets.width_px > 0:
                sx, sy = pm.width() / dets.width_px, pm.height() / dets.height_px
                p = QPainter(pm)
                p.setPen(QPen(QColor(255, 60, 60), 2))
                for b in dets.boxes:
                    p.drawRect(QRectF(b.x_min_px * sx, b.y_min_px * sy, (b.x_max_px - b.x_min_px) * sx,
                                      (b.y_max_px - b.y_min_px) * sy))
                p.end()
            img.setPixmap(pm)
            self._shown[d] = n


class MainWindow(QMainWindow):
    """The ground station window over ``model``; ``flights_dir``: where recorded flights are listed from."""

    #: the tracker (the drone's fused person estimate) and the warnings before the long recorder / detector texts,
    #: so that they stay in view
    COLUMNS = ["drone", "link", "state", "mode", "armed", "battery", "GPS", "pos ±m", "setpt Hz", "tracker",
               "warnings", "recorder", "detector"]

    def __init__(self, model: FleetModel, cfg: GsConfig, title: str = "skycap ground station"):
        super().__init__()
        self.model = model
        self.cfg = cfg
        self.flights_dir = Path(cfg.flights_dir)
        self.setWindowTitle(f"{title} - fleet {model.fleet}")
        self.resize(1500, 900)
        self.pending: tuple[str, list[str]] | None = None
        self.last_run: CommandRun | None = None
        self.plan_run: CommandRun | None = None
        self.job: ProcessFlightJob | None = None
        self._job_runner = None  # the jobs runner (reconstruction.jobs), made at the first "process flight"
        self.job_result: dict | None = None
        self._build()
        self.table_timer = QTimer(self)
        self.table_timer.timeout.connect(self.refresh)
        self.table_timer.start(int(1000 / cfg.ui.table_hz))
        self.thumb_timer = QTimer(self)
        self.thumb_timer.timeout.connect(self.thumbs.refresh)
        self.thumb_timer.start(int(1000 / cfg.ui.thumbs_hz))
        self.refresh()
        self.refresh_flights()

    # --- building ---------------------------------------------------------------------------------
    def _build(self) -> None:
        tb = QToolBar("fleet")
        tb.setMovable(False)
        self.addToolBar(tb)
        sec = "mutual TLS (gcs certificate)" if self.model.client.bus.secure else "INSECURE (plaintext)"
        self._status_base = (f"  fleet {self.model.fleet}  |  {sec}  |  ground-station heartbeat "
                             f"{self.model.client.heartbeat_hz:g} Hz: ")
        self.status_label = QLabel(self._status_base)
        tb.addWidget(self.status_label)
        self.alert_label = QLabel("")
        self.alert_label.setStyleSheet("QLabel { color: white; background: #c01e1e; font-weight: bold; padding: 3px; }")
        self.alert_action = tb.addWidget(self.alert_label)
        self.alert_action.setVisible(False)
        spacer = QWidget()
        spacer.setSizePolicy(spacer.sizePolicy().horizontalPolicy().Expanding, spacer.sizePolicy().verticalPolicy())
        tb.addWidget(spacer)
        self.land_all_btn = QPushButton("LAND ALL")
        self.land_all_btn.setStyleSheet("QPushButton { background: #c01e1e; color: white; font-weight: bold; "
                                        "padding: 6px 18px; }")
        self.land_all_btn.clicked.connect(self.land_all)
        self.land_all_btn.setToolTip("Land every drone now (no confirmation; shortcut Ctrl+Shift+L)")
        self.land_all_shortcut = QShortcut(QKeySequence("Ctrl+Shift+L"), self)
        self.land_all_shortcut.setContext(Qt.ApplicationShortcut)
        self.land_all_shortcut.activated.connect(self.land_all)
        tb.addWidget(self.land_all_btn)

        split = QSplitter(Qt.Horizontal)
        left = QWidget()
        ll = QVBoxLayout(left)
        self.table = QTableWidget(0, len(self.COLUMNS))
        self.table.setHorizontalHeaderLabels(self.COLUMNS)
        self.table.setSelectionBehavior(QAbstractItemView.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.MultiSelection)
        self.table.verticalHeader().hide()
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        ll.addWidget(QLabel("<b>Fleet</b> (select rows: the command targets; none selected = all)"))
        ll.addWidget(self.table, 3)
        cmds = QHBoxLayout()
        self.cmd_buttons = {}
        for action, label in ACTIONS.items():
            b = QPushButton(label)
            b.clicked.connect(lambda _=False, a=action: self.request_command(a))
            cmds.addWidget(b)
            self.cmd_buttons[action] = b
        ll.addLayout(cmds)
        self.confirm = ConfirmSlider()
        self.confirm.confirmed.connect(self._confirmed)
        ll.addWidget(self.confirm)
        ll.addWidget(QLabel("<b>Last command: each drone's answer</b>"))
        self.results = QTableWidget(0, 3)
        self.results.setHorizontalHeaderLabels(["drone", "result", "reason"])
        self.results.verticalHeader().hide()
        self.results.horizontalHeader().setStretchLastSection(True)
        self.results_title = QLabel("")
        ll.addWidget(self.results_title)
        ll.addWidget(self.results, 1)
        split.addWidget(left)

        self.tabs = QTabWidget()
        self.tabs.addTab(self._plan_tab(), "Map / plan")
        self.tabs.addTab(self._checklist_tab(), "Checklist")
        self.thumbs = ThumbGrid(self.model)
        sc = QScrollArea()
        sc.setWidget(self.thumbs)
        sc.setWidgetResizable(True)
        self.tabs.addTab(sc, "Live view")
        # a tab of its own (not a toggle on the map): the map stays the 2D planning tool (click = orbit centre),
        # and the 3D view paints only while its tab is shown
        self.view3d = Live3DView(self.model, self.cfg)
        self.tabs.addTab(self.view3d, "3D")
        self.tabs.addTab(self._flights_tab(), "Flights")
        self.log_view = QPlainTextEdit()
        self.log_view.setReadOnly(True)
        self.log_view.setFont(QFont("monospace", 9))
        self.tabs.addTab(self.log_view, "Event log")
        self.tabs.currentChanged.connect(lambda _: self.thumbs.refresh())
        split.addWidget(self.tabs)
        split.setSizes([800, 700])
        self.setCentralWidget(split)
        self._n_events = 0

    def _plan_tab(self) -> QWidget:
        w = QWidget()
        lay = QHBoxLayout(w)
        self.map = MapView(self.model, self.cfg)
        self.map.clicked.connect(self.set_plan_centre)
        lay.addWidget(self.map, 3)
        form_box = QGroupBox("Plan")
        f = QFormLayout(form_box)
        self.plan_mode = QComboBox()
        for key, label in PLAN_MODES.items():
            self.plan_mode.addItem(label, key)
        self.plan_mode.setToolTip("Orbit: circle the centre. Tracking formation: the drones (agents in track mode) "
                                  "find the person near the start guess and keep their slots around them")
        self.plan_mode.currentIndexChanged.connect(self._plan_mode_changed)
        f.addRow("plan", self.plan_mode)
        self.plan_fields: dict[str, QLineEdit] = {}
        self.plan_labels: dict[str, QLabel] = {}
        for name, default in (("center_north_m", "0"), ("center_east_m", "0"), ("radius_m", "8"),
                              ("altitude_m", "6"), ("speed_m_s", "1.2"), ("min_separation_m", "3")):
            e = QLineEdit(default)
            e.textChanged.connect(self._preview)
            self.plan_fields[name] = e
            self.plan_labels[name] = QLabel(name)
            f.addRow(self.plan_labels[name], e)
        self.direction = QComboBox()
        self.direction.addItems(["clockwise (1)", "anticlockwise (-1)"])
        self.direction_label = QLabel("direction")
        f.addRow(self.direction_label, self.direction)
        self.plan_drones = QListWidget()
        self.plan_drones.setMaximumHeight(110)
        f.addRow("drones", self.plan_drones)
        self.send_plan_btn = QPushButton("Validate and send plan")
        self.send_plan_btn.clicked.connect(self.send_plan)
        f.addRow(self.send_plan_btn)
        self.plan_reason = QLabel("")
        self.plan_reason.setWordWrap(True)
        f.addRow(self.plan_reason)
        self.plan_acks = QTableWidget(0, 3)
        self.plan_acks.setHorizontalHeaderLabels(["drone", "plan", "reason"])
        self.plan_acks.verticalHeader().hide()
        self.plan_acks.horizontalHeader().setStretchLastSection(True)
        f.addRow(self.plan_acks)
        self.zones_label = QLabel(self._zones_text())
        self.zones_label.setWordWrap(True)
        f.addRow(self.zones_label)
        form_box.setMaximumWidth(330)
        lay.addWidget(form_box, 1)
        return w

    def _zones_text(self) -> str:
        g = self.cfg.geofence
        zones = "; ".join(f"{z.name or 'zone ' + str(i + 1)}: {z.radius_m:g} m at ({z.north_m:g}, {z.east_m:g})"
                          for i, z in enumerate(self.cfg.keepout_zones)) or "none"
        return (f"Sent with the plan (local NED frame, metres from the origin): geofence {g.radius_m:g} m around the "
                f"origin, altitude {g.min_altitude_m:g}-{g.max_altitude_m:g} m; keep-out zones: {zones}")

    def set_plan_mode(self, mode: str) -> None:
        """Choose the plan form's mode ("orbit" / "track"), as the operator's combo box does."""
        self.plan_mode.setCurrentIndex(list(PLAN_MODES).index(mode))

    def _plan_mode_changed(self, _=None) -> None:
        track = self.plan_mode.currentData() == "track"
        names = {"center_north_m": ("person start guess north_m" if track else "center_north_m"),
                 "center_east_m": ("person start guess east_m" if track else "center_east_m"),
                 "radius_m": ("stand-off radius_m" if track else "radius_m"),
                 "altitude_m": "altitude_m", "speed_m_s": "speed_m_s", "min_separation_m": "min_separation_m"}
        for name, text in names.items():
            self.plan_labels[name].setText(text)
        for w in (self.plan_fields["speed_m_s"], self.plan_labels["speed_m_s"], self.direction,
                  self.direction_label):
            w.setVisible(not track)
        self._preview()

    def _checklist_tab(self) -> QWidget:
        w = QWidget()
        lay = QVBoxLayout(w)
        lay.addWidget(QLabel("Pre-flight checklist per drone: a failing check blocks take-off unless overridden "
                             "(the override is logged)."))
        self.check_table = QTableWidget(0, 3)
        self.check_table.setHorizontalHeaderLabels(["drone / check", "ok", "detail"])
        self.check_table.verticalHeader().hide()
        self.check_table.horizontalHeader().setStretchLastSection(True)
        lay.addWidget(self.check_table, 1)
        row = QHBoxLayout()
        self.override_reason = QLineEdit()
        self.override_reason.setPlaceholderText("reason for overriding the selected drones' checklist (logged)")
        self.override_btn = QPushButton("Override checklist for selected drones")
        self.override_btn.clicked.connect(self.override_selected)
        row.addWidget(self.override_reason, 1)
        row.addWidget(self.override_btn)
        lay.addLayout(row)
        return w

    def _flights_tab(self) -> QWidget:
        outer = QSplitter(Qt.Horizontal)
        w = QWidget()
        lay = QVBoxLayout(w)
        self.flights_label = QLabel("")
        lay.addWidget(self.flights_label)
        self.flights = QListWidget()
        lay.addWidget(self.flights, 1)
        row = QHBoxLayout()
        b = QPushButton("Refresh")
        b.clicked.connect(self.refresh_flights)
        self.process_btn = QPushButton("Process flight")
        self.process_btn.clicked.connect(self.process_selected_flight)
        self.cancel_job_btn = QPushButton("Cancel")
        self.cancel_job_btn.clicked.connect(self.cancel_job)
        self.cancel_job_btn.setEnabled(False)
        for x in (b, self.process_btn, self.cancel_job_btn):
            row.addWidget(x)
        lay.addLayout(row)
        self.job_progress = QProgressBar()
        self.job_progress.setFormat("idle")
        self.job_progress.setValue(0)
        lay.addWidget(self.job_progress)
        self.job_stage = QLabel("")
        lay.addWidget(self.job_stage)
        self.job_log = QPlainTextEdit()
        self.job_log.setReadOnly(True)
        self.job_log.setFont(QFont("monospace", 8))
        self.job_log.setMaximumBlockCount(2000)
        lay.addWidget(self.job_log, 1)
        self.job_result_view = QPlainTextEdit()
        self.job_result_view.setReadOnly(True)
        lay.addWidget(QLabel("<b>Result</b>"))
        lay.addWidget(self.job_result_view, 1)
        self.job_timer = QTimer(self)
        self.job_timer.timeout.connect(self.refresh_job)
        outer.addWidget(w)
        res = QWidget()
        rl = QVBoxLayout(res)
        title = QLabel("<b>Result: 3D skeleton playback</b> (select a processed flight or process one)")
        title.setWordWrap(True)
        rl.addWidget(title)
        self.player = SkeletonPlayer()
        rl.addWidget(self.player, 1)
        outer.addWidget(res)
        outer.setSizes([300, 500])
        self.flights.currentItemChanged.connect(self._flight_selected)
        return outer

    def _flight_selected(self, item, _prev=None) -> None:
        """A processed flight selected: its newest reconstruction in the player."""
        if item is None or self.job_timer.isActive():
            return
        from flightdata.folder import FlightFolder

        f = FlightFolder(item.data(Qt.UserRole))
        dirs = [f.reconstruction_dir(m) for m in ("multiview", "monocular")]
        dirs = [d for d in dirs if (d / "summary.json").exists()]
        if not dirs:
            self.player.clear(f"{f.path.name} is not processed yet: press 'Process flight'")
            return
        d = max(dirs, key=lambda d: (d / "summary.json").stat().st_mtime)
        self.player.load(d, f.summary_path, next(m for m in ("multiview", "monocular") if f.reconstruction_dir(m) == d))

    # --- operator actions -------------------------------------------------------------------------
    def selected_drones(self) -> list[str]:
        rows = sorted({i.row() for i in self.table.selectedIndexes()})
        ids = [self.table.item(r, 0).text() for r in rows if self.table.item(r, 0)]
        return ids or self.model.drone_ids()

    def select_drones(self, ids: list[str] | None) -> None:
        self.table.clearSelection()
        for r in range(self.table.rowCount()):
            if ids is not None and self.table.item(r, 0).text() in ids:
                self.table.selectRow(r)

    def request_command(self, action: str) -> None:
        """Arm the slide-to-confirm for ``action`` on the selected drones, naming each of them."""
        targets = self.selected_drones()
        if not targets:
            self.model.log_event("warning", "", f"{action}: no drone in the fleet to command")
            self.results_title.setText(f"{ACTIONS[action]}: no drone in the fleet to command")
            return
        self.pending = (action, targets)
        warn = self.model.precheck(action, targets)
        extra = "" if not warn else "  -- will NOT be sent to: " + "; ".join(f"{d}: {w}" for d, w in warn.items())
        self.confirm.arm(f"Slide to confirm {ACTIONS[action].upper()} for {len(targets)} drone(s): "
                         f"{', '.join(targets)}{extra}")

    def _confirmed(self) -> None:
        if self.pending is None:
            return
        action, targets = self.pending
        self.pending = None
        self.confirm.disarm()
        self.last_run = self.model.command(action, targets)
        self.refresh()

    def land_all(self) -> None:
        self.pending = None
        self.confirm.disarm()
        self.last_run = self.model.land_all()
        self.refresh()

    def set_plan_centre(self, north_m: float, east_m: float) -> None:
        self.plan_fields["center_north_m"].setText(f"{north_m:g}")
        self.plan_fields["center_east_m"].setText(f"{east_m:g}")

    def plan_form(self) -> tuple[PlanForm | None, str]:
        vals = {}
        for name, e in self.plan_fields.items():
            try:
                vals[name] = float(e.text())
            except ValueError:
                return None, f"{name}: {e.text()!r} is not a number (metres / m/s, e.g. 8)"
        drones = [self.plan_drones.item(i).text() for i in range(self.plan_drones.count())
                  if self.plan_drones.item(i).checkState() == Qt.Checked]
        from flightdata.folder import natural_key

        drones.sort(key=natural_key)  # slots in the fleet's order (the simulator spawns them so)
        return PlanForm(direction=1 if self.direction.currentIndex() == 0 else -1, drones=drones,
                        mode=self.plan_mode.currentData(), **vals), ""

    def _preview(self) -> None:
        try:
            self.map.preview = (float(self.plan_fields["center_north_m"].text()),
                                float(self.plan_fields["center_east_m"].text()),
                                float(self.plan_fields["radius_m"].text()))
        except ValueError:
            self.map.preview = None
        self.map.update()

    def send_plan(self) -> None:
        form, why = self.plan_form()
        run = None
        if form is not None:
            run, why = self.model.send_plan(form)
        else:
            self.model.log_event("warning", "", f"plan not sent: {why}")
        if run is None:
            self.plan_reason.setText(f"NOT SENT: {why}")
            self.plan_reason.setStyleSheet("QLabel { color: #c01e1e; font-weight: bold; }")
        else:
            self.plan_run = run
            kind = "tracking formation" if form.mode == "track" else "orbit"
            self.plan_reason.setText(f"{kind} plan {run.command_ids[run.targets[0]]} sent; waiting for each drone")
            self.plan_reason.setStyleSheet("QLabel { color: #14802a; }")
        self.refresh()

    def override_selected(self) -> None:
        for d in self.selected_drones():
            self.model.override_checklist(d, self.override_reason.text().strip())
        self.refresh()

    def refresh_flights(self) -> None:
        self.flights.clear()
        for f in list_flights(self.flights_dir):
            text = (f"{f['name']}: {', '.join(f['drones'])}" + (f", {f['sorties']} sortie(s), {f['mb']} MB"
                                                               if 'sorties' in f else f" ({f.get('error')})")
                    + (f", processed ({', '.join(f['processed'])})" if f.get("processed") else ", not processed"))
            it = QListWidgetItem(text)
            it.setData(Qt.UserRole, f["path"])
            self.flights.addItem(it)
        self.flights_label.setText(f"Recorded flights in {self.flights_dir.resolve()}: {self.flights.count()}")

    def process_selected_flight(self, path: str | None = None) -> None:
        if not path:
            it = self.flights.currentItem()
            if it is None:
                self.job_stage.setText("select a flight first")
                return
            path = it.data(Qt.UserRole)
        try:
            if self._job_runner is None:
                from reconstruction.jobs import runner_from_config

                self._job_runner = runner_from_config(self.cfg.jobs)
            self.job = ProcessFlightJob.submit(path, self._job_runner, self.cfg.process_set)
        except SkycapError as e:
            self.job_stage.setText(str(e))
            self.model.log_event("warning", "", f"process flight: {e}")
            return
        self.job_result = None
        self.model.log_event("info", "", f"process flight {path}: job {self.job.job.id} on {self.job.job.runner_name}")
        self.job_progress.setRange(0, 100)
        self.job_progress.setValue(0)
        self.job_progress.setFormat("%p %")
        self.cancel_job_btn.setEnabled(True)
        self.process_btn.setEnabled(False)
        self.job_log.clear()
        self._job_lines = 0
        self.job_timer.start(500)

    def cancel_job(self) -> None:
        if self.job is not None:
            self.job.cancel()

    def refresh_job(self) -> None:
        job = self.job
        if job is None:
            return
        state, stage, elapsed = job.progress()
        lines = job.log()
        for line in lines[self._job_lines:]:
            self.job_log.appendPlainText(line)
        self._job_lines = len(lines)
        self.job_stage.setText(f"{state}: {stage} ({elapsed:.0f} s)")
        if state in ("queued", "running"):
            self.job_progress.setValue(round(100 * job.fraction()))
            return
        self.job_timer.stop()
        self.job_progress.setRange(0, 100)
        self.job_progress.setValue(100 if state == "done" else 0)
        self.job_progress.setFormat(state)
        self.cancel_job_btn.setEnabled(False)
        self.process_btn.setEnabled(True)
        try:
            self.job_result = job.result()
        except JobError as e:
            self.job_result_view.setPlainText(f"FAILED: {e}")
            self.model.log_event("alert", "", f"process flight failed: {e}")
            return
        if self.job_result is None:
            self.job_result_view.setPlainText(state)
            self.model.log_event("warning", "", f"process flight {state}")
            return
        self.job_result_view.setPlainText(format_result(self.job_result))
        self.player.load(self.job_result["outputs"]["dir"], job.flight.summary_path, self.job_result.get("method"))
        self.model.log_event("info", "", f"process flight done in {elapsed:.0f} s: {self.job_result['outputs']['dir']}")
        self.refresh_flights()

    # --- refresh ----------------------------------------------------------------------------------
    def refresh(self) -> None:
        m = self.model
        hb = m.client._hb_thread
        self.status_label.setText(self._status_base + ("running" if hb is not None and hb.is_alive() else "STOPPED"))
        m.poll_alerts()
        rows = m.rows()
        self.map.rows = rows
        sel = set(i.row() for i in self.table.selectedIndexes())
        sel_ids = {self.table.item(r, 0).text() for r in sel if self.table.item(r, 0)}
        if self.table.rowCount() != len(rows):
            self.table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            stale = GREY if r.stale else None
            link = ("no message" if r.age_s is None else f"{r.age_s:.1f} s") + ("" if r.present else ", absent")
            link_c = RED if r.lost or not r.present else stale
            batt = "-" if r.battery_frac is None else f"{100 * r.battery_frac:.0f} %"
            batt_c = RED if r.battery_frac is not None and r.battery_frac < m.cfg.checklist.min_battery_frac else stale
            cells = [(r.drone, None, True), (("LOST " if r.lost else "") + link, link_c, r.lost),
                     (r.state, stale, False), (r.mode, stale, False), ("ARMED" if r.armed else "disarmed",
                                                                        stale or (ORANGE if r.armed else None), r.armed),
                     (batt, batt_c, False), (f"{r.gps} ({r.satellites})", stale, False),
                     ("-" if r.position_std_m is None else f"{r.position_std_m:.2f}", stale, False),
                     (f"{r.setpoint_hz:.0f}", stale, False), (r.tracker, stale, False),
                     ("; ".join(r.warnings), RED if r.warnings else stale, bool(r.warnings)), (r.recorder, stale, False),
                     (r.detector, stale, False)]
            for j, (text, colour, bold) in enumerate(cells):
                cur = self.table.item(i, j)
                if cur is None or cur.text() != text or cur.foreground().color() != (colour or QColor()):
                    self.table.setItem(i, j, _item(text, colour, bold))
            if r.drone in sel_ids:
                self.table.selectRow(i)
        # plan form's drone list follows the fleet
        have = {self.plan_drones.item(i).text() for i in range(self.plan_drones.count())}
        for r in rows:
            if r.drone not in have:
                it = QListWidgetItem(r.drone)
                it.setFlags(it.flags() | Qt.ItemIsUserCheckable)
                it.setCheckState(Qt.Checked)
                self.plan_drones.addItem(it)
        self._fill_results(self.results, self.last_run)
        if self.last_run is not None:
            self.results_title.setText(f"{ACTIONS.get(self.last_run.action, self.last_run.action)} to "
                                       f"{', '.join(self.last_run.targets)}")
        self._fill_results(self.plan_acks, self.plan_run)
        self._plan_outcome()
        if self.tabs.currentIndex() == 1:
            self._fill_checklist(rows)
        alerts = m.alerts()
        if alerts:
            a = alerts[-1]
            self.alert_label.setText(f"  {len(alerts)} alert(s); last: {a.drone} {a.text[:70]}  ")
            self.alert_action.setVisible(True)
        if len(m.events) != self._n_events:
            for e in m.events[self._n_events:]:
                colour = "#c01e1e" if e.level == "alert" else "#a06000" if e.level == "warning" else "#222"
                self.log_view.appendHtml(f"<span style='color:{colour}'>{_html(e.line())}</span>")
            self._n_events = len(m.events)
        self.map.update()
        self.view3d.rows = rows
        if self.view3d.isVisible():  # repainted at the table's rate (5 Hz) and only while its tab is shown
            if m.live_skeleton_ned is not None or self.view3d.live_skeleton_ned is not None:
                self.view3d.set_live_skeleton(m.live_skeleton_ned)
            self.view3d.update()

    def _plan_outcome(self) -> None:
        """Once every drone answered the plan: who accepted it and who refused it, with each whole reason."""
        run = self.plan_run
        if run is None or getattr(run, "_outcome_shown", False) or not run.done(list(self.model.client.acks),
                                                                                  self.model.clock()):
            return
        run._outcome_shown = True  # type: ignore[attr-defined]
        res = self.model.results(run)
        ok = [d for d, (r, _) in res.items() if r == "accepted"]
        bad = {d: (r, why) for d, (r, why) in res.items() if r != "accepted"}
        text = f"plan {run.command_ids[run.targets[0]]}: accepted by {', '.join(ok) or 'no drone'}"
        if bad:
            text += "; " + "; ".join(f"{r.upper()} by {d}: {why}" for d, (r, why) in sorted(bad.items()))
        self.plan_reason.setText(text)
        self.plan_reason.setStyleSheet("QLabel { color: %s; font-weight: bold; }" % ("#c01e1e" if bad else "#14802a"))

    def _fill_results(self, table: QTableWidget, run: CommandRun | None) -> None:
        if run is None:
            return
        res = self.model.results(run)
        table.setRowCount(len(res))
        for i, (d, (r, why)) in enumerate(sorted(res.items())):
            table.setItem(i, 0, _item(d))
            table.setItem(i, 1, _item(r, RESULT_COLOURS.get(r), r != "waiting"))
            table.setItem(i, 2, _item(why))

    def _fill_checklist(self, rows) -> None:
        lines = []
        for r in rows:
            checks = self.model.checklist(r.drone)
            ok = all(c.ok for c in checks)
            over = r.drone in self.model.overrides
            lines.append((r.drone, "PASS" if ok else ("OVERRIDDEN" if over else "FAIL"),
                          "" if ok else ", ".join(c.name for c in checks if not c.ok), GREEN if ok else (ORANGE if over else RED)))
            for c in checks:
                lines.append((f"    {c.name}", "ok" if c.ok else "FAIL", c.detail, GREEN if c.ok else RED))
        self.check_table.setRowCount(len(lines))
        for i, (a, b, c, colour) in enumerate(lines):
            self.check_table.setItem(i, 0, _item(a, None, not a.startswith(" ")))
            self.check_table.setItem(i, 1, _item(b, colour, True))
            self.check_table.setItem(i, 2, _item(c))

    def show_tab(self, name: str) -> None:
        for i in range(self.tabs.count()):
            if self.tabs.tabText(i) == name:
                self.tabs.setCurrentIndex(i)
        self.refresh()
        self.thumbs.refresh()

    def closeEvent(self, ev) -> None:
        if self.job is not None:
            self.job.cancel()
        if self._job_runner is not None:
            self._job_runner.close(cancel=True, timeout=10)
            self._job_runner = None
        super().closeEvent(ev)


def _html(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def format_result(res: dict) -> str:
    """The processed flight's result for the operator: where the outputs are and the summary's headline figures."""
    s = res.get("summary", {})
    out = res.get("outputs", {})
    lines = [f"method: {res.get('method', '?')}", f"outputs: {out.get('dir', '?')}"]
    for b in out.get("bvh", []):
        lines.append(f"BVH: {b}")
    lines.append(f"files: {', '.join(out.get('files', []))}")

    def flat(prefix, x, depth=0):
        if isinstance(x, dict) and depth < 2:
            for k, v in x.items():
                yield from flat(f"{prefix}{k}.", v, depth + 1)
        elif isinstance(x, float):
            yield f"{prefix[:-1]} = {x:.4g}"
        elif isinstance(x, (int, bool)) or (isinstance(x, str) and len(x) < 60):
            yield f"{prefix[:-1]} = {x}"

    lines.append("summary:")
    lines += [f"  {t}" for t in list(flat("", s))[:40]]
    return "\n".join(lines)
