"""Today's flight reconstruction (:func:`reconstruction.api.reconstruct_flight`: the simulator's 2D keypoints, the
multi-view or monocular fit, the exports) as a job processor (registered as ``"reconstruct"``), and ``skycap process`` with a plain-data result
(``"process_summary"``)."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobCancelled, ProgressEvent

__all__ = ["ReconstructJobConfig", "process_summary_job", "reconstruct_job"]


@dataclasses.dataclass
class ReconstructJobConfig:
    """method: "multiview" / "monocular" / None (multiview with more than one drone); config: the method's config
    (None: its defaults); sortie: one sortie (None: the whole flight); out_dir: where the outputs go (None: the
    method's folder of the flight)."""

    method: str | None = None
    config: Any = None
    sortie: int | None = None
    out_dir: str | None = None


class _StageProgress:
    """``progress(stage, done, total)`` -> ProgressEvent with a per-stage ETA; raises JobCancelled once cancelled."""

    def __init__(self, emit: Callable[[ProgressEvent], None], cancel: threading.Event):
        self.emit, self.cancel = emit, cancel
        self.stage: str | None = None
        self.t_stage = time.monotonic()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.cancel.is_set():
            raise JobCancelled(f"cancelled during {stage} ({done}/{total})")
        now = time.monotonic()
        if stage != self.stage:
            self.stage, self.t_stage = stage, now
        frac = done / total if total > 0 else 1.0
        eta = (now - self.t_stage) * (1 - frac) / frac if frac > 0 else None
        self.emit(ProgressEvent(stage, frac, eta, f"{stage} {done}/{total}"))


def reconstruct_job(flight_dir: Path, cfg: ReconstructJobConfig | None, progress: Callable[[Any], None],
                    cancel: threading.Event):
    """``reconstruct_flight(flight_dir, ...)`` with progress events per stage and cancel checked at each report."""
    from reconstruction.api import reconstruct_flight

    cfg = cfg or ReconstructJobConfig()
    stages = _StageProgress(progress, cancel)
    stages("load", 0, 1)  # until reconstruct_flight reports: importing the reconstruction (torch, the body model)
    return reconstruct_flight(flight_dir, cfg.method, cfg.config, sortie=cfg.sortie, out_dir=cfg.out_dir,
                              progress=stages)


def process_summary_job(flight_dir: Path, cfg: Any, *, progress: Callable[[Any], None] | None = None,
                        cancel: threading.Event | None = None) -> dict:
    """:func:`reconstruction.process.process` (``cfg``: a ProcessConfig or a list of its ``--set`` overrides) whose
    result is returned as plain data -- ``{"method", "summary", "out_dir", "outputs": {name: path}}`` -- so that the
    submitter (the ground station) reads it without importing the pipeline (torch). Registered as
    ``"process_summary"``."""
    from reconstruction.process import process

    res = process(flight_dir, cfg, progress=progress, cancel=cancel)
    return {"method": res.method, "summary": res.summary, "out_dir": str(res.out_dir),
            "outputs": {k: str(v) for k, v in res.outputs.items()}}
