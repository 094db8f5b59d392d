"""reconstruction.api.reconstruct_flight as a job processor ("reconstruct") in a local worker process."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.jobs import JobStatus


@pytest.mark.slow  # torch and the body model imported in a worker, a short fit
def test_reconstruct_flight_as_a_local_job(local_reconstruction):
    job, flight = local_reconstruction
    res = job.result(timeout=300)
    assert job.status is JobStatus.DONE
    assert res.method == "multiview" and res.joints_ned.shape[1:] == (17, 3) and np.all(np.isfinite(res.joints_ned))
    # its files, in the flight's folder, hold what came back
    z = np.load(flight / "reconstruction" / "motion.npz")
    np.testing.assert_allclose(z["joints_ned"], res.joints_ned)
    steps = [e.step for e in job.events]
    assert steps[0] == "load" and "fit" in steps and steps[-1] == "export"
    assert all(0.0 <= e.fraction <= 1.0 for e in job.events)
    assert any("multiview reconstruction of" in line for line in job.log)
