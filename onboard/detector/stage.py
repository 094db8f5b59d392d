"""The real person detector in the onboard loop: camera frame + the tracker's region of interest -> Detections.

    worker = DetectionWorker(drone_id, PersonDetector(), deliver=lambda det, context: ...)  # called per result
    worker.submit(frame, "roi", roi_xywh, context=plan)  # non-blocking; False (and counted) when still busy
    worker.close()

The detector (NanoDet on onnxruntime, :mod:`onboard.detector.detector`) takes ~20-90 ms per frame on one
CPU thread, longer than the agent's control tick, so it runs on its own worker thread (onnxruntime releases
the GIL while it infers) and the newest frame wins: a frame that arrives while the detector is busy is
dropped and counted, never queued (a queue would only add latency to every later frame). The region of
interest is planned by the caller *before* detection, from the tracking filter's prediction at the frame's
capture time (:func:`onboard.tracking.roi.plan_detection`), and the region actually searched is what the
Detections message reports in ``roi_px``.

:func:`detections_from_frame` is the pure part (decode, detect in the planned mode, build the message) and is
what the tests exercise on frames rendered by the simulator.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from onboard.detector.detector import DetectorInputError, PersonDetector
from shared_msgs.messages import CameraFrame, Detections

__all__ = ["DetectionWorker", "FrameDecodeError", "decode_frame", "detections_from_frame"]

log = logging.getLogger(__name__)


class FrameDecodeError(DetectorInputError):
    """A camera frame whose bytes do not decode to the size it announces."""


def decode_frame(frame: CameraFrame) -> np.ndarray:
    """(H, W, 3) BGR uint8 image of a :class:`CameraFrame` (JPEG or PNG)."""
    img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise FrameDecodeError(f"frame {frame.frame_index} of {frame.camera_id}: {len(frame.data)} bytes do not decode as {frame.encoding}")
    if img.shape[:2] != (frame.height_px, frame.width_px):
        raise FrameDecodeError(f"frame {frame.frame_index} of {frame.camera_id} decodes to {img.shape[1]}x{img.shape[0]}, "
                               f"announced {frame.width_px}x{frame.height_px}")
    return img


def detections_from_frame(
    detector: PersonDetector,
    frame: CameraFrame,
    mode: str = "roi",
    roi_xywh: tuple[float, float, float, float] | None = None,
    *,
    sender_id: str,
    seq: int = 0,
) -> Detections:
    """Run the detector on one frame in ``mode`` ("roi" with ``roi_xywh``, "tiles" or "full").

    The message's ``header.t_measurement_ns`` is the frame's capture time and ``T_world_cam`` the frame's
    camera pose at capture (the vehicle's estimate); ``roi_px`` is the region searched ((0, 0, 0, 0) = whole
    frame). A ROI that lies outside the image falls back to tiles (the person is probably not where the
    filter predicts).
    """
    img = decode_frame(frame)
    try:
        res = detector.detect(img, mode=mode, roi_xywh=roi_xywh)
    except DetectorInputError:
        if mode != "roi":
            raise
        res = detector.detect(img, mode="tiles")
    roi = res.roi_px if res.mode == "roi" else (0.0, 0.0, 0.0, 0.0)
    return Detections(
        header=Detections.make_header(sender_id, frame.header.t_measurement_ns, seq),
        camera_id=frame.camera_id,
        frame_index=frame.frame_index,
        detector=detector.name,
        mode=res.mode,
        boxes=[d.to_msg() for d in res.detections],
        width_px=frame.width_px,
        height_px=frame.height_px,
        T_world_cam=tuple(frame.T_world_cam),
        roi_px=tuple(float(v) for v in roi),
    )


class DetectionWorker:
    """The detector on one worker thread, newest frame wins (see the module doc).

    deliver(det, context) is called on the worker thread with each result and the ``context`` given to
    :meth:`submit` (e.g. the detector plan); an agent wraps it to hop back to its event loop. Counters: ``submitted``, ``dropped_busy`` (arrived while busy), ``failed`` (bad frame, model error),
    ``done``; ``infer_ms`` keeps the last 1000 detection times.
    """

    def __init__(self, drone_id: str, detector: PersonDetector, deliver: Callable[[Detections, object], None]):
        self.drone_id = drone_id
        self.detector = detector
        self.deliver = deliver
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"detector-{drone_id}")
        self._busy = threading.Lock()
        self._seq = 0
        self.counts = {"submitted": 0, "dropped_busy": 0, "failed": 0, "done": 0}
        self.infer_ms: list[float] = []
        self._closed = False

    def submit(self, frame: CameraFrame, mode: str = "roi", roi_xywh: tuple[float, float, float, float] | None = None,
               context: object = None) -> bool:
        """Start detection on ``frame`` unless busy (then the frame is dropped: False)."""
        if self._closed:
            return False
        if len(frame.T_world_cam) != 16:
            self.counts["failed"] += 1
            log.debug("%s: frame %d has no camera pose; not detected", self.drone_id, frame.frame_index)
            return False
        if not self._busy.acquire(blocking=False):
            self.counts["dropped_busy"] += 1
            return False
        self.counts["submitted"] += 1
        self._seq += 1
        try:
            self._pool.submit(self._run, frame, mode, roi_xywh, self._seq, context)
        except RuntimeError:  # pool shut down meanwhile
            self._busy.release()
            return False
        return True

    def _run(self, frame: CameraFrame, mode: str, roi_xywh, seq: int, context: object) -> None:
        try:
            t0 = time.perf_counter()
            det = detections_from_frame(self.detector, frame, mode, roi_xywh, sender_id=self.drone_id, seq=seq)
            self.infer_ms.append(1e3 * (time.perf_counter() - t0))
            del self.infer_ms[:-1000]
        except Exception as e:
            self.counts["failed"] += 1
            log.warning("%s: detector failed on frame %d: %s", self.drone_id, frame.frame_index, e)
            return
        finally:
            self._busy.release()
        self.counts["done"] += 1
        try:
            self.deliver(det, context)
        except Exception:
            log.exception("%s: delivering detections failed", self.drone_id)

    def stats(self) -> dict:
        ms = np.asarray(self.infer_ms, dtype=float)
        return {**self.counts, "detector": self.detector.name,
                "infer_ms_median": round(float(np.median(ms)), 2) if len(ms) else None,
                "infer_ms_p95": round(float(np.percentile(ms, 95)), 2) if len(ms) else None}

    def close(self, wait: bool = True) -> None:
        self._closed = True
        self._pool.shutdown(wait=wait, cancel_futures=True)
