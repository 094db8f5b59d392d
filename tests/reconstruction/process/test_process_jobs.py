"""``skycap process`` as a job (reconstruction.jobs): the real pipeline submitted by name ("process") to a local
worker process and to a Ray head on loopback, over a copy of the processed test flight with its cache -- the job
resumes from the cache (no model runs) and returns the same motion as the in-process run."""

from __future__ import annotations

import numpy as np
import pytest

from process_helpers import copy_flight, make_config  # noqa: E402

pytestmark = pytest.mark.slow


def _same_motion(job_result, processed) -> None:
    ref = processed["runs"][2][0]
    assert job_result.keypoints_source == ref.keypoints_source
    assert all(s.get("cached") for name, s in job_result.steps.items() if name != "export"), job_result.steps
    assert job_result.stats.get("frames_computed", 0) == 0, job_result.stats
    np.testing.assert_allclose(job_result.joints_ned, ref.joints_ned, atol=1e-6)


def test_process_as_a_local_job_resumes_from_the_cache(processed, tmp_path):
    from reconstruction.jobs import JobStatus, LocalRunner

    flight = copy_flight(processed["flight"], tmp_path / "f", with_cache=True)
    with LocalRunner(workers=1, threads_per_worker=1) as runner:
        job = runner.submit(flight, make_config())  # the default processor: "process"
        res = job.result(timeout=300)
    assert job.status == JobStatus.DONE
    assert [e.step for e in job.events][-1] == "export", [e.step for e in job.events]
    _same_motion(res, processed)


def test_process_as_a_ray_job_gives_the_same_motion(processed, ray_runner, tmp_path):
    flight = copy_flight(processed["flight"], tmp_path / "f", with_cache=True)
    res = ray_runner.submit(flight, make_config(), processor="process").result(timeout=300)
    _same_motion(res, processed)
