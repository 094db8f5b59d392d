import math

import numpy as np

from onboard.formation.mpc import FormationMPC, MpcConfig, SharedPlan
from onboard.formation.source import FormationSource


def test_formation_source_follows_target_and_holds():
    src = FormationSource(FormationMPC("d0", MpcConfig(max_solve_time_s=1.0)), slot_angle_rad=math.pi / 2)
    p, v = np.array([0.0, 0.0, -8.0]), np.zeros(3)
    # no target: hold where it is
    sp = src.update(1000.0, p, v, 0.3)
    np.testing.assert_array_equal(sp.position_ned_m, p)
    assert src.last_plan is None
    # start right above the person (inside the keep-out): it must leave toward its slot
    src.set_target([0.0, 0.0, -0.85], [0.0, 0.0, 0.0])
    src.set_teammate_plan(SharedPlan("d1", int(1000e9), 0.1, np.tile([[-8.0, 0.0, -8.0]], (16, 1))))
    src.set_teammate_plan(SharedPlan("d2", int(990e9), 0.1, np.tile([[0.0, 3.0, -8.0]], (16, 1))))  # stale: dropped
    src.set_teammate_state("d3", int(1000e9), [5.0, 5.0, -8.0], [0.0, 0.0, 0.0])  # known by state only
    t = 1000.0
    for _ in range(60):
        sp = src.update(t, p, v, 0.0)
        p, v = sp.position_ned_m, sp.velocity_ned_m_s
        t += 0.1
    np.testing.assert_allclose(p, [0.0, 8.0, -8.0], atol=0.2)
    assert src.mpc.fallback_count == 0
    assert src.last_result.min_teammate_distance_m == np.inf  # d3's state expired after plan_timeout_s
    assert abs(sp.yaw_rad + math.pi / 2) < 0.05 and sp.gimbal_pitch_rad < 0
    assert src.last_plan is not None and src.last_plan.drone_id == "d0" and src.last_plan.positions_ned_m.shape == (16, 3)
    src.hold([1.0, 2.0, -8.0])
    sp = src.update(t, p, v, 0.0)
    np.testing.assert_array_equal(sp.position_ned_m, [1.0, 2.0, -8.0])
    assert abs(sp.yaw_rad - math.atan2(-2.0, -1.0)) < 1e-9
