"""The simulated camera of one drone: at its frame rate, take the latest truth, render, emit messages.

    node = CameraNode("drone_1", SceneConfig(), truth_source=get_truth, sink=lambda topic, msg: ...)
    node.step()                         # one frame now (tests)
    node.run(stop_event)                # at cfg.camera.rate_hz until stop_event is set

Design: no network here. ``truth_source()`` returns the latest :class:`CameraTruth` (or None: nothing to
render yet) and ``sink(topic, msg)`` receives each message with its topic suffix (a
:mod:`shared_msgs.keys` topic such as ``keys.CAMERA_IMAGE``; the Zenoh adapter in
:mod:`simulator.scene.cli` turns it into ``skycap/v1/<fleet>/<drone>/<topic>``).

Per frame (``header.sender_id`` = the drone, ``header.t_measurement_ns`` = the truth's capture time):

| topic | message |
| --- | --- |
| ``camera_info`` | :class:`CameraInfo`, on the first frame, on a change (gimbal pitch or yaw, > 0.01 deg) and every ``info_period_s`` |
| ``camera/image`` | :class:`CameraFrame` (JPEG); ``T_world_cam`` = the camera pose from the vehicle's *estimated* pose when the truth carries one, else empty |
| ``sim/keypoints2d`` | :class:`Keypoints2D`, ``simulated=True``, ``detector="sim_noisy_gt"`` (no person: empty list) |
| ``sim/keypoints2d_gt`` | :class:`Keypoints2D`, ``simulated=True``, ``detector="ground_truth"``: exact projections, confidence 1 where visible, 0.5 where visible but hidden behind another body part, 0 outside the image or behind the camera; box = GT body box |
| ``sim/detections`` | :class:`Detections`, ``detector="simulated"``, ``mode="simulated"`` (only with an estimated pose, which that message requires) |

The ground-truth camera pose is not put in any message here: it is the vehicle truth (``SimTruth``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from shared_msgs import keys
from shared_msgs.messages import (
    BoundingBox,
    CameraFrame,
    CameraInfo,
    Detections,
    Keypoints2D,
    Message,
    PersonKeypoints,
    SimTruth,
    VehicleState,
)
from simulator.scene.camera import GtProjection, PinholeCamera, camera_pose
from simulator.scene.config import SceneConfig
from simulator.scene.render import Renderer, encode_jpeg
from simulator.scene.sim_detector import SIM_BOX_DETECTOR, SIM_KEYPOINT_DETECTOR, SimBoxDetector, SimKeypointDetector
from skycap.frames import R_body_cam, make_T

log = logging.getLogger(__name__)

__all__ = ["CameraTruth", "CameraNode", "truth_from_messages", "SIM_KEYPOINTS2D_GT", "SIM_DETECTIONS", "GT_DETECTOR"]

#: Topic suffixes this node adds to :mod:`shared_msgs.keys` (proposed there as constants).
SIM_KEYPOINTS2D_GT = keys.SIM_KEYPOINTS2D_GT
SIM_DETECTIONS = keys.SIM_DETECTIONS
GT_DETECTOR = "ground_truth"


@dataclasses.dataclass
class CameraTruth:
    """What one camera frame is rendered from.

    t_ns: capture time (ns, the messages' time base); position_ned_m (3,), q_world_body (4,) (w, x, y, z):
    the vehicle's TRUE pose; gimbal_pitch_rad: true gimbal pitch (None: the config's pitch); gimbal_yaw_rad: true
    gimbal yaw relative to the vehicle's heading (None: 0, the camera looks ahead);
    person_joints_ned_m: (17, 3) or None (no person in the scene); est_*: the vehicle's own estimate
    (what its autopilot reports) or None.
    """

    t_ns: int
    position_ned_m: np.ndarray
    q_world_body: np.ndarray
    gimbal_pitch_rad: float | None = None
    person_joints_ned_m: np.ndarray | None = None
    est_position_ned_m: np.ndarray | None = None
    est_q_world_body: np.ndarray | None = None
    gimbal_yaw_rad: float | None = None


def truth_from_messages(truth: SimTruth, drone_id: str, estimate: VehicleState | None = None) -> CameraTruth | None:
    """A :class:`CameraTruth` for ``drone_id`` from the simulator's :class:`SimTruth` (and the drone's
    own :class:`VehicleState`, if any); None if the truth does not list that drone."""
    v = next((v for v in truth.vehicles if v.drone_id == drone_id), None)
    if v is None:
        return None
    joints = np.asarray(truth.person_joints_ned_m, dtype=float).reshape(17, 3) if truth.person_joints_ned_m else None
    return CameraTruth(
        t_ns=truth.header.t_measurement_ns,
        position_ned_m=np.asarray(v.position_ned_m, dtype=float),
        q_world_body=np.asarray(v.q_world_body, dtype=float),
        gimbal_pitch_rad=float(v.gimbal_pitch_rad),
        gimbal_yaw_rad=float(v.gimbal_yaw_rad),
        person_joints_ned_m=joints,
        est_position_ned_m=None if estimate is None else np.asarray(estimate.position_ned_m, dtype=float),
        est_q_world_body=None if estimate is None else np.asarray(estimate.q_world_body, dtype=float),
    )


def _flat(T: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(T, dtype=float).reshape(-1))


def _bbox_msg(b: np.ndarray, score: float = 1.0) -> BoundingBox:
    return BoundingBox(x_min_px=float(b[0]), y_min_px=float(b[1]), x_max_px=float(b[2]), y_max_px=float(b[3]), score=score)


class CameraNode:
    """One drone's simulated camera (see the module doc). ``clock_ns`` is only used when a truth has no time."""

    def __init__(
        self,
        drone_id: str,
        cfg: SceneConfig,
        truth_source: Callable[[], CameraTruth | None],
        sink: Callable[[str, Message], None],
    ):
        self.drone_id = drone_id
        self.cfg = cfg.validate()
        self.cam_cfg = cfg.camera
        self.cam = PinholeCamera.from_config(cfg.camera)
        # distinct, reproducible noise per drone (image noise and simulated detections)
        drone_salt = sum(drone_id.encode()) * 7919
        self.renderer = Renderer(self.cam, cfg.camera, cfg.person, noise_seed=cfg.camera.noise_seed + drone_salt)
        seed = cfg.sim_detector.seed + drone_salt
        self.kp_detector = SimKeypointDetector(cfg.sim_detector, np.random.default_rng(seed))
        self.box_detector = SimBoxDetector(cfg.sim_detector, np.random.default_rng(seed + 1))
        self.truth_source = truth_source
        self.sink = sink
        self.frame_index = 0
        self._last_info: tuple | None = None
        self._last_info_t = -math.inf
        self.stats = {"frames": 0, "no_truth": 0, "render_ms_sum": 0.0, "cpu_ms_sum": 0.0, "late_frames": 0}

    # ------------------------------------------------------------------ messages
    def camera_info(self, t_ns: int, gimbal_pitch_rad: float, gimbal_yaw_rad: float = 0.0) -> CameraInfo:
        c = self.cam
        if self.cam_cfg.mount == "gimbal":
            T_body_cam = make_T(R_body_cam(0.0), self.cam_cfg.lever_arm_body_m)
            pitch, yaw = gimbal_pitch_rad, gimbal_yaw_rad
        else:
            T_body_cam = make_T(R_body_cam(math.radians(self.cam_cfg.pitch_deg)), self.cam_cfg.lever_arm_body_m)
            pitch = yaw = 0.0
        return CameraInfo(
            header=CameraInfo.make_header(self.drone_id, t_ns, self.frame_index),
            camera_id=self.cam_cfg.camera_id,
            width_px=c.width_px, height_px=c.height_px,
            fx_px=c.fx_px, fy_px=c.fy_px, cx_px=c.cx_px, cy_px=c.cy_px,
            T_body_cam=_flat(T_body_cam),
            gimbal_pitch_rad=float(pitch),
            gimbal_yaw_rad=float(yaw),
        )  # fmt: skip

    def _keypoints_msg(self, t_ns: int, detector: str, persons: list[PersonKeypoints]) -> Keypoints2D:
        return Keypoints2D(
            header=Keypoints2D.make_header(self.drone_id, t_ns, self.frame_index),
            camera_id=self.cam_cfg.camera_id,
            frame_index=self.frame_index,
            detector=detector,
            simulated=True,
            persons=persons,
        )

    @staticmethod
    def gt_person(gt: GtProjection) -> PersonKeypoints | None:
        """Exact projections as keypoints (confidence 1 visible, 0.5 visible but occluded by the body, 0 not
        visible; positions behind the camera are reported as 0)."""
        if gt.box_px is None:
            return None
        uv = np.where(gt.in_front[:, None], gt.uv_px, 0.0)
        return PersonKeypoints(
            keypoints_px=tuple(float(v) for v in uv.reshape(-1)),
            confidence=tuple((0.5 if o else 1.0) if v else 0.0 for v, o in zip(gt.visible, gt.occluded)),
            box=_bbox_msg(gt.box_px),
        )

    # ------------------------------------------------------------------ one frame
    def step(self) -> dict[str, Message] | None:
        """Render and emit one frame from the latest truth; returns {topic: message} (None: no truth yet)."""
        cpu0 = time.process_time()
        truth = self.truth_source()
        if truth is None:
            self.stats["no_truth"] += 1
            return None
        t_ns = int(truth.t_ns)
        cc = self.cam_cfg
        if not cc.pitch_from_truth:
            truth = dataclasses.replace(truth, gimbal_pitch_rad=None, gimbal_yaw_rad=None)
        # the gimbal's true attitude: pitch to the horizon, yaw relative to the heading
        gp, gy = truth.gimbal_pitch_rad, truth.gimbal_yaw_rad
        T_true = camera_pose(cc, truth.position_ned_m, truth.q_world_body, gp, gy)
        T_est = None
        if truth.est_position_ned_m is not None and truth.est_q_world_body is not None:
            T_est = camera_pose(cc, truth.est_position_ned_m, truth.est_q_world_body, gp, gy)
        frame = self.renderer.render(T_true, truth.person_joints_ned_m)
        out: dict[str, Message] = {}
        pitch = math.radians(cc.pitch_deg) if gp is None else float(gp)
        yaw = 0.0 if gy is None else float(gy)
        info_key = (round(pitch, 4), round(yaw, 4))
        if info_key != self._last_info or (t_ns - self._last_info_t) >= cc.info_period_s * 1e9:
            out[keys.CAMERA_INFO] = self.camera_info(t_ns, pitch, yaw)
            self._last_info, self._last_info_t = info_key, t_ns
        W, H = self.cam.width_px, self.cam.height_px
        out[keys.CAMERA_IMAGE] = CameraFrame(
            header=CameraFrame.make_header(self.drone_id, t_ns, self.frame_index),
            camera_id=cc.camera_id,
            frame_index=self.frame_index,
            encoding="jpeg",
            width_px=W,
            height_px=H,
            data=encode_jpeg(frame.image, cc.jpeg_quality),
            T_world_cam=_flat(T_est) if T_est is not None else (),
        )
        gt = frame.gt
        persons: list[PersonKeypoints] = []
        gt_persons: list[PersonKeypoints] = []
        if gt is not None:
            det = self.kp_detector.detect(gt, W, H, t_s=t_ns * 1e-9)
            if det is not None:
                persons.append(det.to_person_keypoints())
            gp = self.gt_person(gt)
            if gp is not None:
                gt_persons.append(gp)
        out[keys.SIM_KEYPOINTS2D] = self._keypoints_msg(t_ns, SIM_KEYPOINT_DETECTOR, persons)
        out[SIM_KEYPOINTS2D_GT] = self._keypoints_msg(t_ns, GT_DETECTOR, gt_persons)
        if T_est is not None:
            out[SIM_DETECTIONS] = Detections(
                header=Detections.make_header(self.drone_id, t_ns, self.frame_index),
                camera_id=cc.camera_id,
                frame_index=self.frame_index,
                detector=SIM_BOX_DETECTOR,
                mode="simulated",
                boxes=self.box_detector.detect(gt, W, H),
                width_px=W,
                height_px=H,
                T_world_cam=_flat(T_est),
            )
        for topic, msg in out.items():
            self.sink(topic, msg)
        self.frame_index += 1
        self.stats["frames"] += 1
        self.stats["render_ms_sum"] += frame.timings_ms["total_ms"]
        self.stats["cpu_ms_sum"] += (time.process_time() - cpu0) * 1e3
        return out

    # ------------------------------------------------------------------ loop
    def run(self, stop: threading.Event, max_frames: int | None = None) -> None:
        """Emit frames at ``camera.rate_hz`` (drift-free schedule; a late frame is not made up for)."""
        period = 1.0 / self.cam_cfg.rate_hz
        next_t = time.monotonic()
        n = 0
        while not stop.is_set() and (max_frames is None or n < max_frames):
            try:
                if self.step() is not None:
                    n += 1
            except Exception:
                log.exception("%s camera: frame failed", self.drone_id)
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                self.stats["late_frames"] += 1
                next_t = time.monotonic()  # skip, don't burst
                continue
            stop.wait(delay)
        frames = max(self.stats["frames"], 1)
        log.info(
            "%s camera: %d frames, %.1f ms mean render (wall), %.1f ms CPU per frame, %d late, %d without truth",
            self.drone_id, self.stats["frames"], self.stats["render_ms_sum"] / frames,
            self.stats["cpu_ms_sum"] / frames, self.stats["late_frames"], self.stats["no_truth"],
        )  # fmt: skip
