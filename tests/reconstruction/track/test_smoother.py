"""The offline smoother on synthetic flights with known truth: better than the causal filters, offsets
recovered up to the fleet-common component, robust to blunders and false alarms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from onboard.tracking.filter import CooperativeFilter, TrackerConfig
from reconstruction.track.smoother import Observation, SmootherConfig, SmootherError, smooth_track
from recon_track_scene import make_scene

IDS = ["drone_0", "drone_1", "drone_2"]


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))


def _common(scene, t_s):
    """(M, 3) the fleet-common offset at t_s (mean over the drones): unobservable, removed from every estimate."""
    return np.mean([scene.at(t_s, scene.bias[:, d]) for d in range(scene.bias.shape[1])], axis=0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=3)


@pytest.fixture(scope="module")
def smoothed(scene):
    return smooth_track(scene.measurements, IDS, SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5)))


def _onboard_filter_track(scene, drone_id):
    """The live onboard filter of one drone fed every drone's measurements in time order: causal estimates."""
    f = CooperativeFilter(drone_id, TrackerConfig(offset_sigma_m=1.0, offset_tau_s=60.0))
    t, p = [], []
    for m in scene.measurements:
        f.add(m)
        est = f.estimate()
        if est is not None:
            t.append(m.t_ns * 1e-9)
            p.append(est.position_ned_m)
    return np.array(t), np.array(p)


def test_smoothed_track_beats_the_causal_filters(scene, smoothed):
    tr = smoothed
    ts = tr.t_ns * 1e-9
    keep = ts > 3.0  # after the filters' start-up
    truth = scene.at(ts[keep], scene.person)
    common = _common(scene, ts[keep])
    err_s = _rms(tr.position_ned_m[keep] - truth - common)
    err_fwd = _rms(tr.filtered_position_ned_m[keep] - truth - common)
    onboard = []
    for d in IDS:
        t, p = _onboard_filter_track(scene, d)
        k = t > 3.0
        onboard.append(_rms(p[k] - scene.at(t[k], scene.person) - _common(scene, t[k])))
    print(f"fleet-frame RMSE: smoothed {err_s:.3f}, forward {err_fwd:.3f}, onboard {np.round(onboard, 3)}")
    assert err_s < 0.15, err_s
    assert err_s < 0.8 * err_fwd, (err_s, err_fwd)
    assert err_s < 0.7 * min(onboard), (err_s, onboard)


def test_offsets_recovered_up_to_the_common_component(scene, smoothed):
    tr = smoothed
    ts = tr.t_ns * 1e-9
    true_b = np.stack([scene.at(ts, scene.bias[:, d]) for d in range(3)], axis=1)  # (N, D, 3)
    rel_true = true_b - true_b.mean(axis=1, keepdims=True)
    rel_est = tr.offset_ned_m - tr.offset_ned_m.mean(axis=1, keepdims=True)
    before = _rms(rel_true.reshape(-1, 3))  # error of the reported positions relative to each other
    after = _rms((rel_est - rel_true).reshape(-1, 3))
    assert before > 0.5, before  # the scene has real offsets
    assert after < 0.25 * before and after < 0.2, (before, after)
    # the common component is decided by the zero-mean prior, not by the data
    assert np.linalg.norm(tr.offset_ned_m.mean(axis=(0, 1))) < 0.5


def test_common_offset_shifts_the_track_and_not_the_relative_offsets(scene, smoothed):
    shift = np.array([0.7, -0.4, 0.2])
    moved = [dataclasses.replace(m, position_ned_m=m.position_ned_m + shift) for m in scene.measurements]
    tr = smooth_track(moved, IDS, SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5)))
    rel = tr.offset_ned_m - tr.offset_ned_m.mean(axis=1, keepdims=True)
    rel0 = smoothed.offset_ned_m - smoothed.offset_ned_m.mean(axis=1, keepdims=True)
    assert np.max(np.abs(rel - rel0)) < 0.05
    # the shift goes mostly into the person track (the prior keeps the fleet-mean offset near zero)
    moved_by = (tr.position_ned_m - smoothed.position_ned_m).mean(axis=0)
    assert np.linalg.norm(moved_by - shift) < 0.5 * np.linalg.norm(shift), moved_by


def test_blunders_and_false_alarms_are_rejected(scene, smoothed):
    rng = np.random.default_rng(7)
    obs = [Observation.from_measurement(m, IDS.index(m.source_id)) for m in scene.measurements]
    bad = rng.random(len(obs)) < 0.1
    corrupted, false_alarms = [], 0
    for o, b in zip(obs, bad):
        if b:  # a blunder: the point 4-10 m off (wrong person, wrong box)
            off = rng.normal(0, 1, 3)
            off = off / np.linalg.norm(off) * rng.uniform(4, 10)
            corrupted.append(dataclasses.replace(o, z_ned_m=o.z_ned_m + off))
        else:
            corrupted.append(o)
            if rng.random() < 0.1:  # a false alarm beside the real box in the same image, higher score
                corrupted.append(dataclasses.replace(o, z_ned_m=o.z_ned_m + np.array([6.0, -3.0, 0.0]), score=2.0))
                false_alarms += 1
    assert bad.sum() > 30 and false_alarms > 20
    tr = smooth_track(corrupted, IDS, SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5)))
    ts = tr.t_ns * 1e-9
    keep = ts > 3.0
    truth = scene.at(ts[keep], scene.person)
    common = _common(scene, ts[keep])
    err_clean = _rms(smoothed.position_ned_m[keep] - truth - common)
    err = _rms(tr.position_ned_m[keep] - truth - common)
    assert err < 1.2 * err_clean + 0.02, (err, err_clean)
    # the blunder-only frames are rejected; frames with a false alarm keep the real box
    rejected = ~tr.accepted
    assert rejected.sum() >= 0.9 * bad.sum()
    assert rejected.sum() <= bad.sum() + 0.02 * len(obs)
    # no false-alarm alternative was chosen: every accepted frame's chosen point is within 2 m of the truth
    by_frame = {}
    for o in corrupted:
        by_frame.setdefault((o.t_ns, o.drone), []).append(o)
    for t_ns, d, c in zip(tr.frame_t_ns, tr.frame_drone, tr.frame_choice):
        if c < 0:
            continue
        o = by_frame[(int(t_ns), int(d))][c]
        truth_p = scene.at(np.array([t_ns * 1e-9]), scene.person)[0] + scene.at(np.array([t_ns * 1e-9]), scene.bias[:, d])[0]
        assert np.linalg.norm(o.z_ned_m - truth_p) < 2.0


def test_output_grid_and_interpolation(smoothed):
    tr = smoothed
    g = tr.t_ns[tr.on_grid]
    assert np.allclose(np.diff(g), 50_000_000)  # 20 Hz default
    assert np.all(np.diff(tr.t_ns) > 0)
    mid = (tr.t_ns[10] + tr.t_ns[11]) // 2
    p = tr.position_at(np.array([mid]))[0]
    assert np.all(np.minimum(tr.position_ned_m[10], tr.position_ned_m[11]) - 1e-9 <= p)
    assert tr.offset_at(1, tr.t_ns[:5]).shape == (5, 3)
    assert tr.covariance.shape == (len(tr.t_ns), 6, 6) and tr.offset_cov_m2.shape == (len(tr.t_ns), 3, 3, 3)


def test_bad_input_errors(scene):
    with pytest.raises(SmootherError, match="at least 2 frames"):
        smooth_track(scene.measurements[:1], IDS)
    with pytest.raises(SmootherError, match="not among the drones"):
        smooth_track(scene.measurements, ["drone_0"])
    with pytest.raises(SmootherError, match="offset_sigma_m"):
        smooth_track(scene.measurements, IDS, offset_sigma_m=np.zeros(3))
    with pytest.raises(SmootherError, match="gate_probability"):
        SmootherConfig(gate_probability=1.5)
    nan = dataclasses.replace(Observation.from_measurement(scene.measurements[0], 0), z_ned_m=np.full(3, np.nan))
    obs = [Observation.from_measurement(m, IDS.index(m.source_id)) for m in scene.measurements[:50]]
    tr = smooth_track([nan, *obs], IDS)  # non-finite observations are dropped, not fatal
    assert np.all(np.isfinite(tr.position_ned_m))


def test_blunders_at_the_start_do_not_capture_the_track(scene, smoothed):
    obs = [Observation.from_measurement(m, IDS.index(m.source_id)) for m in scene.measurements]
    for i in range(4):  # the first four images all see "the person" 8 m away (another person, a false alarm)
        obs[i] = dataclasses.replace(obs[i], z_ned_m=obs[i].z_ned_m + np.array([8.0, 0.0, 0.0]))
    tr = smooth_track(obs, IDS, SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5)))
    assert np.all(tr.frame_choice[:4] == -1), tr.frame_choice[:6]
    ts = tr.t_ns * 1e-9
    keep = ts > 1.0
    assert np.max(np.abs(tr.position_ned_m[keep] - smoothed.position_ned_m[keep])) < 0.1
