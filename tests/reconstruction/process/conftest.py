"""A short real flight for ``skycap process``: recorded once per test session by ``skycap demo`` (2 drones, small
camera images at 5 Hz, a short orbit), then processed once with the real ONNX models -- cancelled in the keypoint
step, resumed, and run again all from the cache -- with the model, box and fit calls counted."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from tests.helpers.ports import free_tcp_port, free_udp_base

from process_helpers import copy_flight, make_config  # noqa: E402


@pytest.fixture(scope="session")
def recorded_flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("process_flight") / "flight"
    cmd = [sys.executable, "-m", "apps.cli", "demo", "--drones", "2", "--duration", "8", "--out", str(out),
           "--set", f"zenoh_endpoint=\"tcp/127.0.0.1:{free_tcp_port()}\"", "--set", f"mavlink_base={free_udp_base(2)}",
           "--set", "fleet=\"processtest\"", "--set", "reconstruct=false", "--set", "settle_s=2",
           "--set", 'camera_set=["camera.width_px=320", "camera.height_px=180", "camera.rate_hz=5"]']
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    return out


class Counter:
    def __init__(self):
        self.crops = 0
        self.fits = 0
        self.boxes = 0


@pytest.fixture(scope="session")
def processed(recorded_flight, tmp_path_factory):
    """{"flight", "runs": [(result or exception, Counter, events)]}: run 1 cancelled in the keypoint step after
    its first chunks, run 2 resumed, run 3 from the cache."""
    import reconstruction.process.pipeline as pipeline
    from reconstruction.keypoints import detectors
    from reconstruction.process import Cancelled, process

    flight = copy_flight(recorded_flight, tmp_path_factory.mktemp("processed") / "flight")
    runs = []
    with pytest.MonkeyPatch.context() as mp:
        counter = {"c": Counter()}

        def counting(fn, field, n=lambda a: 1):
            def wrapper(*a, **k):
                setattr(counter["c"], field, getattr(counter["c"], field) + n(a))
                return fn(*a, **k)
            return wrapper

        mp.setattr(detectors.KeypointModel, "predict", counting(detectors.KeypointModel.predict, "crops", lambda a: len(a[1])))
        mp.setattr(detectors.BlazePose, "predict", counting(detectors.BlazePose.predict, "crops", lambda a: len(a[1])))
        mp.setattr(pipeline, "fit_capture", counting(pipeline.fit_capture, "fits"))
        mp.setattr(pipeline, "compute_boxes", counting(pipeline.compute_boxes, "boxes"))
        for run in range(3):
            counter["c"] = Counter()
            events, cancel = [], threading.Event()

            def on_progress(ev, events=events, cancel=cancel, run=run):
                events.append(ev)
                if run == 0 and ev.step == "keypoints" and ev.fraction >= 0.3:
                    cancel.set()

            try:
                res = process(flight, make_config(), progress=on_progress, cancel=cancel)
            except Cancelled as e:
                res = e
            runs.append((res, counter["c"], events))
    return {"flight": flight, "runs": runs}
