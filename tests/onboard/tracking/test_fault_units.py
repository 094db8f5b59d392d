"""Fault handling without I/O: malformed detections ignored and counted by the tracking stage; the simulated
GPS jump of the vehicle's estimator."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import msgspec
import numpy as np

from tracking_scene import camera_info, detections_message

from onboard.tracking.stage import TrackingStage, box_problem, detection_problem
from shared_msgs.messages import BoundingBox
from simulator.config import SimConfig
from simulator.vehicle.autopilot import SimVehicle


def _box(**kw):
    base = dict(x_min_px=10.0, y_min_px=20.0, x_max_px=30.0, y_max_px=80.0, score=0.9)
    base.update(kw)
    return BoundingBox(**base)


def test_box_and_message_problems_are_named():
    assert box_problem(_box()) is None
    assert "inverted" in box_problem(_box(x_max_px=5.0))
    assert "non-finite" in box_problem(_box(y_min_px=float("nan")))
    assert "variance" in box_problem(_box(var_x_min_px2=-1.0))
    assert "score" in box_problem(_box(score=3.0))
    det, _ = detections_message(1, 1.0, 0, np.random.default_rng(0))
    assert detection_problem(det) is None
    T = np.asarray(det.T_world_cam).reshape(4, 4).copy()
    T[:3, :3] *= 2.0
    assert "rigid" in detection_problem(msgspec.structs.replace(det, T_world_cam=tuple(T.reshape(-1))))
    assert "16" in detection_problem(msgspec.structs.replace(det, T_world_cam=(1.0,) * 9))
    assert "image size" in detection_problem(msgspec.structs.replace(det, width_px=0))
    assert "covariance" in detection_problem(msgspec.structs.replace(det, T_world_cam_cov=(-1.0,) * 36))
    assert "ground_down_m" in detection_problem(msgspec.structs.replace(det, ground_down_m=float("inf")))
    assert detection_problem(msgspec.structs.replace(det, ground_down_m=-0.4)) is None


def test_stage_ignores_and_counts_malformed_detections_and_keeps_tracking():
    rng = np.random.default_rng(5)
    stage, ref = TrackingStage("drone_0"), TrackingStage("drone_0")
    stage.set_camera_info(camera_info())
    ref.set_camera_info(camera_info())
    n_bad = 0
    for i in range(100):
        for k in range(3):
            t = i / 5.0 + k / 15.0
            det, _ = detections_message(k, t, i, rng)
            for st in (stage, ref):
                (st.on_own_detections if k == 0 else st.on_teammate_detections)(det)
            if i % 10 == 3:  # a teammate's garbage: NaN box, inverted box, broken pose, in turn
                bad = [msgspec.structs.replace(det, header=msgspec.structs.replace(det.header, sender_id="drone_1"),
                                               boxes=[_box(x_min_px=float("nan"))]),
                       msgspec.structs.replace(det, header=msgspec.structs.replace(det.header, sender_id="drone_2"),
                                               boxes=[_box(x_max_px=1.0)]),
                       msgspec.structs.replace(det, T_world_cam=(0.0,) * 16)][(i // 10) % 3]
                n_bad += 1
                if k == 0:  # a broken pose drops the message, bad boxes are dropped from it
                    out = stage.on_own_detections(bad)
                    assert out is None if (i // 10) % 3 == 2 else out.boxes == []
                else:
                    stage.on_teammate_detections(bad)
    assert stage.counts["malformed_detections"] == n_bad and stage.last_malformed
    assert stage.filter.stats.rejected_nonfinite == 0  # refused before the filter
    # the garbage changed nothing: same estimate as the stage that never saw it
    e, r = stage.estimate(int(21e9)), ref.estimate(int(21e9))
    np.testing.assert_allclose(e.position_ned_m, r.position_ned_m, atol=1e-9)
    # one bad box among good ones: only that box is dropped
    det, _ = detections_message(1, 21.0, 200, rng)
    mixed = msgspec.structs.replace(det, boxes=[*det.boxes, _box(score=float("inf"))])
    before = stage.counts["teammate_measurements"]
    stage.on_teammate_detections(mixed)
    assert stage.counts["teammate_measurements"] == before + 1 and stage.counts["malformed_boxes"] >= 1


def test_gps_jump_steps_the_estimate_and_the_vehicle_holds_in_the_jumped_frame():
    cfg = SimConfig()
    cfg.estimator.pos_noise_std_m = 0.0
    cfg.estimator.pos_bias_time_constant_s = 0.0  # no drift: the jump alone moves the bias
    v = SimVehicle(0, cfg.validate())

    def ff(seconds):
        for _ in range(int(round(seconds / 0.01))):
            v.step(v.t_s + 0.01, 0.01, np.zeros(3))

    ff(cfg.estimator.gps_lock_delay_s + 0.1)
    assert v.cmd_arm(True) == 0 and v.cmd_takeoff() == 0
    ff(8.0)
    true0 = v.truth.position_ned_m.copy()
    bias0 = v.est_position_ned_m - true0
    v.schedule_gps_jump(v.t_s + 1.0, [3.0, 0.0, 0.0])
    ff(0.9)
    assert not v.gps_jumps_done
    ff(0.2)
    assert len(v.gps_jumps_done) == 1
    bias1 = v.est_position_ned_m - v.truth.position_ned_m
    np.testing.assert_allclose(bias1 - bias0, [3.0, 0.0, 0.0], atol=0.05)
    ff(8.0)  # HOLD keeps the estimated position: the vehicle really moves ~3 m south
    moved = v.truth.position_ned_m - true0
    assert abs(moved[0] + 3.0) < 0.5 and math.hypot(moved[1], moved[2]) < 0.5
    try:
        v.schedule_gps_jump(1.0, [float("nan"), 0, 0])
    except ValueError as e:
        assert "finite" in str(e)
    else:
        raise AssertionError("a NaN jump must be refused")


def test_stage_takes_a_position_step_back_from_its_own_poses():
    rng = np.random.default_rng(2)
    stage, ref = TrackingStage("drone_0"), TrackingStage("drone_0")
    for st in (stage, ref):
        st.set_camera_info(camera_info())
    step = np.array([3.0, -1.0, 0.0])
    stage.set_position_step(step, int(10e9), relax_s=30.0)
    errs = []
    for i in range(150):
        for k in range(3):
            t = i / 5.0 + k / 15.0
            det, _ = detections_message(k, t, i, rng)
            if k == 0:
                jumped = det
                if t >= 10.0:  # the reported pose carries the step (a GPS jump at t = 10 s)
                    T = np.asarray(det.T_world_cam).reshape(4, 4).copy()
                    T[:3, 3] += step
                    jumped = msgspec.structs.replace(det, T_world_cam=tuple(T.reshape(-1)))
                out = stage.on_own_detections(jumped)
                ref.on_own_detections(det)
                # shared with the pose taken back: what the teammates get is consistent with the fleet's frame
                corr = step * math.exp(-(t - 10.0) / 30.0) if t >= 10.0 else np.zeros(3)
                np.testing.assert_allclose(np.asarray(out.T_world_cam).reshape(4, 4)[:3, 3],
                                           np.asarray(jumped.T_world_cam).reshape(4, 4)[:3, 3] - corr, atol=1e-9)
            else:
                stage.on_teammate_detections(det)
                ref.on_teammate_detections(det)
        if i / 5.0 > 12.0:
            e, r = stage.estimate(int(i / 5.0 * 1e9)), ref.estimate(int(i / 5.0 * 1e9))
            errs.append(np.linalg.norm(e.position_ned_m - r.position_ned_m))
            # total own correction = the filter's offset + the step still being taken back ~ the whole step
            np.testing.assert_allclose(stage.own_offset(e, int(i / 5.0 * 1e9)) - ref.own_offset(r, int(i / 5.0 * 1e9)),
                                       step, atol=0.6)
    assert max(errs) < 0.3, max(errs)  # the person estimate is not dragged by the jump
    assert stage.counts["position_steps"] == 1
    o = np.asarray(stage.offset_log)
    assert abs(o[-1, 1] - np.asarray(ref.offset_log)[-1, 1] - 3.0) < 0.6
