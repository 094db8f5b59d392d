"""Benchmark: onboard person detector and 2D keypoint models (shipped ONNX files, onnxruntime CPU).

    python bench/bench_perception.py [--repeats 30] [--threads 1 2] [--image PATH]

Prints one table per thread count: detector latency on a 320x320 region of interest (the normal
onboard case; goal >= 30 Hz on one core), the full tiled search of a 1920x1080 frame (tiles mode, with
and without the extra 90-degree pass), the whole frame scaled to 640 (full mode), and the keypoint
latency per person crop for each model (crop + inference + mapping back; BlazePose includes its own
pose-detector stage). Times are wall time after warm-up: minimum, median and 90th percentile (on a
shared machine the minimum is the closest to the uncontended latency; the load average is printed) and
the median CPU time of the process (summed over its threads; with one thread, the single-core cost
even when other work shares the cores).
The frame is shared/data/images/aerial/general_example.png when present, else a synthetic frame.
"""

from __future__ import annotations

import argparse
import os
import sys
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from onboard.detector.detector import DetectorConfig, PersonDetector
from reconstruction.keypoints.detectors import KEYPOINT_MODELS, load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_IMAGE = REPO.parent / "shared" / "data" / "images" / "aerial" / "general_example.png"


def machine() -> str:
    import onnxruntime as ort

    return describe_machine(f"onnxruntime {ort.__version__}")

def timeit(fn, repeats: int, warmup: int = 2) -> tuple[float, float, float, float]:
    """(min, median, p90) of wall time and the median CPU time of this process (all its threads)."""
    for _ in range(warmup):
        fn()
    ts, cs = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    ts.sort()
    return ts[0], statistics.median(ts), ts[min(len(ts) - 1, int(0.9 * len(ts)))], statistics.median(cs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--image", type=Path, default=DEFAULT_IMAGE)
    args = ap.parse_args()
    if args.image.is_file():
        frame = cv2.imread(str(args.image))
        src = str(args.image.name)
    else:
        frame = np.random.default_rng(0).integers(0, 255, (1080, 1920, 3), dtype=np.uint8)
        src = "synthetic noise"
    frame = cv2.resize(frame, (1920, 1080)) if frame.shape[:2] != (1080, 1920) else frame
    roi = (520, 230, 320, 320)  # the group of pedestrians in general_example.png
    person_box = (557, 960, 47, 90)  # one pedestrian (about 90 px tall)
    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.1f} (1 min)")
    print(f"frame: {src} 1920x1080; ROI {roi}; keypoint box {person_box}; repeats {args.repeats}")
    for th in args.threads:
        rows = []
        det = PersonDetector(DetectorConfig(threads=th))
        mn, med, p90, cpu = timeit(lambda: det.detect(frame, "roi", roi), args.repeats)
        rows.append(("detector roi 320x320 (1 inference)", mn, med, p90, cpu))
        reps = max(3, args.repeats // 10)
        r = det.detect(frame, "tiles")
        mn, med, p90, cpu = timeit(lambda: det.detect(frame, "tiles"), reps, warmup=1)
        rows.append((f"detector tiles 1920x1080 ({r.inferences} inferences of 416x416)", mn, med, p90, cpu))
        det_up = PersonDetector(DetectorConfig(threads=th, tile_rotate_90=False))
        r = det_up.detect(frame, "tiles")
        mn, med, p90, cpu = timeit(lambda: det_up.detect(frame, "tiles"), reps, warmup=1)
        rows.append((f"detector tiles, no 90-deg pass ({r.inferences} inferences)", mn, med, p90, cpu))
        mn, med, p90, cpu = timeit(lambda: det.detect(frame, "full"), args.repeats)
        rows.append(("detector full frame at 640x360 (1 inference)", mn, med, p90, cpu))
        for name in KEYPOINT_MODELS:
            m = load_model(name, threads=th)
            mn, med, p90, cpu = timeit(lambda: m.predict([frame], np.array([person_box])), args.repeats)
            rows.append((f"keypoints {name} ({m.input_px}x{m.input_px}) per crop", mn, med, p90, cpu))
        print(f"\nintra-op threads: {th}")
        print(f"{'what':62s} {'min ms':>8s} {'median ms':>10s} {'p90 ms':>8s} {'Hz (median)':>12s} {'CPU ms':>8s}")
        for what, mn, med, p90, cpu in rows:
            print(f"{what:62s} {mn * 1e3:8.1f} {med * 1e3:10.1f} {p90 * 1e3:8.1f} {1.0 / med:12.1f} {cpu * 1e3:8.1f}")


if __name__ == "__main__":
    main()
