"""Benchmark of the simulator's camera rendering: ms per frame at a few image sizes.

    python bench/bench_render.py [--frames 40] [--sizes 320x180,640x360,960x540,1280x720] [--rate 10 --cameras 3]

Renders a drone orbiting the default person (8 m radius, 4 m up, gimbal at the person) and prints, per
size, the median milliseconds of each stage (ground+sky, shadow, person, JPEG encoding), the whole camera
step (render + JPEG + simulated detectors + messages, as :class:`CameraNode.step` does it) and what
``--cameras`` cameras at ``--rate`` Hz cost in CPU cores. Single process, OpenCV threads as configured
(``--cv-threads``, default 1: one camera process per drone on a shared machine).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from simulator.scene.camera import camera_pose
from simulator.scene.camera_node import CameraNode, CameraTruth
from simulator.scene.config import CameraConfig, SceneConfig
from simulator.scene.person import PersonSim
from simulator.scene.render import encode_jpeg

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402


def _machine() -> str:
    return describe_machine(f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads)")

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--sizes", default="320x180,480x270,640x360,960x540,1280x720")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--cv-threads", type=int, default=1)
    args = ap.parse_args(argv)
    cv2.setNumThreads(args.cv_threads)
    person = PersonSim()
    print(f"machine: {_machine()}")
    print(f"scene: orbit r=8 m, 4 m up, person walking/jumping; {args.frames} frames per size (median ms)")
    hdr = f"{'size':>10} {'ground':>7} {'shadow':>7} {'person':>7} {'render':>7} {'jpeg':>6} {'step':>6} {'stepCPU':>7} {'kB/frame':>8} {'person px':>9}  {args.cameras} cams @ {args.rate:g} Hz"
    print("wall-clock medians per stage; stepCPU = process CPU time of a whole CameraNode.step (the cost)")
    print(hdr)
    print("-" * len(hdr))
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.lower().split("x"))
        cfg = SceneConfig(camera=CameraConfig(width_px=w, height_px=h, rate_hz=args.rate))
        state = {"t": 0.0}

        def truth() -> CameraTruth:
            t = state["t"]
            a = 0.25 * t
            pos = np.array([8 * math.cos(a), 8 * math.sin(a), -4.0])
            x, y, z, qw = Rotation.from_euler("ZYX", [math.atan2(-pos[1], -pos[0]), 0, 0]).as_quat()
            q = np.array([qw, x, y, z])
            return CameraTruth(int(t * 1e9), pos, q, -math.atan2(3.0, 8.0), person.state_at(t).joints_ned_m, pos, q)

        node = CameraNode("drone_1", cfg, truth, lambda topic, msg: None)
        rec: dict[str, list[float]] = {k: [] for k in ("ground_ms", "shadow_ms", "person_ms", "total_ms", "jpeg", "step", "step_cpu", "kb", "hpx")}
        for i in range(args.frames + 3):
            state["t"] = 0.37 * i
            ct = truth()
            T = camera_pose(cfg.camera, ct.position_ned_m, ct.q_world_body, ct.gimbal_pitch_rad)
            fr = node.renderer.render(T, ct.person_joints_ned_m)
            t0 = time.perf_counter()
            data = encode_jpeg(fr.image, cfg.camera.jpeg_quality)
            t1 = time.perf_counter()
            c1 = time.process_time()
            node.step()
            t2 = time.perf_counter()
            c2 = time.process_time()
            if i < 3:
                continue  # warm-up
            for k in ("ground_ms", "shadow_ms", "person_ms", "total_ms"):
                rec[k].append(fr.timings_ms.get(k, 0.0))
            rec["jpeg"].append((t1 - t0) * 1e3)
            rec["step"].append((t2 - t1) * 1e3)
            rec["step_cpu"].append((c2 - c1) * 1e3)
            rec["kb"].append(len(data) / 1024)
            b = fr.gt.box_px if fr.gt is not None else None
            rec["hpx"].append(0.0 if b is None else b[3] - b[1])
        m = {k: float(np.median(v)) for k, v in rec.items()}
        m["step_cpu"] = float(np.mean(rec["step_cpu"]))  # process_time ticks coarsely: mean, not median
        cores = args.cameras * args.rate * m["step_cpu"] / 1000.0
        print(
            f"{size:>10} {m['ground_ms']:7.1f} {m['shadow_ms']:7.1f} {m['person_ms']:7.1f} {m['total_ms']:7.1f} "
            f"{m['jpeg']:6.1f} {m['step']:6.1f} {m['step_cpu']:7.1f} {m['kb']:8.1f} {m['hpx']:9.0f}  {cores:5.2f} cores"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
