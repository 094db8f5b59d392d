"""One captured frame, as every camera source hands it over."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Frame"]


@dataclass(frozen=True)
class Frame:
    """A decoded image with its capture time.

    ``image``: (H, W, 3) uint8 BGR (OpenCV order). ``t_capture_ns``: when the image was exposed (middle of the
    exposure where known), system realtime clock, ns since the UNIX epoch. ``frame_index``: the source's own
    counter (driver sequence, buffer offset, RTP-derived or file frame number): a gap means frames were dropped
    before they reached us. ``t_received_ns``: when the capture code got the buffer (same clock), so
    ``t_received_ns - t_capture_ns`` is the measured latency. ``exposure_s``: exposure time, None when unknown.
    """

    image: np.ndarray
    t_capture_ns: int
    frame_index: int
    t_received_ns: int
    exposure_s: float | None = None

    @property
    def width_px(self) -> int:
        return int(self.image.shape[1])

    @property
    def height_px(self) -> int:
        return int(self.image.shape[0])
