"""The flight-grade evaluation harness: real motion -> virtual drones with the FLIGHT's errors -> the real keypoint
models on rendered images -> the multi-view fit -> metrics (``skycap harness``).

The same orbit geometry, fit and metrics as the multiview harness (:mod:`reconstruction.multiview.evaluate`,
:func:`reconstruction.synth.synthesize_capture`), with two inputs made as on the product's own flights:

* **Drone poses** (``pose_errors``): ``"flight"`` (default) = the simulator's estimator error model
  (:class:`simulator.config.EstimatorConfig`; :class:`simulator.vehicle.environment.EstimatorErrorModel` on a
  simulated flight): per drone a Gauss-Markov position bias (horizontal / vertical std, correlation time 60 s) plus
  white position noise, a Gauss-Markov attitude error (1 deg per axis, correlation time 1 s; by default its yaw alone
  turns the camera, as on the product's gimbal-stabilised drones whose tilt the gimbal reports:
  ``synth.flight_errors.attitude_axes = "all"`` for a body-fixed camera), the processes in their
  stationary state (the drones have flown ``synth.flight_errors.margin_s`` before the clip), velocity reported, no
  angular velocity (as the flight reader gives the fit). ``position_grade`` picks the estimator's preset,
  ``"rtk"`` (default, cm-level bias) or ``"gps"`` (m-level), from :data:`simulator.config.POSITION_GRADES` -- the
  presets ``skycap demo`` flies with. ``"white"`` = the original harness's white noise (``synth.camera_*_noise``).
* **2D keypoints** (``keypoints``): ``"models"`` (default) = each camera's frames rendered by the simulator's
  renderer (:class:`simulator.scene.render.Renderer`, ``camera.person_model = "anny"``: the posed Anny body, its
  shape and outfit from ``person.body_seed``, shadow on textured ground, the camera's resolution, blur and sensor
  noise; the person posed with the clip's joints at the frame time, seen from the TRUE camera pose), the shipped
  keypoint models run on the person's box (the rendered mesh's box: the harness does not score the box detector)
  and fused per joint as ``skycap process`` does (:func:`reconstruction.process.keypoints.fuse_keypoints`).
  ``"sim"`` = simulated 2D (true projections + noise, outliers, swaps, misses) with the simulator's simulated
  detector's rates (:class:`simulator.scene.config.SimDetectorConfig`) at this camera's scale.

Camera: the simulator's (:class:`simulator.scene.config.CameraConfig`; default 640x360, 70 deg, 10 Hz). Metrics as
the multiview harness (``mpjpe_mm``, ``pa_mpjpe_mm``, ``w_mpjpe_mm``, ``root_err_mm``, ``per_group_mm``, ...) plus
``keypoints_source`` (``"models:<names>"`` or ``"sim"``), ``position_grade`` (``"rtk"``, ``"gps"`` or ``"white"``)
and ``render_ms_per_frame`` / ``keypoints_ms_per_frame``. Example::

    skycap harness --motion ../shared/data/mocap/cmu/002/002_05.bvh --frames 25 --out out/h   # 2.5 s, RTK, models
    skycap harness --motion FILE.bvh --keypoints sim --position-grade gps --out out/h_gps

    from evaluation.harness import HarnessConfig, run_harness
    metrics = run_harness(HarnessConfig(motion="FILE.bvh", frames=25))
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from reconstruction.capture import Capture
from reconstruction.multiview.evaluate import clip_indices, load_motion, score_capture, write_outputs
from reconstruction.multiview.fit import FitConfig
from reconstruction.process.config import KeypointsConfig
from reconstruction.synth import POSE_ERRORS, FlightPoseErrors, SynthConfig, interpolate_joints, synthesize_capture
from simulator.config import POSITION_GRADES, EstimatorConfig, estimator_for_grade
from simulator.scene.config import CameraConfig, PersonConfig, SimDetectorConfig
from skycap.camera import PinholeCamera
from skycap.config import ConfigError

log = logging.getLogger(__name__)

__all__ = ["KEYPOINT_SOURCES", "HarnessConfig", "flight_errors_from_estimator", "resolve", "render_keypoints", "run_harness"]

#: where the harness's 2D keypoints come from: the real models on rendered images, or simulated
KEYPOINT_SOURCES = ("models", "sim")
#: a person's height the simulated 2D noise is scaled with (the simulated detector's noise grows with the box)
_PERSON_HEIGHT_M = 1.7


def _anny_camera() -> CameraConfig:
    return CameraConfig(person_model="anny")


def _harness_synth() -> SynthConfig:
    return SynthConfig(pose_errors="flight")


@dataclasses.dataclass
class HarnessConfig:
    """``skycap harness``'s settings (``--config`` / ``--set``); saved beside the outputs as config.toml, with the
    values :func:`resolve` derived (the grade's error numbers, the camera's intrinsics) filled in."""

    motion: str = ""
    out: str = ""
    #: output frames at the camera rate (camera.rate_hz; 0 = all): 25 = a 2.5 s clip at 10 Hz
    frames: int = 100
    start: int = 0
    #: seconds of the flight before and after the scored clip (where the motion has them) that the cameras film and
    #: the fit sees, unscored: a clip cut from a longer flight (0 = the fit sees the clip alone, as the old harness)
    context_s: float = 0.0
    seed: int = 0
    export: bool = True
    #: "models" (the keypoint models on rendered images) or "sim" (simulated 2D)
    keypoints: str = "models"
    #: "flight" (the simulator's estimator error model at ``position_grade``) or "white" (the original harness)
    pose_errors: str = "flight"
    #: "rtk" or "gps": simulator.config.POSITION_GRADES (with pose_errors = "flight")
    position_grade: str = "rtk"
    #: the estimator the grade's preset is applied to (default: the simulator's defaults; e.g.
    #: ``estimator.att_noise_std_deg=0`` takes the attitude error out, to measure its share)
    estimator: EstimatorConfig = dataclasses.field(default_factory=EstimatorConfig)
    #: the simulator's camera (resolution, field of view, rate, blur, noise) and person (Anny shape and outfit)
    camera: CameraConfig = dataclasses.field(default_factory=_anny_camera)
    person: PersonConfig = dataclasses.field(default_factory=PersonConfig)
    #: the keypoint models, their threads and fusion (as ``skycap process``)
    detect: KeypointsConfig = dataclasses.field(default_factory=KeypointsConfig)
    #: simulated 2D (keypoints = "sim"): the simulator's simulated detector's noise, outlier, swap and miss rates
    #: (its noise at the person's expected height in this camera; its time correlation and occlusion are not modelled)
    sim_detector: SimDetectorConfig = dataclasses.field(default_factory=SimDetectorConfig)
    #: orbit geometry and the pose-error numbers (synth.flight_errors is filled from the grade by :func:`resolve`)
    synth: SynthConfig = dataclasses.field(default_factory=_harness_synth)
    fit: FitConfig = dataclasses.field(default_factory=FitConfig)

    def validate(self) -> "HarnessConfig":
        if self.keypoints not in KEYPOINT_SOURCES:
            raise ConfigError(f"keypoints={self.keypoints!r}; use one of {', '.join(map(repr, KEYPOINT_SOURCES))}")
        if self.pose_errors not in POSE_ERRORS:
            raise ConfigError(f"pose_errors={self.pose_errors!r}; use one of {', '.join(map(repr, POSE_ERRORS))}")
        if self.position_grade not in POSITION_GRADES:
            raise ConfigError(f"position_grade={self.position_grade!r}; use one of "
                              f"{', '.join(map(repr, POSITION_GRADES))} (simulator.config.POSITION_GRADES)")
        if self.keypoints == "models" and self.camera.person_model != "anny":
            raise ConfigError("keypoints='models' needs camera.person_model='anny' (the models do not see the "
                              "ellipsoid person); set it, or use keypoints='sim'")
        self.camera.validate()
        return self


def flight_errors_from_estimator(est: EstimatorConfig, margin_s: float = 60.0, attitude_axes: str = "yaw") -> FlightPoseErrors:
    """The harness's pose-error model with the simulator's estimator numbers (the fields of the same names)."""
    names = {f.name for f in dataclasses.fields(EstimatorConfig)}
    own = [f.name for f in dataclasses.fields(FlightPoseErrors) if f.name in names]
    return FlightPoseErrors(**{n: float(getattr(est, n)) for n in own}, margin_s=margin_s, attitude_axes=attitude_axes)


def resolve(cfg: HarnessConfig) -> HarnessConfig:
    """A copy of ``cfg`` with what follows from its choices filled into ``synth``: the camera's size, focal length and
    rate; the grade's estimator errors (pose_errors = "flight"); the simulated detector's 2D error rates scaled to
    this camera (keypoints = "sim"). Validates."""
    cfg = dataclasses.replace(cfg, synth=dataclasses.replace(cfg.synth)).validate()
    cam = PinholeCamera.from_config(cfg.camera)
    s = cfg.synth
    s.width_px, s.height_px, s.focal_px, s.camera_rate_hz = cam.width_px, cam.height_px, cam.fx_px, cfg.camera.rate_hz
    s.pose_errors = cfg.pose_errors
    if cfg.pose_errors == "flight":
        s.flight_errors = flight_errors_from_estimator(estimator_for_grade(cfg.position_grade, cfg.estimator),
                                                      s.flight_errors.margin_s, s.flight_errors.attitude_axes)
    if cfg.keypoints == "sim":
        sd = cfg.sim_detector
        height_px = cam.fx_px * _PERSON_HEIGHT_M / math.hypot(s.radius_m, s.altitude_m)
        s.noise_px = math.hypot(sd.noise_px, sd.noise_frac_of_height * height_px)
        s.outlier_rate, s.swap_rate, s.miss_rate = sd.outlier_prob, sd.swap_prob, sd.miss_prob
    return cfg


def render_keypoints(cap: Capture, T_world_cam_frames: list[np.ndarray], t_ns: np.ndarray, joints_ned: np.ndarray,
                     cfg: HarnessConfig, models: list | None = None, stats: dict | None = None) -> Capture:
    """``cap`` with each camera's keypoints replaced by the keypoint models' (fused) on its rendered frames.

    Camera ``c``'s frame ``f`` is rendered from the true pose ``T_world_cam_frames[c][f]`` with the person posed by
    the joints (``joints_ned`` (T, 17, 3) at ``t_ns`` (T,)) interpolated to the frame time; the models run on the
    rendered mesh's box. ``models``: opened models (default: ``cfg.detect``'s). ``stats`` gets the CPU times."""
    from reconstruction.process.keypoints import fuse_keypoints, load_models
    from simulator.scene.render import Renderer

    kc = cfg.detect
    models = load_models(kc) if models is None else models
    stats = {} if stats is None else stats
    pin = PinholeCamera.from_config(cfg.camera)
    cams = []
    render_s = kp_s = 0.0
    errs, heights = [], []
    n_frames = 0
    for ci, cam in enumerate(cap.cameras):
        if cam.width_px != pin.width_px or cam.height_px != pin.height_px or not np.isclose(cam.K[0, 0, 0], pin.fx_px):
            raise ConfigError(f"{cam.name}: the capture's camera ({cam.width_px}x{cam.height_px}, f {cam.K[0, 0, 0]:.1f}"
                              f") is not the rendered one ({pin.width_px}x{pin.height_px}, f {pin.fx_px:.1f}); "
                              "build the capture with resolve(cfg).synth")
        renderer = Renderer(pin, cfg.camera, cfg.person, noise_seed=cfg.camera.noise_seed + 1000 * cfg.seed + ci)
        X = interpolate_joints(t_ns, joints_ned, cam.t_frame_ns)
        F = len(X)
        kp = np.full((F, len(models), 17, 3), np.nan)
        kp[..., 2] = 0.0
        box = np.full((F, 4), np.nan)
        uv_true = np.full((F, 17, 2), np.nan)
        tracks = [{} for _ in models]
        for b0 in range(0, F, kc.batch_size):
            ids, imgs = [], []
            t0 = time.process_time()
            for f in range(b0, min(F, b0 + kc.batch_size)):
                fr = renderer.render(T_world_cam_frames[ci][f], X[f])
                if fr.gt is None or fr.gt.box_px is None:
                    continue
                x0, y0, x1, y1 = fr.gt.box_px
                box[f] = (x0, y0, x1 - x0, y1 - y0)
                uv_true[f] = fr.gt.uv_px
                ids.append(f)
                imgs.append(fr.image)
            t1 = time.process_time()
            for m, model in enumerate(models):
                if not ids:
                    break
                if kc.track_rois and getattr(model, "predict_sequence", None) is not None:
                    kp[ids, m] = model.predict(imgs, box[ids], kc.batch_size, frame_ids=ids, track=tracks[m])
                else:
                    kp[ids, m] = model.predict(imgs, box[ids], kc.batch_size)
            render_s += t1 - t0
            kp_s += time.process_time() - t1
            n_frames += len(range(b0, min(F, b0 + kc.batch_size)))
        if kc.fuse:
            uv, conf = fuse_keypoints(kp, box, kc.agree_fraction, kc.min_confidence)
            uv, conf, dets = uv[:, None], conf[:, None], ("fused:" + "+".join(kc.models),)
        else:
            uv = np.nan_to_num(kp[..., :2])
            conf = np.where(np.isfinite(kp[..., 0]), np.nan_to_num(kp[..., 2]), 0.0)
            dets = tuple(kc.models)
        err = np.linalg.norm(uv[:, 0] - uv_true, axis=-1) / box[:, 3:4]  # (F, 17) fraction of the box height
        ok = np.isfinite(err) & (conf[:, 0] > 0)
        errs.append(err[ok])
        heights.append(box[np.isfinite(box[:, 3]), 3])
        stats.setdefault("frames_without_person", 0)
        stats["frames_without_person"] += int(np.sum(~np.all(np.isfinite(box), axis=1)))
        cams.append(dataclasses.replace(cam, keypoints_px=uv, confidence=conf, detectors=dets))
    stats["render_ms_per_frame"] = 1e3 * render_s / max(n_frames, 1)
    stats["keypoints_ms_per_frame"] = 1e3 * kp_s / max(n_frames, 1)
    stats["rendered_frames"] = n_frames
    e, h = np.concatenate(errs), np.concatenate(heights)
    # the fused keypoints against the true joints' projections (joint definitions differ a little: not all model error)
    stats["keypoint_err_median_frac_of_height"] = float(np.median(e)) if e.size else float("nan")
    stats["keypoint_err_p90_frac_of_height"] = float(np.percentile(e, 90)) if e.size else float("nan")
    stats["person_height_px_median"] = float(np.median(h)) if h.size else float("nan")
    return Capture(cams, meta={**cap.meta, "keypoints": "models", "models": list(kc.models)})


def run_harness(cfg: HarnessConfig, progress: bool = True, models: list | None = None) -> dict:
    """Run the harness (module doc); writes ``cfg.out``/metrics.json, config.toml (+ exports) when ``cfg.out`` is
    set. Returns the metrics. ``models``: already opened keypoint models (tests share them)."""
    cfg = resolve(cfg)
    J, t_ns, fps = load_motion(cfg.motion)
    idx = clip_indices(len(J), fps, cfg.synth.camera_rate_hz, cfg.start, cfg.frames, cfg.motion)
    ctx = max(int(round(cfg.context_s * cfg.synth.camera_rate_hz)), 0)  # the flight goes on around the clip
    start_all = max(cfg.start - ctx, 0)
    idx_all = clip_indices(len(J), fps, cfg.synth.camera_rate_hz, start_all, cfg.start - start_all + len(idx) + ctx,
                           cfg.motion)
    scored = np.isin(idx_all, idx)
    lo, hi = idx_all[0], idx_all[-1] + 1
    cap, truth = synthesize_capture(J[lo:hi], t_ns[lo:hi], cfg.synth, seed=cfg.seed)
    stats: dict = {}
    if cfg.keypoints == "models":
        cap = render_keypoints(cap, truth.T_world_cam_true_frames, t_ns[lo:hi], J[lo:hi], cfg, models, stats)
    t_grid = t_ns[idx_all]
    res, metrics = score_capture(cap, truth, t_grid, J[idx], cfg.fit, cfg.motion, progress, scored)
    metrics["clip_s"] = float((t_ns[idx[-1]] - t_ns[idx[0]]) * 1e-9)
    metrics["keypoints_source"] = "models:" + "+".join(cfg.detect.models) if cfg.keypoints == "models" else "sim"
    metrics["position_grade"] = cfg.position_grade if cfg.pose_errors == "flight" else "white"
    metrics["pose_errors"] = cfg.pose_errors
    metrics.update({k: (round(v, 4) if isinstance(v, float) else v) for k, v in stats.items()})
    if cfg.out:
        write_outputs(cfg.out, cfg, metrics, res, cap, t_grid, J[idx_all], cfg.export)
    return metrics
