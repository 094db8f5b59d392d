"""Fixtures shared by the reconstruction tests: one Ray head on loopback for the whole session (the job tests
and the process-as-a-job tests use the same one)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def ray_runner():
    """A RayRunner on a one-machine Ray cluster started here on 127.0.0.1 (2 CPUs, no dashboard), shut down at the
    end of the session."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'skycap[ray]')")
    from reconstruction.jobs.ray_runner import RayRunner

    runner = RayRunner("local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1")
    yield runner
    runner.close()
