"""One drone's recorded camera frames, streamed from its MCAP recordings (never all images at once).

:func:`frame_table` reads the frames' times and numbers (no JPEG decoding); :func:`iter_images` yields the
decoded images of chosen frames in the same order. Frames are taken in recording order (sortie after sortie);
a frame is identified by its position ``i`` in that order, its capture time and its (sortie, frame_index).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from flightdata.flightlog import FlightLog
from flightdata.folder import Sortie
from shared_msgs.messages import CameraFrame

__all__ = ["IMAGE_TOPIC", "FrameTable", "frame_table", "iter_images", "has_images"]

IMAGE_TOPIC = "camera/image"


@dataclasses.dataclass
class FrameTable:
    """The recorded frames of one drone: capture time ``t_ns`` (F,), ``sortie`` (F,), ``frame_index`` (F,)
    (restarts with each sortie), image size."""

    t_ns: np.ndarray
    sortie: np.ndarray
    frame_index: np.ndarray
    width_px: int
    height_px: int

    def __len__(self) -> int:
        return len(self.t_ns)


def _frames(sorties: Sequence[Sortie], decode: bool) -> Iterator[tuple[int, object]]:
    for s in sorties:
        for m in FlightLog(s.path).messages([IMAGE_TOPIC]):
            if isinstance(m.msg, CameraFrame):
                yield s.number, m.msg


def has_images(sorties: Sequence[Sortie]) -> bool:
    """Whether any of the recordings holds camera frames (from the MCAP summary when the file is finalised)."""
    return any(FlightLog(s.path).topic_counts().get(IMAGE_TOPIC, 0) > 0 for s in sorties)


def frame_table(sorties: Sequence[Sortie]) -> FrameTable:
    """The frames of the recordings (in recording order) without decoding any image."""
    t, srt, idx = [], [], []
    w = h = 0
    for n, msg in _frames(sorties, decode=False):
        t.append(msg.header.t_measurement_ns)
        srt.append(n)
        idx.append(msg.frame_index)
        w, h = msg.width_px, msg.height_px
    return FrameTable(np.asarray(t, dtype=np.int64), np.asarray(srt, dtype=np.int64), np.asarray(idx, dtype=np.int64),
                      int(w), int(h))


def decode_image(msg: CameraFrame) -> np.ndarray | None:
    """BGR uint8 (H, W, 3) of a recorded frame, None when its data does not decode."""
    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
    return img if img is not None and img.ndim == 3 else None


def iter_images(sorties: Sequence[Sortie], wanted: Iterable[int]) -> Iterator[tuple[int, np.ndarray | None]]:
    """``(i, image)`` for the frames at positions ``wanted`` (recording order, as :func:`frame_table`), decoded one
    at a time: memory holds one image whatever the flight's length (None: the frame's data does not decode)."""
    want = sorted(set(int(i) for i in wanted))
    if not want:
        return
    k = 0
    for i, (_, msg) in enumerate(_frames(sorties, decode=True)):
        if i < want[k]:
            continue
        yield i, decode_image(msg)
        k += 1
        if k == len(want):
            return


def recording_paths(sorties: Sequence[Sortie]) -> list[Path]:
    return [s.path for s in sorties]
