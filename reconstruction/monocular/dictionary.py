"""The 3D pose dictionary of the single-frame initialisation (sparse representation of human poses).

Skeleton: the model works on all 17 COCO-17 keypoints of :mod:`skycap.skeleton` (2D detections come in
as COCO-17) with :data:`skycap.skeleton.COCO17_LIMBS` as the limbs of the articulation term; results are
scored on :data:`skycap.skeleton.SCORED_JOINTS` (the 12 limb joints + head).

A pose S (3, 17) is modelled as ``S = sum_k c_k B_k`` with few non-zero c_k (Zhou et al., "Sparseness
meets deepness", CVPR 2016; PAMI 2017). Training poses are put in a canonical body frame first (centred
on the joint mean, rotated so that the hips lie along x and the torso along -y (up), metres), so the
dictionary models articulation and the camera rotation models the view.

The shipped dictionary ``reconstruction/dictionary/cmu_coco17_k64.npz`` is learned by
``python -m reconstruction.dictionary.learn_dictionary`` from CMU motion capture (credit: "The data used
in this project was obtained from mocap.cs.cmu.edu. The database was created with funding from NSF
EIA-0196217."); the npz records which clips were used.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from skycap.errors import SkycapError
from skycap.skeleton import COCO17, COCO17_LIMBS

log = logging.getLogger(__name__)

__all__ = [
    "PoseDictionary",
    "DictionaryError",
    "DEFAULT_DICTIONARY",
    "canonicalize_poses",
    "load_dictionary",
    "learn_dictionary",
    "sparse_code",
]

DEFAULT_DICTIONARY = Path(__file__).resolve().parents[1] / "dictionary" / "cmu_coco17_k64.npz"
NUM_JOINTS = 17


class DictionaryError(SkycapError):
    """A pose dictionary file that is missing or malformed."""


@dataclasses.dataclass
class PoseDictionary:
    """Pose bases ``B`` (K, 3, J) in the canonical body frame (unit Frobenius norm each)."""

    bases: np.ndarray  # (K, 3, J)
    mean_pose: np.ndarray | None = None  # (3, J) mean training pose (canonical frame): fixes the sign of S
    limbs: tuple[tuple[int, int], ...] = COCO17_LIMBS
    clips: tuple[str, ...] = ()
    credit: str = ""

    @property
    def num_bases(self) -> int:
        return int(self.bases.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.bases.shape[2])

    def compose(self, coeffs: np.ndarray) -> np.ndarray:
        """Poses (..., 3, J) from coefficients (..., K)."""
        return np.einsum("...k,kij->...ij", coeffs, self.bases)

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            p,
            bases=self.bases.astype(np.float32),
            mean_pose=(np.zeros((3, self.num_joints)) if self.mean_pose is None else self.mean_pose).astype(np.float32),
            limbs=np.asarray(self.limbs, dtype=np.int16),
            clips=np.asarray(self.clips, dtype=str),
            credit=np.asarray(self.credit),
        )
        return p


def load_dictionary(path: str | Path | None = None) -> PoseDictionary:
    """Load a dictionary npz (default: the shipped CMU COCO-17 one)."""
    p = Path(path) if path is not None else DEFAULT_DICTIONARY
    if not p.is_file():
        raise DictionaryError(
            f"pose dictionary {p} not found; learn one with `python -m reconstruction.dictionary.learn_dictionary "
            f"--out {p}` or pass an existing file"
        )
    with np.load(p, allow_pickle=False) as z:
        if "bases" not in z:
            raise DictionaryError(f"{p} has no 'bases' array; it is not a pose dictionary")
        bases = z["bases"].astype(float)
        if bases.ndim != 3 or bases.shape[1] != 3 or bases.shape[2] != NUM_JOINTS:
            raise DictionaryError(f"{p}: bases have shape {bases.shape}, expected (K, 3, {NUM_JOINTS})")
        limbs = tuple(tuple(int(v) for v in l) for l in z["limbs"]) if "limbs" in z else COCO17_LIMBS
        clips = tuple(str(c) for c in z["clips"]) if "clips" in z else ()
        mean_pose = z["mean_pose"].astype(float) if "mean_pose" in z else None
        credit = str(z["credit"]) if "credit" in z else ""
    return PoseDictionary(bases=bases, mean_pose=mean_pose, limbs=limbs, clips=clips, credit=credit)


def canonicalize_poses(joints: np.ndarray) -> np.ndarray:
    """World poses (N, 17, 3) -> canonical body-frame poses (N, 3, 17).

    Centred on the mean of the joints; x along right_hip -> left_hip... precisely: x = unit(left_hip -
    right_hip), y = "down" = unit(mid_hip - mid_shoulder) orthogonalised against x, z = x cross y.
    """
    X = np.asarray(joints, dtype=float)
    X = X - X.mean(axis=1, keepdims=True)
    Rb = canonical_rotation(X)
    return np.einsum("nij,nkj->nik", Rb, X)  # (N, 3, 17)


def canonical_rotation(joints: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) whose rows are the body axes (see :func:`canonicalize_poses`) of poses (N, 17, 3)."""
    X = np.asarray(joints, dtype=float)
    x = X[:, COCO17["left_hip"]] - X[:, COCO17["right_hip"]]
    x /= np.linalg.norm(x, axis=-1, keepdims=True) + 1e-12
    mid_hip = 0.5 * (X[:, COCO17["left_hip"]] + X[:, COCO17["right_hip"]])
    mid_sh = 0.5 * (X[:, COCO17["left_shoulder"]] + X[:, COCO17["right_shoulder"]])
    y = mid_hip - mid_sh
    y -= x * np.sum(x * y, -1, keepdims=True)
    y /= np.linalg.norm(y, axis=-1, keepdims=True) + 1e-12
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)  # (N, 3, 3): rows are the body axes in world


def sparse_code(X: np.ndarray, D: np.ndarray, lam: float, iters: int = 200, C0: np.ndarray | None = None) -> np.ndarray:
    """Lasso codes C (N, K) minimising 1/2 ||X - C D||^2 + lam ||C||_1 by FISTA.

    X (N, d) data rows, D (K, d) atoms as rows.
    """
    G = D @ D.T
    L = float(np.linalg.eigvalsh(G)[-1]) + 1e-12
    XD = X @ D.T
    C = np.zeros((X.shape[0], D.shape[0])) if C0 is None else C0.copy()
    Y, tk = C.copy(), 1.0
    for _ in range(iters):
        grad = Y @ G - XD
        Z = Y - grad / L
        Cn = np.sign(Z) * np.maximum(np.abs(Z) - lam / L, 0.0)
        tn = 0.5 * (1 + np.sqrt(1 + 4 * tk * tk))
        Y = Cn + ((tk - 1) / tn) * (Cn - C)
        C, tk = Cn, tn
    return C


def learn_dictionary(
    poses: np.ndarray, num_bases: int = 64, lam: float = 0.01, iters: int = 30, seed: int = 0
) -> tuple[np.ndarray, dict]:
    """Learn bases (K, 3, 17) from canonical poses (N, 3, 17) by sparse coding (alternating lasso / MOD).

    Minimises 1/2 ||X - C B||_F^2 + lam ||C||_1 with unit-norm atoms; atoms start at random training poses.
    Returns the bases and a dict of statistics (relative reconstruction error, mean active atoms).
    """
    rng = np.random.default_rng(seed)
    N = poses.shape[0]
    X = poses.reshape(N, -1)
    D = X[rng.choice(N, size=num_bases, replace=False)].copy()
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    C = None
    for it in range(iters):
        C = sparse_code(X, D, lam, iters=100, C0=C)
        # MOD dictionary update: least squares, then renormalise (rescale codes accordingly)
        G = C.T @ C + 1e-6 * np.eye(num_bases)
        D = np.linalg.solve(G, C.T @ X)
        unused = np.linalg.norm(D, axis=1) < 1e-8
        if unused.any():  # restart dead atoms at the worst-represented poses
            err = np.linalg.norm(X - C @ D, axis=1)
            D[unused] = X[np.argsort(-err)[: unused.sum()]]
        norms = np.linalg.norm(D, axis=1, keepdims=True)
        D /= norms
        C *= norms.T
        rel = np.linalg.norm(X - C @ D) / np.linalg.norm(X)
        log.info("dictionary iter %d: relative error %.4f, active %.1f", it, rel, np.mean(np.sum(np.abs(C) > 1e-9, 1)))
    C = sparse_code(X, D, lam, iters=300, C0=C)
    stats = {
        "relative_error": float(np.linalg.norm(X - C @ D) / np.linalg.norm(X)),
        "mean_active": float(np.mean(np.sum(np.abs(C) > 1e-9, 1))),
        "rms_error_m": float(np.sqrt(np.mean(np.sum((X - C @ D).reshape(N, 3, -1) ** 2, axis=1)))),
    }
    return D.reshape(num_bases, 3, NUM_JOINTS), stats
