"""A look at the simulated scene without flying: a camera orbiting the person, written as a video and a
contact sheet, with the ground-truth and simulated keypoints drawn on top.

    skycap sim-preview --out preview/ [--seconds 20] [--radius-m 8] [--altitude-m 4] [--set camera.width_px=960]
    python -m simulator.scene.preview --out preview/

Writes ``preview.mp4`` (OpenCV ``mp4v``), ``contact_sheet.jpg`` (12 frames) and ``config.toml``.
Overlay: ground truth in white (skeleton, box), the simulated detector's keypoints as coloured dots
(green inlier, orange occluded joint, red outlier, nothing for a miss).
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from simulator.scene.camera_node import CameraNode, CameraTruth
from simulator.scene.config import SceneConfig
from simulator.scene.person import PersonSim
from skycap.skeleton import COCO17_LIMBS
from shared_msgs import keys
from simulator.scene.camera_node import SIM_KEYPOINTS2D_GT
from skycap.config import add_config_args, load_config, save_config
from skycap.logsetup import setup_logging
from tqdm import tqdm

log = logging.getLogger(__name__)


def orbit_truth(person: PersonSim, t_s: float, radius_m: float, altitude_m: float, deg_per_s: float) -> CameraTruth:
    """A drone on a circle around the origin, yawed at the person, gimbal pitched at their hips."""
    a = math.radians(deg_per_s * t_s)
    pos = np.array([radius_m * math.cos(a), radius_m * math.sin(a), -altitude_m])
    st = person.state_at(t_s)
    d = st.root_ned_m - pos
    x, y, z, w = Rotation.from_euler("ZYX", [math.atan2(d[1], d[0]), 0.0, 0.0]).as_quat()
    pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))
    q = np.array([w, x, y, z])
    return CameraTruth(int(t_s * 1e9), pos, q, pitch, st.joints_ned_m, pos, q)


def draw_overlay(img: np.ndarray, out: dict) -> np.ndarray:

    img = img.copy()
    gt = out[SIM_KEYPOINTS2D_GT].persons
    if gt:
        uv = np.array(gt[0].keypoints_px).reshape(17, 2)
        conf = np.array(gt[0].confidence)
        for a, b in COCO17_LIMBS:
            if conf[a] > 0 and conf[b] > 0:
                cv2.line(img, tuple(np.round(uv[a]).astype(int)), tuple(np.round(uv[b]).astype(int)), (255, 255, 255), 1, cv2.LINE_AA)
        bx = gt[0].box
        cv2.rectangle(img, (int(bx.x_min_px), int(bx.y_min_px)), (int(bx.x_max_px), int(bx.y_max_px)), (255, 255, 255), 1)
        occluded = conf == 0.5
    else:
        occluded = np.zeros(17, bool)
    sim = out[keys.SIM_KEYPOINTS2D].persons
    if sim:
        uv = np.array(sim[0].keypoints_px).reshape(17, 2)
        conf = np.array(sim[0].confidence)
        for k in range(17):
            if conf[k] <= 0:
                continue
            color = (0, 0, 255) if conf[k] < 0.6 and not occluded[k] else ((0, 160, 255) if occluded[k] else (0, 220, 0))
            cv2.circle(img, tuple(np.round(uv[k]).astype(int)), 2, color, -1, cv2.LINE_AA)
    return img


def run_preview(cfg: SceneConfig, out_dir: Path, seconds: float, radius_m: float, altitude_m: float, deg_per_s: float) -> Path:

    out_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out_dir / "config.toml")
    person = PersonSim(cfg.person)
    state = {"t": 0.0}
    node = CameraNode("preview", cfg, lambda: orbit_truth(person, state["t"], radius_m, altitude_m, deg_per_s), lambda t, m: None)
    W, H = cfg.camera.width_px, cfg.camera.height_px
    fps = cfg.camera.rate_hz
    video = out_dir / "preview.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), fps, (W, H))
    n = int(round(seconds * fps))
    sheet_at = set(np.linspace(0, n - 1, 12).astype(int).tolist())
    sheet = []
    try:

        frames = tqdm(range(n), desc="rendering", unit="frame")
    except ImportError:  # tqdm is optional here
        frames = range(n)
    for i in frames:
        state["t"] = i / fps
        out = node.step()

        img = cv2.imdecode(np.frombuffer(out[keys.CAMERA_IMAGE].data, np.uint8), cv2.IMREAD_COLOR)
        img = draw_overlay(img, out)
        writer.write(img)
        if i in sheet_at:
            cv2.putText(img, f"t={state['t']:.1f}s", (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            sheet.append(img)
    writer.release()
    while len(sheet) % 4:
        sheet.append(np.zeros_like(sheet[0]))
    rows = [np.hstack(sheet[r : r + 4]) for r in range(0, len(sheet), 4)]
    cv2.imwrite(str(out_dir / "contact_sheet.jpg"), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 88])
    log.info("wrote %s (%d frames) and %s", video, n, out_dir / "contact_sheet.jpg")
    return video


def add_args(p: argparse.ArgumentParser) -> None:

    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--radius-m", type=float, default=8.0)
    p.add_argument("--altitude-m", type=float, default=4.0)
    p.add_argument("--deg-per-s", type=float, default=12.0, help="orbit angular speed")
    add_config_args(p)


def run_from_args(args: argparse.Namespace) -> int:

    cfg = load_config(SceneConfig, args.config, args.set).validate()
    run_preview(cfg, args.out, args.seconds, args.radius_m, args.altitude_m, args.deg_per_s)
    return 0


def main(argv: list[str] | None = None) -> int:

    ap = argparse.ArgumentParser(prog="python -m simulator.scene.preview", description=__doc__.splitlines()[0])
    add_args(ap)
    args = ap.parse_args(argv)
    setup_logging("INFO")
    return run_from_args(args)


if __name__ == "__main__":
    raise SystemExit(main())
