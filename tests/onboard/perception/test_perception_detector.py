"""Onboard person detector on the real ONNX model: real drone images, the three modes, decoding helpers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from onboard.detector.detector import (
    DetectorConfig,
    DetectorInputError,
    PersonDetector,
    draw_detections,
    nms,
    tile_origins,
)


def iou(a, b) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def match(detections, gt_boxes, min_iou: float = 0.3) -> tuple[int, list]:
    """Greedy one-to-one matching, best score first; returns (true positives, false-positive boxes)."""
    used: set[int] = set()
    fps = []
    for d in detections:
        b = (d.x_min_px, d.y_min_px, d.x_max_px, d.y_max_px)
        cand = [(iou(b, g), k) for k, g in enumerate(gt_boxes) if k not in used]
        best = max(cand, default=(0.0, -1))
        if best[0] >= min_iou:
            used.add(best[1])
        else:
            fps.append((round(d.x_min_px), round(d.y_min_px), round(d.x_max_px), round(d.y_max_px), round(d.score, 2)))
    return len(used), fps


# --- pure logic -------------------------------------------------------------------------------------------
def test_nms_keeps_best_and_suppresses_overlaps_and_fragments() -> None:
    boxes = np.array(
        [[0, 0, 10, 20], [1, 1, 11, 21], [30, 0, 40, 20], [30, 0, 40, 8], [0, 50, 10, 70]], np.float32
    )
    scores = np.array([0.9, 0.8, 0.7, 0.65, 0.1], np.float32)
    assert nms(boxes, scores, 0.5).tolist() == [0, 2, 3, 4]  # the fragment is not an IoU duplicate
    assert nms(boxes, scores, 0.5, containment_thr=0.6).tolist() == [0, 2, 4]  # it lies inside box 2
    scores[3] = 0.75  # a fragment scoring higher than the whole box does not remove it
    assert nms(boxes, scores, 0.5, containment_thr=0.6).tolist() == [0, 3, 2, 4]
    assert nms(boxes, scores, 0.5, max_keep=2).tolist() == [0, 3]
    assert nms(boxes[:0], scores[:0], 0.5).size == 0


@pytest.mark.parametrize("length,tile,overlap", [(1920, 416, 96), (1080, 416, 96), (416, 416, 96), (300, 416, 96)])
def test_tiles_cover_the_frame_with_the_overlap(length, tile, overlap) -> None:
    starts = tile_origins(length, tile, overlap)
    assert starts[0] == 0 and min(starts[-1] + tile, length) == length
    for a, b in zip(starts, starts[1:]):
        assert a + tile - b >= overlap


# --- real model, real images -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def general(aerial_dir):
    img = cv2.imread(str(aerial_dir / "general_example.png"))
    assert img is not None and img.shape == (1080, 1920, 3)
    return img


@pytest.fixture(scope="module")
def general_tiles(detector, general):
    return detector.detect(general, mode="tiles")


def test_tiles_find_the_pedestrians_in_the_oblique_drone_image(general_tiles, aerial_labels) -> None:
    gt = [p["box"] for p in aerial_labels["general_example.png"]]
    assert len(gt) >= 17
    tp, fps = match(general_tiles.detections, gt)
    assert tp / len(gt) >= 0.8, f"recall {tp}/{len(gt)}"
    assert len(fps) <= 2, f"false positives {fps}"


def test_tiles_find_all_three_people_seen_from_straight_above(detector, aerial_dir, aerial_labels) -> None:
    img = cv2.imread(str(aerial_dir / "top_example.png"))
    res = detector.detect(img, mode="tiles")
    gt = [p["box"] for p in aerial_labels["top_example.png"]]
    tp, _ = match(res.detections, gt)
    assert tp == 3
    # the 90-degree pass is what finds them: without it a COCO detector misses top-down people
    upright_only = PersonDetector(DetectorConfig(tile_rotate_90=False)).detect(img, mode="tiles")
    assert match(upright_only.detections, gt)[0] < 3


def test_detections_carry_scores_and_per_edge_variance_in_full_image_pixels(general_tiles) -> None:
    assert general_tiles.mode == "tiles" and general_tiles.inferences == 2 * len(general_tiles.regions)
    for d in general_tiles.detections:
        assert 0.0 <= d.x_min_px < d.x_max_px <= 1920 and 0.0 <= d.y_min_px < d.y_max_px <= 1080
        assert 0.35 <= d.score <= 1.0
        var = np.array([d.var_x_min_px2, d.var_y_min_px2, d.var_x_max_px2, d.var_y_max_px2])
        assert np.all(np.isfinite(var)) and np.all(var > 0) and np.all(var < 30.0**2)
        msg = d.to_msg()
        assert msg.x_min_px == pytest.approx(d.x_min_px) and msg.var_y_max_px2 == pytest.approx(d.var_y_max_px2)


def test_roi_mode_returns_full_image_boxes_that_agree_with_tiles(detector, general, general_tiles, aerial_labels) -> None:
    roi = (520, 230, 320, 320)  # around the group on the plaza edge
    res = detector.detect(general, mode="roi", roi_xywh=roi)
    assert res.inferences == 1 and res.roi_px == roi
    gt_in_roi = [
        p["box"]
        for p in aerial_labels["general_example.png"]
        if p["box"][0] >= roi[0] and p["box"][1] >= roi[1] and p["box"][2] <= roi[0] + roi[2] and p["box"][3] <= roi[1] + roi[3]
    ]
    assert len(gt_in_roi) >= 6
    tp, fps = match(res.detections, gt_in_roi)
    assert tp >= len(gt_in_roi) - 2 and len(fps) <= 1
    # the same people from the ROI and from the tiles: same places in the full image
    tiled = [(d.x_min_px, d.y_min_px, d.x_max_px, d.y_max_px) for d in general_tiles.detections]
    best = [max(iou((d.x_min_px, d.y_min_px, d.x_max_px, d.y_max_px), t) for t in tiled) for d in res.detections]
    assert sum(b > 0.6 for b in best) >= 5


def test_roi_partly_outside_the_image_is_clipped(detector, general) -> None:
    res = detector.detect(general, mode="roi", roi_xywh=(1800, 950, 400, 400))
    assert res.roi_px == (1800.0, 950.0, 120.0, 130.0)
    for d in res.detections:
        assert d.x_min_px >= 1800 and d.y_min_px >= 950


def test_full_mode_finds_a_large_person(detector, grace_hopper) -> None:
    res = detector.detect(grace_hopper, mode="full")
    assert res.detections and res.inferences == 1
    best = res.detections[0]
    assert iou((best.x_min_px, best.y_min_px, best.x_max_px, best.y_max_px), (20, 30, 512, 600)) > 0.3


def test_roi_without_region_falls_back_to_full(detector, grace_hopper) -> None:
    assert detector.detect(grace_hopper, mode="roi").mode == "full"


def test_bad_inputs_give_clear_errors(detector, general) -> None:
    with pytest.raises(DetectorInputError, match="unknown detector mode"):
        detector.detect(general, mode="everywhere")
    with pytest.raises(DetectorInputError, match="outside"):
        detector.detect(general, mode="roi", roi_xywh=(5000, 5000, 100, 100))
    with pytest.raises(DetectorInputError, match="positive width"):
        detector.detect(general, mode="roi", roi_xywh=(0, 0, 0, 10))
    with pytest.raises(DetectorInputError, match="uint8"):
        detector.detect(general.astype(np.float32), mode="full")
    with pytest.raises(DetectorInputError, match="image array"):
        detector.detect(None, mode="full")


def test_grey_and_annotated_output(detector, general) -> None:
    grey = cv2.cvtColor(general[300:620, 520:840], cv2.COLOR_BGR2GRAY)
    res = detector.detect(grey, mode="full")
    assert len(res.detections) >= 3
    out = draw_detections(grey, res)
    assert out.shape == (320, 320, 3) and not np.array_equal(out, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))


def test_two_threads_give_the_same_detections(general) -> None:
    crop = np.ascontiguousarray(general[230:550, 520:840])
    a = PersonDetector(DetectorConfig(threads=1)).detect(crop, mode="full")
    b = PersonDetector(DetectorConfig(threads=2)).detect(crop, mode="full")
    assert len(a.detections) == len(b.detections)
    for x, y in zip(a.detections, b.detections):
        assert x.x_min_px == pytest.approx(y.x_min_px, abs=0.05) and x.score == pytest.approx(y.score, abs=1e-3)


def test_small_roi_is_upscaled_and_mapped_back(detector, general, aerial_labels) -> None:
    # a tracker ROI of 100x110 px around one pedestrian (1093, 680)-(1122, 740): scaled 2.9x to the model
    res = detector.detect(general, mode="roi", roi_xywh=(1060, 650, 100, 110))
    assert res.detections
    best = res.detections[0]
    b = (best.x_min_px, best.y_min_px, best.x_max_px, best.y_max_px)
    assert iou(b, (1093, 680, 1122, 740)) > 0.5
    # the variance shrinks with the upscaling (finer model pixels) but stays positive
    assert 0 < best.var_x_min_px2 < 10.0


def test_result_fits_the_detections_message(detector, general) -> None:
    from shared_msgs.codec import decode, encode
    from shared_msgs.messages import Detections

    res = detector.detect(general, mode="roi", roi_xywh=(520, 230, 320, 320))
    msg = Detections(
        header=Detections.make_header("drone_1", 123),
        camera_id="drone_1/cam0",
        frame_index=7,
        detector=detector.name,
        mode=res.mode,
        boxes=[d.to_msg() for d in res.detections],
        width_px=general.shape[1],
        height_px=general.shape[0],
        T_world_cam=tuple(float(v) for v in np.eye(4).ravel()),
        roi_px=res.roi_px,
    )
    back = decode(encode(msg), Detections)
    assert len(back.boxes) == len(res.detections) >= 6
    assert back.boxes[0].var_x_max_px2 == pytest.approx(res.detections[0].var_x_max_px2)
