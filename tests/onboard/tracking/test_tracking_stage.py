"""The agent's tracking stage (pure logic): Detections of three drones -> fused estimate, own-offset
estimate, ROI planned from the estimate; and the tracking summary helpers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tracking_scene import camera_info, detections_message, person_center

from evaluation.flight import lost_time_s
from onboard.tracking.roi import box_in_roi
from onboard.tracking.stage import TrackingStage


def test_stage_fuses_teammates_estimates_own_offset_and_plans_rois():
    rng = np.random.default_rng(3)
    offset = np.array([1.2, -0.8, 0.4])  # drone_0's GPS offset (reported = true + offset)
    stage = TrackingStage("drone_0")
    stage.set_camera_info(camera_info())
    hits, errs = [], []
    rate, dur = 5.0, 40.0
    for i in range(int(dur * rate)):
        for k in range(3):
            t = i / rate + k / (3 * rate)
            # drone_0: GPS grade and biased; the teammates report (and have) RTK-grade poses, which pin the
            # fleet's frame, so drone_0's whole bias is observable
            det, box_true = detections_message(k, t, i, rng, offset if k == 0 else np.zeros(3), pos_var_m2=1.0 if k == 0 else 0.05**2)
            if k == 0:
                shared = stage.on_own_detections(det)
                assert shared.header.sender_id == "drone_0" and shared.boxes == det.boxes
                if t > 5.0:
                    hits.append(box_in_roi(box_true, shared.roi_px))
            else:
                stage.on_teammate_detections(det)
        est = stage.estimate(int(t * 1e9))
        if t > 10.0:
            errs.append(np.linalg.norm(est.position_ned_m - person_center(t)))
    assert np.sqrt(np.mean(np.square(errs))) < 0.3
    assert np.mean(hits) > 0.95
    est = stage.estimate(int(dur * 1e9))
    # the filter's offset converges towards drone_0's true GPS offset
    assert np.linalg.norm(est.offset_ned_m - offset) < 0.5, est.offset_ned_m
    msg = stage.target_message(int(dur * 1e9))
    assert msg.status == "tracking" and msg.num_sources == 3 and msg.header.sender_id == "drone_0"
    assert len(stage.offset_log) == stage.counts["own_frames"]
    assert stage.counts["teammate_measurements"] == 2 * stage.counts["own_frames"]


def test_stage_without_track_plans_full_frame_and_publishes_nothing():
    stage = TrackingStage("drone_0")
    assert stage.target_message(0) is None
    rng = np.random.default_rng(0)
    det, _ = detections_message(0, 0.0, 0, rng)
    # no camera info yet: nothing can be fused, ROI empty
    out = stage.on_own_detections(det)
    assert out.roi_px == (0.0, 0.0, 0.0, 0.0) and not stage.filter.initialised
    stage.set_camera_info(camera_info())
    out = stage.on_own_detections(det)
    assert out.roi_px == (0.0, 0.0, 0.0, 0.0)  # first frame: no track yet -> full-frame search
    assert stage.last_plan.search and stage.filter.initialised


def test_box_in_roi_and_lost_time():
    assert box_in_roi((10, 10, 20, 20), (5, 5, 20, 20))
    assert not box_in_roi((10, 10, 30, 20), (5, 5, 20, 20))
    assert not box_in_roi((10, 10, 20, 20), (0, 0, 0, 0))
    assert lost_time_s(np.arange(0, 10, 0.1), 0.0, 10.0) == pytest.approx(0.0)
    assert lost_time_s(np.array([]), 0.0, 10.0) == pytest.approx(10.0)
    # a 3 s hole: covered 1 s after the last estimate before it
    t = np.concatenate([np.arange(0, 4, 0.1), np.arange(7, 10, 0.1)])
    assert lost_time_s(t, 0.0, 10.0) == pytest.approx(7.0 - 3.9 - 1.0, abs=1e-6)


def test_stage_plans_before_a_real_detector_and_keeps_the_searched_region():
    """With a detector that takes the region (the ONNX one), the plan is made before detection
    (plan_for at the frame's time and pose) and the shared message reports the region actually searched."""
    import msgspec

    rng = np.random.default_rng(4)
    stage = TrackingStage("drone_0")
    assert stage.plan_for(0, np.eye(4)) is None  # no camera info yet
    stage.set_camera_info(camera_info())
    for i in range(40):
        for k in range(3):
            det, _ = detections_message(k, i / 4 + k / 12, i, rng)
            (stage.on_own_detections if k == 0 else stage.on_teammate_detections)(det)
    t = 10.0
    det, box_true = detections_message(0, t, 99, rng)
    plan = stage.plan_for(int(t * 1e9), det.T_world_cam)
    assert plan.mode == "roi" and not plan.search and box_in_roi(box_true, plan.roi_px)
    searched = (plan.roi_px[0] - 3.0, plan.roi_px[1] - 3.0, plan.roi_px[2] + 6.0, plan.roi_px[3] + 6.0)  # clipped/rounded by the detector
    shared = stage.on_own_detections(msgspec.structs.replace(det, roi_px=searched, mode="roi", detector="nanodet"), plan)
    assert shared.roi_px == searched and stage.last_plan is plan


def _own_offset_after_flight(stamp_ground: bool, offset: np.ndarray) -> np.ndarray:
    """drone_0 (GPS grade, reported = true + offset) among RTK teammates: its filter's own-offset estimate after
    40 s; with stamp_ground its detections carry its take-off ground in its reported frame (set_own_ground)."""
    rng = np.random.default_rng(11)
    stage = TrackingStage("drone_0")
    stage.set_camera_info(camera_info())
    if stamp_ground:
        stage.set_own_ground(0.0 + offset[2])  # reported down while standing on the ground (true down 0)
    rate, dur = 5.0, 40.0
    for i in range(int(dur * rate)):
        for k in range(3):
            t = i / rate + k / (3 * rate)
            det, _ = detections_message(k, t, i, rng, offset if k == 0 else np.zeros(3),
                                        pos_var_m2=1.0 if k == 0 else 0.05**2)
            if k == 0:
                shared = stage.on_own_detections(det)
                assert shared.ground_down_m == (offset[2] if stamp_ground else None)
            else:
                stage.on_teammate_detections(det)
    return stage.estimate(int(dur * 1e9)).offset_ned_m


def test_own_take_off_ground_keeps_a_height_error_out_of_the_horizontal_offset():
    """A drone whose estimate is 1 m too high (and right horizontally): over the true ground its feet rays land
    too far out, and its horizontal offset takes the radial error; with its own take-off ground stamped on its
    detections the measurement is person + offset and the horizontal offset stays near zero."""
    offset = np.array([0.0, 0.0, -1.0])
    stamped = _own_offset_after_flight(True, offset)
    legacy = _own_offset_after_flight(False, offset)
    assert np.linalg.norm(stamped[:2]) < 0.12, stamped
    assert np.linalg.norm(legacy[:2]) > np.linalg.norm(stamped[:2]) + 0.15, legacy
    assert np.linalg.norm(stamped - offset) < 0.15, stamped


def test_reported_position_accuracy_becomes_the_own_pose_covariance_and_offset_prior():
    """set_own_position_cov (the agent passes VehicleState.position_cov_m2, the receiver's accuracy): stamped as the
    position block of the own detections' pose covariance when the detector left it empty, and used as the own
    offset's prior (vertical 0.25 m^2 instead of the configured 1 m^2 leaves a smaller posterior variance)."""
    import msgspec

    def first_frame_var(var):
        stage = TrackingStage("drone_0")
        stage.set_camera_info(camera_info())
        if var is not None:
            stage.set_own_position_cov(var)
        det, _ = detections_message(0, 1.0, 0, np.random.default_rng(5))
        det = msgspec.structs.replace(det, T_world_cam_cov=())  # the detector leaves the covariance to the stage
        shared = stage.on_own_detections(det)
        cov = np.reshape(shared.T_world_cam_cov, (6, 6))
        _, P, _ = stage.filter.state
        return np.diag(cov), np.diag(P)[6:9]

    cov_cfg, P_cfg = first_frame_var(None)
    np.testing.assert_allclose(cov_cfg[:3], [1.0, 1.0, 1.0])  # camera_position_sigma_m = 1 m
    cov_rep, P_rep = first_frame_var((1.0, 1.0, 0.25))
    np.testing.assert_allclose(cov_rep[:3], [1.0, 1.0, 0.25])
    np.testing.assert_allclose(cov_rep[3:], cov_cfg[3:])  # attitude: still the configured grade
    assert P_rep[2] < 0.25 < P_cfg[2], (P_rep, P_cfg)
    stage = TrackingStage("drone_0")
    for bad in ((np.nan, 1.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0)):
        with pytest.raises(ValueError):
            stage.set_own_position_cov(bad)
