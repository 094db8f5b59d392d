"""Camera model (intrinsics, mount, projections checked by hand geometry) and the renderer."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simulator.scene.body import body_ellipsoids
from simulator.scene.camera import PinholeCamera, camera_pose, ellipsoid_boxes, project_person
from simulator.scene.config import CameraConfig, PersonConfig
from simulator.scene.person import PersonSim
from simulator.scene.render import Renderer, encode_jpeg
from skycap.frames import invert_T


def q_wxyz(yaw_rad=0.0, pitch_rad=0.0, roll_rad=0.0):
    x, y, z, w = Rotation.from_euler("ZYX", [yaw_rad, pitch_rad, roll_rad]).as_quat()
    return (w, x, y, z)


def looking_at(cfg: CameraConfig, pos_ned, target_ned):
    """Camera pose of a gimbal camera on a level vehicle at pos, yawed and pitched at target."""
    d = np.asarray(target_ned, float) - np.asarray(pos_ned, float)
    yaw = math.atan2(d[1], d[0])
    pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))  # target below (d[2] > 0): negative pitch
    cfg0 = CameraConfig(**{**cfg.__dict__, "lever_arm_body_m": [0.0, 0.0, 0.0]})
    return camera_pose(cfg0, pos_ned, q_wxyz(yaw), pitch)


def test_intrinsics_from_fov():
    cam = PinholeCamera.from_fov(640, 360, 70.0)
    assert cam.fx_px == pytest.approx(320 / math.tan(math.radians(35)))
    assert cam.fy_px == cam.fx_px and (cam.cx_px, cam.cy_px) == (320.0, 180.0)
    assert cam.vfov_deg == pytest.approx(2 * math.degrees(math.atan(180 / cam.fx_px)))


def test_projection_matches_hand_geometry():
    cfg = CameraConfig(lever_arm_body_m=[0.0, 0.0, 0.0], pitch_deg=0.0)
    cam = PinholeCamera.from_config(cfg)
    # vehicle 10 m south of the origin at 2 m height, facing north, level gimbal
    T = camera_pose(cfg, [-10.0, 0.0, -2.0], q_wxyz(0.0), 0.0)
    uv, z = cam.project(T, np.array([[0.0, 0.0, -2.0], [0.0, 1.0, -2.0], [0.0, 0.0, -1.0]]))
    f = cam.fx_px
    assert np.allclose(z, 10.0)
    assert np.allclose(uv[0], [320, 180])  # straight ahead -> principal point
    assert np.allclose(uv[1], [320 + f * 0.1, 180])  # 1 m east at 10 m -> right by f/10
    assert np.allclose(uv[2], [320, 180 + f * 0.1])  # 1 m lower -> down by f/10
    # gimbal pitched 30 deg down at 2 m height: the optical axis hits the ground 2/tan(30) m ahead
    T = camera_pose(cfg, [-10.0, 0.0, -2.0], q_wxyz(0.0), math.radians(-30))
    uv, _ = cam.project(T, np.array([[-10.0 + 2.0 / math.tan(math.radians(30)), 0.0, 0.0]]))
    assert np.allclose(uv[0], [320, 180], atol=1e-6)
    # facing east (yaw 90 deg): a point east of the vehicle is straight ahead
    T = camera_pose(cfg, [0.0, 0.0, -2.0], q_wxyz(math.pi / 2), 0.0)
    uv, z = cam.project(T, np.array([[0.0, 5.0, -2.0]]))
    assert np.allclose(uv[0], [320, 180]) and z[0] == pytest.approx(5.0)


def test_gimbal_ignores_roll_and_pitch_fixed_mount_follows_them():
    g = CameraConfig(mount="gimbal", pitch_deg=-20.0, lever_arm_body_m=[0.0, 0.0, 0.0])
    fx = CameraConfig(mount="fixed", pitch_deg=-20.0, lever_arm_body_m=[0.0, 0.0, 0.0])
    q_tilted = q_wxyz(0.3, math.radians(-10), math.radians(15))
    Tg = camera_pose(g, [0, 0, -5], q_tilted, None)
    Tl = camera_pose(g, [0, 0, -5], q_wxyz(0.3), None)
    assert np.allclose(Tg, Tl)  # stabilised
    Tf = camera_pose(fx, [0, 0, -5], q_tilted, None)
    assert not np.allclose(Tf, Tl)
    Tf_level = camera_pose(fx, [0, 0, -5], q_wxyz(0.3), None)
    assert np.allclose(Tf_level, Tl)  # a level vehicle: fixed mount = gimbal at the same pitch
    # the lever arm moves the camera with the body
    T = camera_pose(CameraConfig(lever_arm_body_m=[1.0, 0.0, 0.0]), [0, 0, -5], q_wxyz(math.pi / 2), None)
    assert np.allclose(T[:3, 3], [0.0, 1.0, -5.0])


def test_ellipsoid_boxes_are_tight():
    """The dual-quadric outline box equals the box of densely sampled surface points."""
    person = PersonSim(PersonConfig())
    cfg = CameraConfig(lever_arm_body_m=[0.0, 0.0, 0.0])
    cam = PinholeCamera.from_config(cfg)
    T = camera_pose(cfg, [-6.0, 1.0, -3.0], q_wxyz(-0.1), math.radians(-15))
    T_cw = invert_T(T)
    ell = body_ellipsoids(person.state_at(4.0).joints_ned_m).transformed(T_cw[:3, :3], T_cw[:3, 3])
    boxes, front = ellipsoid_boxes(cam, ell)
    assert front.all()
    rng = np.random.default_rng(0)
    s = rng.normal(size=(20000, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    for e in range(len(ell.centers)):
        pts = np.linalg.solve(ell.M[e], s.T).T + ell.centers[e]  # x = c + M^-1 s on the surface
        uv, _ = cam.project_cam(pts)
        sampled = np.r_[uv.min(0), uv.max(0)]
        assert np.allclose(sampled, boxes[e], atol=0.15), e
        assert np.all(sampled[:2] >= boxes[e][:2] - 1e-6) and np.all(sampled[2:] <= boxes[e][2:] + 1e-6)


def test_gt_projection_visibility_and_box():
    person = PersonSim(PersonConfig())
    cfg = CameraConfig()
    cam = PinholeCamera.from_config(cfg)
    st = person.state_at(1.0)
    T = looking_at(cfg, [st.root_ned_m[0] - 8, st.root_ned_m[1], -4], st.root_ned_m)
    gt = project_person(cam, T, st.joints_ned_m)
    assert gt.visible.all() and not gt.truncated
    uv_root, _ = cam.project(T, st.root_ned_m[None])
    assert np.allclose(uv_root[0], [320, 180], atol=1e-6)  # looked at
    b = gt.box_px
    assert np.all(gt.uv_px[:, 0] > b[0]) and np.all(gt.uv_px[:, 0] < b[2])
    assert np.all(gt.uv_px[:, 1] > b[1]) and np.all(gt.uv_px[:, 1] < b[3])
    # about 1.8 m of body at about 9 m: height ~ f * 1.8 / 9 (perspective and pitch make it approximate)
    assert (b[3] - b[1]) == pytest.approx(cam.fy_px * 1.85 / np.linalg.norm(T[:3, 3] - st.root_ned_m), rel=0.25)
    # looking away: nothing visible, no box
    T_away = looking_at(cfg, [st.root_ned_m[0] - 8, st.root_ned_m[1], -4], [st.root_ned_m[0] - 16, st.root_ned_m[1], 0])
    gt = project_person(cam, T_away, st.joints_ned_m)
    assert not gt.visible.any() and not gt.in_front.any() and gt.box_px is None


def test_self_occlusion_depends_on_the_view():
    person = PersonSim(PersonConfig())
    cfg = CameraConfig()
    cam = PinholeCamera.from_config(cfg)
    st = person.state_at(1.0)  # standing at the first stop
    h = st.heading_rad

    def occluded_from(angle_rad):
        pos = st.root_ned_m + 6.0 * np.array([math.cos(h + angle_rad), math.sin(h + angle_rad), 0.0])
        pos[2] = -1.5
        return set(np.nonzero(project_person(cam, looking_at(cfg, pos, st.root_ned_m), st.joints_ned_m).occluded)[0])

    front, back, left = occluded_from(0.0), occluded_from(math.pi), occluded_from(-math.pi / 2)
    assert not {0, 1, 2} & front and {0, 1, 2} <= back  # the face is hidden from behind only
    assert not {5, 7, 11, 13} & front and not {5, 7, 11, 13} & back
    assert {6, 12} <= left and not {5, 11} & left  # seen from the left, the right shoulder and hip hide


@pytest.fixture(scope="module")
def scene():
    person = PersonSim(PersonConfig())
    cfg = CameraConfig(width_px=320, height_px=180)
    cam = PinholeCamera.from_config(cfg)
    st = person.state_at(5.0)
    T = looking_at(cfg, [st.root_ned_m[0] - 5, st.root_ned_m[1] + 2, -3], st.root_ned_m)
    return cam, cfg, st, T


def test_renderer_draws_the_person_where_the_gt_box_says(scene):
    cam, cfg, st, T = scene
    r = Renderer(cam, cfg, shadows=False)
    with_p = r.render(T, st.joints_ned_m)
    without = r.render(T, None)
    assert with_p.image.shape == (180, 320, 3) and with_p.image.dtype == np.uint8
    diff = np.abs(with_p.image.astype(int) - without.image.astype(int)).max(axis=2) > 12
    ys, xs = np.nonzero(diff)
    b = with_p.gt.box_px
    assert len(xs) > 0.25 * (b[2] - b[0]) * (b[3] - b[1])  # a body, not a few pixels
    # every changed pixel lies in the GT box, and the changed pixels span the box
    assert xs.min() >= math.floor(b[0]) - 1 and xs.max() <= math.ceil(b[2])
    assert ys.min() >= math.floor(b[1]) - 1 and ys.max() <= math.ceil(b[3])
    assert xs.min() <= b[0] + 2 and xs.max() >= b[2] - 3 and ys.min() <= b[1] + 2 and ys.max() >= b[3] - 3
    # shirt (red in BGR) appears only inside the box, and does appear
    img = with_p.image.astype(int)
    red = (img[..., 2] > img[..., 1] + 60) & (img[..., 2] > img[..., 0] + 60)
    ry, rx = np.nonzero(red)
    assert len(rx) > 10 and rx.min() >= b[0] - 1 and rx.max() <= b[2] + 1 and ry.min() >= b[1] - 1


def test_shadow_darkens_ground_only(scene):
    cam, cfg, st, T = scene
    img_s = Renderer(cam, cfg, shadows=True).render(T, st.joints_ned_m).image.astype(int)
    img_n = Renderer(cam, cfg, shadows=False).render(T, st.joints_ned_m).image.astype(int)
    d = img_s - img_n
    assert (d <= 1).all()  # a shadow only darkens
    assert (d.sum(axis=2) < -30).sum() > 20  # and there is one


def test_ground_and_sky_with_level_camera():
    cfg = CameraConfig(width_px=320, height_px=180, pitch_deg=0.0, lever_arm_body_m=[0.0, 0.0, 0.0])
    cam = PinholeCamera.from_config(cfg)
    T = camera_pose(cfg, [0.0, 0.0, -2.0], q_wxyz(0.4), 0.0)
    img = Renderer(cam, cfg).render(T, None).image.astype(int)
    top, bottom = img[:60], img[130:]
    assert (top[..., 0] > top[..., 1]).mean() > 0.95  # sky: blue above the horizon (BGR)
    assert (bottom[..., 1] > bottom[..., 0]).mean() > 0.95  # grass: green below
    # texture detail near the camera (not a flat colour)
    assert bottom[..., 1].std() > 5
    # a landed drone (camera at ground level or a little under it) still sees ground below the horizon
    for down in (0.0, 0.05):
        img = Renderer(cam, cfg).render(camera_pose(cfg, [0.0, 0.0, down], q_wxyz(0.4), 0.0), None).image.astype(int)
        assert (img[100:][..., 1] > img[100:][..., 0]).mean() > 0.95


def test_jpeg_round_trip(scene):
    cam, cfg, st, T = scene
    img = Renderer(cam, cfg).render(T, st.joints_ned_m).image
    data = encode_jpeg(img, 85)
    assert data[:2] == b"\xff\xd8"
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert back.shape == img.shape and np.abs(back.astype(int) - img.astype(int)).mean() < 6


@pytest.mark.parametrize("size", [(320, 180), (640, 360)])
def test_renders_at_sizes_close_and_far(size):
    person = PersonSim(PersonConfig())
    cfg = CameraConfig(width_px=size[0], height_px=size[1])
    cam = PinholeCamera.from_config(cfg)
    r = Renderer(cam, cfg)
    st = person.state_at(2.5)
    for dist in (1.5, 6.0, 40.0):
        T = looking_at(cfg, [st.root_ned_m[0] - dist, st.root_ned_m[1], -2.0], st.root_ned_m)
        f = r.render(T, st.joints_ned_m)
        assert f.image.shape == (size[1], size[0], 3)
        assert f.gt.box_px is not None
