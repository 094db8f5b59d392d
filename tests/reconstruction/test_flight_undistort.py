"""reconstruction.flight: keypoints seen through a plumb_bob lens are undistorted (per frame, with the CameraInfo
in force then) before they reach the pinhole fit."""

from __future__ import annotations

import numpy as np
import pytest

from shared_msgs import CameraInfo
from skycap.camera import PinholeCamera

DIST = (-0.25, 0.08, 0.001, -0.0005, 0.0)


def _info(t_ns: int, model: str, dist: tuple) -> CameraInfo:
    return CameraInfo(header=CameraInfo.make_header("drone_1", t_ns), camera_id="cam0", width_px=640, height_px=480,
                      fx_px=520.0, fy_px=515.0, cx_px=322.0, cy_px=236.0, distortion_model=model, distortion=dist)


def _points(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform([-2.0, -1.5, 4.0], [2.0, 1.5, 8.0], size=(n, 3))


def test_undistort_keypoints_uses_the_camera_info_in_force_per_frame():
    from reconstruction.flight import undistort_keypoints

    infos = [_info(100, "plumb_bob", DIST), _info(300, "none", ())]
    t_info = np.array([100, 300])
    lens, pinhole = PinholeCamera.from_camera_info(infos[0]), PinholeCamera.from_camera_info(infos[1])
    p = _points(3 * 17).reshape(3, 1, 17, 3)  # frames x detectors x joints
    seen, _ = lens.project_cam(p)
    ideal, _ = pinhole.project_cam(p)
    conf = np.full((3, 1, 17), 0.9)
    conf[1, 0, 5] = 0.0  # not detected: left alone
    t_frame = np.array([50, 200, 300])  # before the first info (its lens), under it, under the second (no lens)
    out = undistort_keypoints(seen, conf, t_frame, infos, t_info)
    np.testing.assert_allclose(out[:2][conf[:2] > 0], ideal[:2][conf[:2] > 0], atol=1e-6)
    np.testing.assert_array_equal(out[1, 0, 5], seen[1, 0, 5])
    np.testing.assert_array_equal(out[2], seen[2])  # "none": the pixels are the pinhole's already


def test_read_drone_log_undistorts_plumb_bob_keypoints(tmp_path):
    pytest.importorskip("mcap")
    from flightdata.recorder import Recorder
    from reconstruction.flight import read_drone_log
    from shared_msgs.messages import Header, Keypoints2D, PersonKeypoints, VehicleState

    lens = PinholeCamera.from_camera_info(_info(0, "plumb_bob", DIST))
    p = _points(2 * 17).reshape(2, 17, 3)
    seen, _ = lens.project_cam(p)
    hdr = lambda t: Header(schema_version=1, sender_id="drone_1", t_measurement_ns=int(t), t_sent_ns=int(t))  # noqa: E731
    with Recorder.new_sortie(tmp_path, "drone_1") as rec:
        rec.record_message("camera_info", _info(1_000, "plumb_bob", DIST))
        for t in (1_000, 20_000_000, 40_000_000):
            rec.record_message("state", VehicleState(header=hdr(t), position_ned_m=(0.0, 0.0, -5.0),
                                                     velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0),
                                                     position_cov_m2=(0.01, 0.01, 0.01)))
        for k, t in enumerate((10_000_000, 30_000_000)):
            pk = PersonKeypoints(keypoints_px=tuple(map(float, seen[k].reshape(-1))), confidence=tuple([0.9] * 17))
            rec.record_message("sim/keypoints2d", Keypoints2D(header=hdr(t), camera_id="cam0", frame_index=k,
                                                              detector="sim", simulated=True, persons=[pk]))
    cap = read_drone_log(sorted(tmp_path.glob("drone_1*.mcap")))
    ideal = p[..., :2] / p[..., 2:] * [520.0, 515.0] + [322.0, 236.0]
    np.testing.assert_allclose(cap.keypoints_px[:, 0], ideal, atol=1e-6)
    assert np.abs(seen - ideal).max() > 5  # the lens moved them by pixels
