"""Shared fixtures of the job tests: small flight folders (the Ray head on loopback: tests/reconstruction/conftest.py)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_flight(tmp_path_factory):
    """A 3-drone recorded flight of 12 frames (simulated keypoints), to copy per test (outputs go into it)."""
    pytest.importorskip("mcap")
    from tests.reconstruction.jobs.smallflight import write_small_flight

    return write_small_flight(tmp_path_factory.mktemp("small_flight") / "flight")


@pytest.fixture(scope="session")
def local_reconstruction(small_flight, tmp_path_factory):
    """``reconstruct_flight`` (a short fit) run as a job on a LocalRunner over a copy of the small flight: (job, folder)."""
    import shutil

    from reconstruction.jobs import LocalRunner, submit
    from tests.reconstruction.jobs.smallflight import QUICK

    flight = shutil.copytree(small_flight, tmp_path_factory.mktemp("local_reconstruction") / "flight")
    with LocalRunner(workers=1, threads_per_worker=1) as runner:
        job = submit(flight, QUICK, processor="reconstruct", runner=runner)
        job.wait(300)
    return job, flight
