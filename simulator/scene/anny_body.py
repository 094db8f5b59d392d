"""The simulated person as an Anny body mesh, posed from the 17 COCO joints the simulator carries.

    bodies = AnnyBodies.load()                       # the baked meshes (simulator/data/anny_bodies.npz)
    person = bodies.person(seed=3)                   # one shape and outfit, chosen by the seed
    verts_ned_m = person.pose(joints_ned_m)          # (V, 3) posed vertices, world NED
    person.faces, person.vertex_rgb                  # triangles, clothing colours (BGR 0..1)

Meshes: Anny's decimated ``notoes_collapse10pc`` topology (1229 vertices, 2454 triangles) for 12 adult
phenotypes, baked with :mod:`simulator.scene.anny_bake` (CC0-1.0 assets of Anny, NAVER Corp.). No torch
and no ``anny`` package at run time.

How the mesh is posed (a fit of segment transforms to the joints, no Anny pose parameters):

* Anny's 104 bones are grouped into 11 rigid **segments**: pelvis (root, pelvis, the two lowest spine
  bones), chest (upper spine, clavicles, shoulders), head (neck, head, eyes), upper arms, forearms (with
  the hands), thighs, shins (with the feet). Each vertex's Anny skinning weights are summed per segment:
  linear blend skinning with 11 transforms, so elbows, knees, the waist and the neck bend smoothly.
* The rest mesh's own COCO-17 joints come from Anny's bone heads (hip = ``upperleg01``, knee =
  ``lowerleg01``, ankle = ``foot``, shoulder = ``upperarm01``, elbow = ``lowerarm01``, wrist = ``wrist``,
  eyes = ``eye``; nose and ears at the offsets :func:`skycap.skeleton.mocap_to_coco17` uses), so the
  posed mesh's joints land exactly on the simulator's joints.
* Pelvis, chest and head get the rotation between their rest and target frames (built from the hips,
  the shoulders, and the eyes and nose) and a per-axis scale (width, height) to the target's proportions.
  Every limb segment gets the *minimal* rotation (swing) that carries its bone, as moved by its parent
  segment, onto the target bone direction, and a stretch along the bone to the target bone length
  (girth kept). Twist therefore follows the parent; a foot follows its shin.

Clothing: every vertex gets a material (skin, hair, shirt, trousers, shoes) from its dominant Anny bone and
a few rest-pose cuts (belt line, hair above the eyes and at the back of the head, sleeve and trouser
lengths), and the seed picks colours from palettes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np

from skycap.errors import SkycapError

__all__ = ["AnnyBodies", "AnnyPerson", "AnnyBodyError", "BODIES_PATH", "SEGMENTS", "MATERIALS"]

BODIES_PATH = Path(__file__).resolve().parents[1] / "data" / "anny_bodies.npz"

SEGMENTS = ("pelvis", "chest", "head", "l_upperarm", "r_upperarm", "l_forearm", "r_forearm",
            "l_thigh", "r_thigh", "l_shin", "r_shin")  # fmt: skip
MATERIALS = ("skin", "hair", "shirt", "trousers", "shoes")

# limb segments: (segment, parent segment, COCO joint a, COCO joint b)
_LIMBS = ((3, 1, 5, 7), (4, 1, 6, 8), (5, 3, 7, 9), (6, 4, 8, 10),
          (7, 0, 11, 13), (8, 0, 12, 14), (9, 7, 13, 15), (10, 8, 14, 16))  # fmt: skip

# palettes (BGR 0..255)
_SKIN = ((95, 125, 180), (120, 150, 205), (140, 175, 225), (60, 85, 130), (80, 110, 160), (45, 65, 100))
_HAIR = ((20, 25, 35), (30, 45, 70), (40, 80, 120), (25, 25, 25), (90, 130, 170), (110, 110, 115))
_SHIRT = ((60, 60, 200), (180, 120, 40), (40, 150, 40), (230, 230, 230), (40, 40, 45), (40, 180, 220),
          (150, 70, 120), (30, 90, 200), (160, 160, 150))  # fmt: skip
_TROUSERS = ((110, 70, 40), (60, 55, 50), (150, 120, 80), (30, 30, 35), (80, 120, 140), (90, 90, 95))
_SHOES = ((40, 40, 40), (220, 220, 220), (30, 50, 90), (70, 70, 70))


class AnnyBodyError(SkycapError):
    """The baked Anny meshes are missing or unreadable."""


def _unit(v: np.ndarray) -> np.ndarray:
    if v.ndim == 1:  # the per-frame path: 3-vectors, without numpy's per-call overhead
        n = math.sqrt(float(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))
        return v / max(n, 1e-9)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs ~10x more on single vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _frame(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) with columns (left, back, up) from a left and an up direction (up kept)."""
    u = _unit(up)
    l_ = _unit(left - u * float(left @ u))
    back = _cross(u, l_)  # x = left, z = up -> y = z cross x = back (Anny's right-handed body frame)
    return np.stack([l_, back, u], axis=1)


def _swing(u0: np.ndarray, u1: np.ndarray) -> np.ndarray:
    """The minimal rotation (3, 3) taking unit vector u0 to unit vector u1."""
    v = _cross(u0, u1)
    c = float(u0 @ u1)
    if c < -0.999999:  # opposite: any perpendicular axis
        a = np.cross(u0, [1.0, 0.0, 0.0] if abs(u0[0]) < 0.9 else [0.0, 1.0, 0.0])
        a = _unit(a)
        return 2.0 * np.outer(a, a) - np.eye(3)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


@dataclasses.dataclass
class AnnyPerson:
    """One body shape and outfit. ``pose(joints)`` -> posed vertices (V, 3) in the joints' frame."""

    rest_vertices: np.ndarray  # (V, 3) Anny frame
    rest_joints: np.ndarray  # (17, 3) COCO-17 of the rest mesh
    faces: np.ndarray  # (F, 3), counter-clockwise seen from outside
    weights: np.ndarray  # (V, S) per-segment skinning weights, rows sum to 1
    material: np.ndarray  # (V,) index into MATERIALS
    vertex_bgr: np.ndarray  # (V, 3) float32 0..255
    shape_index: int
    phenotype: dict[str, float]

    def __post_init__(self) -> None:
        j = self.rest_joints
        self._rest_torso = self._torso_frames(j)
        self._rest_len = {s: float(np.linalg.norm(j[b] - j[a])) for s, _, a, b in _LIMBS}

    @staticmethod
    def _torso_frames(j: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, float, float]]:
        """Segment -> (rotation, origin, width m, height m) of pelvis, chest and head from COCO joints."""
        sh_mid, hip_mid = 0.5 * (j[5] + j[6]), 0.5 * (j[11] + j[12])
        up = sh_mid - hip_mid
        L = float(np.linalg.norm(up))
        ear_mid = 0.5 * (j[3] + j[4])
        eye_mid = 0.5 * (j[1] + j[2])
        # head: left from the ears (or eyes), forward from the ears to the nose; up = left x forward ... via _frame
        h_left = (j[3] - j[4]) + (j[1] - j[2])
        h_fwd = j[0] - ear_mid
        h_up = _cross(_unit(h_fwd), _unit(h_left))  # forward x left = up (x left, -y forward, z up)
        return {
            "pelvis": (_frame(j[11] - j[12], up), hip_mid, float(np.linalg.norm(j[11] - j[12])), L),
            "chest": (_frame(j[5] - j[6], up), sh_mid, float(np.linalg.norm(j[5] - j[6])), L),
            "head": (_frame(h_left, h_up), eye_mid, 1.0, 1.0),
        }

    def segment_transforms(self, joints: np.ndarray) -> np.ndarray:
        """(S, 3, 4) affine transforms rest -> posed for the segments, from target joints (17, 3)."""
        j = np.asarray(joints, dtype=float)
        tgt = self._torso_frames(j)
        A = np.zeros((len(SEGMENTS), 3, 4))
        Q = np.zeros((len(SEGMENTS), 3, 3))
        for s, name in enumerate(("pelvis", "chest", "head")):
            R0, o0, w0, h0 = self._rest_torso[name]
            R1, o1, w1, h1 = tgt[name]
            if name == "head":
                sc = np.ones(3)
            else:
                sw = float(np.clip(w1 / max(w0, 1e-6), 0.75, 1.35))
                sh = float(np.clip(h1 / max(h0, 1e-6), 0.75, 1.35))
                sc = np.array([sw, np.sqrt(sw * sh), sh])
            Q[s] = R1 @ R0.T
            M = R1 @ np.diag(sc) @ R0.T
            A[s, :, :3] = M
            A[s, :, 3] = o1 - M @ o0
        r = self.rest_joints
        for s, p, a, b in _LIMBS:
            u_r = _unit(r[b] - r[a])
            u_c = Q[p] @ u_r
            d = j[b] - j[a]
            L1 = math.sqrt(float(d @ d))
            u_t = _unit(d) if L1 > 1e-6 else u_c
            Q[s] = _swing(u_c, u_t) @ Q[p]
            stretch = float(np.clip(L1 / max(self._rest_len[s], 1e-6), 0.6, 1.6))
            M = Q[s] + (stretch - 1.0) * np.outer(Q[s] @ u_r, u_r)
            A[s, :, :3] = M
            A[s, :, 3] = j[a] - M @ r[a]
        return A

    def pose(self, joints: np.ndarray) -> np.ndarray:
        """Posed vertices (V, 3) whose joints are ``joints`` (17, 3), in the joints' frame (e.g. NED m)."""
        A = self.segment_transforms(joints)
        blended = np.einsum("vs,sij->vij", self.weights, A)  # (V, 3, 4)
        v = self.rest_vertices
        return np.einsum("vij,vj->vi", blended[:, :, :3], v) + blended[:, :, 3]


class AnnyBodies:
    """The baked Anny meshes (see :mod:`simulator.scene.anny_bake`)."""

    def __init__(self, data: dict[str, np.ndarray]):
        self.faces = np.asarray(data["faces"], np.int64)
        self.rest_vertices = np.asarray(data["rest_vertices"], np.float64)
        self.rest_bone_heads = np.asarray(data["rest_bone_heads"], np.float64)
        self.bone_labels = [str(s) for s in data["bone_labels"]]
        self.phenotypes = np.asarray(data["phenotypes"], float)
        self.phenotype_labels = [str(s) for s in data["phenotype_labels"]]
        bi = np.asarray(data["vertex_bone_indices"], np.int64)
        bw = np.asarray(data["vertex_bone_weights"], np.float64)
        V = self.rest_vertices.shape[1]
        B = len(self.bone_labels)
        W = np.zeros((V, B))
        np.add.at(W, (np.repeat(np.arange(V), bi.shape[1]), bi.ravel()), bw.ravel())
        self.bone_weights = W / np.maximum(W.sum(1, keepdims=True), 1e-12)
        seg_of_bone = np.array([self._segment_of(b) for b in self.bone_labels])
        S = np.zeros((B, len(SEGMENTS)))
        S[np.arange(B), seg_of_bone] = 1.0
        self.segment_weights = self.bone_weights @ S
        self.dominant_bone = np.argmax(self.bone_weights, axis=1)

    @staticmethod
    @functools.lru_cache(maxsize=4)
    def load(path: str | Path = BODIES_PATH) -> "AnnyBodies":
        p = Path(path)
        if not p.is_file():
            raise AnnyBodyError(f"baked Anny meshes {p} not found; make them with `python -m simulator.scene.anny_bake`")
        try:
            with np.load(p, allow_pickle=False) as d:
                return AnnyBodies({k: d[k] for k in d.files})
        except (OSError, KeyError, ValueError) as e:
            raise AnnyBodyError(f"baked Anny meshes {p} unreadable ({e}); remake them with `python -m simulator.scene.anny_bake`") from e

    @property
    def num_shapes(self) -> int:
        return self.rest_vertices.shape[0]

    @staticmethod
    def _segment_of(label: str) -> int:
        side = "l_" if label.endswith(".L") else "r_"
        base = label.split(".")[0]
        if label == "root" or base == "pelvis" or base in ("spine05", "spine04"):
            return SEGMENTS.index("pelvis")
        if base.startswith("spine") or base in ("clavicle", "shoulder01"):
            return SEGMENTS.index("chest")
        if base.startswith("neck") or base in ("head", "eye", "jaw", "tongue"):
            return SEGMENTS.index("head")
        if base.startswith("upperarm"):
            return SEGMENTS.index(side + "upperarm")
        if base.startswith(("lowerarm", "wrist", "finger", "metacarpal", "thumb")):
            return SEGMENTS.index(side + "forearm")
        if base.startswith("upperleg"):
            return SEGMENTS.index(side + "thigh")
        if base.startswith(("lowerleg", "foot", "toe")):
            return SEGMENTS.index(side + "shin")
        return SEGMENTS.index("chest")

    def rest_joints(self, k: int) -> np.ndarray:
        """COCO-17 joints (17, 3) of rest shape ``k`` (Anny frame: x left, y back, z up)."""
        h = self.rest_bone_heads[k]
        i = self.bone_labels.index
        j = np.zeros((17, 3))
        for c, name in ((1, "eye.L"), (2, "eye.R"), (5, "upperarm01.L"), (6, "upperarm01.R"), (7, "lowerarm01.L"),
                        (8, "lowerarm01.R"), (9, "wrist.L"), (10, "wrist.R"), (11, "upperleg01.L"),
                        (12, "upperleg01.R"), (13, "lowerleg01.L"), (14, "lowerleg01.R"), (15, "foot.L"),
                        (16, "foot.R")):  # fmt: skip
            j[c] = h[i(name)]
        up = h[i("head")] - h[i("neck01")]
        left = _unit(j[1] - j[2])
        upo = _unit(up - left * np.dot(up, left))
        fwd = np.cross(left, upo)
        if fwd[1] > 0:  # forward is -y (Anny's y points back)
            fwd = -fwd
        mid = 0.5 * (j[1] + j[2])
        j[0] = mid + 0.02 * fwd - 0.04 * upo
        j[3] = mid + 0.075 * left - 0.08 * fwd - 0.01 * upo
        j[4] = mid - 0.075 * left - 0.08 * fwd - 0.01 * upo
        return j

    def materials(self, k: int, long_sleeves: bool, long_trousers: bool) -> np.ndarray:
        """(V,) material index (:data:`MATERIALS`) of every vertex of shape ``k``."""
        v = self.rest_vertices[k]
        j = self.rest_joints(k)
        lab = [self.bone_labels[b] for b in self.dominant_bone]
        base = np.array([s.split(".")[0] for s in lab])
        seg = np.argmax(self.segment_weights, axis=1)
        segn = np.array(SEGMENTS)[seg]
        mat = np.full(len(v), MATERIALS.index("shirt"))
        hip_z = 0.5 * (j[11, 2] + j[12, 2])
        sh_z = 0.5 * (j[5, 2] + j[6, 2])
        belt_z = hip_z + 0.22 * (sh_z - hip_z)
        torso = np.isin(segn, ("pelvis", "chest"))
        mat[torso & (v[:, 2] < belt_z)] = MATERIALS.index("trousers")
        legs = np.char.endswith(segn, "thigh") | np.char.endswith(segn, "shin")
        mat[legs] = MATERIALS.index("trousers")
        if not long_trousers:  # shorts: skin below mid-thigh
            knee_z = 0.5 * (j[13, 2] + j[14, 2])
            mat[legs & (v[:, 2] < 0.5 * (knee_z + hip_z))] = MATERIALS.index("skin")
        ankle_z = 0.5 * (j[15, 2] + j[16, 2])
        feet = np.isin(base, ("foot",)) | np.char.startswith(base, "toe") | (legs & (v[:, 2] < ankle_z + 0.03))
        mat[feet] = MATERIALS.index("shoes")
        forearm = np.char.endswith(segn, "forearm")
        hand = np.isin(base, ("wrist",)) | np.char.startswith(base, "finger") | np.char.startswith(base, "metacarpal")
        if long_sleeves:
            mat[hand] = MATERIALS.index("skin")
        else:
            mat[forearm] = MATERIALS.index("skin")
        mat[hand] = MATERIALS.index("skin")
        head = segn == "head"
        mat[head] = MATERIALS.index("skin")
        neck_z = float(self.rest_bone_heads[k][self.bone_labels.index("neck01"), 2])
        mat[head & (v[:, 2] < neck_z + 0.01)] = MATERIALS.index("shirt")  # collar
        eye_z = j[1, 2]
        eye_y = j[1, 1]
        # hair: above the brows, and the back of the head above the nape
        hair = head & ((v[:, 2] > eye_z + 0.035) | ((v[:, 1] > eye_y + 0.10) & (v[:, 2] > eye_z - 0.07)))
        mat[hair] = MATERIALS.index("hair")
        return mat

    def person(self, seed: int = 0, shape: int | None = None) -> AnnyPerson:
        """One person: shape ``shape`` (None: chosen by ``seed``) and an outfit drawn with ``seed``."""
        rng = np.random.default_rng(seed)
        k = int(rng.integers(self.num_shapes)) if shape is None else int(shape) % self.num_shapes
        long_sleeves = bool(rng.random() < 0.5)
        long_trousers = bool(rng.random() < 0.8)
        mat = self.materials(k, long_sleeves, long_trousers)
        pal = [_SKIN, _HAIR, _SHIRT, _TROUSERS, _SHOES]
        cols = np.array([p[int(rng.integers(len(p)))] for p in pal], dtype=np.float32)
        bgr = cols[mat]
        # a little per-vertex variation (fabric folds, skin tone): +-4 %
        bgr = bgr * (1.0 + 0.04 * rng.standard_normal((len(mat), 1))).astype(np.float32)
        faces = self.faces
        # Anny's winding: make faces counter-clockwise seen from outside (normals pointing away from the body)
        v = self.rest_vertices[k]
        n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        c = v[faces].mean(1)
        if np.mean(np.sum(n * (c - v.mean(0)), axis=1) > 0) < 0.5:
            faces = faces[:, [0, 2, 1]]
        ph = {l_: float(x) for l_, x in zip(self.phenotype_labels, self.phenotypes[k])}
        return AnnyPerson(v.copy(), self.rest_joints(k), faces.copy(), self.segment_weights.copy(), mat,
                          np.clip(bgr, 0, 255).astype(np.float32), k, ph)  # fmt: skip
