"""Simulated detectors: the exact ground-truth projections made realistically wrong. SIMULATED, not a model.

    kp = SimKeypointDetector(SimDetectorConfig(seed=1))
    det = kp.detect(gt, width_px, height_px)            # SimKeypoints or None (person not detected)
    msg_person = det.to_person_keypoints()              # shared_msgs.PersonKeypoints
    boxes = SimBoxDetector(cfg).detect(gt, width_px, height_px)   # list[shared_msgs.BoundingBox]

Keypoint errors, per frame, for a detected person (GT box height >= ``min_height_px``):

* **swap** (probability ``swap_prob``): the whole body is reported left/right mirrored (joint k gets
  the position of ``COCO17_FLIP[k]``), like a detector confusing front and back;
* per visible joint, exclusively: **miss** (``miss_prob``: confidence 0), **outlier**
  (``outlier_prob``: uniform in the person's box grown by ``outlier_box_scale``, confidence uniform in
  [outlier_conf_min, outlier_conf_max]) or **inlier**: Gaussian noise of std
  ``sqrt(noise_px^2 + (noise_frac_of_height * box_height)^2)`` per axis (with the frame times given,
  first-order Gauss-Markov in time with correlation time ``noise_correlation_s``: same std, drifting
  rather than white), confidence
  ``clip(N(conf_mean, conf_std)) * exp(-0.5 (|error| / (2 std))^2)`` (larger errors, lower confidence);
* joints hidden behind another body part (``GtProjection.occluded``): noise std times
  ``occluded_noise_scale``, confidence times ``occluded_conf_scale``, miss probability
  ``occluded_miss_prob`` instead of ``miss_prob``;
* joints outside the image or behind the camera: confidence 0, position clamped into the image.

Box detector: the GT box with Gaussian edge noise (std ``box_noise_frac * height``, reported as the
per-edge variance), missed with ``box_miss_prob``, plus Poisson(``box_false_alarm_rate``) false alarms
of person-like shape with low scores.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from shared_msgs.messages import BoundingBox, PersonKeypoints
from simulator.scene.camera import GtProjection
from simulator.scene.config import SimDetectorConfig
from skycap.skeleton import COCO17_FLIP

__all__ = ["SimKeypoints", "SimKeypointDetector", "SimBoxDetector", "SIM_KEYPOINT_DETECTOR", "SIM_BOX_DETECTOR"]

SIM_KEYPOINT_DETECTOR = "sim_noisy_gt"
SIM_BOX_DETECTOR = "simulated"

_FLIP = np.array(COCO17_FLIP)


@dataclasses.dataclass
class SimKeypoints:
    """One simulated detection. uv_px (17, 2), confidence (17,), and what was done (for tests and
    analysis): swapped (whole body), missed / outlier (17,) bool, sigma_px (per-axis inlier noise std of
    an unoccluded joint),
    box_px (4,) the GT box used."""

    uv_px: np.ndarray
    confidence: np.ndarray
    swapped: bool
    missed: np.ndarray
    outlier: np.ndarray
    sigma_px: float
    box_px: np.ndarray

    def to_person_keypoints(self, box: BoundingBox | None = None) -> PersonKeypoints:
        return PersonKeypoints(
            keypoints_px=tuple(float(v) for v in self.uv_px.reshape(-1)),
            confidence=tuple(float(c) for c in self.confidence),
            box=box,
        )


class SimKeypointDetector:
    """Noisy COCO-17 keypoints from :class:`~simulator.scene.camera.GtProjection` (seeded, reproducible)."""

    def __init__(self, cfg: SimDetectorConfig | None = None, rng: np.random.Generator | None = None):
        self.cfg = (cfg or SimDetectorConfig()).validate()
        self.rng = rng if rng is not None else np.random.default_rng(self.cfg.seed)
        self._z: np.ndarray | None = None  # (17, 2) unit-variance noise state
        self._t_s: float | None = None

    def _unit_noise(self, t_s: float | None) -> np.ndarray:
        """(17, 2) standard-normal noise; AR(1) over time when t_s is given and a correlation time is set."""
        tau = self.cfg.noise_correlation_s
        w = self.rng.normal(0.0, 1.0, size=(17, 2))
        if t_s is None or tau <= 0 or self._z is None or self._t_s is None or not 0 <= t_s - self._t_s < 5 * tau:
            z = w
        else:
            rho = float(np.exp(-(t_s - self._t_s) / tau))
            z = rho * self._z + np.sqrt(1.0 - rho * rho) * w
        self._z, self._t_s = z, t_s
        return z

    def detect(self, gt: GtProjection, width_px: int, height_px: int, t_s: float | None = None) -> SimKeypoints | None:
        """A noisy detection of the person in ``gt``; ``t_s`` (frame time) enables temporally correlated noise."""
        cfg, rng = self.cfg, self.rng
        if gt.box_px is None:
            return None
        box = np.asarray(gt.box_px, dtype=float)
        h_box = box[3] - box[1]
        if h_box < cfg.min_height_px:
            return None
        sigma = float(np.hypot(cfg.noise_px, cfg.noise_frac_of_height * h_box))
        uv_true = np.asarray(gt.uv_px, dtype=float).copy()
        visible = np.asarray(gt.visible, dtype=bool).copy()
        occluded = np.asarray(gt.occluded, dtype=bool).copy()
        swapped = bool(rng.random() < cfg.swap_prob)
        if swapped:
            uv_true = uv_true[_FLIP]
            visible = visible[_FLIP]
            occluded = occluded[_FLIP]
        sig_j = np.where(occluded, sigma * cfg.occluded_noise_scale, sigma)
        z = self._unit_noise(t_s)
        noise = (z[_FLIP] if swapped else z) * sig_j[:, None]
        uv = uv_true + noise
        err = np.linalg.norm(noise, axis=1)
        conf_base = np.clip(rng.normal(cfg.conf_mean, cfg.conf_std, size=17), 0.05, 1.0)
        conf = conf_base * np.exp(-0.5 * (err / (2.0 * np.maximum(sig_j, 1e-6))) ** 2)
        conf = np.where(occluded, conf * cfg.occluded_conf_scale, conf)
        u = rng.random(17)
        p_miss = np.where(occluded, cfg.occluded_miss_prob, cfg.miss_prob)
        missed = visible & (u < p_miss)
        outlier = visible & ~missed & (u < p_miss + cfg.outlier_prob)
        if outlier.any():
            c = 0.5 * (box[:2] + box[2:])
            half = 0.5 * (box[2:] - box[:2]) * cfg.outlier_box_scale
            n_out = int(outlier.sum())
            uv[outlier] = c + rng.uniform(-1.0, 1.0, size=(n_out, 2)) * half
            conf[outlier] = rng.uniform(cfg.outlier_conf_min, cfg.outlier_conf_max, size=n_out)
        conf[missed] = 0.0
        conf[~visible] = 0.0
        uv[:, 0] = np.clip(uv[:, 0], 0.0, float(width_px))
        uv[:, 1] = np.clip(uv[:, 1], 0.0, float(height_px))
        return SimKeypoints(uv, conf, swapped, missed, outlier, sigma, box)


class SimBoxDetector:
    """Noisy person boxes from the GT box, with misses and false alarms (seeded, reproducible)."""

    def __init__(self, cfg: SimDetectorConfig | None = None, rng: np.random.Generator | None = None):
        self.cfg = (cfg or SimDetectorConfig()).validate()
        self.rng = rng if rng is not None else np.random.default_rng(self.cfg.seed + 1)

    def detect(self, gt: GtProjection | None, width_px: int, height_px: int) -> list[BoundingBox]:
        cfg, rng = self.cfg, self.rng
        out: list[BoundingBox] = []
        if gt is not None and gt.box_px is not None:
            b = np.asarray(gt.box_px, dtype=float)
            h = b[3] - b[1]
            if h >= cfg.min_height_px and rng.random() >= cfg.box_miss_prob:
                std = cfg.box_noise_frac * h
                nb = b + rng.normal(0.0, std, size=4)
                nb = self._clip(nb, width_px, height_px)
                if nb is not None:
                    var = float(std * std)
                    score = float(np.clip(rng.normal(0.85, 0.07), 0.3, 1.0))
                    out.append(self._box(nb, score, var))
        for _ in range(int(rng.poisson(cfg.box_false_alarm_rate))):
            h = rng.uniform(10.0, max(0.3 * height_px, 11.0))
            w = h * rng.uniform(0.3, 0.6)
            x = rng.uniform(0.0, max(width_px - w, 1.0))
            y = rng.uniform(0.0, max(height_px - h, 1.0))
            nb = self._clip(np.array([x, y, x + w, y + h]), width_px, height_px)
            if nb is not None:
                std = 0.15 * h
                out.append(self._box(nb, float(rng.uniform(0.1, cfg.box_false_alarm_score_max)), float(std * std)))
        return out

    @staticmethod
    def _clip(b: np.ndarray, width_px: int, height_px: int) -> np.ndarray | None:
        x0, x1 = sorted((float(np.clip(b[0], 0, width_px)), float(np.clip(b[2], 0, width_px))))
        y0, y1 = sorted((float(np.clip(b[1], 0, height_px)), float(np.clip(b[3], 0, height_px))))
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:
            return None
        return np.array([x0, y0, x1, y1])

    @staticmethod
    def _box(b: np.ndarray, score: float, var: float) -> BoundingBox:
        return BoundingBox(
            x_min_px=float(b[0]), y_min_px=float(b[1]), x_max_px=float(b[2]), y_max_px=float(b[3]), score=score,
            var_x_min_px2=var, var_y_min_px2=var, var_x_max_px2=var, var_y_max_px2=var, label="person",
        )  # fmt: skip
