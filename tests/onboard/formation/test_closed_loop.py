"""Tracking and formation together (pure logic, no agent): 3 drones fly the formation MPC around a walking
person, detect it in their own cameras (pointed by the plan's yaw and gimbal pitch), share the detections,
fuse them in their cooperative filters and plan around the fused estimate."""

import math

import numpy as np

from onboard.formation.mpc import FormationMPC, MpcConfig, SharedPlan
from onboard.formation.slots import assign_slot_angles
from onboard.tracking.filter import CooperativeFilter
from onboard.tracking.measurement import box_from_person, measurement_from_box
from skycap.camera import PinholeCamera
from onboard.tracking.roi import plan_detection
from skycap.frames import R_world_body_from_euler, T_world_cam_from_pose

CAM = PinholeCamera(fx_px=900.0, fy_px=900.0, cx_px=640.0, cy_px=360.0, width_px=1280, height_px=720)


def person(t):
    return np.array([0.8 * t, 0.3 * t + 1.5 * math.sin(0.15 * t), -0.845])


def test_track_and_follow_walking_person():
    rng = np.random.default_rng(7)
    ids = ["d0", "d1", "d2"]
    n = len(ids)
    p = np.array([[10.0 * math.cos(a), 10.0 * math.sin(a), -6.0] for a in (0.3, 2.0, 4.0)])
    v = np.zeros((n, 3))
    yaw = np.array([math.atan2(-q[1], -q[0]) for q in p])
    pitch = np.full(n, -0.6)
    filters = {i: CooperativeFilter(i) for i in ids}
    mpcs = {i: FormationMPC(i, MpcConfig(max_solve_time_s=1.0)) for i in ids}
    plans = {i: SharedPlan.from_state(i, 0, p[k], v[k], 0.1, 15) for k, i in enumerate(ids)}
    angles = assign_slot_angles(ids, person(0.0), {i: p[k] for k, i in enumerate(ids)})
    dt = 0.1
    seen = np.zeros(n, dtype=int)
    for s in range(200):
        t = s * dt
        t_ns = int(round(t * 1e9))
        # detections at 4 Hz per drone, staggered; shared with everyone
        for k, i in enumerate(ids):
            if int((s + 1 + k) * 0.4) == int((s + k) * 0.4):  # 4 detections per 10 steps, offset per drone
                continue
            T = T_world_cam_from_pose(p[k], R_world_body_from_euler(0.0, 0.0, yaw[k]), gimbal_pitch_rad=pitch[k])
            box, depth = box_from_person(person(t), CAM, T)
            if depth <= 0 or box[0] < 0 or box[2] > CAM.width_px or box[1] < 0 or box[3] > CAM.height_px:
                continue
            seen[k] += 1
            box = box + rng.normal(0, 2.0, 4)
            m = measurement_from_box(box, CAM, T, np.diag([0.25] * 3 + [1e-5] * 3), t_ns=t_ns, source_id=i, edge_var_px2=np.full(4, 4.0))
            for f in filters.values():
                f.add(m)
        res = {}
        for k, i in enumerate(ids):
            est = filters[i].estimate(t_ns)
            if est is None:  # nothing yet: hover
                res[i] = None
                continue
            r = mpcs[i].step(t_ns, p[k], v[k], est.position_ned_m, est.velocity_ned_m_s, angles[i], {j: plans[j] for j in plans if j != i})
            res[i] = r
        for k, i in enumerate(ids):
            r = res[i]
            if r is None:
                continue
            plans[i] = r.plan
            p[k], v[k] = r.setpoint_position_ned_m, r.setpoint_velocity_ned_m_s
            yaw[k], pitch[k] = r.setpoint_yaw_rad, r.plan_gimbal_pitch_rad[1]
        for a in range(n):
            for b in range(a + 1, n):
                assert np.linalg.norm(p[a] - p[b]) >= 3.0 - 0.01
    t = 199 * dt
    truth = person(t)
    for k, i in enumerate(ids):
        est = filters[i].estimate(int(round(t * 1e9)))
        assert np.linalg.norm(est.position_ned_m - truth) < 0.5, i
        assert est.num_sources == 3
        horiz = np.linalg.norm(p[k, :2] - truth[:2])
        assert abs(horiz - 8.0) < 1.0, (i, horiz)
        assert abs(-p[k, 2] - 8.0) < 0.3
        assert mpcs[i].fallback_count == 0
        # the detector's ROI from the estimate contains the person's box
        T = T_world_cam_from_pose(p[k], R_world_body_from_euler(0.0, 0.0, yaw[k]), gimbal_pitch_rad=pitch[k])
        plan = plan_detection(est, CAM, T, int(round(t * 1e9)))
        box, _ = box_from_person(truth, CAM, T)
        x, y, w, h = plan.roi_px
        assert plan.mode == "roi" and x <= box[0] and y <= box[1] and x + w >= box[2] and y + h >= box[3]
    # spread around the person at ~120 degrees
    bearings = sorted(math.atan2(q[1] - truth[1], q[0] - truth[0]) for q in p)
    gaps = np.diff(bearings + [bearings[0] + 2 * math.pi])
    assert np.all(np.abs(gaps - 2 * math.pi / 3) < 0.35), gaps
    assert np.all(seen > 60)
