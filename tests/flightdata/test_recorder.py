"""Recorder file layout, finalised reading with the python mcap reader, drops, errors, flight log reader."""

from __future__ import annotations

import json
import os
import time

import msgspec
import pytest
from mcap.reader import make_reader

from flightdata.flightlog import FlightLog, FlightLogError, read_topic
from flightdata.folder import FlightFolder
from flightdata.recorder import Recorder, RecorderError, channel_name
from shared_msgs import Command, Health, SimTruth, VehicleState, VehicleTruth, encode
from shared_msgs.messages import Header


def state(i: int, t_ns: int) -> VehicleState:
    return VehicleState(
        header=Header(schema_version=1, sender_id="drone_1", t_measurement_ns=t_ns - 5, t_sent_ns=t_ns, seq=i),
        position_ned_m=(float(i), 1.0, -5.0),
        velocity_ned_m_s=(0.5, 0.0, 0.0),
        q_world_body=(1.0, 0.0, 0.0, 0.0),
        armed=True,
    )


def test_paths_and_channel_names(tmp_path) -> None:
    assert FlightFolder(tmp_path).new_recording("drone_2") == tmp_path / "drone_2.s001.mcap"
    assert FlightFolder(tmp_path).truth_path == tmp_path / "truth.mcap"
    assert channel_name("skycap/v1/f/drone_1/camera/image", "drone_1") == "camera/image"
    assert channel_name("skycap/v1/f/gcs/cmd", "drone_1") == "gcs/cmd"
    assert channel_name("skycap/v1/f/drone_2/detections", "drone_1") == "drone_2/detections"


def test_finalised_file_layout_and_round_trip(tmp_path) -> None:
    path = FlightFolder(tmp_path).new_recording("drone_1")
    t0 = 1_700_000_000_000_000_000
    with Recorder(path, node_id="drone_1", metadata={"flight": "f42"}) as rec:
        for i in range(1, 51):
            assert rec.record("state", encode(state(i, t0 + i * 20_000_000)), log_time_ns=t0 + i * 20_000_000 + 1000)
        cmd = Command(header=Command.make_header("gcs", seq=7), command_id="c1", target="drone_1", action="arm")
        rec.record_message("gcs/cmd", cmd, log_time_ns=t0 + 10**9)
        assert rec.record("state", b"\x00 not a message")  # queued; the writer thread refuses it
    assert rec.stats()["written"] == 51 and rec.stats()["invalid"] == 1

    with open(path, "rb") as f:  # the standard python reader, indexed (summary + footer present)
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == "skycap"
        assert summary.statistics.message_count == 51
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {"skycap.vehicle_state.v1", "skycap.command.v1"}
        assert all(s.encoding == "jsonschema" for s in schemas.values())
        js = json.loads(schemas["skycap.vehicle_state.v1"].data)
        assert "VehicleState" in json.dumps(js)
        msgs = list(reader.iter_messages(topics=["state"]))
        assert len(msgs) == 50
        for i, (schema, channel, m) in enumerate(msgs, start=1):
            assert channel.message_encoding == "msgpack" and channel.metadata["type"] == "vehicle_state"
            assert m.publish_time == t0 + i * 20_000_000  # header.t_sent_ns
            assert m.log_time == m.publish_time + 1000  # receive time
            assert m.sequence == i
            assert msgspec.msgpack.decode(m.data)["position_ned_m"][0] == float(i)

    log = FlightLog(path)
    assert log.finalised and log.topic_counts() == {"gcs/cmd": 1, "state": 50}
    assert log.metadata()["skycap"]["flight"] == "f42"
    states = log.read_topic("state", VehicleState)
    assert [s.header.seq for s in states] == list(range(1, 51)) and states[0].armed
    [c] = read_topic(path, "gcs/cmd", Command)
    assert c.command_id == "c1" and c.header.seq == 7
    with pytest.raises(FlightLogError, match="expected Health"):
        log.read_topic("state", Health)


def test_truth_file_with_same_recorder(tmp_path) -> None:
    truth = SimTruth(
        header=SimTruth.make_header("sim"),
        vehicles=[VehicleTruth(drone_id="drone_1", position_ned_m=(0.0, 0.0, -5.0), velocity_ned_m_s=(0.0, 0.0, 0.0),
                               q_world_body=(1.0, 0.0, 0.0, 0.0))],
        person_joints_ned_m=tuple(float(i) for i in range(51)),
        person_root_ned_m=(0.0, 0.0, 0.0),
    )
    with Recorder(FlightFolder(tmp_path).truth_path, node_id="sim") as rec:
        rec.record_message("truth", truth)
    [t] = FlightLog(FlightFolder(tmp_path).truth_path).read_topic("truth", SimTruth)
    assert t == truth


def test_queue_over_limit_drops_instead_of_blocking(tmp_path) -> None:
    rec = Recorder(tmp_path / "x.mcap", max_queue_bytes=100_000)
    payload = encode(
        Health(header=Health.make_header("drone_1"), role="agent", state="x", warnings=["w" * 30_000])
    )
    t = time.perf_counter()
    results = [rec.record("health", payload) for _ in range(2000)]
    assert time.perf_counter() - t < 1.0  # never waits for the disk
    rec.close()
    s = rec.stats()
    assert s["dropped"] == results.count(False) and s["written"] == results.count(True) and s["written"] > 0
    assert FlightLog(tmp_path / "x.mcap").topic_counts()["health"] == s["written"]


def test_errors_are_clear(tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RecorderError, match="cannot create the flight log"):
        Recorder(blocker / "sub" / "d.mcap")
    with pytest.raises(RecorderError, match="compression"):
        Recorder(tmp_path / "a.mcap", compression="gzip")
    rec = Recorder(tmp_path / "b.mcap")
    rec.close()
    rec.close()  # idempotent
    with pytest.raises(RecorderError, match="closed"):
        rec.record("state", encode(state(1, 1)))
    with pytest.raises(FlightLogError, match="does not exist"):
        FlightLog(tmp_path / "missing.mcap")
    (tmp_path / "junk.mcap").write_bytes(os.urandom(100))
    with pytest.raises(FlightLogError, match="not an MCAP file"):
        FlightLog(tmp_path / "junk.mcap")


def test_undecodable_message_names_file_and_topic(tmp_path) -> None:
    path = tmp_path / "v.mcap"
    bad = state(1, 1)
    bad.header.schema_version = 99  # recorded by a newer skycap
    with Recorder(path) as rec:
        rec.record("state", encode(bad))
        rec.record("state", encode(state(2, 2)))
    with pytest.raises(FlightLogError, match=r"v\.mcap.*'state'.*schema version 99"):
        FlightLog(path).read_topic("state")
    assert [m.sequence for m in FlightLog(path).messages(skip_invalid=True)] == [2]


def test_log_cli_info_and_recover(tmp_path, capsys) -> None:
    import argparse

    from flightdata import flightlog

    path = tmp_path / "drone_1.mcap"
    with Recorder(path, node_id="drone_1") as rec:
        for i in range(1, 11):
            rec.record("state", encode(state(i, 10**18 + i * 10**8)), log_time_ns=10**18 + i * 10**8)
    parser = argparse.ArgumentParser()
    flightlog.register(parser.add_subparsers())
    args = parser.parse_args(["log", "info", str(path)])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "finalised" in out and "state" in out and "10 msgs" in out
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 40])
    args = parser.parse_args(["log", "recover", str(cut), str(tmp_path / "fixed.mcap")])
    assert args.func(args) == 0
    # a second recover onto the existing output is refused unless told (--force), and leaves it as it was
    fixed = (tmp_path / "fixed.mcap").read_bytes()
    with pytest.raises(FlightLogError, match="already exists.*--force"):
        args.func(args)
    with pytest.raises(FlightLogError, match="would overwrite"):
        flightlog.recover(cut, cut, overwrite=True)
    assert (tmp_path / "fixed.mcap").read_bytes() == fixed and cut.read_bytes() == data[: len(data) - 40]
    args = parser.parse_args(["log", "recover", "--force", str(path), str(tmp_path / "fixed.mcap")])
    assert args.func(args) == 0
    assert not list(tmp_path.glob(".*partial"))
    assert FlightLog(tmp_path / "fixed.mcap").finalised
    d = flightlog.describe(tmp_path / "fixed.mcap")
    assert d["topics"] == {"state": 10} and d["t_last_ns"] - d["t_first_ns"] == 9 * 10**8


def test_read_topic_is_in_log_time_order_even_when_truncated(tmp_path) -> None:
    path = tmp_path / "o.mcap"
    with Recorder(path) as rec:
        for i, t in enumerate([5, 3, 4, 1, 2], start=1):  # recorded out of log-time order
            rec.record("state", encode(state(i, t)), log_time_ns=t)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 30])
    for p in (path, cut):
        assert [s.header.seq for s in FlightLog(p).read_topic("state")] == [4, 5, 2, 3, 1]


def _wait_error(rec: Recorder, timeout_s: float = 5.0) -> RecorderError:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            rec.record_message("state", state(0, 1))
        except RecorderError as e:
            return e
        time.sleep(0.02)
    raise AssertionError("the recorder did not fail")


def test_simulated_disk_full_keeps_what_was_written_readable(tmp_path) -> None:
    from flightdata.recorder import simulate_disk_full

    rec = Recorder(tmp_path / "d.mcap", flush_interval_s=0.05)
    t0 = 1_700_000_000_000_000_000
    for i in range(50):
        rec.record_message("state", state(i, t0 + i))
    time.sleep(0.3)  # flushed
    simulate_disk_full(tmp_path)
    try:
        for i in range(50, 60):
            rec.record_message("state", state(i, t0 + i))
        e = _wait_error(rec)
        assert "No space left on device" in str(e) and "d.mcap" in str(e), e
        with pytest.raises(RecorderError, match="No space left"):
            Recorder(tmp_path / "e.mcap")  # nor can a new recording be created there
        with pytest.raises(RecorderError):
            rec.close()
    finally:
        simulate_disk_full(tmp_path, full=False)
    # everything written before the disk filled is still there, read as a crash-truncated file
    got = read_topic(tmp_path / "d.mcap", "state")
    assert [m.header.seq for m in got] == list(range(50))
    # and recovered into a finalised file (flightdata.flightlog.recover), the mcap library reads all of it
    from flightdata.flightlog import recover

    recover(tmp_path / "d.mcap", tmp_path / "d.recovered.mcap")
    with open(tmp_path / "d.recovered.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages()) == 50


def test_injected_writer_failure_surfaces_and_keeps_the_flushed_part(tmp_path) -> None:
    rec = Recorder(tmp_path / "k.mcap", flush_interval_s=0.05)
    t0 = 1_700_000_000_000_000_000
    for i in range(20):
        rec.record_message("state", state(i, t0 + i))
    time.sleep(0.3)
    assert rec.error == ""
    rec.inject_writer_failure("test: writer killed")
    e = _wait_error(rec)
    assert "test: writer killed" in rec.error  # what the agent's health reports before the next record() raises
    assert "test: writer killed" in str(e)
    assert len(read_topic(tmp_path / "k.mcap", "state")) >= 20
