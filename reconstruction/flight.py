"""Flight folders from the onboard recorder -> :class:`reconstruction.capture.Capture`: the reader every
reconstruction method uses (:func:`read_capture`).

A flight folder (:class:`flightdata.folder.FlightFolder`, the one owner of its layout) holds per drone one MCAP
per sortie (``<drone_id>.s<NNN>.mcap``; :mod:`flightdata.recorder`; messages of :mod:`shared_msgs.messages`,
read with :mod:`flightdata.flightlog`). The reader takes the drones in natural order (``drone_2`` before
``drone_10``) and either the whole flight (every sortie of a drone, chained in sortie order into one camera)
or one chosen sortie, and says which files it used (``Capture.meta["recordings"]``, logged). Topics used per
drone:

* ``state`` (:class:`VehicleState`): the drone's own pose estimate at ``header.t_measurement_ns``,
  with diagonal position/attitude covariances -> camera pose uncertainty;
* ``camera_info`` (:class:`CameraInfo`): intrinsics (timestamped) and the gimbal angles;
* ``gimbal`` (:class:`GimbalAttitude`, when recorded): the gimbal's reported pitch and yaw, interpolated at
  each pose time (yaw unwrapped; held at the ends) -- used instead of ``camera_info``'s angles; a report stamped
  long before it was sent (the gimbal clock's mapping to the wall clock slipped) is timed by its send time
  (:func:`report_times_ns`);
* ``keypoints2d`` (:class:`Keypoints2D`, a real detector) -- or, when a drone has none,
  ``sim/keypoints2d`` (the simulator's noisy projections). One detector per ``detector`` name; the
  person with the highest mean confidence in each message. With a ``plumb_bob`` lens in the
  ``camera_info`` in force at a frame, its keypoints are undistorted to the ideal pinhole pixels of the
  same K (:func:`undistort_keypoints`): the fit's camera model is the pinhole ``K``.

Camera pose: ``T_world_cam = T_world_cam_from_pose(position, R_yaw, gimbal_pitch, gimbal_yaw)`` with
the gimbal angles (the ``gimbal`` reports at the pose time, else the latest ``camera_info``'s) and the mount's
lever arm (translation of ``T_body_cam``) of the latest ``camera_info``;
the gimbal is taken to stabilise roll and pitch
(``R_yaw`` = the vehicle's yaw only), as :func:`skycap.frames.T_world_cam_from_pose` documents; pass
``gimbal_stabilised=False`` for a camera fixed to the body.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from reconstruction.capture import CameraCapture, Capture, CaptureError
from skycap.frames import R_BODY_CAM_FORWARD, intrinsics_matrix, make_T

log = logging.getLogger(__name__)

__all__ = ["read_capture", "read_drone_log", "recordings_summary", "report_times_ns", "READER_VERSION"]

#: bumped when the reader turns the same recordings into a different capture (a cached fit of it is then stale):
#: 2 = the gimbal reports' clock slip is removed (:func:`report_times_ns`)
READER_VERSION = 2


def _yaw_only(R: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) -> the rotations about the down axis by their yaw."""
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros(yaw.shape + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def T_world_cam_from_poses(position_ned_m: np.ndarray, R_world_body: np.ndarray, gimbal_pitch_rad: np.ndarray,
                           gimbal_yaw_rad: np.ndarray, lever_arm_body_m: np.ndarray) -> np.ndarray:
    """:func:`skycap.frames.T_world_cam_from_pose` of N poses at once: positions (N, 3), R_world_body (N, 3, 3),
    gimbal angles (N,), lever arms (N, 3) -> T_world_cam (N, 4, 4) (the same numbers, one scipy call)."""
    R_gimbal = Rotation.from_euler("ZY", np.stack([gimbal_yaw_rad, gimbal_pitch_rad], -1)).as_matrix()
    R_wc = R_world_body @ (R_gimbal @ R_BODY_CAM_FORWARD)
    t = position_ned_m + np.einsum("nij,nj->ni", R_world_body, lever_arm_body_m)
    return make_T(R_wc, t)


def undistort_keypoints(uv_px: np.ndarray, confidence: np.ndarray, t_frame_ns: np.ndarray, infos: Sequence,
                        t_info_ns: np.ndarray) -> np.ndarray:
    """Keypoints (F, ..., 2) of frames at ``t_frame_ns`` (F,) -> the ideal pinhole pixels of the same K: each frame
    through the lens distortion of the ``CameraInfo`` in force then (the latest at or before it, else the first;
    ``infos`` sorted by time ``t_info_ns``). Keypoints with confidence 0 (none detected) are left as they are."""
    from skycap.camera import PinholeCamera

    uv_px = np.array(uv_px, dtype=float)
    which = np.clip(np.searchsorted(t_info_ns, t_frame_ns, side="right") - 1, 0, len(infos) - 1)
    for j in np.unique(which):
        if infos[j].distortion_model == "none":
            continue
        sel = which == j
        ideal = PinholeCamera.from_camera_info(infos[j]).undistort_points(uv_px[sel])
        uv_px[sel] = np.where((np.asarray(confidence)[sel] > 0)[..., None], ideal, uv_px[sel])
    return uv_px


def report_times_ns(t_measurement_ns: np.ndarray, t_sent_ns: np.ndarray, max_delay_s: float = 0.1,
                    window_s: float = 1.0) -> np.ndarray:
    """Measurement times of reports stamped by another clock, made consistent with their send times.

    A report is sent at ``t_sent_ns`` (the sender's wall clock) and describes the moment ``t_measurement_ns``
    (e.g. the gimbal's boot-time stamp mapped to the wall clock by the agent, :class:`onboard.agent.gimbal.BootClock`).
    When that mapping slips -- the stamping clock runs slower than the wall clock, as the simulator's boot clock
    does when it falls behind real time on a loaded machine, by tens of seconds over a flight -- the reports look
    seconds older than they are, and the gimbal angle taken at a frame is the one of seconds later. The send delay
    beyond the smallest one seen (the transport's floor) is the slip plus the publication's own delay; its lower
    envelope over the next ``window_s`` of sends leaves the slip alone (a single late publication does not move
    a stamp). Where that exceeds ``max_delay_s`` it is removed beyond ``max_delay_s``; reports within it keep their
    stamp, as do reports without a send time (``t_sent <= 0``). Shapes (N,) -> (N,) int64."""
    t_m = np.asarray(t_measurement_ns, dtype=np.int64)
    t_s = np.asarray(t_sent_ns, dtype=np.int64)
    ok = t_s > 0
    if not ok.any():
        return t_m.copy()
    idx = np.flatnonzero(ok)
    order = idx[np.argsort(t_s[idx], kind="stable")]
    ts, excess = t_s[order], t_s[order] - t_m[order]
    excess = excess - excess.min()
    hi = np.searchsorted(ts, ts + int(window_s * 1e9), side="right")
    env = np.array([excess[i:h].min() for i, h in enumerate(hi)], dtype=np.int64)
    out = t_m.copy()
    out[order] += np.maximum(env - int(max_delay_s * 1e9), 0)
    return out


def _gimbal_track(msgs, max_delay_s: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t_ns, pitch_rad, unwrapped yaw_rad) of the finite ``gimbal`` reports in time order (their times made
    consistent with their send times, :func:`report_times_ns`); None without any."""
    msgs = [m for m in msgs if np.isfinite(m.pitch_rad) and np.isfinite(m.yaw_rad)]
    if not msgs:
        return None
    t = report_times_ns(np.array([m.header.t_measurement_ns for m in msgs], dtype=np.int64),
                        np.array([m.header.t_sent_ns for m in msgs], dtype=np.int64), max_delay_s)
    slipped = float((t - np.array([m.header.t_measurement_ns for m in msgs])).max()) * 1e-9
    if slipped > 0:
        log.warning("gimbal reports stamped up to %.2f s before they were sent (the gimbal's clock slipped behind "
                    "the wall clock): their times are taken from the send times", slipped)
    rows = sorted(zip(t.tolist(), (m.pitch_rad for m in msgs), (m.yaw_rad for m in msgs)))
    tt, p, y = (np.array(c, dtype=float) for c in zip(*rows))
    return tt, p, np.unwrap(y)


def read_drone_log(paths: str | Path | Sequence[str | Path], gimbal_stabilised: bool = True,
                   position_offset: tuple[np.ndarray, np.ndarray] | None = None, name: str | None = None,
                   keypoints: tuple | None = None) -> CameraCapture:
    """One drone's recording(s) -> its :class:`CameraCapture` (see the module docstring).

    paths: one MCAP file or the drone's sorties in sortie order (read as one log, :class:`SortieLogs`);
    name: the camera's name (default: the drone id the first file names, ``drone_1.s002.mcap`` -> ``drone_1``).
    position_offset: optional (t_ns (N,), offset_ned_m (N, 3)) subtracted from the reported positions
    (interpolated, held at the ends): the offline smoother's estimate of the drone's GPS offset.
    keypoints: ``(t_frame_ns (F,), detectors (D,), keypoints_px (F, D, 17, 2), confidence (F, D, 17))`` computed
    elsewhere (``skycap process`` runs the keypoint models on the recorded images): used instead of the
    ``keypoints2d`` / ``sim/keypoints2d`` topics (undistorted the same way).
    """
    from flightdata.flightlog import SortieLogs
    from shared_msgs.messages import CameraInfo, GimbalAttitude, Keypoints2D, VehicleState

    paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    flog = SortieLogs(paths)
    path = ", ".join(str(p) for p in paths)  # for the messages
    wanted = {"state": VehicleState, "camera_info": CameraInfo}
    if gimbal_stabilised:
        wanted["gimbal"] = GimbalAttitude
    if keypoints is None:
        wanted.update({"keypoints2d": Keypoints2D, "sim/keypoints2d": Keypoints2D})
    got = flog.read_topics(wanted)  # one pass over the files: their chunks also hold the images
    states, infos = got["state"], got["camera_info"]
    gimbal = _gimbal_track(got["gimbal"]) if gimbal_stabilised else None
    kps = None
    if keypoints is None:
        kps = got["keypoints2d"] or got["sim/keypoints2d"]
    name = name or paths[0].name.split(".")[0]
    if not states:
        raise CaptureError(f"{path}: no 'state' messages; the drone's pose is needed for every camera")
    if not infos:
        raise CaptureError(f"{path}: no 'camera_info' messages; the camera intrinsics are needed")
    if keypoints is None and not kps:
        raise CaptureError(f"{path}: no 'keypoints2d' or 'sim/keypoints2d' messages; run the keypoint models on the "
                           "flight's images first (skycap process FLIGHT_DIR)")
    infos = sorted(infos, key=lambda m: m.header.t_measurement_ns)
    t_info = np.array([m.header.t_measurement_ns for m in infos], dtype=np.int64)
    K = np.stack([intrinsics_matrix(m.fx_px, m.fy_px, m.cx_px, m.cy_px) for m in infos])
    states = sorted(states, key=lambda m: m.header.t_measurement_ns)
    kept, last = [], None
    for s in states:  # one pose per time
        if last is None or s.header.t_measurement_ns > last:
            kept.append(s)
            last = s.header.t_measurement_ns
    states = kept
    # all pose samples at once (a per-sample scipy call was a large part of reading a drone's log)
    t_pose = np.array([s.header.t_measurement_ns for s in states], dtype=np.int64)
    which = np.clip(np.searchsorted(t_info, t_pose, side="right") - 1, 0, len(infos) - 1)
    q = np.array([s.q_world_body for s in states], dtype=float)  # (w, x, y, z)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    levers = np.array([np.asarray(m.T_body_cam, dtype=float).reshape(4, 4)[:3, 3] if len(m.T_body_cam) == 16
                       else np.zeros(3) for m in infos])[which]
    pos = np.array([s.position_ned_m for s in states], dtype=float)
    if position_offset is not None:
        pos = pos - np.stack([np.interp(t_pose, position_offset[0], position_offset[1][:, k]) for k in range(3)], -1)
    if gimbal is not None:  # the gimbal's own reports at the pose times
        g_pitch, g_yaw = np.interp(t_pose, gimbal[0], gimbal[1]), np.interp(t_pose, gimbal[0], gimbal[2])
    else:
        g_pitch = np.array([m.gimbal_pitch_rad for m in infos], dtype=float)[which]
        g_yaw = np.array([m.gimbal_yaw_rad for m in infos], dtype=float)[which]
    T_world_cam = T_world_cam_from_poses(pos, _yaw_only(R) if gimbal_stabilised else R, g_pitch, g_yaw, levers)
    ps = np.sqrt(np.array([s.position_cov_m2 for s in states], dtype=float).sum(axis=1))
    rs = np.degrees(np.sqrt(np.array([s.attitude_cov_rad2 for s in states], dtype=float).sum(axis=1)))
    # the camera moves with the body (the lever arm's rotational velocity, centimetres per second, is left out)
    vel = [s.velocity_ned_m_s for s in states]
    vs = np.sqrt(np.array([s.velocity_cov_m2_s2 for s in states], dtype=float).sum(axis=1))
    if keypoints is not None:
        t_kp, detectors, uv, conf = keypoints
        frames, detectors = [int(t) for t in t_kp], list(detectors)
        uv, conf = np.nan_to_num(np.array(uv, dtype=float)), np.array(conf, dtype=float)
    else:
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
    uv = undistort_keypoints(uv, conf, np.array(frames, dtype=np.int64), infos, t_info)  # the fit is pinhole
    vel_a, vs_a = np.asarray(vel, dtype=float), np.asarray(vs, dtype=float)
    if not (np.all(np.isfinite(vel_a)) and np.all(np.isfinite(vs_a)) and np.all(vs_a > 0)):
        log.warning("%s: some 'state' velocities are NaN or have no variance; fitting without this drone's velocities", path)
        vel_a, vs_a = None, None
    return CameraCapture(
        vel_world_mps=vel_a, vel_sigma_mps=vs_a,
        name=name, t_pose_ns=t_pose, T_world_cam=T_world_cam, pos_sigma_m=ps,
        rot_sigma_deg=rs, t_intrinsics_ns=t_info, K=K, width_px=infos[-1].width_px,
        height_px=infos[-1].height_px, t_frame_ns=np.array(frames, dtype=np.int64), keypoints_px=uv,
        confidence=conf, detectors=tuple(detectors),
    )  # fmt: skip


def read_capture(flight, *, sortie: int | None = None, drone_ids: Iterable[str] | None = None,
                 gimbal_stabilised: bool = True, use_refined_poses: bool = False, min_cameras: int = 1,
                 progress=None) -> Capture:
    """The drones of a flight folder -> a :class:`Capture`, one camera per drone in natural order.

    flight: a :class:`FlightFolder` or its path. sortie: None reads the whole flight (every sortie of a drone,
    chained in sortie order), N only sortie N of each drone that flew it. drone_ids: only these drones (default
    all). Drones without keypoints are skipped with a warning; fewer than ``min_cameras`` cameras left is a
    :class:`CaptureError`. ``meta["recordings"]``: per camera the file names read; ``meta["sortie"]``: ``sortie``.
    use_refined_poses: subtract the offline smoother's drone position offsets (``refined_track.npz``, written by
    ``skycap refine``) from the reported positions. progress: ``progress("read", done, total)`` per drone.
    """
    from flightdata.folder import FlightFolder

    flight = flight if isinstance(flight, FlightFolder) else FlightFolder(flight)
    logs = flight.drone_logs(sortie=sortie, drone_ids=drone_ids)
    offsets = {}
    if use_refined_poses:
        from reconstruction.track.flight import load_refined_offsets

        offsets = load_refined_offsets(flight)
    cams, used = [], {}
    for i, (d, sorties) in enumerate(logs.items()):
        try:
            cams.append(read_drone_log([s.path for s in sorties], gimbal_stabilised, offsets.get(d), name=d))
            used[d] = sorties
        except CaptureError as e:
            log.warning("skipping %s: %s", d, e)
        if progress is not None:
            progress("read", i + 1, len(logs))
    if len(cams) < min_cameras:
        raise CaptureError(f"{flight.path}: {len(cams)} drone(s) with keypoints (of {flight.describe_logs(logs)}); this "
                           f"reconstruction needs at least {min_cameras}: run a 2D detector on the flight, choose another "
                           f"--sortie or another method")
    what = "the whole flight" if sortie is None else f"sortie {sortie}"
    log.info("read %s of %s: %s", what, flight.path, flight.describe_logs(used) or "nothing")
    meta = {"source": "flight", "flight_dir": str(flight.path), "sortie": sortie, "recordings": flight.recording_names(used)}
    return Capture(cams, meta=meta)


def recordings_summary(capture: Capture, cameras: Iterable[str] | None = None) -> dict:
    """``{"sortie": N | None, "recordings": {drone: [file names]}}`` of a capture read by :func:`read_capture` (of
    ``cameras`` only, when given), for a reconstruction's summary; {} for captures of other sources."""
    rec = capture.meta.get("recordings")
    if rec is None:
        return {}
    if cameras is not None:
        keep = set(cameras)
        rec = {k: v for k, v in rec.items() if k in keep}
    return {"sortie": capture.meta.get("sortie"), "recordings": rec}
