"""The recorder survives ``kill -9``: the file stays readable and loses at most ~one flush interval."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader

from flightdata.flightlog import FlightLog, recover
from flightdata.recorder import Recorder
from shared_msgs import CameraFrame, VehicleState
from tests.helpers.paths import REPO

HERE = Path(__file__).resolve().parent
FLUSH_S = 0.5


@pytest.fixture(scope="module")
def killed_log(tmp_path_factory) -> tuple[Path, int]:
    """(path of the file left by a recorder killed with SIGKILL after ~3 s, kill time in ns)."""
    path = tmp_path_factory.mktemp("kill9") / "drone_1.mcap"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen(
        [sys.executable, str(HERE / "record_proc.py"), str(path), str(FLUSH_S)],
        cwd=REPO, env=env, stdout=subprocess.PIPE, text=True,
    )
    try:
        line = child.stdout.readline()
        assert line.strip() == "recording", line
        time.sleep(1.7)
        t_kill_ns = time.time_ns()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == -signal.SIGKILL
    return path, t_kill_ns


def test_killed_file_is_readable_and_loses_at_most_about_one_second(killed_log) -> None:
    path, t_kill_ns = killed_log
    log = FlightLog(path)
    assert not log.finalised  # no footer: it really was cut short
    states = [m for m in log.messages(["state"])]
    assert log.truncated
    assert len(states) > 150  # > ~2.5 s at 100 Hz reached the disk
    seqs = [m.sequence for m in states]
    assert seqs == list(range(1, len(seqs) + 1))  # nothing missing before the cut
    assert all(isinstance(m.msg, VehicleState) and m.msg.position_ned_m[0] == m.sequence for m in states)
    lost_s = (t_kill_ns - states[-1].log_time_ns) / 1e9
    assert 0 <= lost_s <= 1.0, f"lost {lost_s:.2f} s of data"
    frames = log.read_topic("camera/image", CameraFrame)
    assert len(frames) >= len(states) // 10 - 1 and all(len(f.data) == 40_000 for f in frames)
    assert log.metadata()["skycap"]["node_id"] == "drone_1"


def test_killed_file_with_the_python_mcap_reader(killed_log) -> None:
    """The standard python reader streams the non-finalised file up to the cut (then raises at the cut).

    ``log_time_order=False``: the default order buffers the whole file before yielding anything."""
    path, _ = killed_log
    n = 0
    with open(path, "rb") as f:
        reader = NonSeekingReader(f)
        with pytest.raises(Exception):  # the incomplete last record
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                assert channel.message_encoding == "msgpack" and schema.encoding == "jsonschema"
                n += 1
    assert n == sum(FlightLog(path).topic_counts().values())


def test_recover_makes_a_finalised_file(killed_log, tmp_path) -> None:
    path, _ = killed_log
    out = tmp_path / "recovered.mcap"
    counts = recover(path, out)
    assert counts == FlightLog(path).topic_counts()
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == sum(counts.values())
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {"state", "camera/image", "health"}
        assert sum(1 for _ in reader.iter_messages(topics=["state"])) == counts["state"]
    assert FlightLog(out).finalised


@pytest.mark.skipif(shutil.which("mcap") is None, reason="the Go `mcap` CLI is not installed (no pip/npm/apt package)")
def test_mcap_cli_reads_recovered_file(killed_log, tmp_path) -> None:
    path, _ = killed_log
    out = tmp_path / "cli_recovered.mcap"
    subprocess.run(["mcap", "recover", str(path), "-o", str(out)], check=True, capture_output=True)
    info = subprocess.run(["mcap", "info", str(out)], check=True, capture_output=True, text=True).stdout
    assert "state" in info and "camera/image" in info


def _mcap_js_dir() -> str | None:
    d = os.environ.get("SKYCAP_MCAP_JS")
    if shutil.which("node") and d and (Path(d) / "node_modules" / "@mcap" / "core").is_dir():
        return d
    return None


@pytest.mark.skipif(
    _mcap_js_dir() is None,
    reason="optional: set SKYCAP_MCAP_JS to a folder where `npm install @mcap/core @mcap/support @mcap/nodejs` ran",
)
def test_official_typescript_mcap_library_reads_killed_and_recovered_files(killed_log, tmp_path) -> None:
    """Foxglove's @mcap/core (what Foxglove Studio uses) streams the killed file up to the cut and reads the
    recovered one with its index."""
    import json

    path, _ = killed_log
    counts = FlightLog(path).topic_counts()
    env = dict(os.environ, SKYCAP_MCAP_JS=_mcap_js_dir())

    def js(p: Path) -> dict:
        r = subprocess.run(["node", str(HERE / "mcap_js_check.cjs"), str(p)], capture_output=True, text=True,
                           env=env, timeout=60)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    killed = js(path)
    assert not killed["streamDone"] and killed["stream"] == counts and killed["encodings"] == ["msgpack"]
    out = tmp_path / "recovered.mcap"
    recover(path, out)
    rec = js(out)
    assert rec["streamDone"] and rec["indexed"] == counts and rec["profile"] == "skycap"

    closed = tmp_path / "closed.mcap"  # a normally closed recorder file: many small chunks, summary, footer
    with Recorder(closed, flush_interval_s=0.05) as r:
        for m in FlightLog(path).messages(decode_messages=False):
            r.record(m.topic, m.data, m.log_time_ns)
            if m.sequence % 50 == 0:
                time.sleep(0.06)
    assert r.stats()["flushes"] > 3
    assert js(closed)["indexed"] == counts
