"""Flight folder -> the offline smoother -> ``refined_track.npz`` + ``refined_track.json`` (``skycap refine``).

Reads every drone of a flight folder (:class:`flightdata.folder.FlightFolder`, natural drone order): the whole
flight (every sortie of a drone, in sortie order) or one chosen sortie (:mod:`flightdata.flightlog`):

* the drone's own person detections: topic ``detections`` (what the tracking stage shared, with the camera
  pose covariance filled in) or, on flights without the tracking stage (orbit mode), ``sim/detections``
  (the simulator's detector; its empty pose covariance is filled from the positioning grade,
  ``camera_position_sigma_m``);
* ``camera_info`` (intrinsics), ``state`` (the drone's reported position), ``target`` (the live onboard
  estimate, for comparison) and ``sim/keypoints2d_gt`` (true person boxes, for evaluation only).

Every box is turned into a 3D measurement with :func:`onboard.tracking.measurement.measurements_from_detections`
(the onboard geometry, reused), all drones' measurements are smoothed together
(:func:`reconstruction.track.smoother.smooth_track`), and the results are written beside the recordings:

``refined_track.npz``
    ``drone_ids`` (D,), ``t_ns`` (N,), ``position_ned_m`` / ``velocity_ned_m_s`` (N, 3), ``covariance``
    (N, 6, 6) over (p, v), ``offset_ned_m`` (N, D, 3) and ``offset_cov_m2`` (N, D, 3, 3), ``on_grid`` (N,);
    per drone ``<id>.state_t_ns`` (S,), ``<id>.position_reported_ned_m`` / ``<id>.position_refined_ned_m``
    (S, 3) (reported minus the smoothed offset), and per detection frame ``<id>.frame_index`` /
    ``<id>.frame_t_ns`` (F,), ``<id>.box_px`` (F, 4: x_min, y_min, x_max, y_max: the smoothed person,
    an upright segment of the prior height, projected with the refined camera pose) and ``<id>.roi_px``
    (F, 4: x, y, w, h, grown by the projected uncertainty as onboard; NaN where the person is out of view).
``refined_track.json``
    counts, settings, the recordings read (``sortie``, ``recordings``: per drone its files) and, when
    ``truth.mcap`` is present (simulated flights), the evaluation (:func:`evaluate`).

Library entry: :func:`refine_flight` (a flight and a :class:`RefineConfig` -> a :class:`RefineResult`); ``skycap
refine`` (:mod:`apps.refine`) is a thin layer over it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from flightdata.folder import FlightFolder
from reconstruction.track.smoother import Observation, SmoothedTrack, SmootherConfig, SmootherError, smooth_track
import msgspec
from flightdata.flightlog import FlightLog
from flightdata.folder import read_sim_truth
from onboard.tracking.measurement import PERSON_HEIGHT_PRIOR_M, MeasurementConfig, box_from_person, measurements_from_detections
from onboard.tracking.roi import RoiConfig, box_in_roi, roi_from_estimate
from shared_msgs.messages import CameraInfo, Command, Detections, Keypoints2D, TargetEstimate, VehicleState
from skycap.camera import PinholeCamera

__all__ = ["DroneRecording", "RefineConfig", "RefineResult", "read_recordings", "flight_observations", "refine_flight",
           "frame_boxes", "evaluate", "load_refined_offsets", "format_evaluation"]

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]

MEASUREMENT_MODES = ("height_prior", "height_and_ground", "bearing", None)


def _folder(flight: FlightFolder | str | Path) -> FlightFolder:
    return flight if isinstance(flight, FlightFolder) else FlightFolder(flight)


def _report(progress: Progress | None, stage: str, done: int, total: int) -> None:
    if progress is not None:
        progress(stage, done, total)


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """The offline smoother's settings (``skycap refine``).

    smoother: :class:`reconstruction.track.smoother.SmootherConfig`; person_height_m: box height prior (None: the
    flight's ``config.toml`` ``track.person_height_m``, else the onboard prior); camera_position_sigma_m: camera
    position std for detections without pose covariance (None: from the flight's RTK/GPS setting, else 1 m);
    min_score: detections below are left out; measurement_mode: box -> 3D model (None: the onboard default; see
    :func:`flight_observations`).
    """

    smoother: SmootherConfig = dataclasses.field(default_factory=SmootherConfig)
    person_height_m: float | None = None
    camera_position_sigma_m: float | None = None
    min_score: float = 0.5
    measurement_mode: str | None = "height_prior"

    def __post_init__(self) -> None:
        if self.measurement_mode not in MEASUREMENT_MODES:
            raise SmootherError(f"measurement_mode {self.measurement_mode!r} is unknown; use one of "
                                f"{', '.join(str(m) for m in MEASUREMENT_MODES)} (None = the onboard default)")
        if self.person_height_m is not None and not self.person_height_m > 0:
            raise SmootherError(f"person_height_m={self.person_height_m} must be > 0 (or None for the flight's setting)")


@dataclasses.dataclass
class RefineResult:
    """What :func:`refine_flight` returns: ``summary`` (what ``refined_track.json`` holds), ``arrays`` (what
    ``refined_track.npz`` holds), the smoothed ``track``, the drones' ``recordings`` and the files written
    (``paths``: {"npz", "json"}; empty when not written)."""

    summary: dict
    arrays: dict[str, np.ndarray]
    track: SmoothedTrack
    recordings: list[DroneRecording]
    boxes: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    paths: dict[str, Path] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class DroneRecording:
    """What the smoother and its evaluation need from one drone's recording.

    detections: the drone's own Detections (time-ordered); state_t_ns (S,), state_position_ned_m (S, 3):
    its reported position; target_t_ns (T,), target_position_ned_m (T, 3): the live onboard estimate
    (empty without the tracking stage);
    gt_boxes: (sortie, frame_index) -> (4,) true person box (simulator only); detection_sorties (len(detections),):
    the sortie of each detection (frame indices restart with each sortie); files: the recordings read.
    """

    drone_id: str
    intrinsics: object  # onboard.tracking.measurement.PinholeCamera
    detections: list
    detections_topic: str
    state_t_ns: np.ndarray
    state_position_ned_m: np.ndarray
    target_t_ns: np.ndarray
    target_position_ned_m: np.ndarray
    gt_boxes: dict[tuple[int, int], np.ndarray]
    land_t_ns: int | None
    detection_sorties: np.ndarray | None = None
    files: tuple[str, ...] = ()

    def sorties_of_detections(self) -> np.ndarray:
        """The sortie of each detection (all 1 when not recorded)."""
        if self.detection_sorties is None:
            return np.ones(len(self.detections), dtype=np.int64)
        return self.detection_sorties


def read_recordings(flight: FlightFolder | str | Path, sortie: int | None = None,
                    progress: Progress | None = None, truth_boxes: bool = True) -> list[DroneRecording]:
    """Every drone of a flight folder (natural order) -> :class:`DroneRecording` (drones without detections are left
    out): the whole flight (``sortie=None``: every sortie of a drone, in sortie order) or only sortie ``sortie``.
    ``truth_boxes=False``: the simulator's true person boxes (``sim/keypoints2d_gt``, for :func:`evaluate` only)
    are not read (``gt_boxes`` stays empty)."""

    flight = _folder(flight)
    logs = flight.drone_logs(sortie=sortie)
    out = []
    topics = ["detections", "sim/detections", "camera_info", "state", "target", "gcs/cmd"] + (["sim/keypoints2d_gt"] if truth_boxes else [])
    for di, (d, sorties) in enumerate(logs.items()):
        name = ", ".join(s.path.name for s in sorties)
        dets = {"detections": [], "sim/detections": []}
        info = None
        st_t, st_p, tg_t, tg_p, gt = [], [], [], [], {}
        land = None
        for srt in sorties:
            for m in FlightLog(srt.path).messages(topics):
                msg = m.msg
                if isinstance(msg, Detections):
                    if msg.header.sender_id == d:
                        dets[m.topic].append((srt.number, msg))
                elif isinstance(msg, CameraInfo):
                    info = msg
                elif isinstance(msg, VehicleState):
                    st_t.append(msg.header.t_measurement_ns)
                    st_p.append(msg.position_ned_m)
                elif isinstance(msg, TargetEstimate):
                    tg_t.append(msg.header.t_measurement_ns)
                    tg_p.append(msg.position_ned_m)
                elif isinstance(msg, Keypoints2D):
                    if msg.persons and msg.persons[0].box is not None:
                        b = msg.persons[0].box
                        gt[(srt.number, msg.frame_index)] = np.array([b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px])
                elif isinstance(msg, Command) and msg.action == "land":
                    land = msg.header.t_sent_ns if land is None else min(land, msg.header.t_sent_ns)
        _report(progress, "read", di + 1, len(logs))
        topic = "detections" if dets["detections"] else "sim/detections"
        if not dets[topic]:
            log.warning("%s: no person detections (topics 'detections' / 'sim/detections'): left out", name)
            continue
        if info is None:
            raise SmootherError(f"{name}: no 'camera_info' messages; the camera intrinsics are needed")
        if not st_t:
            raise SmootherError(f"{name}: no 'state' messages; the drone's reported position is needed")
        o = np.argsort(st_t, kind="stable")
        ot = np.argsort(tg_t, kind="stable")
        det_sorted = sorted(dets[topic], key=lambda x: x[1].header.t_measurement_ns)
        out.append(DroneRecording(
            drone_id=d, intrinsics=PinholeCamera.from_camera_info(info),
            detections=[m for _, m in det_sorted], detections_topic=topic,
            state_t_ns=np.asarray(st_t, dtype=np.int64)[o], state_position_ned_m=np.asarray(st_p, dtype=float).reshape(-1, 3)[o],
            target_t_ns=np.asarray(tg_t, dtype=np.int64)[ot], target_position_ned_m=np.asarray(tg_p, dtype=float).reshape(-1, 3)[ot],
            gt_boxes=gt, land_t_ns=land, detection_sorties=np.array([n for n, _ in det_sorted], dtype=np.int64),
            files=tuple(s.path.name for s in sorties),
        ))  # fmt: skip
    if not out:
        raise SmootherError(f"{flight.path}: no drone recorded person detections ({flight.describe_logs(logs)}); "
                            "nothing to smooth: record with the detector running, or choose another --sortie")
    return out


def flight_settings(flight: FlightFolder | str | Path) -> dict:
    """Person height prior and positioning grade from the flight's ``config.toml`` (the demo's), else {}."""
    p = _folder(flight).config_path
    if not p.is_file():
        return {}
    try:
        cfg = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, OSError) as e:
        log.warning("cannot read %s (%s): using defaults", p, e)
        return {}
    out = {}
    track = cfg.get("track", {})
    if "person_height_m" in track:
        out["person_height_m"] = float(track["person_height_m"])
    rtk = track.get("rtk") if cfg.get("mode") == "track" else cfg.get("rtk")
    if rtk is not None:
        out["camera_position_sigma_m"] = 0.05 if rtk else 1.0
    return out


def flight_observations(recordings: list[DroneRecording], person_height_m: float | None = None,
                        camera_position_sigma_m: float = 1.0, camera_rotation_sigma_rad: float = 0.017,
                        min_score: float = 0.5, ground_down_m: float = 0.0, measurement_mode: str | None = "height_prior",
                        offset_step_m: float = 0.1) -> tuple[list[Observation], np.ndarray]:
    """All drones' detections -> smoother :class:`Observation` s, and the offsets' prior stds (D, 3).

    Each box goes through :func:`onboard.tracking.measurement.measurements_from_detections` (the onboard
    geometry, with its mode fallbacks) with the reported camera pose. ``measurement_mode`` (None = the
    onboard default) picks the model: "height_prior" (default here) is exactly invariant to a shift of the
    camera (``J_offset = I``), so the offsets are cleanly separable from the person; with the other modes
    ``J_offset`` is computed by running the geometry again with the camera shifted by ``offset_step_m``
    along each axis (forward differences). Why height-prior by default: the ground-plane point is anchored to
    the world, so the camera's vertical offset moves it along the line of sight; with the drones at fixed
    angles around the person (track mode) a common vertical offset plus radial horizontal offsets is then
    nearly unobservable, and on the 30 s track demo the smoother drifted along that direction (refined
    drone positions 2-3 m off, against 0.6 m with the height prior). A detection without pose
    covariance gets ``diag(camera_position_sigma_m^2 (3), camera_rotation_sigma_rad^2 (3))``. The prior std
    of drone i's offset is the median reported camera position std of its detections.
    """


    mcfg = MeasurementConfig() if person_height_m is None else dataclasses.replace(MeasurementConfig(), person_height_m=person_height_m)
    cov = tuple(float(v) for v in np.diag([camera_position_sigma_m**2] * 3 + [camera_rotation_sigma_rad**2] * 3).reshape(-1))
    kw = dict(ground_down_m=ground_down_m, min_score=min_score, config=mcfg)
    if measurement_mode is not None:
        kw["mode"] = measurement_mode
    out: list[Observation] = []
    sig = np.zeros((len(recordings), 3))
    for di, r in enumerate(recordings):
        pos_std = []
        for det in r.detections:
            if len(det.T_world_cam) != 16 or not det.boxes:
                continue
            if len(det.T_world_cam_cov) != 36:
                det = msgspec.structs.replace(det, T_world_cam_cov=cov)
            pos_std.append(np.sqrt(np.clip(np.diag(np.asarray(det.T_world_cam_cov, dtype=float).reshape(6, 6))[:3], 0, None)))
            T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4)
            for box in det.boxes:
                one = msgspec.structs.replace(det, boxes=[box])
                m0 = measurements_from_detections(one, r.intrinsics, **kw)
                if not m0:
                    continue
                J = np.eye(3)
                for i in range(3 if m0[0].mode not in ("height_prior",) else 0):
                    Ti = T.copy()
                    Ti[i, 3] += offset_step_m
                    mi = measurements_from_detections(msgspec.structs.replace(one, T_world_cam=tuple(Ti.reshape(-1))), r.intrinsics, **kw)
                    if len(mi) != 1 or mi[0].mode != m0[0].mode:
                        J = np.eye(3)  # the model switched at the shifted pose: the shift-invariant default
                        break
                    J[:, i] = (mi[0].position_ned_m - m0[0].position_ned_m) / offset_step_m
                out.append(Observation.from_measurement(m0[0], di, J))
        sig[di] = np.median(pos_std, axis=0) if pos_std else camera_position_sigma_m
    return out, sig


def frame_boxes(track: SmoothedTrack, rec: DroneRecording, person_height_m: float) -> dict[str, np.ndarray]:
    """Per detection frame of one drone: the smoothed person projected with the refined camera pose.

    Returns frame_index (F,), frame_t_ns (F,), box_px (F, 4) x_min, y_min, x_max, y_max and roi_px (F, 4)
    x, y, w, h (NaN rows where the person is behind the camera or outside the image, or outside the span), and
    frame_sortie (F,): the sortie of each frame (frame indices restart with each sortie).
    """

    d = track.drone_ids.index(rec.drone_id)
    rcfg = RoiConfig(person_height_m=person_height_m)
    fi = np.array([m.frame_index for m in rec.detections], dtype=np.int64)
    ft = np.array([m.header.t_measurement_ns for m in rec.detections], dtype=np.int64)
    box = np.full((len(fi), 4), np.nan)
    roi = np.full((len(fi), 4), np.nan)
    inside = (ft >= track.t_ns[0]) & (ft <= track.t_ns[-1])
    if inside.any():
        p = track.position_at(ft)
        off = track.offset_at(d, ft)
        k = np.clip(np.searchsorted(track.t_ns, ft), 0, len(track.t_ns) - 1)
        for j, m in enumerate(rec.detections):
            if not inside[j] or len(m.T_world_cam) != 16:
                continue
            T = np.asarray(m.T_world_cam, dtype=float).reshape(4, 4).copy()
            T[:3, 3] -= off[j]
            r = roi_from_estimate(p[j], track.covariance[k[j], :3, :3], rec.intrinsics, T, rcfg)
            if r is None:
                continue
            roi[j] = r
            box[j] = box_from_person(p[j], rec.intrinsics, T, person_height_m, rcfg.aspect_w_over_h)[0]
    return {"frame_index": fi, "frame_t_ns": ft, "box_px": box, "roi_px": roi, "frame_sortie": rec.sorties_of_detections()}


def refine_recordings(recs: list[DroneRecording], config: RefineConfig | None = None, *,
                      progress: Progress | None = None) -> RefineResult:
    """The offline smoother over drone recordings (:func:`read_recordings`): all drones' detections -> the smoothed
    person track, the drones' position offsets and the per-frame boxes/ROIs. ``config.person_height_m`` /
    ``camera_position_sigma_m`` left None take the onboard prior / 1 m (:func:`refine_flight` fills them from the
    flight's settings first). progress: ``("measurements", d, D)`` per drone, ``("smooth", 0|1, 1)``,
    ``("boxes", d, D)``. Writes nothing; ``summary`` has no flight-level fields (``flight_dir``, ``evaluation``)."""

    config = config or RefineConfig()
    H = float(config.person_height_m) if config.person_height_m is not None else PERSON_HEIGHT_PRIOR_M
    sig = config.camera_position_sigma_m if config.camera_position_sigma_m is not None else 1.0
    obs, offset_sigma = [], np.zeros((len(recs), 3))
    for di, r in enumerate(recs):  # one drone at a time, for the progress (flight_observations is per drone)
        o, s = flight_observations([r], H, sig, min_score=config.min_score, measurement_mode=config.measurement_mode)
        obs += [dataclasses.replace(x, drone=di) for x in o]
        offset_sigma[di] = s[0]
        _report(progress, "measurements", di + 1, len(recs))
    ids = [r.drone_id for r in recs]
    _report(progress, "smooth", 0, 1)
    track = smooth_track(obs, ids, config.smoother, offset_sigma_m=offset_sigma)
    _report(progress, "smooth", 1, 1)
    arrays: dict[str, np.ndarray] = {
        "drone_ids": np.array(ids), "t_ns": track.t_ns, "position_ned_m": track.position_ned_m,
        "velocity_ned_m_s": track.velocity_ned_m_s, "covariance": track.covariance, "offset_ned_m": track.offset_ned_m,
        "offset_cov_m2": track.offset_cov_m2, "on_grid": track.on_grid,
    }  # fmt: skip
    boxes = {}
    for di, r in enumerate(recs):
        arrays[f"{r.drone_id}.state_t_ns"] = r.state_t_ns
        arrays[f"{r.drone_id}.position_reported_ned_m"] = r.state_position_ned_m
        arrays[f"{r.drone_id}.position_refined_ned_m"] = r.state_position_ned_m - track.offset_at(di, r.state_t_ns)
        boxes[r.drone_id] = frame_boxes(track, r, H)
        for k in ("frame_index", "frame_t_ns", "box_px", "roi_px"):
            arrays[f"{r.drone_id}.{k}"] = boxes[r.drone_id][k]
        _report(progress, "boxes", di + 1, len(recs))
    acc = track.accepted
    summary = {
        "drones": ids,
        "detections_topic": {r.drone_id: r.detections_topic for r in recs},
        "person_height_m": H,
        "measurement_mode": config.measurement_mode or "onboard default",
        "camera_position_sigma_m": sig,
        "offset_prior_sigma_m": {d: [round(float(v), 4) for v in track.offset_sigma_m[i]] for i, d in enumerate(ids)},
        "measurements": len(obs),
        "frames": int(len(acc)),
        "frames_used": int(acc.sum()),
        "frames_rejected": int((~acc).sum()),
        "frames_downweighted": int(np.sum(acc & (track.frame_weight < 1.0))),
        "reweighting_passes": track.iterations,
        "span_s": round(float((track.t_ns[-1] - track.t_ns[0]) * 1e-9), 3),
        "offset_mean_ned_m": {d: [round(float(v), 3) for v in track.offset_ned_m[:, i].mean(axis=0)] for i, d in enumerate(ids)},
        "config": dataclasses.asdict(config.smoother),
    }
    return RefineResult(summary=summary, arrays=arrays, track=track, recordings=recs, boxes=boxes)


def refine_flight(flight: FlightFolder | str | Path, config: RefineConfig | None = None, *, sortie: int | None = None,
                  write: bool = True, progress: Progress | None = None) -> RefineResult:
    """Smooth a recorded flight (a :class:`FlightFolder` or its path): the whole flight (``sortie=None``: every
    sortie of each drone, in order) or one sortie. ``config`` fields left None are taken from the flight's
    ``config.toml`` (:func:`flight_settings`). With ``write``, writes ``refined_track.npz`` / ``.json`` (see the module
    doc). The summary names the recordings read (``sortie``, ``recordings``) and holds the ``evaluation`` when the
    flight has ``truth.mcap``. progress: as :func:`refine_recordings`, after ``("read", d, D)`` per drone."""
    flight = _folder(flight)
    config = config or RefineConfig()
    settings = flight_settings(flight)
    fill = {k: settings[k] for k in ("person_height_m", "camera_position_sigma_m")
            if getattr(config, k) is None and settings.get(k) is not None}
    config = dataclasses.replace(config, **fill) if fill else config
    recs = read_recordings(flight, sortie=sortie, progress=progress)
    used = {r.drone_id: list(r.files) for r in recs}
    log.info("refining %s of %s: %s", "the whole flight" if sortie is None else f"sortie {sortie}", flight.path,
             "; ".join(f"{d}: {', '.join(f)}" for d, f in used.items()))
    res = refine_recordings(recs, config, progress=progress)
    summary = {"flight_dir": str(flight.path), **res.summary, "sortie": sortie, "recordings": used}
    if flight.truth_path.is_file():
        _report(progress, "evaluate", 0, 1)
        summary["evaluation"] = evaluate(flight, res.track, recs, res.boxes)
        _report(progress, "evaluate", 1, 1)
    res.summary = summary
    if write:
        np.savez_compressed(flight.refined_npz_path, **res.arrays)
        flight.refined_json_path.write_text(json.dumps(summary, indent=2, default=_json_default))
        res.paths = {"npz": flight.refined_npz_path, "json": flight.refined_json_path}
        log.info("wrote %s and %s", flight.refined_npz_path, flight.refined_json_path)
    return res


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(type(o).__name__)


def load_refined_offsets(flight: FlightFolder | str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``refined_track.npz`` -> {drone id: (t_ns (N,), offset_ned_m (N, 3))}: what to subtract from the drone's
    reported positions (see :func:`reconstruction.flight.read_capture`, ``use_refined_poses``)."""
    flight = _folder(flight)
    p = flight.refined_npz_path
    if not p.is_file():
        raise SmootherError(f"{p} does not exist: run `skycap refine {flight.path}` first")
    z = np.load(p)
    ids = [str(s) for s in z["drone_ids"]]
    return {d: (z["t_ns"], z["offset_ned_m"][:, i]) for i, d in enumerate(ids)}


# ------------------------------------------------------------------------------------------------ evaluation
def _read_truth(path: Path, drone_ids: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_ns (T,), person root (T, 3), drone positions (T, D, 3)) from the simulator truth."""

    ts, person, veh, _ = read_sim_truth(path, drone_ids)
    if len(ts) < 2:
        raise SmootherError(f"{path} holds no simulator truth for {drone_ids}")
    return ts, person, veh


def _interp(tq: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    tq = (np.asarray(tq, dtype=np.int64) - t[0]).astype(float)
    tt = (t - t[0]).astype(float)
    return np.stack([np.interp(tq, tt, rows[:, i]) for i in range(rows.shape[1])], axis=-1)


def _rms3(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1)))) if len(e) else math.nan


def _window_ns(flight: FlightFolder, recs: list[DroneRecording], t_truth_end: int, settle_s: float) -> tuple[int, int]:
    """Steady window as the flight summary uses it: plan start + settle_s to the first land command."""
    t0 = None
    if flight.plan_path.is_file():
        t0 = flight.plan().start_time_ns + int(settle_s * 1e9)
    lands = [r.land_t_ns for r in recs if r.land_t_ns is not None]
    t1 = min(min(lands) if lands else t_truth_end, t_truth_end)
    if t0 is None:
        t0 = int(min(r.detections[0].header.t_measurement_ns for r in recs))
    return int(t0), int(t1)


def evaluate(flight: FlightFolder | str | Path, track: SmoothedTrack, recs: list[DroneRecording], boxes: dict[str, dict],
             settle_s: float = 8.0) -> dict:
    """The smoother against the simulator truth, beside the live onboard figures, over the steady window.

    * person track: RMS 3D error of the smoothed track (output grid), of its forward (causal, centralised)
      pass and of each drone's live ``target`` estimates, against the true person root at their own times;
      ``*_fleet_frame_m``: the same with the fleet's common position bias removed -- the window mean over the
      drones of (reported position - true position), the definition of the flight summary's
      ``target_rmse_fleet_frame_m``: no estimator can observe it without an absolute reference;
    * drone positions: RMS error of the reported and of the refined (reported - smoothed offset) positions, and
      the same in the fleet frame (each set's own common component -- window mean over drones -- removed);
    * regions of interest: the share of frames whose true person box lies inside the smoothed ROI and inside
      the live one (``roi_px`` of the shared detections, track mode), and the IoU of the smoothed person box
      with the true box.
    """

    flight = _folder(flight)
    ids = track.drone_ids
    rec_by = {r.drone_id: r for r in recs}
    tt, person, veh = _read_truth(flight.truth_path, ids)
    t0, t1 = _window_ns(flight, recs, int(tt[-1]), settle_s)
    if t1 <= t0:
        raise SmootherError(f"{flight.path}: no steady window (plan start + {settle_s} s to the land command)")

    # common bias (reported positions), as evaluation.flight defines it
    rep_err, ref_err = [], []
    drones = {}
    for di, d in enumerate(ids):
        r = rec_by[d]
        sel = (r.state_t_ns >= t0) & (r.state_t_ns <= t1)
        ts = r.state_t_ns[sel]
        true_p = _interp(ts, tt, veh[:, di])
        rep = r.state_position_ned_m[sel]
        ref = rep - track.offset_at(di, ts)
        rep_err.append(rep - true_p)
        ref_err.append(ref - true_p)
    common_rep = np.mean([e.mean(axis=0) for e in rep_err if len(e)], axis=0)
    common_ref = np.mean([e.mean(axis=0) for e in ref_err if len(e)], axis=0)
    for di, d in enumerate(ids):
        drones[d] = {
            "position_err_m_reported": round(_rms3(rep_err[di]), 3),
            "position_err_m_refined": round(_rms3(ref_err[di]), 3),
            "position_err_fleet_frame_m_reported": round(_rms3(rep_err[di] - common_rep), 3),
            "position_err_fleet_frame_m_refined": round(_rms3(ref_err[di] - common_ref), 3),
        }
    # person track
    g = track.on_grid & (track.t_ns >= t0) & (track.t_ns <= t1)
    truth_g = _interp(track.t_ns[g], tt, person)
    e_s = track.position_ned_m[g] - truth_g
    e_f = track.filtered_position_ned_m[g] - truth_g
    live = []
    for di, d in enumerate(ids):
        r = rec_by[d]
        sel = (r.target_t_ns >= t0) & (r.target_t_ns <= t1)
        row = drones[d]
        if sel.sum():
            e = r.target_position_ned_m[sel] - _interp(r.target_t_ns[sel], tt, person)
            live.append(e)
            row["live_target_rmse_m"] = round(_rms3(e), 3)
            row["live_target_rmse_fleet_frame_m"] = round(_rms3(e - common_rep), 3)
        # ROIs
        b = boxes[d]
        fsel = (b["frame_t_ns"] >= t0) & (b["frame_t_ns"] <= t1)
        hit_s, hit_l, ious = [], [], []
        live_roi = {(int(n), m.frame_index): m.roi_px for n, m in zip(r.sorties_of_detections(), r.detections)}
        for j in np.flatnonzero(fsel):
            f = (int(b["frame_sortie"][j]), int(b["frame_index"][j]))
            gt = r.gt_boxes.get(f)
            if gt is None:
                continue
            roi = b["roi_px"][j]
            hit_s.append(bool(np.all(np.isfinite(roi))) and box_in_roi(gt, roi))
            if r.detections_topic == "detections":
                hit_l.append(box_in_roi(gt, live_roi.get(f, (0.0, 0.0, 0.0, 0.0))))
            bx = b["box_px"][j]
            ious.append(_iou(bx, gt) if np.all(np.isfinite(bx)) else 0.0)
        row["roi_frames"] = len(hit_s)
        row["person_in_roi_rate_smoothed"] = round(float(np.mean(hit_s)), 4) if hit_s else math.nan
        row["person_in_roi_rate_live"] = round(float(np.mean(hit_l)), 4) if hit_l else math.nan
        row["box_iou_smoothed_median"] = round(float(np.median(ious)), 3) if ious else math.nan
    live_all = np.concatenate(live) if live else np.zeros((0, 3))
    fleet = {
        "window_s": [round(t0 * 1e-9, 3), round(t1 * 1e-9, 3)],
        "person_rmse_m_smoothed": round(_rms3(e_s), 3),
        "person_rmse_m_forward": round(_rms3(e_f), 3),
        "person_rmse_m_live": round(_rms3(live_all), 3),
        "person_rmse_fleet_frame_m_smoothed": round(_rms3(e_s - common_rep), 3),
        "person_rmse_fleet_frame_m_forward": round(_rms3(e_f - common_rep), 3),
        "person_rmse_fleet_frame_m_live": round(_rms3(live_all - common_rep), 3),
        "person_rmse_h_m_smoothed": round(_rms3(e_s[:, :2]), 3),
        "fleet_common_bias_ned_m_reported": [round(float(v), 3) for v in common_rep],
        "fleet_common_bias_ned_m_refined": [round(float(v), 3) for v in common_ref],
        "grid_points": int(g.sum()),
        "truth_person_reference": "person_root_ned_m",
    }
    return {"drones": drones, "fleet": fleet}


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x1 - x0) * max(0.0, y1 - y0)
    ua = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / ua) if ua > 0 else 0.0


def format_evaluation(ev: dict) -> str:
    """The evaluation as a table: person track (fleet) and, per drone, positions and ROIs."""
    f = ev["fleet"]
    lines = [
        "person track RMSE (m) vs truth, steady window        3D      3D fleet-frame",
        f"  live onboard filters (target, all drones)       {f['person_rmse_m_live']:6.3f}    {f['person_rmse_fleet_frame_m_live']:6.3f}",
        f"  offline forward pass (causal, all drones)       {f['person_rmse_m_forward']:6.3f}    {f['person_rmse_fleet_frame_m_forward']:6.3f}",
        f"  offline smoother (RTS, robust)                  {f['person_rmse_m_smoothed']:6.3f}    {f['person_rmse_fleet_frame_m_smoothed']:6.3f}",
        f"  fleet common bias (reported, NED m): {f['fleet_common_bias_ned_m_reported']}",
        "",
        f"{'drone':10s}{'pos_err_rep':>12s}{'pos_err_ref':>12s}{'ff_rep':>9s}{'ff_ref':>9s}{'live_tgt':>10s}"
        f"{'roi_live':>10s}{'roi_smth':>10s}{'box_iou':>9s}",
    ]
    for d, r in ev["drones"].items():
        lines.append(f"{d:10s}{r['position_err_m_reported']:12.3f}{r['position_err_m_refined']:12.3f}"
                     f"{r['position_err_fleet_frame_m_reported']:9.3f}{r['position_err_fleet_frame_m_refined']:9.3f}"
                     f"{r.get('live_target_rmse_m', math.nan):10.3f}{r['person_in_roi_rate_live']:10.3f}"
                     f"{r['person_in_roi_rate_smoothed']:10.3f}{r['box_iou_smoothed_median']:9.3f}")  # fmt: skip
    lines.append("pos_err: drone position RMSE (m), reported / refined; ff_*: with each set's fleet-common component removed")
    return "\n".join(lines)
