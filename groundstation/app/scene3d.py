"""The ground station's 3D widgets, drawn with QPainter (no OpenGL: they work offscreen and on any laptop):

* :class:`Scene3DView` - an orbiting camera over the NED world (drag: turn, wheel: zoom) with a ground grid;
  the maths is :mod:`groundstation.app.view3d`.
* :class:`SkeletonView` / :class:`SkeletonPlayer` - a processed flight's ``motion.npz`` played back at its real
  rate (play / pause, frame slider with time), the reconstruction's metrics and "Open in rerun".
* :class:`Live3DView` - the fleet live: drones (heading, camera frustum), the person estimate or the simulator's
  truth, the planned orbit (or tracking formation), the geofence and keep-out zone cylinders;
  :meth:`Live3DView.set_live_skeleton` draws a (17, 3) NED
  skeleton (fed from :attr:`FleetModel.live_skeleton_ned`, which nothing fills yet: a future live triangulation
  of the drones' keypoints would).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PySide6.QtCore import QLineF, QPointF, Qt, QTimer
from PySide6.QtGui import QColor, QPainter, QPen
from PySide6.QtWidgets import QHBoxLayout, QLabel, QPushButton, QSlider, QVBoxLayout, QWidget

from groundstation.app import view3d
from skycap.skeleton import COCO17_LIMBS, COCO17_NAMES

log = logging.getLogger(__name__)

__all__ = ["Scene3DView", "SkeletonView", "SkeletonPlayer", "Live3DView", "rerun_executable", "load_motion"]

BONE_COLOURS = {view3d.LEFT: QColor(30, 90, 220), view3d.RIGHT: QColor(220, 50, 30), view3d.CENTRE: QColor(40, 40, 40)}
BONE_WIDTH_PX = 3


class Scene3DView(QWidget):
    """A perspective view of the NED world from an orbiting camera; subclasses draw in :meth:`draw_scene`."""

    VFOV_RAD = math.radians(50)

    def __init__(self):
        super().__init__()
        self.target_ned = np.array([0.0, 0.0, -1.0])
        self.azimuth_rad = math.radians(-135)  # the camera south-west of the target
        self.elevation_rad = math.radians(25)
        self.distance_m = 12.0
        self.grid_half_m = 10.0
        self.grid_step_m = 1.0
        self._drag = None
        self.setMinimumSize(200, 160)

    # --- camera -----------------------------------------------------------------------------------
    def camera(self) -> tuple[np.ndarray, np.ndarray]:
        return view3d.orbit_camera(self.target_ned, self.azimuth_rad, self.elevation_rad, self.distance_m)

    def to_px(self, points_ned) -> np.ndarray:
        """(N, 3) NED -> (N, 2) widget pixels (NaN behind the camera)."""
        pos, R = self.camera()
        return view3d.project_ned(points_ned, pos, R, self.width(), self.height(), self.VFOV_RAD)

    def mousePressEvent(self, ev) -> None:
        self._drag = (ev.position().x(), ev.position().y(), self.azimuth_rad, self.elevation_rad)

    def mouseMoveEvent(self, ev) -> None:
        if self._drag is None:
            return
        x0, y0, az0, el0 = self._drag
        self.azimuth_rad = az0 - 0.01 * (ev.position().x() - x0)
        self.elevation_rad = float(np.clip(el0 + 0.01 * (ev.position().y() - y0), math.radians(2), math.radians(89)))
        self.update()

    def mouseReleaseEvent(self, ev) -> None:
        self._drag = None

    def wheelEvent(self, ev) -> None:
        self.distance_m = float(np.clip(self.distance_m * (0.85 if ev.angleDelta().y() > 0 else 1.18), 1.0, 500.0))
        self.update()

    # --- drawing ----------------------------------------------------------------------------------
    def _segments(self, p: QPainter, segs_ned: np.ndarray) -> int:
        """Draw (K, 2, 3) NED segments; returns how many were drawn (both ends in front of the camera)."""
        if len(segs_ned) == 0:
            return 0
        uv = self.to_px(np.asarray(segs_ned, dtype=float).reshape(-1, 3)).reshape(-1, 4)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv):  # one Qt call for all of them (each Qt call costs)
            p.drawLines([QLineF(*map(float, s)) for s in uv])
        return len(uv)

    def _polyline(self, p: QPainter, pts_ned: np.ndarray) -> int:
        pts = np.asarray(pts_ned, dtype=float)
        return self._segments(p, np.stack([pts[:-1], pts[1:]], axis=1))

    def _skeleton(self, p: QPainter, joints_ned: np.ndarray, names=COCO17_NAMES) -> int:
        """Bones of a (17, 3) NED skeleton, the person's left blue, right red, the rest dark; returns bones drawn."""
        n = 0
        for a, b in COCO17_LIMBS:
            ja, jb = joints_ned[a], joints_ned[b]
            if not (np.all(np.isfinite(ja)) and np.all(np.isfinite(jb))):
                continue
            p.setPen(QPen(BONE_COLOURS[view3d.bone_side(names, a, b)], BONE_WIDTH_PX, Qt.SolidLine, Qt.RoundCap))
            n += self._segments(p, np.array([[ja, jb]]))
        return n

    def paintEvent(self, ev) -> None:
        p = QPainter(self)
        p.setRenderHint(QPainter.Antialiasing)
        p.fillRect(self.rect(), QColor(245, 247, 240))
        p.setPen(QPen(QColor(205, 208, 200), 1))
        self._segments(p, view3d.ground_grid(float(self.target_ned[0]), float(self.target_ned[1]),
                                             self.grid_half_m, self.grid_step_m))
        # north arrow on the ground at the grid's centre
        c = np.array([self.target_ned[0], self.target_ned[1], 0.0])
        p.setPen(QPen(QColor(120, 120, 120), 2))
        self._segments(p, np.array([[c, c + [self.grid_step_m * 2, 0, 0]]]))
        tip = self.to_px([c + [self.grid_step_m * 2.3, 0, 0]])[0]
        if np.all(np.isfinite(tip)):
            p.drawText(QPointF(tip[0], tip[1]), "N")
        self.draw_scene(p)
        p.setPen(QColor(90, 90, 90))
        p.drawText(8, self.height() - 8, f"grid {self.grid_step_m:g} m  |  drag: turn, wheel: zoom  |  "
                   f"az {math.degrees(self.azimuth_rad) % 360:.0f} deg, el {math.degrees(self.elevation_rad):.0f} deg, "
                   f"{self.distance_m:.1f} m")
        p.end()

    def draw_scene(self, p: QPainter) -> None:  # pragma: no cover - overridden
        pass


# --- processed flight: skeleton playback ------------------------------------------------------------

class MotionError(ValueError):
    """A motion.npz the player cannot show (the message says what is wrong and how to get a good one)."""


def load_motion(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(t_ns (T,), joints_ned (T, 17, 3), joint names) from a reconstruction's motion.npz; MotionError if missing or
    malformed."""
    path = Path(path)
    if not path.exists():
        raise MotionError(f"no {path.name} at {path.parent}: process the flight first (skycap reconstruct)")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "t_ns" not in z.files or "joints_ned" not in z.files:
                raise MotionError(f"{path} lacks t_ns / joints_ned (it holds {', '.join(z.files) or 'nothing'}): "
                                  f"re-run skycap reconstruct to rewrite it")
            t_ns = np.asarray(z["t_ns"]).astype(np.int64).reshape(-1)
            joints = np.asarray(z["joints_ned"], dtype=float)
            names = tuple(str(n) for n in z["joint_names"]) if "joint_names" in z.files else COCO17_NAMES
    except MotionError:
        raise
    except Exception as e:  # noqa: BLE001 - a corrupt file: say so
        raise MotionError(f"{path} is not a readable npz ({type(e).__name__}: {e}): re-run skycap reconstruct") from e
    if joints.ndim != 3 or joints.shape[1:] != (17, 3) or len(joints) != len(t_ns):
        raise MotionError(f"{path}: joints_ned has shape {joints.shape}, t_ns {t_ns.shape}; expected (T, 17, 3) "
                          f"and (T,): re-run skycap reconstruct")
    if len(t_ns) == 0:
        raise MotionError(f"{path} holds no frame (T = 0): the reconstruction found no person")
    if len(names) != 17:
        names = COCO17_NAMES
    return t_ns, joints, names


def rerun_executable() -> str | None:
    """The ``rerun`` viewer (rerun-sdk): on PATH or beside this Python; None when not installed."""
    exe = shutil.which("rerun")
    if exe:
        return exe
    cand = Path(sys.executable).parent / "rerun"
    return str(cand) if cand.exists() else None


class SkeletonView(Scene3DView):
    """One frame of a skeleton sequence over the ground grid."""

    def __init__(self):
        super().__init__()
        self.joints_ned: np.ndarray | None = None  #: (T, 17, 3)
        self.names = COCO17_NAMES
        self.frame = 0
        self.message = "no result loaded: process a flight"
        self.bones_drawn = 0  #: bones drawn by the last paint

    def fit_camera(self) -> None:
        """Aim at the sequence's mean root; the distance to see its extent."""
        j = self.joints_ned
        finite = j[np.all(np.isfinite(j), axis=-1)]
        if len(finite) == 0:
            return
        # robust to a reconstruction's outlier frames: the median and the 5..95 % spread, not the mean and extremes
        c = np.median(finite, axis=0)
        self.target_ned = np.array([c[0], c[1], min(c[2], -0.9)])
        lo, hi = np.percentile(finite[:, :2], [5, 95], axis=0)
        ext = float((hi - lo).max()) if len(finite) > 1 else 2.0
        self.distance_m = max(4.0, 1.2 * ext + 3.0)
        self.grid_half_m = max(4.0, ext / 2 + 3.0)
        self.grid_step_m = 1.0 if self.grid_half_m <= 20 else 5.0

    def draw_scene(self, p: QPainter) -> None:
        self.bones_drawn = 0
        if self.joints_ned is None:
            p.setPen(QColor(160, 30, 30))
            p.drawText(self.rect().adjusted(10, 10, -10, -30), Qt.AlignTop | Qt.AlignLeft | Qt.TextWordWrap, self.message)
            return
        f = self.joints_ned[self.frame]
        self.bones_drawn = self._skeleton(p, f, self.names)
        # the root's shadow on the ground
        hips = f[[11, 12]]
        if np.all(np.isfinite(hips)):
            root = hips.mean(axis=0)
            p.setPen(QPen(QColor(150, 150, 150), 1, Qt.DashLine))
            self._segments(p, np.array([[root, [root[0], root[1], 0.0]]]))


class SkeletonPlayer(QWidget):
    """A processed flight's 3D skeleton played back at its recording's rate, with its metrics and outputs."""

    def __init__(self):
        super().__init__()
        self.view = SkeletonView()
        self.t_ns = np.zeros(0, np.int64)
        self.recon_dir: Path | None = None
        self.play_btn = QPushButton("Play")
        self.play_btn.clicked.connect(self.toggle)
        self.slider = QSlider(Qt.Horizontal)
        self.slider.valueChanged.connect(self.seek)
        self.time_label = QLabel("-")
        self.metrics = QLabel("")
        self.metrics.setWordWrap(True)
        self.metrics.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.rerun_btn = QPushButton("Open in rerun")
        self.rerun_btn.clicked.connect(self.open_in_rerun)
        self.rerun_proc: subprocess.Popen | None = None
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)
        self._play_t0 = None  # (monotonic s, t_ns at that moment)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.view, 1)
        row = QHBoxLayout()
        row.addWidget(self.play_btn)
        row.addWidget(self.slider, 1)
        row.addWidget(self.time_label)
        lay.addLayout(row)
        row2 = QHBoxLayout()
        row2.addWidget(self.metrics, 1)
        row2.addWidget(self.rerun_btn, 0, Qt.AlignTop)
        lay.addLayout(row2)
        self._set_enabled(False)
        self._update_rerun()

    @property
    def frames(self) -> int:
        return len(self.t_ns)

    @property
    def frame(self) -> int:
        return self.view.frame

    @property
    def playing(self) -> bool:
        return self.timer.isActive()

    def frame_period_s(self) -> float:
        """The recording's median frame period (its real rate)."""
        if len(self.t_ns) < 2:
            return 0.1
        return float(np.median(np.diff(self.t_ns))) / 1e9

    def _set_enabled(self, on: bool) -> None:
        self.play_btn.setEnabled(on)
        self.slider.setEnabled(on)

    def clear(self, message: str) -> None:
        self.pause()
        self.t_ns = np.zeros(0, np.int64)
        self.view.joints_ned = None
        self.view.frame = 0
        self.view.message = message
        self._set_enabled(False)
        self.time_label.setText("-")
        self.view.update()

    def load(self, recon_dir: str | Path, flight_summary: str | Path | None = None, method: str | None = None) -> bool:
        """Load ``recon_dir``/motion.npz (and summary.json for the metrics; the flight's summary.json for the
        accuracy against the simulator's truth when present); False with the reason shown when it cannot."""
        self.recon_dir = Path(recon_dir)
        self._update_rerun()
        self.metrics.setText(self._metrics_text(flight_summary, method))
        try:
            t_ns, joints, names = load_motion(self.recon_dir / "motion.npz")
        except MotionError as e:
            log.warning("skeleton player: %s", e)
            self.clear(f"cannot show the skeleton: {e}")
            return False
        self.pause()
        self.t_ns, self.view.names = t_ns, names
        self.view.joints_ned = joints
        self.view.fit_camera()
        self.slider.blockSignals(True)
        self.slider.setRange(0, len(t_ns) - 1)
        self.slider.setValue(0)
        self.slider.blockSignals(False)
        self._set_enabled(True)
        self.seek(0)
        log.info("skeleton player: %d frames at %.1f Hz from %s", len(t_ns), 1 / self.frame_period_s(), self.recon_dir)
        return True

    def _metrics_text(self, flight_summary, method: str | None) -> str:
        lines = []
        s = {}
        p = self.recon_dir / "summary.json"
        try:
            s = json.loads(p.read_text()) if p.exists() else {}
        except ValueError as e:
            lines.append(f"{p} unreadable: {e}")
        method = method or s.get("method") or self.recon_dir.name
        parts = [f"method <b>{method}</b>"]
        for key, label, fmt in (("frames", "frames", "{:d}"), ("cameras", "cameras", "{:d}"),
                                ("fit_seconds", "fit", "{:.1f} s")):
            if isinstance(s.get(key), (int, float)):
                parts.append(f"{label} {fmt.format(int(s[key]) if fmt == '{:d}' else s[key])}")
        lines.append(", ".join(parts))
        acc = {}
        if flight_summary is not None and Path(flight_summary).exists():
            try:
                acc = (json.loads(Path(flight_summary).read_text()).get("reconstruction") or {}).get("accuracy_vs_truth") or {}
            except ValueError:
                acc = {}
        if acc.get("w_mpjpe_mm") is not None:
            lines.append(_accuracy_line(acc))
        elif acc.get("mpjpe_mm") is not None:  # a summary written before the metrics were named: its MPJPE was world
            lines.append(f"vs simulator truth (older summary): W-MPJPE {acc['mpjpe_mm']:.1f} mm, PA-MPJPE "
                         f"{acc.get('pa_mpjpe_mm', float('nan')):.1f} mm over {acc.get('frames_scored', '?')} frames")
        else:
            lines.append("accuracy vs truth: not in the flight's summary.json (only simulated flights scored by "
                         "skycap demo have it)")
        bvh = sorted(self.recon_dir.glob("*.bvh")) if self.recon_dir.is_dir() else []
        lines.append(f"outputs: {self.recon_dir}" + (f" (BVH: {', '.join(b.name for b in bvh)})" if bvh else ""))
        return "<br>".join(lines)

    def _update_rerun(self) -> None:
        exe = rerun_executable()
        rrd = self.recon_dir / "motion.rrd" if self.recon_dir else None
        if exe is None:
            self.rerun_btn.setEnabled(False)
            self.rerun_btn.setToolTip("the rerun viewer is not installed: pip install 'skycap[recon]' "
                                      "(the 'recon' extra brings rerun-sdk)")
        elif rrd is None or not rrd.exists():
            self.rerun_btn.setEnabled(False)
            self.rerun_btn.setToolTip(f"no motion.rrd in {self.recon_dir or 'the result'}: process the flight first")
        else:
            self.rerun_btn.setEnabled(True)
            self.rerun_btn.setToolTip(f"{exe} {rrd}")

    def open_in_rerun(self) -> None:
        exe = rerun_executable()
        rrd = self.recon_dir / "motion.rrd" if self.recon_dir else None
        if exe is None or rrd is None or not rrd.exists():
            self._update_rerun()
            return
        log.info("open in rerun: %s %s", exe, rrd)
        self.rerun_proc = subprocess.Popen([exe, str(rrd)], start_new_session=True)

    # --- playback -----------------------------------------------------------------------------------
    def seek(self, i: int) -> None:
        if self.view.joints_ned is None:
            return
        i = int(np.clip(i, 0, len(self.t_ns) - 1))
        self.view.frame = i
        if self.slider.value() != i:
            self.slider.blockSignals(True)
            self.slider.setValue(i)
            self.slider.blockSignals(False)
        if self.playing:  # a seek while playing: go on from there
            self._play_t0 = (time.monotonic(), int(self.t_ns[i]))
        self.time_label.setText(f"{(self.t_ns[i] - self.t_ns[0]) / 1e9:.2f} / {(self.t_ns[-1] - self.t_ns[0]) / 1e9:.2f} s"
                                f"  ({i + 1}/{len(self.t_ns)})")
        self.view.update()

    def play(self) -> None:
        if self.view.joints_ned is None:
            return
        if self.view.frame >= len(self.t_ns) - 1:
            self.seek(0)
        self._play_t0 = (time.monotonic(), int(self.t_ns[self.view.frame]))
        self.timer.start(max(10, round(1000 * self.frame_period_s())))
        self.play_btn.setText("Pause")

    def pause(self) -> None:
        self.timer.stop()
        self.play_btn.setText("Play")

    def toggle(self) -> None:
        self.pause() if self.playing else self.play()

    def _tick(self) -> None:
        """The frame at the recording's time since play was pressed (real rate, frames skipped if painting lags)."""
        t0, tn0 = self._play_t0
        want_ns = tn0 + int(1e9 * (time.monotonic() - t0))
        i = int(np.searchsorted(self.t_ns, want_ns, side="right")) - 1
        if i >= len(self.t_ns) - 1:
            self.seek(len(self.t_ns) - 1)
            self.pause()
            return
        if i != self.view.frame:
            self.seek(i)


# --- live fleet -------------------------------------------------------------------------------------

class Live3DView(Scene3DView):
    """The fleet in 3D from the model's rows (set by the window's refresh, 5 Hz): each drone with its heading and
    camera frustum, the person estimate / the simulator's truth, the planned orbit and the geofence cylinder.
    ``drawn`` counts what the last paint drew (what the self-test checks)."""

    def __init__(self, model, cfg):
        super().__init__()
        self.model = model
        self.cfg = cfg
        self.rows = []
        self.live_skeleton_ned: np.ndarray | None = None
        self.drawn: dict[str, int] = {"drones": 0, "persons": 0, "skeleton_bones": 0, "zones": 0}
        self.distance_m = max(20.0, 2.2 * cfg.geofence.radius_m)
        self.elevation_rad = math.radians(30)
        self.target_ned = np.array([0.0, 0.0, -2.0])
        self.grid_half_m = cfg.geofence.radius_m
        self.grid_step_m = 5.0 if cfg.geofence.radius_m > 15 else 2.0
        self.user_moved = False  #: the operator turned or zoomed: no more automatic framing of the plan

    def mousePressEvent(self, ev) -> None:
        self.user_moved = True
        super().mousePressEvent(ev)

    def wheelEvent(self, ev) -> None:
        self.user_moved = True
        super().wheelEvent(ev)

    def paintEvent(self, ev) -> None:
        self._frame_plan()
        super().paintEvent(ev)

    def _frame_plan(self) -> None:
        """Aim at the plan's orbit (centre, half its altitude) from a distance that shows the circle."""
        plan = self.model.plan
        if plan is None or self.user_moved:
            return
        self.target_ned = np.array([plan.center_ned_m[0], plan.center_ned_m[1], -plan.altitude_m / 2])
        # far enough to show the circle, and the keep-out zones near it (within the fence)
        cn, ce = plan.center_ned_m[0], plan.center_ned_m[1]
        zones = max((math.hypot(z.north_m - cn, z.east_m - ce) + z.radius_m for z in self.cfg.keepout_zones),
                    default=0.0)
        self.distance_m = max(10.0, 3.8 * plan.radius_m, 2.8 * zones)

    def set_live_skeleton(self, joints_ned) -> None:
        """Draw a (17, 3) NED skeleton (COCO-17, metres); None removes it. The feed is
        :attr:`FleetModel.live_skeleton_ned`, which a future live triangulation of the drones' keypoints fills."""
        if joints_ned is None:
            self.live_skeleton_ned = None
        else:
            j = np.asarray(joints_ned, dtype=float)
            if j.shape != (17, 3):
                raise ValueError(f"live skeleton of shape {j.shape}: expected (17, 3) COCO-17 joints, NED metres")
            self.live_skeleton_ned = j
        self.update()

    def draw_scene(self, p: QPainter) -> None:
        m, g = self.model, self.cfg.geofence
        drawn = {"drones": 0, "persons": 0, "skeleton_bones": 0, "zones": 0}
        # geofence cylinder: floor and ceiling circles and 8 uprights
        p.setPen(QPen(QColor(200, 30, 30, 170), 1, Qt.DashLine))
        for alt in (g.min_altitude_m, g.max_altitude_m):
            self._polyline(p, view3d.circle_ned(0.0, 0.0, -alt, g.radius_m))
        for k in range(8):
            a = k * math.pi / 4
            n, e = g.radius_m * math.cos(a), g.radius_m * math.sin(a)
            self._segments(p, np.array([[[n, e, -g.min_altitude_m], [n, e, -g.max_altitude_m]]]))
        # keep-out zones: red cylinders from the ground to the fence's ceiling, with their names
        for i, z in enumerate(self.cfg.keepout_zones):
            p.setPen(QPen(QColor(200, 30, 30), 2))
            for alt in (0.0, g.max_altitude_m):
                self._polyline(p, view3d.circle_ned(z.north_m, z.east_m, -alt, z.radius_m))
            for k in range(6):
                a = k * math.pi / 3
                n, e = z.north_m + z.radius_m * math.cos(a), z.east_m + z.radius_m * math.sin(a)
                self._segments(p, np.array([[[n, e, 0.0], [n, e, -g.max_altitude_m]]]))
            uv = self.to_px([[z.north_m, z.east_m, 0.0]])[0]  # its foot
            if np.all(np.isfinite(uv)) and 0 <= uv[0] <= self.width() and 0 <= uv[1] <= self.height():
                drawn["zones"] += 1  # counted only when in view
            self._label(p, [z.north_m - z.radius_m, z.east_m, 0.0], f"keep-out: {z.name or i + 1}")
        plan = m.plan
        if plan is not None:
            cn, ce = plan.center_ned_m[0], plan.center_ned_m[1]
            if plan.mode == "track":  # a tracking formation: its stand-off circle around the person estimate
                est = m.person_estimate()
                if est is not None:
                    cn, ce = est.position_ned_m[0], est.position_ned_m[1]
            p.setPen(QPen(QColor(30, 90, 200), 2))
            self._polyline(p, view3d.circle_ned(cn, ce, -plan.altitude_m, plan.radius_m))
            p.setPen(QPen(QColor(30, 90, 200, 90), 1, Qt.DotLine))
            self._polyline(p, view3d.circle_ned(cn, ce, 0.0, plan.radius_m))
        truth = m.truth
        if truth is not None:
            r = truth.person_root_ned_m
            p.setPen(QPen(QColor(110, 110, 110), 2))
            if self._segments(p, np.array([[[r[0], r[1], 0.0], [r[0], r[1], -1.7]]])):
                drawn["persons"] += 1
                self._label(p, [r[0], r[1], -1.8], "person (sim truth)")
        shown = m.person_estimate()
        for d, t in list(m.targets.items()):
            pos = t.position_ned_m
            p.setPen(QPen(QColor(160, 0, 160), 3))
            if self._segments(p, np.array([[[pos[0], pos[1], 0.0], [pos[0], pos[1], -1.7]]])):
                drawn["persons"] += 1
                if t is shown:  # one label: the drones' estimates overlap
                    self._label(p, [pos[0], pos[1], -1.9], f"person est. ({d}, {t.status}; {len(m.targets)} drone(s))")
        if self.live_skeleton_ned is not None:
            drawn["skeleton_bones"] = self._skeleton(p, self.live_skeleton_ned)
        for r in self.rows:
            if r.age_s is None:
                continue
            pos = np.array([r.north_m, r.east_m, -r.altitude_m])
            colour = QColor(150, 150, 150) if r.stale else (QColor(20, 20, 20) if r.ok else QColor(210, 120, 0))
            # the drone: a cross of arms, its heading, its shadow line to the ground
            p.setPen(QPen(QColor(150, 150, 150), 1, Qt.DotLine))
            self._segments(p, np.array([[pos, [pos[0], pos[1], 0.0]]]))
            p.setPen(QPen(colour, 3))
            arm = 0.5
            n_drawn = self._segments(p, np.array([[pos + [-arm, -arm, 0], pos + [arm, arm, 0]],
                                                  [pos + [-arm, arm, 0], pos + [arm, -arm, 0]]]))
            head = pos + 1.5 * np.array([math.cos(r.yaw_rad), math.sin(r.yaw_rad), 0.0])
            p.setPen(QPen(colour, 2))
            self._segments(p, np.array([[pos, head]]))
            fr = self._frustum(r, pos)
            if fr is not None:
                p.setPen(QPen(QColor(0, 140, 140, 170), 1))
                self._segments(p, fr)
            if n_drawn:
                drawn["drones"] += 1
                p.setPen(colour)
                self._label(p, pos + [0, 0, -0.8], f"{r.drone} {r.altitude_m:.1f} m"
                            + (f" ({r.age_s:.0f} s old)" if r.stale else ""))
        self.drawn = drawn
        p.setPen(QColor(60, 60, 60))
        p.drawText(8, 16, f"3D: {drawn['drones']} drone(s), {drawn['persons']} person marker(s), {drawn['zones']} "
                   "keep-out zone(s); live skeleton: "
                   + ("drawn" if drawn["skeleton_bones"] else "none (the drones publish no live 3D keypoints yet)"))

    def _label(self, p: QPainter, at_ned, text: str) -> None:
        uv = self.to_px([at_ned])[0]
        if np.all(np.isfinite(uv)):
            p.drawText(QPointF(uv[0] + 6, uv[1]), text)

    def _frustum(self, r, pos) -> np.ndarray | None:
        """The camera frustum: the camera's reported gimbal angles, else looking at the plan's centre."""
        info = self.model.camera_info.get(r.drone)
        plan = self.model.plan
        yaw = r.yaw_rad
        if info is not None:
            dep, yaw = -info.gimbal_pitch_rad, r.yaw_rad + info.gimbal_yaw_rad
        elif plan is not None:
            dist = math.hypot(plan.center_ned_m[0] - r.north_m, plan.center_ned_m[1] - r.east_m)
            dep = math.atan2(max(r.altitude_m, 0.0), max(dist, 0.1))
        else:
            return None
        hfov = 2 * math.atan2(info.width_px / 2, info.fx_px) if info else math.radians(70)
        vfov = 2 * math.atan2(info.height_px / 2, info.fy_px) if info else math.radians(50)
        return view3d.frustum_segments(pos, yaw, dep, hfov, vfov, 2.0)


def _accuracy_line(acc: dict) -> str:
    """The flight summary's ``accuracy_vs_truth`` in one line: the steady orbit's figures when scored (else the
    whole flight's), MPJPE root-aligned, PA-MPJPE per frame, W-MPJPE world, with the 2D source and position grade."""
    sfx = "_window" if acc.get("mpjpe_mm_window") is not None else ""
    nan = float("nan")
    return (f"vs simulator truth ({'steady orbit' if sfx else 'whole flight'}): MPJPE {acc.get('mpjpe_mm' + sfx, nan):.1f} mm, "
            f"PA-MPJPE {acc.get('pa_mpjpe_mm' + sfx, nan):.1f} mm, W-MPJPE {acc.get('w_mpjpe_mm' + sfx, nan):.1f} mm, "
            f"root {acc.get('root_err_mm' + sfx, nan):.1f} mm over {acc.get('frames_scored' + sfx, '?')} frames; "
            f"2D {acc.get('keypoints_source', 'unknown')}, positions {acc.get('position_grade', 'unknown')}")
