"""The boxes step on a real recorded flight: the smoother's one read of the recordings gives the box choice the same
detections as reading them again, and the same boxes."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def test_the_smoothers_read_serves_the_box_choice(recorded_flight):
    from flightdata.folder import FlightFolder
    from reconstruction.process.boxes import TrackBoxes, compute_boxes, read_detections, smoother_boxes
    from reconstruction.process.config import BoxesConfig
    from reconstruction.process.frames import frame_table

    flight = FlightFolder(recorded_flight)
    logs = flight.drone_logs()
    track = smoother_boxes(flight, None)
    assert sorted(track) == sorted(logs)
    cfg = BoxesConfig(detector_fill=False)
    for d, tb in track.items():
        assert isinstance(tb, TrackBoxes) and len(tb) > 10
        topic, dets = read_detections(logs[d], d)
        assert tb.topic == topic and sorted(tb.detections) == sorted(dets)
        for t, rows in dets.items():
            np.testing.assert_array_equal(tb.detections[t], rows)
        frames = frame_table(logs[d])
        tick = lambda *a: None  # noqa: E731
        got = compute_boxes([], d, frames, cfg, tb, None, tick)  # no recordings: everything from the smoother's read
        want = compute_boxes(logs[d], d, frames, cfg, dict(tb), None, tick)  # a plain dict: read again
        np.testing.assert_array_equal(got["source"], want["source"])
        np.testing.assert_array_equal(got["box_xywh"], want["box_xywh"])
        assert np.sum(got["source"] == 1) > 10  # recorded detections were chosen, not only the track


def test_boxes_in_threads_equal_one_thread_and_hit_the_same_cache(recorded_flight, tmp_path):
    """``boxes.workers``: the drones' box choice and detector re-runs in threads give the one-thread boxes, and the
    number of threads is not part of the cache key (a flight boxed with 1 thread is a cache hit with 2)."""
    from flightdata.folder import FlightFolder
    from reconstruction.process import pipeline
    from reconstruction.process.cache import file_identity
    from reconstruction.process.config import ProcessConfig

    flight = FlightFolder(recorded_flight)

    def run(workers, cache_dir):
        logs = flight.drone_logs()
        drones = list(logs)
        ident = {d: [file_identity(s.path) for s in logs[d]] for d in drones}
        cfg = ProcessConfig()
        cfg.boxes.workers = workers
        steps: dict = {}

        def step_dir(step):
            p = cache_dir / step
            p.mkdir(parents=True, exist_ok=True)
            return p

        out = pipeline._boxes_step(flight, logs, drones, {}, ident, cfg.validate(), step_dir, None, None, steps)
        return out, steps["boxes"]

    one, s1 = run(1, tmp_path / "a")
    two, s2 = run(2, tmp_path / "b")
    assert not s1["cached"] and not s2["cached"] and s2["workers"] == 2
    assert list(one) == list(two) == list(flight.drone_logs())
    for d in one:
        for k in ("t_ns", "box_xywh", "source"):
            np.testing.assert_array_equal(one[d][k], two[d][k])
        assert str(one[d]["key"]) == str(two[d]["key"])
    again, s3 = run(2, tmp_path / "a")
    assert s3["cached"] and s3["workers"] == 0
    with pytest.raises(Exception, match="boxes.workers"):
        cfg = ProcessConfig()
        cfg.boxes.workers = 0
        cfg.validate()
