import dataclasses
import math

import numpy as np
import pytest

from onboard.tracking.measurement import (
    DegenerateGeometryError,
    MeasurementConfig,
    MeasurementError,
    box_from_person,
    measurement_from_box,
    measurements_from_detections,
)
from shared_msgs.messages import BoundingBox, Detections
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose
from tracking_scene import CAM, PERSON_HALF_H, look_at_pose

POSE_COV = np.diag([0.0] * 6)


def test_height_prior_recovers_position_centred():
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 3.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, depth = box_from_person(person, CAM, T)
    # hand check of the box: person in the image centre column, f H cos(depression) / depth pixels tall
    d = person - cam
    depression = math.atan2(d[2], math.hypot(d[0], d[1]))
    assert abs(depth - np.linalg.norm(d)) < 1e-9
    assert abs(0.5 * (box[0] + box[2]) - CAM.cx_px) < 1e-6
    assert abs((box[3] - box[1]) / (1000.0 * 1.69 * math.cos(depression) / depth) - 1) < 0.01
    m = measurement_from_box(box, CAM, T, POSE_COV, t_ns=5, source_id="d1")
    np.testing.assert_allclose(m.position_ned_m, person, atol=1e-6)
    assert m.t_ns == 5 and m.source_id == "d1" and m.mode == "height_prior"


def test_height_prior_off_centre_and_rolled_camera():
    cam = np.array([2.0, -1.0, -10.0])
    person = np.array([9.0, 4.0, -PERSON_HALF_H])
    # camera yawed 15 deg away from the person and slightly rolled: person off-centre in the image
    d = person - cam
    yaw = math.atan2(d[1], d[0]) + math.radians(15)
    T = T_world_cam_from_pose(cam, R_world_body_from_euler(math.radians(3), 0.0, yaw), gimbal_pitch_rad=-0.8)
    box, _ = box_from_person(person, CAM, T)
    assert abs(0.5 * (box[0] + box[2]) - CAM.cx_px) > 100
    m = measurement_from_box(box, CAM, T, POSE_COV)
    assert np.linalg.norm(m.position_ned_m - person) < 0.15


@pytest.mark.parametrize("mode", ["height_prior", "height_and_ground"])
def test_covariance_elongated_along_ray_and_matches_monte_carlo(mode):
    from onboard.tracking.measurement import MeasurementConfig

    rng = np.random.default_rng(0)
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    var = np.full(4, 9.0)
    cfg = MeasurementConfig(person_height_sigma_m=0.08, ground_sigma_m=0.15)
    m = measurement_from_box(box, CAM, T, POSE_COV, edge_var_px2=var, mode=mode, config=cfg)
    assert np.linalg.norm(m.position_ned_m - person) < 0.02
    w, V = np.linalg.eigh(m.cov_m2)
    ray = (person - cam) / np.linalg.norm(person - cam)
    assert abs(V[:, -1] @ ray) > 0.98, "largest uncertainty must lie along the viewing ray"
    assert w[-1] > 20 * w[1]
    # Monte Carlo over edge noise, the height prior and (height_and_ground) the ground's height
    samples = []
    for _ in range(3000):
        b = box + rng.normal(0, 3.0, 4)
        h = 1.69 + rng.normal(0, 0.08)
        g = rng.normal(0, 0.15) if mode == "height_and_ground" else 0.0
        mm = measurement_from_box(b, CAM, T, POSE_COV, edge_var_px2=var, mode=mode, ground_down_m=-g,
                                  config=dataclasses.replace(cfg, person_height_m=h))
        samples.append(mm.position_ned_m)
    emp = np.cov(np.array(samples).T)
    along_pred, along_emp = ray @ m.cov_m2 @ ray, ray @ emp @ ray
    assert abs(along_emp / along_pred - 1) < 0.2
    perp = np.cross(ray, [0, 0, 1.0])
    perp /= np.linalg.norm(perp)
    assert abs((perp @ emp @ perp) / (perp @ m.cov_m2 @ perp) - 1) < 0.2


def test_camera_pose_covariance_adds_and_is_separated():
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    cov = np.diag([1.0, 1.0, 1.0, 0, 0, 0])
    m = measurement_from_box(box, CAM, T, cov)
    # a camera position error moves the measurement one to one
    np.testing.assert_allclose(m.cov_m2 - m.cov_no_cam_position_m2, np.eye(3), atol=1e-3)


def test_bearing_mode_ground_plane_and_range_hint():
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([6.0, -5.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    m = measurement_from_box(box, CAM, T, POSE_COV, mode="bearing", ground_down_m=0.0)
    # box centre is the centre of the person's projected segment; for this view it is within a few cm
    assert np.linalg.norm(m.position_ned_m - person) < 0.1
    ray = (m.position_ned_m - cam) / np.linalg.norm(m.position_ned_m - cam)
    assert math.sqrt(ray @ m.cov_m2 @ ray) > 100
    rng_hint = float(np.linalg.norm(person - cam))
    m2 = measurement_from_box(box, CAM, T, POSE_COV, mode="bearing", range_hint_m=rng_hint)
    assert abs(np.linalg.norm(m2.position_ned_m - cam) - rng_hint) < 1e-9


def test_nadir_view_is_degenerate_and_detections_fall_back_to_bearing():
    cam = np.array([0.0, 0.0, -15.0])
    person = np.array([0.3, 0.2, -PERSON_HALF_H])
    T = T_world_cam_from_pose(cam, np.eye(3), gimbal_pitch_rad=-math.pi / 2)
    box, _ = box_from_person(person, CAM, T)
    box = np.array([box[0] - 20, min(box[1], box[3]) - 5, box[2] + 20, max(box[1], box[3]) + 5])
    with pytest.raises(DegenerateGeometryError):
        measurement_from_box(box, CAM, T, POSE_COV)
    det = Detections(
        header=Detections.make_header("drone_2", 123),
        camera_id="cam0",
        frame_index=1,
        detector="simulated",
        mode="full",
        boxes=[BoundingBox(x_min_px=box[0], y_min_px=box[1], x_max_px=box[2], y_max_px=box[3], score=0.9)],
        width_px=1920,
        height_px=1080,
        T_world_cam=tuple(T.reshape(-1)),
    )
    ms = measurements_from_detections(det, CAM)
    assert len(ms) == 1 and ms[0].mode == "bearing" and ms[0].source_id == "drone_2" and ms[0].t_ns == 123
    assert np.linalg.norm(ms[0].position_ned_m[:2] - person[:2]) < 0.1


def test_bad_input_raises_clear_errors():
    T = look_at_pose(np.array([0, 0, -8.0]), np.array([8.0, 0, -1]))
    with pytest.raises(MeasurementError, match="finite"):
        measurement_from_box(np.array([1.0, np.nan, 3, 4]), CAM, T)
    with pytest.raises(MeasurementError, match="empty box"):
        measurement_from_box(np.array([10.0, 10, 5, 40]), CAM, T)


def test_crouching_person_stays_on_the_ground_with_the_ground_term():
    """A crouch shrinks the box to 60 % of a standing person's: the height prior alone reads it as a person
    ~1.7x farther away (and below the ground); the feet-on-ground term keeps it where the feet are."""
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    crouch = np.array(box, dtype=float)
    crouch[1] = crouch[3] - 0.6 * (crouch[3] - crouch[1])  # head lowered, feet where they were
    h_only = measurement_from_box(crouch, CAM, T, POSE_COV, mode="height_prior")
    fused = measurement_from_box(crouch, CAM, T, POSE_COV, mode="height_and_ground")
    assert np.linalg.norm(h_only.position_ned_m[:2] - person[:2]) > 3.0
    assert np.linalg.norm(fused.position_ned_m[:2] - person[:2]) < 0.6
    assert fused.position_ned_m[2] < 0.0, "the fused centre stays above the ground"
    # standing: both agree with the truth
    for mode in ("height_prior", "height_and_ground"):
        assert np.linalg.norm(measurement_from_box(box, CAM, T, POSE_COV, mode=mode).position_ned_m - person) < 0.02


def test_ground_term_missing_falls_back_to_height_prior():
    """Camera below the ground plane (a drone at low altitude over a slope): the feet ray cannot meet the
    plane ahead; the fused mode gives the height-prior measurement instead of failing."""
    cam = np.array([0.0, 0.0, -1.0])
    person = np.array([10.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    m = measurement_from_box(box, CAM, T, POSE_COV, mode="height_and_ground", ground_down_m=-3.0)
    h = measurement_from_box(box, CAM, T, POSE_COV, mode="height_prior", ground_down_m=-3.0)
    assert m.mode == "height_prior" and np.allclose(m.position_ned_m, h.position_ned_m)


def test_stride_lead_moves_the_centre_away_from_the_camera_by_the_walk_along_the_ray():
    """The nearest foot (the box bottom) leads a person walking along the view ray: with the person's velocity
    the centre moves away from the camera by stride_lead_s * |v . u| horizontally; walking across the ray, or
    without a velocity, nothing moves (hand geometry: camera due south of the person, u = north)."""
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)
    cfg = MeasurementConfig(stride_lead_s=0.14)
    for mode in ("height_prior", "height_and_ground"):
        base = measurement_from_box(box, CAM, T, POSE_COV, mode=mode, config=cfg).position_ned_m
        for v, shift in (([1.2, 0.0, 0.0], 0.168), ([-1.2, 0.0, 0.0], 0.168), ([0.0, 1.5, 0.0], 0.0), ([0.6, 0.6, 0.3], 0.084)):
            m = measurement_from_box(box, CAM, T, POSE_COV, mode=mode, config=cfg, person_velocity_ned_mps=np.array(v))
            np.testing.assert_allclose(m.position_ned_m - base, [shift, 0.0, 0.0], atol=1e-9)
        nan = measurement_from_box(box, CAM, T, POSE_COV, mode=mode, config=cfg, person_velocity_ned_mps=np.full(3, np.nan))
        np.testing.assert_allclose(nan.position_ned_m, base, atol=1e-12)
    # bearing mode carries no range: no correction; stride_lead_s = 0 turns it off
    b0 = measurement_from_box(box, CAM, T, POSE_COV, mode="bearing", config=cfg).position_ned_m
    b1 = measurement_from_box(box, CAM, T, POSE_COV, mode="bearing", config=cfg, person_velocity_ned_mps=np.array([1.2, 0, 0])).position_ned_m
    np.testing.assert_allclose(b1, b0, atol=1e-12)
    off = MeasurementConfig(stride_lead_s=0.0)
    a = measurement_from_box(box, CAM, T, POSE_COV, mode="height_prior", config=off, person_velocity_ned_mps=np.array([1.2, 0, 0]))
    np.testing.assert_allclose(a.position_ned_m, person, atol=1e-6)


def test_sender_ground_in_its_own_frame_makes_the_measurement_person_plus_offset():
    """A sender whose estimate is off by b (0.44 m too high, and 0.3 m north) reports its camera at c + b. With
    the ground in the true frame (down 0), the feet ray of the shifted camera meets it ~0.44 / tan(depression) too
    far along the ray; with the message's ground_down_m = its reported down on the take-off ground (0 + b_down),
    camera and ground move together and the measurement is exactly person + b (the filter's z = p + b_j)."""
    b = np.array([0.3, 0.0, -0.44])
    cam = np.array([0.0, 0.0, -8.0])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T_true = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T_true)
    T_reported = T_true.copy()
    T_reported[:3, 3] += b

    def det(ground):
        return Detections(
            header=Detections.make_header("drone_3", 7), camera_id="cam0", frame_index=1, detector="simulated",
            mode="full", width_px=1920, height_px=1080, T_world_cam=tuple(T_reported.reshape(-1)),
            T_world_cam_cov=tuple(np.diag([0.1**2] * 3 + [1e-6] * 3).reshape(-1)),
            boxes=[BoundingBox(x_min_px=box[0], y_min_px=box[1], x_max_px=box[2], y_max_px=box[3], score=0.9)],
            ground_down_m=ground)

    own = measurements_from_detections(det(0.0 + b[2]), CAM, mode="height_and_ground", ground_down_m=123.0)[0]
    np.testing.assert_allclose(own.position_ned_m, person + b, atol=1e-6)
    # no ground in the message: the receiver's configured ground (the true one here) -> slides along the ray
    legacy = measurements_from_detections(det(None), CAM, mode="height_and_ground", ground_down_m=0.0)[0]
    along = legacy.position_ned_m[0] - (person + b)[0]
    assert along > 0.3, f"a camera 0.44 m too high over the true ground puts the person {along:.2f} m too far"
    with pytest.raises(MeasurementError, match="ground_down_m"):
        measurements_from_detections(det(float("nan")), CAM)


def test_camera_height_error_the_offset_cannot_explain_stays_in_the_measurement_noise():
    """cov_no_cam_position_m2 leaves the camera position to the filter's offset (z = p + b): exact for the height
    prior, whose point moves with the camera, so its covariance does not depend on the camera position variance.
    The ground point slides along the ray when the camera's height is off (hand check: 1 m of camera
    height slides the feet 8 / 8.845 m): that part stays, and the fused mode leans on the height prior when it is large."""
    cam = np.array([0.0, 0.0, -8.0 - PERSON_HALF_H])
    person = np.array([8.0, 0.0, -PERSON_HALF_H])
    T = look_at_pose(cam, person)
    box, _ = box_from_person(person, CAM, T)

    def cov(var_m2, mode):
        C = np.diag([var_m2] * 3 + [1e-6] * 3)
        return measurement_from_box(box, CAM, T, C, mode=mode, edge_var_px2=np.full(4, 4.0))

    hp_small, hp_big = cov(0.05**2, "height_prior"), cov(1.0, "height_prior")
    np.testing.assert_allclose(hp_small.cov_no_cam_position_m2, hp_big.cov_no_cam_position_m2, atol=1e-9)
    bearing = measurement_from_box(box, CAM, T, np.diag([1.0] * 3 + [1e-6] * 3), mode="bearing",
                                   config=MeasurementConfig(bearing_range_sigma_m=0.0))
    # bearing mode puts the feet on the ground plane: camera 8.845 m over the ground, feet 8 m ahead, so the feet
    # slide 8 / 8.845 m north per metre of camera height
    slide = bearing.cov_no_cam_position_m2[0, 0] - measurement_from_box(
        box, CAM, T, np.diag([0.0] * 3 + [1e-6] * 3), mode="bearing", config=MeasurementConfig(bearing_range_sigma_m=0.0)
    ).cov_no_cam_position_m2[0, 0]
    assert abs(slide - (8.0 / 8.845) ** 2) < 0.02, slide
    f_small, f_big = cov(0.05**2, "height_and_ground"), cov(1.0, "height_and_ground")
    assert f_big.cov_no_cam_position_m2[0, 0] > f_small.cov_no_cam_position_m2[0, 0] + 0.02
    # and the fused point is still the person (both terms agree on exact boxes)
    np.testing.assert_allclose(f_big.position_ned_m, person, atol=0.02)
