import math

import numpy as np
import pytest

from onboard.formation.mpc import Cylinder, FormationMPC, MpcConfig, MpcError, SharedPlan

PERSON = np.array([0.0, 0.0, -0.85])


def fly(mpcs, p, v, person_fn, angles, steps, dt_ns=int(1e8)):
    """Lockstep closed loop: every drone plans against the others' plans of the previous step and then
    flies its setpoint exactly. Returns positions (steps + 1, n, 3), velocities and results."""
    ids = list(mpcs)
    # before the first plans arrive, teammates are known by their state (as the agent does)
    plans = {i: SharedPlan.from_state(i, 0, p[k], v[k], 0.1, 15) for k, i in enumerate(ids)}
    P, V, R = [p.copy()], [v.copy()], []
    for s in range(steps):
        t = s * dt_ns
        pp, pv = person_fn(t * 1e-9)
        res = {i: mpcs[i].step(t, p[k], v[k], pp, pv, angles[i], {j: plans[j] for j in plans if j != i}) for k, i in enumerate(ids)}
        plans = {i: r.plan for i, r in res.items()}
        p = np.array([res[i].setpoint_position_ned_m for i in ids])
        v = np.array([res[i].setpoint_velocity_ned_m_s for i in ids])
        P.append(p)
        V.append(v)
        R.append(res)
    return np.array(P), np.array(V), R


def pairwise_min(P):
    n = P.shape[1]
    return min(np.linalg.norm(P[:, a] - P[:, b], axis=1).min() for a in range(n) for b in range(a + 1, n))


def still(_t):
    return PERSON, np.zeros(3)


def test_reaches_slot_with_yaw_toward_person():
    m = FormationMPC("d0", MpcConfig(max_solve_time_s=1.0))
    P, V, R = fly({"d0": m}, np.array([[-3.0, 4.0, -6.0]]), np.zeros((1, 3)), still, {"d0": math.pi / 2}, 80)
    np.testing.assert_allclose(P[-1, 0], [0.0, 8.0, -8.0], atol=0.1)
    r = R[-1]["d0"]
    assert abs(r.setpoint_yaw_rad - (-math.pi / 2)) < 0.02  # looking south-west... at the person: west
    assert r.plan_gimbal_pitch_rad[0] < 0  # camera down
    assert m.fallback_count == 0


def test_three_drones_same_slot_keep_separation_and_limits():
    cfg = MpcConfig(min_separation_m=3.0, max_solve_time_s=1.0)
    ids = ["d0", "d1", "d2"]
    mpcs = {i: FormationMPC(i, cfg) for i in ids}
    p = np.array([[-10.0, -6.0, -8.0], [-10.0, 0.0, -8.0], [-10.0, 6.0, -8.0]])
    P, V, R = fly(mpcs, p, np.zeros((3, 3)), still, {i: math.pi for i in ids}, 80)
    assert pairwise_min(P) >= 3.0 - 0.01
    # they did converge toward the common slot (crowding around it)
    assert all(np.linalg.norm(P[-1, k, :2] - [-8.0, 0.0]) < 4.5 for k in range(3))
    vh = np.linalg.norm(V[:, :, :2], axis=2)
    assert vh.max() <= 5.0 + 1e-3 and np.abs(V[:, :, 2]).max() <= 1.0 + 1e-3
    acc = np.diff(V, axis=0) / 0.1
    assert np.linalg.norm(acc[:, :, :2], axis=2).max() <= 4.0 + 1e-2
    assert sum(m.fallback_count for m in mpcs.values()) == 0


def test_ipopt_nonconvex_variant_keeps_separation():
    with pytest.raises(MpcError, match="ipopt"):
        MpcConfig(separation="nonconvex")
    cfg = MpcConfig(solver="ipopt", separation="nonconvex", max_teammates=2, max_solve_time_s=1.0)
    ids = ["d0", "d1", "d2"]
    mpcs = {i: FormationMPC(i, cfg) for i in ids}
    p = np.array([[-10.0, -6.0, -8.0], [-10.0, 0.0, -8.0], [-10.0, 6.0, -8.0]])
    P, V, R = fly(mpcs, p, np.zeros((3, 3)), still, {i: math.pi for i in ids}, 30)
    assert pairwise_min(P) >= 3.0 - 0.01
    # both sides avoid each other's old plan at the full distance: crowding makes it (locally) infeasible
    # now and then -> brake fallbacks; the buffered-Voronoi QP has none here (test above)
    assert sum(m.fallback_count for m in mpcs.values()) <= 9
    assert np.linalg.norm(np.diff(V, axis=0)[:, :, :2] / 0.1, axis=2).max() <= 4.0 + 1e-2


def test_head_on_swap_keeps_separation():
    ids = ["a", "b"]
    mpcs = {i: FormationMPC(i, MpcConfig(max_solve_time_s=1.0)) for i in ids}
    p = np.array([[8.0, 0.0, -8.0], [-8.0, 0.0, -8.0]])
    # slots swapped: they must pass each other around the person
    P, V, R = fly(mpcs, p, np.zeros((2, 3)), still, {"a": math.pi, "b": 0.0}, 120)
    assert pairwise_min(P) >= 3.0 - 0.01
    assert np.min(np.linalg.norm(P[:, :, :2], axis=2)) >= 4.0 - 0.05  # person keep-out
    np.testing.assert_allclose(P[-1, 0, :2], [-8.0, 0.0], atol=0.5)


def test_speed_limit_when_far_and_person_walking():
    m = FormationMPC("d0", MpcConfig(max_solve_time_s=1.0))

    def walking(t):
        return PERSON + np.array([1.2 * t, 0.0, 0.0]), np.array([1.2, 0.0, 0.0])

    P, V, R = fly({"d0": m}, np.array([[-40.0, 30.0, -4.0]]), np.zeros((1, 3)), walking, {"d0": 0.0}, 200)
    vh = np.linalg.norm(V[:, 0, :2], axis=1)
    assert 4.5 < vh.max() <= 5.0 + 1e-3
    assert np.abs(V[:, 0, 2]).max() <= 1.0 + 1e-3
    # following the walking person at the end
    person_end, _ = walking(199 * 0.1)
    assert np.linalg.norm(P[-1, 0, :2] - (person_end[:2] + [8.0, 0.0])) < 1.5


def test_geofence_respected():
    fence = ((-20.0, -20.0), (-20.0, 20.0), (5.0, 20.0), (5.0, -20.0))  # north edge at 5 m
    cfg = MpcConfig(geofence_ne_m=fence, geofence_margin_m=1.0, max_solve_time_s=1.0)
    m = FormationMPC("d0", cfg)
    # slot straight north at 8 m: outside the fence; the drone starts on the far (south) side
    P, V, R = fly({"d0": m}, np.array([[-8.0, 0.5, -8.0]]), np.zeros((1, 3)), still, {"d0": 0.0}, 100)
    assert P[:, 0, 0].max() <= 4.0 + 0.02
    assert P[-1, 0, 0] > 3.5  # pressed against the fence, as close to the slot as allowed
    assert np.min(np.linalg.norm(P[:, 0, :2], axis=1)) >= 4.0 - 0.05  # went around the person
    assert abs(R[-1]["d0"].min_geofence_margin_m - (5.0 - R[-1]["d0"].plan.positions_ned_m[:, 0].max())) < 1e-9
    assert R[-1]["d0"].min_geofence_margin_m >= 1.0 - 0.02
    assert m.fallback_count == 0


def test_obstacle_avoided():
    cfg = MpcConfig(obstacles=(Cylinder(0.0, 8.0, 1.5),), obstacle_margin_m=0.5, max_solve_time_s=1.0)
    m = FormationMPC("d0", cfg)
    P, V, R = fly({"d0": m}, np.array([[0.0, 16.0, -8.0]]), np.zeros((1, 3)), still, {"d0": -math.pi / 2}, 150)
    d = np.linalg.norm(P[:, 0, :2] - [0.0, 8.0], axis=1)
    assert d.min() >= 2.0 - 0.05
    np.testing.assert_allclose(P[-1, 0, :2], [0.0, -8.0], atol=0.5)


def test_infeasible_falls_back_to_brake_and_counts():
    fence = ((-20.0, -20.0), (-20.0, 20.0), (10.0, 20.0), (10.0, -20.0))
    m = FormationMPC("d0", MpcConfig(geofence_ne_m=fence, geofence_margin_m=1.0, max_solve_time_s=1.0))
    # 5 m/s toward the fence 0.3 m before its margin: cannot stop in time
    r = m.step(0, np.array([8.7, 0.0, -8.0]), np.array([5.0, 0.0, 0.0]), PERSON, np.zeros(3), 0.0)
    assert r.fallback and not r.ok and m.fallback_count == 1
    # brake plan: decelerating at the limit, then hovering
    v = np.linalg.norm(r.plan_velocities_ned_m_s[:, :2], axis=1)
    assert np.all(np.diff(v) <= 1e-9) and abs(v[1] - (5.0 - 0.4)) < 1e-9 and v[-1] < 1e-9
    np.testing.assert_allclose(r.setpoint_velocity_ned_m_s, [4.6, 0.0, 0.0])


def test_late_solve_falls_back():
    m = FormationMPC("d0", MpcConfig(max_solve_time_s=1e-7))
    r = m.step(0, np.array([0.0, 0.0, -8.0]), np.array([0.0, 1.0, 0.0]), PERSON, np.zeros(3), 0.0)
    assert r.fallback and "late" in r.status and m.fallback_count == 1
    m2 = FormationMPC("d0", MpcConfig(max_solve_time_s=1.0))  # generous: the test machine is shared
    for k in range(5):
        r2 = m2.step(k * int(1e8), np.array([0.0, 0.0, -8.0]), np.zeros(3), PERSON + [8, 8, 0], np.zeros(3), 0.0)
        assert r2.ok and not r2.fallback
    assert m2.fallback_count == 0 and m2.solve_count == 5


def test_bad_input():
    m = FormationMPC("d0", MpcConfig(max_solve_time_s=1.0))
    with pytest.raises(MpcError, match="not finite"):
        m.step(0, np.array([np.nan, 0, -8]), np.zeros(3), PERSON, np.zeros(3), 0.0)
    with pytest.raises(MpcError, match="convex"):
        FormationMPC("d0", MpcConfig(geofence_ne_m=((0, 0), (10, 0), (2, 2), (0, 10))))
    with pytest.raises(MpcError, match="altitude"):
        MpcConfig(altitude_m=50.0)


def test_shared_plan_sampling():
    plan = SharedPlan("x", int(1e9), 0.1, np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]))
    s = plan.sample(np.array([0.5e9, 1.05e9, 1.15e9, 5e9]))
    np.testing.assert_allclose(s[:, 0], [0.0, 0.5, 1.5, 2.0])


def test_plan_from_state_is_avoided():
    q = SharedPlan.from_state("mate", 0, [0.0, 8.0, -8.0], [0.0, -2.0, 0.0], 0.1, 15)
    np.testing.assert_allclose(q.positions_ned_m[-1], [0.0, 5.0, -8.0])
    m = FormationMPC("d0", MpcConfig(max_solve_time_s=1.0))
    # my slot is where the teammate is heading
    r = m.step(0, np.array([0.0, 2.0, -8.0]), np.zeros(3), PERSON + [-8.0, 0, 0], np.zeros(3), math.pi / 2, {"mate": q})
    # the bisecting plane shifted by d/2: distance >= (|a - b| + d) / 2 >= d while the old plans were >= d apart
    assert r.ok and r.min_teammate_distance_m >= 3.0 - 1e-2


def test_altitude_band_and_vertical_speed():
    cfg = MpcConfig(min_altitude_m=3.0, max_altitude_m=10.0, altitude_m=8.0, max_speed_down_m_s=1.0, max_solve_time_s=1.0)
    m = FormationMPC("d0", cfg)
    ground = -2.0  # ground 2 m above the origin
    # start 1 m above the ground (below the band): climbs back at <= 1 m/s, never below its start
    p, v = np.array([8.0, 0.0, ground - 1.0]), np.zeros(3)
    alts = []
    for k in range(80):
        r = m.step(k * int(1e8), p, v, np.array([0.0, 0.0, ground - 0.85]), np.zeros(3), 0.0, ground_down_m=ground)
        assert abs(r.setpoint_velocity_ned_m_s[2]) <= 1.0 + 1e-3
        p, v = r.setpoint_position_ned_m, r.setpoint_velocity_ned_m_s
        alts.append(ground - p[2])
    assert min(alts) >= 1.0 - 1e-3 and abs(alts[-1] - 8.0) < 0.1
    assert m.fallback_count == 0
    # the band is a hard limit: a slot above it is clipped to the band
    m2 = FormationMPC("d0", MpcConfig(max_altitude_m=9.0, altitude_m=9.0, max_solve_time_s=1.0))
    for k in range(40):
        r = m2.step(k * int(1e8), np.array([8.0, 0.0, -8.95]), np.zeros(3), PERSON, np.zeros(3), 0.0)
        assert np.all(-r.plan.positions_ned_m[1:, 2] <= 9.0 + 1e-3)


def test_drone_faster_than_the_limits_slows_down_instead_of_falling_back():
    """A vehicle overshoots its setpoints: here it still climbs at take-off speed (1.45 m/s against the MPC's
    1 m/s) and flies 5.8 m/s horizontally (limit 5). A hard limit from the first step would be infeasible
    (brake and hold); the plan must brake at no more than the acceleration limits and be within the speed
    limits once braking at full acceleration gets there."""
    cfg = MpcConfig(max_speed_down_m_s=1.0, max_accel_down_m_s2=2.0, max_speed_h_m_s=5.0, max_accel_h_m_s2=4.0,
                    max_solve_time_s=1.0)
    for v0 in ([0.0, 0.0, -1.45], [0.0, 0.0, 1.45], [5.8, 0.0, 0.0], [-3.0, 4.9, -1.3]):
        m = FormationMPC("d0", cfg)
        v0 = np.array(v0)
        r = m.step(0, np.array([8.0, 0.0, -6.0]), v0, PERSON, np.zeros(3), 0.0)
        assert r.ok and not r.fallback and m.fallback_count == 0, (v0, r.status)
        V = r.plan_velocities_ned_m_s
        dv = np.diff(V, axis=0) / cfg.dt_s
        assert np.all(np.abs(dv[:, 2]) <= 2.0 + 1e-3)
        assert np.all(np.linalg.norm(dv[:, :2], axis=1) <= 4.0 + 1e-3)
        # vertical: within 1 m/s from the step where full deceleration gets there
        t = np.arange(1, cfg.horizon_steps + 1) * cfg.dt_s
        settled_v = abs(v0[2]) - 2.0 * t <= 1.0 - 0.05
        assert np.all(np.abs(V[1:, 2])[settled_v] <= 1.0 + 1e-3)
        assert np.all(np.abs(V[1:, 2]) <= np.maximum(1.0, abs(v0[2]) - 0.98 * 2.0 * t) + 1e-3)
        # horizontal: the speed never grows and ends within the limit
        vh = np.linalg.norm(V[:, :2], axis=1)
        assert vh[-1] <= 5.0 + 1e-3 and vh[1:].max() <= max(5.0, np.linalg.norm(v0[:2])) + 1e-3
    # within the limits nothing changes: the plain limits hold at every step
    m = FormationMPC("d0", cfg)
    r = m.step(0, np.array([8.0, 0.0, -6.0]), np.array([0.0, 0.0, -0.9]), PERSON, np.zeros(3), 0.0)
    assert r.ok and np.all(np.abs(r.plan_velocities_ned_m_s[1:, 2]) <= 1.0 + 1e-3)
