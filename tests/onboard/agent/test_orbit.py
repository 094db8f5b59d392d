"""Orbit geometry and the orbit setpoint source (pure logic)."""

import math

import numpy as np
import pytest

from shared_msgs import OrbitPlan
from onboard.orbit import (
    OrbitController,
    evenly_spaced_phases,
    gimbal_pitch_to_point_rad,
    min_slot_separation_m,
    slot_state,
    yaw_to_point_rad,
)
from onboard.setpoint import HoldSource

T0 = 1_700_000_000.0


def make_plan(**kw):
    ids = kw.pop("ids", ["drone_1", "drone_2", "drone_3"])
    d = dict(plan_id="p1", center_ned_m=(10.0, -5.0, 0.0), radius_m=8.0, altitude_m=6.0, angular_speed_rad_s=0.2,
             direction=1, start_time_ns=int(T0 * 1e9), phase_offset_rad=evenly_spaced_phases(ids))
    d.update(kw)
    return OrbitPlan(header=OrbitPlan.make_header("gcs"), **d)


def test_slot_on_circle_and_velocity_is_derivative():
    plan = make_plan()
    for t in (T0 + 0.5, T0 + 7.3, T0 + 31.0):
        p, v, a = slot_state(plan, "drone_2", t)
        c = np.array(plan.center_ned_m)
        assert math.hypot(p[0] - c[0], p[1] - c[1]) == pytest.approx(8.0)
        assert p[2] == pytest.approx(-6.0)
        h = 1e-2
        p2, _, _ = slot_state(plan, "drone_2", t + h)
        p1, _, _ = slot_state(plan, "drone_2", t - h)
        np.testing.assert_allclose(v, (p2 - p1) / (2 * h), atol=1e-4)
        assert np.linalg.norm(v[:2]) == pytest.approx(8.0 * 0.2)
        # centripetal acceleration points at the centre
        assert np.dot(a[:2], (c - p)[:2]) > 0


def test_clockwise_seen_from_above_and_waits_before_start():
    plan = make_plan()
    p0, v0, _ = slot_state(plan, "drone_1", T0 - 3)  # phase 0 = north of the centre, not moving yet
    np.testing.assert_allclose(p0, [18.0, -5.0, -6.0])
    assert np.all(v0 == 0)
    _, v, _ = slot_state(plan, "drone_1", T0 + 0.01)
    assert v[1] > 0  # at north, direction 1 moves east: clockwise seen from above (NED)
    plan_ccw = make_plan(direction=-1)
    _, v, _ = slot_state(plan_ccw, "drone_1", T0 + 0.01)
    assert v[1] < 0


def test_phase_spacing_is_kept():
    plan = make_plan()
    for t in (T0, T0 + 13.0):
        ps = [slot_state(plan, d, t)[0] for d in ("drone_1", "drone_2", "drone_3")]
        for i in range(3):
            assert np.linalg.norm(ps[i] - ps[(i + 1) % 3]) == pytest.approx(2 * 8.0 * math.sin(math.pi / 3))
    assert min_slot_separation_m(plan) == pytest.approx(2 * 8 * math.sin(math.pi / 3))


def test_yaw_and_pitch_point_at_the_centre():
    assert yaw_to_point_rad([0, 0, 0], [0, 5, 0]) == pytest.approx(math.pi / 2)  # east
    assert yaw_to_point_rad([0, 0, 0], [-5, 0, 0]) == pytest.approx(math.pi)
    assert gimbal_pitch_to_point_rad([0, 0, -5], [5, 0, 0]) == pytest.approx(-math.pi / 4)  # down 45 deg


def test_controller_approaches_with_bounded_speed_then_tracks_with_feed_forward():
    plan = make_plan()
    ctl = OrbitController(plan, "drone_1", approach_speed_m_s=3.0, approach_climb_m_s=1.0)
    pos = np.array([0.0, 0.0, -3.0])
    dt = 0.05
    prev = None
    t = T0 - 10
    for k in range(1200):
        sp = ctl.update(t, pos, np.zeros(3), 0.0)
        if prev is not None and not ctl.captured:
            step = sp.position_ned_m - prev
            assert math.hypot(step[0], step[1]) <= (3.0 + 1.6) * dt + 1e-9
            assert abs(step[2]) <= 1.0 * dt + 1e-9
        prev = sp.position_ned_m
        pos = sp.position_ned_m  # a perfect follower
        t += dt
    assert ctl.captured
    p, v, _ = slot_state(plan, "drone_1", t - dt)
    np.testing.assert_allclose(sp.position_ned_m, p, atol=1e-9)
    np.testing.assert_allclose(sp.velocity_ned_m_s, v, atol=1e-9)
    assert sp.yaw_rad == pytest.approx(yaw_to_point_rad(p, plan.center_ned_m))
    assert sp.gimbal_pitch_rad == pytest.approx(-math.atan2(6.0, 8.0))


def test_controller_refuses_a_drone_without_slot():
    with pytest.raises(ValueError, match="no phase slot"):
        OrbitController(make_plan(), "drone_9")


def test_hold_source():
    sp = HoldSource([1, 2, -3], 0.5).update(0.0, np.zeros(3), np.zeros(3), 0.0)
    np.testing.assert_allclose(sp.position_ned_m, [1, 2, -3])
    assert sp.yaw_rad == 0.5 and np.all(sp.velocity_ned_m_s == 0)


@pytest.mark.parametrize("direction", [1, -1])
def test_trim_removes_a_steady_lag_and_outward_bias_in_the_rotating_frame(direction):
    """A vehicle that flies its setpoint 0.4 m outside and 0.3 m behind (what drag along the track leaves an
    autopilot's world-frame integrator): the trim moves the setpoint until the vehicle is on its slot."""
    plan = make_plan(ids=["d1"], center_ned_m=(2.0, -1.0, 0.0), angular_speed_rad_s=0.15, direction=direction)
    t0 = T0
    ctl = OrbitController(plan, "d1", trim_gain_per_s=0.3)
    p, vp, _ = slot_state(plan, "d1", t0)
    ctl.update(t0, p, vp, 0.0)
    assert ctl.captured

    def vehicle(sp_pos):  # outward 0.4 m, behind 0.3 m, 0.1 m low, of where it is asked to be
        axes = ctl._rtu_axes(sp_pos)
        return sp_pos + axes.T @ np.array([0.4, -0.3, -0.1])

    err0 = np.linalg.norm(vehicle(slot_state(plan, "d1", t0)[0]) - slot_state(plan, "d1", t0)[0])
    pos = p
    for k in range(1, 20 * 30):
        t = t0 + k / 20
        sp = ctl.update(t, pos, vp, 0.0)
        pos = vehicle(sp.position_ned_m)
    slot = slot_state(plan, "d1", t)[0]
    err_rtu = ctl._rtu_axes(slot) @ (pos - slot)
    # radial and vertical errors gone; along the track what is left is this model's own one-tick delay (the
    # position fed back is the one reached for the previous setpoint: 1.2 m/s x 0.05 s)
    assert err0 == pytest.approx(0.51, abs=0.01)
    assert abs(err_rtu[0]) < 0.01 and abs(err_rtu[2]) < 0.01 and abs(err_rtu[1]) < 0.065, err_rtu
    # bounded: an error it cannot remove does not wind the trim up past trim_max_m
    ctl2 = OrbitController(plan, "d1", trim_gain_per_s=0.3, trim_max_m=0.5)
    ctl2.update(t0, p, vp, 0.0)
    for k in range(1, 400):
        ctl2.update(t0 + k / 20, slot_state(plan, "d1", t0 + k / 20)[0] + np.array([0.0, 0.0, 1.0]), vp, 0.0)
    assert np.linalg.norm(ctl2.trim_rtu_m) == pytest.approx(0.5)
