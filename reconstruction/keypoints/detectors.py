"""2D keypoint detectors (COCO-17) for reconstruction: crop around a person box, run ONNX models.

Shipped models (``reconstruction/keypoints/models/``, built by ``scripts/make_models/``):

================== ============ ======= ======================================================
name               input        source  notes
================== ============ ======= ======================================================
movenet_lightning  192x192 RGB  Google  MoveNet single-pose Lightning v4 (Apache-2.0), COCO-17
movenet_thunder    256x256 RGB  Google  MoveNet single-pose Thunder v4 (Apache-2.0), COCO-17
blazepose_full     256x256 RGB  Google  BlazePose GHUM landmark "full" (Apache-2.0), 33 points
                                        mapped to COCO-17 (:data:`BLAZEPOSE_TO_COCO17`)
blazepose_lite     256x256 RGB  Google  BlazePose GHUM landmark "lite": the same outputs, about half
                                        the CPU time of "full", less accurate on hard poses
================== ============ ======= ======================================================

MoveNet and BlazePose are different networks trained on different data (MoveNet: COCO + Active;
BlazePose: Google's own 33-landmark set), so their errors are partly independent, which is what the
multi-detector fusion in reconstruction wants (AirCap fused AlphaPose and OpenPose).

Every model sees the same square crop: centred on the person box, side = ``crop_scale`` x the box's
longer side, cut out with an affine warp (zero padding outside the image), resized to the model input.
Outputs are mapped back to full-image pixels. Images are OpenCV BGR uint8 (H, W, 3).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from onboard.detector.modelfile import ThreadSettings, open_session, resolve_model
from reconstruction.keypoints import DEFAULT_MODELS, KEYPOINT_MODELS  # re-exported here
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

MODELS_DIR = Path(__file__).resolve().parent / "models"

#: BlazePose 33-landmark index for each COCO-17 keypoint, in COCO-17 order.
BLAZEPOSE_TO_COCO17: tuple[int, ...] = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)


class KeypointInputError(SkycapError, ValueError):
    """Bad image, box or model name given to the keypoint detectors."""


@dataclass
class KeypointConfig:
    """Keypoint detector settings (``[keypoints]`` in a TOML config)."""

    models: list[str] | None = None  #: model names; None = DEFAULT_MODELS
    threads: int = 1  #: onnxruntime intra-op threads per model
    crop_scale: float = 1.25  #: square crop side / longer box side
    batch_size: int = 16  #: crops per call for models with a dynamic batch (BlazePose)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def network_input(name: str, crops_u8: np.ndarray) -> np.ndarray:
    """uint8 RGB crops (n, S, S, 3) -> the input the network ``name`` takes: MoveNet int32 0..255, BlazePose's pose
    detector float32 in [-1, 1], BlazePose's landmarks float32 in [0, 1]."""
    if name.startswith("movenet"):
        return crops_u8.astype(np.int32)
    if name.startswith("blazepose_detector"):
        return crops_u8.astype(np.float32) * (2.0 / 255.0) - 1.0
    return crops_u8.astype(np.float32) * (1.0 / 255.0)


def roi_transform(center_xy, side_px: float, size_px: int, up_xy=(0.0, -1.0)) -> np.ndarray:
    """Affine (2, 3) matrix mapping full-image pixels to a ``size_px`` square crop.

    The crop shows a square of side ``side_px`` centred on ``center_xy`` whose "up" points along the
    image direction ``up_xy`` (``(0, -1)``: upright; BlazePose turns its crop along the body axis).
    Pixel indices are used on both sides (pixel centres at integers).
    """
    if not (side_px > 0 and np.isfinite(side_px)):
        raise KeypointInputError(f"crop side {side_px} must be a positive number of pixels")
    ux, uy = (float(v) for v in up_xy)
    n = math.hypot(ux, uy)
    ux, uy = (ux / n, uy / n) if n > 0 else (0.0, -1.0)
    vx, vy = -uy, ux  # crop x axis in the image (perpendicular to up, to its right)
    s = size_px / float(side_px)
    cx, cy = (float(v) for v in center_xy)
    c = (size_px - 1) / 2.0
    return np.array(
        [[s * vx, s * vy, c - s * (vx * cx + vy * cy)], [-s * ux, -s * uy, c + s * (ux * cx + uy * cy)]], np.float64
    )


def box_transform(box_xywh, size_px: int, crop_scale: float) -> np.ndarray:
    """Upright square crop centred on the box, side ``crop_scale * max(w, h)`` (see :func:`roi_transform`)."""
    x, y, w, h = (float(v) for v in box_xywh)
    if not (w > 0 and h > 0) or not np.all(np.isfinite([x, y, w, h])):
        raise KeypointInputError(f"person box {tuple(box_xywh)} must be finite with positive width and height (x, y, w, h)")
    return roi_transform((x + w / 2.0, y + h / 2.0), crop_scale * max(w, h), size_px)


def warp_crop(image_bgr: np.ndarray, A: np.ndarray, size_px: int) -> np.ndarray:
    """RGB uint8 (size_px, size_px, 3) crop of the image through the (2, 3) transform ``A`` (zeros outside)."""
    scale = math.hypot(A[0, 0], A[0, 1])
    interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    crop = cv2.warpAffine(image_bgr, A, (size_px, size_px), flags=interp, borderMode=cv2.BORDER_CONSTANT)
    return cv2.cvtColor(crop, cv2.COLOR_BGR2RGB)


def crop_person(image_bgr: np.ndarray, box_xywh, size_px: int, crop_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Square RGB crop (size_px, size_px, 3) uint8 around the box and its (2, 3) image->crop transform."""
    A = box_transform(box_xywh, size_px, crop_scale)
    return warp_crop(image_bgr, A, size_px), A


def crop_to_image(points_crop: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Map (..., 2) crop pixel coordinates back to full-image pixels with the inverse of ``A``."""
    Ai = cv2.invertAffineTransform(A)
    p = np.asarray(points_crop, np.float64)
    return p @ Ai[:, :2].T + Ai[:, 2]


class KeypointModel:
    """One ONNX keypoint model.

    :meth:`predict` takes images and person boxes and returns COCO-17 keypoints in image pixels;
    :meth:`predict_crops` runs the network on model-sized crops.
    """

    name: str
    input_px: int
    dynamic_batch: bool = False

    def __init__(self, name: str, threads: int = 1, crop_scale: float = 1.25):
        if name not in KEYPOINT_MODELS:
            raise KeypointInputError(f"unknown keypoint model {name!r}; use one of {', '.join(KEYPOINT_MODELS)}")
        self.name = name
        self.crop_scale = float(crop_scale)
        self.session, self.model_path = _open(name, threads)
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        self.input_px = int(inp.shape[1])
        self.dynamic_batch = not isinstance(inp.shape[0], int)
        self.output_names = [o.name for o in self.session.get_outputs()]

    def _run(self, crops_rgb: np.ndarray) -> np.ndarray:  # (n, S, S, 3) uint8 -> (n, 17, 3)
        raise NotImplementedError

    def predict_crops(self, crops_rgb: np.ndarray, batch_size: int = 16) -> np.ndarray:
        """Keypoints of one person per crop.

        Args:
            crops_rgb: (N, S, S, 3) uint8 RGB crops, S = ``input_px``.
        Returns:
            (N, 17, 3): x, y in crop pixels, confidence in [0, 1], COCO-17 order.
        """
        crops_rgb = np.asarray(crops_rgb)
        if crops_rgb.ndim != 4 or crops_rgb.shape[1:] != (self.input_px, self.input_px, 3):
            raise KeypointInputError(
                f"{self.name} expects crops of shape (N, {self.input_px}, {self.input_px}, 3), got {crops_rgb.shape}"
            )
        step = max(1, batch_size) if self.dynamic_batch else 1
        outs = [self._run(crops_rgb[i : i + step]) for i in range(0, len(crops_rgb), step)]
        return np.concatenate(outs) if outs else np.zeros((0, 17, 3), np.float32)

    def predict(self, images: list[np.ndarray], boxes_xywh: np.ndarray, batch_size: int = 16) -> np.ndarray:
        """COCO-17 keypoints for person ``i`` = box ``boxes_xywh[i]`` in ``images[i]``.

        Args:
            images: P images (H, W, 3) BGR uint8 (the same array may repeat for several people).
            boxes_xywh: (P, 4) x, y, w, h in image pixels.
        Returns:
            (P, 17, 3): x_px, y_px in image pixels, confidence in [0, 1].
        """
        mats = [box_transform(b, self.input_px, self.crop_scale) for b in boxes_xywh]
        return self._predict_rois(images, mats, batch_size)

    def _predict_rois(self, images, mats, batch_size: int) -> np.ndarray:
        if not mats:
            return np.zeros((0, 17, 3))
        crops = np.stack([warp_crop(img, A, self.input_px) for img, A in zip(images, mats)])
        kp = self.predict_crops(crops, batch_size).astype(np.float64)
        for i, A in enumerate(mats):
            kp[i, :, :2] = crop_to_image(kp[i, :, :2], A)
        return kp


class MoveNet(KeypointModel):
    """MoveNet single-pose: int32 RGB 0..255 input, output (1, 1, 17, 3) = (y, x, score), y and x in [0, 1]."""

    def _run(self, crops_rgb: np.ndarray) -> np.ndarray:
        out = np.empty((len(crops_rgb), 17, 3), np.float32)
        for i, c in enumerate(crops_rgb):
            y = self.session.run(self.output_names, {self.input_name: network_input(self.name, c[None])})[0][0, 0]
            out[i, :, 0] = y[:, 1] * self.input_px - 0.5
            out[i, :, 1] = y[:, 0] * self.input_px - 0.5
            out[i, :, 2] = y[:, 2]
        return out


def _pose_detector_anchors() -> np.ndarray:
    """(2254, 2) anchor centres in [0, 1] of MediaPipe's 224x224 pose detector (SSD, strides 8, 16, 32 x3,
    two anchors per layer and cell, fixed anchor size)."""
    out = []
    for stride, per_cell in ((8, 2), (16, 2), (32, 6)):
        fm = 224 // stride
        ys, xs = np.meshgrid((np.arange(fm) + 0.5) / fm, (np.arange(fm) + 0.5) / fm, indexing="ij")
        out.append(np.repeat(np.stack([xs.ravel(), ys.ravel()], 1), per_cell, axis=0))
    return np.concatenate(out)


class BlazePose(KeypointModel):
    """BlazePose GHUM (MediaPipe) in its own two stages, within the given person box:

    1. pose detector (224x224, RGB in [-1, 1]) on an upright crop around the box: it finds the face and
       predicts the hip centre (keypoint 0) and a point on the circle enclosing the body (keypoint 1);
    2. landmark model (256x256, RGB in [0, 1]) on MediaPipe's region from those: centred on the hip
       centre, side 2 x 1.25 x |kp1 - kp0|, upright (``upright=True``, the default: a drone's gimbal keeps
       the horizon level and the people it films stand; the detector's face->hip tilt estimate was
       the larger error on the test portraits) or turned along the hip->head axis as MediaPipe does
       (``upright=False``). ``ld_3d`` (N, 195) =
       39 x (x, y, z, visibility, presence), x/y in input pixels, visibility/presence as logits.

    Without a detection (score < ``min_detection_score``) the landmark model gets the upright box crop.
    """

    min_detection_score = 0.5
    upright = True

    #: the landmark outputs read here (the shipped landmark file is cut to them, see scripts/make_models/)
    landmark_outputs = ("ld_3d", "output_poseflag")

    def __init__(self, name: str, threads: int = 1, crop_scale: float = 1.25):
        super().__init__(name, threads, crop_scale)
        self.output_names = [o for o in self.landmark_outputs if o in self.output_names]
        self.det_session, _ = _open("blazepose_detector", threads)
        self.det_input = self.det_session.get_inputs()[0].name
        self.anchors = _pose_detector_anchors()

    def _run(self, crops_rgb: np.ndarray) -> np.ndarray:
        x = network_input(self.name, crops_rgb)
        res = dict(zip(self.output_names, self.session.run(self.output_names, {self.input_name: x})))
        ld = res["ld_3d"].reshape(len(crops_rgb), 39, 5)[:, BLAZEPOSE_TO_COCO17]
        flag = res["output_poseflag"].reshape(-1, 1)
        out = np.empty((len(crops_rgb), 17, 3), np.float32)
        out[..., 0] = ld[..., 0] - 0.5
        out[..., 1] = ld[..., 1] - 0.5
        conf = _sigmoid(ld[..., 3]) * _sigmoid(ld[..., 4])
        out[..., 2] = conf * np.clip(flag, 0.0, 1.0)
        return out

    def detect_rois(self, images, boxes_xywh, batch_size: int = 16) -> list[np.ndarray | None]:
        """MediaPipe landmark regions (2, 3) image->crop transforms, one per box (None: no detection)."""
        S = 224
        mats = [box_transform(b, S, 1.5) for b in boxes_xywh]
        rois: list[np.ndarray | None] = []
        for i in range(0, len(mats), max(1, batch_size)):
            chunk = list(zip(images[i : i + batch_size], mats[i : i + batch_size]))
            x = network_input("blazepose_detector", np.stack([warp_crop(img, A, S) for img, A in chunk]))
            raw = self.det_session.run(None, {self.det_input: x})[0]  # (n, 2254, 13): score logit, 12 regressors
            for (_, A), r in zip(chunk, raw):
                k = int(np.argmax(r[:, 0]))
                if _sigmoid(np.clip(r[k, 0], -50, 50)) < self.min_detection_score:
                    rois.append(None)
                    continue
                kp = r[k, 5:9].reshape(2, 2) + self.anchors[k] * S  # hip centre, body-circle point (crop px)
                kp_img = crop_to_image(kp, A)
                up = kp_img[1] - kp_img[0]
                side = 2.0 * 1.25 * float(np.hypot(*up))
                direction = (0.0, -1.0) if self.upright else up
                rois.append(roi_transform(kp_img[0], side, self.input_px, direction) if side > 4 else None)
        return rois

    def predict(self, images, boxes_xywh, batch_size: int = 16, *, frame_ids=None, track: dict | None = None) -> np.ndarray:
        """As :meth:`KeypointModel.predict`. With ``frame_ids`` (the frames' positions in their video) and a
        ``track`` dict (kept by the caller, one per camera, empty at the start): MediaPipe's video mode
        (:meth:`predict_sequence`), the pose detector only where the track is lost."""
        if track is not None and frame_ids is not None:
            return self.predict_sequence(images, boxes_xywh, frame_ids, track)
        boxes = np.asarray(boxes_xywh, np.float64).reshape(-1, 4)
        rois = self.detect_rois(images, boxes, batch_size)
        mats = [A if A is not None else box_transform(b, self.input_px, self.crop_scale) for A, b in zip(rois, boxes)]
        return self._predict_rois(images, mats, batch_size)

    def roi_from_landmarks(self, ld_img: np.ndarray) -> np.ndarray | None:
        """MediaPipe's landmark region for the next frame from this frame's auxiliary landmarks (ld 33: hip
        centre, 34: body-circle point, image pixels), as :meth:`detect_rois` makes it from the detector's two
        keypoints (side 2 x 1.25 x their distance; upright or along the hip->point axis); None when degenerate."""
        up = ld_img[1] - ld_img[0]
        side = 2.0 * 1.25 * float(np.hypot(*up))
        if not (side > 4 and np.all(np.isfinite(ld_img))):
            return None
        direction = (0.0, -1.0) if self.upright else up
        return roi_transform(ld_img[0], side, self.input_px, direction)

    def predict_sequence(self, images, boxes_xywh, frame_ids, state: dict | None = None) -> np.ndarray:
        """:meth:`predict` on consecutive video frames, MediaPipe's video mode: the landmark region of a frame is
        made from the previous frame's auxiliary landmarks (:meth:`roi_from_landmarks`) when that frame is the one
        just before (``frame_ids`` consecutive), its pose flag was >= ``min_detection_score`` and the tracked hip
        centre lies inside this frame's person box (grown by half its size); otherwise the pose detector runs, as
        in :meth:`predict`. ``state`` (a dict kept by the caller) carries the track across calls (one per camera).
        Returns (P, 17, 3) as :meth:`predict`; ``state["detector_runs"]`` counts the detector calls."""
        state = state if state is not None else {}
        boxes = np.asarray(boxes_xywh, np.float64).reshape(-1, 4)
        out = np.zeros((len(boxes), 17, 3))
        S = self.input_px
        for i, (img, b, fid) in enumerate(zip(images, boxes, frame_ids)):
            A = None
            prev = state.get("roi")
            if prev is not None and state.get("frame_id") == int(fid) - 1:
                cx, cy = state["hip_px"]
                x, y, w, h = b
                if x - w / 2 <= cx <= x + 1.5 * w and y - h / 2 <= cy <= y + 1.5 * h:
                    A = prev
            if A is None:
                state["detector_runs"] = state.get("detector_runs", 0) + 1
                A = self.detect_rois([img], b[None], 1)[0]
                if A is None:
                    A = box_transform(b, S, self.crop_scale)
            crop = warp_crop(img, A, S)
            x = network_input(self.name, crop[None])
            res = dict(zip(self.output_names, self.session.run(self.output_names, {self.input_name: x})))
            ld = res["ld_3d"].reshape(39, 5)
            flag = float(np.clip(res["output_poseflag"].reshape(-1)[0], 0.0, 1.0))
            kp = np.empty((17, 3))
            kp[:, :2] = crop_to_image(ld[BLAZEPOSE_TO_COCO17, :2] - 0.5, A)
            vis = np.clip(ld[BLAZEPOSE_TO_COCO17, 3:5].astype(np.float64), -50, 50)
            kp[:, 2] = _sigmoid(vis[:, 0]) * _sigmoid(vis[:, 1]) * flag
            out[i] = kp
            aux = crop_to_image(ld[33:35, :2] - 0.5, A)
            nxt = self.roi_from_landmarks(aux) if flag >= self.min_detection_score else None
            state.update(roi=nxt, frame_id=int(fid), hip_px=aux[0])
        return out


def _open(name: str, threads: int):
    filename = f"{name}.onnx"
    rel = f"reconstruction/keypoints/models/{filename}"
    path = resolve_model(filename, MODELS_DIR, rel)
    return open_session(path, ThreadSettings(intra_op=threads, inter_op=1), rel), path


def load_model(name: str, threads: int = 1, crop_scale: float = 1.25) -> KeypointModel:
    """Open one shipped keypoint model by name (see :data:`KEYPOINT_MODELS`)."""
    if name.startswith("movenet"):
        return MoveNet(name, threads, crop_scale)
    if name.startswith("blazepose"):
        return BlazePose(name, threads, crop_scale)
    raise KeypointInputError(f"unknown keypoint model {name!r}; use one of {', '.join(KEYPOINT_MODELS)}")


@dataclass
class PersonKeypoints:
    """COCO-17 keypoints of one person from one model, in full-image pixels."""

    model: str
    box_xywh: tuple[float, float, float, float]
    keypoints_px: np.ndarray  #: (17, 2) x, y
    confidence: np.ndarray  #: (17,)

    def to_dict(self) -> dict:
        from skycap.skeleton import COCO17_NAMES

        return {
            "model": self.model,
            "box_xywh": [round(float(v), 2) for v in self.box_xywh],
            "keypoints": {
                n: {"x_px": round(float(p[0]), 2), "y_px": round(float(p[1]), 2), "confidence": round(float(c), 4)}
                for n, p, c in zip(COCO17_NAMES, self.keypoints_px, self.confidence)
            },
        }

    def to_msg(self):
        """As the wire type :class:`shared_msgs.messages.PersonKeypoints` (box left empty)."""
        from shared_msgs.messages import PersonKeypoints as Msg

        return Msg(
            keypoints_px=tuple(float(v) for v in self.keypoints_px.reshape(-1)),
            confidence=tuple(float(c) for c in self.confidence),
        )


class KeypointDetectors:
    """Several keypoint models run over the same person boxes."""

    def __init__(self, config: KeypointConfig | None = None):
        self.config = cfg = config or KeypointConfig()
        names = list(cfg.models or DEFAULT_MODELS)
        if not names:
            raise KeypointInputError("no keypoint model selected; pass at least one of " + ", ".join(KEYPOINT_MODELS))
        self.models: dict[str, KeypointModel] = {n: load_model(n, cfg.threads, cfg.crop_scale) for n in names}

    def detect(self, image_bgr: np.ndarray, boxes_xywh) -> dict[str, list[PersonKeypoints]]:
        """Keypoints of each person box from each model.

        Args:
            image_bgr: (H, W, 3) BGR uint8.
            boxes_xywh: (P, 4) person boxes x, y, w, h in full-image pixels.
        Returns:
            model name -> list of P :class:`PersonKeypoints`.
        """
        img = _check_image(image_bgr)
        boxes = np.asarray(boxes_xywh, np.float64).reshape(-1, 4)
        out: dict[str, list[PersonKeypoints]] = {}
        for name, m in self.models.items():
            kp = m.predict([img] * len(boxes), boxes, self.config.batch_size)
            out[name] = [PersonKeypoints(name, tuple(map(float, b)), k[:, :2], k[:, 2]) for b, k in zip(boxes, kp)]
        return out

    def detect_recording(self, frames, boxes_per_frame, progress: bool = True) -> dict[str, np.ndarray]:
        """Batch path for a whole recording: one person box per frame (a NaN box = no person).

        Frames are read one at a time and processed in chunks of ``batch_size`` (memory stays bounded).

        Args:
            frames: iterable of (H, W, 3) BGR uint8 images (e.g. a generator reading a video).
            boxes_per_frame: (T, 4) x, y, w, h per frame.
        Returns:
            model name -> (T, 17, 3): x_px, y_px, confidence (NaN, NaN, 0 for frames without a box).
        """
        from tqdm import tqdm

        boxes = np.asarray(boxes_per_frame, np.float64).reshape(-1, 4)
        T = len(boxes)
        out = {n: np.full((T, 17, 3), np.nan) for n in self.models}
        for n in out:
            out[n][..., 2] = 0.0
        bs = max(1, self.config.batch_size)
        pending: list[tuple[int, np.ndarray]] = []

        def flush() -> None:
            if not pending:
                return
            idx = [t for t, _ in pending]
            imgs = [f for _, f in pending]
            for name, m in self.models.items():
                out[name][idx] = m.predict(imgs, boxes[idx], bs)
            pending.clear()

        t0 = time.perf_counter()
        n_frames = 0
        for t, frame in enumerate(tqdm(frames, total=T, desc="keypoints", disable=not progress, unit="frame")):
            if t >= T:
                raise KeypointInputError(f"more frames than boxes ({T}); give one box (or NaNs) per frame")
            n_frames += 1
            if np.all(np.isfinite(boxes[t])):
                pending.append((t, _check_image(frame)))
                if len(pending) >= bs:
                    flush()
        flush()
        if n_frames != T:
            raise KeypointInputError(f"got {n_frames} frames for {T} boxes; give one box (or NaNs) per frame")
        log.info("keypoints: %d frames x %d models in %.1f s", T, len(self.models), time.perf_counter() - t0)
        return out


def _check_image(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise KeypointInputError(
            f"expected a BGR uint8 image of shape (H, W, 3), got {getattr(image, 'dtype', type(image))} "
            f"{getattr(image, 'shape', '')}"
        )
    return image


def draw_keypoints(image_bgr: np.ndarray, people: dict[str, list[PersonKeypoints]], min_conf: float = 0.2) -> np.ndarray:
    """A copy of the image with each model's COCO-17 skeleton in its own colour (and the person boxes)."""
    from skycap.skeleton import COCO17_LIMBS

    colours = [(0, 255, 0), (255, 128, 0), (0, 0, 255), (255, 0, 255)]
    out = image_bgr.copy()
    for k, (name, persons) in enumerate(people.items()):
        col = colours[k % len(colours)]
        for p in persons:
            x, y, w, h = p.box_xywh
            cv2.rectangle(out, (int(x), int(y)), (int(x + w), int(y + h)), (200, 200, 200), 1)
            for a, b in COCO17_LIMBS:
                if p.confidence[a] >= min_conf and p.confidence[b] >= min_conf:
                    pa, pb = p.keypoints_px[a], p.keypoints_px[b]
                    cv2.line(out, (int(pa[0]), int(pa[1])), (int(pb[0]), int(pb[1])), col, 2)
            for q, c in zip(p.keypoints_px, p.confidence):
                if c >= min_conf:
                    cv2.circle(out, (int(q[0]), int(q[1])), 3, col, -1)
        cv2.putText(out, name, (8, 20 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.55, col, 2)
    return out
