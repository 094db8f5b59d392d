"""Writers for reconstructed motion, shared by every reconstruction method.

All take COCO-17 joints ``joints_ned`` (T, 17, 3) in metres, world NED (:mod:`skycap.frames`), with
times ``t_ns`` (T,) int64:

* :func:`write_joints_bvh` — a BVH animation (Y-up, centimetres, like the CMU input) of the COCO-17
  skeleton of :mod:`reconstruction.body.skeleton17` (root ``pelvis`` = mid-hip, then hips/knees/ankles,
  spine/neck/shoulders/elbows/wrists, head with nose/eyes/ears). Joint rotations come from
  :func:`reconstruction.body.skeleton17.inverse_kinematics`; any BVH reader's forward kinematics gives
  back the COCO-17 positions (joint ``nose`` = COCO nose, ... see :data:`BVH_JOINT_FOR_COCO`) exactly
  when the input is a rigid skeleton (a body-model fit), otherwise with limb lengths fixed to their
  medians (the largest deviation is logged and returned).
* :func:`write_joints_csv` — one row per frame: ``t_s`` then ``<coco_name>_{north,east,down}_m``.
* :func:`write_motion_npz` — ``t_ns``, ``joints_ned`` and any model parameters (``params`` dict of arrays).
* :func:`export_motion` — all of the above plus the rerun recording (:mod:`reconstruction.viz`) into one folder.

Example::

    paths = export_motion("out/", joints_ned, t_ns, params={"pose": pose}, cameras=cams)
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from reconstruction.body import skeleton17 as sk
from skycap.bvh import Skeleton, write_bvh
from skycap.frames import R_YUP_NED, ned_to_yup
from skycap.skeleton import COCO17_NAMES

__all__ = ["BVH_JOINT_FOR_COCO", "write_joints_bvh", "write_joints_csv", "write_motion_npz", "export_motion", "bvh_skeleton"]

log = logging.getLogger(__name__)

#: COCO-17 index -> BVH joint name in files written by :func:`write_joints_bvh`.
BVH_JOINT_FOR_COCO: tuple[str, ...] = tuple(sk.NODE_NAMES[n] for n in sk.COCO_TO_NODE)
_LEAVES = (3, 6, 11, 14, 16, 17, 18, 19, 20)


def bvh_skeleton(shape: np.ndarray, units_per_m: float = 100.0) -> tuple[Skeleton, np.ndarray]:
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
    path: str | Path, joints_ned: np.ndarray, frame_time_s: float, shape: np.ndarray | None = None
) -> tuple[Path, float]:
    """Write joints (T, 17, 3) NED metres as a BVH (Y-up, cm). ``shape`` (16,) is the skeleton's
    (from the body-model fit); if None it is estimated from the joints.

    Returns (path, max_error_m): the largest distance between the BVH's COCO joints and the input.
    """
    joints_ned = np.asarray(joints_ned, dtype=float)
    if joints_ned.ndim != 3 or joints_ned.shape[1:] != (17, 3):
        raise ValueError(f"joints_ned must be (T, 17, 3), got {joints_ned.shape}")
    shape = sk.estimate_shape(joints_ned) if shape is None else np.asarray(shape, dtype=float)
    R_root, R_loc, transl = sk.inverse_kinematics(joints_ned, shape)
    back = sk.forward_kinematics_np(R_root, R_loc, transl, shape)[:, sk.COCO_TO_NODE]
    err = float(np.max(np.linalg.norm(back - joints_ned, axis=-1)))
    if err > 1e-3:
        log.warning("BVH export: joints are not a rigid skeleton; largest joint deviation %.1f mm", err * 1e3)
    skel, idx = bvh_skeleton(shape)
    T = joints_ned.shape[0]
    R_all = np.broadcast_to(np.eye(3), (T, skel.num_joints, 3, 3)).copy()
    R_all[:, idx[0]] = R_YUP_NED @ R_root
    for slot, j in enumerate(sk.POSE_JOINTS):
        R_all[:, idx[j]] = R_loc[:, slot]
    root = ned_to_yup(transl) * 100.0
    p = write_bvh(path, skel, frame_time_s, root, R_all, rotation_order="ZYX", precision=5)
    return p, err


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
    """Write ``<stem>.bvh``, ``<stem>.npz``, ``<stem>.csv`` and ``<stem>.rrd`` into ``out_dir``.

    ``cameras``: optional list of dicts ``{"name", "t_ns" (F,), "T_world_cam" (F,4,4), "K" (3,3),
    "width_px", "height_px"}`` drawn in the recording; ``capture``: optional
    :class:`reconstruction.capture.Capture` whose 2D keypoints are drawn.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_ns = np.asarray(t_ns, dtype=np.int64)
    dt = float(np.median(np.diff(t_ns))) * 1e-9 if len(t_ns) > 1 else 1 / 30
    paths: dict[str, Path] = {}
    paths["bvh"], err = write_joints_bvh(out / f"{stem}.bvh", joints_ned, dt, shape)
    paths["npz"] = write_motion_npz(out / f"{stem}.npz", joints_ned, t_ns, params, bvh_max_error_m=err)
    paths["csv"] = write_joints_csv(out / f"{stem}.csv", joints_ned, t_ns)
    if rrd:
        from reconstruction.viz import write_rrd

        paths["rrd"] = write_rrd(out / f"{stem}.rrd", joints_ned, t_ns, cameras=cameras, capture=capture)
    return paths
