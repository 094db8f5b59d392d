"""Monocular reconstruction of a capture (one drone's camera): the pipeline, placed in the world, exported.

:func:`reconstruct_capture` takes a :class:`reconstruction.capture.Capture` (from the flight-folder reader
:func:`reconstruction.multiview.flight.read_flight` or :func:`reconstruction.synth.synthesize_capture`),
picks one camera and its most confident detector, runs :func:`reconstruction.monocular.pipeline.reconstruct_monocular`
on the span in which the camera sees the person (with the true, uneven frame times) and writes BVH/NPZ/CSV/RRD
with :func:`reconstruction.export.export_motion`, plus ``config.toml`` and ``summary.json``.

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

from reconstruction.capture import Capture, CaptureError
from reconstruction.monocular.dictionary import load_dictionary
from reconstruction.monocular.pipeline import MonocularConfig, reconstruct_monocular, to_world_metric

log = logging.getLogger(__name__)

__all__ = ["reconstruct_capture", "read_flight_cameras"]


def read_flight_cameras(flight_dir: str | Path, camera: str | None = None) -> Capture:
    """The drones of a flight folder as a :class:`Capture` (one drone is enough here), read with the
    multiview package's per-drone reader :func:`reconstruction.multiview.flight.read_drone_log`
    (``read_flight`` itself requires two drones). With ``camera`` only that drone's file is read."""
    from reconstruction.multiview.flight import read_drone_log

    flight_dir = Path(flight_dir)
    files = sorted(flight_dir.glob("drone_*.mcap"))
    if camera is not None:
        files = [f for f in files if f.stem == camera] or files
    if not files:
        raise CaptureError(f"{flight_dir} holds no drone_<i>.mcap files; pass a flight folder written by the onboard recorder")
    cams = []
    for f in files:
        try:
            cams.append(read_drone_log(f))
        except CaptureError as e:
            log.warning("skipping %s: %s", f.name, e)
    if not cams:
        raise CaptureError(f"{flight_dir}: no drone log with keypoints (need drone_<i>.mcap with keypoints2d)")
    return Capture(cams, meta={"source": str(flight_dir)})


def reconstruct_capture(
    cap: Capture,
    out_dir: str | Path,
    camera: str | None = None,
    variant: str = "perspective",
    body_rms_radius_m: float | None = None,
    cfg: MonocularConfig | None = None,
    rrd: bool = True,
) -> dict:
    """Reconstruct one camera of ``cap`` into ``out_dir``; returns the summary dict (also written)."""
    from reconstruction.export import export_motion
    from skycap.config import save_config

    cfg = cfg or MonocularConfig(ablation_no_articulation=False)
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
    if variant not in ("paper", "extended", "perspective"):
        raise CaptureError(f"variant must be 'paper', 'extended' or 'perspective', not {variant!r}")
    persp = variant == "perspective"
    if persp and body_rms_radius_m is not None:
        # the perspective BA's size reference is the bones' RMS length: the adult's, scaled like the given radius
        pc = cfg.perspective
        bone_rms = pc.body_bone_rms_m * body_rms_radius_m / pc.body_rms_radius_m
        cfg = dataclasses.replace(cfg, perspective=dataclasses.replace(pc, body_rms_radius_m=body_rms_radius_m,
                                                                       body_bone_rms_m=bone_rms))  # fmt: skip
    dt_s = float(np.median(np.diff(t_frame_ns))) * 1e-9
    res = reconstruct_monocular(W, conf, d, cfg, T_world_cam=T_wc, extended=variant != "paper", K=K, perspective=persp, dt_s=dt_s,
                                t_ns=t_frame_ns)  # fmt: skip
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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    cams = [{"name": cam.name, "t_ns": t_frame_ns, "T_world_cam": T_wc, "K": K[-1], "width_px": cam.width_px,
             "height_px": cam.height_px}]  # fmt: skip
    paths = export_motion(out, joints, t_frame_ns, params=params, shape=shape, cameras=cams, capture=cap, rrd=rrd)
    summary = {
        "method": "monocular", "variant": variant, "camera": cam.name, "detector": cam.detectors[det],
        "frames": int(len(t_frame_ns)), "init_seconds": res.init_seconds, "ba_seconds": res.ba_seconds,
        "perspective_seconds": res.perspective_seconds, "body_model_fit": res.model is not None,
        "model_seconds": res.model_seconds, "lifted_seconds": res.lifted_seconds,
        "perspective_start": res.perspective_start, "model_start": res.model_start,
        "body_rms_radius_m": radius, "outputs": {k: str(v) for k, v in paths.items()},
        **({"body_scale": res.ba_perspective.body_scale,
            "bone_rms_m": res.ba_perspective.body_scale * cfg.perspective.body_bone_rms_m} if persp else {}),
    }  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
