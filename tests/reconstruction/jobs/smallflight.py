"""A small recorded flight for the job tests: three hovering drones looking at the procedural walker, written with
the real flight recorder (MCAP) with the simulator's 2D keypoints -- what ``reconstruct_flight`` reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reconstruction.synth import procedural_walker
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose, intrinsics_matrix, project_points


def quick_config():
    """A short multiview fit (these tests are about the jobs; the fit's quality is tested in
    tests/reconstruction/multiview)."""
    from reconstruction.jobs.adapters import ReconstructJobConfig
    from reconstruction.multiview.fit import FitConfig
    from reconstruction.multiview.run import MultiviewConfig

    return ReconstructJobConfig(method="multiview", config=MultiviewConfig(fit=FitConfig(iters=30), rrd=False))


QUICK = quick_config()


def write_small_flight(folder: Path, frames: int = 12) -> Path:
    from flightdata.recorder import Recorder
    from shared_msgs.messages import CameraInfo, Header, Keypoints2D, PersonKeypoints, VehicleState

    folder.mkdir(parents=True, exist_ok=True)
    J, t_ns, *_ = procedural_walker(frames)
    K = intrinsics_matrix(1200.0, 1200.0, 640.0, 360.0)
    centre = J[:, 11:13].mean((0, 1))
    for i in range(3):
        ang = 2 * np.pi * i / 3
        pos = centre + np.array([7 * np.cos(ang), 7 * np.sin(ang), 0.0])
        pos[2] = -6.0
        d = centre - pos
        yaw = np.arctan2(d[1], d[0])
        pitch = -np.arctan2(-d[2], np.hypot(d[0], d[1]))
        Tc = T_world_cam_from_pose(pos, R_world_body_from_euler(0, 0, yaw), pitch, 0.0)
        sender = f"drone_{i + 1}"

        def hdr(t, s=sender):
            return Header(schema_version=1, sender_id=s, t_measurement_ns=int(t), t_sent_ns=int(t))

        with Recorder.new_sortie(folder, sender) as rec:
            rec.record_message("camera_info", CameraInfo(
                header=hdr(t_ns[0]), camera_id="cam0", width_px=1280, height_px=720, fx_px=1200.0, fy_px=1200.0,
                cx_px=640.0, cy_px=360.0, gimbal_pitch_rad=float(pitch)))
            for t in np.arange(t_ns[0], t_ns[-1] + 1, 20_000_000):
                rec.record_message("state", VehicleState(
                    header=hdr(t), position_ned_m=tuple(map(float, pos)), velocity_ned_m_s=(0.0, 0.0, 0.0),
                    q_world_body=(float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))),
                    position_cov_m2=(0.01, 0.01, 0.01)))
            for f, t in enumerate(t_ns):
                uv, _ = project_points(K, Tc, J[f])
                pk = PersonKeypoints(keypoints_px=tuple(map(float, uv.reshape(-1))), confidence=tuple([0.9] * 17))
                rec.record_message("sim/keypoints2d", Keypoints2D(
                    header=hdr(t), camera_id="cam0", frame_index=int(f), detector="sim", simulated=True, persons=[pk]))
    return folder
