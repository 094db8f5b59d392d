"""The ``keypoints`` step: the shipped keypoint models on one drone's recorded frames, in cached chunks, and the
fusion of the models per joint (:func:`fuse_keypoints`, pure).

Frames are decoded one at a time and sent to the models ``batch_size`` at a time; every ``chunk_frames`` frames
the chunk's keypoints are written atomically (``processing/keypoints/<drone>-<key>/chunk_NNNNN.npz``), so a
crash or a cancel loses at most one chunk; a resumed run skips the written chunks without decoding their images.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from flightdata.folder import Sortie
from reconstruction.process.cache import atomic_write_npz, read_npz
from reconstruction.process.config import KeypointsConfig
from reconstruction.process.frames import iter_images

log = logging.getLogger(__name__)

__all__ = ["fuse_keypoints", "compute_keypoints", "load_models"]


def fuse_keypoints(kp: np.ndarray, box_xywh: np.ndarray, agree_fraction: float = 0.15,
                   min_confidence: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Fuse M models' COCO-17 keypoints per joint.

    kp: (F, M, 17, 3) x_px, y_px, confidence per model (NaN / 0 where a model gave nothing); box_xywh (F, 4).
    Per frame and joint, the models at or above ``min_confidence`` vote. When all voters lie within
    ``agree_fraction`` x the box's longer side of their confidence-weighted mean, the joint is that mean with the
    highest voter's confidence (agreement confirms it); otherwise the most confident model's point is kept with its
    confidence lowered by the runner-up's (c1 - c2: two confident models that disagree make an ambiguous joint).
    Returns (uv (F, 17, 2), confidence (F, 17)); confidence 0 (uv 0) where no model voted.
    """
    kp = np.asarray(kp, dtype=float)
    F, M = kp.shape[:2]
    xy = np.nan_to_num(kp[..., :2])
    c = np.nan_to_num(kp[..., 2])
    c = np.where(np.all(np.isfinite(kp[..., :2]), axis=-1) & (c >= min_confidence), c, 0.0)  # (F, M, 17)
    wh = np.asarray(box_xywh, dtype=float)[:, 2:]
    side = np.where(np.all(np.isfinite(wh), axis=1), np.max(np.nan_to_num(wh), axis=1), 1.0)  # (F,)
    side = np.where(side > 0, side, 1.0)
    wsum = c.sum(axis=1)  # (F, 17)
    voted = wsum > 0
    mean = np.einsum("fmj,fmjk->fjk", c, xy) / np.where(voted, wsum, 1.0)[..., None]
    dist = np.linalg.norm(xy - mean[:, None], axis=-1)  # (F, M, 17)
    spread = np.where(c > 0, dist, 0.0).max(axis=1)  # (F, 17)
    agree = spread <= agree_fraction * side[:, None]
    order = np.argsort(-c, axis=1)  # (F, M, 17)
    best = np.take_along_axis(c, order[:, :1], axis=1)[:, 0]
    second = np.take_along_axis(c, order[:, 1:2], axis=1)[:, 0] if M > 1 else np.zeros_like(best)
    best_xy = np.take_along_axis(xy, order[:, :1, :, None], axis=1)[:, 0]
    uv = np.where(agree[..., None], mean, best_xy)
    conf = np.where(agree, best, np.clip(best - second, 0.0, 1.0))
    uv = np.where(voted[..., None], uv, 0.0)
    conf = np.where(voted, conf, 0.0)
    return uv, conf


def load_models(cfg: KeypointsConfig) -> list:
    """The configured keypoint models, each with ``cfg.threads`` onnxruntime threads."""
    from reconstruction.keypoints.detectors import load_model

    return [load_model(n, cfg.threads, cfg.crop_scale) for n in cfg.models]


def compute_keypoints(sorties: Sequence[Sortie], drone_id: str, boxes: dict[str, np.ndarray], cfg: KeypointsConfig,
                      chunk_dir: Path, models: Callable[[], list],
                      tick: Callable[[float, float, str], None], stats: dict,
                      only_chunks: Sequence[int] | None = None) -> np.ndarray:
    """The models' keypoints (F, M, 17, 3) of one drone's frames with a box, chunk by chunk (see the module doc).
    ``models()`` opens the models when a chunk needs computing; ``tick(done, total, message)`` is called after each
    batch (and checks the cancel event); ``stats["frames_computed"]`` counts the frames run here. ``only_chunks``:
    compute (and write) only these chunks -- a part of the drone's frames for one worker; the others stay NaN."""
    box = boxes["box_xywh"]
    F, M, n = len(box), len(cfg.models), cfg.chunk_frames
    n_chunks = max(1, -(-F // n))
    out = np.full((F, M, 17, 3), np.nan)
    out[..., 2] = 0.0
    todo = []
    for c in range(n_chunks):
        z = read_npz(chunk_dir / f"chunk_{c:05d}.npz")
        if z is not None and z["kp"].shape == (min(n, F - c * n), M, 17, 3):
            out[c * n : (c + 1) * n] = z["kp"]
        elif only_chunks is None or c in only_chunks:
            todo.append(c)
    size = lambda c: min(n, F - c * n)  # noqa: E731
    total = F if only_chunks is None else sum(size(c) for c in set(only_chunks) if 0 <= c < n_chunks)  # progress
    done_frames = total - sum(size(c) for c in todo)
    tick(done_frames, total, f"{drone_id}: {done_frames}/{total} frames from the cache" if done_frames else f"{drone_id}: starting")
    if not todo:
        return out
    mods = models()
    has_box = np.all(np.isfinite(box), axis=1)
    wanted = [i for c in todo for i in range(c * n, min((c + 1) * n, F)) if has_box[i]]
    pending: list[tuple[int, np.ndarray]] = []
    tracks: list[dict] = [{} for _ in mods]  # per model: the video-mode region track of this camera
    chunk_of = lambda i: i // n  # noqa: E731
    remaining = {c: int(np.sum(has_box[c * n : min((c + 1) * n, F)])) for c in todo}

    def flush() -> None:
        if not pending:
            return
        idx = [i for i, _ in pending]
        imgs = [im for _, im in pending]
        for m, model in enumerate(mods):
            if cfg.track_rois and getattr(model, "predict_sequence", None) is not None:
                # the region track starts afresh in every chunk (a batch never spans two): a chunk's keypoints then
                # do not depend on which chunks this run computed, so a resumed run or another split of the chunks
                # over the workers gives the uninterrupted run's keypoints
                if tracks[m].get("chunk") != chunk_of(idx[0]):
                    tracks[m].clear()
                    tracks[m]["chunk"] = chunk_of(idx[0])
                out[idx, m] = model.predict(imgs, box[idx], cfg.batch_size, frame_ids=idx, track=tracks[m])
                stats["pose_detector_runs"] = stats.get("pose_detector_runs", 0) + tracks[m].pop("detector_runs", 0)
            else:
                out[idx, m] = model.predict(imgs, box[idx], cfg.batch_size)
        stats["frames_computed"] = stats.get("frames_computed", 0) + len(idx)
        stats["model_calls"] = stats.get("model_calls", 0) + len(mods)
        pending.clear()

    def finish_ready() -> None:
        nonlocal done_frames
        for c in [c for c in todo if remaining[c] == 0]:
            atomic_write_npz(chunk_dir / f"chunk_{c:05d}.npz", kp=out[c * n : (c + 1) * n])
            todo.remove(c)
            done_frames += min(n, F - c * n)

    finish_ready()  # chunks without any boxed frame
    for i, img in iter_images(sorties, wanted):
        if img is None:
            log.warning("%s: frame %d does not decode; left out", drone_id, i)
        else:
            pending.append((i, img))
        remaining[chunk_of(i)] -= 1
        if len(pending) >= cfg.batch_size or remaining[chunk_of(i)] == 0:
            flush()
            finish_ready()
            tick(done_frames, total, f"{drone_id}: {done_frames}/{total} frames")
    flush()
    finish_ready()
    if todo:  # frames the recording no longer yields (cannot happen with an unchanged file)
        raise RuntimeError(f"{drone_id}: chunks {todo} incomplete: the recording yielded fewer frames than its table")
    tick(total, total, f"{drone_id}: {total} frames")
    return out
