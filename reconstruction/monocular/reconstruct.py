"""Monocular reconstruction of a capture (one drone's camera): the pipeline, placed in the world, exported.

:func:`run` (the method as a library function: ``run(capture, MonocularRunConfig(...), out_dir=..., progress=...)
-> MonocularRunResult``) takes a :class:`reconstruction.capture.Capture` (from the flight-folder reader
:func:`read_flight_cameras` / :func:`reconstruction.flight.read_capture` or :func:`reconstruction.synth.synthesize_capture`),
picks one camera and its most confident detector, runs :func:`reconstruction.monocular.pipeline.reconstruct_monocular`
on the span in which the camera sees the person (with the true, uneven frame times) and, with ``out_dir``, writes
BVH/NPZ/CSV/RRD with :func:`reconstruction.export.export_motion`, plus ``config.toml`` and ``summary.json``.
The flight-level entry (``skycap reconstruct --method monocular``) is :func:`reconstruction.api.reconstruct_flight`.

Placement in the world: the default (``variant="perspective"``) is the perspective BA with the drone's camera
poses (:mod:`reconstruction.monocular.perspective`): the body's metric scale from an adult bone-length prior and
the orbit's parallax (``summary.json``: ``body_scale``), started from the orthographic BAs and from the learned
single-frame lift (``summary.json``: ``perspective_start``, the start kept); then, by default (``cfg.model.enabled``), the body model
fitted from it (:func:`reconstruction.monocular.pipeline.model_fit`) gives the exported joints and the model
parameters (``root_orient``, ``pose``, ``transl``, ``shape`` in the npz, as from the multi-view path). The orthographic variants have no metric scale: the
person is given the RMS joint radius of the dictionary's mean pose (or ``body_rms_radius_m``) and placed along
the camera ray of its 2D centre at the depth that this size implies
(:func:`reconstruction.monocular.pipeline.to_world_metric`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from reconstruction.result import Progress, ReconstructionError, ReconstructionResult, report
from reconstruction.capture import Capture, CaptureError
from reconstruction.flight import recordings_summary
from reconstruction.monocular.dictionary import load_dictionary
from reconstruction.monocular.pipeline import MonocularConfig, MonocularResult, reconstruct_monocular, to_world_metric

log = logging.getLogger(__name__)

__all__ = ["MonocularRunConfig", "MonocularRunResult", "VARIANTS", "read_capture", "read_flight_cameras", "run"]

VARIANTS = ("paper", "extended", "perspective")


def _default_pipeline() -> MonocularConfig:
    return MonocularConfig(ablation_no_articulation=False)


@dataclasses.dataclass
class MonocularRunConfig:
    """The monocular reconstruction's settings.

    camera: the camera (drone) to use (None: the first, in natural order); variant: the BA -- ``"paper"``,
    ``"extended"`` (with the drone attitude prior) or ``"perspective"`` (in the world with the drone's camera poses,
    default); body_rms_radius_m: assumed RMS joint radius of the person (None: the dictionary mean pose's;
    perspective: scales the adult bone-length prior); pipeline: the algorithm's settings
    (:class:`reconstruction.monocular.pipeline.MonocularConfig`, written as the output's ``config.toml``);
    rrd: also write the Rerun recording.
    """

    camera: str | None = None
    variant: str = "perspective"
    body_rms_radius_m: float | None = None
    pipeline: MonocularConfig = dataclasses.field(default_factory=_default_pipeline)
    rrd: bool = True

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ReconstructionError(f"variant must be 'paper', 'extended' or 'perspective', not {self.variant!r}")
        if self.body_rms_radius_m is not None and not self.body_rms_radius_m > 0:
            raise ReconstructionError(f"body_rms_radius_m={self.body_rms_radius_m} must be > 0 (or None for the default)")


@dataclasses.dataclass
class MonocularRunResult(ReconstructionResult):
    """:class:`reconstruction.api.ReconstructionResult` plus the camera used and the pipeline's result
    (:class:`reconstruction.monocular.pipeline.MonocularResult`)."""

    camera: str = ""
    pipeline: MonocularResult | None = None


def read_flight_cameras(flight, camera: str | None = None, sortie: int | None = None,
                        progress: Progress | None = None) -> Capture:
    """The drones of a flight folder (a :class:`flightdata.folder.FlightFolder` or its path) as a :class:`Capture`
    (one drone is enough here; :func:`reconstruction.flight.read_capture`), the whole flight or one ``sortie``.
    With ``camera`` (a drone id of the flight) only that drone's recordings are read."""
    from flightdata.folder import FlightFolder
    from reconstruction.flight import read_capture as read_flight_capture

    flight = flight if isinstance(flight, FlightFolder) else FlightFolder(flight)
    ids = [camera] if camera is not None and camera in flight.drone_ids() else None
    return read_flight_capture(flight, sortie=sortie, drone_ids=ids, min_cameras=1, progress=progress)


def read_capture(flight, config: MonocularRunConfig | None = None, *, sortie: int | None = None,
                 progress: Progress | None = None) -> Capture:
    """The capture of a flight folder for this method (:func:`read_flight_cameras` of ``config.camera``)."""
    config = config or MonocularRunConfig()
    return read_flight_cameras(flight, camera=config.camera, sortie=sortie, progress=progress)


def run(cap: Capture, config: MonocularRunConfig | None = None, *, out_dir: str | Path | None = None,
        progress: Progress | None = None) -> MonocularRunResult:
    """Reconstruct one camera of ``cap`` (``config.camera``); with ``out_dir`` write the motion, ``config.toml`` and
    ``summary.json`` there. progress: ``("monocular", 0|1, 1)`` around the pipeline, then ``("export", 0|1, 1)``."""
    from reconstruction.export import export_motion
    from skycap.config import save_config

    config = config or MonocularRunConfig()
    cfg, camera, variant, body_rms_radius_m = config.pipeline, config.camera, config.variant, config.body_rms_radius_m
    names = [c.name for c in cap.cameras]
    if camera is None:
        cam = cap.cameras[0]
        if len(names) > 1:
            log.warning("capture has %d cameras; the monocular method uses %s (choose with --mono-camera)", len(names), cam.name)
    elif camera in names:
        cam = cap.cameras[names.index(camera)]
    else:
        raise CaptureError(f"camera {camera!r} not in the capture; cameras: {', '.join(names)}")
    if cam.num_frames < 10:
        raise CaptureError(f"camera {cam.name!r} has {cam.num_frames} frames with keypoints; need at least 10")
    det = int(np.argmax(cam.confidence.mean(axis=(0, 2))))
    # only the span in which the camera sees the person (take-off and landing look at the ground or the sky)
    seen = np.flatnonzero((cam.confidence[:, det] >= 0.3).sum(axis=-1) >= 8)
    if len(seen) < 10:
        raise CaptureError(f"camera {cam.name!r} sees the person (>= 8 keypoints at confidence >= 0.3) in {len(seen)} "
                           f"frames; need at least 10")
    span = slice(int(seen[0]), int(seen[-1]) + 1)
    t_frame_ns = cam.t_frame_ns[span]
    conf = cam.confidence[span, det]
    W = np.swapaxes(cam.keypoints_px[span, det], 1, 2)
    W = np.where((conf > 0)[:, None, :], W, np.nan)
    T_wc = cam.pose_at(t_frame_ns)
    K = cam.K_at(t_frame_ns)
    d = load_dictionary()
    persp = variant == "perspective"
    if persp and body_rms_radius_m is not None:
        # the perspective BA's size reference is the bones' RMS length: the adult's, scaled like the given radius
        pc = cfg.perspective
        bone_rms = pc.body_bone_rms_m * body_rms_radius_m / pc.body_rms_radius_m
        cfg = dataclasses.replace(cfg, perspective=dataclasses.replace(pc, body_rms_radius_m=body_rms_radius_m,
                                                                       body_bone_rms_m=bone_rms))  # fmt: skip
    dt_s = float(np.median(np.diff(t_frame_ns))) * 1e-9
    log.info("monocular reconstruction (%s) of camera %s over %d frames", variant, cam.name, len(t_frame_ns))
    report(progress, "monocular", 0, 1)
    res = reconstruct_monocular(W, conf, d, cfg, T_world_cam=T_wc, extended=variant != "paper", K=K, perspective=persp, dt_s=dt_s,
                                t_ns=t_frame_ns)  # fmt: skip
    report(progress, "monocular", 1, 1)
    if variant == "extended" and res.ba_extended is not None:
        ba, frame = res.ba_extended, res.ba_extended_frame
    else:
        ba, frame = res.ba, "canonical"
    radius = body_rms_radius_m
    params = {"S_orthographic_px": ba.S, "R_orthographic": ba.R, "weights": res.weights, "init_S_px": res.init.S}
    shape = None
    if persp:
        joints = res.ba_perspective.X  # placed by the perspective BA with the camera poses
        radius = cfg.perspective.body_rms_radius_m
        if res.model is not None:  # the body model fitted after it: joints and model parameters, as the multi-view path
            joints, shape = res.model.joints_ned, res.model.shape
            params = {**params, **res.model.params()}
    else:
        if radius is None:
            mp = d.mean_pose if d.mean_pose is not None else d.bases[0]
            radius = float(np.sqrt(np.mean(np.sum(mp**2, axis=0))))
        joints = to_world_metric(ba.S, ba.R, W, res.weights, T_wc, K, radius, frame=frame)
    out = Path(out_dir) if out_dir is not None else None
    paths = {}
    if out is not None:
        report(progress, "export", 0, 1)
        out.mkdir(parents=True, exist_ok=True)
        save_config(cfg, out / "config.toml")
        cams = [{"name": cam.name, "t_ns": t_frame_ns, "T_world_cam": T_wc, "K": K[-1], "width_px": cam.width_px,
                 "height_px": cam.height_px}]  # fmt: skip
        paths = export_motion(out, joints, t_frame_ns, params=params, shape=shape, cameras=cams, capture=cap, rrd=config.rrd)
    summary = {
        "method": "monocular", "variant": variant, "camera": cam.name, "detector": cam.detectors[det],
        "frames": int(len(t_frame_ns)), "init_seconds": res.init_seconds, "ba_seconds": res.ba_seconds,
        "perspective_seconds": res.perspective_seconds, "body_model_fit": res.model is not None,
        "model_seconds": res.model_seconds, "lifted_seconds": res.lifted_seconds,
        "perspective_start": res.perspective_start, "model_start": res.model_start,
        "body_rms_radius_m": radius, "outputs": {k: str(v) for k, v in paths.items()},
        **({"body_scale": res.ba_perspective.body_scale,
            "bone_rms_m": res.ba_perspective.body_scale * cfg.perspective.body_bone_rms_m} if persp else {}),
        **recordings_summary(cap, [cam.name]),
    }  # fmt: skip
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        report(progress, "export", 1, 1)
        log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return MonocularRunResult(method="monocular", t_ns=t_frame_ns, joints_ned=joints, summary=summary, out_dir=out,
                              outputs=dict(paths), camera=cam.name, pipeline=res)  # fmt: skip
