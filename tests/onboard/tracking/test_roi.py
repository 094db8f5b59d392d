import numpy as np

from onboard.tracking.filter import TrackEstimate
from onboard.tracking.measurement import box_from_person
from onboard.tracking.roi import RoiConfig, plan_detection, roi_from_estimate
from tracking_scene import CAM, PERSON_HALF_H, look_at_pose

CAM_POS = np.array([0.0, 0.0, -8.0])
PERSON = np.array([8.0, 2.0, -PERSON_HALF_H])
T = look_at_pose(CAM_POS, PERSON)


def est(cov_pos_m2: float, t_last_ns: int = 0, position=PERSON):
    P = np.eye(6) * 0.1
    P[:3, :3] = np.eye(3) * cov_pos_m2
    return TrackEstimate(
        t_ns=t_last_ns,
        position_ned_m=np.asarray(position, float),
        velocity_ned_m_s=np.zeros(3),
        covariance=P,
        offset_ned_m=np.zeros(3),
        offset_cov_m2=np.eye(3),
        status="tracking",
        num_sources=3,
        t_last_measurement_ns=t_last_ns,
    )


def contains(roi, box):
    x, y, w, h = roi
    return x <= box[0] and y <= box[1] and x + w >= box[2] and y + h >= box[3]


def test_roi_contains_person_and_grows_with_uncertainty():
    box, _ = box_from_person(PERSON, CAM, T, aspect_w_over_h=0.5)
    small = roi_from_estimate(PERSON, np.eye(3) * 0.01, CAM, T)
    big = roi_from_estimate(PERSON, np.eye(3) * 1.0, CAM, T)
    assert contains(small, box) and contains(big, box)
    assert big[2] * big[3] > 2 * small[2] * small[3]
    # centred on the person's projection (image centre here; vertically the head-feet box centre differs
    # from the centre's projection by a few pixels of perspective)
    assert abs(small[0] + small[2] / 2 - CAM.cx_px) < 1 and abs(small[1] + small[3] / 2 - CAM.cy_px) < 5
    # 1 m position sigma at ~11 m range is ~90 px: 3 sigma each side
    assert big[2] > 2 * 3 * 60


def test_roi_moved_person_still_inside_3_sigma():
    rng = np.random.default_rng(0)
    cov = np.diag([0.5, 0.5, 0.1])
    roi = roi_from_estimate(PERSON, cov, CAM, T, RoiConfig(margin_frac=0.0))
    inside = 0
    for _ in range(200):
        p = PERSON + rng.multivariate_normal(np.zeros(3), cov)
        if contains(roi, box_from_person(p, CAM, T, aspect_w_over_h=0.5)[0]):
            inside += 1
    assert inside >= 180


def test_roi_none_behind_or_outside():
    assert roi_from_estimate(np.array([-8.0, -2.0, -0.8]), np.eye(3) * 0.01, CAM, T) is None
    assert roi_from_estimate(np.array([8.0, 40.0, -0.8]), np.eye(3) * 0.01, CAM, T) is None
    clipped = roi_from_estimate(np.array([8.0, 6.5, -0.8]), np.eye(3) * 0.01, CAM, T)
    assert clipped is not None and clipped[0] + clipped[2] <= CAM.width_px


def test_plan_detection_modes():
    assert plan_detection(None, CAM, T, 0).search
    p = plan_detection(est(0.05), CAM, T, int(0.5e9))
    assert p.mode == "roi" and not p.search and p.roi_px is not None
    assert plan_detection(est(25.0), CAM, T, int(0.5e9)).mode == "tiles"
    stale = plan_detection(est(0.05), CAM, T, int(4e9))
    assert stale.search and stale.mode == "full"
    out = plan_detection(est(0.05, position=[-8.0, 0, -0.8]), CAM, T, 0)
    assert out.mode == "full" and not out.search
