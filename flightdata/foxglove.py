"""A processed flight as one Foxglove-ready MCAP, in Foxglove's own published schemas (protobuf, written with
the ``foxglove-sdk`` package), so that Foxglove's Image, 3D and plot panels show it without any skycap code.

    from flightdata.foxglove import export_foxglove

    out = export_foxglove("flights/demo", result)   # result: t_ns, joints_ned -> flights/demo/flight.foxglove.mcap
    out.counts                       # {"/drone_1/camera/image": 186, ...}: messages written per topic

or ``skycap log foxglove FLIGHT_DIR`` (the skeleton from the flight's reconstruction ``motion.npz`` when there
is one). Open the file in Foxglove (File > Open local file); the layout in the README (Outputs) says which panel
shows which topic.

Topics (``<d>`` = a drone id; all times are the measurement times of the recorded messages, nanoseconds since
the Unix epoch, also used as the MCAP log times):

| topic | schema | from |
| --- | --- | --- |
| ``/tf`` | ``foxglove.FrameTransforms`` | static ``world`` -> ``ned``; per state ``ned`` -> ``<d>/body``; per image ``ned`` -> ``<d>/camera`` |
| ``/<d>/camera/image`` | ``foxglove.CompressedImage`` | ``camera/image`` (the recorded JPEG / PNG bytes, frame ``<d>/camera``) |
| ``/<d>/camera/calibration`` | ``foxglove.CameraCalibration`` | ``camera_info`` (K, plumb_bob D, P = [K 0]) |
| ``/<d>/camera/annotations`` | ``foxglove.ImageAnnotations`` | per image: the person boxes (``detections``, else ``sim/detections``) and the 2D keypoints with their limbs (``keypoints2d``, else ``sim/keypoints2d``) of that frame |
| ``/drones`` | ``foxglove.SceneUpdate`` | a box per drone, locked to ``<d>/body`` |
| ``/person/track`` | ``foxglove.SceneUpdate`` | the person: the offline smoother's track (``refined_track.npz``) or else each drone's onboard estimate (``target``): a sphere and the path so far |
| ``/person/truth`` | ``foxglove.SceneUpdate`` | simulated flights: the simulator's person root (``truth.mcap``), drawn the same way |
| ``/reconstruction/skeleton`` | ``foxglove.SceneUpdate`` | the reconstructed COCO-17 skeleton per frame: joint spheres and limb lines |

Frames: ``ned`` is skycap's world (north, east, down; :mod:`skycap.frames`), the parent of every drone and camera
frame; ``world`` is its east-north-up parent (the usual Z-up of 3D viewers), so the 3D panel shows the scene
upright with ``world`` as its display frame. ``<d>/camera`` is the optical frame (x right, y down, z forward), the
convention of Foxglove's CameraCalibration. A drone whose recording cannot be read is skipped with a warning.
Images are streamed drone by drone: memory does not grow with the flight's length.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from flightdata.flightlog import FlightLogError, SortieLogs
from flightdata.folder import FlightFolder
from shared_msgs.messages import CameraFrame, CameraInfo, Detections, Keypoints2D, TargetEstimate, VehicleState
from skycap.errors import SkycapError
from skycap.skeleton import COCO17_LIMBS, COCO17_NAMES

log = logging.getLogger(__name__)

__all__ = ["FoxgloveExport", "FoxgloveExportError", "R_ENU_NED", "export_foxglove", "register"]

#: NED -> ENU (east, north, up): the rotation of the static ``world`` -> ``ned`` transform.
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
WORLD, NED = "world", "ned"
BOX_TOPICS = ("detections", "sim/detections")
KEYPOINT_TOPICS = ("keypoints2d", "sim/keypoints2d")
_DRONE_BOX_M = (0.5, 0.5, 0.15)


class FoxgloveExportError(SkycapError):
    """A Foxglove export that cannot be written (no readable drone, an existing output file, no foxglove-sdk)."""


@dataclasses.dataclass
class FoxgloveExport:
    """What :func:`export_foxglove` wrote: ``path``, ``counts`` (topic -> messages) and ``skipped`` (drone -> why)."""

    path: Path
    counts: dict[str, int]
    skipped: dict[str, str]


def _ts(t_ns: int):
    from foxglove.messages import Timestamp

    t_ns = int(t_ns)
    return Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


def _pose_msgs(R: np.ndarray | None, t: np.ndarray, quat_xyzw: np.ndarray | None = None):
    """(Vector3, Quaternion) of a pose: rotation ``R`` (None: the identity) or its quaternion ``quat_xyzw`` already
    computed (:func:`_quats`, many at once: a scipy call per message was most of the export's time)."""
    from foxglove.messages import Quaternion, Vector3

    if quat_xyzw is None:
        quat_xyzw = _IDENTITY_XYZW if R is None else Rotation.from_matrix(R).as_quat()
    x, y, z, w = quat_xyzw
    return Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])), Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


#: scipy's quaternion of the identity matrix
_IDENTITY_XYZW = np.array([0.0, 0.0, 0.0, 1.0])


def _quats(R: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) (x, y, z, w) of rotations (N, 3, 3), as ``Rotation.from_matrix(R[i]).as_quat()`` each."""
    return Rotation.from_matrix(R).as_quat() if len(R) else np.zeros((0, 4))


def _tf(t_ns: int, parent: str, child: str, R: np.ndarray | None, t: np.ndarray, quat_xyzw: np.ndarray | None = None):
    from foxglove.messages import FrameTransform

    tr, q = _pose_msgs(R, t, quat_xyzw)
    return FrameTransform(timestamp=_ts(t_ns), parent_frame_id=parent, child_frame_id=child, translation=tr, rotation=q)


def _color(r: float, g: float, b: float, a: float = 1.0):
    from foxglove.messages import Color

    return Color(r=r, g=g, b=b, a=a)


def _calibration(info: CameraInfo, frame_id: str):
    from foxglove.messages import CameraCalibration

    K = [info.fx_px, 0.0, info.cx_px, 0.0, info.fy_px, info.cy_px, 0.0, 0.0, 1.0]
    P = [info.fx_px, 0.0, info.cx_px, 0.0, 0.0, info.fy_px, info.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0]
    plumb = info.distortion_model == "plumb_bob"
    return CameraCalibration(
        timestamp=_ts(info.header.t_measurement_ns), frame_id=frame_id, width=int(info.width_px),
        height=int(info.height_px), distortion_model="plumb_bob",
        D=[float(v) for v in info.distortion] if plumb else [0.0] * 5,
        K=[float(v) for v in K], R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], P=[float(v) for v in P])


def _annotations(t_ns: int, det: Detections | None, kp: Keypoints2D | None):
    from foxglove.messages import ImageAnnotations, Point2, PointsAnnotation, PointsAnnotationType, TextAnnotation

    ts = _ts(t_ns)
    points, texts = [], []
    for b in det.boxes if det is not None else []:
        corners = [(b.x_min_px, b.y_min_px), (b.x_max_px, b.y_min_px), (b.x_max_px, b.y_max_px), (b.x_min_px, b.y_max_px)]
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.LineLoop, thickness=2.0,
                                       points=[Point2(x=float(u), y=float(v)) for u, v in corners],
                                       outline_color=_color(0.1, 0.9, 0.1)))
        texts.append(TextAnnotation(timestamp=ts, position=Point2(x=float(b.x_min_px), y=float(b.y_min_px) - 4.0),
                                    text=f"{b.label} {b.score:.2f}", font_size=12.0, text_color=_color(0.1, 0.9, 0.1),
                                    background_color=_color(0, 0, 0, 0.5)))
    if kp is not None and kp.persons:
        person = max(kp.persons, key=lambda p: float(np.mean(p.confidence)))
        uv = np.asarray(person.keypoints_px, dtype=float).reshape(17, 2)
        seen = np.asarray(person.confidence, dtype=float) > 0
        pts = [Point2(x=float(u), y=float(v)) for u, v in uv[seen]]
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, thickness=5.0, points=pts,
                                       outline_color=_color(1.0, 0.3, 0.1), fill_color=_color(1.0, 0.3, 0.1)))
        limbs = [Point2(x=float(u), y=float(v)) for a, b in COCO17_LIMBS if seen[a] and seen[b] for u, v in (uv[a], uv[b])]
        if limbs:
            points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.LineList, thickness=2.0, points=limbs,
                                           outline_color=_color(1.0, 0.8, 0.1)))
    return ImageAnnotations(timestamp=ts, points=points, texts=texts)


def _by_frame(got: dict[str, list], topics: tuple[str, ...]) -> tuple[str | None, dict[tuple[str, int], Any]]:
    """The first of ``topics`` with messages in ``got`` (topic -> messages), as {(camera_id, frame_index): message}."""
    for topic in topics:
        if got.get(topic):
            return topic, {(m.camera_id, m.frame_index): m for m in got[topic]}
    return None, {}


def _skeleton_entity(t_ns: int, joints_ned: np.ndarray):
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType, Point3, SceneEntity, SpherePrimitive, Vector3

    ok = np.all(np.isfinite(joints_ned), axis=-1)
    spheres = [SpherePrimitive(pose=_pose(p), size=Vector3(x=0.06, y=0.06, z=0.06), color=_color(0.2, 0.6, 1.0))
               for p in joints_ned[ok]]
    seg = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
           for a, b in COCO17_LIMBS if ok[a] and ok[b] for p in (joints_ned[a], joints_ned[b])]
    lines = [LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.03, scale_invariant=False, points=seg,
                           color=_color(0.9, 0.9, 0.9))] if seg else []
    return SceneEntity(timestamp=_ts(t_ns), frame_id=NED, id="skeleton", spheres=spheres, lines=lines,
                       metadata=_kv({"joints": ",".join(COCO17_NAMES)}))


def _pose(p: np.ndarray, R: np.ndarray | None = None):
    from foxglove.messages import Pose

    tr, q = _pose_msgs(R, p)
    return Pose(position=tr, orientation=q)


def _kv(d: dict[str, str]):
    from foxglove.messages import KeyValuePair

    return [KeyValuePair(key=k, value=v) for k, v in d.items()]


def _points3(path_ned: np.ndarray) -> list:
    from foxglove.messages import Point3

    return [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in path_ned]


def _track_entity(t_ns: int, name: str, path_ned: np.ndarray, color, points: list | None = None):
    """The person at ``path_ned[-1]`` and its path ``path_ned``; ``points``: that path as Point3s already made
    (:func:`_points3` of the whole track once, then picked per message)."""
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType, SceneEntity, SpherePrimitive, Vector3

    here = path_ned[-1]
    spheres = [SpherePrimitive(pose=_pose(here), size=Vector3(x=0.3, y=0.3, z=0.3), color=color)]
    lines = [LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=0.05, scale_invariant=False, color=color,
                           points=_points3(path_ned) if points is None else points)] if len(path_ned) > 1 else []
    return SceneEntity(timestamp=_ts(t_ns), frame_id=NED, id=f"person/{name}", spheres=spheres, lines=lines)


def _decimate(n: int, keep: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, keep)).round().astype(int)) if n else np.zeros(0, int)


def export_foxglove(
    flight_dir: str | Path | FlightFolder,
    result: Any = None,
    out_path: str | Path | None = None,
    *,
    sortie: int | None = None,
    overwrite: bool = False,
    track_path_points: int = 200,
    progress: Callable[[str, int, int], None] | None = None,
) -> FoxgloveExport:
    """Write the flight (every sortie, or ``sortie``) and the reconstruction ``result`` (any object with ``t_ns`` (T,)
    and ``joints_ned`` (T, 17, 3), e.g. a :class:`reconstruction.result.ReconstructionResult`; None: no skeleton) as a
    Foxglove MCAP at ``out_path`` (default: :attr:`FlightFolder.foxglove_path`, ``<flight>/flight.foxglove.mcap``). See the module docstring for the topics.

    An existing ``out_path`` is refused unless ``overwrite``. A drone whose recording cannot be read is skipped with
    a warning (``FoxgloveExport.skipped``); :class:`FoxgloveExportError` when none can be. ``track_path_points``
    bounds the person path drawn in each track message. ``progress(stage, done, total)``: per drone ("foxglove").
    """
    try:
        import foxglove
        from foxglove import channels as ch
        from foxglove.messages import CubePrimitive, FrameTransforms, SceneEntity, SceneUpdate, Vector3
    except ImportError:
        raise FoxgloveExportError("the Foxglove export needs the foxglove-sdk package: pip install -e '.[recon]' "
                                  "(or pip install foxglove-sdk)") from None
    flight = flight_dir if isinstance(flight_dir, FlightFolder) else FlightFolder(flight_dir)
    out = Path(out_path) if out_path is not None else flight.foxglove_path
    if out.exists() and not overwrite:
        raise FoxgloveExportError(f"{out} already exists; choose another output file or pass overwrite=True (--force)")
    logs_by_drone = flight.drone_logs(sortie=sortie)
    out.parent.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    skipped: dict[str, str] = {}
    ctx = foxglove.Context()
    chans: dict[str, Any] = {}

    def emit(kind: type, topic: str, msg: Any, t_ns: int) -> None:
        c = chans.get(topic)
        if c is None:
            c = chans[topic] = kind(topic, context=ctx)
        c.log(msg, log_time=int(t_ns))
        counts[topic] = counts.get(topic, 0) + 1

    tmp = out.with_name(f".{out.name}.partial")
    tmp.unlink(missing_ok=True)
    writer = foxglove.open_mcap(tmp, context=ctx)
    try:
        t_first: int | None = None
        drone_ids: list[str] = []
        targets: dict[str, list[tuple[int, np.ndarray]]] = {}
        for i, (d, sorties) in enumerate(logs_by_drone.items()):
            if progress:
                progress("foxglove", i, len(logs_by_drone))
            try:
                t0 = _export_drone(d, SortieLogs([s.path for s in sorties]), emit, ch, FrameTransforms, targets)
            except (FlightLogError, OSError, ValueError) as e:
                log.warning("Foxglove export: skipped %s, its recording cannot be read (%s)", d, e)
                skipped[d] = str(e)
                continue
            drone_ids.append(d)
            if t0 is not None:
                t_first = t0 if t_first is None else min(t_first, t0)
        if not drone_ids:
            raise FoxgloveExportError(f"{flight.path}: no drone recording could be read ({skipped}); nothing to export")
        t_first = t_first or 0
        emit(ch.FrameTransformsChannel, "/tf",
             FrameTransforms(transforms=[_tf(t_first, WORLD, NED, R_ENU_NED, np.zeros(3))]), t_first)
        boxes = [SceneEntity(timestamp=_ts(t_first), frame_id=f"{d}/body", id=d, frame_locked=True,
                             cubes=[CubePrimitive(pose=_pose(np.zeros(3)), size=Vector3(x=_DRONE_BOX_M[0], y=_DRONE_BOX_M[1],
                                                                                        z=_DRONE_BOX_M[2]),
                                                  color=_color(0.9, 0.2, 0.2, 0.8))])
                 for d in drone_ids]
        emit(ch.SceneUpdateChannel, "/drones", SceneUpdate(entities=boxes), t_first)
        _export_track(flight, targets, emit, ch, track_path_points)
        _export_truth(flight, drone_ids, emit, ch, track_path_points)
        if result is not None:
            t_ns = np.asarray(result.t_ns, dtype=np.int64)
            J = np.asarray(result.joints_ned, dtype=float)
            if J.shape != (len(t_ns), 17, 3):
                raise FoxgloveExportError(f"result.joints_ned has shape {J.shape}; expected ({len(t_ns)}, 17, 3)")
            for k in range(len(t_ns)):
                emit(ch.SceneUpdateChannel, "/reconstruction/skeleton",
                     SceneUpdate(entities=[_skeleton_entity(int(t_ns[k]), J[k])]), int(t_ns[k]))
        if progress:
            progress("foxglove", len(logs_by_drone), len(logs_by_drone))
    except BaseException:
        writer.close()
        tmp.unlink(missing_ok=True)
        raise
    writer.close()
    tmp.replace(out)
    log.info("wrote %s: %d messages on %d topics%s", out, sum(counts.values()), len(counts),
             f"; skipped {sorted(skipped)}" if skipped else "")
    return FoxgloveExport(out, dict(sorted(counts.items())), skipped)


def _export_drone(d: str, logs: SortieLogs, emit, ch, FrameTransforms, targets) -> int | None:
    """One drone's transforms, calibrations, images and annotations; its target estimates into ``targets``. Two
    passes over the recording: everything but the images (kept), then the images (streamed, one at a time)."""
    got = logs.read_topics({"state": VehicleState, "camera_info": CameraInfo, "target": TargetEstimate,
                            **{t: Detections for t in BOX_TOPICS}, **{t: Keypoints2D for t in KEYPOINT_TOPICS}})
    states = got["state"]
    if states:
        q = np.array([s.q_world_body for s in states], dtype=float)  # (w, x, y, z)
        quats = _quats(Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix())
    for s, qs in zip(states, quats if states else []):
        t = s.header.t_measurement_ns
        emit(ch.FrameTransformsChannel, "/tf", FrameTransforms(transforms=[
            _tf(t, NED, f"{d}/body", None, np.asarray(s.position_ned_m), qs)]), t)
    t_first = min(s.header.t_measurement_ns for s in states) if states else None
    for info in got["camera_info"]:
        emit(ch.CameraCalibrationChannel, f"/{d}/camera/calibration", _calibration(info, f"{d}/camera"),
             info.header.t_measurement_ns)
    _, dets = _by_frame(got, BOX_TOPICS)
    _, kps = _by_frame(got, KEYPOINT_TOPICS)
    from foxglove.messages import CompressedImage

    cam_t, cam_T = [], []
    for m in logs.messages(["camera/image"]):
        f = m.msg
        if not isinstance(f, CameraFrame):
            continue
        t = f.header.t_measurement_ns
        t_first = t if t_first is None else min(t_first, t)
        if len(f.T_world_cam) == 16:
            T = np.asarray(f.T_world_cam, dtype=float).reshape(4, 4)
        else:
            det = dets.get((f.camera_id, f.frame_index))
            T = np.asarray(det.T_world_cam, dtype=float).reshape(4, 4) if det is not None and len(det.T_world_cam) == 16 else None
        if T is not None:
            cam_t.append(t)
            cam_T.append(T)
        emit(ch.CompressedImageChannel, f"/{d}/camera/image",
             CompressedImage(timestamp=_ts(t), frame_id=f"{d}/camera", data=bytes(f.data), format=f.encoding), t)
        key = (f.camera_id, f.frame_index)
        emit(ch.ImageAnnotationsChannel, f"/{d}/camera/annotations", _annotations(t, dets.get(key), kps.get(key)), t)
    if cam_T:  # the camera poses at the images' times, their rotations converted at once
        cam_T = np.stack(cam_T)
        for t, T, qc in zip(cam_t, cam_T, _quats(cam_T[:, :3, :3])):
            emit(ch.FrameTransformsChannel, "/tf", FrameTransforms(transforms=[
                _tf(t, NED, f"{d}/camera", None, T[:3, 3], qc)]), t)
    targets_d = [(e.header.t_measurement_ns, np.asarray(e.position_ned_m, dtype=float))
                 for e in got["target"] if e.status in ("tracking", "predicting")]
    if got["target"]:
        targets[d] = targets_d
    return t_first


def _export_track(flight: FlightFolder, targets: dict, emit, ch, keep: int) -> None:
    """``/person/track``: the offline smoother's track when the flight has one, else the drones' onboard estimates."""
    from foxglove.messages import SceneUpdate

    sources: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if flight.refined_npz_path.is_file():
        z = np.load(flight.refined_npz_path)
        sources["refined"] = (np.asarray(z["t_ns"], dtype=np.int64), np.asarray(z["position_ned_m"], dtype=float))
    else:
        for d, rows in targets.items():
            if rows:
                sources[d] = (np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1] for r in rows]))
    palette = [(1.0, 0.85, 0.1), (0.1, 0.8, 0.9), (0.8, 0.3, 0.9), (0.3, 0.9, 0.3)]
    for i, (name, (t_ns, p)) in enumerate(sources.items()):
        color = _color(*palette[i % len(palette)])
        pts = _points3(p)
        for k in range(len(t_ns)):
            lo = max(0, k + 1 - 10 * keep)
            idx = lo + _decimate(k + 1 - lo, keep)
            emit(ch.SceneUpdateChannel, "/person/track", SceneUpdate(entities=[
                _track_entity(int(t_ns[k]), name, p[idx], color, [pts[j] for j in idx])]), int(t_ns[k]))


def _export_truth(flight: FlightFolder, drone_ids: list[str], emit, ch, keep: int) -> None:
    """``/person/truth``: the simulator's person root, when the flight has a ``truth.mcap``."""
    from foxglove.messages import SceneUpdate

    if not flight.truth_path.is_file():
        return
    try:
        t_ns, person, _, _ = flight.sim_truth(drone_ids)
    except (FlightLogError, OSError) as e:
        log.warning("Foxglove export: the simulator truth %s cannot be read (%s); no /person/truth", flight.truth_path, e)
        return
    color = _color(0.2, 1.0, 0.4, 0.6)
    pts = _points3(person)
    for k in range(len(t_ns)):
        lo = max(0, k + 1 - 10 * keep)
        idx = lo + _decimate(k + 1 - lo, keep)
        emit(ch.SceneUpdateChannel, "/person/truth", SceneUpdate(entities=[
            _track_entity(int(t_ns[k]), "truth", person[idx], color, [pts[j] for j in idx])]), int(t_ns[k]))


# ------------------------------------------------------------------------------------------------ CLI
def register(cmds: Any) -> None:
    """``skycap log foxglove FLIGHT_DIR [--out FILE] [--sortie N] [--motion NPZ] [--force]``."""
    p = cmds.add_parser("foxglove", help="write the flight (images, annotations, drones, skeleton) as a Foxglove MCAP",
                        description="Write a flight folder as one MCAP in Foxglove's schemas: per drone its camera "
                        "images with box and keypoint annotations, calibration and camera/drone transforms; the "
                        "person track; the reconstructed skeleton (from --motion, default the flight's "
                        "reconstruction/motion.npz, else reconstruction_monocular/motion.npz, when present). "
                        "Example: skycap log foxglove flights/demo  (writes flights/demo/flight.foxglove.mcap)")
    p.add_argument("flight", type=Path)
    p.add_argument("--out", type=Path, default=None, help="output file (default FLIGHT/flight.foxglove.mcap)")
    p.add_argument("--sortie", type=int, default=None, help="only this sortie (default: the whole flight)")
    p.add_argument("--motion", type=Path, default=None, help="a motion.npz (t_ns, joints_ned) to draw as the skeleton")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.set_defaults(func=_cmd_foxglove)


@dataclasses.dataclass
class _Motion:
    t_ns: np.ndarray
    joints_ned: np.ndarray


def _load_motion(flight: FlightFolder, path: Path | None) -> _Motion | None:
    cands = [path] if path is not None else [flight.reconstruction_dir(m) / "motion.npz" for m in ("multiview", "monocular")]
    for c in cands:
        if c.is_file():
            z = np.load(c)
            log.info("skeleton from %s", c)
            return _Motion(z["t_ns"], z["joints_ned"])
    if path is not None:
        raise FoxgloveExportError(f"{path} does not exist; pass the motion.npz of a reconstruction")
    log.warning("%s has no reconstruction (motion.npz): the export has no skeleton; run skycap reconstruct first",
                flight.path)
    return None


def _cmd_foxglove(args: Any) -> int:
    flight = FlightFolder(args.flight)
    res = export_foxglove(flight, _load_motion(flight, args.motion), args.out, sortie=args.sortie, overwrite=args.force)
    print(f"wrote {res.path}: {sum(res.counts.values())} messages on {len(res.counts)} topics")
    for t, n in res.counts.items():
        print(f"  {t:<36} {n:>7}")
    for d, why in res.skipped.items():
        print(f"  skipped {d}: {why}")
    return 0
