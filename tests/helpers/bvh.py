"""A tiny CMU-named BVH written by the tests (the simulated person's ``--motion``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# A tiny CMU-named skeleton (metres, Y-up, facing +z, the person's left = +x): head joint 1.47 m above the ankles.
#            name          parent         offset (m)
_JOINTS = [("Hips", None, (0.0, 0.0, 0.0)),
           ("LeftUpLeg", "Hips", (0.09, -0.05, 0.0)), ("LeftLeg", "LeftUpLeg", (0.0, -0.42, 0.0)),
           ("LeftFoot", "LeftLeg", (0.0, -0.40, 0.0)),
           ("RightUpLeg", "Hips", (-0.09, -0.05, 0.0)), ("RightLeg", "RightUpLeg", (0.0, -0.42, 0.0)),
           ("RightFoot", "RightLeg", (0.0, -0.40, 0.0)),
           ("Spine", "Hips", (0.0, 0.10, 0.0)), ("Neck", "Spine", (0.0, 0.40, 0.0)), ("Head", "Neck", (0.0, 0.10, 0.0)),
           ("LeftArm", "Spine", (0.18, 0.38, 0.0)), ("LeftForeArm", "LeftArm", (0.28, 0.0, 0.0)),
           ("LeftHand", "LeftForeArm", (0.25, 0.0, 0.0)),
           ("RightArm", "Spine", (-0.18, 0.38, 0.0)), ("RightForeArm", "RightArm", (-0.28, 0.0, 0.0)),
           ("RightHand", "RightForeArm", (-0.25, 0.0, 0.0))]  # fmt: skip


def write_bvh(path: Path, m_per_unit: float = 0.0254, frames: int = 31, fps: float = 30.0, z_up: bool = False,
              drop: str = "", arms_down: bool = True) -> Path:
    """A BVH of the skeleton above in units of ``m_per_unit``: frame 0 a T-pose (no rotations), then the arms down
    (``arms_down``) while the root walks 1 m forward; ``z_up``: the same in Z-up axes without rotations."""
    names = [j[0] for j in _JOINTS if j[0] != drop]
    kids = {n: [j[0] for j in _JOINTS if j[1] == n and j[0] != drop] for n in names}
    off = {j[0]: np.array(j[2]) / m_per_unit for j in _JOINTS}
    fix = (lambda v: np.array([v[0], -v[2], v[1]])) if z_up else (lambda v: v)  # Y-up -> Z-up (proper rotation)
    lines = ["HIERARCHY"]

    def emit(n: str, depth: int) -> None:
        ind = "  " * depth
        lines.append(f"{ind}{'ROOT' if depth == 0 else 'JOINT'} {n}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}  OFFSET " + " ".join(f"{v:.5f}" for v in fix(off[n])))
        ch = "6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" if depth == 0 else "3 Zrotation Xrotation Yrotation"
        lines.append(f"{ind}  CHANNELS {ch}")
        for c in kids[n]:
            emit(c, depth + 1)
        if not kids[n]:
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 0 0", f"{ind}  }}"])
        lines.append(f"{ind}}}")

    emit("Hips", 0)
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / fps:.6f}"]
    for f in range(frames):
        vals = []
        for n in names:
            if n == "Hips":
                p = fix(np.array([0.0, 0.95, 1.0 * f / (frames - 1)]) / m_per_unit)
                vals += [*p, 0.0, 0.0, 0.0]
            else:
                z = 0.0
                if arms_down and not z_up and f > 0 and n in ("LeftArm", "RightArm"):
                    z = -80.0 if n == "LeftArm" else 80.0
                vals += [z, 0.0, 0.0]
        lines.append(" ".join(f"{v:.5f}" for v in vals))
    path.write_text("\n".join(lines) + "\n")
    return path
