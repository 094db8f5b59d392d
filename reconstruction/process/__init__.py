"""``skycap process``: a recorded flight -> 3D body motion from the recorded images with the shipped 2D models;
boxes -> keypoints -> fit -> export, cached and resumable. See :mod:`reconstruction.process.pipeline`.

Light on purpose: the names below are imported on first use (``skycap --help`` does not load torch).
"""

from __future__ import annotations

__all__ = ["Cancelled", "ProcessConfig", "ProcessError", "ProcessResult", "ProgressEvent", "STEPS", "process"]


def __getattr__(name: str):
    if name in ("Cancelled", "ProcessError", "ProgressEvent", "STEPS"):
        from reconstruction.process import events

        return getattr(events, name)
    if name == "ProcessConfig":
        from reconstruction.process.config import ProcessConfig

        return ProcessConfig
    if name in ("process", "ProcessResult"):
        from reconstruction.process import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)
