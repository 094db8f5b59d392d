"""FlightFolder: names, natural drone order, sorties, and that no recording is ever opened for writing twice."""

from __future__ import annotations

import pytest

from flightdata.flightlog import FlightLog
from flightdata.folder import FlightFolder, FlightFolderError, Sortie, natural_key
from flightdata.recorder import Recorder, RecorderError
from shared_msgs import Health


def _health(node: str, i: int) -> Health:
    return Health(header=Health.make_header(node, 10**18 + i), role="agent", state=f"s{i}")


def _record(folder, node: str, n: int = 3) -> Recorder:
    with Recorder.new_sortie(folder, node) as rec:
        for i in range(n):
            rec.record_message("health", _health(node, i))
    return rec


def test_drone_ids_are_in_natural_order(tmp_path):
    for d in ("drone_10", "drone_2", "drone_1"):
        _record(tmp_path, d)
    _record(tmp_path, "truth")
    (tmp_path / "drone_3.log").write_text("not a recording")
    f = FlightFolder(tmp_path)
    assert f.drone_ids() == ["drone_1", "drone_2", "drone_10"]
    assert sorted(["drone_10", "drone_2"], key=natural_key) == ["drone_2", "drone_10"]


def test_each_start_is_a_new_sortie_and_earlier_ones_stay_byte_identical(tmp_path):
    first = _record(tmp_path, "drone_1").path
    data = first.read_bytes()
    second = _record(tmp_path, "drone_1", n=5).path
    assert (first.name, second.name) == ("drone_1.s001.mcap", "drone_1.s002.mcap")
    assert first.read_bytes() == data
    f = FlightFolder(tmp_path)
    assert [s.number for s in f.sorties("drone_1")] == [1, 2]
    whole = f.drone_logs()
    assert [s.path for s in whole["drone_1"]] == [first, second]
    assert [s.path for s in f.drone_logs(sortie=2)["drone_1"]] == [second]
    assert "drone_1.s001.mcap, drone_1.s002.mcap" in f.describe_logs(whole)
    assert len(FlightLog(second).read_topic("health")) == 5
    with pytest.raises(FlightFolderError, match="no recording of sortie 7"):
        f.drone_logs(sortie=7)


def test_the_recorder_never_opens_an_existing_file(tmp_path):
    path = _record(tmp_path, "drone_1").path
    data = path.read_bytes()
    with pytest.raises(RecorderError, match="never overwritten"):
        Recorder(path)
    assert path.read_bytes() == data


def test_a_race_for_the_same_sortie_number_takes_the_next(tmp_path, monkeypatch):
    taken = _record(tmp_path, "drone_1").path
    data = taken.read_bytes()
    # another process took sortie 1 between our look at the folder and our open: we still see 'next = 1' once
    real = FlightFolder.new_recording
    calls = iter([taken])
    monkeypatch.setattr(FlightFolder, "new_recording", lambda self, node: next(calls, None) or real(self, node))
    with Recorder.new_sortie(tmp_path, "drone_1") as rec:
        pass
    assert rec.path.name == "drone_1.s002.mcap" and taken.read_bytes() == data


def test_layout_1_recordings_read_as_sortie_1(tmp_path):
    with Recorder(tmp_path / "drone_1.mcap", node_id="drone_1") as rec:
        rec.record_message("health", _health("drone_1", 0))
    f = FlightFolder(tmp_path)
    assert f.sorties("drone_1") == [Sortie(1, tmp_path / "drone_1.mcap")]
    assert f.new_recording("drone_1").name == "drone_1.s002.mcap"
    _record(tmp_path, "drone_1")
    assert [s.path.name for s in f.sorties("drone_1")] == ["drone_1.mcap", "drone_1.s002.mcap"]
    # a layout-1 file beside a sortie-1 file is ambiguous: the error says how to resolve it
    (tmp_path / "drone_2.mcap").write_bytes(b"")
    (tmp_path / "drone_2.s001.mcap").write_bytes(b"")
    with pytest.raises(FlightFolderError, match="rename"):
        f.drone_ids()


def test_sortie_side_files_and_bad_names(tmp_path):
    s = Sortie.of(tmp_path / "drone_4.s012.mcap")
    assert s.number == 12
    assert s.track_stats_path.name == "drone_4.s012.track.json"
    assert s.config_path.name == "drone_4.s012.config.toml"
    with pytest.raises(FlightFolderError, match="not named as a recording"):
        Sortie.of(tmp_path / "notes.txt")
    with pytest.raises(FlightFolderError, match="cannot name a recording"):
        FlightFolder(tmp_path).new_recording("a.b")
    with pytest.raises(FlightFolderError, match="no drone recordings"):
        FlightFolder(tmp_path / "empty").drone_logs()
    with pytest.raises(FlightFolderError, match="orbit plan"):
        FlightFolder(tmp_path).plan()
    assert FlightFolder(tmp_path).reconstruction_dir("monocular").name == "reconstruction_monocular"
