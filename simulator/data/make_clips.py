"""Regenerate the simulator's committed motion clips (``simulator/data/motions/*.npz``) from CMU BVH files.

    python simulator/data/make_clips.py --cmu ../shared/data/mocap/cmu

Why ``.npz`` of COCO-17 joints (and not trimmed BVH): the simulated person is rendered from its 17
COCO joints alone (:mod:`simulator.scene.body`), so that anything carrying COCO-17 joints (the
``SimTruth`` message included) can be rendered; a clip is then ~30 kB instead of ~300 kB of BVH with
142 rig joints, loads in a millisecond (no forward kinematics at run time) and does not tie the
simulator to the CC_Base rig.

Each clip is stored in the person's *canonical local frame*: NED axes rotated so that the person faces
north (+x) at the first frame, the hip midpoint horizontally at the origin at the first frame, the floor
at down = 0 as recorded. The first frame of every CMU file (a prepended T-pose) is never used; the
60 fps data is downsampled to 30 fps. Fields of each file:

* ``joints_ned_m`` (T, 17, 3) float32: COCO-17 joints in the canonical frame.
* ``fps`` (): frame rate (30).
* ``mode`` (): "loop" (walk: played cyclically, root translation removed, see below), "once"
  (a motion played once at a stop), "pingpong" (standing idle: played forwards then backwards).
* ``speed_m_s`` (): for a walk loop, the forward speed the root translation was removed at
  (the person must move at this speed along its path for the feet not to slide); 0 otherwise.
* ``source`` (): CMU subject/trial and frame range, for the credit and for regeneration.

Walk loop: within the chosen trial the best-matching pair of frames (a, b) about two gait cycles apart
is found (pose distance after removing the root), the straight-line root translation between them is
removed (leaving the natural sway and bob) and the residual closing error is spread linearly over the
loop so that it joins exactly.

Credit: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created with
funding from NSF EIA-0196217."
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from skycap.bvh import read_bvh
from skycap.skeleton import mocap_to_coco17

OUT_DIR = Path(__file__).resolve().parent / "motions"
FPS_OUT = 30.0

#: name -> (trial file, mode, start_s, stop_s) with times from the first non-T-pose frame.
CLIPS: dict[str, tuple[str, str, float, float]] = {
    "walk": ("002/002_01.bvh", "loop", 0.0, 0.0),  # loop found automatically
    "jump": ("002/002_04.bvh", "once", 0.0, 3.9),  # jump, balance
    "punch": ("002/002_05.bvh", "once", 0.4, 4.6),  # punch/strike
    "pickup": ("002/002_06.bvh", "once", 0.3, 2.5),  # bend over, scoop up, rise
    "stand": ("002/002_05.bvh", "pingpong", 14.2, 15.4),  # quiet standing at the end of the trial
}


def _facing_yaw_rad(joints: np.ndarray) -> float:
    """Yaw (NED, 0 = north, + = east) the person faces: perpendicular to the hips, horizontal. joints (17,3)."""
    left = joints[11] - joints[12]  # right hip -> left hip: points to the person's left
    fwd = np.cross(left, np.array([0.0, 0.0, -1.0]))  # left x up = forward
    return float(np.arctan2(fwd[1], fwd[0]))


def _rot_z(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _canonical(joints: np.ndarray, yaw_rad: float, origin_ne: np.ndarray) -> np.ndarray:
    """Translate the horizontal ``origin_ne`` to 0 and rotate by -yaw so that yaw points north. (T,17,3)."""
    j = joints.copy()
    j[..., :2] -= origin_ne
    return j @ _rot_z(-yaw_rad).T


def _find_walk_loop(joints: np.ndarray, fps: float, min_s: float = 1.8, max_s: float = 2.7) -> tuple[int, int]:
    """Frames (a, b), b - a even, about two gait cycles apart with the most similar root-relative poses."""
    root = 0.5 * (joints[:, 11] + joints[:, 12])
    rel = joints - root[:, None, :]
    T = len(joints)
    best = (np.inf, 0, T - 1)
    for a in range(0, T):
        for b in range(a + int(min_s * fps), min(T, a + int(max_s * fps) + 1)):
            if (b - a) % 2:
                continue
            d = np.mean(np.linalg.norm(rel[a] - rel[b], axis=-1))
            # small preference for longer loops (more natural variety)
            score = d - 0.002 * (b - a) / fps
            if score < best[0]:
                best = (score, a, b)
    return best[1], best[2]


def make_walk(joints: np.ndarray, fps: float, source: str) -> dict:
    a, b = _find_walk_loop(joints, fps)
    seg = joints[a : b + 1]
    root = 0.5 * (seg[:, 11] + seg[:, 12])
    disp = root[-1, :2] - root[0, :2]
    yaw = float(np.arctan2(disp[1], disp[0]))
    seg = _canonical(seg, yaw, root[0, :2])
    n = len(seg) - 1
    dur = n / fps
    speed = float(np.linalg.norm(disp) / dur)
    tt = np.arange(n + 1) / fps
    seg[..., 0] -= (speed * tt)[:, None]  # remove the straight-line forward translation
    close_err = seg[-1] - seg[0]  # (17, 3): residual mismatch at the seam
    seg = seg - (np.arange(n + 1) / n)[:, None, None] * close_err[None]
    seg = seg[:-1]  # last frame == first frame
    step = int(round(fps / FPS_OUT))
    if n % step:
        raise RuntimeError("walk loop length must be a multiple of the downsampling step")
    return dict(
        joints_ned_m=seg[::step].astype(np.float32),
        fps=np.float64(fps / step),
        mode="loop",
        speed_m_s=np.float64(speed),
        source=f"CMU {source} frames {a + 1}-{b} (60 fps, frame 0 = T-pose excluded)",
    )


def make_segment(joints: np.ndarray, fps: float, mode: str, start_s: float, stop_s: float, source: str) -> dict:
    i0, i1 = int(round(start_s * fps)), int(round(stop_s * fps))
    seg = joints[i0:i1]
    if len(seg) < 4:
        raise RuntimeError(f"{source}: window {start_s}-{stop_s} s is empty")
    yaw0 = _facing_yaw_rad(np.mean(seg[:6], axis=0))
    root0 = 0.5 * (seg[0, 11] + seg[0, 12])
    seg = _canonical(seg, yaw0, root0[:2])
    step = int(round(fps / FPS_OUT))
    return dict(
        joints_ned_m=seg[::step].astype(np.float32),
        fps=np.float64(fps / step),
        mode=mode,
        speed_m_s=np.float64(0.0),
        source=f"CMU {source} frames {i0 + 1}-{i1} (60 fps, frame 0 = T-pose excluded)",
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=Path(__file__).resolve().parents[3] / "shared/data/mocap/cmu")
    ap.add_argument("--out", type=Path, default=OUT_DIR)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cache: dict[str, tuple[np.ndarray, float]] = {}
    for name, (rel, mode, t0, t1) in CLIPS.items():
        if rel not in cache:
            motion = read_bvh(args.cmu / rel)
            joints = mocap_to_coco17(motion)[1:]  # drop the prepended T-pose frame
            cache[rel] = (joints, float(round(motion.fps)))  # 0.016667 s frames are 60 fps
        joints, fps = cache[rel]
        src = rel.split("/")[-1].removesuffix(".bvh")
        clip = make_walk(joints, fps, src) if mode == "loop" else make_segment(joints, fps, mode, t0, t1, src)
        path = args.out / f"{name}.npz"
        np.savez_compressed(path, **clip)
        T = clip["joints_ned_m"].shape[0]
        print(f"{name:8s} {mode:8s} {T:4d} frames {T / clip['fps']:.2f} s speed {float(clip['speed_m_s']):.2f} m/s "
              f"{path.stat().st_size / 1024:.1f} kB  <- {clip['source']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
