"""A real-PX4 flight for tests: PX4 SITL instances with SIH (``simulator.px4_sitl``), SIH's truth, a Zenoh rendezvous,
the fleet client, and agent processes (``python -m apps.cli agent``) connected to the instances.

The PX4 build is ``../shared/px4-sitl`` (or ``$SKYCAP_PX4_SITL``); :func:`px4_or_skip` skips a test with the
reason where it is absent. Instances start at ``$SKYCAP_PX4_FIRST_INSTANCE`` (default 0).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np

from tests.helpers.flight import AgentFleet

ORIGIN = (47.397742, 8.545594, 488.0)


def px4_or_skip() -> Path:
    import pytest

    from simulator.px4_sitl import Px4SitlError, find_px4_folder

    try:
        return find_px4_folder()
    except Px4SitlError as e:
        pytest.skip(f"real PX4 SITL not available: {e}")


class Px4Flight(AgentFleet):
    """``n`` PX4 SITL vehicles with homes at ``homes_ne_m`` (world north/east m about :data:`ORIGIN`), their truth,
    a rendezvous + fleet client, and helpers to start agents."""

    def __init__(self, tmp: Path, homes_ne_m: list[tuple[float, float]], params: dict[str, float] | None = None):
        from simulator.px4_sitl import Px4Sitl, SihTruthReader
        from skycap.frames import ned_to_geodetic

        self.n = len(homes_ne_m)
        homes = [ned_to_geodetic([n, e, 0.0], *ORIGIN)[:2] for n, e in homes_ne_m]
        first = int(os.environ.get("SKYCAP_PX4_FIRST_INSTANCE", "0"))
        self.px4 = Px4Sitl(tmp / "px4", self.n, first_instance=first, homes_geodetic=homes,
                           params=params).start()
        self.truth = SihTruthReader([self.px4.truth_port(k) for k in range(self.n)], ORIGIN)
        self.truth_log: list[list[tuple[float, np.ndarray]]] = [[] for _ in range(self.n)]
        self.truth.on_truth = lambda k, t: self.truth_log[k].append((t.t_received_ns * 1e-9, t.position_ned_m))
        assert self.truth.wait_all(10.0), "no SIH truth from PX4"
        #: SIH's ground (AMSL) under each vehicle, from its truth at rest: heights are measured from it
        self.ground_amsl_m = [t.altitude_amsl_m for t in self.truth.latest()]
        super().__init__(tmp, fleet_prefix="p")

    def start_agent(self, k: int, *extra: str) -> subprocess.Popen:
        return self._spawn_agent(f"drone_{k + 1}", self.px4.connection_url(k), self.tmp / "rec",
                                 "--set", "record_camera=false", *extra)

    def height_m(self, k: int) -> float:
        """SIH's true height of vehicle ``k`` above its ground."""
        return float(self.truth.latest()[k].altitude_amsl_m - self.ground_amsl_m[k])

    def truth_ned(self, k: int) -> np.ndarray:
        """SIH's true position, world NED with down about the vehicle's ground."""
        t = self.truth.latest()[k]
        p = np.array(t.position_ned_m, dtype=float)
        p[2] = -(t.altitude_amsl_m - self.ground_amsl_m[k])
        return p

    def wait_all(self, state: str, timeout_s: float) -> bool:
        ids = [f"drone_{k + 1}" for k in range(self.n)]
        return self.fleet.wait_until(lambda f: all(self.agent_state(d) == state for d in ids), timeout_s, state)

    def orbit_errors(self, plan, t0_s: float, t1_s: float) -> dict:
        """Orbit figures against SIH's truth between UNIX times t0_s..t1_s (:func:`evaluation.flight.orbit_errors`
        on the truth resampled at 20 Hz): per vehicle the radius RMS and mean (m), height RMS and mean (m), phase
        RMS (deg) against its slot; and the smallest distance between two vehicles (m)."""
        from evaluation.flight import min_pairwise_distance_m, orbit_errors

        ids = [f"drone_{k + 1}" for k in range(self.n)]
        t = np.arange(t0_s, t1_s, 0.05)
        pos = np.empty((self.n, len(t), 3))
        for k in range(self.n):
            rows = [(ti, p) for ti, p in self.truth_log[k] if t0_s - 1.0 <= ti <= t1_s + 1.0]
            tk = np.array([r[0] for r in rows])
            pk = np.array([r[1] for r in rows], dtype=float)
            pk[:, 2] += self.ground_amsl_m[k] - ORIGIN[2]  # truth down about the origin -> about the ground
            pos[k] = np.stack([np.interp(t, tk, pk[:, j]) for j in range(3)], axis=1)
        per = orbit_errors(plan, ids, t, pos)
        c = np.asarray(plan.center_ned_m, dtype=float)
        radius = np.hypot(pos[..., 0] - c[0], pos[..., 1] - c[1])
        out = {"radius_rms_m": [per[d]["orbit_radius_rmse_m"] for d in ids],
               "radius_bias_m": [float(np.mean(r - plan.radius_m)) for r in radius],
               "height_rms_m": [per[d]["altitude_rmse_m"] for d in ids],
               "height_bias_m": [float(np.mean(-p[:, 2] - plan.altitude_m)) for p in pos],
               "phase_rms_deg": [per[d]["phase_error_deg_rms"] for d in ids]}
        if self.n > 1:
            out["min_separation_m"] = min_pairwise_distance_m(pos)
        return out

    def close(self) -> None:
        super().close()
        self.truth.close()
        self.px4.stop()
