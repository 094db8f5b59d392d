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
    limbs = np.array(COCO17_LIMBS)
    n = len(t_ns) if max_frames is None else min(len(t_ns), max_frames)
    for i in range(n):
        rec.set_time("time", duration=(int(t_ns[i]) - t0) * 1e-9)
        J = joints_ned[i]
        rec.log("world/person/joints", rr.Points3D(J, radii=0.03))
        rec.log("world/person/limbs", rr.LineStrips3D(np.stack([J[limbs[:, 0]], J[limbs[:, 1]]], 1), radii=0.015))
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
        for f in range(len(tc)):
            rec.set_time("time", duration=(int(tc[f]) - t0) * 1e-9)
            rec.log(f"world/cameras/{name}", rr.Transform3D(translation=T[f, :3, 3], mat3x3=T[f, :3, :3]))
    if capture is not None:
        for cam in capture.cameras:
            for f in range(cam.num_frames):
                rec.set_time("time", duration=(int(cam.t_frame_ns[f]) - t0) * 1e-9)
                ok = cam.confidence[f, 0] > 0
                rec.log(f"world/cameras/{cam.name}/keypoints", rr.Points2D(cam.keypoints_px[f, 0][ok], radii=3.0))
    rec.flush()
    return path
