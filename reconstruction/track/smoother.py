"""Offline smoother over a whole recorded flight (AirCap's offline step 2), pure numpy/scipy.

The live cooperative filter (:mod:`onboard.tracking.filter`) runs on each drone, causally, with its own
GPS offset only. Offline, every drone's detections of the whole flight are available at once, so one
centralised estimate can use the future as well as the past and estimate every drone's offset jointly.

State (``n = 6 + 3 D`` for D drones): ``x = [p (3), v (3), b_1 (3), ..., b_D (3)]`` in NED metres -- the
person's centre position and velocity and each drone's position offset (its reported position minus its
true position). Process model, per axis, exactly discretised (the onboard filter's model):

* ``v``: Ornstein-Uhlenbeck with time constant ``velocity_tau_s`` and stationary std ``velocity_sigma_m_s``;
  ``p`` integrates ``v`` plus a small random walk (``position_process_var_m2_s``);
* ``b_d``: first-order Gauss-Markov with time constant ``offset_tau_s`` and stationary std
  ``offset_sigma_m[d]`` (per drone and axis: the drone's positioning grade, GPS ~1 m, RTK ~5 cm).

Measurement model: a detection by drone d, turned into a 3D point with the camera pose that drone reported
(:func:`onboard.tracking.measurement.measurement_from_box`), is ``z = p + J_d b_d + e`` with ``e`` of
covariance :attr:`PositionMeasurement.cov_no_cam_position_m2` (box edges, height/ground priors, camera
attitude) plus ``residual_position_var_m2`` (the white part of the position error). ``J_d`` (3, 3) is the
derivative of the measured point with respect to the reported camera position (:class:`Observation`): the
identity for the height-prior point (the camera centre plus a vector that depends on the rays only), not for
points put on the ground plane (a camera reported too high puts the feet too far away); the flight adapter
computes it by re-running the onboard geometry with the camera shifted.

The common component of the offsets is not observable: shifting the person and every drone by the same
vector changes no measurement. The offsets' zero-mean prior decides it (the estimate of the fleet-mean offset
stays near zero, its variance near ``offset_sigma_m**2 / D``): refined drone positions are right relative to
each other and to the person, and share the fleet's mean GPS error.

Why a Rauch-Tung-Striebel smoother (and not a sparse least-squares / factor graph): the model is linear and
Gaussian with Markov structure, for which the RTS recursion *is* the exact batch (MAP) solution, in
``O(N n^3)`` time and ``O(N n^2)`` memory with ``n <= 30`` for 8 drones (about 0.5 ms per step here; 2 x 7 kB
per step for 8 drones: a 20-minute flight of 8 drones at 10 Hz would need ~1.7 GB at once, of 3 drones ~0.2 GB); it
also gives the marginal covariances for free, which a sparse solve would need a separate (selected-inversion) step
for. Long flights are smoothed in overlapping segments (``segment_s`` = 60 s, ``segment_overlap_s`` = 20 s), so
the ``O(N n^2)`` arrays are those of one segment whatever the flight's length: each segment starts from the
previous one's forward prediction at its first step (the forward pass is that of the whole flight), runs on 20 s
past its end (what the backward pass sees of the future) and is cross-faded into the next over 10 s. On a 90 s
synthetic flight with GPS-grade offsets that changes the track by <= 3 mm (the offsets' 60 s correlation reaches
past the look-ahead); the frame choices are the same. Outliers are
handled by iteratively re-weighted smoothing (an M-estimator): every smoothing pass is followed by
re-weighting each detection by a Huber weight of its Mahalanobis residual against the smoothed state
(``huber_k``), rejecting those beyond the chi-square gate (``gate_probability``), and choosing, among the
boxes of one image, the one nearest the smoothed track; the first pass is a gated forward filter as onboard.
Libraries: ``filterpy`` offers the RTS recursion (~15 lines here) but assumes one measurement vector per step
with a fixed model, and ``gtsam`` (robust factor graph) is a large compiled dependency for a linear chain:
neither pays for itself here.

Units: times in ns (``t_ns``) in, seconds inside; positions in metres (NED).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np
from scipy.stats import chi2

from onboard.tracking.measurement import PositionMeasurement
from skycap.errors import SkycapError

__all__ = ["SmootherConfig", "SmootherError", "SmoothedTrack", "smooth_track", "Observation", "Frame", "group_frames",
           "observations_from_measurements"]

log = logging.getLogger(__name__)

NS = 1e-9
I3 = np.eye(3)


class SmootherError(SkycapError, ValueError):
    """Bad input or configuration of the offline smoother."""


@dataclasses.dataclass(frozen=True)
class SmootherConfig:
    """Model and robustness settings of :func:`smooth_track`."""

    velocity_tau_s: float = 3.0
    velocity_sigma_m_s: float = 1.5  #: stationary std of the person's velocity (walking to jogging)
    position_process_var_m2_s: float = 0.05  #: random walk on p (pose changes of the body centre)
    offset_tau_s: float = 60.0  #: correlation time of the GPS offset (the simulator's; AirCap onboard: 30 s)
    #: stationary std of each drone's offset per axis (n, e, d), metres (GPS grade); smooth_track's
    #: ``offset_sigma_m`` argument overrides it per drone (the flight adapter passes each drone's reported
    #: camera position std: its positioning grade)
    offset_sigma_m: tuple[float, float, float] = (1.0, 1.0, 0.5)
    residual_position_var_m2: float = 0.01  #: white position noise not captured by the offset state
    init_position_var_m2: float = 1e4
    gate_probability: float = 0.999  #: chi-square (3 dof) gate on the Mahalanobis residual
    huber_k: float = 3.0  #: Huber threshold on the Mahalanobis residual (sqrt of d^2), in sigmas
    max_iterations: int = 6  #: re-weighting passes after the first
    #: first pass: after this many gate rejections in a row the track is taken to be wrong (e.g. started on a
    #: false alarm) and re-initialised on the next frame, as onboard
    reinit_after_rejections: int = 6
    output_rate_hz: float = 20.0  #: regular output grid between the first and last measurement (0 = none)
    #: bounded memory and time per flight second: a flight longer than ``segment_s + segment_overlap_s`` is smoothed
    #: in segments of ``segment_s`` seconds, each run on to ``segment_overlap_s`` seconds past its end (the future
    #: that the backward pass sees) and started from the previous segment's forward prediction at its start (the
    #: whole past, exactly as the whole-flight forward pass); neighbours are cross-faded over the first half of the
    #: overlap. 0 = the whole flight at once (memory ~ 2 N n^2 floats for N steps).
    segment_s: float = 60.0
    segment_overlap_s: float = 20.0

    def __post_init__(self):
        for name in ("velocity_tau_s", "velocity_sigma_m_s", "offset_tau_s", "init_position_var_m2", "huber_k"):
            if not getattr(self, name) > 0:
                raise SmootherError(f"SmootherConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.gate_probability < 1:
            raise SmootherError(f"SmootherConfig.gate_probability must be in (0, 1), got {self.gate_probability}")
        if len(self.offset_sigma_m) != 3 or min(self.offset_sigma_m) <= 0:
            raise SmootherError(f"SmootherConfig.offset_sigma_m must be 3 positive stds (n, e, d), got {self.offset_sigma_m}")
        if self.max_iterations < 0 or self.output_rate_hz < 0:
            raise SmootherError("SmootherConfig.max_iterations and output_rate_hz must be >= 0")
        if self.segment_s < 0 or (self.segment_s > 0 and not self.segment_overlap_s > 0):
            raise SmootherError(f"SmootherConfig.segment_s must be >= 0 (0 = whole flight) and segment_overlap_s > 0 "
                                f"with segments, got {self.segment_s}, {self.segment_overlap_s}")


@dataclasses.dataclass(frozen=True)
class Observation:
    """One detection as the smoother uses it: ``z = p + J_offset b_drone + e``, ``e ~ N(0, R)``.

    t_ns: capture time; drone: index into the drone list; z_ned_m: (3,) measured person centre;
    R_m2: (3, 3) noise covariance without the camera position part; J_offset: (3, 3) derivative of z with
    respect to the reported camera position; score: detector confidence (picks the first-pass start).
    """

    t_ns: int
    drone: int
    z_ned_m: np.ndarray
    R_m2: np.ndarray
    J_offset: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    score: float = 1.0

    @classmethod
    def from_measurement(cls, m: PositionMeasurement, drone: int, J_offset: np.ndarray | None = None) -> "Observation":
        """From an onboard :class:`PositionMeasurement` (``cov_no_cam_position_m2`` is the noise)."""
        return cls(int(m.t_ns), int(drone), np.asarray(m.position_ned_m, dtype=float),
                   np.asarray(m.cov_no_cam_position_m2, dtype=float), np.eye(3) if J_offset is None else np.asarray(J_offset, dtype=float),
                   float(m.score))  # fmt: skip

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.z_ned_m)) and np.all(np.isfinite(self.R_m2)) and np.all(np.isfinite(self.J_offset)))


@dataclasses.dataclass
class Frame:
    """The observations of one image: alternatives (several person boxes), of which at most one is used."""

    t_ns: int
    drone: int
    alternatives: list[Observation]


def group_frames(observations: Sequence[Observation]) -> list[Frame]:
    """Observations -> frames (one per (drone, t_ns)), time-ordered; non-finite ones are dropped."""
    frames: dict[tuple[int, int], Frame] = {}
    for o in observations:
        if not o.is_finite():
            continue
        key = (int(o.t_ns), int(o.drone))
        frames.setdefault(key, Frame(key[0], key[1], [])).alternatives.append(o)
    return [frames[k] for k in sorted(frames)]


def observations_from_measurements(measurements: Sequence[PositionMeasurement], drone_ids: Sequence[str]) -> list[Observation]:
    """PositionMeasurements (``source_id`` in ``drone_ids``) -> Observations with ``J_offset = I`` (exact for
    the height-prior and range-hint models)."""
    index = {d: i for i, d in enumerate(drone_ids)}
    out = []
    for m in measurements:
        if m.source_id not in index:
            raise SmootherError(f"measurement from {m.source_id!r}, which is not among the drones {list(drone_ids)}")
        out.append(Observation.from_measurement(m, index[m.source_id]))
    return out


@dataclasses.dataclass
class SmoothedTrack:
    """Result of :func:`smooth_track` at the step times ``t_ns`` (N,) (measurement times and output grid).

    position_ned_m, velocity_ned_m_s: (N, 3); covariance: (N, 6, 6) over (p, v); offset_ned_m: (N, D, 3);
    offset_cov_m2: (N, D, 3, 3); filtered_position_ned_m: (N, 3) the causal (forward) pass of the last
    iteration, for comparison; on_grid: (N,) bool, steps of the regular output grid.
    Per frame (F, in the order of ``frames``): frame_t_ns, frame_drone (F,), frame_choice (F,) index of the
    alternative used (-1 = rejected), frame_weight (F,) Huber weight, frame_d2 (F,) Mahalanobis residual^2.
    """

    drone_ids: list[str]
    t_ns: np.ndarray
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    covariance: np.ndarray
    offset_ned_m: np.ndarray
    offset_cov_m2: np.ndarray
    filtered_position_ned_m: np.ndarray
    on_grid: np.ndarray
    frame_t_ns: np.ndarray
    frame_drone: np.ndarray
    frame_choice: np.ndarray
    frame_weight: np.ndarray
    frame_d2: np.ndarray
    iterations: int
    offset_sigma_m: np.ndarray  #: (D, 3) the offset priors used
    segments: int = 1  #: runs of the smoother (:attr:`SmootherConfig.segment_s`)

    def position_at(self, t_ns: np.ndarray) -> np.ndarray:
        """Smoothed person position (M, 3) at times t_ns (M,), linear interpolation (held at the ends)."""
        return _interp(np.asarray(t_ns), self.t_ns, self.position_ned_m)

    def offset_at(self, drone: int, t_ns: np.ndarray) -> np.ndarray:
        """Smoothed offset of drone index ``drone`` (M, 3) at times t_ns (M,), held at the ends."""
        return _interp(np.asarray(t_ns), self.t_ns, self.offset_ned_m[:, drone])

    @property
    def accepted(self) -> np.ndarray:
        return self.frame_choice >= 0


def _interp(tq: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
    tq = (tq.astype(np.int64) - t[0]).astype(float)
    tt = (t - t[0]).astype(float)
    return np.stack([np.interp(tq, tt, rows[:, i]) for i in range(rows.shape[1])], axis=-1)


class _Model:
    """Transition (F, Q) for a step of dt seconds; F is block structured, built densely (n <= 30).

    Memoised per ``dt_s``: the grid's steps repeat a handful of values and every pass of the smoother (forward,
    backward, each reweighting) asks for them again; the cached matrices are read-only (the passes never write
    them), so the results are bit-identical to building them each time."""

    def __init__(self, cfg: SmootherConfig, offset_sigma_m: np.ndarray):
        self.cfg = cfg
        self.sig_b = offset_sigma_m  # (D, 3)
        self.D = offset_sigma_m.shape[0]
        self.n = 6 + 3 * self.D
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        dt_s = float(dt_s)
        hit = self._cache.get(dt_s)
        if hit is None:
            hit = self._build(dt_s)
            for m in hit:
                m.flags.writeable = False
            if len(self._cache) < 4096:  # bounded: irregular steps (dropped frames) must not grow it forever
                self._cache[dt_s] = hit
        return hit

    def _build(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        c = self.cfg
        n = self.n
        F = np.eye(n)
        Q = np.zeros((n, n))
        if dt_s <= 0:
            return F, Q
        a = 1.0 / c.velocity_tau_s
        e = math.exp(-a * dt_s)
        q = 2.0 * c.velocity_sigma_m_s**2 / c.velocity_tau_s
        Phi = np.array([[1.0, (1.0 - e) / a], [0.0, e]])
        q_pp = q / a**2 * (dt_s - 2.0 * (1.0 - e) / a + (1.0 - e * e) / (2.0 * a)) + c.position_process_var_m2_s * dt_s
        q_pv = q / (2.0 * a**2) * (1.0 - e) ** 2
        q_vv = q / (2.0 * a) * (1.0 - e * e)
        F[:6, :6] = np.kron(Phi, I3)
        Q[:6, :6] = np.kron(np.array([[q_pp, q_pv], [q_pv, q_vv]]), I3)
        eb = math.exp(-dt_s / c.offset_tau_s)
        idx = np.arange(6, n)
        F[idx, idx] = eb
        Q[idx, idx] = (self.sig_b.reshape(-1) ** 2) * (1.0 - eb * eb)
        return F, Q


def _frame_HR(fr: Frame, alt: int, n: int, cfg: SmootherConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    o = fr.alternatives[alt]
    H = np.zeros((3, n))
    H[:, :3] = I3
    H[:, 6 + 3 * fr.drone: 9 + 3 * fr.drone] = o.J_offset
    R = o.R_m2 + cfg.residual_position_var_m2 * I3
    return H, 0.5 * (R + R.T), o.z_ned_m


def smooth_track(
    observations: Sequence[Observation] | Sequence[PositionMeasurement],
    drone_ids: Sequence[str],
    config: SmootherConfig = SmootherConfig(),
    offset_sigma_m: np.ndarray | None = None,
    extra_times_ns: np.ndarray | None = None,
) -> SmoothedTrack:
    """Robust RTS smoother over all drones' detections of a flight (see the module doc).

    Args:
        observations: :class:`Observation` s of every drone (any order; several at the same (drone, time) are
            alternatives of one image), or onboard PositionMeasurements (``source_id`` in ``drone_ids``,
            ``J_offset = I``).
        drone_ids: the D drones whose offsets are estimated (Observation.drone indexes this list).
        config: :class:`SmootherConfig`.
        offset_sigma_m: (D, 3) or (3,) stationary std of the offsets per drone and axis; None = config's.
        extra_times_ns: (M,) further times at which to output the state (clipped to the measurement span).

    Returns:
        :class:`SmoothedTrack`.
    """
    drone_ids = list(drone_ids)
    if not drone_ids:
        raise SmootherError("smooth_track needs at least one drone id")
    obs = list(observations)
    if obs and isinstance(obs[0], PositionMeasurement):
        obs = observations_from_measurements(obs, drone_ids)
    if any(not 0 <= o.drone < len(drone_ids) for o in obs):
        raise SmootherError(f"an observation's drone index is outside the {len(drone_ids)} drone ids")
    frames = group_frames(obs)
    if len(frames) < 2:
        raise SmootherError(f"smooth_track needs detections in at least 2 frames, got {len(frames)}: did the drones see the person?")
    frames.sort(key=lambda f: (f.t_ns, f.drone))
    D = len(drone_ids)
    sig_b = np.asarray(config.offset_sigma_m if offset_sigma_m is None else offset_sigma_m, dtype=float)
    sig_b = np.broadcast_to(sig_b, (D, 3)).copy() if sig_b.shape in ((3,), (D, 3)) else None
    if sig_b is None or not np.all(sig_b > 0):
        raise SmootherError(f"offset_sigma_m must be positive, shape (3,) or ({D}, 3)")
    model = _Model(config, sig_b)
    n = model.n
    t0, t1 = frames[0].t_ns, frames[-1].t_ns
    times = {f.t_ns for f in frames}
    grid = np.zeros(0, dtype=np.int64)
    if config.output_rate_hz > 0:
        grid = np.arange(t0, t1 + 1, int(round(1e9 / config.output_rate_hz)), dtype=np.int64)
    extra = np.zeros(0, dtype=np.int64) if extra_times_ns is None else np.asarray(extra_times_ns, dtype=np.int64)
    extra = extra[(extra >= t0) & (extra <= t1)]
    t_steps = np.array(sorted(times | set(grid.tolist()) | set(extra.tolist())), dtype=np.int64)
    step_of = {int(t): i for i, t in enumerate(t_steps)}
    frames_at: list[list[int]] = [[] for _ in t_steps]
    for j, f in enumerate(frames):
        frames_at[step_of[f.t_ns]].append(j)
    on_grid = np.isin(t_steps, grid)
    gate_d2 = float(chi2.ppf(config.gate_probability, 3))
    x0 = np.zeros(n)
    x0[:3] = frames[0].alternatives[int(np.argmax([o.score for o in frames[0].alternatives]))].z_ned_m
    P0 = np.zeros((n, n))
    P0[:3, :3] = config.init_position_var_m2 * I3
    P0[3:6, 3:6] = config.velocity_sigma_m_s**2 * I3
    P0[6:, 6:] = np.diag(sig_b.reshape(-1) ** 2)
    frame_t = np.array([f.t_ns for f in frames], dtype=np.int64)
    seg_ns = int(round(config.segment_s * 1e9))
    ovl_ns = int(round(config.segment_overlap_s * 1e9))
    N, F = len(t_steps), len(frames)
    out = {"pos": np.zeros((N, 3)), "vel": np.zeros((N, 3)), "cov": np.zeros((N, 6, 6)), "off": np.zeros((N, D, 3)),
           "off_cov": np.zeros((N, D, 3, 3)), "fpos": np.zeros((N, 3))}
    choice_all, weight_all, d2_all = np.full(F, -1), np.zeros(F), np.full(F, np.nan)
    starts = [t0] if seg_ns <= 0 or t1 - t0 <= seg_ns + ovl_ns else list(range(t0, t1 + 1, seg_ns))
    fade_ns = ovl_ns // 2
    prev = None  # (step indices, results) of the previous segment over the cross-fade
    iterations = 0
    for k, s0 in enumerate(starts):
        own_end = starts[k + 1] if k + 1 < len(starts) else t1 + 1  # owned: [s0, own_end)
        run_end = own_end + ovl_ns if k + 1 < len(starts) else t1 + 1
        i0, i1 = int(np.searchsorted(t_steps, s0)), int(np.searchsorted(t_steps, run_end))
        j0, j1 = int(np.searchsorted(frame_t, s0)), int(np.searchsorted(frame_t, run_end))
        seg_frames = frames[j0:j1]
        seg_at = [[j - j0 for j in fr if j0 <= j < j1] for fr in frames_at[i0:i1]]
        xs, Ps, xf, choice, weight, d2, it, x_pred, P_pred = _smooth_run(t_steps[i0:i1], seg_frames, seg_at, model,
                                                                          x0, P0, config, gate_d2)
        iterations = max(iterations, it)
        o1, f1 = int(np.searchsorted(t_steps, own_end)), int(np.searchsorted(frame_t, own_end))
        sl, ls = slice(i0, o1), slice(0, o1 - i0)
        rows = {"pos": xs[:, :3], "vel": xs[:, 3:6], "cov": Ps[:, :6, :6], "off": xs[:, 6:].reshape(-1, D, 3),
                "off_cov": np.stack([Ps[:, 6 + 3 * d: 9 + 3 * d, 6 + 3 * d: 9 + 3 * d] for d in range(D)], axis=1),
                "fpos": xf[:, :3]}
        for key, v in rows.items():
            out[key][sl] = v[ls]
        if prev is not None:  # cross-fade from the previous segment over [s0, s0 + fade)
            idx, pv = prev
            w = ((t_steps[idx] - s0) / max(fade_ns, 1)).clip(0.0, 1.0)
            for key, v in pv.items():
                ww = w.reshape((-1,) + (1,) * (v.ndim - 1))
                out[key][idx] = (1.0 - ww) * v + ww * out[key][idx]
        choice_all[j0:f1], weight_all[j0:f1], d2_all[j0:f1] = choice[:f1 - j0], weight[:f1 - j0], d2[:f1 - j0]
        if k + 1 < len(starts):
            nxt = starts[k + 1]
            idx = np.arange(o1, int(np.searchsorted(t_steps, nxt + fade_ns)))
            idx = idx[idx < i1]
            prev = (idx, {key: v[idx - i0].copy() for key, v in rows.items()})
            # the next segment starts from this one's forward prediction at its first step (the whole past)
            x0, P0 = x_pred[o1 - i0].copy(), P_pred[o1 - i0].copy()
        del xs, Ps, xf, x_pred, P_pred, rows
    acc = choice_all >= 0
    log.info("smoother: %d steps, %d frames (%d used, %d rejected), %d drones, %d segment(s), %d re-weighting passes "
             "(most of a segment)", N, F, int(acc.sum()), int((~acc).sum()), D, len(starts), iterations)
    return SmoothedTrack(
        drone_ids=drone_ids, t_ns=t_steps, position_ned_m=out["pos"], velocity_ned_m_s=out["vel"], covariance=out["cov"],
        offset_ned_m=out["off"], offset_cov_m2=out["off_cov"], filtered_position_ned_m=out["fpos"], on_grid=on_grid,
        frame_t_ns=frame_t, frame_drone=np.array([f.drone for f in frames]), frame_choice=choice_all,
        frame_weight=np.where(acc, weight_all, 0.0), frame_d2=d2_all, iterations=iterations, offset_sigma_m=sig_b,
        segments=len(starts),
    )  # fmt: skip


def _smooth_run(t_steps, frames, frames_at, model, x0, P0, config, gate_d2):
    """The robust smoother over one run of steps (the whole flight or a segment) from the prior (x0, P0) at its
    first step: a gated forward pass, then re-weighted passes until the choices and weights settle. Returns
    (xs, Ps, x_f, choice, weight, d2, passes, x_pred, P_pred) of the last pass."""
    step_of = {int(t): i for i, t in enumerate(t_steps)}
    n = model.n
    P_init = np.zeros((n, n))  # what the first pass re-initialises the person's state with
    P_init[:3, :3] = config.init_position_var_m2 * I3
    P_init[3:6, 3:6] = config.velocity_sigma_m_s**2 * I3
    choice = np.full(len(frames), -2)  # -2 = decide in the forward pass
    weight = np.ones(len(frames))
    it = 0
    while True:
        xs, Ps, xf, d2_out, x_pred, P_pred = _rts(t_steps, frames, frames_at, choice, weight, model, x0, P0, P_init,
                                                  config, gate_d2)
        new_choice, new_weight, d2 = _reweight(frames, xs, Ps, step_of, n, config, gate_d2)
        if it > 0:
            changed = bool(len(frames)) and (np.any(new_choice != choice) or np.max(np.abs(new_weight - weight)) > 1e-3)
        else:
            changed = True
        if it >= config.max_iterations or not changed:
            break
        choice, weight = new_choice, new_weight
        it += 1
    if it >= config.max_iterations and changed:
        log.info("smoother: re-weighting stopped after %d passes without full convergence", it)
    return xs, Ps, xf, choice, weight, d2, it, x_pred, P_pred


def _rts(t_steps, frames, frames_at, choice, weight, model, x0, P0, P_init, cfg, gate_d2):
    """One forward filter + RTS backward pass. ``choice`` -2 entries are decided (gated) in place."""
    N, n = len(t_steps), model.n
    x_pred = np.zeros((N, n))
    P_pred = np.zeros((N, n, n))
    x_f = np.zeros((N, n))
    P_f = np.zeros((N, n, n))  # becomes the smoothed covariance in place (memory: 2 N n^2 floats)
    d2_out = np.full(len(frames), np.nan)
    x, P = x0, P0
    rejections = reinits = 0
    for k in range(N):
        dt = 0.0 if k == 0 else (t_steps[k] - t_steps[k - 1]) * NS
        F, Q = model(dt)
        if k > 0:
            x = F @ x
            P = F @ P @ F.T + Q
        x_pred[k], P_pred[k] = x, P
        for j in frames_at[k]:
            fr = frames[j]
            if choice[j] == -2:  # first pass: the gated alternative nearest the prediction
                if rejections >= cfg.reinit_after_rejections:
                    # the track disagrees with everything for a while: forget the person's state, keep the offsets
                    a = int(np.argmax([o.score for o in fr.alternatives]))
                    x = x.copy()
                    x[:3] = fr.alternatives[a].z_ned_m - fr.alternatives[a].J_offset @ x[6 + 3 * fr.drone: 9 + 3 * fr.drone]
                    x[3:6] = 0.0
                    P = P.copy()
                    P[:6, :] = 0.0
                    P[:, :6] = 0.0
                    P[:6, :6] = P_init[:6, :6]
                    rejections = 0
                    reinits += 1
                best = None
                for a in range(len(fr.alternatives)):
                    H, R, z = _frame_HR(fr, a, n, cfg)
                    y = z - H @ x
                    S = H @ P @ H.T + R
                    d2 = float(y @ np.linalg.solve(S, y))
                    if d2 <= gate_d2 and (best is None or d2 < best[1]):
                        best = (a, d2)
                choice[j] = -1 if best is None else best[0]
                rejections = rejections + 1 if best is None else 0
                if best is not None:
                    d2_out[j] = best[1]
            if choice[j] < 0 or weight[j] <= 0:
                continue
            H, R, z = _frame_HR(fr, int(choice[j]), n, cfg)
            R = R / weight[j]
            S = H @ P @ H.T + R
            K = np.linalg.solve(0.5 * (S + S.T), H @ P).T  # S symmetric: (S^-1 H P)^T = P H^T S^-1
            x = x + K @ (z - H @ x)
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K @ R @ K.T
            P = 0.5 * (P + P.T)
        x_f[k], P_f[k] = x, P
    xs = x_f.copy()
    Ps = P_f  # overwritten from the end: Ps[k + 1] is smoothed when step k is
    eps = 1e-12 * np.eye(n)
    for k in range(N - 2, -1, -1):
        Pp = P_pred[k + 1]
        F, _ = model((t_steps[k + 1] - t_steps[k]) * NS)
        C = np.linalg.solve(Pp + eps, F @ P_f[k]).T  # P_f F^T Pp^-1
        xs[k] = x_f[k] + C @ (xs[k + 1] - x_pred[k + 1])
        Pk = P_f[k] + C @ (Ps[k + 1] - Pp) @ C.T
        Ps[k] = 0.5 * (Pk + Pk.T)
    if reinits:
        log.info("smoother: first pass re-initialised the person track %d time(s)", reinits)
    return xs, Ps, x_f, d2_out, x_pred, P_pred


def _reweight(frames, xs, Ps, step_of, n, cfg, gate_d2):
    """Per frame: the alternative nearest the smoothed state, its Huber weight, rejection beyond the gate."""
    choice = np.full(len(frames), -1)
    weight = np.zeros(len(frames))
    d2s = np.full(len(frames), np.nan)
    for j, fr in enumerate(frames):
        k = step_of[fr.t_ns]
        best = None
        for a in range(len(fr.alternatives)):
            H, R, z = _frame_HR(fr, a, n, cfg)
            y = z - H @ xs[k]
            # gate against the residual's own spread (state uncertainty + noise); weight against the noise
            S = H @ Ps[k] @ H.T + R
            d2_gate = float(y @ np.linalg.solve(S, y))
            if best is None or d2_gate < best[1]:
                best = (a, d2_gate, float(y @ np.linalg.solve(R, y)))
        a, d2_gate, d2_R = best
        d2s[j] = d2_gate
        if d2_gate > gate_d2:
            continue
        choice[j] = a
        d = math.sqrt(max(d2_R, 0.0))
        weight[j] = 1.0 if d <= cfg.huber_k else cfg.huber_k / d
    return choice, weight, d2s
