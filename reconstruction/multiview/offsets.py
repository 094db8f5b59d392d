"""Per-detector joint offsets: where a keypoint detector puts a joint, relative to the skeleton's joint centre.

A keypoint model does not mark the skeleton's joint centres: it marks what its training labels marked (the
shoulder's surface seen from the front, the ankle bone, the tip of the nose), so its points sit a few centimetres
off the joint centres the body model and the scoring use, the same way every time. Pose2Sim's marker augmentation
handles that after triangulation; here the fit handles it: for each detector (by its name in
:attr:`reconstruction.capture.CameraCapture.detectors`) a constant per-joint offset in the person's body frame is
added to the model's joints before they are projected and compared with that detector's keypoints:

    x_detector(j, t) = J_j(t) + R_world_body(t) @ offset_body_m[detector][j]

**Body frame** (:func:`body_frame`), from the joints themselves (so it follows the fitted skeleton and is
differentiable): ``left`` = unit vector from the right hip (12) to the left hip (11); ``up`` = the spine, from the
hips' midpoint to the shoulders' midpoint (5, 6), made orthogonal to ``left``; ``forward`` = left x up (the way the
person faces). Columns of ``R_world_body`` = (forward, left, up) in world coordinates; an offset is given as
(forward, left, up) metres (the table in millimetres).

The table (:class:`JointOffsetTable`) is a small TOML file (``data/joint_offsets.toml`` is the one learned by
``python -m evaluation.learn_offsets``), one ``[[detector]]`` entry per detector name with the joint names, the
offsets in mm and the flights it came from. A detector that is not in the table gets no offset.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np

from skycap.errors import SkycapError
from skycap.skeleton import COCO17, COCO17_NAMES

__all__ = ["JointOffsetError", "JointOffsetTable", "BUILTIN_TABLE", "body_frame", "body_frame_torch", "apply_offsets",
           "apply_offsets_torch", "load_offsets", "offsets_for"]

#: the committed table learned on the rendered Anny person (see reconstruction/multiview/README.md)
BUILTIN_TABLE = Path(__file__).parent / "data" / "joint_offsets.toml"

_L_HIP, _R_HIP, _L_SH, _R_SH = COCO17["left_hip"], COCO17["right_hip"], COCO17["left_shoulder"], COCO17["right_shoulder"]


class JointOffsetError(SkycapError):
    """A joint-offset table that cannot be read or used."""


def body_frame(joints: np.ndarray) -> np.ndarray:
    """R_world_body (..., 3, 3) of COCO-17 joints (..., 17, 3): columns (forward, left, up), see the module doc."""
    X = np.asarray(joints, dtype=float)
    left = X[..., _L_HIP, :] - X[..., _R_HIP, :]
    left = left / np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-9)
    up = 0.5 * (X[..., _L_SH, :] + X[..., _R_SH, :]) - 0.5 * (X[..., _L_HIP, :] + X[..., _R_HIP, :])
    up = up - np.sum(up * left, -1, keepdims=True) * left
    up = up / np.maximum(np.linalg.norm(up, axis=-1, keepdims=True), 1e-9)
    fwd = np.cross(left, up)
    return np.stack([fwd, left, up], axis=-1)


def body_frame_torch(joints):
    """:func:`body_frame` on a torch tensor (..., 17, 3) -> (..., 3, 3), differentiable."""
    import torch

    left = joints[..., _L_HIP, :] - joints[..., _R_HIP, :]
    left = left / left.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    up = 0.5 * (joints[..., _L_SH, :] + joints[..., _R_SH, :]) - 0.5 * (joints[..., _L_HIP, :] + joints[..., _R_HIP, :])
    up = up - (up * left).sum(-1, keepdim=True) * left
    up = up / up.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    fwd = torch.cross(left, up, dim=-1)
    return torch.stack([fwd, left, up], dim=-1)


def apply_offsets(joints: np.ndarray, offsets_body_m: np.ndarray) -> np.ndarray:
    """Where a detector with ``offsets_body_m`` (17, 3) (forward, left, up metres) puts joints (..., 17, 3)."""
    R = body_frame(joints)
    return np.asarray(joints, dtype=float) + np.einsum("...ij,nj->...ni", R, np.asarray(offsets_body_m, dtype=float))


def apply_offsets_torch(joints, offsets_body_m):
    """:func:`apply_offsets` in torch: joints (..., 17, 3), offsets (D, 17, 3) -> (..., D, 17, 3)."""
    import torch

    R = body_frame_torch(joints)  # (..., 3, 3)
    return joints.unsqueeze(-3) + torch.einsum("...ij,dnj->...dni", R, offsets_body_m)


@dataclasses.dataclass
class JointOffsetTable:
    """Per detector name, the offsets (17, 3) in metres (forward, left, up), and where each came from."""

    offsets_body_m: dict[str, np.ndarray]
    sources: dict[str, dict] = dataclasses.field(default_factory=dict)

    def for_detectors(self, detectors) -> np.ndarray:
        """(D, 17, 3): the offsets of each of ``detectors`` (zeros for a detector the table does not hold)."""
        return np.stack([self.offsets_body_m.get(d, np.zeros((17, 3))) for d in detectors]) if len(detectors) else np.zeros((0, 17, 3))

    def save(self, path: str | Path) -> Path:
        """Write the table as TOML (offsets in mm, one row per joint, named in a comment)."""
        import json

        import tomli_w

        lines = ['body_frame = "columns (forward, left, up): left = right hip -> left hip; up = hip midpoint -> '
                 'shoulder midpoint, orthogonal to left; forward = left x up"', 'units = "mm"', ""]
        for name, off in self.offsets_body_m.items():
            lines += ["[[detector]]", f"name = {json.dumps(name)}", f"joints = {json.dumps(list(COCO17_NAMES))}",
                      "offset_fwd_left_up_mm = ["]
            lines += [f"    [{row[0] * 1e3:.1f}, {row[1] * 1e3:.1f}, {row[2] * 1e3:.1f}],  # {n}"
                      for n, row in zip(COCO17_NAMES, off)]
            lines.append("]")
            extra = self.sources.get(name, {})
            if extra:
                lines.append(tomli_w.dumps(extra).rstrip())
            lines.append("")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "JointOffsetTable":
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise JointOffsetError(f"joint-offset table {path} does not exist: give an existing TOML file "
                                   f"(``python -m evaluation.learn_offsets`` writes one), 'builtin' or '' (none)") from None
        except tomllib.TOMLDecodeError as e:
            raise JointOffsetError(f"joint-offset table {path} is not valid TOML ({e}): rewrite it with "
                                   f"``python -m evaluation.learn_offsets``") from None
        offs, srcs = {}, {}
        for e in doc.get("detector", []):
            names, rows = e.get("joints"), e.get("offset_fwd_left_up_mm")
            if not isinstance(e.get("name"), str) or names is None or rows is None or len(names) != len(rows):
                raise JointOffsetError(f"{path}: each [[detector]] needs 'name', 'joints' and as many "
                                       f"'offset_fwd_left_up_mm' rows [fwd, left, up] as joints")
            off = np.zeros((17, 3))
            for n, r in zip(names, rows):
                if n not in COCO17 or len(r) != 3:
                    raise JointOffsetError(f"{path}: detector {e['name']!r}: joint {n!r} / row {r}: joints are COCO-17 "
                                           f"names ({', '.join(COCO17_NAMES)}), rows three numbers (mm)")
                off[COCO17[n]] = np.asarray(r, dtype=float) * 1e-3
            offs[e["name"]] = off
            srcs[e["name"]] = {k: v for k, v in e.items() if k not in ("name", "joints", "offset_fwd_left_up_mm")}
        return cls(offs, srcs)


def load_offsets(spec: str) -> JointOffsetTable | None:
    """The table a config names: "" -> None (no offsets), "builtin" -> :data:`BUILTIN_TABLE`, else a TOML path."""
    if not spec:
        return None
    return JointOffsetTable.load(BUILTIN_TABLE if spec == "builtin" else spec)


def offsets_for(spec: str, detectors) -> np.ndarray | None:
    """(D, 17, 3) offsets of ``detectors`` from the table ``spec`` names; None when no offset applies."""
    table = load_offsets(spec)
    if table is None:
        return None
    off = table.for_detectors(list(detectors))
    return off if np.any(off) else None
