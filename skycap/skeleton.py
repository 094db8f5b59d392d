"""The body skeleton every part of skycap speaks: COCO-17 keypoints, their limbs, the scored joints,
and the mapping from motion-capture rigs (the CMU "CC_Base" BVH rig) to COCO-17 in the world frame.

COCO-17 order (index: name)::

    0 nose, 1 left_eye, 2 right_eye, 3 left_ear, 4 right_ear, 5 left_shoulder, 6 right_shoulder,
    7 left_elbow, 8 right_elbow, 9 left_wrist, 10 right_wrist, 11 left_hip, 12 right_hip,
    13 left_knee, 14 right_knee, 15 left_ankle, 16 right_ankle

"left" is the person's own left. BVH joint -> COCO-17 for the CC_Base rig (:data:`CC_BASE_TO_COCO17`):
shoulders = ``*_Upperarm``, elbows = ``*_Forearm``, wrists = ``*_Hand``, hips = ``*_Thigh``,
knees = ``*_Calf``, ankles = ``*_Foot``, eyes = ``*_Eye``; nose and ears have no joint and are placed
at fixed offsets in the head's frame (nose 2 cm ahead of and 4 cm below the eye midpoint, ears 7.5 cm
to each side of it, 8 cm behind and 1 cm below). Scored joints (:data:`SCORED_JOINTS`): shoulders,
elbows, wrists, hips, knees, ankles (12) and the head (nose).
"""

from __future__ import annotations

import numpy as np

from skycap.bvh import BvhMotion, forward_kinematics
from skycap.frames import yup_to_ned

COCO17_NAMES: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
COCO17 = {n: i for i, n in enumerate(COCO17_NAMES)}

#: Limbs (bones) as COCO-17 index pairs, the usual COCO drawing skeleton.
COCO17_LIMBS: tuple[tuple[int, int], ...] = (
    (5, 7), (7, 9), (6, 8), (8, 10),          # arms
    (11, 13), (13, 15), (12, 14), (14, 16),   # legs
    (5, 6), (11, 12), (5, 11), (6, 12),       # torso
    (0, 1), (0, 2), (1, 3), (2, 4),           # face
)  # fmt: skip

#: Left <-> right swap permutation (for flip augmentation and swap detection).
COCO17_FLIP: tuple[int, ...] = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)

#: Joints scored in evaluation (COCO-17 indices): 12 limb joints + head (nose).
SCORED_JOINTS: tuple[int, ...] = (5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 0)

#: Scored-joint groups as in AirCap Table 1 / DroCap (pairs averaged left and right).
JOINT_GROUPS: dict[str, tuple[int, ...]] = {
    "shoulder": (5, 6), "elbow": (7, 8), "wrist": (9, 10),
    "hip": (11, 12), "knee": (13, 14), "ankle": (15, 16), "head": (0,),
}  # fmt: skip

CC_BASE_TO_COCO17: dict[int, str] = {
    1: "CC_Base_L_Eye", 2: "CC_Base_R_Eye",
    5: "CC_Base_L_Upperarm", 6: "CC_Base_R_Upperarm",
    7: "CC_Base_L_Forearm", 8: "CC_Base_R_Forearm",
    9: "CC_Base_L_Hand", 10: "CC_Base_R_Hand",
    11: "CC_Base_L_Thigh", 12: "CC_Base_R_Thigh",
    13: "CC_Base_L_Calf", 14: "CC_Base_R_Calf",
    15: "CC_Base_L_Foot", 16: "CC_Base_R_Foot",
}  # fmt: skip


def mocap_to_coco17(motion: BvhMotion, units_to_m: float = 0.01) -> np.ndarray:
    """COCO-17 joint positions (T, 17, 3) in metres, world NED, from a CC_Base-rig BVH motion.

    The BVH world is Y-up (CMU files after their root rotation); it is converted with
    :func:`skycap.frames.yup_to_ned`. The person's ground contact stays at about down = 0 when the
    file's floor is y = 0.
    """
    sk = motion.skeleton
    R_loc, t_loc = motion.local_transforms()
    _, pg = forward_kinematics(sk.parents, R_loc, t_loc)
    out = np.zeros((motion.num_frames, 17, 3))
    for k, name in CC_BASE_TO_COCO17.items():
        out[:, k] = pg[:, sk.index(name)]
    # Face points: fixed offsets in a head frame built from the animated eyes and neck each frame.
    i = sk.index
    eye_l, eye_r = pg[:, i("CC_Base_L_Eye")], pg[:, i("CC_Base_R_Eye")]
    head, neck = pg[:, i("CC_Base_Head")], pg[:, i("CC_Base_NeckTwist01")]
    eye_mid = 0.5 * (eye_l + eye_r)
    left = _unit(eye_l - eye_r)
    up = head - neck
    up = _unit(up - left * np.sum(up * left, -1, keepdims=True))
    fwd = np.cross(left, up)
    fwd *= np.sign(np.sum((eye_mid - head) * fwd, -1, keepdims=True) + 1e-12)
    cm = 1.0 / (units_to_m * 100.0)  # file units per centimetre
    out[:, 0] = eye_mid + cm * (2.0 * fwd - 4.0 * up)
    out[:, 3] = eye_mid + cm * (7.5 * left - 8.0 * fwd - 1.0 * up)
    out[:, 4] = eye_mid + cm * (-7.5 * left - 8.0 * fwd - 1.0 * up)
    return yup_to_ned(out * units_to_m)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def limb_lengths(joints: np.ndarray, limbs=COCO17_LIMBS) -> np.ndarray:
    """Lengths (..., L) of the limbs of joint arrays (..., 17, 3)."""
    a = np.array([l[0] for l in limbs])
    b = np.array([l[1] for l in limbs])
    return np.linalg.norm(joints[..., a, :] - joints[..., b, :], axis=-1)


# ------------------------------------------------------------------------------------------------------------
# any CMU-style BVH rig -> COCO-17 (the simulated person's --motion FILE.bvh)

#: Known BVH rigs: COCO-17 index -> joint name for the 12 limb joints, plus the head and neck joints (and the eyes
#: where the rig has them). "cc_base": the CMU data retargeted onto the CC_Base rig (``../shared/data/mocap/cmu``);
#: "cmu": the classic CMU BVH conversions (cgspeed / Bandai-Namco style names: ``LeftUpLeg``, ``LeftLeg``,
#: ``LeftFoot``, ``LeftArm``, ``LeftForeArm``, ``LeftHand``, ``Neck``/``Neck1``, ``Head``). A rig's joint names
#: may carry a namespace prefix (``mixamorig:LeftArm``): it is ignored.
BVH_RIGS: dict[str, dict] = {
    "cc_base": {"limbs": {k: v for k, v in CC_BASE_TO_COCO17.items() if k >= 5},
                "head": "CC_Base_Head", "neck": ("CC_Base_NeckTwist01",), "eyes": ("CC_Base_L_Eye", "CC_Base_R_Eye")},
    "cmu": {"limbs": {5: "LeftArm", 6: "RightArm", 7: "LeftForeArm", 8: "RightForeArm", 9: "LeftHand", 10: "RightHand",
                      11: "LeftUpLeg", 12: "RightUpLeg", 13: "LeftLeg", 14: "RightLeg", 15: "LeftFoot", 16: "RightFoot"},
            "head": "Head", "neck": ("Neck1", "Neck"), "eyes": None},
}  # fmt: skip


def _strip_ns(name: str) -> str:
    return name.rsplit(":", 1)[-1]


def detect_bvh_rig(names: list[str]) -> tuple[str | None, dict[str, list[str]]]:
    """(the first rig of :data:`BVH_RIGS` whose joints ``names`` all has, or None; per rig the joints it lacks)."""
    have = {_strip_ns(n) for n in names}
    missing = {}
    for rig, spec in BVH_RIGS.items():
        need = list(spec["limbs"].values()) + [spec["head"]] + list(spec["eyes"] or ())
        lack = [n for n in need if n not in have]
        if not any(n in have for n in spec["neck"]):
            lack.append(" or ".join(spec["neck"]))
        missing[rig] = lack
        if not lack:
            return rig, missing
    return None, missing


def bvh_rig_to_coco17(world_positions: np.ndarray, names: list[str], rig: str, cm_units: float) -> np.ndarray:
    """COCO-17 joints (T, 17, 3) in the file's own axes and units from FK world positions (T, J, 3) of a ``rig`` of
    :data:`BVH_RIGS`. ``cm_units``: file units per centimetre (for the face offsets). Face points as in
    :func:`mocap_to_coco17` from the eyes; a rig without eyes gets them 6 cm above and 8 cm ahead of its head joint
    (ahead = perpendicular to the shoulders and the neck-to-head direction)."""
    spec = BVH_RIGS[rig]
    idx = {_strip_ns(n): i for i, n in enumerate(names)}
    pg = world_positions
    out = np.zeros((pg.shape[0], 17, 3))
    for k, name in spec["limbs"].items():
        out[:, k] = pg[:, idx[name]]
    head = pg[:, idx[spec["head"]]]
    neck = pg[:, idx[next(n for n in spec["neck"] if n in idx)]]
    if spec["eyes"]:
        eye_l, eye_r = pg[:, idx[spec["eyes"][0]]], pg[:, idx[spec["eyes"][1]]]
        out[:, 1], out[:, 2] = eye_l, eye_r
        left = _unit(eye_l - eye_r)
    else:
        left = _unit(out[:, 5] - out[:, 6])
    up = head - neck
    up = _unit(up - left * np.sum(up * left, -1, keepdims=True))
    fwd = np.cross(left, up)  # right-handed axes: left x up = forward
    if spec["eyes"]:
        eye_mid = 0.5 * (eye_l + eye_r)
        fwd *= np.sign(np.sum((eye_mid - head) * fwd, -1, keepdims=True) + 1e-12)
    else:
        eye_mid = head + cm_units * (6.0 * up + 8.0 * fwd)
        out[:, 1] = eye_mid + cm_units * 3.2 * left
        out[:, 2] = eye_mid - cm_units * 3.2 * left
    out[:, 0] = eye_mid + cm_units * (2.0 * fwd - 4.0 * up)
    out[:, 3] = eye_mid + cm_units * (7.5 * left - 8.0 * fwd - 1.0 * up)
    out[:, 4] = eye_mid + cm_units * (-7.5 * left - 8.0 * fwd - 1.0 * up)
    return out
