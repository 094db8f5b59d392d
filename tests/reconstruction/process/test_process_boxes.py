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
