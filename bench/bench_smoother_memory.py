"""Benchmark: peak RSS and time of the offline smoother alone on a synthetic flight as long as you like.

    python bench/bench_smoother_memory.py [--duration 600] [--drones 3] [--rate 7] [--passes 0] [--segment-s 60]

Observations as the boxes step feeds them (``Observation``: a person centre per drone and frame, J_offset = I,
3x3 noise) of a random-walking person seen by ``--drones`` drones at ``--rate`` Hz each, drifting offsets; the
smoother's 20 Hz output grid. ``--passes`` caps the re-weighting passes (``max_iterations``: the peak memory is
reached in the first pass already, the time grows with the passes). Prints one JSON line: the process's RSS after
building the observations, its peak (``ru_maxrss``) after smoothing, the difference, the wall seconds and the
steps. Runs against any checkout (``segment_s`` is only passed where the SmootherConfig has it). One process per
measurement: the peak is the process's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--rate", type=float, default=7.0)
    ap.add_argument("--passes", type=int, default=0)
    ap.add_argument("--segment-s", type=float, default=None)
    a = ap.parse_args(argv)

    import numpy as np

    from reconstruction.track.smoother import Observation, SmootherConfig, smooth_track

    rng = np.random.default_rng(0)
    t = np.arange(0.0, a.duration, 1.0 / a.rate)
    person = np.cumsum(rng.normal(0, 0.1, (len(t), 3)), axis=0) * [1, 1, 0]
    obs = []
    for d in range(a.drones):
        bias = np.cumsum(rng.normal(0, 0.005, (len(t), 3)), axis=0)
        z = person + bias + rng.normal(0, 0.1, (len(t), 3))
        R = 0.01 * np.eye(3)
        obs += [Observation(int(round((tk + 0.013 * d) * 1e9)), d, z[k], R) for k, tk in enumerate(t)]
    kw = {"max_iterations": a.passes}
    if a.segment_s is not None:
        kw["segment_s"] = a.segment_s
    cfg = dataclasses.replace(SmootherConfig(), **kw)
    rss0 = _rss_mb()
    t0 = time.perf_counter()
    tr = smooth_track(obs, [f"d{i}" for i in range(a.drones)], cfg)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"duration_s": a.duration, "drones": a.drones, "rate_hz": a.rate, "passes_cap": a.passes,
                      "segment_s": getattr(cfg, "segment_s", "n/a (whole flight)"), "steps": int(len(tr.t_ns)),
                      "rss_before_mb": round(rss0, 1), "peak_rss_mb": round(peak, 1), "peak_minus_before_mb": round(peak - rss0, 1),
                      "smooth_s": round(wall, 2), "load": [round(x, 2) for x in os.getloadavg()]}))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
