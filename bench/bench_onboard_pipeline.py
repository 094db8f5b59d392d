"""Benchmark: the whole onboard pipeline per camera frame, with the real components: capture (GStreamer) ->
JPEG for the recorder -> decode for the detector -> ONNX person detector on the ROI -> the frame's pose ->
cooperative filter -> formation MPC (per control step).

    python bench/bench_onboard_pipeline.py [--seconds 5] [--size 1280x720] [--fps 30] [--repeats 30]

Each stage's cost is CPU time of this process (all its threads; one intra-op thread for onnxruntime), the
median over the repeats, beside its wall time. The capture stage is measured over a live ``videotestsrc``
pipeline at the given size and rate: CPU seconds of the process / frames delivered, which includes the test
pattern's generation and the conversion to BGR that a real camera's driver (or its MJPEG decode) replaces. The
table ends with the per-frame sum, the frame rate one core of this machine sustains, and what that implies for
a Raspberry Pi 5 and a Jetson Orin Nano class companion computer (an estimate from relative single-core speed,
stated as such: neither was measured here).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "onboard" / "tracking"))
from _machine import describe_machine  # noqa: E402
from bench_perception import timeit  # noqa: E402
from bench_tracking import bench_filter, bench_mpc  # noqa: E402

from onboard.camera.pose import CameraPoser  # noqa: E402
from onboard.camera.sources import GStreamerSource  # noqa: E402
from onboard.detector.detector import DetectorConfig, PersonDetector  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
IMAGE = REPO.parent / "shared" / "data" / "images" / "aerial" / "general_example.png"

#: single-core speed of each board's CPU relative to this machine's core for this kind of work (float inference,
#: OpenCV, numpy): a range, from public per-core benchmark ratios of Cortex-A76 @ 2.4 GHz (Pi 5) and
#: Cortex-A78AE @ 1.5 GHz (Orin Nano) against a Zen 2 server core at ~3 GHz. An estimate, not a measurement.
BOARDS = {"Raspberry Pi 5 (4x Cortex-A76 2.4 GHz)": (0.45, 0.65),
          "Jetson Orin Nano (6x Cortex-A78AE 1.5 GHz), CPU only": (0.35, 0.5)}


def timed(fn, repeats: int, warmup: int = 2) -> tuple[float, float]:
    """(median wall ms, median CPU ms of this process) of ``fn()`` (bench_perception's timer)."""
    _mn, med, _p90, cpu = timeit(fn, repeats, warmup)
    return med * 1e3, cpu * 1e3


def capture_cost(width: int, height: int, fps: int, seconds: float) -> tuple[float, float, int, int]:
    """(wall ms per frame, CPU ms per frame, frames, dropped) of a live GStreamer capture to BGR frames."""
    src = GStreamerSource(f"videotestsrc is-live=true pattern=ball ! video/x-raw,width={width},height={height},"
                          f"framerate={fps}/1")
    src.open()
    try:
        while src.read(2.0) is None:  # the pipeline is up
            pass
        n, c0, t0 = 0, time.process_time(), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            if src.read(1.0) is not None:
                n += 1
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return wall / max(n, 1) * 1e3, cpu / max(n, 1) * 1e3, n, src.stats.dropped
    finally:
        src.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="capture measured over this long")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--fps", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=30)
    a = ap.parse_args(argv)
    import onnxruntime as ort

    w, h = (int(v) for v in a.size.split("x"))
    print(f"machine: {describe_machine(f'onnxruntime {ort.__version__}', f'OpenCV {cv2.__version__}')}")
    if IMAGE.is_file():
        img = cv2.resize(cv2.imread(str(IMAGE)), (w, h))
        what = f"{IMAGE.name} scaled to {w}x{h}"
    else:
        img = np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8)
        what = f"synthetic noise {w}x{h}"
    print(f"frame: {what}; capture: videotestsrc {w}x{h} @ {a.fps} fps for {a.seconds:.0f} s; repeats {a.repeats}")
    rows: list[tuple[str, float, float, str]] = []

    cw, cc, n, dropped = capture_cost(w, h, a.fps, a.seconds)
    rows.append(("capture: GStreamer -> BGR frame with its capture time", cw, cc, f"{n} frames, {dropped} dropped"))
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    rows.append(("JPEG encode q90 (camera service: camera/image, recorded)",
                 *timed(lambda: cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90]), a.repeats),
                 f"{len(jpg) / 1e3:.0f} kB"))
    rows.append(("JPEG decode (the detector's worker)",
                 *timed(lambda: cv2.imdecode(jpg, cv2.IMREAD_COLOR), a.repeats), ""))
    det = PersonDetector(DetectorConfig(threads=1))
    roi = (w * 0.27, h * 0.21, 320, 320)
    rows.append(("person detector, ROI 320x320 (1 thread)", *timed(lambda: det.detect(img, "roi", roi), a.repeats),
                 det.name))
    poser = CameraPoser("gimbal", -0.5)
    from types import SimpleNamespace as NS
    for k in range(50):
        poser.add_state(NS(header=NS(t_measurement_ns=k * 20_000_000), position_ned_m=(0.1 * k, 0.0, -8.0),
                           q_world_body=(1.0, 0.0, 0.0, 0.0)))
        poser.add_gimbal(NS(header=NS(t_measurement_ns=k * 100_000_000), pitch_rad=-0.5, yaw_rad=0.0))
    rows.append(("frame pose at capture (states + gimbal interpolated)",
                 *timed(lambda: poser.T_world_cam(500_000_000), a.repeats * 10), ""))
    filt = {name: (med, cpu) for name, med, _p99, _mx, cpu in bench_filter(360)}
    meas = filt["measurement_from_box (height_and_ground + covariance)"]
    add = next(v for k, v in filt.items() if k.startswith("filter add, in order (3 drones"))
    rows.append(("box -> measurement + cooperative filter add (3 drones)", meas[0] + add[0], meas[1] + add[1], ""))
    m = bench_mpc(3, "osqp", "bvc", 60)
    rows.append(("formation MPC step (3 drones, OSQP) per control step", m["step_med"], m["cpu_med"],
                 f"{m['fallbacks']} fallbacks / {m['solves']}"))

    print()
    print("| stage | wall median ms | CPU median ms | note |")
    print("| --- | --- | --- | --- |")
    for name, wall, cpu, note in rows:
        print(f"| {name} | {wall:.2f} | {cpu:.2f} | {note} |")
    # every captured frame is converted, encoded and recorded; the detector's worker takes the newest frame when it
    # is free (newest wins), so detection runs at its own rate: decode + detector + pose + filter per detection
    frame_cpu = rows[0][2] + rows[1][2]
    det_cpu = sum(r[2] for r in rows[2:6])
    mpc_cpu, ctl_hz = rows[6][2], 10.0
    print()
    print(f"every frame (capture + JPEG for the recorder): {frame_cpu:.1f} CPU ms -> {a.fps} fps uses "
          f"{frame_cpu * a.fps / 10:.0f} % of a core")
    print(f"every detection (decode + detector ROI + pose + filter): {det_cpu:.1f} CPU ms -> at most "
          f"{1000 / det_cpu:.1f} detections/s on one core")
    print(f"formation MPC at {ctl_hz:.0f} Hz: {mpc_cpu * ctl_hz / 10:.0f} % of a core")
    print()
    print(f"| companion computer (estimate: this machine's CPU ms / relative single-core speed) | every frame CPU ms "
          f"| {a.fps} fps capture + record, share of one core | detection CPU ms | detections/s on one core |")
    print("| --- | --- | --- | --- | --- |")
    print(f"| this machine (measured) | {frame_cpu:.1f} | {frame_cpu * a.fps / 10:.0f} % | {det_cpu:.0f} | "
          f"{1000 / det_cpu:.1f} |")
    for board, (lo, hi) in BOARDS.items():
        f_lo, f_hi = frame_cpu / hi, frame_cpu / lo
        d_lo, d_hi = det_cpu / hi, det_cpu / lo
        print(f"| {board} | {f_lo:.0f}-{f_hi:.0f} | {f_lo * a.fps / 10:.0f}-{f_hi * a.fps / 10:.0f} % | "
              f"{d_lo:.0f}-{d_hi:.0f} | {1000 / d_hi:.1f}-{1000 / d_lo:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
