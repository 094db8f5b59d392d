"""Background jobs of the ground station: "process flight" as a job of :mod:`reconstruction.jobs` -- the pipeline
``skycap process`` runs (boxes -> keypoint models -> fit -> exports, cached in the flight folder and resumable) on the
app's runner: a local worker process by default, a Ray cluster with ``jobs.runner = "ray"`` (``GsConfig.jobs``).

    runner = runner_from_config(cfg.jobs)
    job = ProcessFlightJob.submit("flights/f1", runner, ['keypoints.source="sim"'])
    job.progress()   # (state, stage, elapsed_s): state "queued" / "running" / "done" / "failed" / "cancelled"
    job.fraction()   # 0..1 over the whole pipeline (each step weighted by its usual share of the time)
    job.log()        # one line per step change, and the worker's log lines
    job.cancel()     # stops at the pipeline's next batch; finished steps stay cached (processing again resumes)
    job.result()     # {"summary", "method", "outputs"} once done (None before, or cancelled; raises on failure)

No Qt and no torch here (the worker imports the pipeline; its result comes back as plain data): the widgets poll it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from flightdata.folder import FlightFolder
from reconstruction.jobs import Job, JobCancelled, JobStatus
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["JobError", "ProcessFlightJob", "STEP_WEIGHTS", "list_flights"]


class JobError(SkycapError):
    """A background job that could not start or failed (its log says why)."""


#: the pipeline's steps and their usual share of the processing time (the keypoint models dominate), for one
#: progress bar over the whole job
STEP_WEIGHTS: dict[str, float] = {"boxes": 0.1, "keypoints": 0.55, "fit": 0.3, "export": 0.05}
_STAGE_NAMES = {"boxes": "finding the person (boxes)", "keypoints": "2D keypoints (models)",
                "fit": "fitting the body model", "export": "writing the outputs"}


class ProcessFlightJob:
    """"process flight" of one flight folder, as a :class:`reconstruction.jobs.Job` (processor
    ``"process_summary"``), seen the way the Flights tab shows it."""

    def __init__(self, job: Job, flight: FlightFolder):
        self.job = job
        self.flight = flight

    @classmethod
    def submit(cls, flight_dir: str | Path, runner: Any, overrides: list[str] | None = None) -> "ProcessFlightJob":
        """Submit ``flight_dir`` to ``runner`` (a LocalRunner / RayRunner); ``overrides``: ``--set`` overrides of
        the pipeline's ProcessConfig (e.g. ``['keypoints.source="sim"']``)."""
        flight = FlightFolder(flight_dir)
        if not flight.has_recordings():
            raise JobError(f"{flight.path} holds no drone recording (<drone>.sNNN.mcap): nothing to process")
        job = runner.submit(flight.path, list(overrides or []), processor="process_summary")
        log.info("process flight %s: job %s on %s", flight.path, job.id, job.runner_name)
        return cls(job, flight)

    def progress(self) -> tuple[str, str, float]:
        """(state, stage, elapsed_s): state "queued", "running", "done", "failed" or "cancelled"."""
        st = self.job.status
        ev = self.job.progress
        if st == JobStatus.RUNNING:
            stage = "starting (loading the models)" if ev is None else _STAGE_NAMES.get(ev.step, ev.step)
            if ev is not None and ev.eta_s is not None and ev.fraction < 1.0:
                stage += f", {ev.eta_s:.0f} s left in this step"
        else:
            stage = str(st)
        return str(st), stage, self.job.elapsed_s

    def fraction(self) -> float:
        """0..1 over the whole pipeline (1 when done)."""
        if self.job.status == JobStatus.DONE:
            return 1.0
        ev = self.job.progress
        if ev is None or ev.step not in STEP_WEIGHTS:
            return 0.0
        steps = list(STEP_WEIGHTS)
        before = sum(STEP_WEIGHTS[s] for s in steps[: steps.index(ev.step)])
        return min(1.0, before + STEP_WEIGHTS[ev.step] * ev.fraction)

    def log(self) -> list[str]:
        lines, last = [], None
        for ev in self.job.events:
            if ev.step != last:
                lines.append(f"[{ev.elapsed_s:6.1f} s] step {ev.step}: {ev.message}")
                last = ev.step
        return lines + self.job.log

    def cancel(self) -> None:
        if not self.job.done():
            log.info("cancelling the processing of %s", self.flight.path)
            self.job.cancel()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self.job.wait(timeout_s)

    def result(self) -> dict | None:
        """{"summary", "method", "outputs": {"dir", "bvh", "files", name: path}} once done; None while running or
        when cancelled; a failure raises :class:`JobError` with the worker's message."""
        if not self.job.done():
            return None
        try:
            res = self.job.result(0)
        except JobCancelled:
            return None
        except Exception as e:  # noqa: BLE001 - the worker's error, shown to the operator
            raise JobError(f"processing failed: {type(e).__name__}: {e}; last lines: "
                           f"{' | '.join(self.log()[-5:])}") from e
        d = Path(res["out_dir"])
        outputs = {**res["outputs"], "dir": str(d), "bvh": sorted(str(p) for p in d.glob("*.bvh")),
                   "files": sorted(p.name for p in d.iterdir()) if d.is_dir() else []}
        return {"summary": res["summary"], "method": res["method"], "outputs": outputs}


def list_flights(root: str | Path) -> list[dict]:
    """The flight folders under ``root`` (newest first): drones, sorties, whether processed."""
    root = Path(root)
    out = []
    if not root.is_dir():
        return out
    for p in sorted(root.iterdir(), key=lambda p: p.stat().st_mtime, reverse=True):
        if not p.is_dir():
            continue
        f = FlightFolder(p)
        try:
            ids = f.drone_ids()
        except Exception as e:  # noqa: BLE001 - a broken folder is listed with its problem
            out.append({"path": str(p), "name": p.name, "drones": [], "error": str(e)})
            continue
        if not ids:
            continue
        recon = [m for m in ("multiview", "monocular") if (f.reconstruction_dir(m) / "summary.json").exists()]
        out.append({"path": str(p), "name": p.name, "drones": ids,
                    "sorties": max(len(f.sorties(d)) for d in ids), "processed": recon,
                    "mb": round(sum(q.stat().st_size for q in p.glob("*.mcap")) / 1e6, 1)})
    return out
