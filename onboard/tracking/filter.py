"""Cooperative detection-and-tracking (CDT) filter: one per drone, pure numpy.

State ``x = [p (3), v (3), b_self (3), b_1 (3), ..., b_k (3)]`` in NED metres — the person's centre position
``p`` and velocity ``v``, this drone's own position offset ``b_self`` (its reported/GPS position minus its true
position; always ``x[6:9]``) and, with ``fleet_offsets`` (default), one offset per teammate heard from, added
when its first detection arrives (9 states for one drone, 6 + 3 N for a fleet of N).

Measurement models:

* **own detection** (source == ``self_id``): the measurement is computed from the camera pose reported by
  this drone, whose position is ``true + b_self``, so ``z = p + b_self + noise``: ``H = [I 0 I 0 ...]`` (exact
  for the height prior, whose point moves with the camera; with the feet-on-the-ground term a camera *height*
  error slides the point along the ray instead -- using that exact sensitivity made the vertical offsets
  swing by metres during take-off, where the ray is near the horizon, so the identity is kept; the slide is
  measurement noise instead, and each drone gives the ground in its own reported frame, its take-off ground,
  so that only the height drift since take-off slides the point), noise covariance
  :attr:`PositionMeasurement.cov_no_cam_position_m2` (the camera-position part the offset explains is the
  state) plus ``self_residual_position_var_m2`` (the white part of the GPS error).
* **teammate j's detection**: ``z = p + b_j + noise``, the same model with ``b_j``'s block. (AirCap's filter
  kept only ``b_self`` and treated ``b_j`` as white noise (``fleet_offsets=False``: ``H = [I 0 0]``, covariance
  :attr:`PositionMeasurement.cov_m2`); but a GPS bias is slow, so averaging a teammate's detections over time
  does not average its bias away: that filter places the person in the mean frame of the *teammates* and each
  drone ends up with a different estimate. With every offset a state and all of them zero-mean a priori, every
  drone's filter places the person in the mean frame of the whole fleet (the common part of the biases is
  unobservable without an absolute reference), the drones agree, and each offset is estimated relative to it.)

Process model: ``v`` is a first-order Gauss-Markov (Ornstein-Uhlenbeck) process with time constant
``velocity_tau_s`` (~3 s) and stationary std ``velocity_sigma_m_s``; ``p`` integrates ``v``; ``b`` is
Gauss-Markov with ``offset_tau_s`` (~30 s) and stationary std ``offset_sigma_m``. Discretisation is exact
(closed-form integrated Ornstein-Uhlenbeck process noise).

Late and out-of-order measurements: every processed measurement is kept in a time-ordered buffer of
``buffer_size`` (~40) entries with the filter state before it; a measurement older than the newest is
inserted in time order and the filter is re-run from the entry before it (re-filtering). One older than
the whole buffer is dropped (counted ``too_late``).

Robustness: non-finite measurements are ignored (``rejected_nonfinite``); measurements whose normalised
innovation squared exceeds the chi-square quantile ``gate_probability`` (3 dof) are rejected
(``rejected_gate``); after ``max_consecutive_rejections`` rejections in a row the track is considered
wrong and re-initialised from the newest measurement; after ``reset_after_s`` (10 s) without an accepted
measurement the filter resets and the next measurement re-acquires.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from typing import Literal

import numpy as np
from scipy.stats import chi2

from onboard.tracking.measurement import PositionMeasurement
from shared_msgs.messages import TargetEstimate
from skycap.errors import SkycapError

__all__ = ["TrackerConfig", "TrackEstimate", "CooperativeFilter", "FilterStats", "TrackerError"]

log = logging.getLogger(__name__)

NS = 1e-9
I3 = np.eye(3)
TrackStatus = Literal["tracking", "predicting", "lost"]


class TrackerError(SkycapError, ValueError):
    """Bad configuration or use of the cooperative filter."""


@dataclasses.dataclass(frozen=True)
class TrackerConfig:
    velocity_tau_s: float = 3.0
    velocity_sigma_m_s: float = 1.5  #: stationary std of the person's velocity (walking to jogging)
    offset_tau_s: float = 30.0
    offset_sigma_m: float = 2.0  #: stationary std of the GPS offset
    self_residual_position_var_m2: float = 0.05  #: white GPS noise not captured by the offset state
    position_process_var_m2_s: float = 0.05  #: small random walk on p (pose changes of the body centre)
    init_position_var_m2: float = 1e4  #: prior on p when (re-)initialising from a measurement
    init_velocity_var_m2_s2: float | None = None  #: None = velocity_sigma_m_s ** 2
    buffer_size: int = 40  #: must cover (largest latency) x (total detection rate of the fleet): 40 = 1.25 s at 8 x 4 Hz
    gate_probability: float = 0.999  #: chi-square (3 dof) gate; 0.999 -> d^2 < 16.27
    max_consecutive_rejections: int = 12
    reset_after_s: float = 10.0
    predicting_after_s: float = 1.0  #: status "predicting" when the newest accepted measurement is older
    source_window_s: float = 3.0  #: a teammate counts as a source if it contributed within this window
    estimate_offset: bool = True  #: False: 6-state filter behaviour (own detections as H_other)
    fleet_offsets: bool = True  #: a GPS-offset state per teammate too (False: AirCap's 9 states, see the module doc)

    def __post_init__(self):
        for name in ("velocity_tau_s", "offset_tau_s", "reset_after_s", "velocity_sigma_m_s", "offset_sigma_m"):
            if not getattr(self, name) > 0:
                raise TrackerError(f"TrackerConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.buffer_size < 2:
            raise TrackerError(f"TrackerConfig.buffer_size must be >= 2, got {self.buffer_size}")
        if not 0 < self.gate_probability < 1:
            raise TrackerError(f"TrackerConfig.gate_probability must be in (0, 1), got {self.gate_probability}")


@dataclasses.dataclass
class FilterStats:
    accepted: int = 0
    rejected_gate: int = 0
    rejected_nonfinite: int = 0
    too_late: int = 0
    refiltered: int = 0  #: out-of-order insertions that re-ran the filter
    resets: int = 0  #: resets after reset_after_s without data
    reinitialisations: int = 0  #: after max_consecutive_rejections


@dataclasses.dataclass(frozen=True)
class TrackEstimate:
    """The filter's estimate at ``t_ns``.

    position_ned_m, velocity_ned_m_s, offset_ned_m: (3,); covariance: (6, 6) over (p, v);
    offset_cov_m2: (3, 3); position_offset_cov_m2: (3, 3) cross-covariance of p and the own offset (they are
    strongly correlated: with every drone's offset a state, p's common-mode uncertainty is shared with b).
    """

    t_ns: int
    position_ned_m: np.ndarray
    velocity_ned_m_s: np.ndarray
    covariance: np.ndarray
    offset_ned_m: np.ndarray
    offset_cov_m2: np.ndarray
    status: TrackStatus
    num_sources: int
    t_last_measurement_ns: int
    position_offset_cov_m2: np.ndarray | None = None
    velocity_offset_cov: np.ndarray | None = None  #: (3, 3) cross-covariance of v and the own offset

    def in_reported_frame(self) -> "TrackEstimate":
        """The estimate in this drone's reported (GPS) frame, in which its own camera pose is given: person at
        p + b, position covariance cov(p) + cov(b) + cov(p, b) + cov(b, p)."""
        cov = self.covariance.copy()
        C = np.zeros((3, 3)) if self.position_offset_cov_m2 is None else self.position_offset_cov_m2
        cov[:3, :3] = cov[:3, :3] + self.offset_cov_m2 + C + C.T
        cov[:3, 3:6] = cov[:3, 3:6] + (np.zeros((3, 3)) if self.velocity_offset_cov is None else self.velocity_offset_cov)
        cov[3:6, :3] = cov[:3, 3:6].T
        return dataclasses.replace(self, position_ned_m=self.position_ned_m + self.offset_ned_m, covariance=cov)

    def to_message(self, sender_id: str, seq: int = 0) -> TargetEstimate:
        """As a :class:`shared_msgs.messages.TargetEstimate` (header time = estimate time)."""
        return TargetEstimate(
            header=TargetEstimate.make_header(sender_id, self.t_ns, seq),
            position_ned_m=tuple(float(x) for x in self.position_ned_m),
            velocity_ned_m_s=tuple(float(x) for x in self.velocity_ned_m_s),
            covariance=tuple(float(x) for x in self.covariance.reshape(-1)),
            status=self.status,
            num_sources=int(self.num_sources),
        )

    def corrected_self_position(self, reported_position_ned_m: np.ndarray) -> np.ndarray:
        """This drone's position corrected by the estimated offset: reported - b."""
        return np.asarray(reported_position_ned_m, dtype=float) - self.offset_ned_m


@dataclasses.dataclass
class _Entry:
    t_ns: int
    order: int
    meas: tuple[PositionMeasurement, ...]  #: alternatives of one frame (best gated one is used)
    x_before: np.ndarray | None = None
    P_before: np.ndarray | None = None
    t_before_ns: int | None = None
    consec_before: int = 0
    accepted: bool = False


class CooperativeFilter:
    """The CDT filter of one drone (``self_id``); see the module doc.

    Use: ``add(measurement)`` (or ``add_frame(alternatives)`` for the boxes of one image) in any order as
    detections arrive from this drone and its teammates; ``estimate(t_ns)`` for the prediction at any time
    at or after the newest measurement (it does not change the filter).
    """

    def __init__(self, self_id: str, config: TrackerConfig = TrackerConfig()):
        self.self_id = self_id
        self.cfg = config
        self.stats = FilterStats()
        self._gate_d2 = float(chi2.ppf(config.gate_probability, 3))
        self._order = 0
        self._model_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._clear()

    # ------------------------------------------------------------------ state
    def _clear(self) -> None:
        self._x: np.ndarray | None = None
        self._P: np.ndarray | None = None
        self._t_ns: int | None = None
        self._consec_rejections = 0
        self._buffer: list[_Entry] = []
        self._last_seen_ns: dict[str, int] = {}
        self._t_last_accepted_ns: int | None = None
        self._offset_ids: list[str] = [self.self_id]  #: whose offset each 3-block from x[6:] is
        #: stationary variance (3,) of each offset: own = offset_sigma_m^2, a teammate's = the camera position
        #: variance it reports with its detections (its positioning grade), else offset_sigma_m^2
        self._offset_var: list[np.ndarray] = [np.full(3, self.cfg.offset_sigma_m**2)]

    @property
    def offset_ids(self) -> list[str]:
        """The drones whose position offsets are states, in state order (self first)."""
        return list(self._offset_ids)

    def _offset_index(self, m: PositionMeasurement) -> int | None:
        """State index of m's sender's offset block (adding the block for a new teammate); None = not a state."""
        if not self.cfg.estimate_offset:
            return None
        if m.source_id == self.self_id:
            return 6
        if not self.cfg.fleet_offsets:
            return None
        if m.source_id not in self._offset_ids:
            self._offset_ids.append(m.source_id)
            var = np.full(3, self.cfg.offset_sigma_m**2)
            c = m.camera_position_cov_m2
            if c is not None and np.all(np.isfinite(np.diag(c))) and np.all(np.diag(c) > 0):
                var = np.diag(c).astype(float).copy()
            self._offset_var.append(var)
        return 6 + 3 * self._offset_ids.index(m.source_id)

    def set_own_offset_variance(self, var_m2) -> None:
        """The own offset's stationary variance (3,) m^2 (north, east, down): this drone's reported positioning
        grade (e.g. the receiver's accuracy), replacing ``offset_sigma_m^2``. Used from the next prediction on."""
        v = np.asarray(var_m2, dtype=float).reshape(3)
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise TrackerError(f"set_own_offset_variance: need 3 finite variances > 0 (m^2), got {var_m2!r}")
        self._offset_var[0] = v.copy()

    def _offset_var_vec(self, n: int) -> np.ndarray:
        return np.concatenate(self._offset_var)[: n - 6]

    def _padded(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x, P grown to the current number of offset states (a new teammate's offset: its prior, independent)."""
        n = 6 + 3 * len(self._offset_ids)
        if len(x) == n:
            return x, P
        x2 = np.zeros(n)
        x2[: len(x)] = x
        P2 = np.diag(np.concatenate([np.zeros(6), self._offset_var_vec(n)]))
        P2[: len(x), : len(x)] = P
        return x2, P2

    @property
    def initialised(self) -> bool:
        return self._x is not None

    @property
    def state(self) -> tuple[np.ndarray, np.ndarray, int] | None:
        """(x (n,), P (n, n), t_ns) after the newest processed measurement, or None; n = 6 + 3 x offsets
        (:attr:`offset_ids`), own offset at x[6:9]."""
        if self._x is None:
            return None
        return self._x.copy(), self._P.copy(), int(self._t_ns)

    def reset(self) -> None:
        """Forget the track (re-acquire from the next measurement)."""
        self._clear()

    # ------------------------------------------------------------------ model
    def _transition(self, dt_s: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(F (n, n), Q (n, n)) for a step of dt_s seconds, n = 6 + 3 x offsets (cached per microsecond)."""
        key = (int(round(dt_s * 1e6)), n)
        hit = self._model_cache.get(key)
        if hit is not None:
            F, Q, eb = hit
            Q = Q.copy()
            Q[6:, 6:] = np.diag(self._offset_var_vec(n) * (1.0 - eb * eb))
            return F, Q
        c = self.cfg
        tv, tb = c.velocity_tau_s, c.offset_tau_s
        # per axis: p' = v + w_p, v' = -v / tv + w_v, E[w_v w_v] = q = 2 sigma^2 / tv (exact discretisation)
        a = 1.0 / tv
        e = np.exp(-a * dt_s)
        q = 2.0 * c.velocity_sigma_m_s**2 / tv
        Phi = np.array([[1.0, (1.0 - e) / a], [0.0, e]])
        q_pp = q / a**2 * (dt_s - 2.0 * (1.0 - e) / a + (1.0 - e * e) / (2.0 * a)) + c.position_process_var_m2_s * dt_s
        q_pv = q / (2.0 * a**2) * (1.0 - e) ** 2
        q_vv = q / (2.0 * a) * (1.0 - e * e)
        Qd = np.array([[q_pp, q_pv], [q_pv, q_vv]])
        F = np.zeros((n, n))
        Q = np.zeros((n, n))
        F[:6, :6] = np.kron(Phi, I3)
        Q[:6, :6] = np.kron(Qd, I3)
        eb = np.exp(-dt_s / tb)
        F[6:, 6:] = eb * np.eye(n - 6)
        if len(self._model_cache) > 4096:
            self._model_cache.clear()
        self._model_cache[key] = (F, Q, eb)
        Q = Q.copy()
        Q[6:, 6:] = np.diag(self._offset_var_vec(n) * (1.0 - eb * eb))
        return F, Q

    def _predict(self, x: np.ndarray, P: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        if dt_s <= 0:
            return x, P
        F, Q = self._transition(dt_s, len(x))
        return F @ x, F @ P @ F.T + Q

    def _H_R(self, m: PositionMeasurement, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Measurement matrix (3, n) and noise (3, 3) of m; the offset block must exist (see _offset_index)."""
        H = np.zeros((3, n))
        H[:, :3] = I3
        k = self._offset_index(m)
        if k is not None:
            H[:, k : k + 3] = I3
            R = m.cov_no_cam_position_m2 + self.cfg.self_residual_position_var_m2 * I3
        else:
            R = m.cov_m2
        return H, R

    def _init_from(self, m: PositionMeasurement) -> tuple[np.ndarray, np.ndarray]:
        c = self.cfg
        self._offset_index(m)
        n = 6 + 3 * len(self._offset_ids)
        x = np.zeros(n)
        x[:3] = m.position_ned_m
        P = np.zeros((n, n))
        P[:3, :3] = c.init_position_var_m2 * I3
        vv = c.velocity_sigma_m_s**2 if c.init_velocity_var_m2_s2 is None else c.init_velocity_var_m2_s2
        P[3:6, 3:6] = vv * I3
        P[6:, 6:] = np.diag(self._offset_var_vec(n))
        H, R = self._H_R(m, n)
        return self._kalman(x, P, H, R, m.position_ned_m)[:2]

    @staticmethod
    def _kalman(x, P, H, R, z):
        y = z - H @ x
        S = H @ P @ H.T + R
        S = 0.5 * (S + S.T)
        L = np.linalg.cholesky(S)
        # K = P H^T S^-1 via two triangular solves
        PHt = P @ H.T
        K = np.linalg.solve(L.T, np.linalg.solve(L, PHt.T)).T
        d2 = float(np.sum(np.linalg.solve(L, y) ** 2))
        x_new = x + K @ y
        IKH = np.eye(P.shape[0]) - K @ H
        P_new = IKH @ P @ IKH.T + K @ R @ K.T  # Joseph form
        return x_new, 0.5 * (P_new + P_new.T), d2

    # ------------------------------------------------------------------ processing
    def _process(self, e: _Entry) -> None:
        """Apply entry e on top of the current state (which is at or before e.t_ns)."""
        e.x_before = None if self._x is None else self._x.copy()
        e.P_before = None if self._P is None else self._P.copy()
        e.t_before_ns = self._t_ns
        e.consec_before = self._consec_rejections
        e.accepted = False
        if self._x is None:
            best = max(e.meas, key=lambda m: m.score)
            self._x, self._P = self._init_from(best)
            self._t_ns = e.t_ns
            self._consec_rejections = 0
            e.accepted = True
            return
        self._offset_index(e.meas[0])  # a new teammate's offset block exists from here on
        x, P = self._predict(*self._padded(self._x, self._P), (e.t_ns - self._t_ns) * NS)
        best = None
        for m in e.meas:
            H, R = self._H_R(m, len(x))
            try:
                xn, Pn, d2 = self._kalman(x, P, H, R, m.position_ned_m)
            except np.linalg.LinAlgError:
                continue
            if d2 <= self._gate_d2 and (best is None or d2 < best[2]):
                best = (xn, Pn, d2)
        self._t_ns = e.t_ns
        if best is not None:
            self._x, self._P = best[0], best[1]
            self._consec_rejections = 0
            e.accepted = True
        else:
            self._x, self._P = x, P
            self._consec_rejections += 1
            if self._consec_rejections >= self.cfg.max_consecutive_rejections:
                # the track disagrees with everything for a while: it is wrong; re-initialise
                best_m = max(e.meas, key=lambda m: m.score)
                self._x, self._P = self._init_from(best_m)
                self._consec_rejections = 0
                e.accepted = True
                self.stats.reinitialisations += 1
                log.info("%s: track re-initialised after %d rejections", self.self_id, self.cfg.max_consecutive_rejections)

    def add(self, measurement: PositionMeasurement) -> bool:
        """Add one measurement (own or a teammate's). Returns whether it was accepted (False if rejected,
        dropped as too late or non-finite). Out-of-order arrivals re-run the filter from the buffer."""
        return self.add_frame([measurement])

    def add_frame(self, alternatives: list[PositionMeasurement]) -> bool:
        """Add the measurements of one image (e.g. several person boxes): the one closest to the prediction
        (Mahalanobis) among those passing the gate is used. All must share t_ns and source_id."""
        alts = [m for m in alternatives if m.is_finite()]
        self.stats.rejected_nonfinite += len(alternatives) - len(alts)
        if not alts:
            return False
        t_ns = int(alts[0].t_ns)
        if any(m.t_ns != t_ns or m.source_id != alts[0].source_id for m in alts):
            raise TrackerError("add_frame: all alternatives must come from one image (same t_ns and source_id)")
        # reset after a long silence (judged on the newest time seen)
        newest = t_ns if self._t_ns is None else max(t_ns, self._t_ns)
        if self._t_last_accepted_ns is not None and (newest - self._t_last_accepted_ns) * NS > self.cfg.reset_after_s:
            log.info("%s: no accepted measurement for %.1f s: track reset", self.self_id, (newest - self._t_last_accepted_ns) * NS)
            self._clear()
            self.stats.resets += 1
        e = _Entry(t_ns=t_ns, order=self._order, meas=tuple(alts))
        self._order += 1
        if self._t_ns is None or t_ns >= self._t_ns:
            self._process(e)
            self._buffer.append(e)
        else:
            if not self._buffer or t_ns < self._buffer[0].t_ns:
                self.stats.too_late += 1
                return False
            keys = [(b.t_ns, b.order) for b in self._buffer]
            i = bisect.bisect_right(keys, (t_ns, e.order))
            first = self._buffer[i]
            self._x, self._P, self._t_ns = first.x_before, first.P_before, first.t_before_ns
            self._consec_rejections = first.consec_before
            self._buffer.insert(i, e)
            for b in self._buffer[i:]:
                self._process(b)
            self.stats.refiltered += 1
        if len(self._buffer) > self.cfg.buffer_size:
            del self._buffer[: len(self._buffer) - self.cfg.buffer_size]
        if e.accepted:
            self.stats.accepted += 1
        else:
            self.stats.rejected_gate += 1
        self._recount()
        return e.accepted

    def _recount(self) -> None:
        # last accepted time per source: kept beyond the buffer (which may span less than source_window_s
        # with many drones); entries still in the buffer are authoritative for their own times
        for b in self._buffer:
            if b.accepted:
                sid = b.meas[0].source_id
                self._last_seen_ns[sid] = max(self._last_seen_ns.get(sid, b.t_ns), b.t_ns)
                if self._t_last_accepted_ns is None or b.t_ns > self._t_last_accepted_ns:
                    self._t_last_accepted_ns = b.t_ns
        n_acc = sum(1 for b in self._buffer if b.accepted)
        self._buffer_counts = (n_acc, len(self._buffer) - n_acc)

    # ------------------------------------------------------------------ output
    def sources(self, t_ns: int) -> list[str]:
        """Drones whose detections were accepted within source_window_s before t_ns."""
        w = self.cfg.source_window_s / NS
        return sorted(s for s, t in self._last_seen_ns.items() if t_ns - t <= w)

    def estimate(self, t_ns: int | None = None) -> TrackEstimate | None:
        """The estimate predicted to t_ns (default: the newest measurement time); None before the first
        measurement or after a reset (status "lost" is then the caller's)."""
        if self._x is None:
            return None
        t = self._t_ns if t_ns is None else int(t_ns)
        since = (t - self._t_last_accepted_ns) * NS if self._t_last_accepted_ns is not None else np.inf
        if since > self.cfg.reset_after_s:
            return None
        x, P = self._predict(self._x, self._P, (t - self._t_ns) * NS)
        status: TrackStatus = "tracking" if since <= self.cfg.predicting_after_s else "predicting"
        return TrackEstimate(
            t_ns=t,
            position_ned_m=x[:3].copy(),
            velocity_ned_m_s=x[3:6].copy(),
            covariance=P[:6, :6].copy(),
            offset_ned_m=x[6:9].copy(),
            offset_cov_m2=P[6:9, 6:9].copy(),
            position_offset_cov_m2=P[:3, 6:9].copy(),
            velocity_offset_cov=P[3:6, 6:9].copy(),
            status=status,
            num_sources=len(self.sources(t)),
            t_last_measurement_ns=int(self._t_last_accepted_ns),
        )

    def buffer_counts(self) -> tuple[int, int]:
        """(accepted, rejected) entries in the current buffer."""
        return getattr(self, "_buffer_counts", (0, 0))
