"""Judging a flight flown under a fault (``skycap faults run``): was it safe, what did the drones do, how much
recording was lost.

Pure functions on arrays (tested without files) and :func:`judge_flight`, which reads a flight folder (the
simulator's truth, each drone's recordings of every agent start) and applies them.

* **Safe** (from the simulator's truth, never from what the drones believed): the smallest distance between
  two drones stayed at or above the plan's ``min_separation_m``; no drone left the geofence (a cylinder of
  ``geofence_radius_m`` around the orbit centre, up to ``geofence_max_alt_m`` above ground); and every landing
  before the launcher's final land command is one the scenario's policy expects (``landing_by_policy``: e.g.
  the ground-station link lost -> the agents land by their ``safety.gcs_loss_action``; an agent killed and not
  restarted -> its vehicle lands on offboard loss). Any other touchdown is an *uncommanded landing*.
* **Recording lost** (from the recordings): a drone's recorder writes its own vehicle states (50 Hz) and the
  camera's frames (10 Hz); both stop only when the agent or its recorder does. Lost time = the gaps longer
  than ``max_gap_s`` in the union of the recorded ``state`` and ``camera/image`` log times, over every
  recording of that drone (a restarted agent writes a new ``drone_<i>.s<NNN>.mcap``; the gap across the
  two files is the restart), from the plan's start to the end of the judged window; the seam between two
  files of one drone (last message of one, first of the next: the restart) always counts, however short. A
  gap in one stream that
  the other one covers (no telemetry while the MAVLink link is down, the camera still recorded) is not lost
  recording; it is reported per stream (``stream_gaps_s``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flightdata.flightlog import SortieLogs
from flightdata.folder import FlightFolder, natural_key, read_sim_truth

log = logging.getLogger(__name__)

__all__ = ["SafetyLimits", "gaps_s", "geofence_excursions", "judge_flight", "judge_safety", "lost_with_seams_s",
           "min_separation_m", "recording_lost_s", "seams_s", "touchdowns_s"]


@dataclass
class SafetyLimits:
    """What "safe" means for a fault flight (see the module doc)."""

    min_separation_m: float = 3.0
    geofence_center_ned_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    geofence_radius_m: float = 20.0
    geofence_max_alt_m: float = 15.0
    #: the drones whose landing before the final land command the scenario's policy expects
    landing_by_policy: list[str] = field(default_factory=list)


def min_separation_m(pos_ned_m: np.ndarray) -> float:
    """Smallest distance between two drones at the same instant; pos_ned_m (D, T, 3); inf for D < 2."""
    D = pos_ned_m.shape[0]
    best = math.inf
    for i in range(D):
        for j in range(i + 1, D):
            if pos_ned_m.shape[1]:
                best = min(best, float(np.min(np.linalg.norm(pos_ned_m[i] - pos_ned_m[j], axis=-1))))
    return best


def geofence_excursions(t_s: np.ndarray, pos_ned_m: np.ndarray, center_ned_m, radius_m: float,
                        max_alt_m: float) -> list[float]:
    """Seconds each drone spent outside the geofence (horizontal radius ``radius_m`` around the centre, altitude
    above ground ``max_alt_m``); pos_ned_m (D, T, 3), t_s (T,) increasing."""
    if len(t_s) < 2:
        return [0.0] * pos_ned_m.shape[0]
    dt = np.diff(t_s, append=t_s[-1])
    c = np.asarray(center_ned_m, dtype=float)
    out = []
    for p in pos_ned_m:
        horiz = np.hypot(p[:, 0] - c[0], p[:, 1] - c[1])
        outside = (horiz > radius_m) | (-p[:, 2] > max_alt_m)
        out.append(float(np.sum(dt[outside])))
    return out


def touchdowns_s(t_s: np.ndarray, alt_m: np.ndarray, airborne_alt_m: float = 1.0, ground_alt_m: float = 0.3) -> list[float]:
    """Times a drone came down: each first sample at or below ``ground_alt_m`` after it was above
    ``airborne_alt_m`` (hysteresis: bouncing near the ground counts once)."""
    out, up = [], False
    for t, a in zip(t_s, alt_m):
        if not up and a > airborne_alt_m:
            up = True
        elif up and a <= ground_alt_m:
            out.append(float(t))
            up = False
    return out


def gaps_s(t_s: np.ndarray, t0_s: float, t1_s: float, max_gap_s: float) -> list[tuple[float, float]]:
    """The intervals within [t0_s, t1_s] longer than ``max_gap_s`` that hold no sample of ``t_s`` (the window's
    edges count as samples: nothing recorded at all in a window is one gap of the whole window)."""
    if t1_s <= t0_s:
        return []
    t = np.sort(np.asarray(t_s, dtype=float))
    t = t[(t >= t0_s) & (t <= t1_s)]
    edges = np.concatenate([[t0_s], t, [t1_s]])
    d = np.diff(edges)
    return [(float(edges[k]), float(edges[k + 1])) for k in np.nonzero(d > max_gap_s)[0]]


def recording_lost_s(streams_t_s: list[np.ndarray], t0_s: float, t1_s: float, max_gap_s: float = 0.5) -> tuple[float, list]:
    """Seconds of recording lost in [t0_s, t1_s]: the gaps longer than ``max_gap_s`` in the union of the
    streams' log times (s), and those gaps."""
    allt = np.concatenate([np.asarray(s, dtype=float) for s in streams_t_s]) if streams_t_s else np.zeros(0)
    g = gaps_s(allt, t0_s, t1_s, max_gap_s)
    return float(sum(b - a for a, b in g)), g


def seams_s(files_t_s: list[np.ndarray]) -> list[tuple[float, float]]:
    """The gaps between consecutive recordings of one drone: (last log time of file k, first of file k+1) for
    every pair of non-empty files in order."""
    nonempty = [np.asarray(t, dtype=float) for t in files_t_s if len(t)]
    return [(float(a.max()), float(b.min())) for a, b in zip(nonempty, nonempty[1:])]


def lost_with_seams_s(gaps: list[tuple[float, float]], seams: list[tuple[float, float]], t0_s: float,
                      t1_s: float) -> float:
    """Seconds lost: the long ``gaps`` plus the ``seams`` (restarts) that no long gap already covers, each
    clipped to [t0_s, t1_s]."""
    total = sum(b - a for a, b in gaps)
    for a, b in seams:
        a, b = max(a, t0_s), min(b, t1_s)
        if b > a and not any(ga <= a and b <= gb for ga, gb in gaps):
            total += b - a
    return float(total)


def judge_safety(t_s: np.ndarray, pos_ned_m: np.ndarray, drone_ids: list[str], limits: SafetyLimits,
                 t_final_land_s: float) -> dict:
    """The safety verdict from the truth: t_s (T,), pos_ned_m (D, T, 3) world NED; ``t_final_land_s``: when
    the launcher sent its final land command (landings after it are commanded)."""
    sep = min_separation_m(pos_ned_m)
    fence = geofence_excursions(t_s, pos_ned_m, limits.geofence_center_ned_m, limits.geofence_radius_m,
                                limits.geofence_max_alt_m)
    landings, uncommanded = {}, []
    for k, d in enumerate(drone_ids):
        downs = touchdowns_s(t_s, -pos_ned_m[k, :, 2])
        landings[d] = [round(x, 2) for x in downs]
        early = [x for x in downs if x < t_final_land_s]
        if early and d not in limits.landing_by_policy:
            uncommanded.append(d)
    reasons = []
    if sep < limits.min_separation_m:
        reasons.append(f"separation {sep:.2f} m < {limits.min_separation_m:.2f} m")
    out_of_fence = {d: round(s, 2) for d, s in zip(drone_ids, fence) if s > 0}
    if out_of_fence:
        reasons.append(f"outside the geofence: {out_of_fence} s")
    if uncommanded:
        reasons.append(f"uncommanded landing of {uncommanded}")
    return {"safe": not reasons, "unsafe_because": reasons,
            "min_separation_m": round(sep, 3) if math.isfinite(sep) else None,
            "configured_min_separation_m": limits.min_separation_m,
            "geofence_outside_s": {d: round(s, 2) for d, s in zip(drone_ids, fence)},
            "touchdowns_s": landings, "uncommanded_landings": uncommanded,
            "landing_by_policy": list(limits.landing_by_policy)}


def judge_flight(flight_dir: str | Path, drone_ids: list[str], limits: SafetyLimits, t_start_s: float,
                 t_final_land_s: float, max_gap_s: float = 0.5) -> dict:
    """Read ``flight_dir`` (truth.mcap and every recording of each drone) and judge it: the safety verdict
    (:func:`judge_safety`) and, per drone, the recording lost between ``t_start_s`` (the plan's start) and the
    final land command (or the drone's own touchdown before it)."""
    flight = FlightFolder(flight_dir)
    drone_ids = sorted(drone_ids, key=natural_key)
    t_ns, _, pos, _ = read_sim_truth(flight.truth_path, drone_ids)
    t_s = t_ns * 1e-9
    pos = np.transpose(pos, (1, 0, 2))
    verdict = judge_safety(t_s, pos, drone_ids, limits, t_final_land_s)
    logs = flight.drone_logs(drone_ids=drone_ids)
    per: dict[str, dict] = {}
    for d in drone_ids:
        sessions = logs.get(d, [])
        streams: dict[str, list[float]] = {"state": [], "camera/image": []}
        per_file: list[np.ndarray] = []
        for s in sessions:
            file_t: list[float] = []
            for m in SortieLogs([s.path]).messages(list(streams), decode_messages=False):
                streams[m.topic].append(m.log_time_ns * 1e-9)
                file_t.append(m.log_time_ns * 1e-9)
            per_file.append(np.asarray(file_t))
        # the drone's window ends at its own touchdown when it came down before the final land command
        downs = [x for x in verdict["touchdowns_s"].get(d, []) if x < t_final_land_s]
        t_end = min([t_final_land_s, *downs])
        arr = [np.asarray(v) for v in streams.values()]
        _, gaps = recording_lost_s(arr, t_start_s, t_end, max_gap_s)
        seams = seams_s(per_file)
        lost = lost_with_seams_s(gaps, seams, t_start_s, t_end)
        per[d] = {
            "recordings": [s.path.name for s in sessions],
            "recording_lost_s": round(lost, 3),
            "file_seams": [[round(a - t_start_s, 3), round(b - t_start_s, 3)] for a, b in seams],
            "recording_gaps": [[round(a - t_start_s, 2), round(b - t_start_s, 2)] for a, b in gaps],
            "stream_gaps_s": {k: round(sum(b - a for a, b in gaps_s(np.asarray(v), t_start_s, t_end, max_gap_s)), 3)
                              for k, v in streams.items()},
            "judged_window_s": [0.0, round(t_end - t_start_s, 2)],
            "messages_recorded": {k: len(v) for k, v in streams.items()},
        }
    return {**verdict, "drones": per}
