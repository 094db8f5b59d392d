"""SIH truth -> SimTruth without PX4: HIL_STATE_QUATERNION bytes built with pymavlink are sent over loopback UDP
to :class:`simulator.px4_truth.SihTruthPublisher`, which must publish every vehicle in the world frame (down = 0
on SIH's ground, not at the origin's altitude), the fixed gimbal pitch and the person."""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from shared_msgs import SimTruth, keys
from simulator.px4_truth import SihTruthPublisher, px4_param_name_ok, sih_to_vehicle_truth
from simulator.px4_sitl import SihTruth
from skycap.frames import ned_to_geodetic
from tests.helpers.ports import free_udp_base

ORIGIN = (47.397742, 8.545594, 488.0)
GROUND_AMSL_M = 489.4  # SIH_LOC_H0


class FakeBus:
    def __init__(self):
        self.msgs: list[tuple[str, SimTruth]] = []
        self.lock = threading.Lock()

    def publish(self, key, msg):
        with self.lock:
            self.msgs.append((key, msg))


def _hil_bytes(mav, ned_world_m, q_wxyz=(1.0, 0.0, 0.0, 0.0), v_ned_m_s=(0.0, 0.0, 0.0)) -> bytes:
    """A HIL_STATE_QUATERNION for a vehicle at ``ned_world_m`` (down about the ground at GROUND_AMSL_M)."""
    lat, lon, _ = ned_to_geodetic(np.array([ned_world_m[0], ned_world_m[1], 0.0]), *ORIGIN)
    alt_amsl_m = GROUND_AMSL_M - ned_world_m[2]
    msg = mav.hil_state_quaternion_encode(
        0, list(q_wxyz), 0.0, 0.0, 0.0, int(round(float(lat) * 1e7)), int(round(float(lon) * 1e7)),
        int(round(alt_amsl_m * 1e3)), *(int(round(v * 100)) for v in v_ned_m_s), 0, 0, 0, 0, 0)
    return msg.pack(mav)


def _wait(pred, timeout_s=5.0):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_sih_truth_over_udp_becomes_world_frame_simtruth():
    base = free_udp_base(2)
    bus = FakeBus()
    pitch = math.radians(-35.0)
    pub = SihTruthPublisher(bus, "f", [base, base + 1], ORIGIN, rate_hz=50.0, gimbal_pitch_rad=pitch,
                            ground_alt_amsl_m=None, with_person=False)
    mav = mavlink2.MAVLink(None, srcSystem=7, srcComponent=1)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # vehicle 1 only: nothing may be published without every vehicle
        tx.sendto(_hil_bytes(mav, (6.5, 8.0, 0.0)), ("127.0.0.1", base))
        assert _wait(lambda: pub.reader.counts[0] >= 1)
        time.sleep(0.15)
        assert not bus.msgs, "a SimTruth without every vehicle was published"
        # vehicle 2 on the ground (its first sample fixes its ground altitude), then both in the air; SIH sends
        # w = -1 at rest: the quaternion must come out in the w >= 0 hemisphere, unchanged in meaning
        tx.sendto(_hil_bytes(mav, (-4.0, -2.0, 0.0), q_wxyz=(-1.0, 0.0, 0.0, 0.0)), ("127.0.0.1", base + 1))
        assert _wait(lambda: pub.reader.counts[1] >= 1)
        yaw = math.radians(90.0)
        q_yaw = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        tx.sendto(_hil_bytes(mav, (6.5, 8.0, -6.0), q_wxyz=q_yaw), ("127.0.0.1", base))
        tx.sendto(_hil_bytes(mav, (-4.0, -2.0, -3.0), v_ned_m_s=(0.0, 0.0, 0.0)), ("127.0.0.1", base + 1))
        assert _wait(lambda: pub.reader.counts == [2, 2])
        n_before = len(bus.msgs)
        assert _wait(lambda: len(bus.msgs) >= n_before + 3)
    finally:
        tx.close()
        pub.close()
    key, last = bus.msgs[-1]
    assert key == keys.sim_key("f", keys.TRUTH)
    assert isinstance(last, SimTruth)
    by_id = {v.drone_id: v for v in last.vehicles}
    assert set(by_id) == {"drone_1", "drone_2"}
    assert pub.ground_alt_amsl_m == pytest.approx([GROUND_AMSL_M, GROUND_AMSL_M], abs=1e-3)
    np.testing.assert_allclose(by_id["drone_1"].position_ned_m, (6.5, 8.0, -6.0), atol=0.02)
    np.testing.assert_allclose(by_id["drone_2"].position_ned_m, (-4.0, -2.0, -3.0), atol=0.02)
    np.testing.assert_allclose(by_id["drone_1"].q_world_body, q_yaw, atol=1e-6)
    assert by_id["drone_1"].gimbal_pitch_rad == pytest.approx(pitch) and by_id["drone_1"].gimbal_yaw_rad == 0.0
    assert len(last.person_joints_ned_m) == 51
    # the header's time is the publishing wall time (the agents' clock)
    assert abs(last.header.t_measurement_ns * 1e-9 - time.time()) < 5.0
    # published at the asked rate (resampled, not once per SIH sample)
    ts = np.array([m.header.t_measurement_ns for _, m in bus.msgs]) * 1e-9
    assert len(ts) >= 3 and np.median(np.diff(ts)) == pytest.approx(0.02, abs=0.01)


def test_conversion_uses_the_given_ground_and_extrapolates_with_velocity():
    # reader output: down about the origin's altitude (488 m); SIH's ground at 489.4 m -> on the ground: down 0
    s = SihTruth(t_received_ns=0, position_ned_m=np.array([1.0, 2.0, -1.4]), velocity_ned_m_s=np.array([2.0, 0.0, -1.0]),
                 q_world_body_wxyz=(1.0, 0.0, 0.0, 0.0), latitude_deg=0.0, longitude_deg=0.0, altitude_amsl_m=489.4)
    v = sih_to_vehicle_truth("drone_3", s, GROUND_AMSL_M, ORIGIN[2], -0.5)
    np.testing.assert_allclose(v.position_ned_m, (1.0, 2.0, 0.0), atol=1e-9)
    v = sih_to_vehicle_truth("drone_3", s, GROUND_AMSL_M, ORIGIN[2], -0.5, dt_s=0.04)
    np.testing.assert_allclose(v.position_ned_m, (1.08, 2.0, -0.04), atol=1e-9)
    assert v.drone_id == "drone_3" and v.gimbal_pitch_rad == -0.5


def test_px4_param_names():
    assert px4_param_name_ok("COM_OBL_RC_ACT") and px4_param_name_ok("MPC_XY_VEL_MAX")
    assert not px4_param_name_ok("com_obl_rc_act") and not px4_param_name_ok("A" * 17) and not px4_param_name_ok("")
