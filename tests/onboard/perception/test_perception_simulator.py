"""The real detector and keypoint models on a frame rendered by the simulator (simulator.scene)."""

from __future__ import annotations


import numpy as np
import pytest

render = pytest.importorskip("simulator.scene.render")


def _iou(a, b) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    return iw * ih / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - iw * ih)


@pytest.mark.parametrize("mode", ["roi", "tiles", "full"])
def test_detector_finds_the_rendered_person(detector, sim_frame, mode) -> None:
    g = sim_frame.gt.box_px
    roi = (g[0] - 100, g[1] - 100, g[2] - g[0] + 200, g[3] - g[1] + 200) if mode == "roi" else None
    res = detector.detect(sim_frame.image, mode=mode, roi_xywh=roi)
    assert res.detections, f"no person found in the rendered frame ({mode})"
    best = res.detections[0]
    assert _iou((best.x_min_px, best.y_min_px, best.x_max_px, best.y_max_px), g) > 0.6
    assert len(res.detections) <= 2


def test_keypoint_models_on_the_rendered_person(keypoint_detectors, sim_frame) -> None:
    g = sim_frame.gt.box_px
    box = (g[0], g[1], g[2] - g[0], g[3] - g[1])
    out = keypoint_detectors.detect(sim_frame.image, [box])
    vis = sim_frame.gt.visible
    for name, (p,) in out.items():
        err = np.hypot(*(p.keypoints_px - sim_frame.gt.uv_px).T)
        assert np.median(err[vis]) < 0.12 * box[3], (name, np.round(err / box[3], 2))
