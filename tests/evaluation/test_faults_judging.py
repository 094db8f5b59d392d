"""The fault suite's judging (evaluation.faults) on synthetic truth and log times: no files."""

from __future__ import annotations

import numpy as np

from evaluation.faults import (SafetyLimits, gaps_s, geofence_excursions, judge_safety, min_separation_m,
                               recording_lost_s, touchdowns_s)


def _orbit(t_s, phase, radius_m=8.0, alt_m=6.0):
    a = 0.15 * t_s + phase
    return np.stack([radius_m * np.cos(a), radius_m * np.sin(a), -alt_m * np.ones_like(t_s)], axis=-1)


def test_min_separation_of_two_opposite_drones_is_the_diameter():
    t = np.linspace(0, 10, 101)
    pos = np.stack([_orbit(t, 0.0), _orbit(t, np.pi)])
    assert abs(min_separation_m(pos) - 16.0) < 1e-6
    assert min_separation_m(pos[:1]) == float("inf")


def test_geofence_counts_the_seconds_outside():
    t = np.arange(0, 10.0, 0.1)
    p = _orbit(t, 0.0)
    p[50:70, 0] = 25.0  # 2 s beyond a 20 m fence
    out = geofence_excursions(t, p[None], [0, 0, 0], 20.0, 15.0)
    assert abs(out[0] - 2.0) < 1e-6
    p2 = _orbit(t, 0.0, alt_m=16.0)
    assert geofence_excursions(t, p2[None], [0, 0, 0], 20.0, 15.0)[0] > 9.8


def test_touchdowns_count_each_landing_once():
    t = np.arange(0, 30, 0.1)
    alt = np.where((t > 2) & (t < 12), 6.0, 0.0) + np.where((t > 15) & (t < 25), 6.0, 0.0)
    alt[(t > 12.5) & (t < 13)] = 0.5  # a bounce below the airborne height does not count twice
    downs = touchdowns_s(t, alt)
    assert len(downs) == 2 and abs(downs[0] - 12.0) < 0.11 and abs(downs[1] - 25.0) < 0.11


def test_gaps_and_lost_recording_across_a_restart():
    state = np.concatenate([np.arange(0, 10, 0.02), np.arange(11.3, 20, 0.02)])  # agent down 10 .. 11.3
    camera = np.concatenate([np.arange(0, 10, 0.1), np.arange(11.4, 20, 0.1)])
    lost, g = recording_lost_s([state, camera], 0.0, 20.0, 0.5)
    assert len(g) == 1 and abs(lost - 1.32) < 0.03, (lost, g)
    # telemetry missing for 3 s while the camera still records: no recording lost
    state2 = np.concatenate([np.arange(0, 5, 0.02), np.arange(8, 20, 0.02)])
    lost2, _ = recording_lost_s([state2, np.arange(0, 20, 0.1)], 0.0, 20.0, 0.5)
    assert lost2 == 0.0
    assert abs(sum(b - a for a, b in gaps_s(state2, 0, 20, 0.5)) - 3.0) < 0.03
    # nothing at all recorded: the whole window is lost
    assert recording_lost_s([np.zeros(0)], 0.0, 5.0)[0] == 5.0


def test_safety_verdict_landing_by_policy_vs_uncommanded():
    t = np.arange(0, 40, 0.1)
    p1, p2 = _orbit(t, 0.0), _orbit(t, np.pi)
    p2[t > 20, 2] = 0.0  # drone_2 down at 20 s, before the final land at 30 s
    pos = np.stack([p1, p2])
    ids = ["drone_1", "drone_2"]
    v = judge_safety(t, pos, ids, SafetyLimits(min_separation_m=3.0), t_final_land_s=30.0)
    assert v["safe"] is False and v["uncommanded_landings"] == ["drone_2"], v
    v = judge_safety(t, pos, ids, SafetyLimits(min_separation_m=3.0, landing_by_policy=["drone_2"]), 30.0)
    assert v["safe"] is True and not v["unsafe_because"], v
    # a landing after the final land command is commanded
    assert judge_safety(t, pos, ids, SafetyLimits(), t_final_land_s=15.0)["safe"] is True
    # too close
    close = np.stack([p1, p1 + np.array([2.0, 0, 0])])
    v = judge_safety(t, close, ids, SafetyLimits(min_separation_m=3.0), 30.0)
    assert v["safe"] is False and "separation" in v["unsafe_because"][0]


def test_a_restart_seam_counts_however_short():
    from evaluation.faults import lost_with_seams_s, seams_s

    f1 = np.arange(0, 10.0, 0.02)
    f2 = np.arange(10.3, 20, 0.02)  # 0.3 s between the files: under the 0.5 s gap threshold
    lost, g = recording_lost_s([np.concatenate([f1, f2])], 0.0, 20.0, 0.5)
    assert lost == 0.0 and not g
    seams = seams_s([f1, np.zeros(0), f2])
    assert len(seams) == 1 and abs(seams[0][0] - 9.98) < 1e-9 and abs(seams[0][1] - 10.3) < 1e-9
    assert abs(lost_with_seams_s(g, seams, 0.0, 20.0) - 0.32) < 1e-6
    # a seam inside a long gap is not counted twice
    f3 = np.arange(12.0, 20, 0.02)
    lost3, g3 = recording_lost_s([np.concatenate([f1, f3])], 0.0, 20.0, 0.5)
    assert abs(lost_with_seams_s(g3, seams_s([f1, f3]), 0.0, 20.0) - lost3) < 1e-9
