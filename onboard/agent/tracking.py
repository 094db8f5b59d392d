"""Track mode's tracking capture: this drone's and its teammates' detections -> the cooperative person filter.

:class:`TrackingCapture` wires the :class:`onboard.tracking.stage.TrackingStage` (configured by
:class:`onboard.config.TrackConfig`) to the agent: own detections come from the simulator's box detector
(``track.detections = "sim"``: ``<drone>/sim/detections``) or from the ONNX person detector's worker thread
(``"onnx"``: camera frames in, detections delivered back on the agent's event loop); each is fused and shared
with the teammates (``<drone>/detections``), teammates' detections are fused, and the fused estimate is
published on ``<drone>/target``. It also watches the own reported states: the take-off ground, the reported
position accuracy, and jumps of the reported position (GPS jumps), taken back from the own camera poses.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Callable

import numpy as np

from onboard.agent.rates import RateMeter
from onboard.config import TrackConfig
from onboard.tracking.filter import TrackerConfig
from onboard.tracking.measurement import MeasurementConfig
from onboard.tracking.roi import DetectorPlan, RoiConfig
from onboard.tracking.stage import TrackingStage, TrackingStageConfig
from shared_msgs import CameraFrame, CameraInfo, Detections, Message, VehicleState, keys

if TYPE_CHECKING:  # annotations only
    from onboard.detector.stage import DetectionWorker
    from onboard.formation.failsafe import FailsafeLog

log = logging.getLogger(__name__)

__all__ = ["TrackingCapture", "tracking_stage_config"]


def tracking_stage_config(cfg: TrackConfig) -> TrackingStageConfig:
    """The tracking stage's configuration from the agent's ``track`` section."""
    return TrackingStageConfig(
        # the own-position offset's prior: this drone's positioning grade (GPS ~1 m, RTK ~5 cm)
        tracker=TrackerConfig(offset_sigma_m=cfg.camera_position_sigma_m,
                              velocity_sigma_m_s=cfg.person_velocity_sigma_m_s),
        measurement=MeasurementConfig(person_height_m=cfg.person_height_m),
        roi=RoiConfig(person_height_m=cfg.person_height_m),
        camera_position_sigma_m=cfg.camera_position_sigma_m,
        camera_rotation_sigma_rad=cfg.camera_rotation_sigma_rad)


class TrackingCapture:
    """One drone's tracking capture (see the module doc).

    ``publish(topic, msg)`` sends on this drone's keys (and records); ``events`` is the failsafe log a GPS jump
    is written to (source ``"estimator"``); ``warn(text)`` adds a health warning.
    """

    def __init__(self, drone_id: str, cfg: TrackConfig, publish: Callable[[str, Message], None],
                 events: FailsafeLog, warn: Callable[[str], None]):
        self.drone_id = drone_id
        self.cfg = cfg
        self.stage = TrackingStage(drone_id, tracking_stage_config(cfg))
        self.detections_rate = RateMeter()  #: own detections fused (the health report's ``detections``)
        self._publish = publish
        self._events = events
        self._warn = warn
        self._loop: asyncio.AbstractEventLoop | None = None
        self._jump_prev: tuple[int, np.ndarray, np.ndarray] | None = None  #: the previous state (t_ns, p, v)
        self._last_target_pub_s = 0.0
        #: the ONNX detector's worker thread (``track.detections = "onnx"``), else None
        self.detector_worker: DetectionWorker | None = None
        if cfg.detections == "onnx":
            # the ONNX detector (onnxruntime, OpenCV) is loaded only when configured: start-up cost
            from onboard.detector.detector import DetectorConfig, PersonDetector
            from onboard.detector.stage import DetectionWorker

            self.detector_worker = DetectionWorker(
                drone_id, PersonDetector(DetectorConfig(model=cfg.detector_model, threads=cfg.detector_threads)),
                self._deliver_detections)

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """The agent's event loop: the detector's worker hands its detections over to it."""
        self._loop = loop

    # --- own vehicle -------------------------------------------------------------------------------------
    def on_state(self, st: VehicleState) -> None:
        """An own VehicleState: GPS jump check, the take-off ground, the reported position accuracy."""
        if self.cfg.gps_jump_threshold_m > 0:
            self._check_gps_jump(st)
        if st.landed_state == "on_ground" and np.isfinite(st.position_ned_m[2]):
            self.stage.set_own_ground(st.position_ned_m[2])  # the take-off ground in the reported frame
        if self.cfg.camera_cov_from_state:
            var = np.asarray(st.position_cov_m2, dtype=float)
            if var.shape == (3,) and np.all(np.isfinite(var)) and np.all(var > 0):
                self.stage.set_own_position_cov(var)

    def _check_gps_jump(self, st: VehicleState) -> None:
        """Notice a jump of the reported position (a step the reported velocity does not explain, between
        samples <= 0.5 s apart); log and count it, and hand it to the tracking stage, which takes it back from
        the own camera poses and the planning position (relaxing over ``track.gps_jump_relax_s`` while the
        filter's offset takes over), so that the drone stays in the fleet's frame."""
        t_ns = int(st.header.t_measurement_ns)
        p = np.asarray(st.position_ned_m, dtype=float)
        v = np.asarray(st.velocity_ned_m_s, dtype=float)
        prev, self._jump_prev = self._jump_prev, (t_ns, p, v)
        if prev is None or not 0 < (t_ns - prev[0]) * 1e-9 <= 0.5:
            return
        dt_s = (t_ns - prev[0]) * 1e-9
        v_mean = 0.5 * (prev[2] + v)
        step = p - (prev[1] + v_mean * dt_s)
        size = float(np.linalg.norm(step))
        # receive-time stamps: a delayed sample followed by a burst makes dt too long; tolerate the whole travel
        # over dt on top of the threshold so that such bursts never look like jumps
        if size <= self.cfg.gps_jump_threshold_m + float(np.linalg.norm(v_mean)) * dt_s:
            return
        t = self.cfg
        self.stage.set_position_step(step, t_ns, t.gps_jump_relax_s)
        reason = (f"reported position jumped {size:.2f} m ({', '.join(f'{x:+.2f}' for x in step)} NED) against its "
                  f"velocity: taken back from the own poses, relaxing over {t.gps_jump_relax_s:.0f} s")
        log.warning("%s: GPS jump: %s", self.drone_id, reason)
        self._warn("GPS jump " + reason)
        self._events.add(time.time(), "gps_jump", [reason], source="estimator")

    # --- camera and detections ---------------------------------------------------------------------------
    def set_camera_info(self, info: CameraInfo) -> None:
        self.stage.set_camera_info(info)

    def on_sim_detections(self, det: Detections) -> None:
        """The simulator's detections of this drone's camera: the own detections unless the ONNX detector
        makes them."""
        if self.detector_worker is None:
            self.own_detections(det, None)

    def on_frame(self, frame: CameraFrame) -> None:
        """A camera frame: handed to the ONNX detector (if configured) with the region the filter predicts."""
        if self.detector_worker is None:
            return
        try:
            plan = self.stage.plan_for(frame.header.t_measurement_ns, frame.T_world_cam)
            if plan is not None:
                self.detector_worker.submit(frame, plan.mode, plan.roi_px, context=plan)
        except Exception:
            log.exception("%s: planning the detection failed", self.drone_id)

    def own_detections(self, det: Detections, plan: DetectorPlan | None) -> None:
        """This drone's detections (the simulator's, or the ONNX detector's with the plan it ran with) ->
        the tracking stage -> shared with the teammates."""
        self.detections_rate.tick()
        try:
            out = self.stage.on_own_detections(det, plan)
            if out is not None:  # None: malformed, ignored and counted by the stage
                self._publish(keys.DETECTIONS, out)
        except Exception:
            log.exception("%s: tracking stage failed", self.drone_id)

    def _deliver_detections(self, det: Detections, plan: DetectorPlan | None) -> None:
        """Called on the detector's worker thread: hop to the agent's event loop."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self.own_detections, det, plan)

    def teammate_detections(self, det: Detections) -> None:
        """A teammate's shared detections: fused into this drone's filter."""
        try:
            self.stage.on_teammate_detections(det)
        except Exception:
            log.exception("%s: fusing %s's detections failed", self.drone_id, det.header.sender_id)

    # --- outputs -----------------------------------------------------------------------------------------
    def publish_target(self, now_monotonic_s: float) -> None:
        """Publish the fused estimate on ``<drone>/target`` at ``track.target_publish_hz``."""
        if now_monotonic_s - self._last_target_pub_s < 1.0 / self.cfg.target_publish_hz - 1e-3:
            return
        self._last_target_pub_s = now_monotonic_s
        msg = self.stage.target_message(time.time_ns())
        if msg is not None:
            self._publish(keys.TARGET, msg)

    def stats(self) -> dict:
        """The capture's part of the flight statistics (``<drone>.track.json``)."""
        tr, w = self.stage, self.detector_worker
        return {
            "detections_source": ("onnx:" + self.cfg.detector_model) if w is not None else "sim",
            "detector": None if w is None else w.stats(),
            "offset_log": [list(r) for r in tr.offset_log],
            "counts": dict(tr.counts),
            "filter_stats": dict(vars(tr.filter.stats)),
        }

    def malformed_counts(self) -> tuple[int, int]:
        """(detections refused by the stage as inconsistent, non-finite measurements refused by the filter)."""
        return int(self.stage.counts.get("malformed_detections", 0)), int(self.stage.filter.stats.rejected_nonfinite)

    def close(self) -> None:
        if self.detector_worker is not None:
            self.detector_worker.close(wait=False)
