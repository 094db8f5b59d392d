"""Writers for reconstructed motion, shared by every reconstruction method.

All take COCO-17 joints ``joints_ned`` (T, 17, 3) in metres, world NED (:mod:`skycap.frames`), with
times ``t_ns`` (T,) int64. Every Y-up file (BVH, TRC) uses one frame conversion, :func:`skycap.frames.ned_to_yup`:
X = north, Y = up, Z = east (right-handed; OpenSim's and the BVH convention of Y up).

* :func:`write_joints_bvh` — a BVH animation (Y-up, **metres**) of the COCO-17
  skeleton of :mod:`reconstruction.body.skeleton17` (root ``pelvis`` = mid-hip, then hips/knees/ankles,
  spine/neck/shoulders/elbows/wrists, head with nose/eyes/ears). Joint rotations come from
  :func:`reconstruction.body.skeleton17.inverse_kinematics`; any BVH reader's forward kinematics gives
  back the COCO-17 positions (joint ``nose`` = COCO nose, ... see :data:`BVH_JOINT_FOR_COCO`) exactly
  when the input is a rigid skeleton (a body-model fit), otherwise with limb lengths fixed to their
  medians (the largest deviation is logged and returned).
  :func:`export_motion` writes it for Blender (:func:`write_blender_bvh`): metres, so that Blender's importer
  at its default scale 1.0 gives the person's real size (a 1.7 m person is 1.7 units tall), and resampled to
  :data:`BLENDER_FPS` = 24 frames per second. Blender's BVH importer with its defaults ("Scale FPS",
  "Update Scene FPS" and "Update Scene Duration" off) keys BVH frame ``i`` at scene frame ``1 + i`` whatever the
  file's ``Frame Time`` says, and a new Blender scene runs at 24 fps: so a 24 fps file plays at real speed with
  the defaults. The scene's end frame (250 in a new scene, 10.4 s) is not changed by the default import; a longer
  motion is all imported (the action spans frames 1..N) but plays past frame 250 only after "Update Scene
  Duration" is ticked or the End frame set (README, Outputs). A BVH cannot carry the scene's frame range.
  It is written in windows of :data:`BVH_WINDOW_FRAMES` frames (memory flat in the motion's length).
* :func:`write_joints_trc` — OpenSim / Pose2Sim marker trajectories (TRC, tab-separated): marker names are the
  COCO-17 joint names, metres, Y-up (:func:`skycap.frames.ned_to_yup`), a constant ``DataRate`` (resampled
  to it when the frame times are not uniform).
* :func:`write_joints_csv` — one row per frame: ``t_s`` then ``<coco_name>_{north,east,down}_m``.
* :func:`write_motion_npz` — ``t_ns``, ``joints_ned`` and any model parameters (``params`` dict of arrays).
* :func:`export_motion` — all of the above plus the rerun recording (:mod:`reconstruction.viz`) into one folder.

The Foxglove MCAP of a processed flight (images, annotations, drones, the skeleton) is
:func:`flightdata.foxglove.export_foxglove`; it takes the result's ``t_ns`` and ``joints_ned``.

Example::

    paths = export_motion("out/", joints_ned, t_ns, params={"pose": pose}, cameras=cams)
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from reconstruction.body import skeleton17 as sk
from skycap.bvh import Skeleton, bvh_header, bvh_motion_lines, write_bvh
from skycap.frames import R_YUP_NED, ned_to_yup
from skycap.skeleton import COCO17_NAMES

__all__ = ["BLENDER_FPS", "BVH_JOINT_FOR_COCO", "BVH_WINDOW_FRAMES", "TRC_UNITS", "bvh_skeleton", "export_motion", "resample_joints",
           "write_blender_bvh", "write_joints_bvh", "write_joints_csv", "write_joints_trc", "write_motion_npz"]

log = logging.getLogger(__name__)

#: COCO-17 index -> BVH joint name in files written by :func:`write_joints_bvh`.
BVH_JOINT_FOR_COCO: tuple[str, ...] = tuple(sk.NODE_NAMES[n] for n in sk.COCO_TO_NODE)
_LEAVES = (3, 6, 11, 14, 16, 17, 18, 19, 20)

#: Frames per second of the BVH written for Blender: a new Blender scene's rate (bpy 5.0 factory settings: 24 fps,
#: frames 1-250), which the importer's defaults keep (see the module docstring).
BLENDER_FPS = 24.0
#: Units of the TRC files (the ``Units`` header field): metres, as Pose2Sim writes them.
TRC_UNITS = "m"


def bvh_skeleton(shape: np.ndarray, units_per_m: float = 1.0) -> tuple[Skeleton, np.ndarray]:
    """BVH skeleton of the 21 nodes (+ a zero-length End Site under each leaf) for a shape (16,).

    Returns (skeleton, node_index (21,) -> skeleton joint index).
    """
    off = sk.rest_offsets(np.asarray(shape, dtype=float)) * units_per_m
    names, parents, offsets, end = [], [], [], []
    idx = np.zeros(21, dtype=int)
    for j in range(21):
        idx[j] = len(names)
        names.append(sk.NODE_NAMES[j])
        parents.append(-1 if sk.PARENTS[j] < 0 else int(idx[sk.PARENTS[j]]))
        offsets.append(off[j])
        end.append(False)
        if j in _LEAVES:
            names.append(f"{sk.NODE_NAMES[j]}_End")
            parents.append(int(idx[j]))
            offsets.append(np.zeros(3))
            end.append(True)
    # children must follow parents: nodes are already topologically ordered
    skel = Skeleton(names, np.array(parents), np.array(offsets), [[] for _ in names], np.array(end))
    return skel, idx


def write_joints_bvh(
    path: str | Path, joints_ned: np.ndarray, frame_time_s: float, shape: np.ndarray | None = None,
    units_per_m: float = 1.0,
) -> tuple[Path, float]:
    """Write joints (T, 17, 3) NED metres as a BVH (Y-up; metres, or ``units_per_m`` units per metre, e.g. 100 for
    centimetres). ``shape`` (16,) is the skeleton's (from the body-model fit); if None it is estimated from the joints.

    Returns (path, max_error_m): the largest distance between the BVH's COCO joints and the input.
    """
    shape, R_root, R_loc, transl, err = _fit_skeleton(joints_ned, shape)
    p = _write_skeleton_bvh(path, shape, R_root, R_loc, transl, frame_time_s, units_per_m)
    return p, err


def _fit_skeleton(joints_ned: np.ndarray, shape: np.ndarray | None):
    """(shape, R_root, R_loc, transl, max_error_m): the rigid skeleton's inverse kinematics of the joints."""
    joints_ned = np.asarray(joints_ned, dtype=float)
    if joints_ned.ndim != 3 or joints_ned.shape[1:] != (17, 3):
        raise ValueError(f"joints_ned must be (T, 17, 3), got {joints_ned.shape}")
    shape = sk.estimate_shape(joints_ned) if shape is None else np.asarray(shape, dtype=float)
    R_root, R_loc, transl = sk.inverse_kinematics(joints_ned, shape)
    back = sk.forward_kinematics_np(R_root, R_loc, transl, shape)[:, sk.COCO_TO_NODE]
    err = float(np.max(np.linalg.norm(back - joints_ned, axis=-1)))
    if err > 1e-3:
        log.warning("BVH export: joints are not a rigid skeleton; largest joint deviation %.1f mm", err * 1e3)
    return shape, np.asarray(R_root), np.asarray(R_loc), np.asarray(transl), err


_BVH_PRECISION = 5


def _skeleton_channels(skel: Skeleton, idx: np.ndarray, R_root, R_loc, transl, units_per_m: float):
    """(root position (T, 3) Y-up, local rotations (T, J, 3, 3)) of the BVH skeleton ``skel`` from the fit."""
    T = len(transl)
    R_all = np.broadcast_to(np.eye(3), (T, skel.num_joints, 3, 3)).copy()
    R_all[:, idx[0]] = R_YUP_NED @ R_root
    for slot, j in enumerate(sk.POSE_JOINTS):
        R_all[:, idx[j]] = R_loc[:, slot]
    return ned_to_yup(transl) * units_per_m, R_all


def _write_skeleton_bvh(path, shape, R_root, R_loc, transl, frame_time_s: float, units_per_m: float) -> Path:
    skel, idx = bvh_skeleton(shape, units_per_m)
    root, R_all = _skeleton_channels(skel, idx, R_root, R_loc, transl, units_per_m)
    return write_bvh(path, skel, frame_time_s, root, R_all, rotation_order="ZYX", precision=_BVH_PRECISION)


def resample_joints(joints_ned: np.ndarray, t_ns: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Joints (T, 17, 3) at times ``t_ns`` (T,) -> at the uniform times ``t_ns[0] + k / rate_hz`` (k = 0, 1, ... up to
    the last time), linearly interpolated. Returns (t_ns (K,) int64, joints (K, 17, 3))."""
    joints_ned = np.asarray(joints_ned, dtype=float)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    if len(t_ns) != len(joints_ned):
        raise ValueError(f"t_ns has {len(t_ns)} times for {len(joints_ned)} frames of joints")
    if len(t_ns) < 2:
        return t_ns.copy(), joints_ned.copy()
    if np.any(np.diff(t_ns) <= 0):
        raise ValueError("t_ns must increase strictly to resample the joints")
    t_rel = (t_ns - t_ns[0]) * 1e-9
    n = int(np.floor(t_rel[-1] * rate_hz + 1e-9)) + 1
    t_new = np.arange(n) / rate_hz
    i = np.clip(np.searchsorted(t_rel, t_new, side="right") - 1, 0, len(t_rel) - 2)
    w = ((t_new - t_rel[i]) / (t_rel[i + 1] - t_rel[i]))[:, None, None]
    out = (1.0 - w) * joints_ned[i] + w * joints_ned[i + 1]
    return t_ns[0] + np.round(t_new * 1e9).astype(np.int64), out


#: BVH frames that :func:`write_blender_bvh` computes and writes at a time (~43 s of motion at 24 fps: a few MB);
#: its memory does not grow with the motion's length beyond the input and per-frame scalars
BVH_WINDOW_FRAMES = 1024


def write_blender_bvh(
    path: str | Path, joints_ned: np.ndarray, t_ns: np.ndarray, shape: np.ndarray | None = None,
    window_frames: int = BVH_WINDOW_FRAMES,
) -> tuple[Path, float]:
    """The BVH for Blender: metres, resampled to :data:`BLENDER_FPS` (module docstring: Blender's default import
    then gives the real size and the real speed). BVH frame ``i`` (Blender frame ``1 + i``) is the motion at
    ``t_ns[0] + i / BLENDER_FPS`` seconds.

    Resampled on the skeleton, not on the joints: the rigid skeleton is fitted at the recorded frames, then its joint
    rotations are slerped and the root translation interpolated linearly, so that every BVH frame is the same rigid
    skeleton (interpolating joint positions between frames 0.3 s apart would shorten the limbs by up to decimetres)
    and the BVH equals the fit at the recorded times. Returns (path, max_error_m) as :func:`write_joints_bvh`: the
    fit's largest joint distance from the input at the recorded frames.

    Streamed: ``window_frames`` BVH frames at a time are fitted (the recorded frames around them), resampled and
    appended to the file, so a long motion needs no more memory than a short one (the skeleton's ``shape``, when not
    given, is still estimated from all frames: it must be one for the whole file). Every window computes exactly what
    one pass over the whole motion would (each BVH frame depends only on the two recorded frames around it).
    """
    joints_ned = np.asarray(joints_ned, dtype=float)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if len(t_ns) != len(joints_ned):
        raise ValueError(f"t_ns has {len(t_ns)} times for {len(joints_ned)} frames of joints")
    if joints_ned.ndim != 3 or joints_ned.shape[1:] != (17, 3):
        raise ValueError(f"joints_ned must be (T, 17, 3), got {joints_ned.shape}")
    if window_frames < 1:
        raise ValueError(f"window_frames must be >= 1, got {window_frames}")
    # frames without every joint, or not later than the frame before, are left out (the motion is interpolated
    # across them) so that one bad frame does not cost the file
    keep = np.all(np.isfinite(joints_ned), axis=(1, 2))
    t_max = np.maximum.accumulate(np.where(keep, t_ns, np.iinfo(np.int64).min))
    keep[1:] &= t_ns[1:] > t_max[:-1]
    if not keep.any():
        raise ValueError("no frame with every joint finite: nothing to write as a BVH")
    if not keep.all():
        log.warning("BVH export: left out %d of %d frames (a joint not finite, or a time not after the one before)",
                    int((~keep).sum()), len(keep))
    t_first = int(t_ns[0])
    kept = np.flatnonzero(keep)
    t_s = (t_ns[kept] - t_first) * 1e-9
    shape = sk.estimate_shape(joints_ned[kept]) if shape is None else np.asarray(shape, dtype=float)
    skel, idx = bvh_skeleton(shape, 1.0)
    n_out = int(np.floor(t_s[-1] * BLENDER_FPS + 1e-9)) + 1 if len(kept) > 1 else 1
    path = Path(path)
    err = 0.0
    with open(path, "w") as f:
        f.write(bvh_header(skel, 1.0 / BLENDER_FPS, n_out, rotation_order="ZYX", precision=_BVH_PRECISION))
        for a in range(0, n_out, window_frames):
            b = min(n_out, a + window_frames)
            if len(kept) > 1:
                t_new = np.clip(np.arange(a, b) / BLENDER_FPS, t_s[0], t_s[-1])  # held before the first kept frame
                # the recorded frames bracketing these times, one more on each side: each interval is slerped as in
                # one pass over the whole motion (a time on the last frame of a part would otherwise be reached from
                # the interval before it)
                lo = max(0, int(np.searchsorted(t_s, t_new[0], side="right")) - 2)
                hi = min(len(t_s), int(np.searchsorted(t_s, t_new[-1], side="left")) + 2)
            else:
                lo, hi = 0, 1
            R_root, R_loc, transl, e = _fit_frames(joints_ned[kept[lo:hi]], shape)
            err = max(err, e)
            if len(kept) > 1:
                ts = t_s[lo:hi]
                R_root = Slerp(ts, Rotation.from_matrix(R_root))(t_new).as_matrix()
                R_loc = np.stack([Slerp(ts, Rotation.from_matrix(R_loc[:, j]))(t_new).as_matrix()
                                  for j in range(R_loc.shape[1])], axis=1)
                transl = np.stack([np.interp(t_new, ts, transl[:, k]) for k in range(3)], axis=-1)
            root, R_all = _skeleton_channels(skel, idx, R_root, R_loc, transl, 1.0)
            f.write(bvh_motion_lines(skel, root, R_all, rotation_order="ZYX", precision=_BVH_PRECISION))
    if err > 1e-3:
        log.warning("BVH export: joints are not a rigid skeleton; largest joint deviation %.1f mm", err * 1e3)
    return path, err


def _fit_frames(joints_ned: np.ndarray, shape: np.ndarray):
    """(R_root, R_loc, transl, max_error_m) of the rigid skeleton ``shape`` on these frames (inverse kinematics)."""
    R_root, R_loc, transl = sk.inverse_kinematics(joints_ned, shape)
    back = sk.forward_kinematics_np(R_root, R_loc, transl, shape)[:, sk.COCO_TO_NODE]
    err = float(np.max(np.linalg.norm(back - joints_ned, axis=-1)))
    return np.asarray(R_root), np.asarray(R_loc), np.asarray(transl), err


def write_joints_trc(path: str | Path, joints_ned: np.ndarray, t_ns: np.ndarray, rate_hz: float | None = None) -> Path:
    """OpenSim TRC marker trajectories: one marker per COCO-17 joint (named as :data:`skycap.skeleton.COCO17_NAMES`),
    in :data:`TRC_UNITS` (metres), Y-up by :func:`skycap.frames.ned_to_yup` (X north, Y up, Z east).

    ``rate_hz`` (None: the median frame rate of ``t_ns``, rounded to 0.001 Hz) is the file's ``DataRate`` and
    ``CameraRate``; frames not on that grid are resampled onto it (:func:`resample_joints`), so ``Time`` is
    ``(Frame# - 1) / DataRate`` from the first frame. Joints that are NaN are written as empty fields (a gap).
    """
    path = Path(path)
    joints_ned = np.asarray(joints_ned, dtype=float)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if joints_ned.ndim != 3 or joints_ned.shape[1:] != (17, 3) or len(joints_ned) != len(t_ns) or not len(t_ns):
        raise ValueError(f"write_joints_trc needs joints (T, 17, 3) with T = len(t_ns) >= 1, got {joints_ned.shape} "
                         f"and {len(t_ns)} times")
    if rate_hz is None:
        rate_hz = round(1e9 / float(np.median(np.diff(t_ns))), 3) if len(t_ns) > 1 else 30.0
    t_rel_s = (t_ns - t_ns[0]) * 1e-9
    if len(t_ns) > 1 and np.abs(t_rel_s - np.arange(len(t_ns)) / rate_hz).max() > 1e-6:
        t_ns, joints_ned = resample_joints(joints_ned, t_ns, rate_hz)
    P = ned_to_yup(joints_ned)  # (T, 17, 3) X north, Y up, Z east, metres
    T, M = len(P), len(COCO17_NAMES)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate_hz:g}\t{rate_hz:g}\t{T}\t{M}\t{TRC_UNITS}\t{rate_hz:g}\t1\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in COCO17_NAMES).rstrip("\t"),
        "\t\t" + "\t".join(f"X{m + 1}\tY{m + 1}\tZ{m + 1}" for m in range(M)),
        "",
    ]
    for k in range(T):
        vals = "\t".join("" if not np.isfinite(v) else f"{v:.6f}" for v in P[k].ravel())
        lines.append(f"{k + 1}\t{k / rate_hz:.6f}\t{vals}")
    path.write_text("\n".join(lines) + "\n")
    return path


def write_joints_csv(path: str | Path, joints_ned: np.ndarray, t_ns: np.ndarray) -> Path:
    """CSV: ``t_s`` and ``<coco>_north_m, _east_m, _down_m`` per joint, one row per frame."""
    path = Path(path)
    t_s = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9 if len(t_ns) else np.zeros(0)
    cols = ["t_s"] + [f"{n}_{a}" for n in COCO17_NAMES for a in ("north_m", "east_m", "down_m")]
    data = np.concatenate([t_s[:, None], np.asarray(joints_ned).reshape(len(t_s), -1)], axis=1)
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.6f")
    return path


def write_motion_npz(path: str | Path, joints_ned: np.ndarray, t_ns: np.ndarray, params: dict | None = None, **extra) -> Path:
    """``.npz`` with ``t_ns`` (T,), ``joints_ned`` (T, 17, 3), ``joint_names`` and ``params`` keys prefixed ``param_``."""
    path = Path(path)
    arrays = {"t_ns": np.asarray(t_ns, dtype=np.int64), "joints_ned": np.asarray(joints_ned), "joint_names": np.array(COCO17_NAMES)}
    for k, v in (params or {}).items():
        arrays[f"param_{k}"] = np.asarray(v)
    for k, v in extra.items():
        arrays[k] = np.asarray(v)
    np.savez_compressed(path, **arrays)
    return path


def export_motion(
    out_dir: str | Path,
    joints_ned: np.ndarray,
    t_ns: np.ndarray,
    params: dict | None = None,
    shape: np.ndarray | None = None,
    cameras: list | None = None,
    stem: str = "motion",
    rrd: bool = True,
    capture=None,
) -> dict[str, Path]:
    """Write ``<stem>.bvh`` (for Blender: :func:`write_blender_bvh`), ``<stem>.trc`` (OpenSim), ``<stem>.npz``,
    ``<stem>.csv`` and ``<stem>.rrd`` into ``out_dir``.

    ``cameras``: optional list of dicts ``{"name", "t_ns" (F,), "T_world_cam" (F,4,4), "K" (3,3),
    "width_px", "height_px"}`` drawn in the recording; ``capture``: optional
    :class:`reconstruction.capture.Capture` whose 2D keypoints are drawn.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    paths: dict[str, Path] = {}
    paths["bvh"], err = write_blender_bvh(out / f"{stem}.bvh", joints_ned, t_ns, shape)
    paths["trc"] = write_joints_trc(out / f"{stem}.trc", joints_ned, t_ns)
    paths["npz"] = write_motion_npz(out / f"{stem}.npz", joints_ned, t_ns, params, bvh_max_error_m=err,
                                    bvh_fps=BLENDER_FPS)
    paths["csv"] = write_joints_csv(out / f"{stem}.csv", joints_ned, t_ns)
    if rrd:
        from reconstruction.viz import write_rrd

        paths["rrd"] = write_rrd(out / f"{stem}.rrd", joints_ned, t_ns, cameras=cameras, capture=capture)
    return paths
