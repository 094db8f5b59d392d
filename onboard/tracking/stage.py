"""The agent's tracking stage: detections (own + teammates') -> cooperative filter -> target estimate + ROI.

Pure logic, no I/O: the agent hands it Detections messages and publishes what it returns.

* :meth:`TrackingStage.on_own_detections` -- a Detections of this drone's camera (from the detector on the
  camera frame, or the simulator's detector on ``sim/detections``). Before the measurement is fused, the
  ROI the fused estimate predicts for that frame (pose at capture) is computed (:func:`plan_detection`) and
  written into the message's ``roi_px`` (``(0, 0, 0, 0)`` when the plan is "full"/"tiles"); the message
  is returned for publication on ``<drone>/detections`` so that the teammates fuse it too.
* :meth:`TrackingStage.on_teammate_detections` -- a teammate's Detections (``<other>/detections``).
* :meth:`TrackingStage.estimate` -- the filter's prediction at a time, and :meth:`target_message` the
  :class:`shared_msgs.TargetEstimate` to publish on ``<drone>/target``.

It also keeps the series the flight summary needs: the own-position offset estimate over time
(``offset_log``: (t_ns, north, east, down)) and per-frame ROI hits.
"""

from __future__ import annotations

import dataclasses
import logging

import msgspec
import numpy as np

from onboard.tracking.filter import CooperativeFilter, TrackEstimate, TrackerConfig
from onboard.tracking.measurement import CameraIntrinsics, MeasurementConfig, measurements_from_detections
from onboard.tracking.roi import DetectorPlan, RoiConfig, plan_detection
from shared_msgs.messages import CameraInfo, Detections, TargetEstimate

__all__ = ["TrackingStage", "TrackingStageConfig"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrackingStageConfig:
    tracker: TrackerConfig = TrackerConfig()
    measurement: MeasurementConfig = MeasurementConfig()
    roi: RoiConfig = RoiConfig()
    min_score: float = 0.5  #: boxes below this score are not fused
    #: pose uncertainty this drone reports with its own detections when the detector left it empty
    #: (GNSS grade: ~1 m GPS, ~0.05 m RTK; attitude ~1 deg)
    camera_position_sigma_m: float = 1.0
    camera_rotation_sigma_rad: float = 0.017
    ground_down_m: float = 0.0


class TrackingStage:
    """One drone's tracking (see the module doc)."""

    def __init__(self, drone_id: str, config: TrackingStageConfig = TrackingStageConfig()):
        self.drone_id = drone_id
        self.cfg = config
        self.filter = CooperativeFilter(drone_id, config.tracker)
        self.intrinsics: CameraIntrinsics | None = None
        self.last_plan: DetectorPlan | None = None
        self.offset_log: list[tuple[int, float, float, float]] = []
        self.counts = {"own_frames": 0, "own_measurements": 0, "teammate_measurements": 0, "roi_planned": 0}
        self._seq = 0

    def set_camera_info(self, info: CameraInfo) -> None:
        self.intrinsics = CameraIntrinsics.from_camera_info(info)

    def _intrinsics_of(self, det: Detections) -> CameraIntrinsics | None:
        if self.intrinsics is not None and (self.intrinsics.width_px, self.intrinsics.height_px) == (det.width_px, det.height_px):
            return self.intrinsics
        return self.intrinsics  # teammates fly the same camera model; None until our own info arrives

    def _fuse(self, det: Detections) -> int:
        intr = self._intrinsics_of(det)
        if intr is None or len(det.T_world_cam) != 16:
            return 0
        est = self.filter.estimate(det.header.t_measurement_ns) if self.filter.initialised else None
        hint = None
        if est is not None:
            hint = float(np.linalg.norm(est.position_ned_m - np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)[:3, 3]))
        ms = measurements_from_detections(det, intr, range_hint_m=hint, ground_down_m=self.cfg.ground_down_m,
                                          min_score=self.cfg.min_score, config=self.cfg.measurement)
        if ms:
            self.filter.add_frame(ms)
        return len(ms)

    def on_own_detections(self, det: Detections) -> Detections:
        """Fuse this drone's detections; returns the message to share (``roi_px`` = the ROI planned for it)."""
        self.counts["own_frames"] += 1
        if len(det.T_world_cam_cov) != 36:
            c = self.cfg
            cov = np.diag([c.camera_position_sigma_m**2] * 3 + [c.camera_rotation_sigma_rad**2] * 3)
            det = msgspec.structs.replace(det, T_world_cam_cov=tuple(float(v) for v in cov.reshape(-1)))
        roi = (0.0, 0.0, 0.0, 0.0)
        if self.intrinsics is not None and len(det.T_world_cam) == 16:
            t = det.header.t_measurement_ns
            est = self.filter.estimate(t) if self.filter.initialised else None
            if est is not None:
                est = self.in_reported_frame(est)
            T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)
            self.last_plan = plan_detection(est, self.intrinsics, T, t, self.cfg.roi)
            if self.last_plan.roi_px is not None:
                roi = tuple(float(v) for v in self.last_plan.roi_px)
                self.counts["roi_planned"] += 1
        self.counts["own_measurements"] += self._fuse(det)
        self._log_offset()
        return msgspec.structs.replace(det, roi_px=roi)

    @staticmethod
    def in_reported_frame(est: TrackEstimate) -> TrackEstimate:
        """The estimate as seen from this drone's reported (GPS) frame, in which its camera pose is given:
        person at p + b, position covariance widened by the offset's."""
        cov = est.covariance.copy()
        cov[:3, :3] = cov[:3, :3] + est.offset_cov_m2
        return dataclasses.replace(est, position_ned_m=est.position_ned_m + est.offset_ned_m, covariance=cov)

    def on_teammate_detections(self, det: Detections) -> None:
        if det.header.sender_id == self.drone_id:
            return
        self.counts["teammate_measurements"] += self._fuse(det)

    def _log_offset(self) -> None:
        st = self.filter.state
        if st is not None:
            x, _, t = st
            self.offset_log.append((t, float(x[6]), float(x[7]), float(x[8])))

    def estimate(self, t_ns: int) -> TrackEstimate | None:
        """The prediction at t_ns (None without a track). Before the newest measurement: the newest state."""
        if not self.filter.initialised:
            return None
        st = self.filter.state
        return self.filter.estimate(max(int(t_ns), st[2]))

    def target_message(self, t_ns: int) -> TargetEstimate | None:
        est = self.estimate(t_ns)
        if est is None:
            return None
        self._seq += 1
        msg = est.to_message(self.drone_id, self._seq)
        if self.last_plan is not None and self.last_plan.search:
            msg = msgspec.structs.replace(msg, status="searching")
        return msg
