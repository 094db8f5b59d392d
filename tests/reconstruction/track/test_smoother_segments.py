"""The offline smoother in overlapping segments (SmootherConfig.segment_s): the same track as the whole-flight
smoother within a small tolerance, no jump at the seams, and working memory that does not grow with the flight."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from reconstruction.track.smoother import Observation, SmootherConfig, SmootherError, smooth_track
from recon_track_scene import make_scene

IDS = ["drone_0", "drone_1", "drone_2"]
WHOLE = SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5), segment_s=0.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(seed=7, duration_s=36.0, rate_hz=5.0)


@pytest.fixture(scope="module")
def whole(scene):
    return smooth_track(scene.measurements, IDS, WHOLE)


@pytest.fixture(scope="module")
def segmented(scene):
    return smooth_track(scene.measurements, IDS, dataclasses.replace(WHOLE, segment_s=10.0, segment_overlap_s=8.0))


def test_segments_equal_the_whole_flight_smoother(scene, whole, segmented):
    assert whole.segments == 1 and segmented.segments == 4
    np.testing.assert_array_equal(segmented.t_ns, whole.t_ns)
    np.testing.assert_array_equal(segmented.on_grid, whole.on_grid)
    dp = np.linalg.norm(segmented.position_ned_m - whole.position_ned_m, axis=1)
    do = np.linalg.norm(segmented.offset_ned_m - whole.offset_ned_m, axis=2)
    dv = np.linalg.norm(segmented.velocity_ned_m_s - whole.velocity_ned_m_s, axis=1)
    # GPS-grade offsets (1 m, tau 60 s): the 8 s look-ahead of a segment sees less of their future than the whole
    assert dp.max() < 0.02 and do.max() < 0.02 and dv.max() < 0.02, (dp.max(), do.max(), dv.max())
    assert np.mean(segmented.frame_choice == whole.frame_choice) > 0.99
    np.testing.assert_allclose(segmented.covariance[:, :3, :3], whole.covariance[:, :3, :3], rtol=0.05, atol=1e-4)
    # and both far better than the detections are: the track is a real estimate, not a copy
    truth = scene.at(whole.t_ns * 1e-9, scene.person)
    common = np.mean([scene.at(whole.t_ns * 1e-9, scene.bias[:, d]) for d in range(3)], axis=0)
    assert np.sqrt(np.mean(np.sum((segmented.position_ned_m - truth - common) ** 2, axis=1))) < 0.5


def test_no_jump_at_the_seams(whole, segmented):
    t = segmented.t_ns
    step = np.linalg.norm(np.diff(segmented.position_ned_m, axis=0), axis=1) / np.diff(t * 1e-9)
    step_whole = np.linalg.norm(np.diff(whole.position_ned_m, axis=0), axis=1) / np.diff(t * 1e-9)
    seams = t[0] + np.array([10, 20, 30]) * 10**9
    near = np.zeros(len(step), bool)
    for s in seams:
        near |= np.abs(t[1:] - s) < 5 * 10**9  # the seam and the cross-fade after it
    # speeds across the seams: those of the whole-flight track there, within 2 cm/s
    assert np.max(np.abs(step[near] - step_whole[near])) < 0.02


def _long_observations(duration_s: float, rate_hz: float = 2.0, seed: int = 0) -> list[Observation]:
    """Two drones seeing a random-walking person at ``rate_hz``, their offsets drifting: plain numbers, no camera."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    person = np.cumsum(rng.normal(0, 0.1, (len(t), 3)), axis=0) * [1, 1, 0]
    out = []
    for d in range(2):
        bias = np.cumsum(rng.normal(0, 0.01, (len(t), 3)), axis=0)
        z = person + bias + rng.normal(0, 0.1, (len(t), 3))
        out += [Observation(int(round((tk + 0.01 * d) * 1e9)), d, z[k], 0.01 * np.eye(3)) for k, tk in enumerate(t)]
    return out


def test_each_run_of_the_smoother_is_bounded_whatever_the_flight_length(monkeypatch):
    """The RTS arrays (2 N n^2 floats, what grew with the flight) are only ever as long as a segment plus its
    overlap: the steps per run stay the same for a 3x longer flight; the whole-flight smoother's grow 3x."""
    import reconstruction.track.smoother as S

    runs: list[int] = []
    real = S._rts

    def counting(t_steps, *a, **k):
        runs.append(len(t_steps))
        return real(t_steps, *a, **k)

    monkeypatch.setattr(S, "_rts", counting)
    cfg = SmootherConfig(segment_s=20.0, segment_overlap_s=10.0, max_iterations=0, output_rate_hz=2.0)
    longest = {}
    for duration in (60.0, 180.0):
        runs.clear()
        tr = smooth_track(_long_observations(duration), ["a", "b"], cfg)
        longest[duration] = max(runs)
        assert tr.segments == int(np.ceil((tr.t_ns[-1] - tr.t_ns[0] + 1) / 20e9))
        assert len(tr.t_ns) > 2.5 * longest[duration] or duration < 100
    assert longest[180.0] <= longest[60.0] + 2
    runs.clear()
    whole = smooth_track(_long_observations(180.0), ["a", "b"], dataclasses.replace(cfg, segment_s=0.0))
    assert max(runs) == len(whole.t_ns) > 5 * longest[180.0]


def test_segment_settings_are_checked():
    with pytest.raises(SmootherError, match="segment"):
        SmootherConfig(segment_s=-1.0)
    with pytest.raises(SmootherError, match="segment"):
        SmootherConfig(segment_s=30.0, segment_overlap_s=0.0)
