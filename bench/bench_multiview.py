"""Frames per second of the multiview fits: product (whole sequence) vs paper (AirCap per-frame schedule).

    python bench/bench_multiview.py [--motion FILE.bvh] [--frames 300] [--paper-frames 30] [--device cpu]

One synthetic capture (default harness setting: 3 drones, 8 m radius and altitude, 5 px noise, 10 %
outliers, 0.5 m / 2 deg camera noise, unsynchronised) of ``--frames`` output frames x 3 cameras. The
product path fits all of them; the paper path (1000 Adam steps on the first frame, 100 on each next) is
run on the first ``--paper-frames`` frames and its time extrapolated linearly to ``--frames`` (its cost
is per frame, so this is exact up to the first frame's extra 900 steps, which are counted once).
Accuracy (MPJPE / PA-MPJPE on the frames each path fitted) is printed beside the speed. Without
``--motion`` a CMU clip from ../shared/data is used if present, else a procedural walker.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motion", type=Path, default=None)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--paper-frames", type=int, default=30)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()

    from reconstruction.metrics import mpjpe_mm, pa_mpjpe_mm
    from reconstruction.multiview.evaluate import load_motion
    from reconstruction.multiview.fit import FitConfig, fit_capture
    from reconstruction.synth import SynthConfig, procedural_walker, synthesize_capture
    from skycap.skeleton import SCORED_JOINTS

    motion = a.motion
    if motion is None:
        cand = Path(__file__).resolve().parents[2] / "shared/data/mocap/cmu/002/002_05.bvh"
        motion = cand if cand.is_file() else None
    scfg = SynthConfig()
    if motion is not None:
        J, t_ns, fps = load_motion(motion)
        step = int(round(fps / scfg.camera_rate_hz))
        idx = np.arange(0, len(J), step)[: a.frames]
        J, t_ns, name = J[: idx[-1] + 1], t_ns[: idx[-1] + 1], motion.name
    else:
        J, t_ns, *_ = procedural_walker(a.frames, scfg.camera_rate_hz)
        idx, name = np.arange(len(J)), "procedural walker"
    cap, _ = synthesize_capture(J, t_ns, scfg, seed=0)
    tg, gt = t_ns[idx], J[idx]
    # warm-up (imports, allocator) on a few frames, not timed
    fit_capture(cap, tg[:8], FitConfig(iters=5, device=a.device), progress=False)

    c0 = time.process_time()
    prod = fit_capture(cap, tg, FitConfig(method="product", device=a.device), progress=False)
    prod_cpu = time.process_time() - c0
    n_p = min(a.paper_frames, len(tg))
    c0 = time.process_time()
    pap = fit_capture(cap, tg[:n_p], FitConfig(method="paper", device=a.device), progress=False)
    pap_cpu = time.process_time() - c0
    # extrapolate the paper path: first frame (1000 steps) once + per-frame cost of the others
    per_frame = pap.fit_seconds / (n_p + 9)  # the first frame costs ~10 frames (1000 vs 100 steps)
    pap_total = per_frame * (len(tg) + 9)
    rows = [
        ("product", len(tg), prod.fit_seconds, len(tg) / prod.fit_seconds, prod_cpu,
         mpjpe_mm(prod.joints_ned, gt, SCORED_JOINTS), pa_mpjpe_mm(prod.joints_ned, gt, SCORED_JOINTS),
         mpjpe_mm(prod.joints_ned[:n_p], gt[:n_p], SCORED_JOINTS), pa_mpjpe_mm(prod.joints_ned[:n_p], gt[:n_p], SCORED_JOINTS)),
        ("paper (extrapolated)", len(tg), pap_total, len(tg) / pap_total, pap_cpu * (len(tg) + 9) / (n_p + 9),
         float("nan"), float("nan"), mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS), pa_mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS)),
        (f"paper (measured, {n_p} frames)", n_p, pap.fit_seconds, n_p / pap.fit_seconds, pap_cpu,
         mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS), pa_mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS),
         mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS), pa_mpjpe_mm(pap.joints_ned, gt[:n_p], SCORED_JOINTS)),
    ]  # fmt: skip
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"device {a.device}, threads 1; load average {os.getloadavg()[0]:.1f}")  # fmt: skip
    print(f"motion: {name}; {len(tg)} output frames x {cap.num_cameras} cameras (unsynchronised, 30 fps)")
    print(f"{'path':32s} {'frames':>6s} {'wall s':>8s} {'frames/s':>9s} {'cpu s':>8s} {'MPJPE':>7s} {'PA':>7s} {'MPJPE first':>11s} {'PA first':>8s}")
    for r in rows:
        print(f"{r[0]:32s} {r[1]:6d} {r[2]:8.1f} {r[3]:9.2f} {r[4]:8.1f} {r[5]:7.1f} {r[6]:7.1f} {r[7]:11.1f} {r[8]:8.1f}")
    print(f"speed-up product vs paper schedule: {pap_total / prod.fit_seconds:.1f}x wall, "
          f"{(pap_cpu * (len(tg) + 9) / (n_p + 9)) / prod_cpu:.1f}x CPU time ('first' = on the paper's {n_p} frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
