"""skycap.camera.PinholeCamera: the one camera model (intrinsics, distortion, projection through T_world_cam)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from shared_msgs import CameraInfo
from skycap.camera import CameraError, PinholeCamera
from skycap.frames import invert_T, make_T


def test_projection_with_plumb_bob_distortion_matches_opencv():
    dist = (-0.21, 0.05, 0.001, -0.0015, -0.004)
    cam = PinholeCamera(width_px=1280, height_px=720, fx_px=910.0, fy_px=905.0, cx_px=641.0, cy_px=357.0,
                        distortion_model="plumb_bob", distortion=dist)
    rng = np.random.default_rng(0)
    p_world = rng.uniform([-3, -2, 4], [3, 2, 12], size=(50, 3))
    rvec = np.array([0.1, -0.2, 0.05])
    R, _ = cv2.Rodrigues(rvec)
    T_cam_world = make_T(R, np.array([0.3, -0.1, 0.5]))
    uv, depth = cam.project(invert_T(T_cam_world), p_world)
    ref, _ = cv2.projectPoints(p_world, rvec, T_cam_world[:3, 3], cam.K, np.array(dist))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-6)
    assert np.all(depth > 0)


def test_no_distortion_is_the_plain_pinhole_and_fov_builder():
    cam = PinholeCamera.from_fov(960, 540, 90.0)
    assert cam.fx_px == pytest.approx(480.0) and (cam.cx_px, cam.cy_px) == (480.0, 270.0)
    uv, z = cam.project_cam(np.array([[1.0, -0.5, 2.0]]))
    np.testing.assert_allclose(uv, [[480.0 + 240.0, 270.0 - 120.0]])
    assert cam.in_image(uv).all() and not cam.in_image(np.array([[-1.0, 3.0]])).any()


def test_from_camera_info_keeps_intrinsics_and_distortion():
    info = CameraInfo(header=CameraInfo.make_header("drone_1", 1), camera_id="c", width_px=640, height_px=480,
                      fx_px=500.0, fy_px=501.0, cx_px=320.5, cy_px=239.5, distortion_model="plumb_bob",
                      distortion=(0.1, 0.0, 0.0, 0.0, 0.0))
    cam = PinholeCamera.from_camera_info(info)
    assert (cam.width_px, cam.fy_px, cam.distortion_model, cam.distortion[0]) == (640, 501.0, "plumb_bob", 0.1)


def test_parameters_that_describe_no_camera_are_refused():
    with pytest.raises(CameraError, match="must be > 0"):
        PinholeCamera(width_px=0, height_px=480, fx_px=500.0, fy_px=500.0, cx_px=0.0, cy_px=0.0)
    with pytest.raises(CameraError, match="k1, k2, p1, p2, k3"):
        PinholeCamera(width_px=640, height_px=480, fx_px=500.0, fy_px=500.0, cx_px=0.0, cy_px=0.0,
                      distortion_model="plumb_bob", distortion=(0.1,))
    with pytest.raises(TypeError):  # keyword-only: no silent mix-up of (fx, fy, cx, cy, w, h) orders
        PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _distorted_cam() -> PinholeCamera:
    return PinholeCamera(width_px=640, height_px=480, fx_px=520.0, fy_px=515.0, cx_px=322.0, cy_px=236.0,
                         distortion_model="plumb_bob", distortion=(-0.25, 0.08, 0.001, -0.0005, 0.0))


def test_undistort_points_inverts_project_cam_and_matches_opencv():
    cam = _distorted_cam()
    u, v = np.meshgrid(np.linspace(0, 639, 17), np.linspace(0, 479, 13))
    uv = np.stack([u, v], axis=-1)  # (13, 17, 2): any leading shape
    xy = cam.undistort_normalized(uv)
    back, _ = cam.project_cam(np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1))
    np.testing.assert_allclose(back, uv, atol=1e-6)
    ideal = cam.undistort_points(uv)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, np.array(cam.distortion), P=cam.K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    np.testing.assert_allclose(ideal.reshape(-1, 2), ref[:, 0], atol=1e-3)
    # no distortion: the ideal pixels are the pixels
    plain = dataclasses.replace(cam, distortion_model="none", distortion=())
    np.testing.assert_allclose(plain.undistort_points(uv), uv)


def test_to_toml_round_trips_and_refuses_to_overwrite(tmp_path):
    import tomllib

    cam = _distorted_cam()
    out = tmp_path / "camera.toml"
    cam.to_toml(out, calibration={"rms_reprojection_px": np.float64(0.21), "views_used": 14, "source": "x.mp4",
                                  "image_size_px": (640, 480), "note": None})
    assert PinholeCamera.from_toml(out) == cam
    cal = tomllib.loads(out.read_text())["calibration"]
    assert cal["rms_reprojection_px"] == 0.21 and cal["image_size_px"] == [640, 480] and "note" not in cal
    with pytest.raises(CameraError, match="--force"):
        cam.to_toml(out)
    cam.to_toml(out, overwrite=True)
    assert "calibration" not in tomllib.loads(out.read_text())
