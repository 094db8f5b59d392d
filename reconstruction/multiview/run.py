"""The multiview method as a library function: :func:`run` (a capture and a :class:`MultiviewConfig` -> a
:class:`MultiviewResult`), and :func:`read_capture` (a flight folder -> the capture it takes).

    from reconstruction.multiview.run import MultiviewConfig, run

    res = run(capture, MultiviewConfig(), out_dir="out/rec", progress=lambda s, i, n: ...)
    res.joints_ned, res.fit.T_world_cam_refined, res.summary

The flight-level entry (what ``skycap reconstruct --method multiview`` calls) is
:func:`reconstruction.api.reconstruct_flight`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from reconstruction.result import Progress, ReconstructionError, ReconstructionResult, report
from reconstruction.capture import Capture
from reconstruction.flight import recordings_summary
from reconstruction.multiview.fit import FitConfig, FitResult, fit_capture
from reconstruction.export import export_motion
from reconstruction.multiview.flight import output_grid, read_flight
from skycap.config import save_config

log = logging.getLogger(__name__)

__all__ = ["MultiviewConfig", "MultiviewResult", "read_capture", "run"]

FIT_METHODS = ("product", "paper")


@dataclasses.dataclass
class MultiviewConfig:
    """The multiview reconstruction's settings.

    fit: the body fit (:class:`reconstruction.multiview.fit.FitConfig`; written as the output's ``config.toml``);
    rate_hz: output rate (None: the cameras' median frame rate); rrd: also write the Rerun recording;
    use_refined_poses: when reading a flight, subtract the offline smoother's drone position offsets
    (``refined_track.npz``, ``skycap refine``); gimbal_stabilised: the camera's gimbal holds roll and pitch.
    """

    fit: FitConfig = dataclasses.field(default_factory=FitConfig)
    rate_hz: float | None = None
    rrd: bool = True
    use_refined_poses: bool = False
    gimbal_stabilised: bool = True

    def __post_init__(self) -> None:
        if self.fit.method not in FIT_METHODS:
            raise ReconstructionError(f"unknown multiview fit {self.fit.method!r}; use one of {', '.join(FIT_METHODS)}")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ReconstructionError(f"rate_hz={self.rate_hz} must be > 0 (or None for the cameras' frame rate)")


@dataclasses.dataclass
class MultiviewResult(ReconstructionResult):
    """:class:`reconstruction.api.ReconstructionResult` plus the body fit (:class:`FitResult`: body model
    parameters, refined camera poses) and the capture it was fitted to."""

    fit: FitResult | None = None
    capture: Capture | None = None


def read_capture(flight, config: MultiviewConfig | None = None, *, sortie: int | None = None,
                 progress: Progress | None = None) -> Capture:
    """The capture of a flight folder for this method (:func:`reconstruction.multiview.flight.read_flight`:
    at least two drones with keypoints; the whole flight or one ``sortie``)."""

    config = config or MultiviewConfig()
    return read_flight(flight, gimbal_stabilised=config.gimbal_stabilised, use_refined_poses=config.use_refined_poses,
                       sortie=sortie, progress=progress)


def run(capture: Capture, config: MultiviewConfig | None = None, *, out_dir: str | Path | None = None,
        progress: Progress | None = None) -> MultiviewResult:
    """Fit the body (and the cameras) to ``capture`` over the span in which two cameras see the person.

    With ``out_dir``: writes ``config.toml`` (the fit config), ``motion.{bvh,npz,csv,rrd}``, ``capture.npz`` and
    ``summary.json`` (frames, cameras, fit_seconds, outputs and, for a capture read from a flight, ``sortie`` and
    ``recordings``). progress: ``("fit", i, iters)`` per optimiser step, then ``("export", 0|1, 1)``.
    """

    config = config or MultiviewConfig()
    grid = output_grid(capture, config.rate_hz)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        save_config(config.fit, out / "config.toml")
    log.info("multiview fit (%s) of %d cameras over %d frames", config.fit.method, capture.num_cameras, len(grid))
    res = fit_capture(capture, grid, config.fit, progress=progress if progress is not None else False)
    paths = {}
    if out is not None:
        report(progress, "export", 0, 1)
        cams = []
        for ci, cam in enumerate(capture.cameras):
            sel = res.cam_index == ci
            cams.append({"name": cam.name, "t_ns": res.cam_t_ns[sel], "T_world_cam": res.T_world_cam_refined[sel],
                         "K": cam.K[-1], "width_px": cam.width_px, "height_px": cam.height_px})  # fmt: skip
        paths = export_motion(out, res.joints_ned, res.t_ns, params=res.params(), shape=res.shape, cameras=cams,
                              capture=capture, rrd=config.rrd)  # fmt: skip
        capture.save(out / "capture.npz")
    summary = {"frames": int(len(grid)), "cameras": capture.num_cameras, "fit_seconds": res.fit_seconds,
               "outputs": {k: str(v) for k, v in paths.items()}, **recordings_summary(capture)}  # fmt: skip
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        report(progress, "export", 1, 1)
        log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return MultiviewResult(method="multiview", t_ns=res.t_ns, joints_ned=res.joints_ned, summary=summary, out_dir=out,
                           outputs=dict(paths), fit=res, capture=capture)  # fmt: skip
