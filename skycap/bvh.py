"""BVH motion files: a reader with vectorised forward kinematics, and a writer.

BVH rotation channels are intrinsic rotations in the order listed: ``Zrotation Yrotation Xrotation``
means R = Rz @ Ry @ Rx (degrees in the file). A joint's world transform is its parent's times
(offset + position channels, R). End Sites become joints without channels, named ``<parent>_End``
(or by :func:`write_bvh` from ``Skeleton.end_site``).

Example::

    motion = read_bvh("walk.bvh")
    xyz = motion.world_positions()          # (T, J, 3) in file units
    i = motion.skeleton.index("CC_Base_Head")
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from skycap.errors import SkycapError

__all__ = ["BvhError", "Skeleton", "BvhMotion", "bvh_header", "bvh_motion_lines", "read_bvh", "write_bvh", "forward_kinematics"]


class BvhError(SkycapError):
    """A BVH file that cannot be read."""


@dataclasses.dataclass
class Skeleton:
    """Joint hierarchy: parents precede children; ``parents[root] == -1``."""

    names: list[str]
    parents: np.ndarray  # (J,) int
    offsets: np.ndarray  # (J, 3) rest offsets from the parent, file units
    channels: list[list[str]]  # per joint, e.g. ["Xposition", ..., "Zrotation", "Yrotation", "Xrotation"]
    end_site: np.ndarray  # (J,) bool: End Site entries (no channels)

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise BvhError(f"joint {name!r} is not in this skeleton (has {len(self.names)} joints)") from None

    def children(self, j: int) -> list[int]:
        return [int(c) for c in np.nonzero(self.parents == j)[0]]


@dataclasses.dataclass
class BvhMotion:
    skeleton: Skeleton
    frame_time_s: float
    values: np.ndarray  # (T, C) channel values in file order

    @property
    def num_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time_s

    def channel_slices(self) -> list[slice]:
        out, k = [], 0
        for ch in self.skeleton.channels:
            out.append(slice(k, k + len(ch)))
            k += len(ch)
        return out

    def local_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame local rotations (T, J, 3, 3) and translations (T, J, 3) in file units."""
        sk = self.skeleton
        T = self.num_frames
        J = sk.num_joints
        R = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
        t = np.broadcast_to(sk.offsets, (T, J, 3)).copy()
        for j, (ch, sl) in enumerate(zip(sk.channels, self.channel_slices())):
            if not ch:
                continue
            vals = self.values[:, sl]
            rot_axes = "".join(c[0].upper() for c in ch if c.lower().endswith("rotation"))
            rot_idx = [i for i, c in enumerate(ch) if c.lower().endswith("rotation")]
            if rot_axes:
                R[:, j] = Rotation.from_euler(rot_axes, vals[:, rot_idx], degrees=True).as_matrix()
            for i, c in enumerate(ch):
                if c.lower().endswith("position"):
                    t[:, j, "xyz".index(c[0].lower())] += vals[:, i]
        return R, t

    def world_positions(self) -> np.ndarray:
        """World positions (T, J, 3) of every joint, in file units and axes."""
        R, t = self.local_transforms()
        _, p = forward_kinematics(self.skeleton.parents, R, t)
        return p

    def slice(self, start: int, stop: int | None = None, step: int = 1) -> "BvhMotion":
        return BvhMotion(self.skeleton, self.frame_time_s * step, self.values[start:stop:step].copy())


def forward_kinematics(parents: np.ndarray, R_local: np.ndarray, t_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global rotations (..., J, 3, 3) and positions (..., J, 3) from local ones; parents precede children."""
    J = len(parents)
    Rg = np.empty_like(R_local)
    pg = np.empty_like(t_local)
    for j in range(J):
        p = parents[j]
        if p < 0:
            Rg[..., j, :, :] = R_local[..., j, :, :]
            pg[..., j, :] = t_local[..., j, :]
        else:
            Rg[..., j, :, :] = Rg[..., p, :, :] @ R_local[..., j, :, :]
            pg[..., j, :] = pg[..., p, :] + np.einsum("...ij,...j->...i", Rg[..., p, :, :], t_local[..., j, :])
    return Rg, pg


_TOKEN = re.compile(r"\S+")


def read_bvh(path: str | Path) -> BvhMotion:
    """Read a BVH file. Raises :class:`BvhError` naming the file and line on malformed input."""
    path = Path(path)
    if not path.is_file():
        raise BvhError(f"BVH file {path} does not exist")
    text = path.read_text(errors="replace")
    lines = text.splitlines()
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_site: list[bool] = []
    stack: list[int] = []
    pending: int | None = None  # index of joint awaiting "{"
    i = 0

    def fail(msg: str) -> BvhError:
        return BvhError(f"{path}:{i + 1}: {msg}; the file is not a valid BVH hierarchy")

    while i < len(lines):
        tok = lines[i].split()
        if not tok:
            i += 1
            continue
        key = tok[0].upper()
        if key == "HIERARCHY":
            pass
        elif key in ("ROOT", "JOINT"):
            if len(tok) < 2:
                raise fail(f"{key} without a name")
            names.append(tok[1])
            parents.append(stack[-1] if stack else -1)
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            end_site.append(False)
            pending = len(names) - 1
        elif key == "END":
            if not stack:
                raise fail("End Site outside a joint")
            names.append(f"{names[stack[-1]]}_End")
            parents.append(stack[-1])
            offsets.append([0.0, 0.0, 0.0])
            channels.append([])
            end_site.append(True)
            pending = len(names) - 1
        elif key == "{":
            if pending is None:
                raise fail("unexpected '{'")
            stack.append(pending)
            pending = None
        elif key == "}":
            if not stack:
                raise fail("unbalanced '}'")
            stack.pop()
        elif key == "OFFSET":
            try:
                offsets[stack[-1]] = [float(v) for v in tok[1:4]]
            except (ValueError, IndexError):
                raise fail("OFFSET needs three numbers") from None
        elif key == "CHANNELS":
            try:
                n = int(tok[1])
            except (ValueError, IndexError):
                raise fail("CHANNELS needs a count") from None
            if len(tok) != n + 2:
                raise fail(f"CHANNELS says {n} but lists {len(tok) - 2}")
            channels[stack[-1]] = tok[2:]
        elif key == "MOTION":
            i += 1
            break
        else:
            raise fail(f"unexpected token {tok[0]!r}")
        i += 1
    else:
        raise BvhError(f"{path}: no MOTION section; the file is truncated or not a BVH file")
    if stack or not names:
        raise BvhError(f"{path}: hierarchy is incomplete (unbalanced braces or no joints)")
    header: dict[str, str] = {}
    while i < len(lines) and len(header) < 2:
        if ":" in lines[i]:
            k, v = lines[i].split(":", 1)
            header[k.strip().lower()] = v.strip()
        i += 1
    try:
        n_frames = int(header["frames"])
        frame_time = float(header["frame time"])
    except (KeyError, ValueError):
        raise BvhError(f"{path}: MOTION section needs 'Frames:' and 'Frame Time:' lines") from None
    n_ch = sum(len(c) for c in channels)
    body = " ".join(lines[i:])
    try:
        vals = np.array(body.split(), dtype=float)
    except ValueError:
        raise BvhError(f"{path}: motion data has non-numeric values") from None
    n_have = vals.size // n_ch if n_ch else 0
    if n_have < n_frames:
        raise BvhError(
            f"{path}: header says {n_frames} frames of {n_ch} channels but the file holds {n_have} complete "
            f"frames; the file is truncated"
        )
    vals = vals[: n_frames * n_ch].reshape(n_frames, n_ch)
    if frame_time <= 0:
        raise BvhError(f"{path}: Frame Time must be positive, got {frame_time}")
    skel = Skeleton(names, np.array(parents, dtype=int), np.array(offsets, dtype=float), channels, np.array(end_site, bool))
    return BvhMotion(skel, frame_time, vals)


def write_bvh(
    path: str | Path,
    skeleton: Skeleton,
    frame_time_s: float,
    root_position: np.ndarray,
    R_local: np.ndarray,
    rotation_order: str = "ZYX",
    precision: int = 6,
) -> Path:
    """Write a BVH file: the root gets ``Xposition Yposition Zposition`` + rotations, other joints
    rotations only (``rotation_order`` e.g. "ZYX" -> ``Zrotation Yrotation Xrotation``).

    Shapes: root_position (T, 3) in the skeleton's units; R_local (T, J, 3, 3) local rotations
    (ignored for End Sites). ``skeleton.channels`` is ignored and rewritten. A long motion can be written in parts
    with the same result: :func:`bvh_header` with the total frame count, then :func:`bvh_motion_lines` per part.
    """
    path = Path(path)
    header = bvh_header(skeleton, frame_time_s, root_position.shape[0], rotation_order, precision)
    path.write_text(header + bvh_motion_lines(skeleton, root_position, R_local, rotation_order, precision))
    return path


def bvh_header(skeleton: Skeleton, frame_time_s: float, num_frames: int, rotation_order: str = "ZYX",
               precision: int = 6) -> str:
    """The text of a BVH file before its frames: the hierarchy, ``MOTION``, ``Frames:`` and ``Frame Time:``."""
    J = skeleton.num_joints
    rot_ch = [f"{a}rotation" for a in rotation_order]
    lines = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        ind = "  " * depth
        if skeleton.end_site[j]:
            lines.append(f"{ind}End Site")
        else:
            lines.append(f"{ind}{'ROOT' if skeleton.parents[j] < 0 else 'JOINT'} {skeleton.names[j]}")
        lines.append(f"{ind}{{")
        off = " ".join(f"{v:.{precision}f}" for v in skeleton.offsets[j])
        lines.append(f"{ind}  OFFSET {off}")
        if not skeleton.end_site[j]:
            ch = (["Xposition", "Yposition", "Zposition"] if skeleton.parents[j] < 0 else []) + rot_ch
            lines.append(f"{ind}  CHANNELS {len(ch)} {' '.join(ch)}")
        for c in skeleton.children(j):
            emit(c, depth + 1)
        lines.append(f"{ind}}}")

    emit(_root(skeleton), 0)
    lines += ["MOTION", f"Frames: {num_frames}", f"Frame Time: {frame_time_s:.6f}"]
    return "\n".join(lines) + "\n"


def bvh_motion_lines(skeleton: Skeleton, root_position: np.ndarray, R_local: np.ndarray, rotation_order: str = "ZYX",
                     precision: int = 6) -> str:
    """The frame lines (each ending in a newline) of root positions (T, 3) and local rotations (T, J, 3, 3)."""
    T = root_position.shape[0]
    movers = [j for j in _dfs_order(skeleton, _root(skeleton)) if not skeleton.end_site[j]]
    euler = Rotation.from_matrix(R_local[:, movers].reshape(-1, 3, 3)).as_euler(rotation_order, degrees=True)
    euler = euler.reshape(T, len(movers), 3)
    data = np.concatenate([root_position.reshape(T, 3), euler.reshape(T, -1)], axis=1)
    fmt = f"%.{precision}f"
    return "\n".join(" ".join(fmt % v for v in row) for row in data) + "\n"


def _root(skeleton: Skeleton) -> int:
    roots = [j for j in range(skeleton.num_joints) if skeleton.parents[j] < 0]
    if len(roots) != 1:
        raise BvhError(f"a BVH skeleton needs exactly one root, got {len(roots)}")
    return roots[0]


def _dfs_order(skeleton: Skeleton, j: int) -> list[int]:
    out = [j]
    for c in skeleton.children(j):
        out += _dfs_order(skeleton, c)
    return out
