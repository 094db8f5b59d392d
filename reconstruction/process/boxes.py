"""The ``boxes`` step: the person's box in every recorded frame of one drone.

Per frame, in order of preference:

1. ``detection``: the drone's recorded person detections (topic ``detections``, the onboard ONNX detector; on
   flights without it the simulator's ``sim/detections``), at or above ``min_score``; among several boxes the one
   that overlaps the offline smoother's projected person most (else the highest score);
2. ``track``: the offline smoother's person (:func:`reconstruction.track.flight.refine_recordings`, all drones'
   detections smoothed together) projected into the frame, where the frame has no detection;
3. ``detector``: the ONNX person detector (:class:`onboard.detector.detector.PersonDetector`) re-run on the
   recorded image where neither gave a box, in gaps of at most ``detector_max_gap_s`` between boxed frames, within
   the neighbours' boxes (:func:`detector_gaps`; a longer gap -- take-off, landing -- is a camera that does not see
   the person);
4. none (NaN box): the frame is left out of the keypoint step.

:func:`choose_boxes` is the pure choice; :func:`compute_boxes` does the I/O.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from flightdata.flightlog import FlightLog
from flightdata.folder import Sortie
from reconstruction.process.config import BoxesConfig
from reconstruction.process.frames import FrameTable, iter_images
from shared_msgs.messages import Detections

log = logging.getLogger(__name__)

__all__ = ["SOURCE_NAMES", "TrackBoxes", "choose_boxes", "compute_boxes", "read_detections", "iou_xyxy", "smoother_boxes"]

#: box source codes in the cache: 0 none, 1 recorded detection, 2 smoother track, 3 detector re-run
SOURCE_NAMES = ("none", "detection", "track", "detector")


def iou_xyxy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes a (N, 4) with one box b (4,), x_min, y_min, x_max, y_max."""
    a = np.atleast_2d(a)
    x0, y0 = np.maximum(a[:, 0], b[0]), np.maximum(a[:, 1], b[1])
    x1, y1 = np.minimum(a[:, 2], b[2]), np.minimum(a[:, 3], b[3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    ua = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return np.where(ua > 0, inter / np.where(ua > 0, ua, 1), 0.0)


def _person_rows(d: Detections) -> np.ndarray:
    rows = [(b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px, b.score) for b in d.boxes if b.label == "person"]
    return np.asarray(rows, dtype=float).reshape(-1, 5)


def read_detections(sorties: Sequence[Sortie], drone_id: str) -> tuple[str, dict[int, np.ndarray]]:
    """(topic used, {capture time ns: boxes (N, 5) x_min, y_min, x_max, y_max, score}) of the drone's own person
    detections: ``detections`` when recorded, else ``sim/detections``."""
    found: dict[str, dict[int, np.ndarray]] = {"detections": {}, "sim/detections": {}}
    for s in sorties:
        for m in FlightLog(s.path).messages(list(found)):
            d = m.msg
            if not isinstance(d, Detections) or d.header.sender_id != drone_id:
                continue
            found[m.topic][int(d.header.t_measurement_ns)] = _person_rows(d)
    topic = "detections" if found["detections"] else "sim/detections"
    return topic, found[topic]


class TrackBoxes(dict):
    """{capture time ns: the smoothed person's box (x_min, y_min, x_max, y_max)} of one drone, with the drone's
    person detections the smoother read (``topic``, ``detections`` as :func:`read_detections` returns them), so
    that :func:`compute_boxes` does not read the recording again."""

    def __init__(self, boxes: dict[int, np.ndarray], topic: str, detections: dict[int, np.ndarray]):
        super().__init__(boxes)
        self.topic = topic
        self.detections = detections


def choose_boxes(t_ns: np.ndarray, width_px: int, height_px: int, detections: dict[int, np.ndarray],
                 track_boxes: dict[int, np.ndarray] | None, min_score: float) -> tuple[np.ndarray, np.ndarray]:
    """Pure choice of one box per frame (see the module doc, steps 1-2). Returns (box_xywh (F, 4), NaN where
    none; source (F,) int8 codes of :data:`SOURCE_NAMES`)."""
    F = len(t_ns)
    out = np.full((F, 4), np.nan)
    src = np.zeros(F, dtype=np.int8)
    track_boxes = track_boxes or {}
    for i, t in enumerate(np.asarray(t_ns, dtype=np.int64).tolist()):
        cand = detections.get(t)
        tb = track_boxes.get(t)
        tb = tb if tb is not None and np.all(np.isfinite(tb)) else None
        if cand is not None and len(cand):
            cand = cand[cand[:, 4] >= min_score]
        if cand is not None and len(cand):
            k = int(np.argmax(cand[:, 4]))
            if tb is not None and len(cand) > 1:
                ov = iou_xyxy(cand[:, :4], tb)
                if ov.max() > 0.05:
                    k = int(np.argmax(ov))
            b = cand[k, :4]
            src[i] = 1
        elif tb is not None:
            b = np.array([max(tb[0], 0.0), max(tb[1], 0.0), min(tb[2], width_px - 1.0), min(tb[3], height_px - 1.0)])
            if b[2] - b[0] < 4 or b[3] - b[1] < 4:  # outside the image
                continue
            src[i] = 2
        else:
            continue
        out[i] = (b[0], b[1], b[2] - b[0], b[3] - b[1])
    return out, src


def detector_gaps(t_ns: np.ndarray, boxes: np.ndarray, src: np.ndarray, max_gap_s: float, width_px: int,
                  height_px: int) -> tuple[np.ndarray, dict[int, tuple]]:
    """The frames worth re-running the detector on: those of a run of box-less frames between two boxed frames
    that lasts at most ``max_gap_s`` (a longer run -- take-off, landing, turning away -- is a camera that does not
    see the person), each with its search region: the two neighbours' boxes, united and doubled. Pure."""
    have = np.flatnonzero(src > 0)
    frames, rois = [], {}
    for a, b in zip(have[:-1], have[1:]):
        if b - a < 2 or (t_ns[b] - t_ns[a]) * 1e-9 > max_gap_s:
            continue
        x0 = min(boxes[a, 0], boxes[b, 0])
        y0 = min(boxes[a, 1], boxes[b, 1])
        x1 = max(boxes[a, 0] + boxes[a, 2], boxes[b, 0] + boxes[b, 2])
        y1 = max(boxes[a, 1] + boxes[a, 3], boxes[b, 1] + boxes[b, 3])
        cx, cy, w, h = (x0 + x1) / 2, (y0 + y1) / 2, 2 * (x1 - x0), 2 * (y1 - y0)
        rx0, ry0 = max(0.0, cx - w / 2), max(0.0, cy - h / 2)
        rx1, ry1 = min(float(width_px), cx + w / 2), min(float(height_px), cy + h / 2)
        if rx1 - rx0 < 16 or ry1 - ry0 < 16:
            continue
        for i in range(a + 1, b):
            frames.append(i)
            rois[i] = (rx0, ry0, rx1 - rx0, ry1 - ry0)
    return np.asarray(frames, dtype=np.int64), rois


def smoother_boxes(flight, sortie: int | None) -> dict[str, TrackBoxes]:
    """{drone: {capture time ns: the smoothed person's box (x_min, y_min, x_max, y_max)}} from the offline
    smoother over the whole flight (in segments: :attr:`reconstruction.track.smoother.SmootherConfig.segment_s`),
    each a :class:`TrackBoxes` that carries the drone's detections too; {} when it cannot run (no detections, ...).
    The recordings are read once, without the simulator's true boxes (evaluation only) and without images."""
    import dataclasses

    from reconstruction.track.flight import RefineConfig, flight_settings, read_recordings, refine_recordings

    try:  # refine_flight without its evaluation against the truth (not needed here)
        settings = flight_settings(flight)
        cfg = dataclasses.replace(RefineConfig(), **{k: settings[k] for k in ("person_height_m", "camera_position_sigma_m")
                                                     if settings.get(k) is not None})
        recs = read_recordings(flight, sortie=sortie, truth_boxes=False)
        res = refine_recordings(recs, cfg)
    except Exception as e:  # the boxes still come from the detections and the detector
        log.warning("offline smoother not used for the boxes: %s", e)
        return {}
    out = {}
    by_id = {r.drone_id: r for r in recs}
    for d, b in res.boxes.items():
        r = by_id[d]
        dets = {int(m.header.t_measurement_ns): _person_rows(m) for m in r.detections}
        out[d] = TrackBoxes({int(t): bx for t, bx in zip(b["frame_t_ns"].tolist(), b["box_px"])}, r.detections_topic, dets)
    return out


def compute_boxes(sorties: Sequence[Sortie], drone_id: str, frames: FrameTable, cfg: BoxesConfig,
                  track_boxes: dict[int, np.ndarray] | None, detector_factory: Callable | None,
                  tick: Callable[[float, float, str], None]) -> dict[str, np.ndarray]:
    """One drone's boxes (the cache entry): ``t_ns``, ``box_xywh`` (F, 4), ``source`` (F,)."""
    if isinstance(track_boxes, TrackBoxes):  # the smoother read them already
        topic, dets = track_boxes.topic, track_boxes.detections
    else:
        topic, dets = read_detections(sorties, drone_id)
    boxes, src = choose_boxes(frames.t_ns, frames.width_px, frames.height_px, dets, track_boxes, cfg.min_score)
    missing, rois = detector_gaps(frames.t_ns, boxes, src, cfg.detector_max_gap_s, frames.width_px, frames.height_px)
    tick(0.5, 1.0, f"{drone_id}: {len(frames) - len(missing)}/{len(frames)} frames boxed from {topic} and the track")
    if len(missing) and cfg.detector_fill and detector_factory is not None:
        det = detector_factory()
        for n, (i, img) in enumerate(iter_images(sorties, missing)):
            if img is not None:
                res = det.detect(img, mode="roi", roi_xywh=rois[i])
                if res.detections:
                    boxes[i] = res.detections[0].xywh
                    src[i] = 3
            if n % 16 == 15:
                tick(0.5 + 0.5 * (n + 1) / len(missing), 1.0, f"{drone_id}: detector on {n + 1}/{len(missing)} frames")
    counts = {SOURCE_NAMES[k]: int(np.sum(src == k)) for k in range(len(SOURCE_NAMES))}
    log.info("%s: boxes of %d frames: %s (recorded detections: %s)", drone_id, len(frames), counts, topic)
    return {"t_ns": frames.t_ns, "sortie": frames.sortie, "frame_index": frames.frame_index, "box_xywh": boxes,
            "source": src, "size_px": np.array([frames.width_px, frames.height_px])}
