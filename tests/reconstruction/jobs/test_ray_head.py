"""The Ray runner on a Ray head started apart (``ray start --head`` on loopback, every port its own free one, its own
temp folder), reached by address from ``skycap process --ray HOST:PORT`` in another process (a driver that joins
an existing cluster, as on a real one), gives the local runner's motion; the head is stopped at the end (its
process group: ``ray stop`` would stop every Ray on the machine)."""

from __future__ import annotations

import importlib.util

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.helpers.ports import free_tcp_port

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]


def _quick_config():
    from reconstruction.process.config import ProcessConfig

    cfg = ProcessConfig()
    cfg.method = "multiview"
    cfg.multiview.fit.iters = 30
    cfg.export.rrd = False
    cfg.export.extra = []
    return cfg.validate()


#: the head's token (Ray >= 2.52 `ray start` requires token authentication; a driver that connects by address sends
#: one only with RAY_AUTH_MODE=token): this test's own, never the user's ~/.ray/auth_token
TOKEN = "skycap-test-" + os.urandom(16).hex()


def _env(token: bool = True) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
               RAY_USAGE_STATS_ENABLED="0")
    for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "RAY_ADDRESS"):
        env.pop(k, None)
    if token:
        env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=TOKEN)
    return env


@pytest.fixture
def ray_head():
    """``ray start --head --block`` on 127.0.0.1 (2 CPUs): its GCS address; killed with its process group after."""
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'skycap[ray]')")
    ray_bin = Path(sys.executable).with_name("ray")
    if not ray_bin.is_file():
        pytest.skip(f"no 'ray' command beside {sys.executable}")
    # the Ray Client server (its own port) only where its dependency is installed: `ray start` refuses the port
    # option without grpcio (a plain `pip install ray`, as the `ray` extra installs it)
    client = ("ray-client-server-port",) if importlib.util.find_spec("grpc") else ()

    started: list[tuple[subprocess.Popen, Any, str]] = []  # (head, its log, its temp folder): all cleaned up after

    def start() -> tuple[subprocess.Popen, int, str]:
        port = free_tcp_port()
        temp = tempfile.mkdtemp(prefix="rayh", dir="/tmp")  # short: Ray's socket paths live there
        ports = {f"--{k}": str(free_tcp_port()) for k in (
            *client, "node-manager-port", "object-manager-port", "dashboard-agent-listen-port",
            "dashboard-agent-grpc-port", "metrics-export-port", "runtime-env-agent-port")}
        lo = free_tcp_port()
        cmd = [str(ray_bin), "start", "--head", f"--port={port}", "--node-ip-address=127.0.0.1", "--num-cpus=2",
               "--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={temp}", "--block",
               f"--min-worker-port={lo}", f"--max-worker-port={lo + 200}",
               *[f"{k}={v}" for k, v in ports.items()]]
        head_log = open(Path(temp).with_suffix(".log"), "w+")
        head = subprocess.Popen(cmd, stdout=head_log, stderr=subprocess.STDOUT, text=True, env=_env(),
                                start_new_session=True)
        started.append((head, head_log, temp))
        t_end = time.monotonic() + 90
        while True:
            if head.poll() is not None:
                head_log.seek(0)
                return head, 0, f"ray start exited {head.returncode}:\n{head_log.read()[-3000:]}"
            if time.monotonic() > t_end:
                return head, 0, "the Ray head did not open its port within 90 s"
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                return head, port, ""
            except OSError:
                time.sleep(0.2)

    head, port, why = start()
    if not port and head.poll() is not None:  # a port taken between choosing it and Ray binding it: once more
        head, port, why = start()
    try:
        assert port, why
        yield f"127.0.0.1:{port}"
    finally:
        # the head's processes (ray start, GCS, raylet, workers) are its process group: SIGTERM, up to 5 s to end,
        # then SIGKILL what is left
        for head, head_log, temp in started:
            _stop_group(head)
            head_log.close()
            Path(head_log.name).unlink(missing_ok=True)
            shutil.rmtree(temp, ignore_errors=True)


def _stop_group(head: subprocess.Popen) -> None:
    def group() -> list[str]:
        out = subprocess.run(["ps", "-o", "pid=,stat=", "-g", str(head.pid)], capture_output=True, text=True).stdout
        return [ln.split()[0] for ln in out.splitlines() if ln.split() and not ln.split()[1].startswith("Z")]

    try:
        os.killpg(head.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
    t_end = time.monotonic() + 5
    while group() and time.monotonic() < t_end:
        time.sleep(0.2)
    try:
        os.killpg(head.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    head.wait(10)


def test_process_on_a_separately_started_ray_head_equals_the_local_runner(ray_head, small_flight, tmp_path):
    from reconstruction.jobs import LocalRunner, submit
    from skycap.config import save_config

    cfg = _quick_config()
    cfg_path = save_config(cfg, tmp_path / "process.toml")
    on_ray = shutil.copytree(small_flight, tmp_path / "ray")
    r = subprocess.run([sys.executable, "-m", "apps.cli", "process", str(on_ray), "--config", str(cfg_path),
                        "--ray", ray_head], capture_output=True, text=True, timeout=300, env=_env(), cwd=ROOT)
    assert r.returncode == 0, r.stderr[-5000:]
    s = json.loads(r.stdout[r.stdout.index("{"):])
    assert s["method"] == "multiview" and s["keypoints_source"].startswith("recorded:")
    local = shutil.copytree(small_flight, tmp_path / "local")
    with LocalRunner(workers=1, threads_per_worker=1) as runner:
        ref = submit(local, cfg, processor="process", runner=runner).result(timeout=300)
    with np.load(on_ray / "reconstruction" / "motion.npz") as z:
        np.testing.assert_array_equal(z["t_ns"], ref.t_ns)
        np.testing.assert_allclose(z["joints_ned"], ref.joints_ned, atol=1e-4)
    assert s["frames"] == len(ref.t_ns) and s["steps"]["fit"]["windows"] == ref.steps["fit"]["windows"]
    # without the token the head refuses the driver: a clear error naming the fix
    r = subprocess.run([sys.executable, "-m", "apps.cli", "process", str(on_ray), "--config", str(cfg_path),
                        "--ray", ray_head], capture_output=True, text=True, timeout=120, env=_env(token=False), cwd=ROOT)
    assert r.returncode != 0 and "RAY_AUTH_MODE=token" in r.stderr, r.stderr[-3000:]
