"""Flight folders from the onboard recorder -> :class:`reconstruction.capture.Capture`, and
``skycap reconstruct FLIGHT_DIR`` for the multiview method.

A flight folder holds one MCAP per drone, ``drone_<i>.mcap`` (:mod:`flightdata.recorder`; messages of
:mod:`shared_msgs.messages`, read with :mod:`flightdata.flightlog`). Topics used per drone:

* ``state`` (:class:`VehicleState`): the drone's own pose estimate at ``header.t_measurement_ns``,
  with diagonal position/attitude covariances -> camera pose uncertainty;
* ``camera_info`` (:class:`CameraInfo`): intrinsics (timestamped) and the gimbal angles;
* ``keypoints2d`` (:class:`Keypoints2D`, a real detector) -- or, when a drone has none,
  ``sim/keypoints2d`` (the simulator's noisy projections). One detector per ``detector`` name; the
  person with the highest mean confidence in each message.

Camera pose: ``T_world_cam = T_world_cam_from_pose(position, R_yaw, gimbal_pitch, gimbal_yaw)`` with
the gimbal angles and the mount's lever arm (translation of ``T_body_cam``) of the latest ``camera_info``;
the gimbal is taken to stabilise roll and pitch
(``R_yaw`` = the vehicle's yaw only), as :func:`skycap.frames.T_world_cam_from_pose` documents; pass
``gimbal_stabilised=False`` for a camera fixed to the body.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from reconstruction.capture import CameraCapture, Capture, CaptureError
from skycap.frames import T_world_cam_from_pose, intrinsics_matrix

log = logging.getLogger(__name__)

__all__ = ["read_flight", "read_drone_log", "reconstruct_flight_dir"]


def _yaw_only(R: np.ndarray) -> np.ndarray:
    yaw = np.arctan2(R[1, 0], R[0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def read_drone_log(path: str | Path, gimbal_stabilised: bool = True,
                   position_offset: tuple[np.ndarray, np.ndarray] | None = None) -> CameraCapture:
    """One drone's MCAP -> its :class:`CameraCapture` (see the module docstring).

    position_offset: optional (t_ns (N,), offset_ned_m (N, 3)) subtracted from the reported positions
    (interpolated, held at the ends): the offline smoother's estimate of the drone's GPS offset.
    """
    from flightdata.flightlog import FlightLog
    from shared_msgs.messages import CameraInfo, Keypoints2D, VehicleState

    path = Path(path)
    flog = FlightLog(path)
    states = flog.read_topic("state", VehicleState)
    infos = flog.read_topic("camera_info", CameraInfo)
    kps = flog.read_topic("keypoints2d", Keypoints2D)
    if not kps:
        kps = flog.read_topic("sim/keypoints2d", Keypoints2D)
    name = path.stem
    if not states:
        raise CaptureError(f"{path}: no 'state' messages; the drone's pose is needed for every camera")
    if not infos:
        raise CaptureError(f"{path}: no 'camera_info' messages; the camera intrinsics are needed")
    if not kps:
        raise CaptureError(f"{path}: no 'keypoints2d' or 'sim/keypoints2d' messages; run a 2D detector on the flight first")
    infos = sorted(infos, key=lambda m: m.header.t_measurement_ns)
    t_info = np.array([m.header.t_measurement_ns for m in infos], dtype=np.int64)
    K = np.stack([intrinsics_matrix(m.fx_px, m.fy_px, m.cx_px, m.cy_px) for m in infos])
    states = sorted(states, key=lambda m: m.header.t_measurement_ns)
    t_pose, T_list, ps, rs, vel, vs = [], [], [], [], [], []
    for s in states:
        t = s.header.t_measurement_ns
        if t_pose and t <= t_pose[-1]:
            continue
        i = int(np.clip(np.searchsorted(t_info, t, side="right") - 1, 0, len(infos) - 1))
        w, x, y, z = s.q_world_body
        R = Rotation.from_quat([x, y, z, w]).as_matrix()
        lever = np.asarray(infos[i].T_body_cam, dtype=float).reshape(4, 4)[:3, 3] if len(infos[i].T_body_cam) == 16 else None
        pos = np.array(s.position_ned_m)
        if position_offset is not None:
            pos = pos - np.array([np.interp(t, position_offset[0], position_offset[1][:, k]) for k in range(3)])
        T_list.append(T_world_cam_from_pose(pos, _yaw_only(R) if gimbal_stabilised else R,
                                            infos[i].gimbal_pitch_rad, infos[i].gimbal_yaw_rad, lever))  # fmt: skip
        t_pose.append(t)
        ps.append(float(np.sqrt(np.sum(s.position_cov_m2))))
        rs.append(float(np.degrees(np.sqrt(np.sum(s.attitude_cov_rad2)))))
        # the camera moves with the body (the lever arm's rotational velocity, centimetres per second, is left out)
        vel.append(s.velocity_ned_m_s)
        vs.append(float(np.sqrt(np.sum(s.velocity_cov_m2_s2))))
    detectors = sorted({m.detector for m in kps})
    frames = sorted({m.header.t_measurement_ns for m in kps})
    fidx = {t: i for i, t in enumerate(frames)}
    D, F = len(detectors), len(frames)
    uv = np.zeros((F, D, 17, 2))
    conf = np.zeros((F, D, 17))
    for m in kps:
        if not m.persons:
            continue
        best = max(m.persons, key=lambda p: float(np.mean(p.confidence)))
        f, d = fidx[m.header.t_measurement_ns], detectors.index(m.detector)
        uv[f, d] = np.asarray(best.keypoints_px, dtype=float).reshape(17, 2)
        conf[f, d] = np.asarray(best.confidence, dtype=float)
    vel_a, vs_a = np.asarray(vel, dtype=float), np.asarray(vs, dtype=float)
    if not (np.all(np.isfinite(vel_a)) and np.all(np.isfinite(vs_a)) and np.all(vs_a > 0)):
        log.warning("%s: some 'state' velocities are NaN or have no variance; fitting without this drone's velocities", path)
        vel_a, vs_a = None, None
    return CameraCapture(
        vel_world_mps=vel_a, vel_sigma_mps=vs_a,
        name=name, t_pose_ns=np.array(t_pose), T_world_cam=np.stack(T_list), pos_sigma_m=np.array(ps),
        rot_sigma_deg=np.array(rs), t_intrinsics_ns=t_info, K=K, width_px=infos[-1].width_px,
        height_px=infos[-1].height_px, t_frame_ns=np.array(frames, dtype=np.int64), keypoints_px=uv,
        confidence=conf, detectors=tuple(detectors),
    )  # fmt: skip


def read_flight(flight_dir: str | Path, gimbal_stabilised: bool = True, use_refined_poses: bool = False) -> Capture:
    """All ``drone_*.mcap`` of a flight folder -> a :class:`Capture` (drones without keypoints are skipped with a warning).

    use_refined_poses: subtract the offline smoother's drone position offsets (``refined_track.npz``, written by
    ``skycap refine``) from the reported positions.
    """
    flight_dir = Path(flight_dir)
    files = sorted(flight_dir.glob("drone_*.mcap"))
    if not files:
        raise CaptureError(f"{flight_dir} holds no drone_<i>.mcap files; pass a flight folder written by the onboard recorder")
    offsets = {}
    if use_refined_poses:
        from reconstruction.track.flight import load_refined_offsets

        offsets = load_refined_offsets(flight_dir)
    cams = []
    for f in files:
        try:
            cams.append(read_drone_log(f, gimbal_stabilised, offsets.get(f.stem)))
        except CaptureError as e:
            log.warning("skipping %s: %s", f.name, e)
    if len(cams) < 2:
        raise CaptureError(f"{flight_dir}: multiview reconstruction needs at least 2 drones with keypoints, found {len(cams)}")
    return Capture(cams, meta={"source": "flight", "flight_dir": str(flight_dir)})


def seen_span_ns(capture: Capture, min_cameras: int = 2, min_joints: int = 8, min_conf: float = 0.3) -> tuple[int, int]:
    """The time span in which at least ``min_cameras`` cameras see the person.

    A camera sees the person in a frame when ``min_joints`` keypoints (best detector) reach ``min_conf``. The span
    runs from the time the ``min_cameras``-th camera first sees the person to the time the ``min_cameras``-th last
    camera last sees them: take-off and landing, when the cameras look at the ground or the sky, are left out.
    """
    firsts, lasts = [], []
    for c in capture.cameras:
        if not c.num_frames:
            continue
        seen = (c.confidence.max(axis=1) >= min_conf).sum(axis=-1) >= min_joints
        if seen.any():
            t = c.t_frame_ns[seen]
            firsts.append(int(t[0]))
            lasts.append(int(t[-1]))
    if len(firsts) < min_cameras:
        raise CaptureError(
            f"only {len(firsts)} camera(s) see the person (>= {min_joints} keypoints at confidence >= {min_conf}); "
            f"multiview reconstruction needs {min_cameras}: check the keypoints of the flight or use --method monocular"
        )
    t0 = sorted(firsts)[min_cameras - 1]
    t1 = sorted(lasts)[-min_cameras]
    if t1 <= t0:
        raise CaptureError(f"no time in which {min_cameras} cameras see the person at once")
    return t0, t1


def output_grid(capture: Capture, rate_hz: float | None = None) -> np.ndarray:
    """Output times: the span in which at least two cameras see the person (:func:`seen_span_ns`), at
    ``rate_hz`` (default: the cameras' median frame rate)."""
    t0, t1 = seen_span_ns(capture)
    if rate_hz is None:
        rate_hz = float(np.median([1e9 / np.median(np.diff(c.t_frame_ns)) for c in capture.cameras if c.num_frames > 1]))
    return np.arange(t0, t1 + 1, int(round(1e9 / rate_hz)), dtype=np.int64)


def reconstruct_flight_dir(flight_dir: Path, args: argparse.Namespace) -> int:
    """``skycap reconstruct FLIGHT_DIR --method multiview``: fit, then write BVH/NPZ/CSV/RRD + config beside."""
    from reconstruction.export import export_motion
    from reconstruction.multiview.fit import FitConfig, fit_capture
    from skycap.config import save_config

    cap = read_flight(flight_dir, use_refined_poses=bool(getattr(args, "mv_use_refined_poses", False)))
    grid = output_grid(cap)
    cfg = FitConfig(method=getattr(args, "mv_fit", "product") or "product", device=getattr(args, "mv_device", "cpu") or "cpu")
    out = Path(getattr(args, "mv_out", None) or Path(flight_dir) / "reconstruction")
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    res = fit_capture(cap, grid, cfg)
    cams = []
    for ci, cam in enumerate(cap.cameras):
        sel = res.cam_index == ci
        cams.append({"name": cam.name, "t_ns": res.cam_t_ns[sel], "T_world_cam": res.T_world_cam_refined[sel],
                     "K": cam.K[-1], "width_px": cam.width_px, "height_px": cam.height_px})  # fmt: skip
    paths = export_motion(out, res.joints_ned, res.t_ns, params=res.params(), shape=res.shape, cameras=cams, capture=cap)
    cap.save(out / "capture.npz")
    summary = {"frames": int(len(grid)), "cameras": cap.num_cameras, "fit_seconds": res.fit_seconds,
               "outputs": {k: str(v) for k, v in paths.items()}}  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0
