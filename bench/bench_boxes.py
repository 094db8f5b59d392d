"""Benchmark: the ``boxes`` step of ``skycap process`` alone, on a recorded flight, without the cache.

    python bench/bench_boxes.py FLIGHT [--out boxes.npz] [--set boxes.use_smoother=false ...]

Runs :func:`reconstruction.process.pipeline._boxes_step` over every drone (the smoother over all drones' detections,
the choice of boxes, the detector re-run in gaps) into a temporary folder and prints one JSON line: wall seconds,
the span of the recorded camera frames (what ``seconds_per_flight_second`` divides by), seconds per flight second,
this process's peak RSS (``ru_maxrss``: imports included) and the load average before / after. ``--out`` saves every
drone's boxes (``<drone>.box_xywh``, ``.source``, ``.t_ns``) to compare two versions. Run it in a fresh process per
measurement (the peak RSS is the process's).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flight", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="save the boxes here (npz)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="ProcessConfig overrides")
    a = ap.parse_args(argv)

    import numpy as np

    from flightdata.folder import FlightFolder
    from reconstruction.process import pipeline as P
    from reconstruction.process.cache import file_identity
    from reconstruction.process.config import ProcessConfig
    from reconstruction.process.frames import frame_table
    from skycap.config import load_config

    cfg = load_config(ProcessConfig, None, a.set).validate()
    flight = FlightFolder(a.flight)
    logs = flight.drone_logs(sortie=cfg.sortie_or_none)
    drones = list(logs)
    ident = {d: [file_identity(s.path) for s in logs[d]] for d in drones}
    spans = []
    for d in drones:
        t = frame_table(logs[d]).t_ns
        if len(t):
            spans += [int(t.min()), int(t.max())]
    span_s = (max(spans) - min(spans)) * 1e-9 if spans else float("nan")
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-boxes-") as tmp:
        def step_dir(step):
            p = Path(tmp) / step
            p.mkdir(parents=True, exist_ok=True)
            return p

        steps, skipped = {}, {}
        t0 = time.perf_counter()
        boxes = P._boxes_step(flight, logs, list(drones), skipped, ident, cfg, step_dir, None, None, steps)
        wall = time.perf_counter() - t0
    if a.out is not None:
        np.savez(a.out, **{f"{d}.{k}": np.asarray(z[k]) for d, z in boxes.items() for k in ("t_ns", "box_xywh", "source")})
    print(json.dumps({
        "flight": str(a.flight), "drones": drones, "boxes_s": round(wall, 2), "images_span_s": round(span_s, 2),
        "boxes_s_per_flight_s": round(wall / span_s, 4), "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "load_before": [round(x, 2) for x in load0], "load_after": [round(x, 2) for x in os.getloadavg()],
        "frames": {d: int(len(z["t_ns"])) for d, z in boxes.items()},
    }))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
