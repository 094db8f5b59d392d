"""Benchmark of the simulator's camera rendering: ms per frame at a few image sizes.

    python bench/bench_render.py [--frames 40] [--sizes 320x180,640x360,960x540,1280x720] [--rate 10 --cameras 3]
                                 [--person-model ellipsoids|anny] [--blur 0.6 --noise 2]
    python bench/bench_render.py --keypoints 100 [--person-model anny]   # the real models' error on the render

Renders a drone orbiting the default person (8 m radius, 4 m up, gimbal at the person) and prints, per
size, the median milliseconds of each stage (ground+sky, shadow, person, JPEG encoding), the whole camera
step (render + JPEG + simulated detectors + messages, as :class:`CameraNode.step` does it) and what
``--cameras`` cameras at ``--rate`` Hz cost in CPU cores. Single process, OpenCV threads as configured
(``--cv-threads``, default 1: one camera process per drone on a shared machine).

``--realtime S`` instead runs ``--cameras`` :class:`CameraNode` loops (one process each, as the demo runs
them) at ``--rate`` Hz for S seconds at the first size, with the orbiting drone's truth, and prints the
frames each delivered against the schedule, the late ones and the CPU per frame.

``--keypoints N`` instead renders N frames of varied views (distance 4-12 m, height 1.5-8 m, any
azimuth, any time of the person's loop, body seeds 0..5 for the Anny person) at the first size, runs the
shipped keypoint models on each with the true body box, and prints per model the median error of the
joints inside the image as a percentage of the box height (and the 90th percentile, the share under 5 %).
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
    ap.add_argument("--person-model", default="ellipsoids", choices=("ellipsoids", "anny"))
    ap.add_argument("--blur", type=float, default=-1.0, help="camera.blur_sigma_px (-1: the person model's default)")
    ap.add_argument("--noise", type=float, default=-1.0, help="camera.noise_std (-1: the person model's default)")
    ap.add_argument("--realtime", type=float, default=0.0,
                    help="run --cameras camera nodes (one process each) at --rate for this many seconds instead")
    ap.add_argument("--keypoints", type=int, default=0, help="measure the keypoint models on N frames instead")
    ap.add_argument("--models", default="movenet_lightning,movenet_thunder,blazepose_full")
    ap.add_argument("--save", default="", help="with --keypoints: write a contact sheet of the first frames here")
    args = ap.parse_args(argv)
    cv2.setNumThreads(args.cv_threads)
    if args.keypoints:
        return keypoint_error(args)
    if args.realtime:
        return realtime(args)
    person = PersonSim()
    print(f"machine: {_machine()}")
    print(f"person model: {args.person_model}, blur {args.blur} px, noise {args.noise}")
    print(f"scene: orbit r=8 m, 4 m up, person walking/jumping; {args.frames} frames per size (median ms)")
    hdr = f"{'size':>10} {'ground':>7} {'shadow':>7} {'person':>7} {'render':>7} {'jpeg':>6} {'step':>6} {'stepCPU':>7} {'kB/frame':>8} {'person px':>9}  {args.cameras} cams @ {args.rate:g} Hz"
    print("wall-clock medians per stage; stepCPU = process CPU time of a whole CameraNode.step (the cost)")
    print(hdr)
    print("-" * len(hdr))
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.lower().split("x"))
        cfg = SceneConfig(camera=CameraConfig(width_px=w, height_px=h, rate_hz=args.rate, person_model=args.person_model,
                                              blur_sigma_px=args.blur, noise_std=args.noise))
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


def _realtime_camera(args, w: int, h: int, k: int, out) -> None:
    import threading

    cv2.setNumThreads(args.cv_threads)
    cfg = SceneConfig(camera=CameraConfig(width_px=w, height_px=h, rate_hz=args.rate, person_model=args.person_model,
                                          blur_sigma_px=args.blur, noise_std=args.noise))
    person = PersonSim()
    t_start = time.monotonic()

    def truth() -> CameraTruth:
        t = time.monotonic() - t_start
        a = 0.25 * t + k * 2.0944
        pos = np.array([8 * math.cos(a), 8 * math.sin(a), -4.0])
        x, y, z, qw = Rotation.from_euler("ZYX", [math.atan2(-pos[1], -pos[0]), 0, 0]).as_quat()
        q = np.array([qw, x, y, z])
        return CameraTruth(int(t * 1e9), pos, q, -math.atan2(3.0, 8.0), person.state_at(t).joints_ned_m, pos, q)

    node = CameraNode(f"drone_{k + 1}", cfg, truth, lambda topic, msg: None)
    stop = threading.Event()
    threading.Timer(args.realtime, stop.set).start()
    node.run(stop)
    out.put((k, dict(node.stats)))


def realtime(args) -> int:
    """``--cameras`` camera processes at ``--rate`` for ``--realtime`` seconds (see the module doc)."""
    import multiprocessing as mp

    w, h = (int(v) for v in args.sizes.split(",")[0].lower().split("x"))
    q = mp.get_context("spawn").Queue()
    procs = [mp.get_context("spawn").Process(target=_realtime_camera, args=(args, w, h, k, q)) for k in range(args.cameras)]
    for p in procs:
        p.start()
    res = dict(q.get() for _ in procs)
    for p in procs:
        p.join()
    print(f"machine: {_machine()}")
    print(f"{args.cameras} camera processes, {args.person_model} at {w}x{h}, {args.rate:g} Hz for {args.realtime:g} s "
          f"(blur {args.blur} px, noise {args.noise}); expected {args.rate * args.realtime:.0f} frames each")
    for k in sorted(res):
        st = res[k]
        n = max(st["frames"], 1)
        print(f"  camera {k + 1}: {st['frames']} frames, {st['late_frames']} late, {st['cpu_ms_sum'] / n:.1f} ms CPU "
              f"and {st['render_ms_sum'] / n:.1f} ms wall render per frame")
    return 0


def keypoint_error(args) -> int:
    """The shipped keypoint models' error on rendered frames (see the module doc)."""
    from reconstruction.keypoints.detectors import load_model
    from simulator.scene.config import PersonConfig
    from simulator.scene.render import Renderer

    w, h = (int(v) for v in args.sizes.split(",")[0].lower().split("x"))
    cc = CameraConfig(width_px=w, height_px=h, person_model=args.person_model, blur_sigma_px=args.blur, noise_std=args.noise)
    person = PersonSim()
    from simulator.scene.camera import PinholeCamera

    cam = PinholeCamera.from_config(cc)
    renderers = {}
    rng = np.random.default_rng(1)
    frames = []
    t_render = []
    for i in range(args.keypoints):
        seed = i % 6
        if seed not in renderers:
            renderers[seed] = Renderer(cam, cc, PersonConfig(body_seed=seed))
        st = person.state_at(float(rng.uniform(0, person.period_s)))
        rad, up, az = rng.uniform(4, 12), rng.uniform(1.5, 8), rng.uniform(0, 2 * math.pi)
        root = st.root_ned_m
        pos = np.array([root[0] + rad * math.cos(az), root[1] + rad * math.sin(az), -up])
        yaw = math.atan2(root[1] - pos[1], root[0] - pos[0]) + rng.normal(0, 0.1)
        x, y, z, qw = Rotation.from_euler("ZYX", [yaw, 0, 0]).as_quat()
        pitch = -math.atan2(up - 0.9, rad) + rng.normal(0, 0.05)
        T = camera_pose(cc, pos, np.array([qw, x, y, z]), pitch)
        t0 = time.perf_counter()
        fr = renderers[seed].render(T, st.joints_ned_m)
        t_render.append((time.perf_counter() - t0) * 1e3)
        gt = fr.gt
        if gt is None or gt.box_px is None or gt.truncated or gt.visible.sum() < 12:
            continue
        frames.append((fr.image, gt))
    print(f"machine: {_machine()}")
    blur, noise = cc.camera_effects()
    print(f"person model {args.person_model} at {w}x{h}, blur {blur} px, noise {noise}: {len(frames)} usable "
          f"frames of {args.keypoints}; render median {np.median(t_render):.1f} ms (wall)")
    heights = np.array([g.box_px[3] - g.box_px[1] for _, g in frames])
    print(f"box height px: median {np.median(heights):.0f}, range {heights.min():.0f}-{heights.max():.0f}")
    if args.save:
        tiles = []
        for img, g in frames[:8]:
            x0, y0, x1, y1 = (int(v) for v in g.box_px)
            cy, cx, s_ = (y0 + y1) // 2, (x0 + x1) // 2, int(0.65 * max(y1 - y0, x1 - x0)) + 4
            crop = cv2.copyMakeBorder(img, s_, s_, s_, s_, cv2.BORDER_CONSTANT)[cy : cy + 2 * s_, cx : cx + 2 * s_]
            tiles.append(cv2.resize(crop, (192, 192)))
        cv2.imwrite(args.save, np.hstack(tiles))
    from skycap.skeleton import JOINT_GROUPS

    print(f"{'':>18}  per joint group (median %): " + " ".join(f"{g:>8}" for g in JOINT_GROUPS))
    for name in args.models.split(","):
        model = load_model(name)
        errs = []
        per_joint: list[list[float]] = [[] for _ in range(17)]
        for img, g in frames:
            b = g.box_px
            kp = model.predict([img], np.array([[b[0], b[1], b[2] - b[0], b[3] - b[1]]]))[0]
            e = np.linalg.norm(kp[:, :2] - g.uv_px, axis=1) / (b[3] - b[1]) * 100.0
            errs.append(e[g.visible])
            for jj in np.nonzero(g.visible)[0]:
                per_joint[jj].append(e[jj])
        e = np.concatenate(errs)
        per_frame = np.array([np.median(x) for x in errs])
        print(f"{name:>18}: median {np.median(e):5.2f} % of box height, p90 {np.percentile(e, 90):5.1f} %, "
              f"{100 * np.mean(e < 5):4.0f} % of joints under 5 %, frame medians {np.median(per_frame):.2f} %")
        groups = [np.median(sum((per_joint[jj] for jj in js), [])) for js in JOINT_GROUPS.values()]
        print(f"{'':>18}  {'':>27} " + " ".join(f"{v:8.2f}" for v in groups))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
