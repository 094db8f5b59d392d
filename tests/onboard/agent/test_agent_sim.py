"""The agent flying the built-in simulator for real: MAVSDK over UDP loopback, Zenoh to the fleet client,
an agent OS process; checked against the simulator's ground truth."""

from __future__ import annotations

import math
import signal
import time

import msgspec
import numpy as np
import pytest

from groundstation.fleet import FleetError, make_orbit_plan
from shared_msgs import Command, CommandAck, OrbitPlan, VehicleState, encode, keys, now_ns

pytestmark = pytest.mark.slow


def _hover(fl, drone="drone_1"):
    assert fl.fleet.wait_until(lambda f: drone in f.states and f.states[drone].health_ok, 40, "healthy state"), fl.log(drone)
    acks = fl.fleet.command("takeoff", wait_s=30, expect=[drone], results=("completed", "failed", "refused"))
    assert acks[drone].result == "completed", (acks, fl.log(drone))
    assert fl.wait_state(drone, "hover", 40), fl.log(drone)


def test_agent_flies_orbit_refuses_bad_input_and_lands(flight):
    # a small estimator bias (RTK-like): the errors against the truth then measure the agent's control
    fl = flight(1, ["estimator.pos_bias_std_xy_m=0.05", "estimator.pos_bias_std_z_m=0.05"])
    proc = fl.start_agent(0)
    _hover(fl)
    home = fl.truth()
    center = (home[0] + 4.0, home[1], 0.0)
    plan = make_orbit_plan(["drone_1"], center, radius_m=4.0, altitude_m=4.0, angular_speed_rad_s=0.4, start_in_s=1.0)
    fl.fleet.send_plan(plan)
    assert fl.fleet.wait_acks(plan.plan_id, ["drone_1"], 5)["drone_1"].result == "accepted"
    acks = fl.fleet.command("start", wait_s=10, expect=["drone_1"], results=("completed", "failed", "refused"))
    assert acks["drone_1"].result == "completed", fl.log("drone_1")
    assert fl.fleet.states["drone_1"].flight_mode == "OFFBOARD" or fl.wait_state("drone_1", "orbit", 2)

    def orbit_errors(seconds):
        rad, alt = [], []
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            p = fl.truth()
            rad.append(math.hypot(p[0] - center[0], p[1] - center[1]) - 4.0)
            alt.append(-p[2] - 4.0)
            time.sleep(0.1)
        return float(np.sqrt(np.mean(np.square(rad)))), float(np.sqrt(np.mean(np.square(alt))))

    time.sleep(8.0)  # approach + settle
    r_rmse, a_rmse = orbit_errors(4.0)
    assert r_rmse < 0.5 and a_rmse < 0.3, (r_rmse, a_rmse)

    # a plan with a bad field: refused with the reason, the orbit goes on unchanged
    # (the fleet client refuses to send it; a client that does not check, or a peer, still gets the agent's refusal)
    with pytest.raises(FleetError, match="radius_m"):
        make_orbit_plan(["drone_1"], center, radius_m=-2.0, altitude_m=4.0)
    bad = msgspec.structs.replace(make_orbit_plan(["drone_1"], center, radius_m=2.0, altitude_m=4.0), radius_m=-2.0)
    with pytest.raises(FleetError, match="radius_m"):
        fl.fleet.send_plan(bad)
    fl.bus.publish(keys.gcs_key(fl.fleet_id, keys.PLAN), bad, latch=True)
    ack = fl.fleet.wait_acks(bad.plan_id, ["drone_1"], 5)["drone_1"]
    assert ack.result == "refused" and "radius_m" in ack.reason
    wrong = make_orbit_plan(["drone_7"], center, radius_m=4.0, altitude_m=4.0)
    fl.fleet.send_plan(wrong)
    ack = fl.fleet.wait_acks(wrong.plan_id, ["drone_1"], 5)["drone_1"]
    assert ack.result == "refused" and "wrong target" in ack.reason
    # a command with a bad field, and a stale one
    acks = fl.fleet.command("takeoff", params={"altitude_m": -5.0}, wait_s=5, expect=["drone_1"])
    assert acks["drone_1"].result == "refused" and "altitude_m" in acks["drone_1"].reason
    stale = Command(header=Command.make_header("gcs"), command_id="stale-land", target="*", action="land")
    stale.header.t_sent_ns = now_ns() - int(30e9)
    fl.bus.publish_raw(keys.gcs_key(fl.fleet_id, keys.CMD), encode(stale))
    ack = fl.fleet.wait_acks("stale-land", ["drone_1"], 5)["drone_1"]
    assert ack.result == "refused" and "stale" in ack.reason
    assert fl.agent_state("drone_1") == "orbit"
    r_rmse, a_rmse = orbit_errors(3.0)
    assert r_rmse < 0.5 and a_rmse < 0.3, (r_rmse, a_rmse)

    acks = fl.fleet.command("land", wait_s=5, expect=["drone_1"])
    assert acks["drone_1"].result in ("accepted", "completed")  # "completed" may overtake "accepted"
    assert fl.wait_state("drone_1", "landed", 30), fl.log("drone_1")
    assert -fl.truth()[2] < 0.3

    proc.send_signal(signal.SIGTERM)
    assert proc.wait(15) == 0, fl.log("drone_1")

    from flightdata.flightlog import FlightLog

    log = FlightLog(fl.tmp / "drone_1.s001.mcap")  # the agent's first (only) sortie
    assert log.finalised
    counts = log.topic_counts()
    states = log.read_topic("state", VehicleState)
    t = np.array([s.header.t_measurement_ns for s in states]) * 1e-9
    assert len(states) / (t[-1] - t[0]) > 45.0, "state must be recorded at ~50 Hz"
    # the position covariance is the receiver's reported accuracy (GPS_RAW_INT h_acc / v_acc via MAVSDK's
    # RawGps): the estimator grade set above (0.05 m), not the message's 1 m^2 default
    np.testing.assert_allclose(states[-1].position_cov_m2, (0.05**2, 0.05**2, 0.05**2), rtol=0.02)
    assert counts.get("gcs/cmd", 0) >= 5 and counts.get("ack", 0) >= 8 and counts.get("gcs/plan", 0) >= 3
    acks = log.read_topic("ack", CommandAck)
    assert any(a.result == "refused" and "stale" in a.reason for a in acks)


def test_agent_lands_when_ground_station_heartbeat_stops_and_on_sigterm(flight):
    fl = flight(1)
    proc = fl.start_agent(0, "--set", "safety.gcs_heartbeat_timeout_s=2.0")
    _hover(fl)
    fl.fleet.stop_heartbeat()
    t0 = time.monotonic()
    assert fl.wait_state("drone_1", "landing", 6), fl.log("drone_1")
    assert time.monotonic() - t0 >= 1.5  # not before the timeout
    assert "heartbeat lost" in fl.log("drone_1")
    assert fl.wait_state("drone_1", "landed", 30), fl.log("drone_1")
    assert -fl.truth()[2] < 0.3

    # heartbeat back, fly again, then SIGTERM while airborne: the agent lands before exiting
    fl.fleet.start_heartbeat()
    time.sleep(3.0)  # the autopilot disarms after landing
    _hover(fl)
    assert -fl.truth()[2] > 2.0
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(40) == 0, fl.log("drone_1")
    assert -fl.truth()[2] < 0.3, "the agent exited before touchdown"
    assert "shutdown while airborne: land" in fl.log("drone_1")


def test_agent_lands_on_low_battery(flight):
    fl = flight(1, ["battery.start_percent=24", "battery.hover_drain_pct_per_min=60"])
    fl.start_agent(0, "--set", "safety.low_battery_frac=0.2")
    assert fl.fleet.wait_until(lambda f: "drone_1" in f.states and f.states["drone_1"].health_ok, 40), fl.log("drone_1")
    acks = fl.fleet.command("takeoff", wait_s=30, expect=["drone_1"], results=("completed", "failed", "refused"))
    assert acks["drone_1"].result == "completed", fl.log("drone_1")
    assert fl.fleet.wait_until(lambda f: -fl.truth()[2] > 1.0, 20), "never took off"
    assert fl.wait_state("drone_1", "landing", 15), fl.log("drone_1")
    assert "low battery" in fl.log("drone_1")
    assert fl.fleet.states["drone_1"].battery_remaining_frac < 0.2
    assert fl.wait_state("drone_1", "landed", 30), fl.log("drone_1")
    assert -fl.truth()[2] < 0.3


def test_agent_holds_when_another_drone_comes_too_close(flight):
    fl = flight(1)
    fl.start_agent(0)
    _hover(fl)
    home = fl.truth()
    center = (home[0] + 4.0, home[1], 0.0)
    plan = make_orbit_plan(["drone_1"], center, radius_m=4.0, altitude_m=4.0, angular_speed_rad_s=0.3,
                           min_separation_m=3.0)
    fl.fleet.send_plan(plan)
    assert fl.fleet.wait_acks(plan.plan_id, ["drone_1"], 5)["drone_1"].result == "accepted"
    assert fl.fleet.command("start", wait_s=10, expect=["drone_1"], results=("completed",))["drone_1"]
    time.sleep(3.0)
    assert fl.agent_state("drone_1") == "orbit"
    # an intruder (another fleet member's state) 1.5 m away
    key = keys.drone_key(fl.fleet_id, "drone_9", keys.STATE)
    t_end = time.monotonic() + 2.0
    while time.monotonic() < t_end:
        p = fl.fleet.states["drone_1"].position_ned_m
        st = VehicleState(header=VehicleState.make_header("drone_9"), position_ned_m=(p[0] + 1.5, p[1], p[2]),
                          velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0))
        fl.bus.publish(key, st)
        time.sleep(0.1)
    assert fl.wait_state("drone_1", "paused", 3), fl.log("drone_1")
    assert "separation: drone_9" in fl.log("drone_1")
    assert fl.fleet.wait_until(lambda f: f.states["drone_1"].flight_mode == "HOLD", 3)


def test_agent_resumes_offboard_after_a_stalled_stream(flight):
    """A frozen companion computer (SIGSTOP): the offboard-loss failsafe the agent configured (COM_OBL_RC_ACT =
    Hold) holds; once the agent runs again the vehicle is back in offboard (PX4 returns by itself when setpoints
    resume, or the agent switches back), the agent reports the autopilot's failsafe, and the orbit goes on."""
    import os

    fl = flight(1)
    proc = fl.start_agent(0)
    _hover(fl)
    home = fl.truth()
    plan = make_orbit_plan(["drone_1"], (home[0] + 4.0, home[1], 0.0), radius_m=4.0, altitude_m=4.0,
                           angular_speed_rad_s=0.3)
    fl.fleet.send_plan(plan)
    assert fl.fleet.wait_acks(plan.plan_id, ["drone_1"], 5)["drone_1"].result == "accepted"
    assert fl.fleet.command("start", wait_s=10, expect=["drone_1"], results=("completed",))["drone_1"]
    time.sleep(3.0)
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        assert fl.fleet.wait_until(lambda f: fl.world.vehicles[0].mode.name == "HOLD", 5), "no offboard failsafe"
    finally:
        os.kill(proc.pid, signal.SIGCONT)
    assert fl.fleet.wait_until(lambda f: fl.world.vehicles[0].mode.name == "OFFBOARD", 10), fl.log("drone_1")
    assert fl.fleet.wait_until(lambda f: "(offboard-loss failsafe after a setpoint stall)" in fl.log("drone_1"), 5), \
        fl.log("drone_1")
    assert fl.agent_state("drone_1") == "orbit"
