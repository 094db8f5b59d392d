"""Flight summary: how well a recorded orbit flight went, from the drones' MCAP files and the simulator truth.

    summary = summarize_flight("flights/demo")        # reads plan.json, drone_*.mcap, truth.mcap
    print(format_table(summary))

Per drone (from its own recording): ``setpoint_rate_hz`` (the agent's measured offboard stream during the
orbit, from its health reports), ``state_rate_hz`` (recorded vehicle state samples per second during the
orbit), ``frames_recorded`` / ``image_rate_hz`` (camera frames in its file); against the **true**
trajectory (``truth.mcap``) during the steady orbit phase (from ``plan.start_time + settle_s`` until the
first land command): ``orbit_radius_rmse_m``, ``altitude_rmse_m``, ``phase_error_deg_rms`` (angle about
the centre minus the slot angle, so including a lag common to the fleet) and
``phase_spacing_error_deg_rms`` (the same with the fleet's mean error at each instant removed: how well
the spacing is kept), ``yaw_to_center_error_deg_rms`` (true heading minus the bearing to the centre: the
camera pointing); ``orbit_radius_rmse_est_m`` / ``altitude_rmse_est_m`` are the same errors against the
vehicle's own recorded estimate, and ``phase_error_est_deg_rms`` (the control's tracking; the gap to the truth errors is the autopilot's
estimation error, e.g. a GPS bias, which the agent cannot see). Fleet-wide: ``min_separation_m`` (closest approach of two drones over the whole
flight, truth), ``flight_s`` (first take-off to last touch-down, truth above ``airborne_alt_m``).

The computations (:func:`orbit_errors`, :func:`min_pairwise_distance_m`) are plain numpy functions.

Tracking flights (``skycap demo --mode track``): :func:`summarize_tracking` adds, per drone, over the steady
window (plan start + ``settle_s`` to the land command): ``target_rmse_m`` / ``target_rmse_h_m`` (the drone's
published fused estimate ``target`` against the true person root, 3D / horizontal, each estimate against the
truth at its own time: the capture time of the newest detection fused), ``target_rmse_at_send_m`` (each
estimate predicted with its velocity to the time it was sent, against the truth then: adds the detection
latency's prediction error), ``target_rmse_fleet_frame_m`` (the same after removing the fleet's mean GPS bias at
each estimate's time, which no drone can observe without an absolute reference), ``person_in_roi_rate`` (own frames whose ROI, planned from the fused estimate before
the frame's detection was fused, contains the person's exact image box, among frames where the person is in
the image), ``mpc_solve_ms_median`` / ``mpc_solve_ms_p99`` / ``mpc_fallbacks`` (from the sortie's ``<drone>.s<NNN>.track.json``,
written by the agent), ``detector_hz`` (own detection messages per second), ``self_pos_err_m_before`` /
``self_pos_err_m_after`` (RMS 3D error of the drone's reported position against the truth, without / with the
filter's estimated offset subtracted); fleet: ``min_separation_m`` (truth, steady window) and
``tracking_lost_s`` (time in the window during which no drone published a ``tracking`` estimate within 1 s).
Fault and failsafe counters per drone (failsafe decision changes, malformed detections ignored, simulated
network drops/delays, the filter's re-filtering and gating): see :func:`_fault_figures`.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from flightdata.flightlog import FlightLog, SortieLogs
from flightdata.folder import FlightFolder, Sortie, natural_key, read_sim_truth
from reconstruction.metrics import accuracy_metrics
from onboard.tracking.roi import box_in_roi
from shared_msgs import CameraFrame, Command, Detections, Health, Keypoints2D, OrbitPlan, SimTruth, TargetEstimate, VehicleState
from skycap.errors import SkycapError
from skycap.skeleton import SCORED_JOINTS

log = logging.getLogger(__name__)

__all__ = ["SummaryError", "orbit_errors", "min_pairwise_distance_m", "yaw_to_center_error_deg_rms", "summarize_flight", "format_table",
           "write_summary", "summarize_tracking", "format_tracking_table",
           "lost_time_s", "reconstruction_accuracy", "format_accuracy"]


class SummaryError(SkycapError):
    """A flight folder that lacks what the summary needs."""


def _wrap_rad(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def orbit_errors(plan: OrbitPlan, drone_ids: list[str], t_s: np.ndarray, pos_ned_m: np.ndarray) -> dict[str, dict[str, float]]:
    """Errors of true positions against the plan.

    t_s: (T,) UNIX seconds; pos_ned_m: (D, T, 3) true positions of ``drone_ids`` at those times.
    Returns per drone: orbit_radius_rmse_m, altitude_rmse_m, phase_error_deg_rms, phase_spacing_error_deg_rms.
    """
    c = np.asarray(plan.center_ned_m, dtype=float)
    t0 = plan.start_time_ns * 1e-9
    w = plan.direction * plan.angular_speed_rad_s
    rel = pos_ned_m[..., :2] - c[:2]
    radius = np.hypot(rel[..., 0], rel[..., 1])
    angle = np.arctan2(rel[..., 1], rel[..., 0])
    slot = np.stack([plan.phase_offset_rad[d] + w * np.maximum(0.0, t_s - t0) for d in drone_ids])
    phase_err = _wrap_rad(angle - slot)  # (D, T)
    mean_err = np.angle(np.exp(1j * phase_err).mean(axis=0))  # circular mean over drones
    spacing_err = _wrap_rad(phase_err - mean_err)
    out = {}
    for k, d in enumerate(drone_ids):
        out[d] = {
            "orbit_radius_rmse_m": float(np.sqrt(np.mean((radius[k] - plan.radius_m) ** 2))),
            "altitude_rmse_m": float(np.sqrt(np.mean((-pos_ned_m[k, :, 2] - plan.altitude_m) ** 2))),
            "phase_error_deg_rms": float(np.degrees(np.sqrt(np.mean(phase_err[k] ** 2)))),
            "phase_spacing_error_deg_rms": float(np.degrees(np.sqrt(np.mean(spacing_err[k] ** 2)))),
        }
    return out


def yaw_to_center_error_deg_rms(center_ned_m, pos_ned_m: np.ndarray, yaw_rad: np.ndarray) -> float:
    """RMS of heading minus the bearing to the centre (degrees); pos_ned_m (T, 3), yaw_rad (T,)."""
    c = np.asarray(center_ned_m, dtype=float)
    bearing = np.arctan2(c[1] - pos_ned_m[:, 1], c[0] - pos_ned_m[:, 0])
    return float(np.degrees(np.sqrt(np.mean(_wrap_rad(yaw_rad - bearing) ** 2))))


def _finite_or_none(x: float, ndigits: int = 3) -> float | None:
    """JSON has no infinity: a distance with nothing to measure (one drone) is None."""
    return round(float(x), ndigits) if math.isfinite(x) else None


def _fmt_m(x: float | None) -> str:
    return "n/a (one drone)" if x is None else f"{x:.2f}"


def min_pairwise_distance_m(pos_ned_m: np.ndarray) -> float:
    """Smallest distance between two drones at the same instant; pos_ned_m: (D, T, 3). inf for D < 2."""
    D = pos_ned_m.shape[0]
    best = math.inf
    for i in range(D):
        for j in range(i + 1, D):
            best = min(best, float(np.min(np.linalg.norm(pos_ned_m[i] - pos_ned_m[j], axis=-1))))
    return best


def _read_truth(path: Path, drone_ids: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s (T,), positions (D, T, 3), yaw_rad (D, T)) of the drones from the simulator truth."""
    t_ns, _, pos, yaw = read_sim_truth(path, drone_ids)
    if not len(t_ns):
        raise SummaryError(f"{path} holds no simulator truth for {drone_ids}")
    return t_ns * 1e-9, np.transpose(pos, (1, 0, 2)), yaw.T


def _flight_logs(flight: FlightFolder, drone_ids: list[str], sortie: int | None) -> dict[str, list[Sortie]]:
    """Each planned drone's recordings (every sortie, or only ``sortie``); a drone without one is an error."""
    logs = flight.drone_logs(sortie=sortie, drone_ids=drone_ids)
    missing = [d for d in drone_ids if d not in logs]
    if missing:
        which = "any recording" if sortie is None else f"a recording of sortie {sortie}"
        raise SummaryError(f"{flight.path}: {missing} lack {which}: the agent did not record (--record-dir)")
    log.info("summary of %s from %s", flight.path, flight.describe_logs(logs))
    return logs


def summarize_flight(flight_dir: str | Path, settle_s: float = 8.0, airborne_alt_m: float = 0.3,
                     sortie: int | None = None, plan: OrbitPlan | None = None) -> dict:
    """The summary dict of a flight folder (see the module docstring) over every sortie of each drone, or
    only ``sortie``; writes nothing. ``plan``: the orbit to score (default ``plan.json``); its steady window
    ends at the first land command after the plan's start time, so a later orbit in the same recordings (a
    second take-off without restarting the agents) is scored with its own plan."""
    flight = FlightFolder(flight_dir)
    flight_dir = flight.path
    plan = flight.plan() if plan is None else plan
    drone_ids = sorted(plan.phase_offset_rad, key=natural_key)
    logs = _flight_logs(flight, drone_ids, sortie)
    per: dict[str, dict] = {}
    t_land = math.inf
    for d in drone_ids:
        state_t, state_p, frame_t, setpoint_hz = [], [], [], []
        for m in SortieLogs([s.path for s in logs[d]]).messages(["state", "camera/image", "health", "gcs/cmd"]):
            msg = m.msg
            if isinstance(msg, VehicleState):
                state_t.append(msg.header.t_measurement_ns * 1e-9)
                state_p.append(msg.position_ned_m)
            elif isinstance(msg, CameraFrame):
                frame_t.append(msg.header.t_measurement_ns * 1e-9)
            elif isinstance(msg, Health):
                if msg.state == "orbit":
                    setpoint_hz.append(msg.rates_hz.get("setpoint", 0.0))
            elif isinstance(msg, Command) and msg.action == "land" and msg.header.t_sent_ns >= plan.start_time_ns:
                t_land = min(t_land, msg.header.t_sent_ns * 1e-9)
        per[d] = {"_state_t": np.asarray(state_t), "_state_p": np.asarray(state_p, dtype=float).reshape(-1, 3),
                  "_frame_t": np.asarray(frame_t),
                  # the first report of the orbit covers the offboard start: skip it
                  "setpoint_rate_hz": float(np.median(setpoint_hz[1:])) if len(setpoint_hz) > 1 else 0.0}
    t_truth, pos, yaw = _read_truth(flight.truth_path, drone_ids)
    t_start = plan.start_time_ns * 1e-9 + settle_s
    t_end = min(t_land, t_truth[-1])
    steady = (t_truth >= t_start) & (t_truth <= t_end)
    if steady.sum() < 10:
        raise SummaryError(f"no steady orbit phase in {flight_dir} (from plan start + {settle_s} s to the land "
                           f"command): fly longer (--duration)")
    errs = orbit_errors(plan, drone_ids, t_truth[steady], pos[:, steady])
    out_drones = {}
    for k, d in enumerate(drone_ids):
        st, ft = per[d]["_state_t"], per[d]["_frame_t"]
        sel = (st >= t_start) & (st <= t_end)
        in_orbit = st[sel]
        # the same errors against the vehicle's own estimate: what the control achieves; the difference
        # to the truth errors is the autopilot's estimation error (GPS-like bias), invisible to the agent
        est = orbit_errors(plan, [d], in_orbit, per[d]["_state_p"][sel][None])[d] if sel.sum() >= 10 else {}
        out_drones[d] = {
            "setpoint_rate_hz": round(per[d]["setpoint_rate_hz"], 2),
            **{k: round(v, 3) for k, v in errs[d].items()},
            "orbit_radius_rmse_est_m": round(est.get("orbit_radius_rmse_m", math.nan), 3),
            "altitude_rmse_est_m": round(est.get("altitude_rmse_m", math.nan), 3),
            "phase_error_est_deg_rms": round(est.get("phase_error_deg_rms", math.nan), 3),
            "yaw_to_center_error_deg_rms": round(yaw_to_center_error_deg_rms(
                plan.center_ned_m, pos[k, steady], yaw[k, steady]), 3),
            "frames_recorded": int(len(ft)),
            "image_rate_hz": round(float((len(ft) - 1) / (ft[-1] - ft[0])) if len(ft) > 1 else 0.0, 2),
            "state_rate_hz": round(float(len(in_orbit) / (t_end - t_start)), 2),
        }
    alt = -pos[..., 2]
    flying = np.any(alt > airborne_alt_m, axis=0)
    flight_s = float(t_truth[flying][-1] - t_truth[flying][0]) if flying.any() else 0.0
    return {
        "flight_dir": str(flight_dir),
        "recordings": {d: [s.path.name for s in ss] for d, ss in logs.items()},
        "plan_id": plan.plan_id,
        "drones": out_drones,
        "fleet": {
            "min_separation_m": _finite_or_none(min_pairwise_distance_m(pos)),
            "configured_min_separation_m": plan.min_separation_m,
            "flight_s": round(flight_s, 2),
            "steady_orbit_s": round(float(t_end - t_start), 2),
            "steady_orbit_window_s": [round(float(t_start), 3), round(float(t_end), 3)],
        },
    }


def _drone_table(title: str, drones: dict[str, dict], cols: list[str], short: list[str], width: int) -> list[str]:
    """Title, header and one row per drone (floats with 3 decimals, ints as they are)."""
    lines = [title, "drone     " + "".join(f"{s:>{width}s}" for s in short)]
    for d, row in drones.items():
        lines.append(f"{d:10s}" + "".join(f"{row[c]:>{width}.3f}" if isinstance(row[c], float) else f"{row[c]:>{width}d}"
                                          for c in cols))
    return lines


def format_table(summary: dict) -> str:
    cols = ["setpoint_rate_hz", "orbit_radius_rmse_m", "altitude_rmse_m", "phase_error_deg_rms",
            "phase_spacing_error_deg_rms", "yaw_to_center_error_deg_rms", "orbit_radius_rmse_est_m", "altitude_rmse_est_m", "phase_error_est_deg_rms", "frames_recorded",
            "image_rate_hz", "state_rate_hz"]
    short = ["setpt_hz", "radius_m", "alt_m", "phase_deg", "spacing_deg", "yaw_deg", "radius_est_m", "alt_est_m", "phase_est_deg", "frames",
             "img_hz", "state_hz"]
    lines = _drone_table("errors are RMS against the true trajectory (radius_m, alt_m, phase) and the vehicle's "
                         "estimate (*_est_m)", summary["drones"], cols, short, 14)
    f = summary["fleet"]
    lines.append(f"fleet: min_separation_m={_fmt_m(f['min_separation_m'])} (configured {f['configured_min_separation_m']}), "
                 f"flight_s={f['flight_s']:.1f}, steady_orbit_s={f['steady_orbit_s']:.1f}")
    return "\n".join(lines)


def write_summary(flight_dir: str | Path, **kw) -> dict:
    s = summarize_flight(flight_dir, **kw)
    FlightFolder(flight_dir).summary_path.write_text(json.dumps(s, indent=2))
    return s


def reconstruction_accuracy(flight_dir: str | Path, motion_npz: str | Path | None = None,
                            window_s: tuple[float, float] | None = None, keypoints_source: str | None = None,
                            position_grade: str | None = None) -> dict:
    """Accuracy of a flight's reconstruction against the simulator's ground truth (simulated flights only).

    Reads the person's true COCO-17 joints from ``truth.mcap`` (SimTruth, NED metres), interpolates them
    linearly to the reconstruction's frame times (``reconstruction/motion.npz``: ``t_ns``, ``joints_ned``)
    and scores the joints of :data:`skycap.skeleton.SCORED_JOINTS` over all reconstructed frames and, with
    ``window_s`` (UNIX seconds, e.g. the steady orbit), over that window (``*_window`` keys), with
    :func:`reconstruction.metrics.accuracy_metrics`: ``mpjpe_mm`` (root-aligned, Human3.6M protocol 1),
    ``pa_mpjpe_mm`` (protocol 2), ``w_mpjpe_mm`` (world, no alignment), ``root_err_mm``, ``per_group_mm``
    (torso / arms / legs / head). Also says what was scored: ``keypoints_source`` (the 2D keypoints the
    reconstruction used: as given, else the detectors named in its ``capture.npz``) and ``position_grade``
    (the drones' position estimate, e.g. "rtk" / "gps", as given). Returns {} when either file is absent.
    """

    flight = FlightFolder(flight_dir)
    flight_dir = flight.path
    npz = Path(motion_npz) if motion_npz else flight.reconstruction_dir("multiview") / "motion.npz"
    truth = flight.truth_path
    if not (npz.is_file() and truth.is_file()):
        return {}
    rec = np.load(npz)
    t_rec = rec["t_ns"].astype(np.int64)
    pred = np.asarray(rec["joints_ned"], dtype=float)
    true = read_true_joints(truth)
    if true is None:
        return {}
    t_true, J = true
    inside = (t_rec >= t_true[0]) & (t_rec <= t_true[-1])
    if not inside.any():
        return {}
    gt = joints_at(t_true, J, t_rec[inside])
    pred = pred[inside]
    sj = list(SCORED_JOINTS)
    out = {"keypoints_source": keypoints_source or _capture_detectors(npz.parent / "capture.npz"),
           "position_grade": position_grade or "unknown",
           "joints_scored": "COCO-17 " + ", ".join(str(j) for j in sj),
           **accuracy_metrics(pred, gt, sj)}
    if window_s is not None:
        t_s = t_rec[inside] * 1e-9
        sel = (t_s >= window_s[0]) & (t_s <= window_s[1])
        if sel.any():
            out.update(accuracy_metrics(pred[sel], gt[sel], sj, suffix="_window"))
            out["window_s"] = [float(window_s[0]), float(window_s[1])]
    return out


def read_true_joints(truth_path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The person's true COCO-17 joints of a ``truth.mcap`` (SimTruth): (t_ns (T,) int64 in time order,
    joints (T, 17, 3) NED m); None with fewer than two samples."""
    ts, joints = [], []
    for m in FlightLog(truth_path).messages():
        if isinstance(m.msg, SimTruth) and len(m.msg.person_joints_ned_m) == 51:
            ts.append(m.msg.header.t_measurement_ns)
            joints.append(np.asarray(m.msg.person_joints_ned_m, dtype=float).reshape(17, 3))
    if len(ts) < 2:
        return None
    order = np.argsort(ts)
    return np.asarray(ts, dtype=np.int64)[order], np.asarray(joints)[order]


def joints_at(t_true_ns: np.ndarray, joints: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """Joints (T, 17, 3) at times ``t_true_ns`` (T,) -> at ``t_ns`` (Q,): (Q, 17, 3), linearly interpolated (held at
    the ends)."""
    tq = (np.asarray(t_ns, dtype=np.int64) - t_true_ns[0]).astype(float)
    tt = (np.asarray(t_true_ns, dtype=np.int64) - t_true_ns[0]).astype(float)
    J = np.asarray(joints, dtype=float).reshape(len(tt), -1)
    return np.stack([np.interp(tq, tt, J[:, k]) for k in range(J.shape[1])], -1).reshape(len(tq), 17, 3)


def _capture_detectors(path: Path) -> str:
    """The 2D keypoint detectors of a reconstruction's ``capture.npz`` (comma-separated), or "unknown"."""
    try:
        z = np.load(path, allow_pickle=False)
        names = sorted({str(d) for k in z.files if k.endswith(".detectors") for d in z[k].tolist()})
    except (OSError, ValueError, KeyError):
        return "unknown"
    return ", ".join(names) or "unknown"


def format_accuracy(acc: dict) -> str:
    """The accuracy lines the demo prints: steady orbit (window) and the whole flight, with what was scored."""
    def row(label: str, sfx: str) -> str:
        g = acc.get(f"per_group_mm{sfx}", {})
        groups = ", ".join(f"{k} {v['mpjpe_mm']:.1f}" for k, v in g.items())
        return (f"  {label:<40s} MPJPE {acc[f'mpjpe_mm{sfx}']:6.1f}  PA-MPJPE {acc[f'pa_mpjpe_mm{sfx}']:6.1f}  "
                f"W-MPJPE {acc[f'w_mpjpe_mm{sfx}']:6.1f}  root {acc[f'root_err_mm{sfx}']:6.1f} mm over "
                f"{acc[f'frames_scored{sfx}']} frames (MPJPE by group: {groups})")

    lines = [f"reconstruction vs truth (2D source: {acc.get('keypoints_source', 'unknown')}; position grade: "
             f"{acc.get('position_grade', 'unknown')}; MPJPE root-aligned, PA per frame, W-MPJPE world):"]
    if "mpjpe_mm_window" in acc:
        lines.append(row("steady orbit", "_window"))
    lines.append(row("whole flight incl. take-off and landing", ""))
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------
# tracking flights
def lost_time_s(t_tracking_s: np.ndarray, t0_s: float, t1_s: float, max_gap_s: float = 1.0) -> float:
    """Seconds of [t0, t1] not within max_gap_s after some time in t_tracking_s (sorted)."""
    t = np.sort(np.asarray(t_tracking_s, dtype=float))
    t = t[(t >= t0_s - max_gap_s) & (t <= t1_s)]
    if len(t) == 0:
        return float(t1_s - t0_s)
    covered_until = t0_s
    lost = 0.0
    for ti in t:
        if ti > covered_until:
            lost += ti - covered_until
        covered_until = max(covered_until, ti + max_gap_s)
    lost += max(0.0, t1_s - covered_until)
    return float(lost)


def _interp_rows(t_query: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t_query, t, rows[:, i]) for i in range(rows.shape[1])], axis=1)


def summarize_tracking(flight_dir: str | Path, settle_s: float = 8.0, sortie: int | None = None) -> dict:
    """The tracking figures of a ``--mode track`` flight (see the module doc); reads the recordings."""

    flight = FlightFolder(flight_dir)
    flight_dir = flight.path
    plan = flight.plan()
    drone_ids = sorted(plan.phase_offset_rad, key=natural_key)
    logs = _flight_logs(flight, drone_ids, sortie)
    tt, person, vpos, _ = flight.sim_truth(drone_ids)  # vpos: (T, D, 3)
    if not len(tt):
        raise SummaryError(f"{flight.truth_path} holds no simulator truth")
    tt = tt * 1e-9
    t_land = math.inf
    per = {}
    t_tracking_all = []
    for k, d in enumerate(drone_ids):
        t_est, p_est, status, t_state, p_state = [], [], [], [], []
        t_pub, p_pred = [], []
        rois: dict[int, tuple] = {}
        gt_boxes: dict[int, tuple] = {}
        det_t = []
        for m in SortieLogs([s.path for s in logs[d]]).messages(["target", "detections", "sim/keypoints2d_gt", "state", "gcs/cmd"]):
            msg = m.msg
            if isinstance(msg, TargetEstimate):
                t_est.append(msg.header.t_measurement_ns * 1e-9)
                p_est.append(msg.position_ned_m)
                status.append(msg.status)
                # predicted to the time it was sent (what a receiver acting at once would use)
                dt = (msg.header.t_sent_ns - msg.header.t_measurement_ns) * 1e-9
                t_pub.append(msg.header.t_sent_ns * 1e-9)
                p_pred.append(np.asarray(msg.position_ned_m) + dt * np.asarray(msg.velocity_ned_m_s))
            elif isinstance(msg, Detections):
                rois[msg.frame_index] = msg.roi_px
                det_t.append(msg.header.t_measurement_ns * 1e-9)
            elif isinstance(msg, Keypoints2D):
                if msg.persons and msg.persons[0].box is not None:
                    b = msg.persons[0].box
                    gt_boxes[msg.frame_index] = (b.x_min_px, b.y_min_px, b.x_max_px, b.y_max_px)
            elif isinstance(msg, VehicleState):
                t_state.append(msg.header.t_measurement_ns * 1e-9)
                p_state.append(msg.position_ned_m)
            elif isinstance(msg, Command) and msg.action == "land":
                t_land = min(t_land, msg.header.t_sent_ns * 1e-9)
        # the counters of the drone's latest sortie that wrote them (each agent start counts from zero)
        stats_paths = [s.track_stats_path for s in logs[d] if s.track_stats_path.is_file()]
        stats = json.loads(stats_paths[-1].read_text()) if stats_paths else {}
        per[d] = dict(t_est=np.asarray(t_est), p_est=np.asarray(p_est, dtype=float).reshape(-1, 3), status=status,
                      t_pub=np.asarray(t_pub), p_pred=np.asarray(p_pred, dtype=float).reshape(-1, 3),
                      rois=rois, gt_boxes=gt_boxes, det_t=np.asarray(sorted(det_t)), t_state=np.asarray(t_state),
                      p_state=np.asarray(p_state, dtype=float).reshape(-1, 3), stats=stats)
    t0 = plan.start_time_ns * 1e-9 + settle_s
    t1 = min(t_land, tt[-1])
    if t1 - t0 < 2.0:
        raise SummaryError(f"no steady tracking window in {flight_dir}: fly longer (--duration)")
    # each drone's position estimate error (reported - true) at its state samples: the own-position figures and
    # the fleet's common bias
    bias = {d: per[d]["p_state"] - _interp_rows(per[d]["t_state"], tt, vpos[:, j])
            for j, d in enumerate(drone_ids) if len(per[d]["t_state"])}
    out = {}
    for k, d in enumerate(drone_ids):
        P = per[d]
        sel = (P["t_est"] >= t0) & (P["t_est"] <= t1)
        if sel.sum():
            truth_p = _interp_rows(P["t_est"][sel], tt, person)
            err = P["p_est"][sel] - truth_p
            rmse = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
            rmse_h = float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1))))
        else:
            rmse = rmse_h = math.nan
        psel = (P["t_pub"] >= t0) & (P["t_pub"] <= t1)
        rmse_pred = math.nan
        if psel.sum():
            e_pred = P["p_pred"][psel] - _interp_rows(P["t_pub"][psel], tt, person)
            rmse_pred = float(np.sqrt(np.mean(np.sum(e_pred**2, axis=1))))
        t_tracking_all.extend(t for t, s, ok in zip(P["t_est"], P["status"], sel) if s == "tracking")
        frames = [f for f in P["rois"] if f in P["gt_boxes"]]
        hits = [box_in_roi(P["gt_boxes"][f], P["rois"][f]) for f in frames]
        dt_in = P["det_t"][(P["det_t"] >= t0) & (P["det_t"] <= t1)]
        solve = np.asarray(P["stats"].get("mpc_solve_ms", []), dtype=float)
        # own position error: reported state vs truth, without / with the filter's offset estimate
        before = after = math.nan
        ssel = (P["t_state"] >= t0) & (P["t_state"] <= t1)
        off = np.asarray(P["stats"].get("offset_log", []), dtype=float).reshape(-1, 4)
        if ssel.sum() and len(off) >= 2:
            e_own = bias[d][ssel]
            o_t = off[:, 0] * 1e-9
            oo = np.argsort(o_t)
            b = _interp_rows(P["t_state"][ssel], o_t[oo], off[oo, 1:])
            before = float(np.sqrt(np.mean(np.sum(e_own**2, axis=1))))
            after = float(np.sqrt(np.mean(np.sum((e_own - b) ** 2, axis=1))))
        # the same with the fleet's common GPS bias removed (truth-derived): without an absolute reference the
        # drones can only agree on a frame shifted by the mean of their biases; this is the error within it. The
        # biases drift (GPS wander, baro drift), so the mean is taken at each estimate's time, not over the window
        rmse_ff = math.nan
        if sel.sum():
            common = [_interp_rows(P["t_est"][sel], per[dj]["t_state"], bias[dj]) for dj in drone_ids
                      if len(per[dj]["t_state"]) >= 2]
            if common:
                e2 = err - np.mean(common, axis=0)
                rmse_ff = float(np.sqrt(np.mean(np.sum(e2**2, axis=1))))
        out[d] = {
            "target_rmse_m": round(rmse, 3),
            "target_rmse_fleet_frame_m": round(rmse_ff, 3),
            "target_rmse_h_m": round(rmse_h, 3),
            "target_rmse_at_send_m": round(rmse_pred, 3),
            "target_estimates": int(sel.sum()),
            "person_in_roi_rate": round(float(np.mean(hits)), 4) if hits else math.nan,
            "roi_frames": len(hits),
            "mpc_solve_ms_median": round(float(np.median(solve)), 3) if len(solve) else math.nan,
            "mpc_solve_ms_p99": round(float(np.percentile(solve, 99)), 3) if len(solve) else math.nan,
            "mpc_steps": int(len(solve)),
            "mpc_fallbacks": int(P["stats"].get("mpc_fallbacks", -1)),
            "detector_hz": round(float(len(dt_in) / (t1 - t0)), 2),
            "detections_source": P["stats"].get("detections_source", "unknown"),
            "self_pos_err_m_before": round(before, 3),
            "self_pos_err_m_after": round(after, 3),
            **_fault_figures(P["stats"]),
        }
    w = (tt >= t0) & (tt <= t1)
    return {
        "drones": out,
        "fleet": {
            "min_separation_m": _finite_or_none(min_pairwise_distance_m(np.transpose(vpos[w], (1, 0, 2)))),
            "configured_min_separation_m": plan.min_separation_m,
            "tracking_lost_s": round(lost_time_s(np.asarray(t_tracking_all), t0, t1), 2),
            "window_s": [round(float(t0), 3), round(float(t1), 3)],
            "truth_person_reference": "person_root_ned_m",
        },
    }


def _fault_figures(stats: dict) -> dict:
    """Failsafe and fault counters from an agent's ``<drone>.track.json`` (absent when the agent did not write
    it, e.g. killed): ``failsafe_events`` (decision changes), ``failsafe_counts`` (per action),
    ``malformed_detections`` (ignored: refused by the codec, by the tracking stage, non-finite),
    ``fault_judged`` / ``fault_dropped`` / ``fault_delayed`` (teammate messages the simulated network fault layer applied to / dropped / delayed), the filter's
    ``filter_refiltered`` (late measurements re-filtered), ``filter_rejected_gate``, ``filter_reinitialisations``."""
    if not stats:
        return {"agent_stats": False}
    fs = stats.get("filter_stats", {})
    tp = stats.get("transport", {})
    return {
        "agent_stats": True,
        "failsafe_events": len(stats.get("failsafe_events", [])),
        "failsafe_counts": dict(stats.get("failsafe_counts", {})),
        "malformed_detections": int(stats.get("malformed_detections", {}).get("total", 0)),
        "fault_judged": int(tp.get("fault_judged", 0)),
        "fault_dropped": int(tp.get("fault_dropped", 0)),
        "fault_delayed": int(tp.get("fault_delayed", 0)),
        "filter_refiltered": int(fs.get("refiltered", 0)),
        "filter_rejected_gate": int(fs.get("rejected_gate", 0)),
        "filter_reinitialisations": int(fs.get("reinitialisations", 0)),
    }


def format_tracking_table(tracking: dict) -> str:
    cols = ["target_rmse_m", "target_rmse_fleet_frame_m", "person_in_roi_rate", "mpc_solve_ms_median", "mpc_solve_ms_p99", "mpc_fallbacks",
            "detector_hz", "self_pos_err_m_before", "self_pos_err_m_after"]
    short = ["tgt_rmse_m", "tgt_rmse_ff_m", "in_roi", "mpc_med_ms", "mpc_p99_ms", "fallbacks", "det_hz", "pos_err_m", "pos_err_corr_m"]
    lines = _drone_table("tracking (fused estimate vs true person; own position error without / with the filter's "
                         "offset)", tracking["drones"], cols, short, 15)
    f = tracking["fleet"]
    lines.append(f"fleet: min_separation_m={_fmt_m(f['min_separation_m'])} (configured {f['configured_min_separation_m']}), "
                 f"tracking_lost_s={f['tracking_lost_s']:.1f}")
    return "\n".join(lines)
