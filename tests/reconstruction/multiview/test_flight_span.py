"""The flight's output span: only where at least two cameras see the person (take-off and landing left out)."""

import numpy as np
import pytest

from reconstruction.capture import CameraCapture, Capture, CaptureError
from reconstruction.multiview.flight import output_grid, seen_span_ns


def _cam(name: str, seen_from_s: float, seen_to_s: float) -> CameraCapture:
    t = (np.arange(0, 100) * 0.1e9).astype(np.int64)  # 10 Hz for 10 s
    conf = np.zeros((100, 17))
    sel = (t >= seen_from_s * 1e9) & (t <= seen_to_s * 1e9)
    conf[sel] = 0.9
    return CameraCapture(
        name=name, t_pose_ns=t, T_world_cam=np.broadcast_to(np.eye(4), (100, 4, 4)).copy(),
        pos_sigma_m=np.full(100, 0.1), rot_sigma_deg=np.full(100, 1.0), t_intrinsics_ns=t[:1],
        K=np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]]), width_px=640, height_px=360,
        t_frame_ns=t, keypoints_px=np.zeros((100, 17, 2)), confidence=conf,
    )


def test_span_starts_when_the_second_camera_sees_and_ends_when_the_second_last_stops():
    cap = Capture([_cam("a", 1.0, 9.0), _cam("b", 2.0, 8.0), _cam("c", 3.0, 9.5)])
    t0, t1 = seen_span_ns(cap)
    assert t0 == int(2.0e9) and t1 == int(9.0e9)
    grid = output_grid(cap)
    assert grid[0] == t0 and grid[-1] <= t1 and np.allclose(np.diff(grid), 0.1e9)


def test_span_needs_two_cameras_that_see_the_person():
    with pytest.raises(CaptureError, match="only 1 camera"):
        seen_span_ns(Capture([_cam("a", 1.0, 9.0), _cam("b", 20.0, 30.0)]))
