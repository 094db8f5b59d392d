"""Synthetic captures from real motion: virtual drones orbit a person whose 3D joints come from motion
capture, and record noisy 2D keypoints and noisy self-pose estimates (the evaluation harness's source).

Pipeline (:func:`synthesize_capture`):

1. Ground-truth joints ``joints_ned`` (T, 17, 3) metres, world NED, at times ``t_ns`` (T,) — e.g.
   ``mocap_to_coco17(read_bvh(f))`` (:mod:`skycap.skeleton`).
2. ``drones`` cameras fly a circular orbit of ``radius_m`` at ``altitude_m`` above the ground (down = 0)
   about the person's (smoothed) hip centre, evenly spaced, moving at ``speed_mps`` along the orbit,
   each camera aimed at the same smoothed hip centre (the filtered person estimate a gimbal controller
   tracks), with a small slow aim wobble. True poses are sampled at ``pose_rate_hz``.
3. Each camera captures frames at ``camera_rate_hz``; with ``unsync`` each camera gets its own random
   phase in [0, 1/rate) and a small per-frame jitter, so frames of different cameras never coincide.
4. Keypoints: true joints (linearly interpolated to the frame time) projected with the TRUE pose, plus
   Gaussian noise ``noise_px`` per axis; with probability ``outlier_rate`` a keypoint is replaced by a
   wrong point (uniform in the person's box grown by 50 %), with ``swap_rate`` a whole detection has
   left/right swapped, with ``miss_rate`` a keypoint is missing (confidence 0); points outside the
   image are missing. Confidences: inliers U(0.5, 1), outliers U(0.2, 0.8) (a detector is often
   confident about its mistakes). ``detectors`` independent detectors per camera.
5. Drone self-pose estimates: true pose + error. ``pose_errors = "flight"``: the simulator's estimator error model
   (``flight_errors``, :class:`FlightPoseErrors`; :mod:`evaluation.harness` fills it from
   ``simulator.config.EstimatorConfig`` at RTK or GPS grade): per drone a position bias, first-order Gauss-Markov
   per axis (horizontal / vertical std, correlation time ``pos_bias_time_constant_s``, 60 s by default), plus white
   position noise per pose sample, and an attitude error per axis, Gauss-Markov (std ``att_noise_std_deg``,
   correlation time ``att_noise_time_constant_s``), applied as ``R_est = R_true @ exp(err)`` as the simulator does
   (``attitude_axes = "all"``: a body-fixed camera) or, by default (``"yaw"``), only its yaw part about the world's
   down axis: a gimbal-stabilised camera's tilt comes from the gimbal, its pan from the vehicle's yaw estimate;
   the processes start in their stationary state ``margin_s`` before the clip (the drones have flown a while, as on
   a real flight: :func:`skycap.gauss_markov.gauss_markov_series`). With ``pose_errors = "flight"`` the drones report
   velocity (noise ``vel_noise_std_m_s`` per axis) but no angular velocity, as the flight reader gives the fit.
   ``pose_errors = "white"`` (the original harness): ``camera_pos_noise_m`` and ``camera_rot_noise_deg``
   are the RMS 3D error (position norm, rotation angle). A fraction ``camera_noise_drift_fraction`` of
   the error variance is a constant bias + slow drift (period 5-20 s) per axis, the rest is white
   noise per pose sample (GNSS/IMU jitter). Default 0 (white): a bias common to all drones cannot be
   observed from images (it moves cameras and person together) and shows up in MPJPE 1:1. The capture
   carries these sigmas as the drones' uncertainty.
6. With ``imu_rates`` the drones also report what their estimator and IMU measure precisely over
   seconds: camera velocity (true velocity + white noise ``camera_vel_noise_mps`` RMS 3D; GNSS Doppler
   velocity is good to about 0.05 m/s per axis) and camera angular velocity in the camera frame (true
   rate + white noise ``camera_rate_noise_degps`` + a constant per-drone bias ``camera_rate_bias_degps``,
   both RMS 3D: the residual gyro bias an estimator leaves). These draws come from their own random
   stream, so the same seed gives the same keypoints and pose samples with or without them.

Example::

    cap, truth = synthesize_capture(joints_ned, t_ns, SynthConfig(drones=3), seed=0)
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from reconstruction.capture import CameraCapture, Capture, CaptureError, interpolate_poses
from skycap.config import ConfigError
from skycap.frames import intrinsics_matrix, make_T, project_points
from skycap.gauss_markov import gauss_markov_series
from skycap.skeleton import COCO17_FLIP

__all__ = ["SynthConfig", "FlightPoseErrors", "POSE_ERRORS", "flight_pose_errors", "SynthTruth", "synthesize_capture", "true_rates", "interpolate_joints", "look_at_T_world_cam"]


#: how the drones' pose estimates err: "white" (white noise, the original harness) or "flight" (the simulator's
#: estimator: Gauss-Markov position bias and attitude error, :class:`FlightPoseErrors`)
POSE_ERRORS = ("white", "flight")


@dataclasses.dataclass
class FlightPoseErrors:
    """The flight's pose-error model (``pose_errors = "flight"``); field names and meanings as
    ``simulator.config.EstimatorConfig``, whose values :mod:`evaluation.harness` copies in (the layers keep
    reconstruction/ from importing the simulator). Zero = no such error."""

    pos_bias_std_xy_m: float = 0.0
    pos_bias_std_z_m: float = 0.0
    pos_bias_time_constant_s: float = 60.0
    pos_noise_std_m: float = 0.0
    att_noise_std_deg: float = 0.0
    att_noise_time_constant_s: float = 1.0
    vel_noise_std_m_s: float = 0.0
    #: which camera axes the attitude error turns: "yaw" (a gimbal-stabilised camera, as the product flies: its tilt
    #: comes from the gimbal, its pan from the vehicle's yaw estimate -- the flight reader takes only the yaw from
    #: the estimated attitude) or "all" (a camera fixed to the body: roll, pitch and yaw errors)
    attitude_axes: str = "yaw"
    #: the processes start (stationary) this long before the clip: the drones have been flying
    margin_s: float = 60.0

    def pos_sigma_m(self) -> float:
        """RMS 3D position error (the capture's ``pos_sigma_m``)."""
        return float(np.sqrt(2 * self.pos_bias_std_xy_m**2 + self.pos_bias_std_z_m**2 + 3 * self.pos_noise_std_m**2))

    def rot_sigma_deg(self) -> float:
        """RMS 3D attitude error, degrees (the capture's ``rot_sigma_deg``)."""
        return float((1.0 if self.attitude_axes == "yaw" else np.sqrt(3.0)) * self.att_noise_std_deg)


@dataclasses.dataclass
class SynthConfig:
    """Virtual flight and detector noise. Defaults = the issue's default harness setting."""

    drones: int = 3
    radius_m: float = 8.0
    altitude_m: float = 8.0
    speed_mps: float = 1.0  # tangential speed of the orbit (0 = hover)
    camera_rate_hz: float = 30.0
    unsync: bool = True
    frame_jitter_ms: float = 2.0
    pose_rate_hz: float = 50.0
    noise_px: float = 5.0
    outlier_rate: float = 0.10
    swap_rate: float = 0.02
    miss_rate: float = 0.05
    detectors: int = 1
    camera_pos_noise_m: float = 0.5
    camera_rot_noise_deg: float = 2.0
    camera_noise_drift_fraction: float = 0.0
    #: "white" (the camera_*_noise fields above) or "flight" (``flight_errors``); see the module doc, 5
    pose_errors: str = "white"
    flight_errors: FlightPoseErrors = dataclasses.field(default_factory=FlightPoseErrors)
    imu_rates: bool = True
    camera_vel_noise_mps: float = 0.1
    camera_rate_noise_degps: float = 0.2
    camera_rate_bias_degps: float = 0.02
    width_px: int = 1920
    height_px: int = 1080
    focal_px: float = 1500.0
    aim_wobble_deg: float = 1.0


@dataclasses.dataclass
class SynthTruth:
    """Ground truth of a synthetic capture."""

    t_ns: np.ndarray  # (T,) joint times
    joints_ned: np.ndarray  # (T, 17, 3)
    T_world_cam_true: list[np.ndarray]  # per camera (P, 4, 4) at that camera's t_pose_ns
    T_world_cam_true_frames: list[np.ndarray]  # per camera (F, 4, 4) at its frame times


def interpolate_joints(t_ns: np.ndarray, joints: np.ndarray, t_query_ns: np.ndarray) -> np.ndarray:
    """Joints (Q, J, 3) linearly interpolated in time (clamped). Shapes: t_ns (T,), joints (T, J, 3)."""
    t = (np.asarray(t_ns, dtype=np.int64) - t_ns[0]).astype(float)
    q = (np.asarray(t_query_ns, dtype=np.int64) - t_ns[0]).astype(float)
    flat = joints.reshape(len(t), -1)
    out = np.stack([np.interp(q, t, flat[:, k]) for k in range(flat.shape[1])], axis=-1)
    return out.reshape((len(q),) + joints.shape[1:])


def look_at_T_world_cam(cam_pos_ned: np.ndarray, target_ned: np.ndarray) -> np.ndarray:
    """Camera poses (N, 4, 4) at ``cam_pos_ned`` (N, 3) looking at ``target_ned`` (N, 3), image x level
    (no roll): optical z = towards target, x = right (horizontal), y = down-ish."""
    z = target_ned - cam_pos_ned
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    down = np.array([0.0, 0.0, 1.0])
    x = np.cross(down, z)  # right: down x forward
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)
    return make_T(R, cam_pos_ned)


def _smooth_error(rng: np.random.Generator, t_s: np.ndarray, rms: float) -> np.ndarray:
    """(N, 3) error: constant bias + slow sinusoidal drift, expected RMS 3D norm = ``rms``."""
    if rms <= 0:
        return np.zeros((len(t_s), 3))
    per_axis = rms / np.sqrt(3.0)
    bias = rng.normal(0.0, per_axis * np.sqrt(0.7), 3)
    amp = rng.normal(0.0, per_axis * np.sqrt(0.3 * 2.0), 3)
    period = rng.uniform(5.0, 20.0, 3)
    phase = rng.uniform(0, 2 * np.pi, 3)
    return bias + amp * np.sin(2 * np.pi * t_s[:, None] / period + phase)


def _pose_error(rng: np.random.Generator, t_s: np.ndarray, rms: float, drift_fraction: float) -> np.ndarray:
    """(N, 3) error with RMS 3D norm ``rms``: drift part (variance fraction) + white part."""
    f = float(np.clip(drift_fraction, 0.0, 1.0))
    white = rng.normal(0.0, rms * np.sqrt(1 - f) / np.sqrt(3.0), (len(t_s), 3))
    return _smooth_error(rng, t_s, rms * np.sqrt(f)) + white


def flight_pose_errors(rng: np.random.Generator, tp_s: np.ndarray, fe: FlightPoseErrors) -> tuple[np.ndarray, np.ndarray]:
    """One drone's (position error (P, 3) NED m, attitude error (P, 3) rad rotation vector) at the pose times ``tp_s``
    (P,) seconds from the clip's start, under the flight's model (module doc, 5): Gauss-Markov bias + white position
    noise, Gauss-Markov attitude error, both run from ``fe.margin_s`` before the clip in their stationary state. The
    attitude error is a rotation vector in the camera frame (``attitude_axes = "all"``) or about the world's down axis
    only (``"yaw"``: the pan of a gimbal-stabilised camera; its x and y are 0)."""
    t = np.concatenate([[tp_s[0] - max(fe.margin_s, 0.0)], tp_s])
    sig_p = np.array([fe.pos_bias_std_xy_m, fe.pos_bias_std_xy_m, fe.pos_bias_std_z_m])
    bias = gauss_markov_series(t, fe.pos_bias_time_constant_s, sig_p, rng)[1:]
    white = rng.normal(0.0, fe.pos_noise_std_m, (len(tp_s), 3))
    att = gauss_markov_series(t, fe.att_noise_time_constant_s, np.radians(fe.att_noise_std_deg), rng)[1:]
    if fe.attitude_axes == "yaw":
        att[:, :2] = 0.0
    elif fe.attitude_axes != "all":
        raise ConfigError(f"flight_errors.attitude_axes={fe.attitude_axes!r}; use 'yaw' or 'all'")
    return bias + white, att


def true_rates(t_s: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact camera velocity (P, 3) world and angular velocity (P, 3) camera frame of a pose track
    (times (P,) seconds, poses (P, 4, 4)): velocity by central differences; angular velocity forward,
    so that R[k+1] = R[k] exp([omega[k] dt]x) holds exactly (the last sample repeats the one before)."""
    v = np.gradient(T_world_cam[:, :3, 3], t_s, axis=0)
    R = Rotation.from_matrix(T_world_cam[:, :3, :3])
    w = (R[:-1].inv() * R[1:]).as_rotvec() / np.diff(t_s)[:, None]
    return v, np.concatenate([w, w[-1:]], axis=0)


def _imu_rates(rng: np.random.Generator, t_s: np.ndarray, T_true: np.ndarray, cfg: SynthConfig) -> dict:
    """The rate channels of one camera (CameraCapture keyword arguments): truth + noise (module doc, 6); with
    ``pose_errors = "flight"`` the velocity alone, with the estimator's velocity noise (module doc, 5)."""
    v, w = true_rates(t_s, T_true)
    n = len(t_s)
    if cfg.pose_errors == "flight":
        s = cfg.flight_errors.vel_noise_std_m_s
        return {"vel_world_mps": v + rng.normal(0.0, s, (n, 3)), "vel_sigma_mps": max(np.sqrt(3.0) * s, 1e-3)}
    v_meas = v + rng.normal(0.0, cfg.camera_vel_noise_mps / np.sqrt(3.0), (n, 3))
    bias = rng.normal(0.0, np.radians(cfg.camera_rate_bias_degps) / np.sqrt(3.0), 3)
    w_meas = w + bias + rng.normal(0.0, np.radians(cfg.camera_rate_noise_degps) / np.sqrt(3.0), (n, 3))
    w_sigma = np.radians(np.hypot(cfg.camera_rate_noise_degps, cfg.camera_rate_bias_degps))
    return {"vel_world_mps": v_meas, "vel_sigma_mps": max(cfg.camera_vel_noise_mps, 1e-3),
            "omega_cam_radps": w_meas, "omega_sigma_radps": max(w_sigma, 1e-5)}  # fmt: skip


def synthesize_capture(
    joints_ned: np.ndarray, t_ns: np.ndarray, cfg: SynthConfig | None = None, seed: int = 0
) -> tuple[Capture, SynthTruth]:
    """Fly virtual drones around real motion; shapes in the module docstring.

    Returns (capture with drone-estimated poses and noisy keypoints, ground truth).
    """
    cfg = cfg or SynthConfig()
    joints_ned = np.asarray(joints_ned, dtype=float)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if joints_ned.ndim != 3 or joints_ned.shape[1:] != (17, 3):
        raise CaptureError(f"joints_ned must be (T, 17, 3) COCO-17 metres, got {joints_ned.shape}")
    if len(t_ns) != len(joints_ned) or len(t_ns) < 2:
        raise CaptureError("t_ns must give one time per joint frame, at least 2 frames")
    if cfg.drones < 1:
        raise CaptureError("drones must be >= 1")
    if cfg.pose_errors not in POSE_ERRORS:
        raise ConfigError(f"synth.pose_errors={cfg.pose_errors!r}; use one of {', '.join(map(repr, POSE_ERRORS))}")
    rng = np.random.default_rng(seed)
    rng_rates = np.random.default_rng([seed, 1])  # own stream: rates on/off leaves the other draws alone
    rng_flight = np.random.default_rng([seed, 2])  # own stream: the flight's pose errors
    t0, t1 = int(t_ns[0]), int(t_ns[-1])
    dur_s = (t1 - t0) * 1e-9
    hip_mid = 0.5 * (joints_ned[:, 11] + joints_ned[:, 12])
    fps = (len(t_ns) - 1) / max(dur_s, 1e-9)
    centre = gaussian_filter1d(hip_mid, sigma=max(fps * 0.5, 1.0), axis=0, mode="nearest")  # follow ~0.5 s lag-free

    t_pose = np.arange(t0, t1 + 1, int(1e9 / cfg.pose_rate_hz), dtype=np.int64)
    if t_pose[-1] != t1:
        t_pose = np.append(t_pose, t1)
    tp_s = (t_pose - t0) * 1e-9
    centre_p = interpolate_joints(t_ns, centre[:, None], t_pose)[:, 0]
    hip_p = interpolate_joints(t_ns, hip_mid[:, None], t_pose)[:, 0]
    omega = cfg.speed_mps / max(cfg.radius_m, 1e-6)
    K = intrinsics_matrix(cfg.focal_px, cfg.focal_px, cfg.width_px / 2.0, cfg.height_px / 2.0)
    period_ns = int(1e9 / cfg.camera_rate_hz)
    if cfg.pose_errors == "flight":
        pos_sigma, rot_sigma = cfg.flight_errors.pos_sigma_m(), cfg.flight_errors.rot_sigma_deg()
    else:
        pos_sigma, rot_sigma = cfg.camera_pos_noise_m, cfg.camera_rot_noise_deg

    cams, T_true_all, T_true_frames = [], [], []
    for c in range(cfg.drones):
        ang = 2 * np.pi * c / cfg.drones + omega * tp_s + rng.uniform(-0.1, 0.1)
        pos = np.stack(
            [centre_p[:, 0] + cfg.radius_m * np.cos(ang), centre_p[:, 1] + cfg.radius_m * np.sin(ang),
             np.full_like(ang, -cfg.altitude_m)], axis=-1)  # fmt: skip
        wob = _smooth_error(rng, tp_s, np.radians(cfg.aim_wobble_deg) * np.linalg.norm(pos - hip_p, axis=-1).mean())
        T_true = look_at_T_world_cam(pos, centre_p + wob)  # gimbal tracks the filtered person estimate
        if cfg.pose_errors == "flight":  # the simulator's estimator: R_est = R_true @ exp(err), or the pan error alone
            dp, dr = flight_pose_errors(rng_flight, tp_s, cfg.flight_errors)
            if cfg.flight_errors.attitude_axes == "yaw":  # the vehicle's yaw error turns the camera about world down
                R_est = Rotation.from_rotvec(dr).as_matrix() @ T_true[:, :3, :3]
            else:
                R_est = T_true[:, :3, :3] @ Rotation.from_rotvec(dr).as_matrix()
        else:  # drone estimate = truth + bias/drift
            dp = _pose_error(rng, tp_s, cfg.camera_pos_noise_m, cfg.camera_noise_drift_fraction)
            dr = _pose_error(rng, tp_s, np.radians(cfg.camera_rot_noise_deg), cfg.camera_noise_drift_fraction)
            R_est = Rotation.from_rotvec(dr).as_matrix() @ T_true[:, :3, :3]
        T_est = make_T(R_est, T_true[:, :3, 3] + dp)

        phase = int(rng.uniform(0, period_ns)) if cfg.unsync else 0
        tf = np.arange(t0 + phase, t1 + 1, period_ns, dtype=np.int64)
        if cfg.unsync and cfg.frame_jitter_ms > 0:
            tf = tf + rng.normal(0, cfg.frame_jitter_ms * 1e6, len(tf)).astype(np.int64)
            tf = np.clip(np.sort(tf), t0, t1)

        T_tf = interpolate_poses(t_pose, T_true, tf)
        X = interpolate_joints(t_ns, joints_ned, tf)  # (F, 17, 3)
        F, D = len(tf), cfg.detectors
        kp = np.zeros((F, D, 17, 2))
        conf = np.zeros((F, D, 17))
        for f in range(F):
            uv, z = project_points(K, T_tf[f], X[f])
            lo, hi = uv.min(0), uv.max(0)
            span = np.maximum(hi - lo, 20.0)
            for d in range(D):
                u = uv + rng.normal(0, cfg.noise_px, uv.shape)
                cf = rng.uniform(0.5, 1.0, 17)
                out = rng.random(17) < cfg.outlier_rate
                if out.any():
                    u[out] = lo - 0.25 * span + rng.random((out.sum(), 2)) * 1.5 * span
                    cf[out] = rng.uniform(0.2, 0.8, out.sum())
                if rng.random() < cfg.swap_rate:
                    u, cf = u[list(COCO17_FLIP)], cf[list(COCO17_FLIP)]
                miss = rng.random(17) < cfg.miss_rate
                inside = (z > 0.1) & (u[:, 0] >= 0) & (u[:, 0] < cfg.width_px) & (u[:, 1] >= 0) & (u[:, 1] < cfg.height_px)
                cf[miss | ~inside] = 0.0
                kp[f, d] = u
                conf[f, d] = cf
        rates = _imu_rates(rng_rates, tp_s, T_true, cfg) if cfg.imu_rates else {}
        cams.append(
            CameraCapture(
                **rates,
                name=f"drone_{c}", t_pose_ns=t_pose, T_world_cam=T_est,
                pos_sigma_m=max(pos_sigma, 1e-3), rot_sigma_deg=max(rot_sigma, 1e-2),
                t_intrinsics_ns=np.array([t0]), K=K[None], width_px=cfg.width_px, height_px=cfg.height_px,
                t_frame_ns=tf, keypoints_px=kp, confidence=conf,
                detectors=tuple(f"synthetic_{d}" for d in range(D)),
            )  # fmt: skip
        )
        T_true_all.append(T_true)
        T_true_frames.append(T_tf)
    cap = Capture(cams, meta={"source": "synthetic", "synth": dataclasses.asdict(cfg), "seed": seed})
    return cap, SynthTruth(t_ns, joints_ned, T_true_all, T_true_frames)


def procedural_walker(num_frames: int = 40, fps: float = 30.0, shape: np.ndarray | None = None, speed_mps: float = 1.2):
    """A rigid COCO-17 skeleton walking north with swinging legs and a bent elbow (no mocap needed).

    Returns (joints_ned (T, 17, 3), t_ns (T,), shape (16,), pose (T, 11, 3) axis-angle, root_orient (T, 3),
    transl (T, 3)) -- the exact parameters of :mod:`reconstruction.body.skeleton17` that produce it.
    """
    import torch

    from reconstruction.body import skeleton17 as sk

    shape = sk.DEFAULT_SHAPE.copy() if shape is None else np.asarray(shape, dtype=float)
    t = np.arange(num_frames) / fps
    pose = np.zeros((num_frames, sk.NUM_POSE, 3))
    pose[:, 0, 0] = 0.5 * np.sin(2 * t)  # l_hip
    pose[:, 2, 0] = -0.5 * np.sin(2 * t)  # r_hip
    pose[:, 1, 0] = 0.4 + 0.3 * np.sin(2 * t)  # l_knee
    pose[:, 3, 0] = 0.4 - 0.3 * np.sin(2 * t)  # r_knee
    pose[:, 6, 2] = -1.3  # l_shoulder: arm down
    pose[:, 8, 2] = 1.3
    pose[:, 7, 1] = 0.8  # l_elbow
    pose[:, 9, 1] = -0.8
    # body (x left, y up, z forward) -> NED facing north: forward = north, left = -east, up = -down
    R_root = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])
    root_orient = np.tile(Rotation.from_matrix(R_root).as_rotvec(), (num_frames, 1))
    transl = np.stack([t * speed_mps, np.zeros_like(t), np.full_like(t, -(shape[1] + shape[2]) - 0.05)], -1)
    R_loc = sk.axis_angle_to_matrix(torch.tensor(pose))
    nodes = sk.forward_kinematics_torch(torch.tensor(R_root).expand(num_frames, 3, 3), R_loc, torch.tensor(transl), torch.tensor(shape))
    joints = nodes.numpy()[:, sk.COCO_TO_NODE]
    return joints, np.round(t * 1e9).astype(np.int64), shape, pose, root_orient, transl
