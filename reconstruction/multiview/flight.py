"""The multiview method's view of a flight: :func:`read_flight` (at least two drones, via the shared reader
:func:`reconstruction.flight.read_capture`) and the output times (:func:`seen_span_ns`, :func:`output_grid`).
The method itself: :mod:`reconstruction.multiview.run`.
"""

from __future__ import annotations

import logging

import numpy as np

from reconstruction.capture import Capture, CaptureError
from reconstruction.flight import read_capture, read_drone_log  # noqa: F401  (read_drone_log: re-exported)

log = logging.getLogger(__name__)

__all__ = ["read_flight", "read_drone_log", "seen_span_ns", "output_grid"]


def read_flight(flight, gimbal_stabilised: bool = True, use_refined_poses: bool = False, sortie: int | None = None,
                progress=None) -> Capture:
    """The drones of a flight folder (a :class:`flightdata.folder.FlightFolder` or its path) -> a :class:`Capture`
    for the multiview method: :func:`reconstruction.flight.read_capture` with at least two drones with keypoints.
    sortie: None = the whole flight (every sortie of a drone, in order), N = only sortie N."""
    return read_capture(flight, sortie=sortie, gimbal_stabilised=gimbal_stabilised,
                        use_refined_poses=use_refined_poses, min_cameras=2, progress=progress)


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
