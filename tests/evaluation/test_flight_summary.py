"""Flight-summary computations on synthetic trajectories (pure numpy)."""

import math

import numpy as np
import pytest

from groundstation.fleet import make_orbit_plan
from evaluation.flight import min_pairwise_distance_m, orbit_errors
from onboard.orbit import slot_state


def _plan():
    p = make_orbit_plan(["drone_1", "drone_2", "drone_3"], (1.0, 2.0, 0.0), radius_m=8.0, altitude_m=6.0,
                        angular_speed_rad_s=0.2, start_in_s=1.0)
    return p


def _track(plan, t, radius_off=0.0, alt_off=0.0, lag_rad=(0.0, 0.0, 0.0)):
    pos = []
    c = np.array(plan.center_ned_m)
    for k, d in enumerate(["drone_1", "drone_2", "drone_3"]):
        rows = []
        for ts in t:
            p, _, _ = slot_state(plan, d, ts)
            th = math.atan2(p[1] - c[1], p[0] - c[0]) - lag_rad[k]
            r = plan.radius_m + radius_off
            rows.append([c[0] + r * math.cos(th), c[1] + r * math.sin(th), -(plan.altitude_m + alt_off)])
        pos.append(rows)
    return np.array(pos)


def test_perfect_track_has_zero_errors_and_offsets_are_measured():
    plan = _plan()
    t = plan.start_time_ns * 1e-9 + np.linspace(2, 40, 300)
    e = orbit_errors(plan, ["drone_1", "drone_2", "drone_3"], t, _track(plan, t))
    for d in e.values():
        assert all(v == pytest.approx(0.0, abs=1e-9) for v in d.values())
    e = orbit_errors(plan, ["drone_1", "drone_2", "drone_3"], t,
                     _track(plan, t, radius_off=0.3, alt_off=-0.2, lag_rad=(0.1, 0.1, 0.2)))
    assert e["drone_1"]["orbit_radius_rmse_m"] == pytest.approx(0.3)
    assert e["drone_1"]["altitude_rmse_m"] == pytest.approx(0.2)
    assert e["drone_3"]["phase_error_deg_rms"] == pytest.approx(math.degrees(0.2))
    # a common lag is not a spacing error; drone_3's extra lag is (relative to the circular mean)
    mean = (0.1 + 0.1 + 0.2) / 3
    assert e["drone_1"]["phase_spacing_error_deg_rms"] == pytest.approx(math.degrees(mean - 0.1), abs=0.05)
    assert e["drone_3"]["phase_spacing_error_deg_rms"] == pytest.approx(math.degrees(0.2 - mean), abs=0.05)


def test_min_pairwise_distance():
    pos = np.zeros((3, 4, 3))
    pos[1, :, 0] = [10, 5, 2.5, 7]
    pos[2, :, 1] = 20
    assert min_pairwise_distance_m(pos) == pytest.approx(2.5)
    assert min_pairwise_distance_m(pos[:1]) == math.inf


def test_yaw_to_center_error():
    from evaluation.flight import yaw_to_center_error_deg_rms

    pos = np.array([[10.0, 0.0, -5.0], [0.0, 10.0, -5.0]])
    assert yaw_to_center_error_deg_rms((0, 0, 0), pos, np.array([math.pi, -math.pi / 2])) == pytest.approx(0.0, abs=1e-9)
    assert yaw_to_center_error_deg_rms((0, 0, 0), pos, np.array([math.pi + 0.1, -math.pi / 2 + 0.1])) == \
        pytest.approx(math.degrees(0.1))


def test_reconstruction_accuracy_against_truth(tmp_path):
    """A reconstruction offset by 10 cm from the truth scores W-MPJPE and root error 100 mm, (root-aligned) MPJPE
    and PA-MPJPE 0; the window selects; the summary says what was scored."""
    import numpy as np

    from evaluation.flight import reconstruction_accuracy
    from flightdata.folder import FlightFolder
    from flightdata.recorder import Recorder
    from shared_msgs import SimTruth

    rng = np.random.default_rng(0)
    t0 = 1_700_000_000_000_000_000
    t_truth = t0 + np.arange(0, 100) * 20_000_000  # 50 Hz for 2 s
    base = rng.normal(size=(17, 3))
    truth = [base + np.array([0.5 * k * 0.02, 0.0, 0.0]) for k in range(len(t_truth))]  # walking north 0.5 m/s
    rec = Recorder(FlightFolder(tmp_path).truth_path, node_id="sim")
    for t, j in zip(t_truth, truth):
        msg = SimTruth(header=SimTruth.make_header("sim", int(t)), vehicles=[],
                       person_joints_ned_m=tuple(j.ravel().tolist()), person_root_ned_m=tuple(j[11].tolist()))
        rec.record_message("truth", msg, int(t))
    rec.close()
    t_rec = t0 + 5_000_000 + np.arange(0, 19) * 100_000_000  # 10 Hz, between truth samples
    walked = 0.5 * (t_rec - t0) * 1e-9
    pred = base[None] + np.stack([walked, 0 * walked, 0 * walked], -1)[:, None] + np.array([0.0, 0.1, 0.0])
    (tmp_path / "reconstruction").mkdir()
    np.savez(tmp_path / "reconstruction" / "motion.npz", t_ns=t_rec, joints_ned=pred)
    acc = reconstruction_accuracy(tmp_path, window_s=((t0 * 1e-9) + 1.0, (t0 * 1e-9) + 1.5),
                                  keypoints_source="sim_noisy_gt", position_grade="rtk")
    assert acc["frames_scored"] == 19
    assert abs(acc["w_mpjpe_mm"] - 100.0) < 0.5 and abs(acc["root_err_mm"] - 100.0) < 0.5
    assert acc["mpjpe_mm"] < 0.5 and acc["pa_mpjpe_mm"] < 0.5
    assert acc["frames_scored_window"] == 5 and abs(acc["w_mpjpe_mm_window"] - 100.0) < 0.5
    assert acc["mpjpe_mm_window"] < 0.5 and abs(acc["per_group_mm_window"]["legs"]["w_mpjpe_mm"] - 100.0) < 0.5
    assert acc["keypoints_source"] == "sim_noisy_gt" and acc["position_grade"] == "rtk"
    assert reconstruction_accuracy(tmp_path)["keypoints_source"] == "unknown"  # no capture.npz beside the motion
    from evaluation.flight import format_accuracy

    text = format_accuracy(acc)
    assert "2D source: sim_noisy_gt; position grade: rtk" in text and "steady orbit" in text
    assert "W-MPJPE  100.0  root  100.0 mm over 5 frames" in text and "legs 0.0" in text
    assert reconstruction_accuracy(tmp_path / "nothing-here") == {}
