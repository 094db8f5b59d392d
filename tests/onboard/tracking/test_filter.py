import dataclasses

import numpy as np
import pytest

from onboard.tracking.filter import CooperativeFilter, TrackerConfig, TrackerError
from shared_msgs.codec import decode, encode  # noqa: F401  (message round trip below)
from tracking_scene import person_center, simulate


def run(filt, meas):
    for m in meas:
        filt.add(m)
    return filt


def vel_true(t):
    h = 1e-3
    return (person_center(t + h) - person_center(t - h)) / (2 * h)


@pytest.fixture(scope="module")
def walk():
    return simulate(20.0, np.random.default_rng(1))


def test_converges_on_walking_target_seen_by_three_cameras(walk):
    f = run(CooperativeFilter("drone_0"), walk)
    t = walk[-1].t_ns
    est = f.estimate(t)
    ts = t * 1e-9
    assert np.linalg.norm(est.position_ned_m - person_center(ts)) < 0.3
    assert np.linalg.norm(est.velocity_ned_m_s - vel_true(ts)) < 0.5
    assert est.status == "tracking" and est.num_sources == 3
    assert f.stats.rejected_gate <= 2 and f.stats.accepted >= len(walk) - 2
    # errors over the last 10 s, and the covariance is consistent with them (not overconfident by > 3x)
    f2 = CooperativeFilter("drone_0")
    errs, sig = [], []
    for m in walk:
        f2.add(m)
        if m.t_ns > 10e9:
            e = f2.estimate(m.t_ns)
            errs.append(e.position_ned_m - person_center(m.t_ns * 1e-9))
            sig.append(np.sqrt(np.diag(e.covariance[:3, :3])))
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    assert np.all(rms < 0.3), rms
    assert np.all(rms < 3 * np.mean(sig, axis=0)), (rms, np.mean(sig, axis=0))
    msg = est.to_message("drone_0")
    assert decode(encode(msg)).position_ned_m == msg.position_ned_m and len(msg.covariance) == 36


def test_out_of_order_and_late_same_as_in_order(walk):
    rng = np.random.default_rng(2)
    # teammates' detections arrive 0-0.6 s late (shuffled order); own arrive on time
    arrival = [m.t_ns + (0 if m.source_id == "drone_0" else int(rng.uniform(0, 0.6e9))) for m in walk]
    late = [walk[i] for i in np.argsort(arrival, kind="stable")]
    assert late != walk
    f_in = run(CooperativeFilter("drone_0"), walk)
    f_late = run(CooperativeFilter("drone_0"), late)
    assert f_late.stats.refiltered > 10 and f_late.stats.too_late == 0
    t = walk[-1].t_ns
    a, b = f_in.estimate(t), f_late.estimate(t)
    np.testing.assert_allclose(a.position_ned_m, b.position_ned_m, atol=1e-6)
    np.testing.assert_allclose(a.velocity_ned_m_s, b.velocity_ned_m_s, atol=1e-6)
    np.testing.assert_allclose(a.covariance, b.covariance, atol=1e-8)


def test_older_than_buffer_is_dropped_and_counted(walk):
    f = CooperativeFilter("drone_0", TrackerConfig(buffer_size=40))
    run(f, walk[1:])
    state_before = f.state
    assert f.add(walk[0]) is False
    assert f.stats.too_late == 1
    np.testing.assert_array_equal(f.state[0], state_before[0])


def test_outlier_gated_and_nan_ignored(walk):
    f = run(CooperativeFilter("drone_0"), walk[:60])
    x_before = f.state[0]
    m = walk[60]
    out = dataclasses.replace(m, position_ned_m=m.position_ned_m + np.array([6.0, -4.0, 0.0]))
    assert f.add(out) is False
    assert f.stats.rejected_gate == 1
    # a rejected measurement only predicts: position moves by at most velocity * dt
    assert np.linalg.norm(f.state[0][:3] - x_before[:3]) < 0.2
    nan = dataclasses.replace(walk[61], position_ned_m=np.array([np.nan, 0.0, 0.0]))
    n_acc = f.stats.accepted
    assert f.add(nan) is False
    assert f.stats.rejected_nonfinite == 1 and f.stats.accepted == n_acc
    assert np.all(np.isfinite(f.state[0]))
    assert f.add(walk[62]) is True


def test_reset_after_ten_seconds_and_reacquire(walk):
    f = CooperativeFilter("drone_0")
    first = [m for m in walk if m.t_ns < 5e9]
    run(f, first)
    t_last = first[-1].t_ns
    assert f.estimate(t_last + int(9.5e9)).status == "predicting"
    assert f.estimate(t_last + int(10.5e9)) is None
    later = [m for m in walk if m.t_ns > t_last + 10.5e9]
    assert f.add(later[0]) is True
    assert f.stats.resets == 1
    np.testing.assert_allclose(f.state[0][3:6], 0.0, atol=1e-9)  # fresh track: velocity from the prior
    run(f, later[1:])
    t = later[-1].t_ns
    assert np.linalg.norm(f.estimate(t).position_ned_m - person_center(t * 1e-9)) < 0.3


def test_wrong_track_reinitialised_after_consecutive_rejections(walk):
    f = CooperativeFilter("drone_0", TrackerConfig(max_consecutive_rejections=5))
    bogus = dataclasses.replace(walk[0], position_ned_m=walk[0].position_ned_m + 30.0)
    f.add(bogus)
    run(f, walk[1:40])
    assert f.stats.reinitialisations == 1
    t = walk[39].t_ns
    assert np.linalg.norm(f.estimate(t).position_ned_m - person_center(t * 1e-9)) < 0.5


def test_teammates_appearing_and_disappearing(walk):
    f = CooperativeFilter("drone_0")
    t_cut = 8e9
    seq = [m for m in walk if not (m.source_id == "drone_2" and m.t_ns > t_cut)]
    for m in seq:
        f.add(m)
        if 5e9 < m.t_ns < t_cut:
            assert f.estimate(m.t_ns).num_sources == 3
    t = seq[-1].t_ns
    est = f.estimate(t)
    assert est.num_sources == 2 and f.sources(t) == ["drone_0", "drone_1"]
    assert np.linalg.norm(est.position_ned_m - person_center(t * 1e-9)) < 0.4


def test_estimates_own_gps_offset():
    offset = np.array([1.5, -1.2, 0.6])
    # drone_0 has a consistent GPS bias and reports an honest (large) position variance; its teammates are good
    meas = simulate(30.0, np.random.default_rng(3), offsets={0: offset}, pos_var_m2={0: 4.0})
    f = run(CooperativeFilter("drone_0"), meas)
    est = f.estimate(meas[-1].t_ns)
    np.testing.assert_allclose(est.offset_ned_m, offset, atol=0.35)
    true_pos = np.zeros(3)
    corrected = est.corrected_self_position(true_pos + offset)
    assert np.linalg.norm(corrected - true_pos) < 0.4 * np.linalg.norm(offset)
    # the person estimate is not dragged by the biased drone
    assert np.linalg.norm(est.position_ned_m - person_center(meas[-1].t_ns * 1e-9)) < 0.35
    # a teammate's filter sees the same bias as noise and estimates no offset of its own
    g = run(CooperativeFilter("drone_1"), meas)
    assert np.linalg.norm(g.estimate(meas[-1].t_ns).offset_ned_m) < 0.35


def test_config_validation():
    with pytest.raises(TrackerError, match="velocity_tau_s"):
        TrackerConfig(velocity_tau_s=0)
    with pytest.raises(TrackerError, match="buffer_size"):
        TrackerConfig(buffer_size=1)


def test_process_model_decays():
    f = CooperativeFilter("d")
    F, Q = f._transition(3.0, 9)
    assert abs(F[3, 3] - np.exp(-1.0)) < 1e-12 and abs(F[6, 6] - np.exp(-0.1)) < 1e-12
    # long-horizon velocity variance tends to the stationary sigma^2
    F, Q = f._transition(100.0, 9)
    assert abs(Q[3, 3] - 1.5**2) < 1e-6 and abs(Q[6, 6] - 2.0**2) < 0.02


def test_sources_counted_beyond_buffer_span():
    # 8 drones at 4 Hz: 40 entries span 1.25 s, less than the 3 s source window
    meas = simulate(6.0, np.random.default_rng(5), n=8)
    f = CooperativeFilter("drone_0", TrackerConfig(buffer_size=40))
    late_src = [m for m in meas if not (m.source_id == "drone_7" and m.t_ns > 4.0e9)]
    run(f, late_src)
    t = late_src[-1].t_ns
    assert f.estimate(t).num_sources == 8  # drone_7 last seen ~2 s ago: still a source
    assert f.estimate(t + int(1.5e9)).num_sources == 7


def test_fleet_offsets_put_every_drone_in_the_fleet_mean_frame():
    """All three drones biased (same GPS grade, 1 m): with a per-teammate offset state every drone's filter
    places the person in the fleet's mean frame (error = the mean bias, the unobservable common part), the
    drones agree, and each own-offset estimate is its bias relative to that frame. AirCap's 9-state filter
    (teammates' biases as white noise) puts each drone in the mean frame of its *teammates* instead."""
    biases = {0: np.array([1.2, -0.4, 0.3]), 1: np.array([-0.9, 0.8, -0.2]), 2: np.array([0.3, 0.9, 0.4])}
    mean_b = np.mean(list(biases.values()), axis=0)
    meas = simulate(40.0, np.random.default_rng(11), offsets=biases, pos_var_m2=1.0)
    t = meas[-1].t_ns
    truth = person_center(t * 1e-9)
    fleet = {k: run(CooperativeFilter(f"drone_{k}", TrackerConfig(offset_sigma_m=1.0)), meas).estimate(t) for k in biases}
    solo = {k: run(CooperativeFilter(f"drone_{k}", TrackerConfig(offset_sigma_m=1.0, fleet_offsets=False)), meas).estimate(t) for k in biases}
    for k, est in fleet.items():
        # the person sits where the fleet-mean frame puts it: truth + mean bias
        assert np.linalg.norm(est.position_ned_m - (truth + mean_b)) < 0.25, (k, est.position_ned_m - truth)
        assert np.linalg.norm(est.offset_ned_m - (biases[k] - mean_b)) < 0.3, (k, est.offset_ned_m, biases[k] - mean_b)
    spread = max(np.linalg.norm(fleet[a].position_ned_m - fleet[b].position_ned_m) for a in fleet for b in fleet)
    spread_solo = max(np.linalg.norm(solo[a].position_ned_m - solo[b].position_ned_m) for a in solo for b in solo)
    assert spread < 0.15 and spread_solo > 3 * spread, (spread, spread_solo)
    assert len(run(CooperativeFilter("drone_0"), meas).state[0]) == 6 + 3 * 3


def test_teammate_offset_prior_from_its_reported_grade():
    """A teammate reporting an RTK-grade pose (5 cm) pins the frame: the biased GPS-grade drone's offset is
    recovered in full (not shared with the good drones)."""
    offset = np.array([1.5, -1.2, 0.6])
    meas = simulate(30.0, np.random.default_rng(3), offsets={0: offset}, pos_var_m2={0: 4.0, 1: 0.05**2, 2: 0.05**2})
    est = run(CooperativeFilter("drone_0"), meas).estimate(meas[-1].t_ns)
    np.testing.assert_allclose(est.offset_ned_m, offset, atol=0.25)
    assert np.linalg.norm(est.position_ned_m - person_center(meas[-1].t_ns * 1e-9)) < 0.25
