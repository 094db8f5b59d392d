"""Benchmark: the offline smoother (reconstruction.track) on synthetic flights of 3, 5 and 8 drones, and
optionally ``skycap refine`` stages on recorded flight folders.

    python bench/bench_smoother.py [--duration 60] [--flight /tmp/trk ...]

Per drone count: detections at 10 Hz per drone, GPS-grade offsets (1 m / 0.5 m, 60 s), 2 px box noise; the
table gives the smoother's wall time (all re-weighting passes), steps, state size, passes, and the person
track RMSE with the drifting fleet-common offset removed (smoothed vs its own causal forward pass).
With ``--flight``: read time (MCAP -> detections), box -> observation time, smoothing time, ROI time.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "recon_track"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import describe_machine  # noqa: E402
from recon_track_scene import make_scene  # noqa: E402

from reconstruction.track.smoother import SmootherConfig, smooth_track  # noqa: E402


def _rms(e):
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))


def synthetic(duration_s: float) -> list[str]:
    rows = [f"{'drones':>6s}{'state':>7s}{'frames':>8s}{'steps':>7s}{'passes':>8s}{'smooth_s':>10s}{'ms/step':>9s}"
            f"{'rmse_ff_fwd_m':>15s}{'rmse_ff_smooth_m':>18s}"]
    for D in (3, 5, 8):
        sc = make_scene(seed=D, duration_s=duration_s, n_drones=D)
        ids = [f"drone_{d}" for d in range(D)]
        t0 = time.perf_counter()
        tr = smooth_track(sc.measurements, ids, SmootherConfig(offset_sigma_m=(1.0, 1.0, 0.5)))
        dt = time.perf_counter() - t0
        ts = tr.t_ns * 1e-9
        keep = ts > 3.0
        common = np.mean([sc.at(ts[keep], sc.bias[:, d]) for d in range(D)], axis=0)
        truth = sc.at(ts[keep], sc.person) + common
        rows.append(f"{D:6d}{6 + 3 * D:7d}{len(tr.frame_t_ns):8d}{len(ts):7d}{tr.iterations + 1:8d}{dt:10.2f}"
                    f"{1e3 * dt / len(ts) / (tr.iterations + 1):9.3f}{_rms(tr.filtered_position_ned_m[keep] - truth):15.3f}"
                    f"{_rms(tr.position_ned_m[keep] - truth):18.3f}")  # fmt: skip
    return rows


def flight(folder: Path) -> list[str]:
    from reconstruction.track import flight as F

    t0 = time.perf_counter()
    recs = F.read_recordings(folder)
    t1 = time.perf_counter()
    settings = F.flight_settings(folder)
    H = settings.get("person_height_m", 1.69)
    obs, sig = F.flight_observations(recs, H, settings.get("camera_position_sigma_m", 1.0))
    t2 = time.perf_counter()
    tr = smooth_track(obs, [r.drone_id for r in recs], SmootherConfig(), offset_sigma_m=sig)
    t3 = time.perf_counter()
    for r in recs:
        F.frame_boxes(tr, r, H)
    t4 = time.perf_counter()
    return [f"{folder}: {len(recs)} drones, {len(obs)} observations, {len(tr.t_ns)} steps: read {t1 - t0:.2f} s, "
            f"boxes->observations {t2 - t1:.2f} s, smooth {t3 - t2:.2f} s ({tr.iterations + 1} passes), ROIs {t4 - t3:.2f} s"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="synthetic flight length, s")
    ap.add_argument("--flight", type=Path, action="append", default=[], help="recorded flight folder(s) to time")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    print(describe_machine(f"numpy {np.__version__}"))
    print(f"synthetic {a.duration:.0f} s flights, 10 Hz detections per drone")
    for row in synthetic(a.duration):
        print(row)
    for f in a.flight:
        for row in flight(f):
            print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
