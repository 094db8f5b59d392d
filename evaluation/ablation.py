"""Error ablation of a simulated flight's multiview reconstruction: which cause carries how much of the error.

A diagnostic, not a product path: the same recorded flight is refitted with parts of its input replaced by the
simulator's truth (``truth.mcap``), and every variant is scored against the true joints:

========  ===========================================================================================
row       camera poses / 2D keypoints given to the fit
========  ===========================================================================================
recorded  as recorded (the drones' own estimate; what ``skycap process --keypoints sim`` fits)
true_pos  true camera positions, recorded attitude
true_att  true camera attitude, recorded positions
true_pose true camera poses (position and attitude)
exact_2d  true camera poses and the exact projections of the true joints (no 2D noise)
========  ===========================================================================================

plus the input errors themselves (:func:`pose_errors`: RMS camera position error, camera attitude error as
yaw / pitch / roll in the camera's own frame, and the time lag of the recorded poses behind the truth).

    from evaluation.ablation import run_ablation, format_ablation
    table = run_ablation("flights/demo")            # keypoints: the recorded sim/keypoints2d
    print(format_ablation(table))

or ``python -m evaluation.ablation FLIGHT_DIR`` (``bench/ablation.py`` prints the same table).

The substitutions (:func:`substitute_poses`, :func:`exact_keypoints`) and the error figures (:func:`pose_errors`,
:func:`estimate_time_lag_s`) are plain functions on :class:`reconstruction.capture.CameraCapture` and arrays.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from evaluation.flight import joints_at
from flightdata.flightlog import FlightLog
from flightdata.folder import FlightFolder
from reconstruction.capture import CameraCapture, Capture, interpolate_poses
from reconstruction.metrics import accuracy_metrics, root_positions
from reconstruction.multiview.fit import FitConfig, fit_capture
from reconstruction.multiview.flight import output_grid
from shared_msgs import SimTruth
from skycap.errors import SkycapError
from skycap.frames import R_BODY_CAM_FORWARD, T_world_cam_mount
from skycap.skeleton import SCORED_JOINTS

log = logging.getLogger(__name__)

__all__ = ["AblationError", "TruthTracks", "read_truth", "true_camera_track", "substitute_poses", "exact_keypoints",
           "pose_errors", "estimate_time_lag_s", "joint_offsets_body_frame", "pan_tilt_roll", "camera_rotation", "ROWS", "ablation_captures", "score", "run_ablation",
           "format_ablation"]

#: the ablation's rows in order: name -> (true positions, attitude, exact 2D); attitude: "recorded", "true", "tilt"
#: (the true camera tilt -- the gimbal pitch -- with the recorded pan), "pan" (the true pan -- the vehicle's yaw plus
#: the gimbal yaw -- with the recorded tilt)
ROWS: dict[str, tuple[bool, str, bool]] = {
    "recorded": (False, "recorded", False),
    "true_pos": (True, "recorded", False),
    "true_att": (False, "true", False),
    "true_tilt": (False, "tilt", False),
    "true_pan": (False, "pan", False),
    "true_pose": (True, "true", False),
    "exact_2d": (True, "true", True),
}


class AblationError(SkycapError):
    """A flight the ablation cannot score (no simulator truth of its drones or its person)."""


@dataclasses.dataclass
class TruthTracks:
    """The simulator truth of a flight, time-ordered: ``t_ns`` (T,); per drone (``drone_ids``, D)
    ``pos_ned_m`` (D, T, 3), ``vel_ned_m_s`` (D, T, 3), ``q_world_body`` (D, T, 4) (w, x, y, z),
    ``gimbal_pitch_rad`` / ``gimbal_yaw_rad`` (D, T); the person's COCO-17 joints ``joints_ned_m`` (T, 17, 3)."""

    t_ns: np.ndarray
    drone_ids: list[str]
    pos_ned_m: np.ndarray
    vel_ned_m_s: np.ndarray
    q_world_body: np.ndarray
    gimbal_pitch_rad: np.ndarray
    gimbal_yaw_rad: np.ndarray
    joints_ned_m: np.ndarray

    def index(self, drone_id: str) -> int:
        if drone_id not in self.drone_ids:
            raise AblationError(f"the truth has no drone {drone_id!r} (it has {self.drone_ids})")
        return self.drone_ids.index(drone_id)

    def joints_at(self, t_ns: np.ndarray) -> np.ndarray:
        """The true joints (Q, 17, 3) at ``t_ns`` (Q,), linearly interpolated (held at the ends)."""
        return joints_at(self.t_ns, self.joints_ned_m, t_ns)


def read_truth(path: str | Path, drone_ids: list[str]) -> TruthTracks:
    """:class:`TruthTracks` of ``drone_ids`` from a ``truth.mcap`` (the samples that hold every drone and the person)."""
    rows = []
    for m in FlightLog(path).messages():
        msg = m.msg
        if not isinstance(msg, SimTruth) or len(msg.person_joints_ned_m) != 51:
            continue
        by_id = {v.drone_id: v for v in msg.vehicles}
        if all(d in by_id for d in drone_ids):
            rows.append((msg.header.t_measurement_ns, msg, by_id))
    if len(rows) < 2:
        raise AblationError(f"{path}: fewer than two simulator truth samples hold the person and every drone of "
                            f"{drone_ids}: the ablation needs a simulated flight's truth.mcap")
    rows.sort(key=lambda r: r[0])
    t = np.array([r[0] for r in rows], dtype=np.int64)
    keep = np.concatenate([[True], np.diff(t) > 0])
    rows = [r for r, k in zip(rows, keep) if k]

    def per_drone(f):
        return np.array([[f(r[2][d]) for r in rows] for d in drone_ids], dtype=float)

    return TruthTracks(
        t_ns=t[keep], drone_ids=list(drone_ids),
        pos_ned_m=per_drone(lambda v: v.position_ned_m), vel_ned_m_s=per_drone(lambda v: v.velocity_ned_m_s),
        q_world_body=per_drone(lambda v: v.q_world_body), gimbal_pitch_rad=per_drone(lambda v: v.gimbal_pitch_rad),
        gimbal_yaw_rad=per_drone(lambda v: v.gimbal_yaw_rad),
        joints_ned_m=np.array([np.reshape(r[1].person_joints_ned_m, (17, 3)) for r in rows], dtype=float),
    )  # fmt: skip


def true_camera_track(truth: TruthTracks, drone_id: str, lever_arm_body_m=(0.0, 0.0, 0.0),
                      mount: str = "gimbal") -> np.ndarray:
    """The true T_world_cam (T, 4, 4) of ``drone_id``'s camera at ``truth.t_ns``: the simulator's camera model
    (:func:`skycap.frames.T_world_cam_mount`) on the true vehicle pose and gimbal angles."""
    k = truth.index(drone_id)
    return np.stack([T_world_cam_mount(truth.pos_ned_m[k, i], truth.q_world_body[k, i], mount,
                                       truth.gimbal_pitch_rad[k, i], truth.gimbal_yaw_rad[k, i], lever_arm_body_m)
                     for i in range(len(truth.t_ns))])  # fmt: skip


def pan_tilt_roll(R_world_cam: np.ndarray) -> np.ndarray:
    """(..., 3) pan (azimuth of the camera, about world down), tilt (gimbal pitch, negative = down) and roll (about
    the optical axis; 0 for a level gimbal), radians, of camera rotations (..., 3, 3): ``R = Rz(pan) Ry(tilt)
    Rx(roll) R_BODY_CAM_FORWARD`` (the gimbal model of :func:`skycap.frames.R_body_cam` on a yaw-only body)."""
    A = np.asarray(R_world_cam) @ R_BODY_CAM_FORWARD.T
    return Rotation.from_matrix(A.reshape(-1, 3, 3)).as_euler("ZYX").reshape(A.shape[:-2] + (3,))


def camera_rotation(pan_tilt_roll_rad: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pan_tilt_roll`: (..., 3) -> (..., 3, 3)."""
    a = np.asarray(pan_tilt_roll_rad, dtype=float)
    R = Rotation.from_euler("ZYX", a.reshape(-1, 3)).as_matrix() @ R_BODY_CAM_FORWARD
    return R.reshape(a.shape[:-1] + (3, 3))


def substitute_poses(cam: CameraCapture, t_true_ns: np.ndarray, T_true: np.ndarray, *, position: bool,
                     attitude: str | bool, vel_true_mps: np.ndarray | None = None) -> CameraCapture:
    """``cam`` with its pose samples' positions and/or attitudes replaced by the truth ``T_true`` (T, 4, 4) at
    ``t_true_ns`` (T,), interpolated to the pose times; with ``position`` and ``vel_true_mps`` (T, 3) the
    velocities too. attitude: "recorded" (False), "true" (True), "tilt" (the true tilt, the recorded pan and roll)
    or "pan" (the true pan, the recorded tilt and roll), see :func:`pan_tilt_roll`. Sigmas are kept (the fit is
    told what it would be told in flight)."""
    attitude = {False: "recorded", True: "true"}.get(attitude, attitude)
    if attitude not in ("recorded", "true", "tilt", "pan"):
        raise AblationError(f"attitude={attitude!r}: use 'recorded', 'true', 'tilt' or 'pan'")
    if not position and attitude == "recorded":
        return cam
    Tt = interpolate_poses(t_true_ns, T_true, cam.t_pose_ns)
    T = cam.T_world_cam.copy()
    if attitude == "true":
        T[:, :3, :3] = Tt[:, :3, :3]
    elif attitude in ("tilt", "pan"):
        rec, true = pan_tilt_roll(T[:, :3, :3]), pan_tilt_roll(Tt[:, :3, :3])
        k = 1 if attitude == "tilt" else 0
        rec[:, k] = true[:, k]
        T[:, :3, :3] = camera_rotation(rec)
    if position:
        T[:, :3, 3] = Tt[:, :3, 3]
    extra = {}
    if position and vel_true_mps is not None and cam.vel_world_mps is not None:
        tq = (cam.t_pose_ns - t_true_ns[0]).astype(float)
        tt = (np.asarray(t_true_ns) - t_true_ns[0]).astype(float)
        extra["vel_world_mps"] = np.stack([np.interp(tq, tt, vel_true_mps[:, k]) for k in range(3)], -1)
    return dataclasses.replace(cam, T_world_cam=T, **extra)


def exact_keypoints(cam: CameraCapture, t_true_ns: np.ndarray, T_true: np.ndarray, joints_true: np.ndarray,
                    min_confidence: float = 0.0) -> CameraCapture:
    """``cam`` with the exact pinhole projections of the true joints (``joints_true`` (T, 17, 3) at ``t_true_ns``)
    through the true camera (``T_true`` (T, 4, 4)) at each frame time, in every detector; keypoints the
    detector did not report (confidence <= ``min_confidence``) or behind the camera stay missing, the others get
    confidence 1."""
    tf = cam.t_frame_ns
    Tc = interpolate_poses(t_true_ns, T_true, tf)
    tq = (tf - t_true_ns[0]).astype(float)
    tt = (np.asarray(t_true_ns) - t_true_ns[0]).astype(float)
    J = joints_true.reshape(len(tt), -1)
    Jf = np.stack([np.interp(tq, tt, J[:, k]) for k in range(J.shape[1])], -1).reshape(len(tf), 17, 3)
    R, p = Tc[:, :3, :3], Tc[:, :3, 3]
    Xc = np.einsum("fji,fnj->fni", R, Jf - p[:, None])  # world -> camera: R^T (X - p)
    K = cam.K_at(tf)
    z = Xc[..., 2]
    uvw = np.einsum("fij,fnj->fni", K, Xc)
    uv = uvw[..., :2] / np.where(np.abs(z) > 1e-9, z, 1e-9)[..., None]
    ok = (cam.confidence > min_confidence) & (z > 0)[:, None, :]
    kp = np.where(ok[..., None], uv[:, None], cam.keypoints_px)
    return dataclasses.replace(cam, keypoints_px=kp, confidence=np.where(ok, 1.0, 0.0))


def estimate_time_lag_s(t_ns: np.ndarray, pos_rec_m: np.ndarray, t_true_ns: np.ndarray, pos_true_m: np.ndarray,
                        vel_true_mps: np.ndarray) -> tuple[float, np.ndarray]:
    """The time lag of recorded positions behind the truth and their constant offset: least squares of
    ``p_rec(t) = p_true(t - lag) + b ~= p_true(t) - v_true(t) lag + b`` over the samples ``t_ns`` (N,).
    Returns (lag_s, b (3,)); a lag > 0 means the recording says where the drone was ``lag`` seconds earlier."""
    tq = (np.asarray(t_ns) - t_true_ns[0]).astype(float)
    tt = (np.asarray(t_true_ns) - t_true_ns[0]).astype(float)
    p = np.stack([np.interp(tq, tt, pos_true_m[:, k]) for k in range(3)], -1)
    v = np.stack([np.interp(tq, tt, vel_true_mps[:, k]) for k in range(3)], -1)
    d = (np.asarray(pos_rec_m) - p).reshape(-1)  # (3N,)
    N = len(tq)
    A = np.zeros((3 * N, 4))
    A[:, 0] = -v.reshape(-1)
    for k in range(3):
        A[k::3, 1 + k] = 1.0
    x, *_ = np.linalg.lstsq(A, d, rcond=None)
    return float(x[0]), x[1:]


def pose_errors(cam: CameraCapture, t_true_ns: np.ndarray, T_true: np.ndarray, window_ns: tuple[int, int] | None = None,
                pos_true_m: np.ndarray | None = None, vel_true_mps: np.ndarray | None = None) -> dict:
    """The recorded camera poses' errors against the truth at the pose times (within ``window_ns``): RMS and mean of
    the position error (mm, world NED), the attitude error ``R_true^T R_rec`` as camera-frame rotation vector
    (deg: about the camera's x = pitch (tilt), y = pan (yaw), z = roll about the optical axis), RMS and mean;
    with the drone's true positions and velocities (T, 3) also the time lag (:func:`estimate_time_lag_s`)."""
    t = cam.t_pose_ns
    sel = np.ones(len(t), bool) if window_ns is None else (t >= window_ns[0]) & (t <= window_ns[1])
    sel &= (t >= t_true_ns[0]) & (t <= t_true_ns[-1])
    if not sel.any():
        return {}
    Tt = interpolate_poses(t_true_ns, T_true, t[sel])
    Tr = cam.T_world_cam[sel]
    dp = (Tr[:, :3, 3] - Tt[:, :3, 3]) * 1e3
    rv = np.degrees(Rotation.from_matrix(np.einsum("fji,fjk->fik", Tt[:, :3, :3], Tr[:, :3, :3])).as_rotvec())
    out = {"samples": int(sel.sum()),
           "pos_err_rms_mm": round(float(np.sqrt(np.mean(np.sum(dp ** 2, -1)))), 1),
           "pos_err_mean_ned_mm": [round(float(x), 1) for x in dp.mean(0)],
           "att_err_rms_deg": round(float(np.sqrt(np.mean(np.sum(rv ** 2, -1)))), 3),
           "att_err_rms_cam_xyz_deg": [round(float(x), 3) for x in np.sqrt(np.mean(rv ** 2, 0))],
           "att_err_mean_cam_xyz_deg": [round(float(x), 3) for x in rv.mean(0)]}
    d = pan_tilt_roll(Tr[:, :3, :3]) - pan_tilt_roll(Tt[:, :3, :3])
    d = np.degrees((d + np.pi) % (2 * np.pi) - np.pi)
    out["pan_tilt_roll_err_rms_deg"] = [round(float(x), 3) for x in np.sqrt(np.mean(d ** 2, 0))]
    out["pan_tilt_roll_err_mean_deg"] = [round(float(x), 3) for x in d.mean(0)]
    if pos_true_m is not None and vel_true_mps is not None:
        # the recorded camera position minus the lever arm's small rotation is the drone's: compare camera centres
        lag, b = estimate_time_lag_s(t[sel], Tr[:, :3, 3], t_true_ns, T_true[:, :3, 3], vel_true_mps)
        out["time_lag_ms"] = round(lag * 1e3, 1)
        out["offset_ned_mm"] = [round(float(x) * 1e3, 1) for x in b]
    return out


def ablation_captures(capture: Capture, truth: TruthTracks, lever_arm_body_m=(0.0, 0.0, 0.0),
                      rows: dict[str, tuple[bool, str, bool]] | None = None) -> dict[str, Capture]:
    """The capture of each ablation row (see the module doc): ``capture`` (as recorded) with truth substituted."""
    rows = ROWS if rows is None else rows
    tracks = {c.name: true_camera_track(truth, c.name, lever_arm_body_m) for c in capture.cameras}
    out = {}
    for name, (pos, att, exact) in rows.items():
        cams = []
        for c in capture.cameras:
            k = truth.index(c.name)
            cc = substitute_poses(c, truth.t_ns, tracks[c.name], position=pos, attitude=att,
                                  vel_true_mps=truth.vel_ned_m_s[k])
            if exact:
                cc = exact_keypoints(cc, truth.t_ns, tracks[c.name], truth.joints_ned_m)
            cams.append(cc)
        out[name] = Capture(cams, meta=dict(capture.meta, ablation=name))
    return out


def score(t_ns: np.ndarray, joints_ned: np.ndarray, truth: TruthTracks, window_ns: tuple[int, int] | None) -> dict:
    """MPJPE / PA / W-MPJPE / root error (mm) of a reconstruction against the truth, whole and in ``window_ns``."""
    inside = (t_ns >= truth.t_ns[0]) & (t_ns <= truth.t_ns[-1])
    t, pred = t_ns[inside], joints_ned[inside]
    gt = truth.joints_at(t)
    sj = list(SCORED_JOINTS)
    out = accuracy_metrics(pred, gt, sj)
    sel = np.ones(len(t), bool)
    if window_ns is not None:
        sel = (t >= window_ns[0]) & (t <= window_ns[1])
        if sel.any():
            out.update(accuracy_metrics(pred[sel], gt[sel], sj, suffix="_window"))
    if sel.any():  # the root error's constant part (a bias) and what varies around it
        d = (root_positions(pred[sel]) - root_positions(gt[sel])) * 1e3
        out["root_bias_ned_mm_window"] = [round(float(x), 1) for x in d.mean(0)]
        out["root_err_demeaned_rms_mm_window"] = round(float(np.sqrt(np.mean(np.sum((d - d.mean(0)) ** 2, -1)))), 1)
    return {k: v for k, v in out.items() if not k.startswith("per_group")}


def joint_offsets_body_frame(pred: np.ndarray, gt: np.ndarray) -> dict[str, dict]:
    """Per COCO-17 joint, the root-aligned error of ``pred`` against ``gt`` (T, 17, 3) NED metres split into its
    constant part -- the mean signed offset in the person's body frame (forward, left, up; from the true hips and
    the world vertical), mm -- and the RMS of what varies around it (mm): a keypoint convention that puts a joint on
    the body's surface instead of at the skeleton's joint centre shows as an offset, noise as the rest."""
    from skycap.skeleton import COCO17_NAMES

    pred, gt = np.asarray(pred, dtype=float), np.asarray(gt, dtype=float)
    e = (pred - root_positions(pred)[:, None]) - (gt - root_positions(gt)[:, None])  # (T, 17, 3)
    up = np.array([0.0, 0.0, -1.0])
    left = gt[:, 11] - gt[:, 12]
    left[:, 2] = 0.0
    left /= np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-9)
    fwd = np.cross(left, up)
    B = np.stack([fwd, left, np.broadcast_to(up, fwd.shape)], axis=1)  # (T, 3, 3): rows = body axes in NED
    eb = np.einsum("tij,tnj->tni", B, e) * 1e3
    mean = eb.mean(0)
    rest = np.sqrt(np.mean(np.sum((eb - mean) ** 2, -1), 0))
    return {COCO17_NAMES[j]: {"offset_fwd_left_up_mm": [round(float(x), 1) for x in mean[j]],
                              "offset_mm": round(float(np.linalg.norm(mean[j])), 1), "varying_rms_mm": round(float(rest[j]), 1)}
            for j in range(17)}  # fmt: skip


def _lever_arm(flight: FlightFolder, drone_ids: list[str]) -> np.ndarray:
    """The camera's lever arm (body FRD, m) from the first drone's recorded ``camera_info``."""
    from flightdata.flightlog import SortieLogs
    from shared_msgs.messages import CameraInfo

    logs = flight.drone_logs(drone_ids=drone_ids)
    infos = SortieLogs([s.path for s in logs[drone_ids[0]]]).read_topic("camera_info", CameraInfo)
    if infos and len(infos[0].T_body_cam) == 16:
        return np.asarray(infos[0].T_body_cam, dtype=float).reshape(4, 4)[:3, 3]
    return np.zeros(3)


def read_sim_capture(flight: FlightFolder) -> Capture:
    """The flight as ``skycap process --keypoints sim`` fits it: every drone's recorded poses and its recorded
    ``sim/keypoints2d`` (the simulator's noisy true projections), read by the pipeline's own reader."""
    from reconstruction.capture import CaptureError
    from reconstruction.process.pipeline import sim_camera

    cams = []
    for d, sorties in flight.drone_logs().items():
        try:
            cams.append(sim_camera([s.path for s in sorties], d, True, None))
        except CaptureError as e:
            raise AblationError(f"{e} (the ablation needs a simulated flight)") from None
    return Capture(cams, meta={"source": "flight", "flight_dir": str(flight.path), "keypoints_source": "sim"})


def steady_window_ns(flight: FlightFolder) -> tuple[int, int] | None:
    """The steady-orbit window of the flight's ``summary.json`` (``fleet.steady_orbit_window_s``), in ns."""
    p = flight.path / "summary.json"
    if not p.is_file():
        return None
    w = json.loads(p.read_text()).get("fleet", {}).get("steady_orbit_window_s")
    return None if not w else (int(w[0] * 1e9), int(w[1] * 1e9))


def run_ablation(flight_dir, capture: Capture | None = None, fit: FitConfig | None = None,
                 rows: list[str] | None = None, fit_variants: dict[str, FitConfig] | None = None) -> dict:
    """Fit every row (``rows``: names of :data:`ROWS`, default all) of a simulated flight's ablation and score it.

    capture: the recorded capture (default :func:`read_sim_capture`: the simulator's noisy keypoints); fit: the
    multiview fit's config (default the product's). ``fit_variants``: extra rows ``name -> FitConfig`` fitted to the
    recorded capture (e.g. the product with a fix switched on). Returns {"window_ns", "pose_errors" (per camera),
    "rows": {row: metrics + fit_seconds}} (the fit covers the span two cameras see the person, one window)."""
    flight = flight_dir if isinstance(flight_dir, FlightFolder) else FlightFolder(flight_dir)
    capture = read_sim_capture(flight) if capture is None else capture
    names = [c.name for c in capture.cameras]
    truth = read_truth(flight.truth_path, names)
    lever = _lever_arm(flight, names)
    window = steady_window_ns(flight)
    fit = fit or FitConfig()
    grid = output_grid(capture)
    errs = {}
    for c in capture.cameras:
        k = truth.index(c.name)
        T_true = true_camera_track(truth, c.name, lever)
        errs[c.name] = pose_errors(c, truth.t_ns, T_true, window, T_true[:, :3, 3], truth.vel_ned_m_s[k])
    chosen = {k: ROWS[k] for k in (rows or list(ROWS))}
    caps = ablation_captures(capture, truth, lever, chosen)
    jobs = [(name, cap, fit) for name, cap in caps.items()]
    jobs += [(name, capture, cfg) for name, cfg in (fit_variants or {}).items()]
    table = {}
    for name, cap, cfg in jobs:
        t0 = time.perf_counter()
        res = fit_capture(cap, grid, cfg, progress=False)
        m = score(res.t_ns, res.joints_ned, truth, window)
        m["fit_seconds"] = round(time.perf_counter() - t0, 1)
        m["refined_pose_errors"] = _refined_errors(res, cap, truth, lever, window)
        table[name] = m
        log.info("ablation row %s: %s", name, {k: v for k, v in m.items() if k != "refined_pose_errors"})
    return {"flight": str(flight.path), "window_ns": window, "pose_errors": errs, "rows": table}


def _refined_errors(res, capture: Capture, truth: TruthTracks, lever, window) -> dict:
    """The fit's refined camera poses against the truth (RMS over cameras' frames in the window)."""
    out = {}
    for ci, c in enumerate(capture.cameras):
        sel = res.cam_index == ci
        if not sel.any():
            continue
        T_true = true_camera_track(truth, c.name, lever)
        ref = dataclasses.replace(c, t_pose_ns=res.cam_t_ns[sel], T_world_cam=res.T_world_cam_refined[sel],
                                  pos_sigma_m=c.pos_sigma_m[:1].repeat(sel.sum()),
                                  rot_sigma_deg=c.rot_sigma_deg[:1].repeat(sel.sum()), vel_world_mps=None,
                                  vel_sigma_mps=None, omega_cam_radps=None, omega_sigma_radps=None)  # fmt: skip
        e = pose_errors(ref, truth.t_ns, T_true, window)
        out[c.name] = {k: e[k] for k in ("pos_err_rms_mm", "att_err_rms_deg", "pan_tilt_roll_err_rms_deg") if k in e}
    return out


def format_ablation(table: dict) -> str:
    """The ablation as a text table: input pose errors per camera, then one line per row (window figures)."""
    lines = ["camera pose errors (recorded vs truth, steady window):"]
    for cam, e in table["pose_errors"].items():
        lines.append(f"  {cam}: pos RMS {e.get('pos_err_rms_mm')} mm (mean NED {e.get('pos_err_mean_ned_mm')}), "
                     f"att RMS {e.get('att_err_rms_deg')} deg (pan/tilt/roll RMS {e.get('pan_tilt_roll_err_rms_deg')}, mean "
                     f"{e.get('pan_tilt_roll_err_mean_deg')}), lag {e.get('time_lag_ms')} ms")
    sfx = "_window" if any("mpjpe_mm_window" in r for r in table["rows"].values()) else ""
    lines.append(f"{'row':<16s} {'MPJPE':>7s} {'PA':>7s} {'W-MPJPE':>8s} {'root':>7s}  (mm, "
                 f"{'steady window' if sfx else 'whole flight'}; whole-flight MPJPE/W)  refined cam att RMS deg")
    for name, r in table["rows"].items():
        ref = ", ".join(f"{v.get('att_err_rms_deg')}" for v in r.get("refined_pose_errors", {}).values())
        lines.append(f"{name:<16s} {r[f'mpjpe_mm{sfx}']:7.1f} {r[f'pa_mpjpe_mm{sfx}']:7.1f} {r[f'w_mpjpe_mm{sfx}']:8.1f} "
                     f"{r[f'root_err_mm{sfx}']:7.1f}  ({r['mpjpe_mm']:.1f}/{r['w_mpjpe_mm']:.1f}; fit "
                     f"{r['fit_seconds']} s)  [{ref}]  root bias NED {r.get('root_bias_ned_mm_window')}, "
                     f"around it {r.get('root_err_demeaned_rms_mm_window')}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from skycap.config import load_config

    ap = argparse.ArgumentParser(prog="python -m evaluation.ablation", description=__doc__.split("\n\n")[0])
    ap.add_argument("flight", help="a simulated flight folder (truth.mcap, drone recordings with sim/keypoints2d)")
    ap.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated rows of {list(ROWS)}")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="FitConfig overrides")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE[;KEY=VALUE]",
                    help="an extra row: the recorded capture fitted with these FitConfig overrides")
    ap.add_argument("--json", help="also write the table here")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    fit = load_config(FitConfig, None, a.set)
    variants = {}
    for v in a.variant:
        name, _, sets = v.partition(":")
        variants[name] = load_config(FitConfig, None, a.set + [s for s in sets.split(";") if s])
    table = run_ablation(a.flight, fit=fit, rows=[r for r in a.rows.split(",") if r], fit_variants=variants)
    print(format_ablation(table))
    if a.json:
        Path(a.json).write_text(json.dumps(table, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
