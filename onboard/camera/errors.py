"""Errors of the camera capture (user-facing: the CLI prints the message alone)."""

from __future__ import annotations

from skycap.errors import SkycapError

__all__ = ["CameraSourceError"]


class CameraSourceError(SkycapError):
    """A camera source that cannot be opened or read (missing device, bad pipeline, GStreamer absent ...)."""
