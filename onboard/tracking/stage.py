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
(``offset_log``: (t_ns, north, east, down), including a detected position step, see
:meth:`TrackingStage.set_position_step`) and per-frame ROI hits.

Malformed input (:func:`detection_problem`: a camera pose that is not a rigid transform, a covariance with
negative variances, impossible image size, boxes with non-finite or inverted edges, negative variances or a
score outside [0, 1]) is ignored and counted (``counts["malformed_detections"]``): a message with a bad pose
or size entirely, otherwise only its bad boxes. NaN/inf never get here over Zenoh (the codec refuses them on
receipt); they are refused here too for direct callers.
"""

from __future__ import annotations

import dataclasses
import logging

import msgspec
import numpy as np

from onboard.tracking.filter import CooperativeFilter, TrackEstimate, TrackerConfig
from onboard.tracking.measurement import MeasurementConfig, measurements_from_detections
from skycap.camera import PinholeCamera
from onboard.tracking.roi import DetectorPlan, RoiConfig, plan_detection
from shared_msgs.messages import CameraInfo, Detections, TargetEstimate

__all__ = ["TrackingStage", "TrackingStageConfig", "detection_problem", "box_problem"]

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
    #: the ground's down (m) for detections that carry none (a sender that never stood on the ground since its
    #: agent started); each drone stamps its own with its take-off ground (:meth:`TrackingStage.set_own_ground`)
    ground_down_m: float = 0.0


def box_problem(b) -> str | None:
    """Why a :class:`shared_msgs.messages.BoundingBox` is malformed (None when it is usable)."""
    edges = (b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px)
    var = (b.var_x_min_px2, b.var_y_min_px2, b.var_x_max_px2, b.var_y_max_px2)
    if not all(np.isfinite(edges)) or not all(np.isfinite(var)) or not np.isfinite(b.score):
        return "non-finite box"
    if not (b.x_max_px > b.x_min_px and b.y_max_px > b.y_min_px):
        return "inverted or empty box"
    if min(var) < 0:
        return "negative edge variance"
    if not 0.0 <= b.score <= 1.0:
        return f"score {b.score} outside [0, 1]"
    return None


def detection_problem(det: Detections, rigid_tol: float = 1e-3) -> str | None:
    """Why a whole :class:`Detections` message is malformed (None when it is usable): image size, camera
    pose (16 finite floats of a rigid transform: orthonormal rotation with determinant +1, last row 0 0 0 1),
    pose covariance (empty or 36 finite floats with non-negative diagonal), ground (None or finite)."""
    if not (det.width_px > 0 and det.height_px > 0):
        return f"image size {det.width_px}x{det.height_px}"
    if len(det.T_world_cam) != 16:
        return f"T_world_cam has {len(det.T_world_cam)} values, not 16"
    T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return "non-finite T_world_cam"
    R = T[:3, :3]
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > rigid_tol or np.abs(R.T @ R - np.eye(3)).max() > rigid_tol \
            or np.linalg.det(R) < 0:
        return "T_world_cam is not a rigid transform"
    if len(det.T_world_cam_cov) not in (0, 36):
        return f"T_world_cam_cov has {len(det.T_world_cam_cov)} values, not 0 or 36"
    if det.T_world_cam_cov:
        C = np.asarray(det.T_world_cam_cov, dtype=float).reshape(6, 6)
        if not np.all(np.isfinite(C)) or np.diag(C).min() < 0:
            return "T_world_cam_cov is not a covariance"
    if det.ground_down_m is not None and not np.isfinite(det.ground_down_m):
        return f"non-finite ground_down_m {det.ground_down_m!r}"
    return None


class TrackingStage:
    """One drone's tracking (see the module doc)."""

    def __init__(self, drone_id: str, config: TrackingStageConfig = TrackingStageConfig()):
        self.drone_id = drone_id
        self.cfg = config
        self.filter = CooperativeFilter(drone_id, config.tracker)
        self.intrinsics: PinholeCamera | None = None
        self.last_plan: DetectorPlan | None = None
        self.offset_log: list[tuple[int, float, float, float]] = []
        self.counts = {"own_frames": 0, "own_measurements": 0, "teammate_measurements": 0, "roi_planned": 0,
                       "malformed_detections": 0, "malformed_boxes": 0}
        self.last_malformed: str = ""
        #: a detected jump of the own position estimate: (step (3,) m, t_ns of the jump, relax time s)
        self._step: tuple[np.ndarray, int, float] | None = None
        self._seq = 0
        #: this drone's reported down while it last stood on the ground (None until then)
        self.own_ground_down_m: float | None = None
        #: this drone's reported position variance (3,) m^2 n, e, d (None: ``camera_position_sigma_m``)
        self.own_position_var_m2: np.ndarray | None = None

    def set_own_position_cov(self, var_m2) -> None:
        """This drone's reported position variance (north, east, down) m^2, e.g. ``VehicleState.position_cov_m2``
        (the receiver's horizontal / vertical accuracy). It becomes the position block of the pose covariance
        stamped on the own detections (which teammates use as this drone's offset prior) and the own offset's
        stationary variance in the filter, in place of the configured ``camera_position_sigma_m``. The agent calls
        it with every state sample; a change below 1 % is ignored."""
        v = np.asarray(var_m2, dtype=float).reshape(3)
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise ValueError(f"set_own_position_cov: need 3 finite variances > 0 (m^2), got {var_m2!r}")
        if self.own_position_var_m2 is not None and np.allclose(v, self.own_position_var_m2, rtol=0.01, atol=0.0):
            return
        self.own_position_var_m2 = v.copy()
        self.filter.set_own_offset_variance(v)

    def set_own_ground(self, down_m: float) -> None:
        """This drone's reported down while it stands on the (flat) take-off ground; the agent calls it with every
        state sample on the ground. Stamped on the own detections as ``ground_down_m``: the ground plane is then
        given in the same reported frame as their camera pose, so a constant height error of this drone's
        estimate moves camera and ground together and the measurement is the person plus this drone's offset
        (the filter's model), instead of sliding along the ray by the height error over the ray's slope."""
        if not np.isfinite(down_m):
            raise ValueError(f"set_own_ground: the reported down must be finite, got {down_m!r}")
        self.own_ground_down_m = float(down_m)

    def set_camera_info(self, info: CameraInfo) -> None:
        self.intrinsics = PinholeCamera.from_camera_info(info)

    def _intrinsics_of(self, det: Detections) -> PinholeCamera | None:
        if self.intrinsics is not None and (self.intrinsics.width_px, self.intrinsics.height_px) == (det.width_px, det.height_px):
            return self.intrinsics
        return self.intrinsics  # teammates fly the same camera model; None until our own info arrives

    # ------------------------------------------------------------------ own position steps (GPS jumps)
    def set_position_step(self, step_ned_m, t_ns: int, relax_s: float) -> None:
        """The own reported position jumped by ``step_ned_m`` (3,) at ``t_ns`` (a step its velocity does not
        explain: an estimator reset / GPS jump). From then on the own camera poses are taken back by
        :meth:`position_correction` (the step, relaxing to 0 over ``relax_s``: the filter's offset state takes
        it over meanwhile), so that the own detections stay consistent with the fleet's frame."""
        step = np.asarray(step_ned_m, dtype=float).reshape(3)
        if not (np.all(np.isfinite(step)) and relax_s > 0):
            raise ValueError(f"set_position_step: need a finite step (m) and relax_s > 0, got {step_ned_m!r}, {relax_s}")
        self._step = (self.position_correction(t_ns) + step, int(t_ns), float(relax_s))
        self.counts["position_steps"] = self.counts.get("position_steps", 0) + 1

    def position_correction(self, t_ns: int) -> np.ndarray:
        """(3,) m to subtract from the own reported position at t_ns (zeros without a detected step)."""
        if self._step is None or t_ns < self._step[1]:
            return np.zeros(3)
        step, t0, tau = self._step
        return step * float(np.exp(-(t_ns - t0) * 1e-9 / tau))

    def _own_pose(self, det: Detections) -> Detections:
        """The message with its pose covariance (when the detector left it empty: the reported position variance,
        :meth:`set_own_position_cov`, else the configured grade), its
        ground (the take-off ground when the detector left it empty) and its camera position taken back by a
        detected position step."""
        c = self.cfg
        if len(det.T_world_cam_cov) != 36:
            pos_var = self.own_position_var_m2 if self.own_position_var_m2 is not None else [c.camera_position_sigma_m**2] * 3
            cov = np.diag([*pos_var] + [c.camera_rotation_sigma_rad**2] * 3)
            det = msgspec.structs.replace(det, T_world_cam_cov=tuple(float(v) for v in cov.reshape(-1)))
        if det.ground_down_m is None and self.own_ground_down_m is not None:
            det = msgspec.structs.replace(det, ground_down_m=self.own_ground_down_m)
        corr = self.position_correction(det.header.t_measurement_ns)
        if np.any(corr != 0.0):
            T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4).copy()
            T[:3, 3] -= corr
            det = msgspec.structs.replace(det, T_world_cam=tuple(float(v) for v in T.reshape(-1)))
        return det

    def _sanitise(self, det: Detections) -> Detections | None:
        """The message without its malformed boxes; None when the message as a whole is malformed. Counts both."""
        why = detection_problem(det)
        if why is None:
            bad = [(b, box_problem(b)) for b in det.boxes]
            bad = [(b, w) for b, w in bad if w is not None]
            if not bad:
                return det
            self.counts["malformed_boxes"] += len(bad)
            why = f"{len(bad)} malformed box(es): {bad[0][1]}"
            det = msgspec.structs.replace(det, boxes=[b for b in det.boxes if box_problem(b) is None])
        else:
            det = None
        self.counts["malformed_detections"] += 1
        self.last_malformed = why
        n = self.counts["malformed_detections"]
        if n <= 5 or n % 100 == 0:
            log.warning("%s: ignored malformed detections #%d: %s", self.drone_id, n, why)
        return det

    def _fuse(self, det: Detections) -> int:
        intr = self._intrinsics_of(det)
        if intr is None or len(det.T_world_cam) != 16:
            return 0
        est = self.filter.estimate(det.header.t_measurement_ns) if self.filter.initialised else None
        hint = None
        if est is not None:
            hint = float(np.linalg.norm(est.position_ned_m - np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)[:3, 3]))
        ms = measurements_from_detections(det, intr, range_hint_m=hint, ground_down_m=self.cfg.ground_down_m,
                                          min_score=self.cfg.min_score, config=self.cfg.measurement,
                                          person_velocity_ned_mps=None if est is None else est.velocity_ned_m_s)
        if ms:
            self.filter.add_frame(ms)
        return len(ms)

    def plan_for(self, t_ns: int, T_world_cam) -> DetectorPlan | None:
        """The detector's job for a frame captured at t_ns from T_world_cam ((16,) or (4, 4), this drone's
        reported frame): the ROI of the filter's prediction, or a search; None before the camera info."""
        if self.intrinsics is None or np.size(T_world_cam) != 16:
            return None
        est = self.filter.estimate(t_ns) if self.filter.initialised else None
        if est is not None:
            est = est.in_reported_frame()  # this drone's reported (GPS) frame, in which its camera pose is given
        T = np.asarray(T_world_cam, dtype=float).reshape(4, 4)
        return plan_detection(est, self.intrinsics, T, int(t_ns), self.cfg.roi)

    def on_own_detections(self, det: Detections, plan: DetectorPlan | None = None) -> Detections | None:
        """Fuse this drone's detections; returns the message to share, None when the message was malformed
        (ignored and counted; its good boxes, if any, are kept).

        plan: the plan the detector ran with (:meth:`plan_for` before detection; the message's ``roi_px`` is
        then the region it searched). None (a detector that does not take a region, e.g. the simulator's):
        the plan is made here and ``roi_px`` of the shared message is the ROI planned for this frame."""
        det = self._sanitise(det)
        if det is None:
            return None
        self.counts["own_frames"] += 1
        det = self._own_pose(det)
        roi = tuple(det.roi_px) if plan is not None else (0.0, 0.0, 0.0, 0.0)
        if plan is None:
            plan = self.plan_for(det.header.t_measurement_ns, det.T_world_cam)
            if plan is not None and plan.roi_px is not None:
                roi = tuple(float(v) for v in plan.roi_px)
        if plan is not None:
            self.last_plan = plan
            if plan.roi_px is not None:
                self.counts["roi_planned"] += 1
        self.counts["own_measurements"] += self._fuse(det)
        self._log_offset()
        return msgspec.structs.replace(det, roi_px=roi)

    def on_teammate_detections(self, det: Detections) -> None:
        if det.header.sender_id == self.drone_id:
            return
        det = self._sanitise(det)
        if det is None:
            return
        self.counts["teammate_measurements"] += self._fuse(det)

    def own_offset(self, est: TrackEstimate | None, t_ns: int) -> np.ndarray:
        """(3,) this drone's total position correction at t_ns: the filter's offset (reported - true, in the
        frame of the corrected poses) plus a detected position step (zeros for the offset without a track)."""
        b = np.zeros(3) if est is None else np.asarray(est.offset_ned_m, dtype=float)
        return b + self.position_correction(t_ns)

    def _log_offset(self) -> None:
        st = self.filter.state
        if st is not None:
            x, _, t = st
            o = x[6:9] + self.position_correction(t)
            self.offset_log.append((t, float(o[0]), float(o[1]), float(o[2])))

    def estimate(self, t_ns: int) -> TrackEstimate | None:
        """The prediction at t_ns (None without a track). Before the newest measurement: the newest state."""
        if not self.filter.initialised:
            return None
        st = self.filter.state
        return self.filter.estimate(max(int(t_ns), st[2]))

    def target_message(self, t_ns: int) -> TargetEstimate | None:
        """The estimate to publish at t_ns: position/velocity at the newest fused detection's capture time
        (``header.t_measurement_ns``, the time of measurement; receivers predict to their own time with the
        velocity), status as of t_ns; None without a track."""
        now = self.estimate(t_ns)
        if now is None:
            return None
        est = self.filter.estimate(self.filter.state[2])
        est = dataclasses.replace(est, status=now.status, num_sources=now.num_sources)
        self._seq += 1
        msg = est.to_message(self.drone_id, self._seq)
        if self.last_plan is not None and self.last_plan.search:
            msg = msgspec.structs.replace(msg, status="searching")
        return msg
