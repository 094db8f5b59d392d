"""Beyond the paper: a learned single-frame lift of 2D keypoints to a 3D pose (an extra start for the world stages).

The paper's single-frame initialisation (:mod:`reconstruction.monocular.single_frame`) explains each frame's 2D
keypoints by a sparse code of a 64-pose dictionary. On motion far from walking (dances, climbing) many codes fit
the same 2D points at different depths and its lift is 100-190 mm off even with the true camera rotation (see
``results/RESULTS.md``). This module is the alternative the field uses since Martinez et al. ("A simple yet effective
baseline for 3D human pose estimation", ICCV 2017): a small residual MLP trained on motion capture seen from many
random drone-like viewpoints, which learns which depth goes with which 2D configuration.

* Input: one frame's COCO-17 keypoints, centred on their weighted mean and divided by their RMS radius (34 numbers,
  0 where masked) and the 17 visibility bits.
* Output: the 3D pose (17, 3) in the camera frame (x right, y down, z along the optical axis), centred, in units of
  the RMS radius of its own image-plane projection; scaled back by the 2D RMS radius it is in pixels of an
  orthographic camera, the unit of the paper's pipeline.
* Robustness: training inputs carry per-axis noise, dropped joints and gross outliers (uniform in the person's box
  grown by 50 %, as a detector's mistakes); at run time joints whose image position disagrees with the lifted
  pose's projection (after the best 2D scale and shift) are masked and the frame is lifted again.

The pose is returned as an :class:`reconstruction.monocular.single_frame.InitResult` (canonical body frame + the
orthographic camera rotation rows), so every later stage takes it as it takes the paper's init.

The shipped network ``reconstruction/lifter/cmu_coco17_lifter.npz`` is trained by
``python -m reconstruction.lifter.train_lifter`` on CMU motion capture (credit: "The data used in this project was
obtained from mocap.cs.cmu.edu. The database was created with funding from NSF EIA-0196217."); the npz records its
training clips, and the clips it holds out.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch

from reconstruction.monocular.dictionary import canonical_rotation
from reconstruction.monocular.single_frame import InitResult
from reconstruction.synth import look_at_T_world_cam
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_LIFTER", "LifterConfig", "LifterNet", "PoseLifter", "ViewSampling", "training_batch", "LifterError"]

DEFAULT_LIFTER = Path(__file__).resolve().parents[1] / "lifter" / "cmu_coco17_lifter.npz"
NUM_JOINTS = 17


class LifterError(SkycapError):
    """A lifter weights file that is missing or malformed."""


@dataclasses.dataclass
class LifterConfig:
    """The learned lift as an extra start of the perspective BA (``reconstruction.monocular.pipeline``)."""

    enabled: bool = True
    path: str = ""  # weights (npz); empty = the shipped DEFAULT_LIFTER
    rounds: int = 3  # lift, mask the joints that disagree with the lifted pose, lift again
    outlier_threshold: float = 0.3  # image residual beyond which a joint is masked (RMS radius units)
    noise_outlier_mult: float = 3.0  # the threshold is at least this x the tracks' pixel noise


@dataclasses.dataclass
class ViewSampling:
    """The random views and detector errors of the training set (also recorded in the weights file)."""

    elevation_deg: tuple[float, float] = (-10.0, 50.0)  # camera looking down at the person's centre, uniform
    roll_sigma_deg: float = 4.0
    distance_m: tuple[float, float] = (3.0, 15.0)  # camera to the person's centre: perspective of a near drone
    noise_rel: tuple[float, float] = (0.0, 0.03)  # per-axis noise sigma per sample (RMS radius units), uniform
    drop_rate_max: float = 0.15  # per sample, a rate uniform in [0, this]; each joint dropped at that rate
    outlier_rate_max: float = 0.2  # likewise for gross outliers


class LifterNet(torch.nn.Module):
    """Residual MLP: (N, 51) normalised keypoints + visibility -> (N, 17, 3) camera-frame pose, centred."""

    def __init__(self, hidden: int = 512, blocks: int = 2, dropout: float = 0.2):
        super().__init__()
        self.hidden, self.num_blocks = hidden, blocks
        self.inp = torch.nn.Linear(3 * NUM_JOINTS, hidden)
        self.blocks = torch.nn.ModuleList(
            torch.nn.Sequential(
                torch.nn.Linear(hidden, hidden), torch.nn.LayerNorm(hidden), torch.nn.ReLU(), torch.nn.Dropout(dropout),
                torch.nn.Linear(hidden, hidden), torch.nn.LayerNorm(hidden), torch.nn.ReLU(), torch.nn.Dropout(dropout),
            )  # fmt: skip
            for _ in range(blocks)
        )
        self.out = torch.nn.Linear(hidden, 3 * NUM_JOINTS)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, 51) -> (N, 17, 3), centred on the joint mean."""
        y = torch.relu(self.inp(x))
        for b in self.blocks:
            y = y + b(y)
        P = self.out(y).reshape(-1, NUM_JOINTS, 3)
        return P - P.mean(1, keepdim=True)


def camera_rotations(azimuth_rad: np.ndarray, elevation_rad: np.ndarray, roll_rad: np.ndarray) -> np.ndarray:
    """World (NED) -> camera rotations (N, 3, 3) of cameras looking at the origin from ``azimuth`` (about down),
    ``elevation`` (positive: looking down), with ``roll`` about the optical axis. Rows: camera x (right), y (down),
    z (optical axis), in NED."""
    f = np.stack([np.cos(azimuth_rad) * np.cos(elevation_rad), np.sin(azimuth_rad) * np.cos(elevation_rad),
                  np.sin(elevation_rad)], -1)  # fmt: skip
    R = np.swapaxes(look_at_T_world_cam(-f, np.zeros_like(f))[:, :3, :3], 1, 2)  # the simulator's camera axes
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    Rz = np.zeros_like(R)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    return Rz @ R


def normalise_keypoints(xy: np.ndarray, mask: np.ndarray):
    """Centre (weighted by ``mask``) and scale to unit RMS radius. xy (N, 17, 2), mask (N, 17) ->
    (inputs (N, 51), centre (N, 2), scale (N,))."""
    m = np.asarray(mask, dtype=float)
    n = m.sum(1).clip(1.0)
    c = (xy * m[..., None]).sum(1) / n[:, None]
    d = np.where(m[..., None] > 0, xy - c[:, None], 0.0)
    s = np.sqrt((d**2).sum((1, 2)) / n)
    s = np.where(s > 1e-9, s, 1.0)
    x = (d / s[:, None, None]).reshape(len(xy), -1)
    return np.concatenate([x, m], 1), c, s


def training_batch(poses_ned_m: np.ndarray, rng: np.random.Generator, n: int, view: ViewSampling | None = None):
    """A random batch: inputs (n, 51) and targets (n, 17, 3) (float32 tensors) from world poses (N, 17, 3) centred."""
    v = view or ViewSampling()
    X = poses_ned_m[rng.integers(0, len(poses_ned_m), n)]
    R = camera_rotations(rng.uniform(-np.pi, np.pi, n), np.radians(rng.uniform(*v.elevation_deg, n)),
                         np.radians(rng.normal(0.0, v.roll_sigma_deg, n)))  # fmt: skip
    P = np.einsum("nij,nkj->nki", R, X - X.mean(1, keepdims=True))  # camera frame, centred
    D = rng.uniform(*v.distance_m, n)
    uv = P[..., :2] / (P[..., 2] + D[:, None])[..., None] * D[:, None, None]  # perspective, metres at the centre
    mask = (rng.random((n, NUM_JOINTS)) >= rng.uniform(0.0, v.drop_rate_max, (n, 1))).astype(float)
    lo, hi = uv.min(1), uv.max(1)
    span = np.maximum(hi - lo, 0.05)
    out = rng.random((n, NUM_JOINTS)) < rng.uniform(0.0, v.outlier_rate_max, (n, 1))
    wrong = lo[:, None] - 0.25 * span[:, None] + rng.random((n, NUM_JOINTS, 2)) * 1.5 * span[:, None]
    scale_m = np.sqrt((P[..., :2] ** 2).sum(-1).mean(1))
    noisy = uv + rng.normal(0.0, 1.0, uv.shape) * (rng.uniform(*v.noise_rel, n) * scale_m)[:, None, None]
    uv = np.where(out[..., None], wrong, noisy)
    inp, _, _ = normalise_keypoints(uv, mask)
    tgt = P / scale_m[:, None, None]
    return torch.tensor(inp, dtype=torch.float32), torch.tensor(tgt, dtype=torch.float32)


class PoseLifter:
    """The trained network and what it was trained on (one object per weights file)."""

    def __init__(self, net: LifterNet, clips: tuple[str, ...] = (), held_out: tuple[str, ...] = (), credit: str = ""):
        self.net = net.eval()
        self.clips, self.held_out, self.credit = tuple(clips), tuple(held_out), credit

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        sd = {f"w/{k}": v.detach().cpu().numpy().astype(np.float16) for k, v in self.net.state_dict().items()}
        np.savez_compressed(p, hidden=self.net.hidden, blocks=self.net.num_blocks, clips=np.array(self.clips),
                            held_out=np.array(self.held_out), credit=np.array(self.credit), **sd)  # fmt: skip
        return p

    @classmethod
    def load(cls, path: str | Path | None = None) -> "PoseLifter":
        p = Path(path) if path else DEFAULT_LIFTER
        if not p.is_file():
            raise LifterError(f"lifter weights {p} do not exist; train them with `python -m reconstruction.lifter."
                              "train_lifter` or set method.lifter.enabled=false")  # fmt: skip
        try:
            with np.load(p, allow_pickle=False) as z:
                net = LifterNet(int(z["hidden"]), int(z["blocks"]))
                sd = {k[2:]: torch.tensor(z[k].astype(np.float32)) for k in z.files if k.startswith("w/")}
                net.load_state_dict(sd)
                meta = tuple(str(c) for c in z["clips"]), tuple(str(c) for c in z["held_out"]), str(z["credit"])
        except (KeyError, ValueError, RuntimeError, OSError) as e:
            raise LifterError(f"lifter weights {p} are malformed ({e}); re-train them with `python -m "
                              "reconstruction.lifter.train_lifter`") from e  # fmt: skip
        return cls(net, *meta)

    def predict(self, xy: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame poses (N, 17, 3) in RMS-radius units for keypoints xy (N, 17, 2) (any unit) with mask (N, 17);
        and the inputs' centre (N, 2) and RMS radius (N,) in the unit of xy."""
        inp, c, s = normalise_keypoints(np.nan_to_num(xy), mask)
        with torch.no_grad():
            P = self.net(torch.tensor(inp, dtype=torch.float32)).double().numpy()
        return P, c, s

    def lift(self, W_px: np.ndarray, confidence: np.ndarray, cfg: LifterConfig | None = None, noise_px: float = 0.0) -> InitResult:
        """Lift every frame of W_px (T, 2, 17) (NaN where missing) with ``confidence`` (T, 17) (0 = missing).

        Returns the pose in the paper's orthographic form: S (T, 3, 17) in the canonical body frame, pixel units, and
        the camera rotation rows R (T, 2, 3) and image shift t (T, 2) with W ~ R S + t; ``inlier`` marks the joints
        kept (detected and consistent with the lifted pose), ``coeffs`` is empty (no dictionary code).
        """
        cfg = cfg or LifterConfig()
        W = np.asarray(W_px, dtype=float)
        T = W.shape[0]
        xy = np.swapaxes(W, 1, 2)
        seen = (np.asarray(confidence) > 0) & np.isfinite(xy).all(-1)
        m = seen.astype(float)
        rounds = max(1, cfg.rounds)
        for r in range(rounds):
            P, c, s = self.predict(xy, m)
            obs = (np.nan_to_num(xy) - c[:, None]) / s[:, None, None]  # every joint, in the input's normalisation
            a, b = _scale_shift(P[..., :2], obs, m)
            res = np.linalg.norm(a[:, None, None] * P[..., :2] + b[:, None] - obs, axis=-1)
            thr = np.maximum(cfg.outlier_threshold, cfg.noise_outlier_mult * noise_px / s)
            keep = seen & (res < thr[:, None])
            keep |= seen & (keep.sum(1, keepdims=True) < 6)  # never mask a frame below a usable skeleton
            if r == rounds - 1 or np.array_equal(keep, m > 0):
                break  # m is the mask of the returned lift
            m = keep.astype(float)
        S_cam = P * (a * s)[:, None, None]  # pixel units of the orthographic camera
        Rb = canonical_rotation(S_cam)
        S = np.einsum("nij,nkj->nik", Rb, S_cam)
        R = np.swapaxes(Rb, 1, 2)[:, :2]
        model = R @ S
        t = (np.nan_to_num(W - model) * m[:, None]).sum(-1) / m.sum(-1).clip(1.0)[:, None]
        resid = np.linalg.norm(W - (model + t[..., None]), axis=1)  # NaN where missing
        return InitResult(S=S, R=R, t=t, coeffs=np.zeros((T, 0)), weights=m, inlier=m > 0, residual_px=resid)


def _scale_shift(p: np.ndarray, o: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the scale a (N,) and shift b (N, 2) minimising sum_j m_j |a p_j + b - o_j|^2; p, o (N, J, 2)."""
    n = m.sum(1).clip(1.0)
    mp = (p * m[..., None]).sum(1) / n[:, None]
    mo = (o * m[..., None]).sum(1) / n[:, None]
    dp = p - mp[:, None]
    num = (dp * (o - mo[:, None]) * m[..., None]).sum((1, 2))
    den = ((dp**2).sum(-1) * m).sum(1)
    a = np.where(den > 1e-12, num / np.maximum(den, 1e-12), 1.0)
    a = np.clip(a, 0.5, 2.0)
    return a, mo - a[:, None] * mp
