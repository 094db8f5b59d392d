"""Pure parts of ``skycap process``: the two-model fusion per joint, the window plan and the stitching, the box
choice, the progress events and the atomic cache writes (no flight, no models)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from reconstruction.process.boxes import choose_boxes, detector_gaps
from reconstruction.process.cache import atomic_write_npz, make_key, read_npz
from reconstruction.process.events import Cancelled, StepProgress
from reconstruction.process.keypoints import fuse_keypoints
from reconstruction.process.windows import plan_windows, stitch


def _kp(xy_a, c_a, xy_b, c_b):
    kp = np.zeros((1, 2, 17, 3))
    kp[0, 0, :, :2], kp[0, 0, :, 2] = xy_a, c_a
    kp[0, 1, :, :2], kp[0, 1, :, 2] = xy_b, c_b
    return kp


def test_two_models_that_agree_are_averaged_by_confidence():
    box = np.array([[0.0, 0.0, 50.0, 100.0]])  # longer side 100 px: agreement within 15 px
    kp = _kp([100.0, 200.0], 0.9, [110.0, 200.0], 0.3)
    uv, conf = fuse_keypoints(kp, box)
    np.testing.assert_allclose(uv[0, :, 0], (0.9 * 100 + 0.3 * 110) / 1.2)
    np.testing.assert_allclose(conf[0], 0.9)


def test_two_models_that_disagree_keep_the_more_confident_at_a_lower_confidence():
    box = np.array([[0.0, 0.0, 50.0, 100.0]])
    kp = _kp([100.0, 200.0], 0.4, [160.0, 200.0], 0.9)  # 60 px apart
    uv, conf = fuse_keypoints(kp, box)
    np.testing.assert_allclose(uv[0, :, 0], 160.0)
    np.testing.assert_allclose(conf[0], 0.5)


def test_a_model_without_the_joint_leaves_it_to_the_other_and_none_gives_zero_confidence():
    box = np.array([[0.0, 0.0, 50.0, 100.0]])
    kp = _kp([100.0, 200.0], 0.8, [np.nan, np.nan], 0.0)
    kp[0, 0, 5, 2] = 0.0  # joint 5: neither model
    uv, conf = fuse_keypoints(kp, box)
    np.testing.assert_allclose(uv[0, 0], [100.0, 200.0])
    assert conf[0, 0] == pytest.approx(0.8) and conf[0, 5] == 0.0 and np.all(np.isfinite(uv))


def test_windows_cover_the_span_with_the_overlap_and_no_short_tail():
    s = 1_000_000_000
    w = plan_windows(0, 100 * s, 30.0, 5.0)
    assert w[0][0] == 0 and w[-1][1] == 100 * s
    for (a0, b0), (a1, b1) in zip(w, w[1:]):
        assert b0 - a1 >= 5 * s  # consecutive windows share at least the overlap
    assert all(b - a >= 30 * s for a, b in w)
    assert plan_windows(0, 20 * s, 30.0, 5.0) == [(0, 20 * s)]


def test_stitching_is_continuous_and_equals_each_window_away_from_the_overlaps():
    s = 1_000_000_000
    grid = np.arange(0, 40 * s + 1, s // 10)
    truth = np.sin(grid[:, None, None] * 1e-9) * np.ones((1, 17, 3))
    windows = plan_windows(int(grid[0]), int(grid[-1]), 20.0, 4.0)
    assert len(windows) == 2
    results = []
    for k, (a, b) in enumerate(windows):
        sel = (grid >= a) & (grid <= b)
        results.append((grid[sel], truth[sel] + (0.0 if k == 0 else 0.05)))  # window 2 is 5 cm off
    t, J = stitch(grid, windows, results, 4.0)
    np.testing.assert_array_equal(t, grid)
    a1, b0 = windows[1][0], windows[0][1]
    np.testing.assert_allclose(J[grid < a1], truth[grid < a1])
    np.testing.assert_allclose(J[grid > b0], truth[grid > b0] + 0.05)
    step = np.abs(np.diff(J - truth, axis=0)).max()
    assert step <= 0.05 / (4.0 * 10) + 1e-9  # the 5 cm are faded in over the 4 s overlap, 0.1 s per grid step


def test_a_failed_window_leaves_a_gap_not_a_jump():
    s = 1_000_000_000
    grid = np.arange(0, 60 * s + 1, s // 10)
    windows = plan_windows(0, int(grid[-1]), 20.0, 4.0)
    res = [(grid[(grid >= a) & (grid <= b)], np.zeros((int(np.sum((grid >= a) & (grid <= b))), 17, 3))) for a, b in windows]
    res[1] = None
    t, J = stitch(grid, windows, res, 4.0)
    assert len(t) < len(grid) and np.all(J == 0.0)


def test_box_choice_prefers_detections_near_the_track_then_the_track():
    t = np.array([1, 2, 3])
    dets = {1: np.array([[0, 0, 10, 20, 0.9], [100, 100, 120, 150, 0.8]]), 3: np.array([[5, 5, 9, 9, 0.1]])}
    track = {1: np.array([98.0, 95, 121, 150]), 2: np.array([50.0, 50, 70, 90]), 3: np.array([np.nan] * 4)}
    box, src = choose_boxes(t, 640, 360, dets, track, min_score=0.3)
    np.testing.assert_allclose(box[0], [100, 100, 20, 50])  # the detection on the track, not the higher score
    np.testing.assert_allclose(box[1], [50, 50, 20, 40])  # no detection: the track
    assert np.all(np.isnan(box[2])) and list(src) == [1, 2, 0]  # below min_score and no track: none


def test_progress_events_carry_an_eta_and_the_cancel_stops_at_the_next_report():
    events, cancel = [], threading.Event()
    sp = StepProgress("keypoints", events.append, cancel)
    sp(0, 10, "start")
    sp(5, 10, "half")
    assert events[-1].fraction == 0.5 and events[-1].eta_s is not None and events[-1].eta_s >= 0
    cancel.set()
    with pytest.raises(Cancelled, match="resume"):
        sp(6, 10)


def test_cache_writes_are_atomic_and_keys_follow_the_settings(tmp_path):
    p = atomic_write_npz(tmp_path / "a.npz", x=np.arange(3))
    assert read_npz(p)["x"].tolist() == [0, 1, 2]
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")]  # no temporary left
    p.write_bytes(b"garbage")
    assert read_npz(p) is None  # a damaged entry is recomputed, not trusted
    assert make_key("k", {"a": 1}) == make_key("k", {"a": 1}) != make_key("k", {"a": 2})


def test_the_detector_reruns_only_in_short_gaps_within_the_neighbours_boxes():
    t = np.arange(12) * 100_000_000  # 10 Hz
    src = np.array([0, 1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 1])  # a 0.3 s gap, then a 0.7 s one
    boxes = np.full((12, 4), np.nan)
    boxes[[1, 4, 11]] = [[100, 100, 20, 40], [110, 100, 20, 40], [300, 100, 20, 40]]
    frames, rois = detector_gaps(t, boxes, src, max_gap_s=0.5, width_px=640, height_px=360)
    assert frames.tolist() == [2, 3]  # not before the first box, not in the long gap
    x, y, w, h = rois[2]
    assert x <= 100 and x + w >= 130 and y <= 100 and y + h >= 140 and w == pytest.approx(60.0)
