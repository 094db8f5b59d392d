"""Rerun recordings (``.rrd``) of a reconstruction: the COCO-17 skeleton over time, camera frusta and
trajectories, and the 2D keypoints each camera saw. Open with ``rerun FILE.rrd``.

World is logged in NED metres (``world`` view coordinates RIGHT_HAND_Z_DOWN); timeline ``time`` in
seconds from the first frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skycap.skeleton import COCO17_LIMBS

__all__ = ["write_rrd"]


def write_rrd(
    path: str | Path,
    joints_ned: np.ndarray,
    t_ns: np.ndarray,
    cameras: list[dict] | None = None,
    capture=None,
    max_frames: int | None = None,
) -> Path:
    """Write a recording. Shapes: joints_ned (T, 17, 3), t_ns (T,).

    ``cameras``: list of dicts ``{"name", "t_ns" (F,), "T_world_cam" (F, 4, 4), "K" (3, 3), "width_px",
    "height_px"}`` (e.g. the refined poses); ``capture``: a :class:`reconstruction.capture.Capture`
    whose detector-0 keypoints are drawn in each camera's image plane.
    """
    import rerun as rr

    path = Path(path)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    t0 = int(t_ns[0]) if len(t_ns) else 0
    rec = rr.RecordingStream("skycap_reconstruction")
    rec.save(str(path))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_DOWN, static=True)
    n = len(t_ns) if max_frames is None else min(len(t_ns), max_frames)
    if n:
        J = np.asarray(joints_ned[:n], dtype=np.float32)
        limbs = np.array(COCO17_LIMBS)
        strips = np.stack([J[:, limbs[:, 0]], J[:, limbs[:, 1]]], 2).reshape(-1, 2, 3)  # (n * limbs, 2, 3)
        time = [_time_column(t_ns[:n], t0)]
        rec.send_columns("world/person/joints", time,
                         [*rr.Points3D.columns(positions=J.reshape(-1, 3)).partition(np.full(n, J.shape[1])),
                          *rr.Points3D.columns(radii=np.full(n, 0.03, np.float32))])
        rec.send_columns("world/person/limbs", time,
                         [*rr.LineStrips3D.columns(strips=list(strips)).partition(np.full(n, len(limbs))),
                          *rr.LineStrips3D.columns(radii=np.full(n, 0.015, np.float32))])
    for cam in cameras or []:
        name = cam["name"]
        tc = np.asarray(cam["t_ns"], dtype=np.int64)
        T = np.asarray(cam["T_world_cam"])
        rec.log(f"world/trajectories/{name}", rr.LineStrips3D([T[:, :3, 3]], radii=0.02), static=True)
        K = np.asarray(cam["K"])
        rec.log(
            f"world/cameras/{name}",
            rr.Pinhole(image_from_camera=K, resolution=[cam["width_px"], cam["height_px"]], image_plane_distance=1.0),
            static=True,
        )
        if len(tc):
            rec.send_columns(f"world/cameras/{name}", [_time_column(tc, t0)],
                             rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]))
    if capture is not None:
        for cam in capture.cameras:
            if not cam.num_frames:
                continue
            kp = np.asarray(cam.keypoints_px[:, 0], dtype=np.float32)  # detector 0: (F, 17, 2)
            ok = np.asarray(cam.confidence[:, 0] > 0)
            rec.send_columns(f"world/cameras/{cam.name}/keypoints", [_time_column(cam.t_frame_ns, t0)],
                             [*rr.Points2D.columns(positions=kp[ok]).partition(ok.sum(axis=1)),
                              *rr.Points2D.columns(radii=np.full(cam.num_frames, 3.0, np.float32))])
    rec.flush()
    return path


def _time_column(t_ns: np.ndarray, t0_ns: int):
    """The ``time`` timeline (a duration from the first frame) at ``t_ns``, exact to the nanosecond."""
    import rerun as rr

    return rr.TimeColumn("time", duration=(np.asarray(t_ns, dtype=np.int64) - t0_ns).astype("timedelta64[ns]"))
