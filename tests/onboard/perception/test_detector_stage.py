"""The real detector in the onboard loop (onboard.detector.stage) on frames rendered by the simulator."""

from __future__ import annotations

import threading

import pytest

from onboard.detector.stage import DetectionWorker, FrameDecodeError, decode_frame, detections_from_frame
from shared_msgs import decode, encode
from shared_msgs.messages import CameraFrame

render = pytest.importorskip("simulator.scene.render")


@pytest.fixture(scope="module")
def rendered(sim_frame):
    """(CameraFrame of the simulator-rendered frame as the camera node sends it, GT box)."""
    fr = sim_frame
    H, W = fr.image.shape[:2]
    msg = CameraFrame(header=CameraFrame.make_header("drone_1", 123_456_789, 7), camera_id="drone_1/cam0", frame_index=7,
                      encoding="jpeg", width_px=W, height_px=H, data=render.encode_jpeg(fr.image),
                      T_world_cam=tuple(float(v) for v in fr.T_world_cam.reshape(-1)))
    return decode(encode(msg)), fr.gt.box_px


def _iou(a, b) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    return iw * ih / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - iw * ih)


def test_detections_from_a_rendered_frame_in_the_planned_roi(detector, rendered):
    frame, g = rendered
    roi = (g[0] - 80, g[1] - 80, g[2] - g[0] + 160, g[3] - g[1] + 160)
    det = detections_from_frame(detector, frame, "roi", roi, sender_id="drone_1", seq=3)
    assert det.header.t_measurement_ns == frame.header.t_measurement_ns and det.header.sender_id == "drone_1"
    assert det.T_world_cam == frame.T_world_cam and det.frame_index == 7 and det.mode == "roi"
    assert det.detector == detector.name
    x, y, w, h = det.roi_px
    assert x <= g[0] and y <= g[1] and x + w >= g[2] and y + h >= g[3], "roi_px reports the region searched"
    assert det.boxes, "the rendered person is found in its ROI"
    b = det.boxes[0]
    assert _iou((b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px), g) > 0.6
    assert min(b.var_x_min_px2, b.var_y_min_px2, b.var_x_max_px2, b.var_y_max_px2) > 0
    assert decode(encode(det)) == det  # a valid wire message


def test_roi_outside_the_image_falls_back_to_tiles(detector, rendered):
    frame, g = rendered
    det = detections_from_frame(detector, frame, "roi", (-5000.0, -5000.0, 100.0, 100.0), sender_id="drone_1")
    assert det.mode == "tiles" and det.roi_px == (0.0, 0.0, 0.0, 0.0)
    assert det.boxes and _iou((det.boxes[0].x_min_px, det.boxes[0].y_min_px, det.boxes[0].x_max_px, det.boxes[0].y_max_px), g) > 0.5


def test_corrupt_frame_is_a_clear_error(rendered):
    import msgspec

    frame, _ = rendered
    with pytest.raises(FrameDecodeError, match="do not decode"):
        decode_frame(msgspec.structs.replace(frame, data=frame.data[:100]))
    with pytest.raises(FrameDecodeError, match="announced"):
        decode_frame(msgspec.structs.replace(frame, width_px=frame.width_px + 2))


def test_worker_drops_frames_while_busy_and_delivers_results(detector, rendered):
    frame, g = rendered
    got, done = [], threading.Event()
    gate = threading.Event()

    def deliver(det, context):
        assert context == "plan-7"
        got.append(det)
        done.set()

    w = DetectionWorker("drone_1", detector, deliver)
    try:
        # hold the worker busy on a first job so that the next submissions are dropped, not queued
        w._pool.submit(gate.wait)
        roi = (g[0] - 80, g[1] - 80, g[2] - g[0] + 160, g[3] - g[1] + 160)
        assert w.submit(frame, "roi", roi, context="plan-7")
        assert not w.submit(frame, "roi", roi) and not w.submit(frame, "roi", roi)
        gate.set()
        assert done.wait(30.0)
        assert w.counts["dropped_busy"] == 2 and w.counts["done"] == 1 and len(got) == 1
        assert got[0].boxes
        # idle again: the next frame is taken; a frame without a pose is refused and counted
        done.clear()
        assert w.submit(frame, "roi", roi, context="plan-7") and done.wait(30.0)
        import msgspec

        assert not w.submit(msgspec.structs.replace(frame, T_world_cam=()))
        assert w.counts["failed"] == 1
        st = w.stats()
        assert st["done"] == 2 and st["infer_ms_median"] > 0
    finally:
        w.close()
    assert not w.submit(frame, "roi", None)
